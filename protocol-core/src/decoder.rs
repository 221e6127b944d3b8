//! Streaming response decoder.
//!
//! Feed it any chunk of received bytes ([`Decoder::push`]) and poll it
//! ([`Decoder::poll`]) for complete frames or errors. Memory is bounded: one
//! [`MAX_FRAME_LEN`] scan buffer plus one [`MAX_PAYLOAD`] reassembly buffer.
//!
//! * Bytes that cannot start a frame — anything but the preamble, a preamble
//!   followed by a byte no response starts with, and so the ASCII broadcast lines
//!   of HARDWARE-NOTES — are skipped and counted.
//! * After a CRC or length failure only the first byte (the preamble) is dropped and
//!   the rest is scanned again, so a real frame that starts inside a corrupt one is
//!   still found (the ublox / postcard accumulator approach).
//! * Packetized native replies (0x07, 0x09, 0x11, 0x12; PL bit 7 = more packets,
//!   bits 0-5 = packet ID) are reassembled. A packet with a non-consecutive ID, or a
//!   reassembly interrupted by another frame or by [`Decoder::flush`], is an error;
//!   a partial value is never returned.
//!
//! Nothing here panics, whatever the input.

use crate::command::{self as cmd, PREAMBLE};
use crate::crc::crc16;
use crate::frame::{
    framing, Frame, FrameRef, Framing, NackCode, Payload, MAX_FRAME_LEN, MAX_PAYLOAD,
    PL_MORE_PACKETS, PL_VALUE_MASK,
};

/// Why a candidate frame was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum DecodeError {
    /// The CRC carried by the frame does not match the bytes.
    Crc {
        /// Command byte of the candidate.
        command: u8,
        /// CRC computed over the received bytes.
        computed: u16,
        /// CRC carried by the frame.
        received: u16,
    },
    /// A known command with a PL byte no valid reply can have.
    Length {
        /// Command byte.
        command: u8,
        /// The PL byte received.
        pl: u8,
    },
    /// The input ended (see [`Decoder::flush`]) inside a candidate frame.
    Truncated {
        /// Command byte, if it arrived.
        command: Option<u8>,
        /// Bytes of the candidate received.
        have: usize,
    },
    /// A packet of a multi-packet reply arrived with an unexpected ID.
    PacketSequence {
        /// Command byte.
        command: u8,
        /// The ID that should have come next.
        expected: u8,
        /// The ID that came.
        got: u8,
    },
    /// A multi-packet reply was interrupted (another frame or the end of input)
    /// before its last packet.
    IncompletePackets {
        /// Command byte.
        command: u8,
        /// Packets received before the interruption.
        packets: u8,
    },
    /// The reassembled payload would exceed [`MAX_PAYLOAD`].
    PayloadOverflow {
        /// Command byte.
        command: u8,
    },
    /// A multi-packet reply reassembled to a length the request (or the command's
    /// layout) rules out: a packet went missing. The last packet carries no ID, so
    /// this is how a lost packet just before it is caught.
    PacketLength {
        /// Command byte.
        command: u8,
        /// Expected payload bytes, when the outstanding request tells.
        expected: Option<u16>,
        /// Reassembled payload bytes.
        got: u16,
    },
}

impl DecodeError {
    /// A short snake_case reason, for logs and the replay tool.
    pub const fn reason(&self) -> &'static str {
        match self {
            DecodeError::Crc { .. } => "crc_mismatch",
            DecodeError::Length { .. } => "bad_length",
            DecodeError::Truncated { .. } => "truncated",
            DecodeError::PacketSequence { .. } => "packet_out_of_order",
            DecodeError::IncompletePackets { .. } => "incomplete_packets",
            DecodeError::PayloadOverflow { .. } => "payload_overflow",
            DecodeError::PacketLength { .. } => "packet_missing",
        }
    }
    /// The command byte concerned, when known.
    pub const fn command(&self) -> Option<u8> {
        match *self {
            DecodeError::Crc { command, .. }
            | DecodeError::Length { command, .. }
            | DecodeError::PacketSequence { command, .. }
            | DecodeError::IncompletePackets { command, .. }
            | DecodeError::PayloadOverflow { command }
            | DecodeError::PacketLength { command, .. } => Some(command),
            DecodeError::Truncated { command, .. } => command,
        }
    }
}

