//! Never in the way: the firmware's MQTT session, run in virtual time beside
//! the closed loop (bridge, simulated BMS, inverter output), cannot change what
//! the bridge sends to the BMS or what the inverter output sends on CAN —
//! whatever the broker does.
//!
//! One thread polls both, as the chip's one executor does: the loop a step,
//! then the session until it waits (a no-op waker; its clock is the loop's).
//! The session's broker is an in-memory one that misbehaves a different way on
//! each connection: refused, never answering, a malformed CONNACK, a refusal
//! in the CONNACK, garbage after it, writes that stall (a full TCP window), a
//! connection that drops, one that trickles a byte at a time, and a well
//! behaved one in between. With and without it, every call the loop makes to
//! the bridge (the recorded trace: time, bytes, actions), every CAN frame and
//! every published snapshot are identical; the session meets every kind of
//! trouble, reconnects after each, never panics, and publishes to the good
//! broker. The figures printed: the poll rate, the CAN intervals, the session's
//! heap high-water mark (on this 64-bit host) and its longest poll.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::{Cell, RefCell};
use std::collections::VecDeque;
use std::future::{poll_fn, Future};
use std::pin::pin;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, AtomicI64, Ordering};
use std::task::{Context, Poll, Waker};
use std::time::{Duration, Instant as WallInstant};

use host_tests::closed_loop::{ClosedLoop, STEP_US};
use host_tests::mqtt::{Shared, SharedFeed};
use host_tests::sim::PackModel;
use tinybms_firmware::config::Config;
use tinybms_firmware::inverter::InverterConfig;
use tinybms_firmware::mqtt::publisher::{Publisher, View};
use tinybms_firmware::mqtt::session::{
    self, Clock, Failure, Feed, NetError, Network, Note, Target,
};
use tinybms_firmware::mqtt::Settings;
use tinybms_firmware::Instant;

// ---- the session's heap, counted while it is polled ----

struct Counting;
static COUNTING: AtomicBool = AtomicBool::new(false);
static LIVE: AtomicI64 = AtomicI64::new(0);
static HIGH: AtomicI64 = AtomicI64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            let now = LIVE.fetch_add(l.size() as i64, Ordering::Relaxed) + l.size() as i64;
            HIGH.fetch_max(now, Ordering::Relaxed);
        }
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        if COUNTING.load(Ordering::Relaxed) {
            LIVE.fetch_sub(l.size() as i64, Ordering::Relaxed);
        }
        unsafe { System.dealloc(p, l) }
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

// ---- virtual time ----

#[derive(Clone, Default)]
struct VClock(Rc<Cell<Instant>>);

impl Clock for VClock {
    fn now(&self) -> Instant {
        self.0.get()
    }
    async fn sleep_until(&self, t: Instant) {
        poll_fn(|_| {
            if self.0.get() >= t {
                Poll::Ready(())
            } else {
                Poll::Pending
            }
        })
        .await
    }
}

/// The feed of host_tests (a copy of the telemetry), with a wait in virtual time.
struct VFeed {
    inner: SharedFeed,
    shared: Shared,
    seen: Cell<u64>,
}

impl Feed for VFeed {
    fn with_view<R>(&mut self, now: Instant, f: impl FnOnce(&View<'_>) -> R) -> R {
        self.seen.set(self.shared.lock().generation);
        self.inner.with_view(now, f)
    }
    fn next_event(&mut self) -> Option<protocol_core::events::Event> {
        self.inner.next_event()
    }
    async fn changed(&mut self) {
        poll_fn(|_| {
            if self.shared.lock().generation != self.seen.get() {
                Poll::Ready(())
            } else {
                Poll::Pending
            }
        })
        .await
    }
}

// ---- the broker ----

#[derive(Debug, Clone, Copy, PartialEq)]
enum Mode {
    /// Behaves (as long as any connection lasts: [`CONNECTION_FOR_US`]).
    Good,
    /// The TCP connection is refused.
    Refused,
    /// The TCP connect never completes.
    ConnectHangs,
    /// Takes every byte, never answers.
    Silent,
    /// A CONNACK whose length is not a length.
    MalformedConnack,
    /// A CONNACK that says "not authorized".
    NotAuthorized,
    /// A good CONNACK, then bytes that are not MQTT.
    Garbage,
    /// Writes stop being taken after this many bytes.
    StallWritesAfter(usize),
    /// The connection breaks after this many bytes from the client.
    DropAfter(usize),
    /// Every byte to the client a virtual second after the last.
    Trickle,
}

const MODES: [Mode; 11] = [
    Mode::Good,
    Mode::Refused,
    Mode::ConnectHangs,
    Mode::Silent,
    Mode::MalformedConnack,
    Mode::NotAuthorized,
    Mode::Garbage,
    Mode::StallWritesAfter(3000),
    Mode::DropAfter(5000),
    Mode::Trickle,
    Mode::Good,
];

#[derive(Default)]
struct Seen {
    connects: usize,
    publishes: usize,
    configs: usize,
    states: usize,
    bytes_in: usize,
}

struct ConnState {
    mode: Mode,
    /// Bytes from the client not yet parsed.
    inbox: Vec<u8>,
    /// Bytes to the client.
    outbox: VecDeque<u8>,
    written: usize,
    broken: bool,
    next_byte_at: Instant,
    opened_at: Instant,
    rng: u64,
}

/// How long any connection lasts before the broker breaks it, µs.
const CONNECTION_FOR_US: Instant = 120_000_000;

struct FakeConn {
    st: Rc<RefCell<ConnState>>,
    seen: Rc<RefCell<Seen>>,
    clock: VClock,
}

#[derive(Debug)]
struct Broken;
impl core::fmt::Display for Broken {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("broken")
    }
}
impl std::error::Error for Broken {}
impl embedded_io_async::Error for Broken {
    fn kind(&self) -> embedded_io_async::ErrorKind {
        embedded_io_async::ErrorKind::ConnectionReset
    }
}
impl embedded_io_async::ErrorType for FakeConn {
    type Error = Broken;
}

