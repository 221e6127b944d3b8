//! The trace the RISC-V cost benchmark replays (`host-tests/bench-rv32/trace.bin`) is what
//! the bridge does today: regenerate it with
//! `cargo run -p host-tests --bin bench-trace` when the bridge's decisions change.

use host_tests::trace::{calls, find_live_reply, Call, BENCH_TRACE_SEED, BENCH_TRACE_US};
use host_tests::virtual_time::record_clean;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::Bridge;

#[test]
fn bench_trace_is_current() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/bench-rv32/trace.bin");
    let on_disk = std::fs::read(path).expect("host-tests/bench-rv32/trace.bin");
    let fresh = record_clean(BENCH_TRACE_SEED, BENCH_TRACE_US).expect("a live reply");
    assert!(
        on_disk == fresh,
        "host-tests/bench-rv32/trace.bin is stale: run `cargo run -p host-tests --bin bench-trace`"
    );
}

#[test]
fn live_reply_is_found_only_when_crc_valid() {
    let mut reply = vec![0xAA, 0x03, 112];
    reply.extend((0..112u8).map(|i| i.wrapping_mul(7)));
    let crc = protocol_core::crc::crc16(&reply);
    reply.extend_from_slice(&crc.to_le_bytes());
    let mut rx = vec![0x55, 0xAA, 0x03];
    rx.extend_from_slice(&reply);
    assert_eq!(find_live_reply(&rx), Some(&reply[..]));
    let last = rx.len() - 1;
    rx[last] ^= 1;
    assert_eq!(find_live_reply(&rx), None);
}

/// The harness receives the chip's way (the UART writes into `Bridge::rx_buffer`,
/// then `handle_received`); the copying `handle_rx` (the desktop tool's way)
/// must decide exactly the same on the same bytes: every answer of the 40 s
/// trace, every snapshot and report.
#[test]
fn handle_rx_decides_as_the_in_place_receive() {
    let trace = record_clean(BENCH_TRACE_SEED, BENCH_TRACE_US).expect("a live reply");
    let calls = calls(&trace).expect("a well-formed trace");
    let (mut copying, mut in_place) = (
        Bridge::new(Timing::default(), 0),
        Bridge::new(Timing::default(), 0),
    );
    let (mut polls, mut received, mut snapshots, mut reports) = (0, 0, 0, 0);
    for call in &calls {
        match call {
            Call::Poll { now, action } => {
                assert_eq!(&copying.poll(*now), &**action, "handle_rx path at {now}");
                assert_eq!(&in_place.poll(*now), &**action, "in-place path at {now}");
                polls += 1;
            }
            Call::Rx { now, bytes } => {
                copying.handle_rx(*now, bytes);
                // Into the receive space in two pieces, as two UART reads.
                let half = bytes.len() / 2;
                for piece in [&bytes[..half], &bytes[half..]] {
                    let space = in_place.rx_buffer();
                    assert!(space.len() >= piece.len(), "receive space too small");
                    space[..piece.len()].copy_from_slice(piece);
                    in_place.handle_received(*now, piece.len());
                }
                received += bytes.len();
            }
        }
        loop {
            let (a, b) = (copying.next_report(), in_place.next_report());
            assert_eq!(a, b);
            if a.is_none() {
                break;
            }
            reports += 1;
        }
        let (a, b) = (copying.telemetry(), in_place.telemetry());
        assert_eq!(a.snapshot_seq, b.snapshot_seq);
        assert_eq!(a.snapshot, b.snapshot);
        if a.snapshot_seq != snapshots {
            snapshots = a.snapshot_seq;
        }
    }
    assert_eq!(copying.link_stats(), in_place.link_stats());
    assert!(polls > 1000 && received > 10_000 && snapshots > 100 && reports > 0);
}