/// What the decoder has seen.
///
/// Every counter wraps modulo 2^32 by design (like a hardware counter): a
/// decoder that runs for years never panics on overflow, in debug builds too.
/// Compare two readings with `wrapping_sub`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DecoderStats {
    /// Bytes accepted by [`Decoder::push`].
    pub bytes_in: u32,
    /// Bytes dropped as not belonging to any valid frame.
    pub skipped_bytes: u32,
    /// Complete frames returned (a multi-packet reply counts once).
    pub frames: u32,
    /// CRC failures.
    pub crc_errors: u32,
    /// Impossible PL bytes.
    pub length_errors: u32,
    /// Candidates cut off by [`Decoder::flush`].
    pub truncated: u32,
    /// Multi-packet sequence errors and interrupted reassemblies.
    pub packet_errors: u32,
}

#[derive(Debug, Clone)]
struct Assembly {
    command: u8,
    next_id: u8,
    packets: u8,
    payload: Payload,
}

/// The streaming decoder. See the module documentation.
#[derive(Debug, Clone)]
pub struct Decoder {
    buf: [u8; MAX_FRAME_LEN],
    len: usize,
    asm: Option<Assembly>,
    expect: Option<(u8, Option<u16>)>,
    /// Total length of the candidate at the front of the buffer, once its header
    /// told (0: not known). Until that many bytes are buffered, `poll` answers at
    /// once instead of scanning the same header again after every chunk.
    need: usize,
    /// Bytes at the front that hold the frame last lent by
    /// [`Decoder::poll_ref`]: dropped at the next call.
    lent: usize,
    stats: DecoderStats,
}

