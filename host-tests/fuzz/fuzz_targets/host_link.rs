//! Fuzz target: the firmware's host link (JSON Lines over USB) on arbitrary bytes
//! from the host, over a synced bridge (the simulated BMS syncs it once).
//!
//! Input layout (see `host_tests::virtual_host_link::fuzz_one`, which holds the body so
//! that `cargo test` runs it too, on stable, from property tests):
//! * byte 0 — chunk size for feeding the host link (0 means byte at a time);
//! * byte 1 — bit 0: read-only link; bit 1: a bridge that is not synced yet;
//! * the rest — the bytes from the host.
//!
//! Invariants checked (beyond "never panics"): every output line is one
//! `\n`-terminated JSON object with a `type`; unless a `set`, `reset` or `clear`
//! was answered `accepted`, nothing reached the bridge; a read-only link accepts
//! none of them.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    host_tests::virtual_host_link::fuzz_one(data);
});