/// One MQTT packet off the front of `b`: (type and flags, body), or None.
fn packet(b: &[u8]) -> Option<(u8, Vec<u8>, usize)> {
    let first = *b.first()?;
    let (mut len, mut mult, mut i) = (0usize, 1usize, 1usize);
    loop {
        let x = *b.get(i)?;
        len += usize::from(x & 0x7f) * mult;
        mult *= 128;
        i += 1;
        if x & 0x80 == 0 {
            break;
        }
        if i > 4 {
            return None;
        }
    }
    let body = b.get(i..i + len)?.to_vec();
    Some((first, body, i + len))
}

impl ConnState {
    fn answer(&mut self, seen: &mut Seen) {
        while let Some((first, body, used)) = packet(&self.inbox) {
            self.inbox.drain(..used);
            match first >> 4 {
                1 => {
                    seen.connects += 1;
                    match self.mode {
                        Mode::Silent => {}
                        Mode::MalformedConnack => {
                            self.outbox.extend([0x20, 0xff, 0xff, 0xff, 0xff, 0x7f])
                        }
                        Mode::NotAuthorized => self.outbox.extend([0x20, 3, 0, 0x87, 0]),
                        Mode::Garbage => {
                            self.outbox.extend([0x20, 3, 0, 0, 0]);
                            for _ in 0..4096 {
                                self.rng ^= self.rng << 13;
                                self.rng ^= self.rng >> 7;
                                self.rng ^= self.rng << 17;
                                self.outbox.push_back(self.rng as u8);
                            }
                        }
                        _ => self.outbox.extend([0x20, 3, 0, 0, 0]),
                    }
                }
                3 => {
                    seen.publishes += 1;
                    let tl = usize::from(u16::from_be_bytes([body[0], body[1]]));
                    let topic = String::from_utf8_lossy(&body[2..2 + tl]).into_owned();
                    if topic.ends_with("/config") {
                        seen.configs += 1;
                    }
                    if topic.ends_with("/state") {
                        seen.states += 1;
                    }
                    if (first >> 1) & 3 == 1 {
                        let id = &body[2 + tl..4 + tl];
                        self.outbox.extend([0x40, 2, id[0], id[1]]);
                    }
                }
                8 => self.outbox.extend([0x90, 4, body[0], body[1], 0, 0]),
                12 => self.outbox.extend([0xd0, 0]),
                _ => {}
            }
        }
    }
}

impl embedded_io_async::Read for FakeConn {
    async fn read(&mut self, buf: &mut [u8]) -> Result<usize, Broken> {
        poll_fn(|_| {
            let mut s = self.st.borrow_mut();
            if self.clock.now() >= s.opened_at + CONNECTION_FOR_US {
                s.broken = true;
            }
            if s.broken {
                return Poll::Ready(Err(Broken));
            }
            if s.outbox.is_empty() || buf.is_empty() {
                return Poll::Pending;
            }
            let now = self.clock.now();
            let n = if s.mode == Mode::Trickle {
                if now < s.next_byte_at {
                    return Poll::Pending;
                }
                s.next_byte_at = now + 1_000_000;
                1
            } else {
                buf.len().min(s.outbox.len())
            };
            for b in buf.iter_mut().take(n) {
                *b = s.outbox.pop_front().unwrap_or(0);
            }
            Poll::Ready(Ok(n))
        })
        .await
    }
}