impl Default for Decoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Decoder {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self {
            buf: [0; MAX_FRAME_LEN],
            len: 0,
            asm: None,
            expect: None,
            need: 0,
            lent: 0,
            stats: DecoderStats {
                bytes_in: 0,
                skipped_bytes: 0,
                frames: 0,
                crc_errors: 0,
                length_errors: 0,
                truncated: 0,
                packet_errors: 0,
            },
        }
    }

    /// Counters since creation (not cleared by [`Decoder::reset`]).
    pub const fn stats(&self) -> DecoderStats {
        self.stats
    }

    /// Bytes buffered and not yet decided.
    pub const fn buffered(&self) -> usize {
        self.len - self.lent
    }

    /// True while a multi-packet reply is being reassembled.
    pub const fn in_packets(&self) -> bool {
        self.asm.is_some()
    }

    /// Tells the decoder which request is outstanding, so a multi-packet reply
    /// can be checked against the payload length that request implies.
    pub fn expect(&mut self, request: &crate::request::Request) {
        use crate::request::Request as R;
        let len = match request {
            R::ReadRegistersNative { count, .. } => Some(2 * u16::from(*count)),
            R::ReadIndividual(a) => Some(4 * a.len() as u16),
            _ => None,
        };
        self.expect = Some((request.command(), len));
    }

    /// Forgets the outstanding request.
    pub fn clear_expectation(&mut self) {
        self.expect = None;
    }

    /// Forget buffered bytes and any partial reassembly (counted as skipped).
    pub fn reset(&mut self) {
        self.release();
        self.stats.skipped_bytes = self.stats.skipped_bytes.wrapping_add(self.len as u32);
        self.len = 0;
        self.need = 0;
        self.asm = None;
    }

    /// Copies as many bytes of `input` as fit into the scan buffer and returns how
    /// many were taken. Call [`Decoder::poll`] until it returns `None`, then push the
    /// rest. Once the buffer is full, `poll` always makes progress.
    #[inline]
    pub fn push(&mut self, input: &[u8]) -> usize {
        let spare = self.spare();
        let n = spare.len().min(input.len());
        if let (Some(dst), Some(src)) = (spare.get_mut(..n), input.get(..n)) {
            dst.copy_from_slice(src);
            self.commit(n)
        } else {
            0
        }
    }

    /// The free end of the scan buffer, for a reader to receive into directly
    /// (a UART driver writing there saves the copy [`Decoder::push`] makes);
    /// then [`Decoder::commit`] the bytes written. It is the same space until
    /// then, provided nothing polls the decoder in between (a poll may move the
    /// buffered bytes). Never empty once [`Decoder::poll`] (or `poll_ref`,
    /// `poll_into`) has answered `None`: a full buffer always makes progress.
    #[inline]
    pub fn spare(&mut self) -> &mut [u8] {
        self.release();
        self.buf.get_mut(self.len..).unwrap_or(&mut [])
    }

    /// Takes the first `n` bytes of [`Decoder::spare`] as received; returns how
    /// many were taken (`n`, or the spare room if `n` is larger).
    #[inline]
    pub fn commit(&mut self, n: usize) -> usize {
        self.release();
        let n = n.min(MAX_FRAME_LEN.saturating_sub(self.len));
        self.len += n;
        self.stats.bytes_in = self.stats.bytes_in.wrapping_add(n as u32);
        n
    }

    /// The next frame or error found in the buffered bytes, or `None` when more
    /// bytes are needed.
    pub fn poll(&mut self) -> Option<Result<Frame, DecodeError>> {
        self.step(false)
    }

    /// As [`Decoder::poll`], with the answer written into `out` instead of
    /// returned: a frame is 264 bytes, and a returned one is copied on its way
    /// out. Decoding a stream this way, the frame is built once, where the caller
    /// reads it.
    pub fn poll_into(&mut self, out: &mut Option<Result<Frame, DecodeError>>) {
        self.step_into(false, out);
    }

    /// As [`Decoder::flush`], with the answer written into `out` (see
    /// [`Decoder::poll_into`]).
    pub fn flush_into(&mut self, out: &mut Option<Result<Frame, DecodeError>>) {
        self.step_into(true, out);
    }

    /// Like [`Decoder::poll`], but treats the input as ended: an incomplete candidate
    /// is reported as [`DecodeError::Truncated`] (and rescanned from its second
    /// byte), an unfinished reassembly as [`DecodeError::IncompletePackets`]. Call it
    /// until it returns `None` when a response deadline passes.
    pub fn flush(&mut self) -> Option<Result<Frame, DecodeError>> {
        self.step(true)
    }

    /// Convenience: push all of `input`, calling `sink` with every result in order.
    pub fn feed(&mut self, mut input: &[u8], mut sink: impl FnMut(Result<Frame, DecodeError>)) {
        // Polled into one place (see `poll_into`): a frame is moved once, to
        // `sink`, and a poll that finds nothing moves nothing.
        let mut item = None;
        loop {
            let n = self.push(input);
            input = input.get(n..).unwrap_or(&[]);
            loop {
                self.poll_into(&mut item);
                match item.take() {
                    Some(r) => sink(r),
                    None => break,
                }
            }
            if input.is_empty() {
                break;
            }
        }
    }

    /// Convenience: [`Decoder::flush`] until empty, calling `sink` with each result.
    pub fn finish(&mut self, mut sink: impl FnMut(Result<Frame, DecodeError>)) {
        let mut item = None;
        loop {
            self.flush_into(&mut item);
            match item.take() {
                Some(r) => sink(r),
                None => break,
            }
        }
    }

    /// Drops the frame lent by [`Decoder::poll_ref`], if any.
    #[inline(always)]
    fn release(&mut self) {
        if self.lent > 0 {
            self.release_lent();
        }
    }

    fn release_lent(&mut self) {
        let n = core::mem::take(&mut self.lent);
        self.drop_front(n);
    }

    /// As [`Decoder::poll_into`], with a single-frame data reply (0x03 register
    /// blocks: the live path) lent where it lies in the buffer
    /// instead of copied out. Other answers (ACK, NACK, reassembled packets,
    /// errors) are written into `spill` and lent from there. The frame is
    /// dropped from the buffer at the next call into the decoder.
    #[inline]
    pub fn poll_ref<'a>(
        &'a mut self,
        spill: &'a mut Option<Result<Frame, DecodeError>>,
    ) -> Option<Result<FrameRef<'a>, DecodeError>> {
        self.step_ref(false, spill)
    }

    /// As [`Decoder::flush_into`], lending as [`Decoder::poll_ref`].
    #[inline]
    pub fn flush_ref<'a>(
        &'a mut self,
        spill: &'a mut Option<Result<Frame, DecodeError>>,
    ) -> Option<Result<FrameRef<'a>, DecodeError>> {
        self.step_ref(true, spill)
    }

    #[inline(always)]
    fn step_ref<'a>(
        &'a mut self,
        ending: bool,
        spill: &'a mut Option<Result<Frame, DecodeError>>,
    ) -> Option<Result<FrameRef<'a>, DecodeError>> {
        if self.lent == 0 && !ending && self.len < self.need {
            // The candidate at the front is still short (most polls at small
            // chunks): answered here, without the call.
            *spill = None;
            return None;
        }
        match self.step_inner(ending, spill, true) {
            Some((command, from, to)) => Some(Ok(FrameRef::Data {
                command,
                payload: self.buf.get(from..to).unwrap_or(&[]),
                packets: 1,
            })),
            None => match spill {
                Some(Ok(f)) => Some(Ok(f.as_frame_ref())),
                Some(Err(e)) => Some(Err(*e)),
                None => None,
            },
        }
    }

    fn drop_front(&mut self, n: usize) {
        self.need = 0;
        let n = n.min(self.len);
        self.buf.copy_within(n..self.len, 0);
        self.len -= n;
    }

    fn skip(&mut self, n: usize) {
        self.drop_front(n);
        self.stats.skipped_bytes = self.stats.skipped_bytes.wrapping_add(n as u32);
    }

    fn step(&mut self, ending: bool) -> Option<Result<Frame, DecodeError>> {
        if self.lent == 0 && !ending && self.len < self.need {
            return None; // the candidate at the front is still short
        }
        let mut out = None;
        self.step_into(ending, &mut out);
        out
    }

    /// Writes the decoder's next answer into `out` (`None` when more bytes are
    /// needed).
    fn step_into(&mut self, ending: bool, out: &mut Option<Result<Frame, DecodeError>>) {
        let _owned = self.step_inner(ending, out, false); // None: not lending
    }

    /// The decoding step. With `lend`, a single data frame is left in the
    /// buffer and returned as `(command, payload start, payload end)` (see
    /// [`Decoder::poll_ref`]); every other answer is written into `out`.
    fn step_inner(
        &mut self,
        ending: bool,
        out: &mut Option<Result<Frame, DecodeError>>,
        lend: bool,
    ) -> Option<(u8, usize, usize)> {
        *out = None;
        self.release();
        if !ending && self.len < self.need {
            return None; // the candidate at the front is still short
        }
        loop {
            // Drop everything before the next preamble.
            let data = self.buf.get(..self.len).unwrap_or(&[]);
            let start = data
                .iter()
                .position(|&b| b == PREAMBLE)
                .unwrap_or(data.len());
            if start > 0 {
                self.skip(start);
            }
            if self.len == 0 {
                if ending {
                    if let Some(asm) = self.asm.take() {
                        self.stats.packet_errors = self.stats.packet_errors.wrapping_add(1);
                        *out = Some(Err(DecodeError::IncompletePackets {
                            command: asm.command,
                            packets: asm.packets,
                        }));
                    }
                }
                return None;
            }
            let data = self.buf.get(..self.len).unwrap_or(&[]);
            match framing(data) {
                f @ (Framing::NeedMore | Framing::Short(_)) => {
                    if !ending {
                        if let Framing::Short(n) = f {
                            self.need = n;
                        }
                        return None;
                    }
                    let command = data.get(1).copied();
                    let have = self.len;
                    self.skip(1);
                    self.stats.truncated = self.stats.truncated.wrapping_add(1);
                    *out = Some(Err(DecodeError::Truncated { command, have }));
                    return None;
                }
                Framing::NotAFrame => self.skip(1),
                Framing::BadLength { command, pl } => {
                    self.skip(1);
                    self.stats.length_errors = self.stats.length_errors.wrapping_add(1);
                    *out = Some(Err(DecodeError::Length { command, pl }));
                    return None;
                }
                Framing::Complete(n) => {
                    let Some((body, crc_bytes)) =
                        data.get(..n).and_then(|f| f.split_last_chunk::<2>())
                    else {
                        return None; // unreachable: framing() checked the length
                    };
                    let computed = crc16(body);
                    let received = u16::from_le_bytes(*crc_bytes);
                    let command = body.get(1).copied().unwrap_or(0);
                    if computed != received {
                        self.skip(1);
                        self.stats.crc_errors = self.stats.crc_errors.wrapping_add(1);
                        *out = Some(Err(DecodeError::Crc {
                            command,
                            computed,
                            received,
                        }));
                        return None;
                    }
                    if lend && self.asm.is_none() {
                        if let Some(lent) = self.lend(n) {
                            return Some(lent);
                        }
                    }
                    // Written into `out` where it is built: not moved.
                    self.accept(n, out);
                    if out.is_some() {
                        return None;
                    }
                }
            }
        }
    }

    /// The CRC-valid candidate of length `n` at the front, when it is a single
    /// data frame and no reassembly is in progress: left in the buffer (dropped
    /// at the next call) and returned as `(command, payload
    /// start, payload end)`. What `accept` would build, without the copy.
    fn lend(&mut self, n: usize) -> Option<(u8, usize, usize)> {
        let command = self.buf.get(1).copied()?;
        if matches!(command, cmd::ACK | cmd::NACK) || cmd::is_packetized(command) {
            return None;
        }
        let skip_pl = matches!(
            crate::frame::layout(command),
            crate::frame::Layout::Counted(_)
        );
        let from = if skip_pl { 3 } else { 2 };
        let to = n.checked_sub(2)?;
        if to < from || to - from > MAX_PAYLOAD {
            return None; // accept() reports it
        }
        self.lent = n;
        self.stats.frames = self.stats.frames.wrapping_add(1);
        Some((command, from, to))
    }

    /// A CRC-valid candidate of length `n` sits at the front of the buffer.
    /// Its answer goes into `out` (left `None` for a packet of a reply still
    /// being reassembled).
    fn accept(&mut self, n: usize, out: &mut Option<Result<Frame, DecodeError>>) {
        let frame = self.buf.get(..n).unwrap_or(&[]);
        let command = frame.get(1).copied().unwrap_or(0);
        let body = frame.get(..n.saturating_sub(2)).unwrap_or(&[]);

        // A reassembly in progress can only be continued by the same command.
        if let Some(asm) = &self.asm {
            if command != asm.command || !cmd::is_packetized(command) {
                let err = DecodeError::IncompletePackets {
                    command: asm.command,
                    packets: asm.packets,
                };
                self.asm = None;
                self.stats.packet_errors = self.stats.packet_errors.wrapping_add(1);
                // The frame stays in the buffer and is decoded on the next poll.
                *out = Some(Err(err));
                return;
            }
        }

        match command {
            cmd::ACK => {
                *out = Some(Ok(Frame::Ack {
                    command: body.get(2).copied().unwrap_or(0),
                }))
            }
            cmd::NACK => {
                *out = Some(Ok(Frame::Nack {
                    command: body.get(2).copied().unwrap_or(0),
                    code: NackCode::from_u8(body.get(3).copied().unwrap_or(0)),
                }))
            }
            c if cmd::is_packetized(c) => {
                let pl = body.get(2).copied().unwrap_or(0);
                // Copy the packet out of the scan buffer (at most 63 bytes).
                let mut chunk = heapless::Vec::<u8, { crate::frame::MAX_PACKET_PAYLOAD }>::new();
                if chunk
                    .extend_from_slice(body.get(3..).unwrap_or(&[]))
                    .is_err()
                {
                    *out = Some(Err(DecodeError::PayloadOverflow { command: c }));
                } else {
                    *out = self.packet(c, pl, &chunk);
                }
            }
            c => {
                let skip_pl = matches!(crate::frame::layout(c), crate::frame::Layout::Counted(_));
                let bytes = body.get(if skip_pl { 3 } else { 2 }..).unwrap_or(&[]);
                // Filled in place where the caller receives it (a frame is 264
                // bytes).
                *out = Some(Ok(Frame::Data {
                    command: c,
                    payload: Payload::new(),
                    packets: 1,
                }));
                if let Some(Ok(Frame::Data { payload, .. })) = out {
                    if payload.extend_from_slice(bytes).is_err() {
                        *out = Some(Err(DecodeError::PayloadOverflow { command: c }));
                    }
                }
            }
        }
        self.drop_front(n);
        if let Some(Ok(_)) = out {
            self.stats.frames = self.stats.frames.wrapping_add(1);
        }
    }

    /// Length checks of a complete packetized reply (reassembled or single): the
    /// length the outstanding request implies, and the command's layout (0x07 whole
    /// registers, 0x09 whole address/value pairs, events 4 + 4n). The last packet
    /// carries no ID, so this is how a lost packet is caught.
    fn check_packetized(&mut self, command: u8, got: usize) -> Option<DecodeError> {
        let expected = match self.expect {
            Some((c, len)) if c == command => len,
            _ => None,
        };
        let plausible = match command {
            cmd::READ_BLOCK => got.is_multiple_of(2),
            cmd::READ_INDIVIDUAL => got.is_multiple_of(4),
            _ => got >= 4 && (got - 4).is_multiple_of(4), // events: timestamp + 4 per event
        };
        if !plausible || expected.is_some_and(|e| usize::from(e) != got) {
            self.stats.packet_errors = self.stats.packet_errors.wrapping_add(1);
            Some(DecodeError::PacketLength {
                command,
                expected,
                got: got as u16,
            })
        } else {
            None
        }
    }

    fn packet(&mut self, command: u8, pl: u8, chunk: &[u8]) -> Option<Result<Frame, DecodeError>> {
        let more = pl & PL_MORE_PACKETS != 0;
        let id = pl & PL_VALUE_MASK;
        let mut asm = match self.asm.take() {
            Some(asm) => {
                if more && id != asm.next_id {
                    self.stats.packet_errors = self.stats.packet_errors.wrapping_add(1);
                    // This packet may be the start of a new reply: keep it.
                    self.asm = Some(Assembly {
                        command,
                        next_id: (id + 1) & PL_VALUE_MASK,
                        packets: 1,
                        payload: Payload::from_slice(chunk).unwrap_or_default(),
                    });
                    return Some(Err(DecodeError::PacketSequence {
                        command,
                        expected: asm.next_id,
                        got: id,
                    }));
                }
                asm
            }
            None => {
                if !more {
                    // A lone last packet: it may be the tail of a reply whose first
                    // packets were lost, so it gets the same checks as a reassembly.
                    if let Some(err) = self.check_packetized(command, chunk.len()) {
                        return Some(Err(err));
                    }
                    // Events have no length the request implies, but a tail left
                    // after 1-3 lost 63-byte packets is never 4 + 4n bytes: the
                    // layout check above already refuses it.
                    return Some(
                        Payload::from_slice(chunk)
                            .map(|payload| Frame::Data {
                                command,
                                payload,
                                packets: 1,
                            })
                            .map_err(|_| DecodeError::PayloadOverflow { command }),
                    );
                }
                Assembly {
                    command,
                    next_id: id,
                    packets: 0,
                    payload: Payload::new(),
                }
            }
        };
        if asm.payload.extend_from_slice(chunk).is_err() {
            self.stats.packet_errors = self.stats.packet_errors.wrapping_add(1);
            return Some(Err(DecodeError::PayloadOverflow { command }));
        }
        asm.packets = asm.packets.saturating_add(1);
        if more {
            asm.next_id = (id + 1) & PL_VALUE_MASK;
            self.asm = Some(asm);
            None
        } else {
            if let Some(err) = self.check_packetized(command, asm.payload.len()) {
                return Some(Err(err));
            }
            Some(Ok(Frame::Data {
                command,
                payload: asm.payload,
                packets: asm.packets,
            }))
        }
    }
}

