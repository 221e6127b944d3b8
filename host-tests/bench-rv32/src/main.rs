//! On-target cost benchmark (see `run.sh`): runs each layer of the receive path on
//! RV32IMC under `qemu-riscv32` user mode, between calls to [`bench_mark`]. The
//! runner counts the instructions executed between two marks from qemu's
//! execution log; this program prints how many units of work each phase did, so
//! the runner can print instructions per snapshot and per byte.
//!
//! Phases (in order, each preceded by a mark):
//! 1. `crc`      CRC-16 of the 115 checked bytes of a 0x03 live reply, `REPS` times;
//! 2. `decoder`  the streaming decoder on the 117-byte reply (push + poll);
//! 3. `typed`    decoder + `Response::decode` + `LiveSnapshot` view;
//! 4. `summary`  as `typed` + the snapshot's log summary line;
//! 5. `bridge`   the whole `Bridge` replaying the recorded 40 s trace
//!    (`trace.bin`, from `cargo run -p host-tests --bin bench-trace`, parsed
//!    into records before the phase): every `poll` and `handle_rx` call the
//!    host made, every answer compared (as `Bridge::step` +
//!    `Bridge::transmit_bytes`, what `poll` wraps);
//! 6. `walk`     the same walk over the records and the same comparisons
//!    without the bridge (the replay's own cost, subtracted by the runner);
//! 7. (a full window of the packs' shares, not counted);
//! 8. `shares`   one battery step of `inverter::packs::Shares` with eight packs
//!    on a ramp (every step fits the window and both halves), `SHARE_REPS`
//!    times.
#![no_std]
#![no_main]

use core::hint::black_box;

use protocol_core::crc::crc16;
use protocol_core::decoder::Decoder;
use protocol_core::request::Request;
use protocol_core::response::Response;
use protocol_core::views::LiveSnapshot;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::bridge::snapshot_line;
use tinybms_firmware::bridge::Action;
use tinybms_firmware::{Bridge, Step};

static TRACE: &[u8] = include_bytes!("../trace.bin");

/// Repetitions of the single-reply phases.
const REPS: u32 = 200;

/// Battery steps measured for the packs' shares.
const SHARE_REPS: u32 = 64;

/// Phase boundary: the runner splits the instruction count at each call.
#[no_mangle]
#[inline(never)]
pub extern "C" fn bench_mark(phase: u32) {
    black_box(phase);
}

fn syscall(n: usize, a0: usize, a1: usize, a2: usize) -> isize {
    let ret: isize;
    // SAFETY: Linux RISC-V syscall ABI (a7 = number, a0..a2 = arguments);
    // only `write` and `exit` are used, with valid pointers.
    unsafe {
        core::arch::asm!("ecall", in("a7") n, inlateout("a0") a0 as isize => ret,
            in("a1") a1, in("a2") a2, options(nostack));
    }
    ret
}

fn write(bytes: &[u8]) {
    let _ = syscall(64, 1, bytes.as_ptr() as usize, bytes.len());
}

fn exit(code: usize) -> ! {
    let _ = syscall(93, code, 0, 0);
    loop {
        core::hint::spin_loop();
    }
}

/// A line `name value` (no core::fmt).
fn put(name: &str, value: u64) {
    let mut buf = [0u8; 20];
    let mut i = buf.len();
    let mut v = value;
    loop {
        i -= 1;
        buf[i] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 {
            break;
        }
    }
    write(name.as_bytes());
    write(b" ");
    write(&buf[i..]);
    write(b"\n");
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    write(b"bench-rv32: panic\n");
    exit(101)
}

struct Cursor<'a> {
    b: &'a [u8],
    i: usize,
}

impl<'a> Cursor<'a> {
    fn u8(&mut self) -> Option<u8> {
        let v = *self.b.get(self.i)?;
        self.i += 1;
        Some(v)
    }
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let s = self.b.get(self.i..self.i + n)?;
        self.i += n;
        Some(s)
    }
    fn u64(&mut self) -> Option<u64> {
        let s = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(s);
        Some(u64::from_le_bytes(a))
    }
    fn u16(&mut self) -> Option<u16> {
        let s = self.take(2)?;
        Some(u16::from_le_bytes([s[0], s[1]]))
    }
}

/// Decoder alone: one frame out of `reply`, polled as the link polls it
/// (`Decoder::poll_ref`: a data frame is lent where it lies in the buffer).
#[inline(never)]
fn decode_frame(decoder: &mut Decoder, reply: &[u8]) -> bool {
    let mut input = reply;
    let mut ok = false;
    let mut spill = None;
    loop {
        let n = decoder.push(input);
        input = input.get(n..).unwrap_or(&[]);
        while let Some(it) = decoder.poll_ref(&mut spill) {
            ok |= black_box(&it).is_ok();
        }
        if input.is_empty() {
            break;
        }
    }
    ok
}

