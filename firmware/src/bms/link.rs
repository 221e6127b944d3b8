//! The link engine: one outstanding request at a time over a half-duplex UART.
//!
//! * The response timeout runs from the moment the request's last byte is on the
//!   wire ([`crate::bms::timing::RESPONSE_TIMEOUT_US`]); once reply bytes flow, a gap of
//!   [`crate::bms::timing::REPLY_IDLE_GAP_US`] ends the attempt early.
//! * Wake-up (HARDWARE-NOTES "Sleep"): when a request gets total silence, it is sent
//!   once more before anything counts as a failure. Requests are never sent twice
//!   blindly: an awake BMS would answer twice.
//! * Reads are retried a bounded number of times. A write is re-sent only when
//!   nothing at all came back (no ACK, NACK or 0x10 echo, not even a damaged
//!   one), and never after anything did: then the read-back decides. A write
//!   always follows a read the BMS just answered, so it gets no wake-up resend.
//! * After a transaction that went out more than once, the next request of the
//!   same command waits until an answer to the earlier copy would have arrived,
//!   so a late answer is never taken for the answer to the next request (0x03
//!   replies carry no address; 0x09 replies and 0x10 echoes do, and a reply to
//!   another command is refused by its command byte).
//! * After N consecutive transactions that heard nothing at all (not one byte on
//!   any attempt) the link is offline; the first valid reply brings it back (the
//!   bridge then re-reads version and settings). Any byte received during a
//!   transaction — a corrupt reply, noise, an ASCII line — shows the BMS is there:
//!   such a transaction may fail, but it does not count towards offline, even when
//!   its last attempt got silence; and bytes arriving between transactions (a
//!   late answer) reset the count of silent ones.
//! * Counters wrap modulo 2^32 (like hardware counters): nothing here can
//!   overflow-panic, in debug builds too, however long it runs. Times saturate.
//! * Frames that do not answer the outstanding request are counted as
//!   unsolicited and ignored.

use protocol_core::decoder::{DecodeError, Decoder};
use protocol_core::frame::{FrameRef, NackCode};
use protocol_core::request::{Request, RequestBytes, RequestError};
use protocol_core::response::{Response, ResponseError};

use crate::bms::timing::{Timing, BYTE_TIME_US};
use crate::Instant;

/// Bytes to put on the UART now.
pub type Transmit = RequestBytes;

/// How a transaction treats silence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Silence {
    /// Silence is a failure after the wake-up resend and the retries, and counts
    /// towards "offline".
    Failure,
    /// As [`Silence::Failure`], but a silent failure does not count towards
    /// "offline": reads while the BMS is expected to be restarting.
    Tolerated,
    /// Silence is a normal outcome ([`Failure::Silent`]) and nothing is re-sent:
    /// a reset (its ACK may never come) and a write to 340 (the BMS restarts).
    Expected,
}

/// Why a transaction failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Failure {
    /// Nothing valid arrived before the deadline, every attempt.
    Timeout,
    /// Bytes arrived but never a valid answer (last decode error kept).
    Corrupt(DecodeError),
    /// A CRC-valid frame that does not fit the request (length, echo).
    Invalid(ResponseError),
    /// The BMS answered NACK (for reads: after the retries a CRC NACK allows).
    Nack(NackCode),
    /// Silence where silence was expected (reset).
    Silent,
    /// The request could not be encoded (a bug upstream; never sent).
    Request(RequestError),
}

impl Failure {
    /// Short snake_case name.
    pub const fn name(&self) -> &'static str {
        match self {
            Failure::Timeout => "timeout",
            Failure::Corrupt(e) => e.reason(),
            Failure::Invalid(e) => e.reason(),
            Failure::Nack(_) => "nack",
            Failure::Silent => "silent",
            Failure::Request(e) => e.reason(),
        }
    }
}

/// A finished transaction.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Completion {
    /// What was asked.
    pub request: Request,
    /// What came back.
    pub result: Result<Response, Failure>,
    /// First send to completion, µs.
    pub latency_us: Instant,
    /// How many times the request went out.
    pub sends: u8,
}