/// Decodes a whole byte slice at once (feed + finish), calling `sink` for each result.
pub fn decode_all(input: &[u8], sink: impl FnMut(Result<Frame, DecodeError>)) -> DecoderStats {
    let mut d = Decoder::new();
    let mut sink = sink;
    d.feed(input, &mut sink);
    d.finish(&mut sink);
    d.stats()
}

const _: () = assert!(MAX_PAYLOAD <= u16::MAX as usize);

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;
    use std::vec::Vec;

    fn all(input: &[u8]) -> Vec<Result<Frame, DecodeError>> {
        let mut v = Vec::new();
        decode_all(input, |r| v.push(r));
        v
    }

    fn encode(f: &Frame) -> Vec<u8> {
        let mut b = [0u8; 600];
        let n = f.encode(&mut b).unwrap();
        b[..n].to_vec()
    }

    #[test]
    fn rev_d_temperature_reply() {
        let bytes = [
            0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4E,
        ];
        let r = all(&bytes);
        assert_eq!(r.len(), 1);
        let Ok(Frame::Data {
            command,
            payload,
            packets,
        }) = &r[0]
        else {
            panic!("{r:?}")
        };
        assert_eq!(
            (*command, payload.as_slice(), *packets),
            (0x1B, &bytes[3..9], 1)
        );
    }

    #[test]
    fn ascii_broadcast_and_noise_are_skipped() {
        let good = [
            0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4E,
        ];
        let mut s = b"MST:\tEXT1:----\tEXT2:----\tOS:155\r\n".to_vec();
        s.extend_from_slice(&good);
        s.extend_from_slice(b"MST:\t\r\n");
        let mut d = Decoder::new();
        let mut out = Vec::new();
        d.feed(&s, |r| out.push(r));
        d.finish(|r| out.push(r));
        assert_eq!(out.len(), 1);
        assert!(out[0].is_ok());
        assert_eq!(d.stats().skipped_bytes as usize, s.len() - good.len());
    }

    #[test]
    fn good_frame_inside_corrupt_one_is_found() {
        let good = [
            0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4E,
        ];
        // A 0x03 header claiming 10 bytes, cut short by the good frame.
        let mut s = vec![0xAA, 0x03, 0x0A, 0x97];
        s.extend_from_slice(&good);
        let r = all(&s);
        assert!(
            matches!(r[0], Err(DecodeError::Crc { command: 0x03, .. })),
            "{r:?}"
        );
        assert!(
            r[1..]
                .iter()
                .any(|x| matches!(x, Ok(Frame::Data { command: 0x1B, .. }))),
            "{r:?}"
        );
    }

    #[test]
    fn one_byte_at_a_time() {
        let f = Frame::data(0x1C, &[1, 2, 3, 4]).unwrap();
        let bytes = encode(&f);
        let mut d = Decoder::new();
        let mut out = Vec::new();
        for b in &bytes {
            d.feed(core::slice::from_ref(b), |r| out.push(r));
        }
        assert_eq!(out, vec![Ok(f)]);
    }

    #[test]
    fn multi_packet_reassembly_and_errors() {
        let payload: Vec<u8> = (0..150u8).collect();
        let f = Frame::data(cmd::READ_BLOCK, &payload).unwrap();
        let bytes = encode(&f);
        let got = all(&bytes);
        assert_eq!(
            got,
            vec![Ok(Frame::Data {
                command: 0x07,
                payload: Payload::from_slice(&payload).unwrap(),
                packets: 3
            })]
        );
        // Drop the middle packet (bytes 68..136): never a partial value.
        let mut cut = bytes[..68].to_vec();
        cut.extend_from_slice(&bytes[136..]);
        let got = all(&cut);
        assert!(got.iter().all(|r| r.is_err()), "{got:?}");
        // Even when the remaining length is plausible, the request's length catches it.
        let payload: Vec<u8> = (0..152u8).collect();
        let bytes = encode(&Frame::data(cmd::READ_BLOCK, &payload).unwrap());
        let mut cut = bytes[..68].to_vec();
        cut.extend_from_slice(&bytes[136..]);
        let mut d = Decoder::new();
        d.expect(&crate::request::Request::read_registers_native(0, 76).unwrap());
        let mut got = Vec::new();
        d.feed(&cut, |r| got.push(r));
        assert_eq!(
            got,
            vec![Err(DecodeError::PacketLength {
                command: 7,
                expected: Some(152),
                got: 89
            })]
        );
        // Swap packets 1 and 2.
        let mut swapped = bytes[68..136].to_vec();
        swapped.extend_from_slice(&bytes[..68]);
        swapped.extend_from_slice(&bytes[136..]);
        let got = all(&swapped);
        assert!(got.iter().all(|r| r.is_err()), "{got:?}");
        // Interrupted by another frame.
        let mut inter = bytes[..68].to_vec();
        inter.extend_from_slice(&encode(&Frame::Ack { command: 0x0D }));
        let got = all(&inter);
        assert_eq!(
            got[0],
            Err(DecodeError::IncompletePackets {
                command: 0x07,
                packets: 1
            })
        );
        assert_eq!(got[1], Ok(Frame::Ack { command: 0x0D }));
    }

    #[test]
    fn observed_first_packet_id_0x82_is_accepted() {
        // HARDWARE-NOTES: a 45-register 0x07 read arrived as PL=0x82 then a last packet of 27.
        let payload: Vec<u8> = (0..90u8).collect();
        let mut s = vec![0xAA, 0x07, 0x82];
        s.extend_from_slice(&payload[..63]);
        let c = crc16(&s);
        s.extend_from_slice(&c.to_le_bytes());
        let mut last = vec![0xAA, 0x07, 27];
        last.extend_from_slice(&payload[63..]);
        let c = crc16(&last);
        last.extend_from_slice(&c.to_le_bytes());
        s.extend_from_slice(&last);
        let got = all(&s);
        assert_eq!(got.len(), 1);
        assert!(
            matches!(&got[0], Ok(Frame::Data { packets: 2, payload: p, .. }) if p.as_slice() == payload.as_slice())
        );
    }

    #[test]
    fn valid_single_packet_event_reply_after_noise_is_accepted() {
        // Line noise holding 0xAA and the response command byte, then the real,
        // complete single-packet 0x11 reply (4 + 4n bytes). It must not be dropped
        // as the tail of a lost reply.
        let reply = Frame::data(0x11, &[1, 2, 3, 4, 10, 0, 0, 0x21]).unwrap();
        let mut s = vec![0xAA, 0x11, 0x02, 0x01, 0x02, 0x03, 0x04];
        s.extend(encode(&reply));
        let mut d = Decoder::new();
        d.expect(&crate::request::Request::ReadNewestEvents);
        let mut got = Vec::new();
        d.feed(&s, |r| got.push(r));
        d.clear_expectation();
        assert!(
            got.iter().any(|r| r.is_err()),
            "the noise is reported: {got:?}"
        );
        assert_eq!(got.last(), Some(&Ok(reply)));
    }

    #[test]
    fn lone_event_tail_after_lost_packets_is_refused_by_its_layout() {
        // A 0x12 reply of 20 events: 84 bytes = 63 + 21. With the first packet
        // damaged, the 21-byte tail is not 4 + 4n: refused. With at most 49 events
        // (200 bytes) a tail after 1-3 lost 63-byte packets never is.
        let payload: Vec<u8> = (0..84u8).collect();
        let mut s = vec![0xAA, 0x12, 0x81];
        s.extend_from_slice(&payload[..63]);
        s.extend_from_slice(&[0, 0]); // wrong CRC
        let mut tail = vec![0xAA, 0x12, 21];
        tail.extend_from_slice(&payload[63..]);
        let c = crc16(&tail);
        tail.extend_from_slice(&c.to_le_bytes());
        s.extend_from_slice(&tail);
        let mut d = Decoder::new();
        d.expect(&crate::request::Request::ReadAllEvents);
        let mut got = Vec::new();
        d.feed(&s, |r| got.push(r));
        assert!(got.iter().all(|r| r.is_err()), "{got:?}");
        for lost in 1..=3usize {
            for n in 0..=49usize {
                let len = 4 + 4 * n;
                if len > 63 * lost {
                    assert_ne!((len - 63 * lost) % 4, 0, "n {n} lost {lost}");
                }
            }
        }
    }

    #[test]
    fn counters_wrap_instead_of_panicking() {
        let mut d = Decoder::new();
        d.stats = DecoderStats {
            bytes_in: u32::MAX,
            skipped_bytes: u32::MAX,
            frames: u32::MAX,
            crc_errors: u32::MAX,
            length_errors: u32::MAX,
            truncated: u32::MAX,
            packet_errors: u32::MAX,
        };
        let good = encode(&Frame::Ack { command: 0x0D });
        let mut bad = good.clone();
        bad[3] ^= 0xFF;
        let mut input = b"noise".to_vec();
        input.extend_from_slice(&bad);
        input.extend_from_slice(&good);
        input.extend_from_slice(&[0xAA, 0x03, 0x0A, 1]);
        let mut got = Vec::new();
        d.feed(&input, |r| got.push(r));
        while let Some(r) = d.flush() {
            got.push(r);
        }
        assert!(got.contains(&Ok(Frame::Ack { command: 0x0D })));
        let s = d.stats();
        assert_eq!(s.frames, 0, "wrapped");
        assert!(s.bytes_in < 100 && s.crc_errors < 10 && s.truncated < 10);
    }

    #[test]
    fn truncated_on_flush() {
        let got = all(&[0xAA, 0x03, 0x0A, 1, 2]);
        assert_eq!(
            got[0],
            Err(DecodeError::Truncated {
                command: Some(0x03),
                have: 5
            })
        );
    }
}
