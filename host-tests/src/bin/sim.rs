//! `cargo run -p host-tests --bin sim -- [options]`: the firmware's bridge logic
//! against the simulated TinyBMS, in virtual time. Prints the log lines the device
//! would print, then a summary with the link figures.

use std::process::ExitCode;

use host_tests::harness::Harness;
use host_tests::profile::{parse_assignment, parse_profile};
use host_tests::sim::{FaultConfig, PackProfile, SimBms, SimConfig};
use tinybms_firmware::config::{Config, BYTE_TIME_US};

const USAGE: &str =
    "usage: sim [--duration 10m] [--fault-rate 0.01] [--profile FILE] [--set NAME=VALUE]...
           [--pack lifepo4-16s|liion-14s] [--seed N] [--asleep] [--snapshot-every 10s] [--quiet]

  --duration D       virtual time to run (e.g. 90s, 10m, 2h; default 60s)
  --fault-rate R     per-byte corruption rate on the BMS's replies (bit flips and
                     dropped bytes at R/2 each) plus R per reply of truncation,
                     duplication, delay and lost requests (default 0)
  --profile FILE     settings profile to apply at start (lines `name = value`)
  --set NAME=VALUE   one setting to apply (repeatable), e.g. over_voltage_cutoff=3650
  --pack P           simulated pack (default lifepo4-16s)
  --seed N           seed of the simulator (default 1)
  --asleep           the BMS starts asleep
  --snapshot-every D log period of the snapshot line (default 10s)
  --quiet            only print the summary";

fn parse_duration(s: &str) -> Result<u64, String> {
    let (num, unit) = s
        .find(|c: char| !c.is_ascii_digit() && c != '.')
        .map(|i| s.split_at(i))
        .unwrap_or((s, "s"));
    let v: f64 = num.parse().map_err(|_| format!("bad duration `{s}`"))?;
    let scale = match unit {
        "us" => 1.0,
        "ms" => 1e3,
        "s" | "" => 1e6,
        "m" | "min" => 60e6,
        "h" => 3600e6,
        _ => return Err(format!("bad duration unit in `{s}`")),
    };
    Ok((v * scale) as u64)
}

struct Options {
    duration_us: u64,
    fault_rate: f64,
    profile: Vec<(protocol_core::settings::SettingId, i32)>,
    pack: PackProfile,
    seed: u64,
    asleep: bool,
    snapshot_every_us: u64,
    quiet: bool,
}

fn parse_args() -> Result<Options, String> {
    let mut o = Options {
        duration_us: 60_000_000,
        fault_rate: 0.0,
        profile: Vec::new(),
        pack: PackProfile::LiFePO4_16S,
        seed: 1,
        asleep: false,
        snapshot_every_us: 10_000_000,
        quiet: false,
    };
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = |name: &str| args.next().ok_or_else(|| format!("{name} needs a value"));
        match a.as_str() {
            "--duration" => o.duration_us = parse_duration(&value("--duration")?)?,
            "--fault-rate" => {
                o.fault_rate = value("--fault-rate")?
                    .parse()
                    .map_err(|_| "bad --fault-rate".to_string())?;
                if !(0.0..=1.0).contains(&o.fault_rate) {
                    return Err("--fault-rate must be within 0..1".into());
                }
            }
            "--profile" => {
                let path = value("--profile")?;
                let text = std::fs::read_to_string(&path).map_err(|e| format!("{path}: {e}"))?;
                o.profile
                    .extend(parse_profile(&text).map_err(|e| format!("{path}: {e}"))?);
            }
            "--set" => o.profile.push(parse_assignment(&value("--set")?)?),
            "--pack" => {
                o.pack = match value("--pack")?.as_str() {
                    "lifepo4-16s" => PackProfile::LiFePO4_16S,
                    "liion-14s" => PackProfile::LiIon_14S,
                    other => return Err(format!("unknown pack `{other}`")),
                }
            }
            "--seed" => {
                o.seed = value("--seed")?
                    .parse()
                    .map_err(|_| "bad --seed".to_string())?
            }
            "--asleep" => o.asleep = true,
            "--snapshot-every" => {
                o.snapshot_every_us = parse_duration(&value("--snapshot-every")?)?
            }
            "--quiet" => o.quiet = true,
            "-h" | "--help" => return Err(String::new()),
            other => return Err(format!("unknown option `{other}`")),
        }
    }
    Ok(o)
}

fn main() -> ExitCode {
    let o = match parse_args() {
        Ok(o) => o,
        Err(e) => {
            if !e.is_empty() {
                eprintln!("sim: {e}");
            }
            eprintln!("{USAGE}");
            return ExitCode::from(2);
        }
    };
    let r = o.fault_rate;
    let faults = FaultConfig {
        drop_byte: r / 2.0,
        bit_flip: r / 2.0,
        truncate: r,
        no_reply: r,
        duplicate: r,
        delay: r,
        delay_us: 150_000,
    };
    let config = SimConfig {
        start_asleep: o.asleep,
        sleep_after_us: Some(30_000_000),
        faults,
        ..SimConfig::default()
    };
    let sim = SimBms::new(o.pack, config, o.seed);
    let bridge_config = Config {
        snapshot_log_period_us: o.snapshot_every_us,
        ..Config::default()
    };
    let mut h = Harness::with_config(sim, bridge_config);
    h.echo = !o.quiet;
    if let Err(e) = h.bridge.submit_profile(&o.profile) {
        eprintln!("sim: profile does not fit the command queue: {e:?}");
        return ExitCode::from(2);
    }
    h.run_until(o.duration_us);

    let s = h.bridge.link_stats();
    let secs = h.now as f64 / 1e6;
    let live_reply = 3 + 2 * 56 + 2;
    let live_request = 8;
    println!("--- summary ---");
    println!(
        "virtual time {secs:.1} s, snapshots published {}",
        h.published.len()
    );
    println!("{}", tinybms_firmware::Report::LinkStats(s));
    println!(
        "bytes on the wire per live snapshot: {} request + {} reply = {} ({:.1} ms at 115200 8N1)",
        live_request,
        live_reply,
        live_request + live_reply,
        (live_request + live_reply) as f64 * BYTE_TIME_US as f64 / 1000.0
    );
    if let Some(l) = h.live_latency() {
        println!(
            "snapshot latency (request start -> snapshot decoded): min {:.2} ms, mean {:.2} ms, max {:.2} ms over {} snapshots",
            l.0 as f64 / 1000.0,
            l.1 as f64 / 1000.0,
            l.2 as f64 / 1000.0,
            l.3
        );
    }
    let busy = (h.tx_bytes + h.rx_bytes) as f64 * BYTE_TIME_US as f64;
    println!(
        "bus utilisation: {:.1} % ({} bytes sent, {} received in {secs:.1} s)",
        100.0 * busy / h.now.max(1) as f64,
        h.tx_bytes,
        h.rx_bytes
    );
    ExitCode::SUCCESS
}