/// Decoder + typed decode + view, as the link decodes a lent frame.
#[inline(never)]
fn decode_typed(decoder: &mut Decoder, request: &Request, reply: &[u8]) -> Option<LiveSnapshot> {
    let mut input = reply;
    let mut out = None;
    let mut spill = None;
    loop {
        let n = decoder.push(input);
        input = input.get(n..).unwrap_or(&[]);
        while let Some(it) = decoder.poll_ref(&mut spill) {
            if let Ok(frame) = it {
                if let Ok(Response::Registers(block)) = &Response::decode_ref(request, frame) {
                    out = LiveSnapshot::from_registers(block).ok();
                }
            }
        }
        if input.is_empty() {
            break;
        }
    }
    out
}

/// One recorded call to the bridge, parsed out of `trace.bin` before the
/// measured phases (so neither phase pays for decoding the file).
#[derive(Clone, Copy)]
enum Record<'a> {
    /// `Bridge::step(now)` and what it answered on the host.
    Step { now: u64, expect: Expect<'a> },
    /// `Bridge::handle_rx(now, bytes)`.
    Rx { now: u64, bytes: &'a [u8] },
}

#[derive(Clone, Copy)]
enum Expect<'a> {
    Transmit(&'a [u8]),
    WaitUntil(u64),
}

/// Records in the trace at most (a 40 s run has about 3 000).
const MAX_RECORDS: usize = 8192;

/// Parses the trace body; `None` when it is malformed or longer than `MAX_RECORDS`.
fn parse_trace<'a>(body: &mut Cursor<'a>, out: &mut [Option<Record<'a>>]) -> Option<usize> {
    let mut n = 0;
    loop {
        let record = match body.u8()? {
            b'P' => {
                let now = body.u64()?;
                let expect = match body.u8()? {
                    b'T' => {
                        let len = body.u8()? as usize;
                        Expect::Transmit(body.take(len)?)
                    }
                    b'W' => Expect::WaitUntil(body.u64()?),
                    _ => return None,
                };
                Record::Step { now, expect }
            }
            b'R' => {
                let now = body.u64()?;
                let len = body.u16()? as usize;
                Record::Rx {
                    now,
                    bytes: body.take(len)?,
                }
            }
            b'E' => return Some(n),
            _ => return None,
        };
        *out.get_mut(n)? = Some(record);
        n += 1;
    }
}

struct Replay {
    snapshots: u32,
    reports: u32,
    mismatches: u32,
}

/// What the replay drives: the real bridge, or a stand-in that answers what
/// the trace recorded and does nothing else (the replay's own cost).
trait Target<'a> {
    fn step(&mut self, now: u64, expect: &Expect<'a>) -> Step;
    fn transmit_bytes(&self) -> &[u8];
    fn handle_rx(&mut self, now: u64, bytes: &[u8]);
    fn next_report(&mut self) -> bool;
    fn snapshot_seq(&self) -> u32;
}

/// The bridge, and where (modulo 4) the UART driver's copies landed in its
/// receive space, so that the stand-in's copies take as long.
struct Real {
    bridge: Bridge,
    landed: [u8; MAX_PIECES],
    pieces: usize,
}

/// Received pieces in the trace at most.
const MAX_PIECES: usize = 8192;

impl<'a> Target<'a> for Real {
    #[inline(always)]
    fn step(&mut self, now: u64, _: &Expect<'a>) -> Step {
        self.bridge.step(now)
    }
    #[inline(always)]
    fn transmit_bytes(&self) -> &[u8] {
        self.bridge.transmit_bytes()
    }
    /// The chip's way: the UART driver writes the bytes into the bridge's
    /// receive space (that copy is the driver's: the stand-in makes it too).
    /// Feature `handle-rx`: the copying receive (`Bridge::handle_rx`, all a
    /// tree before the in-place receive has); the stand-in then copies nothing.
    #[cfg(feature = "handle-rx")]
    #[inline(always)]
    fn handle_rx(&mut self, now: u64, bytes: &[u8]) {
        self.bridge.handle_rx(now, bytes);
    }
    #[cfg(not(feature = "handle-rx"))]
    #[inline(always)]
    fn handle_rx(&mut self, now: u64, bytes: &[u8]) {
        let mut rest = bytes;
        while !rest.is_empty() {
            let space = self.bridge.rx_buffer();
            if let Some(at) = self.landed.get_mut(self.pieces) {
                *at = (space.as_ptr() as usize % 4) as u8;
                self.pieces += 1;
            }
            let n = space.len().min(rest.len());
            if let (Some(dst), Some(src)) = (space.get_mut(..n), rest.get(..n)) {
                dst.copy_from_slice(src);
            }
            self.bridge.handle_received(now, n);
            rest = rest.get(n..).unwrap_or(&[]);
        }
    }
    #[inline(always)]
    fn next_report(&mut self) -> bool {
        match self.bridge.next_report() {
            Some(report) => {
                black_box(&report);
                true
            }
            None => false,
        }
    }
    #[inline(always)]
    fn snapshot_seq(&self) -> u32 {
        self.bridge.telemetry().snapshot_seq
    }
}

/// Answers the recorded answer (through `black_box`, so nothing is known in
/// advance); no bridge work at all.
#[cfg_attr(feature = "handle-rx", allow(dead_code))]
struct StandIn<'a> {
    sent: &'a [u8],
    landed: &'a [u8],
    pieces: usize,
    space: Aligned,
}