impl embedded_io_async::Write for FakeConn {
    async fn write(&mut self, buf: &[u8]) -> Result<usize, Broken> {
        poll_fn(|_| {
            let mut s = self.st.borrow_mut();
            if s.broken {
                return Poll::Ready(Err(Broken));
            }
            match s.mode {
                Mode::StallWritesAfter(n) if s.written >= n => return Poll::Pending,
                Mode::DropAfter(n) if s.written >= n => {
                    s.broken = true;
                    return Poll::Ready(Err(Broken));
                }
                _ => {}
            }
            // At most one TCP buffer (the chip's 2048 bytes) per write.
            let n = buf.len().min(2048);
            s.inbox.extend_from_slice(&buf[..n]);
            s.written += n;
            let mut seen = self.seen.borrow_mut();
            seen.bytes_in += n;
            s.answer(&mut seen);
            Poll::Ready(Ok(n))
        })
        .await
    }

    async fn flush(&mut self) -> Result<(), Broken> {
        poll_fn(|_| {
            let s = self.st.borrow();
            match s.mode {
                _ if s.broken => Poll::Ready(Err(Broken)),
                Mode::StallWritesAfter(n) if s.written >= n => Poll::Pending,
                _ => Poll::Ready(Ok(())),
            }
        })
        .await
    }
}

struct FakeNet {
    attempt: usize,
    seen: Rc<RefCell<Seen>>,
    clock: VClock,
    modes_used: Vec<Mode>,
}

impl Network for FakeNet {
    type Conn<'a> = FakeConn;

    async fn connect(&mut self, host: &str, port: u16) -> Result<FakeConn, NetError> {
        assert_eq!((host, port), ("broker.test", 1883));
        let mode = MODES[self.attempt % MODES.len()];
        self.attempt += 1;
        self.modes_used.push(mode);
        match mode {
            Mode::Refused => return Err(NetError::Connect),
            Mode::ConnectHangs => poll_fn(|_| Poll::<()>::Pending).await,
            _ => {}
        }
        Ok(FakeConn {
            st: Rc::new(RefCell::new(ConnState {
                mode,
                inbox: Vec::new(),
                outbox: VecDeque::new(),
                written: 0,
                broken: false,
                next_byte_at: 0,
                opened_at: self.clock.now(),
                rng: 0x9e37_79b9_7f4a_7c15 ^ self.attempt as u64,
            })),
            seen: self.seen.clone(),
            clock: self.clock.clone(),
        })
    }
}

// ---- the runs ----

/// What the loop did, to compare.
#[derive(PartialEq)]
struct LoopOutput {
    trace: Vec<u8>,
    sent: Vec<(u64, u16)>,
    limits: Vec<(u64, u16, u16, u16)>,
    published: Vec<u64>,
}

struct SessionOutput {
    notes: Vec<Note>,
    seen: Seen,
    modes_used: Vec<Mode>,
    longest_poll: Duration,
}

const RUN_US: u64 = 90 * 60 * 1_000_000;

fn new_loop() -> ClosedLoop {
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 11, InverterConfig::default(), 40.0);
    l.h.trace = Some(Vec::new());
    l
}

fn output(l: ClosedLoop) -> LoopOutput {
    LoopOutput {
        published: l.h.published.iter().map(|(t, _)| *t).collect(),
        trace: l.h.trace.unwrap_or_default(),
        sent: l.sent_ids,
        limits: l.sent_limits,
    }
}

fn run_alone() -> LoopOutput {
    let mut l = new_loop();
    let mut t = 0;
    while t < RUN_US {
        t += STEP_US;
        l.run_until(t);
    }
    output(l)
}