/// A finished transaction where the link keeps it ([`Link::completion`]): the
/// same fields as [`Completion`], borrowed instead of moved (the request and the
/// response are hundreds of bytes each).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompletionRef<'a> {
    /// What was asked.
    pub request: &'a Request,
    /// What came back.
    pub result: &'a Result<Response, Failure>,
    /// First send to completion, µs.
    pub latency_us: Instant,
    /// How many times the request went out.
    pub sends: u8,
}

/// What the link keeps of a finished transaction besides its request.
#[derive(Debug, Clone, PartialEq)]
struct Outcome {
    result: Result<Response, Failure>,
    latency_us: Instant,
    sends: u8,
}

/// Link counters (logged periodically). Every counter wraps modulo 2^32 by
/// design; the latency sum restarts when the reply counter wraps.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LinkStats {
    /// Transactions started.
    pub requests: u32,
    /// Valid replies (answers to the outstanding request, NACKs included).
    pub replies: u32,
    /// Attempts that ended in silence or an incomplete reply at the deadline.
    pub timeouts: u32,
    /// Re-sends after silence (wake-up).
    pub wakeup_resends: u32,
    /// Re-sends after a failed attempt.
    pub retries: u32,
    /// Frames with a bad CRC.
    pub crc_errors: u32,
    /// Other framing errors (length, truncation, packet sequence).
    pub framing_errors: u32,
    /// CRC-valid frames that did not fit the request (length, echo).
    pub invalid_replies: u32,
    /// NACK 0x00 (command error).
    pub nacks_command: u32,
    /// NACK 0x01 (CRC error).
    pub nacks_crc: u32,
    /// NACKs with another code.
    pub nacks_other: u32,
    /// Bytes skipped by the decoder (noise, ASCII broadcasts, corrupt frames).
    pub skipped_bytes: u32,
    /// Frames that answered no outstanding request.
    pub unsolicited: u32,
    /// Failed transactions.
    pub failures: u32,
    /// Smallest reply latency, µs.
    pub latency_min_us: u32,
    /// Largest reply latency, µs.
    pub latency_max_us: u32,
    /// Sum of reply latencies, µs (for the mean).
    pub latency_sum_us: u64,
}

impl LinkStats {
    /// Mean reply latency, µs.
    pub fn latency_mean_us(&self) -> u32 {
        if self.replies == 0 {
            0
        } else {
            (self.latency_sum_us / u64::from(self.replies)) as u32
        }
    }
}

/// The transaction in progress (its request and bytes are kept apart in the
/// [`Link`], written once).
#[derive(Debug, Clone)]
struct Pending {
    silence: Silence,
    first_sent: Option<Instant>,
    deadline: Instant,
    /// Bytes arrived during the current attempt.
    heard: bool,
    /// Bytes arrived at any time during the transaction.
    heard_any: bool,
    last_rx: Option<Instant>,
    wake_used: bool,
    retries_used: u8,
    last_error: Option<Failure>,
    sends: u8,
    last_sent: Instant,
    timeout_us: Instant,
    /// Silence after reply bytes that ends an attempt early.
    idle_gap_us: Instant,
}

/// What the link wants next.
#[derive(Debug, Clone, PartialEq)]
pub enum LinkStep {
    /// Transmit these bytes now.
    Send(Transmit),
    /// A transaction finished.
    Done(Completion),
    /// Nothing until this time (or until bytes arrive).
    WaitUntil(Instant),
    /// No transaction in progress.
    Idle,
}

/// What the link wants next, as [`LinkStep`] without the payloads: the bytes to
/// send stay in the link ([`Link::transmit`]) and so does the finished
/// transaction until taken ([`Link::take_completion`]). This is what the bridge
/// uses: a [`Completion`] holds a whole [`Response`] (about 500 bytes), and
/// moving it through return values costs more than decoding it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Next {
    /// Transmit [`Link::transmit`] now.
    Send,
    /// A transaction finished: [`Link::take_completion`].
    Done,
    /// Nothing until this time (or until bytes arrive).
    WaitUntil(Instant),
    /// No transaction in progress.
    Idle,
}

/// The link engine.
#[derive(Debug, Clone)]
pub struct Link {
    config: Timing,
    decoder: Decoder,
    /// The request of the transaction in progress, or of the one finished in
    /// `done`: stored once, referenced from there on.
    request: Request,
    /// Its encoded bytes, while it is in progress.
    bytes: RequestBytes,
    pending: Option<Pending>,
    to_send: bool,
    done: Option<Outcome>,
    stats: LinkStats,
    consecutive_failures: u8,
    online: bool,
    /// No request goes out before this time (see [`Link::step`]).
    quiet_until: Instant,
    /// Command of the transaction that set [`Link::quiet_until`].
    quiet_command: u8,
    /// When the last byte arrived.
    last_heard: Option<Instant>,
}