#[repr(align(4))]
#[cfg_attr(feature = "handle-rx", allow(dead_code))]
struct Aligned([u8; protocol_core::frame::MAX_FRAME_LEN + 4]);

impl<'a> Target<'a> for StandIn<'a> {
    #[inline(always)]
    fn step(&mut self, now: u64, expect: &Expect<'a>) -> Step {
        black_box(now);
        match *expect {
            Expect::Transmit(bytes) => {
                self.sent = black_box(bytes);
                black_box(Step::Transmit)
            }
            Expect::WaitUntil(t) => black_box(Step::WaitUntil(t)),
        }
    }
    #[inline(always)]
    fn transmit_bytes(&self) -> &[u8] {
        black_box(self.sent)
    }
    /// The driver's copy, into a buffer as large as the decoder's, at the
    /// alignment the bridge's copy of the same piece had.
    #[cfg(feature = "handle-rx")]
    #[inline(always)]
    fn handle_rx(&mut self, now: u64, bytes: &[u8]) {
        black_box((now, bytes));
    }
    #[cfg(not(feature = "handle-rx"))]
    #[inline(always)]
    fn handle_rx(&mut self, now: u64, bytes: &[u8]) {
        black_box(now);
        let mut rest = bytes;
        while !rest.is_empty() {
            let at = usize::from(self.landed.get(self.pieces).copied().unwrap_or(0));
            self.pieces += 1;
            let space = self.space.0.get_mut(at..).unwrap_or(&mut []);
            let n = space.len().min(rest.len());
            if let (Some(dst), Some(src)) = (space.get_mut(..n), rest.get(..n)) {
                dst.copy_from_slice(src);
            }
            black_box(&mut self.space);
            rest = rest.get(n..).unwrap_or(&[]);
        }
    }
    #[inline(always)]
    fn next_report(&mut self) -> bool {
        black_box(false)
    }
    #[inline(always)]
    fn snapshot_seq(&self) -> u32 {
        black_box(0)
    }
}