fn run_beside_the_session() -> (LoopOutput, SessionOutput) {
    let mut l = new_loop();
    let clock = VClock::default();
    let shared = Shared::default();
    let seen = Rc::new(RefCell::new(Seen::default()));
    let mut net = FakeNet {
        attempt: 0,
        seen: seen.clone(),
        clock: clock.clone(),
        modes_used: Vec::new(),
    };
    let mut feed = VFeed {
        inner: SharedFeed::new(shared.clone()),
        shared: shared.clone(),
        seen: Cell::new(0),
    };
    let config = Config {
        publish_period_s: 1,
        ..Default::default()
    };
    let mut target = Target::from_config(&config, "tinybms-test");
    target.host.clear();
    target.host.push_str("broker.test").unwrap();
    target.port = 1883;
    let mut publisher = Publisher::new(Settings::from_config(&config), &bridge());
    let notes = RefCell::new(Vec::new());
    let mut note = |n: Note| notes.borrow_mut().push(n);
    let mut longest_poll = Duration::ZERO;
    {
        let mut session = pin!(session::run(
            &mut net,
            &clock,
            &mut feed,
            &target,
            &mut publisher,
            &mut note,
        ));
        let mut cx = Context::from_waker(Waker::noop());
        let mut t = 0;
        while t < RUN_US {
            t += STEP_US;
            l.run_until(t);
            // What the chip's station task hands the MQTT task: copies.
            clock.0.set(t);
            shared.update(&mut l.h.station, t);
            for _ in 0..8 {
                COUNTING.store(true, Ordering::Relaxed);
                let start = WallInstant::now();
                let p = session.as_mut().poll(&mut cx);
                longest_poll = longest_poll.max(start.elapsed());
                COUNTING.store(false, Ordering::Relaxed);
                assert!(p.is_pending(), "the session ended");
            }
        }
    }
    let modes_used = net.modes_used;
    let seen = std::mem::take(&mut *seen.borrow_mut());
    (
        output(l),
        SessionOutput {
            notes: notes.into_inner(),
            seen,
            modes_used,
            longest_poll,
        },
    )
}

fn intervals(ts: impl Iterator<Item = u64>) -> (u64, u64, usize) {
    let v: Vec<u64> = ts.collect();
    let d: Vec<u64> = v.windows(2).map(|w| w[1] - w[0]).collect();
    (
        d.iter().copied().min().unwrap_or(0),
        d.iter().copied().max().unwrap_or(0),
        v.len(),
    )
}

#[test]
fn a_misbehaving_broker_changes_nothing_the_bridge_or_the_inverter_output_does() {
    let alone = run_alone();
    let (beside, session) = run_beside_the_session();

    // The session met every kind of trouble, more than once, and survived.
    for m in MODES {
        let n = session.modes_used.iter().filter(|x| **x == m).count();
        assert!(
            n >= 2,
            "broker mode {m:?} used {n} times: {:?}",
            session.modes_used
        );
    }
    let failed = |f: Failure| {
        session
            .notes
            .iter()
            .any(|n| matches!(n, Note::Failed(x, _) | Note::Disconnected(x, _) if *x == f))
    };
    assert!(
        failed(Failure::Net(NetError::Connect)),
        "{:?}",
        session.notes
    );
    assert!(failed(Failure::Timeout), "{:?}", session.notes);
    // The CONNACK's "not authorized": a login the broker refused.
    assert!(failed(Failure::Login), "{:?}", session.notes);
    assert!(failed(Failure::Protocol), "{:?}", session.notes);
    assert!(failed(Failure::Connection), "{:?}", session.notes);
    let connected = session
        .notes
        .iter()
        .filter(|n| matches!(n, Note::Connected))
        .count();
    assert!(connected >= 4, "{:?}", session.notes);
    // And published to the good broker.
    assert!(
        session.seen.configs >= 34,
        "configs: {}",
        session.seen.configs
    );
    assert!(session.seen.states >= 60, "states: {}", session.seen.states);

    // The loop did exactly the same with the session beside it.
    let polls = intervals(alone.published.iter().copied());
    let frames = intervals(alone.sent.iter().map(|(t, _)| *t));
    let limits = intervals(alone.limits.iter().map(|(t, ..)| *t));
    println!(
        "{} min virtual; {} snapshots (every {}-{} ms); {} CAN frames, limits every {}-{} ms; \
         trace {} bytes",
        RUN_US / 60_000_000,
        polls.2,
        polls.0 / 1000,
        polls.1 / 1000,
        frames.2,
        limits.0 / 1000,
        limits.1 / 1000,
        alone.trace.len()
    );
    println!(
        "session: {} connections tried, {} up; broker got {} publishes ({} configs, {} states), \
         {} bytes; heap high-water {} bytes (64-bit host); longest poll {:?}",
        session.modes_used.len(),
        connected,
        session.seen.publishes,
        session.seen.configs,
        session.seen.states,
        session.seen.bytes_in,
        HIGH.load(Ordering::Relaxed),
        session.longest_poll
    );
    assert!(polls.2 > 1000 && frames.2 > 1000, "the loop ran");
    assert!(alone.trace == beside.trace, "the bridge's calls differ");
    assert!(alone.sent == beside.sent, "the CAN frames differ");
    assert!(alone.limits == beside.limits, "the limits differ");
    assert!(alone.published == beside.published, "the snapshots differ");
    assert!(alone == beside);
}

/// The bridge the publisher speaks for.
fn bridge() -> tinybms_firmware::identity::Identity {
    tinybms_firmware::identity::Identity::desktop("test", Default::default())
}