impl Link {
    /// A link with no transaction; considered online until proven otherwise.
    pub fn new(config: Timing) -> Self {
        Self {
            config,
            decoder: Decoder::new(),
            request: Request::ReadVersion,
            bytes: RequestBytes::new(),
            pending: None,
            to_send: false,
            done: None,
            stats: LinkStats::default(),
            consecutive_failures: 0,
            online: true,
            quiet_until: 0,
            quiet_command: 0,
            last_heard: None,
        }
    }

    /// Replaces the counters: carries them over a restart of the logic, or
    /// presets them near the wrap point in tests.
    pub fn preset_stats(&mut self, stats: LinkStats) {
        self.stats = stats;
    }

    /// Counters.
    pub fn stats(&self) -> LinkStats {
        let mut s = self.stats;
        s.skipped_bytes = self.decoder.stats().skipped_bytes;
        s
    }

    /// True when no transaction is in progress.
    pub fn is_idle(&self) -> bool {
        self.pending.is_none() && self.done.is_none()
    }

    /// True when no reply can be on its way at `now`: no transaction in
    /// progress, no late answer to an earlier copy awaited
    /// (`Link::quiet_until`), and no byte for [`Timing::reply_idle_gap_us`]
    /// (a reply in flight streams back to back). What a flash write, which
    /// stops the CPU for tens of milliseconds while the UART FIFO holds 11 ms
    /// of bytes, waits for.
    pub fn quiet(&self, now: Instant) -> bool {
        self.is_idle()
            && now >= self.quiet_until
            && self
                .last_heard
                .is_none_or(|t| now.saturating_sub(t) >= self.config.reply_idle_gap_us)
    }

    /// When the link turns [`Link::quiet`] if nothing more happens (`None`:
    /// a transaction is under way).
    pub fn quiet_from(&self) -> Option<Instant> {
        self.is_idle().then(|| {
            let heard = self
                .last_heard
                .map_or(0, |t| t.saturating_add(self.config.reply_idle_gap_us));
            heard.max(self.quiet_until)
        })
    }

    /// False after [`crate::bms::timing::OFFLINE_AFTER_FAILURES`] consecutive failures,
    /// until a valid reply arrives.
    pub fn is_online(&self) -> bool {
        self.online
    }

    /// Consecutive transactions that got nothing back.
    pub fn consecutive_failures(&self) -> u8 {
        self.consecutive_failures
    }

    /// Starts a transaction. The request is validated and encoded here; an invalid
    /// one completes at once with [`Failure::Request`] and no byte is sent.
    /// Start when the link is idle ([`Link::is_idle`]): a transaction in
    /// progress, or a finished one not yet taken, is dropped (the request it
    /// referred to is replaced).
    pub fn start(&mut self, now: Instant, request: Request, silence: Silence) {
        self.start_with_timeout(now, request, silence, self.config.response_timeout_us);
    }

    /// As [`Link::start`], with a response timeout of its own (small reads on a
    /// bad line need not wait as long for an answer that is not coming).
    pub fn start_with_timeout(
        &mut self,
        now: Instant,
        request: Request,
        silence: Silence,
        timeout_us: Instant,
    ) {
        self.request = request;
        self.start_written(now, silence, timeout_us);
    }

    /// The slot of the next transaction's request, to write it in place (a
    /// request is hundreds of bytes) and start it with [`Link::start_written`].
    /// `None` while a transaction is in progress or finished and not cleared.
    pub fn request_slot(&mut self) -> Option<&mut Request> {
        self.is_idle().then_some(&mut self.request)
    }

    /// The request of the transaction in progress or just finished (the last
    /// one written into [`Link::request_slot`] otherwise).
    pub fn request(&self) -> &Request {
        &self.request
    }

