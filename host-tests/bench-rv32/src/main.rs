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
//!    (`trace.bin`, from `cargo run -p host-tests --bin bench-trace`): every
//!    `poll` and `handle_rx` call the host made, every answer compared (as
//!    `Bridge::step` + `Bridge::transmit_bytes`, what `poll` wraps);
//! 6. `parse`    the same walk over the trace without the bridge (the replay's own
//!    cost, subtracted by the runner).
#![no_std]
#![no_main]

use core::hint::black_box;

use protocol_core::crc::crc16;
use protocol_core::decoder::Decoder;
use protocol_core::request::Request;
use protocol_core::response::Response;
use protocol_core::views::LiveSnapshot;
use tinybms_firmware::bridge::snapshot_line;
use tinybms_firmware::config::Config;
use tinybms_firmware::{Action, Bridge, Step};

static TRACE: &[u8] = include_bytes!("../trace.bin");

/// Repetitions of the single-reply phases.
const REPS: u32 = 200;

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

/// Decoder alone: one frame out of `reply`.
#[inline(never)]
fn decode_frame(decoder: &mut Decoder, reply: &[u8]) -> bool {
    let mut input = reply;
    let mut ok = false;
    loop {
        let n = decoder.push(input);
        input = input.get(n..).unwrap_or(&[]);
        let mut item = None;
        loop {
            decoder.poll_into(&mut item);
            let Some(it) = &item else { break };
            ok |= black_box(it).is_ok();
        }
        if input.is_empty() {
            break;
        }
    }
    ok
}

/// Decoder + typed decode + view.
#[inline(never)]
fn decode_typed(decoder: &mut Decoder, request: &Request, reply: &[u8]) -> Option<LiveSnapshot> {
    let mut input = reply;
    let mut out = None;
    loop {
        let n = decoder.push(input);
        input = input.get(n..).unwrap_or(&[]);
        let mut item = None;
        loop {
            decoder.poll_into(&mut item);
            let Some(it) = &item else { break };
            if let Ok(frame) = it {
                if let Ok(Response::Registers(block)) = &Response::decode(request, frame) {
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

struct Replay {
    snapshots: u64,
    polls: u64,
    rx_calls: u64,
    reports: u64,
    mismatches: u64,
    malformed: bool,
}

#[inline(never)]
fn replay(body: &mut Cursor<'_>) -> Replay {
    let mut r = Replay {
        snapshots: 0,
        polls: 0,
        rx_calls: 0,
        reports: 0,
        mismatches: 0,
        malformed: false,
    };
    let mut bridge = Bridge::new(Config::default(), 0);
    let mut seen_seq = 0u32;
    loop {
        match body.u8() {
            Some(b'P') => {
                let (Some(now), Some(kind)) = (body.u64(), body.u8()) else {
                    r.malformed = true;
                    break;
                };
                let step = bridge.step(now);
                r.polls += 1;
                let same = match kind {
                    b'T' => {
                        let n = body.u8().unwrap_or(0) as usize;
                        let expected = body.take(n).unwrap_or(&[]);
                        step == Step::Transmit && bridge.transmit_bytes() == expected
                    }
                    b'W' => {
                        let t = body.u64().unwrap_or(u64::MAX);
                        step == Step::WaitUntil(t)
                    }
                    _ => {
                        r.malformed = true;
                        break;
                    }
                };
                if !same {
                    r.mismatches += 1;
                }
            }
            Some(b'R') => {
                let Some(now) = body.u64() else {
                    r.malformed = true;
                    break;
                };
                let n = body.u16().unwrap_or(0) as usize;
                let Some(bytes) = body.take(n) else {
                    r.malformed = true;
                    break;
                };
                bridge.handle_rx(now, bytes);
                r.rx_calls += 1;
            }
            Some(b'E') => break,
            _ => {
                r.malformed = true;
                break;
            }
        }
        while let Some(report) = bridge.next_report() {
            black_box(&report);
            r.reports += 1;
        }
        let seq = bridge.telemetry().snapshot_seq;
        if seq != seen_seq {
            seen_seq = seq;
            r.snapshots += 1;
        }
    }
    r
}

/// The replay's own work, measured apart: the same walk over the trace with
/// every record parsed, and no bridge. Subtracted from the `bridge` phase.
#[inline(never)]
fn parse_only(body: &mut Cursor<'_>) -> u64 {
    let mut records = 0u64;
    loop {
        match body.u8() {
            Some(b'P') => {
                let (Some(now), Some(kind)) = (body.u64(), body.u8()) else {
                    break;
                };
                black_box(now);
                match kind {
                    b'T' => {
                        let n = body.u8().unwrap_or(0) as usize;
                        black_box(body.take(n));
                    }
                    b'W' => {
                        black_box(body.u64());
                    }
                    _ => break,
                }
            }
            Some(b'R') => {
                let Some(now) = body.u64() else {
                    break;
                };
                let n = body.u16().unwrap_or(0) as usize;
                black_box((now, body.take(n)));
            }
            _ => break,
        }
        records += 1;
    }
    records
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
    let body_at = c.i;
    bench_mark(5);
    let r = replay(&mut c);
    bench_mark(6);
    let records = parse_only(&mut Cursor {
        b: TRACE,
        i: body_at,
    });
    bench_mark(7);
    put("records", records);

    put("reps", u64::from(REPS));
    put("reply_bytes", reply.len() as u64);
    put("decoded_ok", ok);
    put("snapshots", r.snapshots);
    put("polls", r.polls);
    put("rx_calls", r.rx_calls);
    put("reports", r.reports);
    put("mismatches", r.mismatches);
    put("bridge_bytes", core::mem::size_of::<Bridge>() as u64);
    put("response_bytes", core::mem::size_of::<Response>() as u64);
    put(
        "frame_bytes",
        core::mem::size_of::<protocol_core::Frame>() as u64,
    );
    put(
        "completion_bytes",
        core::mem::size_of::<tinybms_firmware::link::Completion>() as u64,
    );
    put("action_bytes", core::mem::size_of::<Action>() as u64);
    put("step_bytes", core::mem::size_of::<Step>() as u64);
    if r.malformed {
        write(b"bench-rv32: trace.bin: malformed\n");
        exit(2);
    }
    exit(0)
}
