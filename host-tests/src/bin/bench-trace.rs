//! `cargo run -p host-tests --bin bench-trace -- [OUT]`: records the bridge trace
//! the RISC-V cost benchmark replays (a clean 40 s run of the default bridge
//! against the simulated BMS, seed 1; format in `host_tests::trace`). Default
//! output: `host-tests/bench-rv32/trace.bin`. The test `bench_trace_is_current` fails when
//! the checked-in file no longer matches what the bridge does.

use std::process::ExitCode;

use host_tests::trace::{BENCH_TRACE_SEED, BENCH_TRACE_US};
use host_tests::virtual_time::record_clean;

fn main() -> ExitCode {
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "host-tests/bench-rv32/trace.bin".to_string());
    let Some(trace) = record_clean(BENCH_TRACE_SEED, BENCH_TRACE_US) else {
        eprintln!("bench-trace: the run never received a live reply");
        return ExitCode::FAILURE;
    };
    if let Err(e) = std::fs::write(&out, &trace) {
        eprintln!("bench-trace: {out}: {e}");
        return ExitCode::FAILURE;
    }
    println!("{out}: {} bytes", trace.len());
    ExitCode::SUCCESS
}