    /// As [`Link::start_written`] for a piece of a block read (a 0x09 read of
    /// at most 15 registers): the piece timeout and idle gap
    /// ([`Timing::piece_response_timeout_us`],
    /// [`Timing::piece_reply_idle_gap_us`]).
    pub fn start_written_piece(&mut self, now: Instant, silence: Silence) {
        self.start_written(now, silence, self.config.piece_response_timeout_us);
        if let Some(p) = self.pending.as_mut() {
            p.idle_gap_us = self.config.piece_reply_idle_gap_us;
        }
    }

    /// As [`Link::start_with_timeout`], with the request written into
    /// [`Link::request_slot`] before.
    pub fn start_written(&mut self, now: Instant, silence: Silence, timeout_us: Instant) {
        self.stats.requests = self.stats.requests.wrapping_add(1);
        self.done = None;
        match self.request.encode_to(&mut self.bytes) {
            Ok(()) => {
                self.pending = Some(Pending {
                    silence,
                    first_sent: None,
                    deadline: now,
                    heard: false,
                    heard_any: false,
                    last_rx: None,
                    wake_used: false,
                    retries_used: 0,
                    last_error: None,
                    sends: 0,
                    last_sent: now,
                    timeout_us,
                    idle_gap_us: self.config.reply_idle_gap_us,
                });
                self.to_send = true;
            }
            Err(e) => {
                self.pending = None;
                self.done = Some(Outcome {
                    result: Err(Failure::Request(e)),
                    latency_us: 0,
                    sends: 0,
                });
            }
        }
    }

    /// What to do now. Call after [`Link::start`], after bytes arrived and when a
    /// deadline passed.
    pub fn step(&mut self, now: Instant) -> LinkStep {
        match self.next(now) {
            Next::Send => match self.transmit() {
                Some(b) => LinkStep::Send(b.clone()),
                None => LinkStep::Idle,
            },
            Next::Done => match self.take_completion() {
                Some(c) => LinkStep::Done(c),
                None => LinkStep::Idle,
            },
            Next::WaitUntil(t) => LinkStep::WaitUntil(t),
            Next::Idle => LinkStep::Idle,
        }
    }

    /// The bytes of the request in progress (to send after [`Next::Send`]).
    pub fn transmit(&self) -> Option<&Transmit> {
        self.pending.as_ref().map(|_| &self.bytes)
    }