/// Replays the records into `target`, comparing every answer.
#[inline(never)]
fn replay<'a, T: Target<'a>>(target: &mut T, records: &[Option<Record<'a>>]) -> Replay {
    let mut r = Replay {
        snapshots: 0,
        reports: 0,
        mismatches: 0,
    };
    let mut seen_seq = 0u32;
    for record in records.iter().flatten() {
        match *record {
            Record::Step { now, ref expect } => {
                let step = target.step(now, expect);
                let same = match *expect {
                    Expect::Transmit(bytes) => {
                        step == Step::Transmit && target.transmit_bytes() == bytes
                    }
                    Expect::WaitUntil(t) => step == Step::WaitUntil(t),
                };
                if !same {
                    r.mismatches += 1;
                }
                // As the chip's bridge task: reports are taken while the line
                // is quiet, before a request goes out.
                if step == Step::Transmit {
                    while target.next_report() {
                        r.reports += 1;
                    }
                }
            }
            Record::Rx { now, bytes } => target.handle_rx(now, bytes),
        }
        let seq = target.snapshot_seq();
        if seq != seen_seq {
            seen_seq = seq;
            r.snapshots += 1;
        }
    }
    while target.next_report() {
        r.reports += 1;
    }
    r
}

#[no_mangle]
pub extern "C" fn _start() -> ! {
    let mut c = Cursor { b: TRACE, i: 0 };
    if c.take(4) != Some(b"TBT1".as_slice()) {
        write(b"bench-rv32: trace.bin: bad magic\n");
        exit(2);
    }
    let n = c.u8().unwrap_or(0) as usize;
    let Some(reply) = c.take(n) else {
        write(b"bench-rv32: trace.bin: truncated\n");
        exit(2);
    };
    let Ok(request) = Request::read_registers(0, 56) else {
        exit(3);
    };
    // The trace is parsed before any phase (not measured).
    let mut records = [None; MAX_RECORDS];
    let Some(n_records) = parse_trace(&mut c, &mut records) else {
        write(b"bench-rv32: trace.bin: malformed or too long\n");
        exit(2);
    };
    let records = records.get(..n_records).unwrap_or(&[]);
    let mut real = Real {
        bridge: Bridge::new(Timing::default(), 0),
        landed: [0; MAX_PIECES],
        pieces: 0,
    };
    let mut decoder = Decoder::new();
    let mut ok = 0u64;

    bench_mark(1);
    for _ in 0..REPS {
        black_box(crc16(black_box(&reply[..reply.len() - 2])));
    }
    bench_mark(2);
    for _ in 0..REPS {
        ok += u64::from(decode_frame(&mut decoder, black_box(reply)));
    }
    bench_mark(3);
    for _ in 0..REPS {
        ok +=
            u64::from(black_box(decode_typed(&mut decoder, &request, black_box(reply))).is_some());
    }
    bench_mark(4);
    for _ in 0..REPS {
        if let Some(s) = decode_typed(&mut decoder, &request, black_box(reply)) {
            black_box(snapshot_line(&s));
            ok += 1;
        }
    }
    bench_mark(5);
    let r = replay(&mut real, black_box(records));
    let mut stand_in = StandIn {
        sent: &[],
        landed: &real.landed,
        pieces: 0,
        space: Aligned([0; protocol_core::frame::MAX_FRAME_LEN + 4]),
    };
    bench_mark(6);
    let walk = replay(&mut stand_in, black_box(records));
    bench_mark(7);
    // The packs' shares (inverter::packs::Shares), one battery step of
    // eight packs on a ramp, so that every step fits the whole window and
    // both halves: a full window first (outside the measured phase).
    let mut shares = tinybms_firmware::inverter::packs::Shares::new();
    let mut sample = [(0u8, 0i16); 8];
    let fill = |t: u32, s: &mut [(u8, i16); 8]| {
        for (k, x) in (0u8..).zip(s.iter_mut()) {
            *x = (k + 1, (i32::from(k + 1) * t as i32 + 50) as i16);
        }
    };
    for t in 0..32 {
        fill(t, &mut sample);
        shares.update(black_box(&sample), false);
    }
    bench_mark(8);
    for t in 32..32 + SHARE_REPS {
        fill(t, &mut sample);
        shares.update(black_box(&sample), false);
    }
    bench_mark(9);
    // Improv Wi-Fi: the WPA2 key of a passphrase, derived a step at a time
    // (improv::psk; 16 rounds of PBKDF2-HMAC-SHA1 per station poll).
    let mut psk_steps = 0u64;
    let key = match tinybms_firmware::improv::psk::PskDerivation::start(
        black_box(b"IEEE"),
        black_box(b"password"),
    ) {
        Ok(tinybms_firmware::improv::psk::Start::Derive(mut d)) => loop {
            psk_steps += 1;
            if let Some(k) = d.step() {
                break k;
            }
        },
        _ => tinybms_firmware::improv::psk::PskHex::new(),
    };
    bench_mark(10);
    put("psk_steps", psk_steps);
    // IEEE 802.11i-2004, H.4: a wrong key means the wrong thing was measured.
    put(
        "psk_ok",
        u64::from(
            key.as_str() == "f42c6fc52df0ebef9ebb4b90b38a5f902e83fe1b135a70e23aed762e9710a12e",
        ),
    );
    put("share_updates", u64::from(SHARE_REPS));
    put("shares_learnt", u64::from(shares.of(8).is_some()));
    let (polls, rx_calls) = records.iter().flatten().fold((0, 0), |(p, x), r| match r {
        Record::Step { .. } => (p + 1, x),
        Record::Rx { .. } => (p, x + 1),
    });
    put("polls", polls);
    put("rx_calls", rx_calls);
    put("walk_mismatches", u64::from(walk.mismatches));
    put("pieces", real.pieces as u64);
    if real.pieces > MAX_PIECES
        || stand_in.pieces != real.pieces
        || real.pieces == 0 && !cfg!(feature = "handle-rx")
    {
        write(b"bench-rv32: received pieces differ or overflow\n");
        exit(2);
    }

    put("reps", u64::from(REPS));
    put("reply_bytes", reply.len() as u64);
    put("decoded_ok", ok);
    put("snapshots", u64::from(r.snapshots));
    put("reports", u64::from(r.reports));
    put("mismatches", u64::from(r.mismatches));
    put("bridge_bytes", core::mem::size_of::<Bridge>() as u64);
    put("response_bytes", core::mem::size_of::<Response>() as u64);
    put(
        "frame_bytes",
        core::mem::size_of::<protocol_core::Frame>() as u64,
    );
    put(
        "completion_bytes",
        core::mem::size_of::<tinybms_firmware::bms::link::Completion>() as u64,
    );
    put("action_bytes", core::mem::size_of::<Action>() as u64);
    put("step_bytes", core::mem::size_of::<Step>() as u64);
    exit(0)
}
