//! The trace the RISC-V cost benchmark replays (`host-tests/bench-rv32/trace.bin`) is what
//! the bridge does today: regenerate it with
//! `cargo run -p host-tests --bin bench-trace` when the bridge's decisions change.

use host_tests::trace::{find_live_reply, record_clean, BENCH_TRACE_SEED, BENCH_TRACE_US};

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