    /// The finished transaction, after [`Next::Done`], where the link keeps it.
    pub fn completion(&self) -> Option<CompletionRef<'_>> {
        self.done.as_ref().map(|d| CompletionRef {
            request: &self.request,
            result: &d.result,
            latency_us: d.latency_us,
            sends: d.sends,
        })
    }

    /// Drops the finished transaction (after [`Link::completion`]).
    pub fn clear_completion(&mut self) {
        self.done = None;
    }

    /// The finished transaction, after [`Next::Done`]. Until it is taken,
    /// [`Link::next`] keeps answering [`Next::Done`].
    pub fn take_completion(&mut self) -> Option<Completion> {
        self.done.take().map(|d| Completion {
            request: self.request.clone(),
            result: d.result,
            latency_us: d.latency_us,
            sends: d.sends,
        })
    }

    /// As [`Link::step`], leaving the bytes to send and the finished transaction
    /// in the link (see [`Next`]).
    pub fn next(&mut self, now: Instant) -> Next {
        // Bounded: each pass either returns or changes the state towards a return.
        for _ in 0..4 {
            if self.done.is_some() {
                return Next::Done;
            }
            let Some(p) = self.pending.as_mut() else {
                return Next::Idle;
            };
            if self.to_send {
                // After a transaction that went out more than once, an answer to an
                // earlier copy may still be on its way; 0x03 replies carry no
                // address, so it could pass for the answer to the next request of
                // the same command. Stay quiet until it would have arrived (frames
                // meanwhile are counted as unsolicited). A reply to another
                // command is refused by its command byte, and 0x09 replies and
                // 0x10 echoes carry their addresses: no wait for those.
                let command = self.request.command();
                let self_identifying = matches!(command, 0x09 | 0x10);
                if p.sends == 0
                    && now < self.quiet_until
                    && command == self.quiet_command
                    && !self_identifying
                {
                    return Next::WaitUntil(self.quiet_until);
                }
                self.to_send = false;
                p.sends = p.sends.saturating_add(1);
                p.last_sent = now;
                // Whatever is still buffered belongs to no one now.
                let stats = &mut self.stats;
                self.decoder.finish(|r| count_unsolicited(stats, &r));
                p.first_sent.get_or_insert(now);
                p.heard = false;
                p.last_rx = None;
                p.deadline = now
                    .saturating_add(BYTE_TIME_US * self.bytes.len() as Instant)
                    .saturating_add(p.timeout_us);
                self.decoder.expect(&self.request);
                return Next::Send;
            }
            let deadline = match p.last_rx {
                Some(t) => p.deadline.min(t.saturating_add(p.idle_gap_us)),
                None => p.deadline,
            };
            if now < deadline {
                return Next::WaitUntil(deadline);
            }
            self.on_deadline(now);
        }
        Next::WaitUntil(now)
    }

    /// The response deadline passed.
    fn on_deadline(&mut self, now: Instant) {
        // Whatever is half-received is cut off; a complete frame it reveals may
        // still be the answer.
        self.drain::<true>(now);
        let Some(p) = self.pending.as_mut() else {
            return;
        };
        if self.to_send {
            return; // on_item queued a retry
        }
        self.stats.timeouts = self.stats.timeouts.wrapping_add(1);
        if !p.heard {
            if p.silence == Silence::Expected {
                self.finish(now, Err(Failure::Silent));
                return;
            }
            // A write always follows a read the BMS just answered: it is awake,
            // so silence is not a wake-up case for a write.
            if !p.wake_used && !self.request.is_write() {
                p.wake_used = true;
                self.stats.wakeup_resends = self.stats.wakeup_resends.wrapping_add(1);
                self.to_send = true;
                return;
            }
            self.retry_or_fail(now, Failure::Timeout);
            return;
        }
        let err = p.last_error.unwrap_or(Failure::Timeout);
        if self.request.is_write() {
            // Something came back (a corrupt ACK/echo/NACK?): never re-send a write
            // the BMS may have answered. The read-back decides.
            self.finish(now, Err(err));
        } else {
            self.retry_or_fail(now, err);
        }
    }

    fn retry_or_fail(&mut self, now: Instant, err: Failure) {
        let Some(p) = self.pending.as_mut() else {
            return;
        };
        if p.retries_used < self.config.max_retries {
            p.retries_used += 1;
            p.last_error = Some(err);
            self.stats.retries = self.stats.retries.wrapping_add(1);
            self.to_send = true;
        } else {
            self.finish(now, Err(err));
        }
    }

    fn finish(&mut self, now: Instant, result: Result<Response, Failure>) {
        if self.pending.is_none() {
            return;
        }
        let done = self.done.insert(Outcome {
            result: Err(Failure::Silent),
            latency_us: 0,
            sends: 0,
        });
        done.result = result;
        self.finish_in_place(now);
    }

    /// Finishes the transaction whose result is already in `self.done` (see
    /// [`see`]: a decoded response is written there in place).
    fn finish_in_place(&mut self, now: Instant) {
        let Some(p) = self.pending.take() else {
            self.done = None;
            return;
        };
        let outcome = match self.done.as_ref().map(|d| &d.result) {
            Some(Ok(_)) => Ok(()),
            Some(Err(f)) => Err(*f),
            None => return,
        };
        self.to_send = false;
        self.decoder.clear_expectation();
        if p.sends > 1 {
            // An answer to the last copy may come as late as the full timeout.
            self.quiet_command = self.request.command();
            self.quiet_until = p
                .last_sent
                .saturating_add(BYTE_TIME_US * self.bytes.len() as Instant)
                .saturating_add(self.config.response_timeout_us.max(p.timeout_us));
        }
        let latency_us = now.saturating_sub(p.first_sent.unwrap_or(now));
        match outcome {
            Ok(()) | Err(Failure::Nack(_)) => {
                self.consecutive_failures = 0;
                self.online = true;
                self.stats.replies = self.stats.replies.wrapping_add(1);
                let l = latency_us.min(u64::from(u32::MAX)) as u32;
                if self.stats.replies == 1 || l < self.stats.latency_min_us {
                    self.stats.latency_min_us = l;
                }
                self.stats.latency_max_us = self.stats.latency_max_us.max(l);
                self.stats.latency_sum_us = self.stats.latency_sum_us.wrapping_add(u64::from(l));
                if self.stats.replies == 0 {
                    // The reply counter wrapped: restart the mean with it.
                    self.stats.latency_sum_us = 0;
                }
            }
            Err(Failure::Silent) => {}
            Err(Failure::Timeout) if p.silence == Silence::Tolerated => {
                self.stats.failures = self.stats.failures.wrapping_add(1);
            }
            // Nothing at all came back, on any attempt: that is what counts
            // towards "offline".
            Err(Failure::Timeout) if !p.heard_any => {
                self.stats.failures = self.stats.failures.wrapping_add(1);
                self.consecutive_failures = self.consecutive_failures.saturating_add(1);
                if self.consecutive_failures >= self.config.offline_after_failures {
                    self.online = false;
                }
            }
            // Bytes came back, just never a valid answer: the BMS is there, the
            // line is noisy. A failure, but not a sign of absence.
            Err(_) => {
                self.stats.failures = self.stats.failures.wrapping_add(1);
                self.consecutive_failures = 0;
            }
        }
        if let Some(d) = self.done.as_mut() {
            d.latency_us = latency_us;
            d.sends = p.sends;
        }
    }

    /// Bytes received from the UART at `now`. Call [`Link::step`] afterwards.
    pub fn on_bytes(&mut self, now: Instant, bytes: &[u8]) {
        self.heard(now, !bytes.is_empty());
        let mut input = bytes;
        loop {
            let n = self.decoder.push(input);
            input = input.get(n..).unwrap_or(&[]);
            self.drain::<false>(now);
            if input.is_empty() {
                break;
            }
        }
    }

    /// Where a UART reader can receive directly (the decoder's free space; the
    /// same space until [`Link::on_received`]). Never empty between calls.
    pub fn rx_buffer(&mut self) -> &mut [u8] {
        self.decoder.spare()
    }

    /// The first `n` bytes of [`Link::rx_buffer`] were received at `now`: as
    /// [`Link::on_bytes`] with those bytes, without copying them.
    pub fn on_received(&mut self, now: Instant, n: usize) {
        let n = self.decoder.commit(n);
        self.heard(now, n > 0);
        self.drain::<false>(now);
    }

    /// Bookkeeping for bytes received at `now` (`any`: at least one).
    fn heard(&mut self, now: Instant, any: bool) {
        if !any {
            return;
        }
        self.last_heard = Some(now);
        // Silence means no byte at all: a late answer between two silent
        // transactions (a reply delayed past our timeout) shows the BMS is
        // there just as well.
        self.consecutive_failures = 0;
        if let Some(p) = self.pending.as_mut() {
            // Whatever it is, the BMS (or at least the wire) is there.
            p.heard_any = true;
            if !self.to_send {
                p.last_rx = Some(now);
            }
        }
    }

    /// Handles every frame the decoder finds in what it holds. `ENDING`: at the
    /// response deadline, the half-received rest is cut off too (`flush_ref`),
    /// and the handling stops once the transaction is decided. (A constant: the
    /// receive path polls after every UART read and pays for no test of it.)
    fn drain<const ENDING: bool>(&mut self, now: Instant) {
        // Frames are handled where the decoder keeps them (see `see`).
        let mut spill = None;
        loop {
            let item = if ENDING {
                self.decoder.flush_ref(&mut spill)
            } else {
                self.decoder.poll_ref(&mut spill)
            };
            let Some(item) = item else {
                break;
            };
            let seen = see(
                self.pending.is_some(),
                self.to_send,
                &mut self.done,
                &self.request,
                item,
            );
            self.on_seen(now, seen);
            if ENDING && (self.pending.is_none() || self.to_send) {
                break;
            }
        }
    }

    /// The rest of a decoded item, after [`see`].
    fn on_seen(&mut self, now: Instant, seen: Seen) {
        let decoded = match seen {
            Seen::Unsolicited(None) => {
                self.stats.unsolicited = self.stats.unsolicited.wrapping_add(1);
                return;
            }
            Seen::Unsolicited(Some(e)) => {
                count_decode_error(&mut self.stats, &e);
                return;
            }
            Seen::Corrupt(e) => {
                // Probably our answer, damaged: the BMS is talking.
                if let Some(p) = self.pending.as_mut() {
                    p.heard = true;
                    p.last_error = Some(Failure::Corrupt(e));
                }
                count_decode_error(&mut self.stats, &e);
                return; // keep waiting: a good frame may follow
            }
            Seen::Decoded(d) => d,
        };
        let Some(p) = self.pending.as_mut() else {
            return; // see() decodes only for a transaction in progress
        };
        match decoded {
            Ok(Some(code)) => {
                p.heard = true;
                match code {
                    NackCode::CommandError => {
                        self.stats.nacks_command = self.stats.nacks_command.wrapping_add(1)
                    }
                    NackCode::CrcError => {
                        self.stats.nacks_crc = self.stats.nacks_crc.wrapping_add(1)
                    }
                    NackCode::Unknown(_) => {
                        self.stats.nacks_other = self.stats.nacks_other.wrapping_add(1)
                    }
                }
                // The BMS got our request corrupted: a read may be re-sent (its
                // NACK is complete, nothing else is coming). A write never is.
                if code == NackCode::CrcError && !self.request.is_write() {
                    self.retry_or_fail(now, Failure::Nack(code));
                } else {
                    self.finish(now, Err(Failure::Nack(code)));
                }
            }
            Ok(None) => self.finish_in_place(now),
            // Not for us (a late or duplicated answer, another command): ignored,
            // and it does not count as the BMS answering this request.
            Err(ResponseError::UnexpectedResponse { .. }) => {
                self.stats.unsolicited = self.stats.unsolicited.wrapping_add(1)
            }
            Err(e) => {
                // Our command, CRC-valid, but it does not fit the request (length,
                // address echo): possibly a stale answer. Note it and wait for the
                // deadline rather than re-sending while the real answer may still
                // be coming.
                p.heard = true;
                self.stats.invalid_replies = self.stats.invalid_replies.wrapping_add(1);
                p.last_error = Some(Failure::Invalid(e));
            }
        }
    }
}

