//! The recorded bridge trace replayed by the RISC-V cost benchmark (`host-tests/bench-rv32/`).
//!
//! A trace is every call the harness made to [`tinybms_firmware::Bridge`] during a
//! simulated run, with what `poll` answered, so that the benchmark drives the
//! firmware's own logic on the target exactly as the host did, and can check
//! that it decided the same (a replay that diverges is reported, not counted).
//!
//! Layout (integers little-endian):
//!
//! ```text
//! "TBT1"                       magic
//! u8 n, n bytes                one 0x03 live reply as the BMS sent it (AA 03 70 .. CRC)
//! records until 'E':
//!   'P' u64 now  'T' u8 n, n bytes     poll(now) -> Transmit(bytes)
//!   'P' u64 now  'W' u64 t             poll(now) -> WaitUntil(t)
//!   'R' u64 now  u16 n, n bytes        bytes received at now (handle_rx, or
//!                                      rx_buffer + handle_received)
//! 'E'
//! ```

use protocol_core::crc::crc16;
use tinybms_firmware::bridge::Action;

/// Magic bytes at the start of a trace.
pub const MAGIC: &[u8; 4] = b"TBT1";
/// Virtual time of the checked-in benchmark trace, µs.
pub const BENCH_TRACE_US: u64 = 40 * 1_000_000;
/// Seed of the simulator for the checked-in benchmark trace.
pub const BENCH_TRACE_SEED: u64 = 1;
/// A live reply: AA 03 PL=112 (56 registers) + 112 bytes + CRC.
pub const LIVE_REPLY_LEN: usize = 3 + 112 + 2;

/// Appends a `poll` call and its answer.
pub fn record_poll(out: &mut Vec<u8>, now: u64, action: &Action) {
    out.push(b'P');
    out.extend_from_slice(&now.to_le_bytes());
    match action {
        Action::Transmit(bytes) => {
            out.push(b'T');
            out.push(bytes.len() as u8);
            out.extend_from_slice(bytes);
        }
        Action::WaitUntil(t) => {
            out.push(b'W');
            out.extend_from_slice(&t.to_le_bytes());
        }
    }
}

/// Appends a `handle_rx` call.
pub fn record_rx(out: &mut Vec<u8>, now: u64, bytes: &[u8]) {
    out.push(b'R');
    out.extend_from_slice(&now.to_le_bytes());
    out.extend_from_slice(&(bytes.len() as u16).to_le_bytes());
    out.extend_from_slice(bytes);
}

/// The first CRC-valid 56-register 0x03 reply in `rx`.
pub fn find_live_reply(rx: &[u8]) -> Option<&[u8]> {
    rx.windows(LIVE_REPLY_LEN).find(|w| {
        w.starts_with(&[0xAA, 0x03, 112]) && {
            let crc = crc16(&w[..LIVE_REPLY_LEN - 2]);
            w[LIVE_REPLY_LEN - 2..] == crc.to_le_bytes()
        }
    })
}

/// One recorded call, as [`calls`] reads it back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Call {
    /// `poll(now)` and its answer.
    Poll { now: u64, action: Box<Action> },
    /// Bytes received at `now`.
    Rx { now: u64, bytes: Vec<u8> },
}

/// The calls of a whole trace (magic and live reply skipped); `None` when it is
/// malformed.
pub fn calls(trace: &[u8]) -> Option<Vec<Call>> {
    fn take<'a>(b: &'a [u8], i: &mut usize, n: usize) -> Option<&'a [u8]> {
        let s = b.get(*i..*i + n)?;
        *i += n;
        Some(s)
    }
    fn u64_at(b: &[u8], i: &mut usize) -> Option<u64> {
        Some(u64::from_le_bytes(take(b, i, 8)?.try_into().ok()?))
    }
    if trace.get(..4)? != MAGIC {
        return None;
    }
    let mut i = 5 + usize::from(*trace.get(4)?);
    let mut out = Vec::new();
    loop {
        let tag = *trace.get(i)?;
        i += 1;
        match tag {
            b'P' => {
                let now = u64_at(trace, &mut i)?;
                let kind = *take(trace, &mut i, 1)?.first()?;
                let action = match kind {
                    b'T' => {
                        let n = usize::from(*take(trace, &mut i, 1)?.first()?);
                        let bytes = take(trace, &mut i, n)?;
                        Action::Transmit(tinybms_firmware::Transmit::from_slice(bytes).ok()?)
                    }
                    b'W' => Action::WaitUntil(u64_at(trace, &mut i)?),
                    _ => return None,
                };
                out.push(Call::Poll {
                    now,
                    action: Box::new(action),
                });
            }
            b'R' => {
                let now = u64_at(trace, &mut i)?;
                let n = take(trace, &mut i, 2)?;
                let n = usize::from(u16::from_le_bytes([n[0], n[1]]));
                out.push(Call::Rx {
                    now,
                    bytes: take(trace, &mut i, n)?.to_vec(),
                });
            }
            b'E' => return Some(out),
            _ => return None,
        }
    }
}

/// The received bytes of a trace body, concatenated.
pub fn received(body: &[u8]) -> Vec<u8> {
    let mut rx = Vec::new();
    let mut i = 0;
    while let Some(&tag) = body.get(i) {
        i += 9;
        match tag {
            b'P' => match body.get(i) {
                Some(b'T') => i += 2 + usize::from(body.get(i + 1).copied().unwrap_or(0)),
                _ => i += 9,
            },
            b'R' => {
                let n = body
                    .get(i..i + 2)
                    .map(|b| usize::from(u16::from_le_bytes([b[0], b[1]])))
                    .unwrap_or(0);
                rx.extend_from_slice(body.get(i + 2..i + 2 + n).unwrap_or(&[]));
                i += 2 + n;
            }
            _ => break,
        }
    }
    rx
}
