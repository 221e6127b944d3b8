//! How long `tinybms version PORT` takes, start to exit, through a bridge
//! (`sim --bridge-pty`), direct to a TinyBMS (`sim --pty`: a USB-UART
//! adapter) and on a silent port (`sim --pty --freeze`): a benchmark that
//! prints figures, not a test. Needs the release binaries:
//!
//! ```sh
//! cargo build --release -p host-tests --bins
//! cargo run --release -p host-tests --example connect_times [RUNS]
//! ```

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    // target/release/examples/connect_times -> target/release/NAME
    let dir = exe.parent().unwrap().parent().unwrap();
    dir.join(name)
}

/// A running `sim` and the pty it printed.
fn sim(args: &[&str]) -> (Child, String) {
    let mut child = Command::new(bin("sim"))
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("target/release/sim (cargo build --release -p host-tests --bins)");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    (child, line.trim().to_string())
}

fn main() {
    let runs: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(5);
    for (what, args) in [
        ("through a bridge (sim --bridge-pty)", vec!["--bridge-pty"]),
        ("direct to a TinyBMS (sim --pty)", vec!["--pty"]),
        (
            "a silent port (sim --pty --freeze)",
            vec!["--pty", "--freeze", "0s+600s"],
        ),
    ] {
        let (mut child, pty) = sim(&args);
        // The simulated BMS (or bridge) has its first data.
        std::thread::sleep(Duration::from_secs(2));
        let mut times: Vec<f64> = (0..runs)
            .map(|_| {
                let t = Instant::now();
                let o = Command::new(bin("tinybms"))
                    .args(["version", &pty])
                    .output()
                    .unwrap();
                let s = t.elapsed().as_secs_f64();
                if what.contains("silent") {
                    assert_eq!(o.status.code(), Some(3));
                } else {
                    assert!(o.status.success(), "{what}: {o:?}");
                }
                s
            })
            .collect();
        times.sort_by(f64::total_cmp);
        println!(
            "{what:<40} tinybms version: min {:.3} s, median {:.3} s, max {:.3} s ({runs} runs)",
            times[0],
            times[times.len() / 2],
            times[times.len() - 1]
        );
        let _ = child.kill();
        let _ = child.wait();
    }
}