/// A decoded item, handled as far as it needs the frame itself (see [`see`]).
enum Seen {
    /// No request waits for it (none in progress, a re-send queued, or the
    /// transaction finished): a frame (`None`) or a decode error.
    Unsolicited(Option<DecodeError>),
    /// A decode error while a request waits.
    Corrupt(DecodeError),
    /// A frame decoded against the request in progress: written into the
    /// completion slot when it answers it (`Ok(None)`), a NACK, or why not.
    Decoded(Result<Option<NackCode>, ResponseError>),
}

/// The part of handling a decoded item that needs the frame: it is borrowed
/// from the decoder (a 0x03 reply is never copied out of its buffer) and decoded
/// straight into the completion slot (no `Response` moved); the slot is emptied
/// again unless the reply finishes the transaction. The rest is
/// [`Link::on_seen`], once the decoder is free again.
fn see(
    pending: bool,
    to_send: bool,
    done: &mut Option<Outcome>,
    request: &Request,
    item: Result<FrameRef<'_>, DecodeError>,
) -> Seen {
    if !pending || to_send || done.is_some() {
        // Nothing waits, or a (re-)send is queued: anything arriving now answers
        // an old attempt.
        return Seen::Unsolicited(item.err());
    }
    let frame = match item {
        Ok(f) => f,
        Err(e) => return Seen::Corrupt(e),
    };
    let decoded = {
        let d = done.insert(Outcome {
            result: Ok(Response::Ack { command: 0 }),
            latency_us: 0,
            sends: 0,
        });
        match &mut d.result {
            Ok(r) => Response::decode_ref_into(request, frame, r),
            Err(_) => Ok(()),
        }
    };
    let nack = match (&decoded, done.as_ref().map(|d| &d.result)) {
        (Ok(()), Some(Ok(Response::Nack { code, .. }))) => Some(*code),
        _ => None,
    };
    if decoded.is_err() || nack.is_some() {
        *done = None;
    }
    Seen::Decoded(decoded.map(|()| nack))
}

fn count_decode_error(stats: &mut LinkStats, e: &DecodeError) {
    match e {
        DecodeError::Crc { .. } => stats.crc_errors = stats.crc_errors.wrapping_add(1),
        _ => stats.framing_errors = stats.framing_errors.wrapping_add(1),
    }
}

fn count_unsolicited(stats: &mut LinkStats, item: &Result<protocol_core::Frame, DecodeError>) {
    match item {
        Ok(_) => stats.unsolicited = stats.unsolicited.wrapping_add(1),
        Err(e) => count_decode_error(stats, e),
    }
}
