//! `cargo run -p host-tests --bin sim -- [options]`: the firmware's bridge logic
//! against the simulated TinyBMS, in virtual time. Prints the log lines the device
//! would print, then a summary: the link figures and the ground-truth checks
//! (every published value compared with what the simulated BMS really sent before
//! faults, every write outcome with its register file, every event logged with
//! the events reported). Exits 1 when a wrong value or a false success occurred.

use std::process::ExitCode;

use host_tests::closed_loop::{
    run_scenario, safety_row, scenario_row, ClosedLoop, SAFETY_HEADER, SAFETY_SCENARIOS, SCENARIOS,
    SCENARIO_HEADER,
};
use host_tests::real_time::{serve_sim_pty, SimOptions};
use host_tests::real_time_station::{serve_bridge_pty, BridgePtyOptions};
use host_tests::sim::{FaultConfig, SimBms, SimConfig};
use host_tests::virtual_time::{Harness, Soak};
use protocol_core::settings::{Setting, SettingId};
use tinybms_firmware::bms::timing::{Timing, BYTE_TIME_US};
use tinybms_firmware::inverter::{InverterConfig, Protocol};
use tinybms_firmware::Command;

mod cli;
use cli::{parse_args, Options};

/// How many seeds [`free_seed`] tries before it draws one.
const SEED_SLOTS: u64 = 64;

/// The lowest seed from 1 that no other running simulator on this machine
/// holds: each holds its seed by a lock on a file (`seed-N.lock` in
/// `$TINYBMS_SIM_LOCKS`, or `tinybms-sim-seeds` in the temporary folder)
/// until it ends, however it ends (the system drops the lock of a killed
/// process). A try-out run again gets the seed, serial, MQTT client id and
/// Home Assistant device of the one before; two at once get two. Where no
/// lock can be taken, one drawn from the clock and the process id.
fn free_seed() -> u64 {
    use std::sync::OnceLock;
    static HELD: OnceLock<std::fs::File> = OnceLock::new();
    let dir = std::env::var_os("TINYBMS_SIM_LOCKS")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("tinybms-sim-seeds"));
    if std::fs::create_dir_all(&dir).is_ok() {
        for seed in 1..=SEED_SLOTS {
            let Ok(f) = std::fs::OpenOptions::new()
                .create(true)
                .truncate(false)
                .write(true)
                .open(dir.join(format!("seed-{seed}.lock")))
            else {
                break;
            };
            if f.try_lock().is_ok() {
                let _ = HELD.set(f);
                return seed;
            }
        }
    }
    os_seed()
}

/// A seed from the clock and the process id (splitmix64 of both): two
/// try-outs started together differ by their pids. At most nine digits, to be
/// typed back as `--seed`; never one [`free_seed`] hands out.
fn os_seed() -> u64 {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    let mut z = nanos ^ (u64::from(std::process::id()) << 32) ^ 0x9E37_79B9_7F4A_7C15;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    SEED_SLOTS + 1 + z % (999_999_999 - SEED_SLOTS)
}

/// Harmless settings the `--write-every` cycle changes, with two values each.
const WRITE_CYCLE: [(SettingId, i32, i32); 4] = [
    (SettingId::BatteryMaximumCycles, 3000, 3001),
    (SettingId::ChargerStartupDelay, 20, 21),
    (SettingId::DischargeOverCurrentTimeout, 5, 6),
    (SettingId::PulsesPerUnit, 1000, 1001),
];

/// Totals over the seeds.
#[derive(Default)]
struct Totals {
    seconds: f64,
    published: u64,
    flagged: u64,
    blocks: u64,
    wrong: u64,
    examples: Vec<String>,
    false_successes: u64,
    false_failures: u64,
    outcomes: std::collections::BTreeMap<&'static str, u64>,
    follow_ups: u64,
    offline: u64,
    longest_gap_us: u64,
    never_ready: u64,
    logged: u64,
    reported_once: u64,
    missing: u64,
    pending: u64,
    duplicated: u64,
    invented: u64,
    history: u64,
    lines: u64,
    warn_lines: u64,
    requests: u64,
    clean_first: u64,
    faults: u64,
    /// The bridge's history in flash: records written, given up, flash
    /// operations (each stalls the clock as on the chip).
    flash_history: (u64, u64, u64),
}

fn run_seed(o: &Options, seed: u64, t: &mut Totals) -> Result<(), String> {
    let config = SimConfig {
        start_asleep: o.asleep,
        sleep_after_us: Some(30_000_000),
        faults: FaultConfig::all(o.fault_rate),
        ..SimConfig::default()
    };
    let sim = SimBms::new(o.pack, config, seed);
    let bridge_config = Timing {
        snapshot_log_period_us: o.snapshot_every_us,
        live_period_us: o.live_period_us,
        ..Timing::default()
    };
    let mut h = Harness::checked(sim, bridge_config);
    h.retain = false;
    h.echo = !o.quiet;
    // The chip's flash with its history, as every image has it: the
    // history's writes go into the BMS poll's gaps, each stalling the clock.
    let mut chip = tinybms_desk::ota::ChipFlash(tinybms_desk::ota::chip_flash());
    let history = tinybms_desk::station::open_history(&mut chip);
    h.station.set_history(0, history, Some(1));
    h.ota = Some(chip);
    h.bridge_mut()
        .submit_profile(&o.profile)
        .map_err(|e| format!("profile does not fit the command queue: {e:?}"))?;
    let mut next_write = o.write_every_us;
    let mut next_forge = o.forge_every_us;
    let mut k = 0usize;
    loop {
        let at = [next_write, next_forge, Some(o.duration_us)]
            .into_iter()
            .flatten()
            .min()
            .unwrap_or(o.duration_us);
        h.run_until(at);
        if at >= o.duration_us {
            break;
        }
        if let (Some(t), Some(every)) = (next_write, o.write_every_us) {
            if t == at {
                let (id, a, b) = WRITE_CYCLE[k % WRITE_CYCLE.len()];
                let value = if (k / WRITE_CYCLE.len()).is_multiple_of(2) {
                    a
                } else {
                    b
                };
                let mut items = heapless::Vec::new();
                let _ = items.push(Setting { id, value });
                // A full queue just skips this change.
                let _ = h.bridge_mut().submit(Command::ApplySettings(
                    items,
                    protocol_core::settings::ChemistryCheck::Inferred,
                ));
                k += 1;
                next_write = Some(t + every);
            }
        }
        if let (Some(t), Some(every)) = (next_forge, o.forge_every_us) {
            if t == at {
                let bytes = plausible_forgery(&h.sim);
                h.sim.forge_next_live_reply(bytes);
                next_forge = Some(t + every);
            }
        }
    }
    let ev = h.event_check();
    let gap = h.longest_gap_us();
    let s: Soak = h.soak.clone().unwrap_or_default();
    t.seconds += h.now as f64 / 1e6;
    t.published += s.published;
    t.flagged += s.flagged;
    t.blocks += s.blocks_checked;
    t.wrong += s.wrong;
    for e in s.wrong_examples {
        if t.examples.len() < 10 {
            t.examples.push(format!("seed {seed}: {e}"));
        }
    }
    t.false_successes += s.false_successes;
    t.false_failures += s.false_failures;
    for (k, v) in s.outcomes {
        *t.outcomes.entry(k).or_default() += v;
    }
    t.follow_ups += s.follow_ups;
    t.offline += s.offline_transitions;
    if s.ready_at.is_none() {
        t.never_ready += 1;
        t.longest_gap_us = t.longest_gap_us.max(h.now);
    } else {
        t.longest_gap_us = t.longest_gap_us.max(gap);
    }
    t.logged += ev.logged;
    t.reported_once += ev.reported_once;
    t.missing += ev.missing;
    t.pending += ev.pending;
    t.duplicated += ev.duplicated;
    t.invented += ev.invented;
    t.history += ev.history;
    t.lines += s.lines;
    t.warn_lines += s.warn_lines;
    let ls = h.bridge().link_stats();
    t.requests += u64::from(ls.requests);
    t.clean_first += u64::from(ls.replies);
    t.faults += h.sim.stats().faults.total();
    let (written, given_up) = h.station.history().counts();
    t.flash_history.0 += u64::from(written);
    t.flash_history.1 += u64::from(given_up);
    t.flash_history.2 += h
        .flash_ops
        .iter()
        .filter(|(_, n)| n.starts_with("history"))
        .count() as u64;
    if o.seeds.0 == o.seeds.1 {
        print_link(&h);
    }
    Ok(())
}

/// A whole live reply (0x03, registers 0-55) built from the simulated BMS's
/// registers now, with the first cell 1 mV higher: CRC-valid and consistent
/// with every check, yet never sent by the BMS.
fn plausible_forgery(sim: &SimBms) -> Vec<u8> {
    use protocol_core::request::Request;
    use protocol_core::response::{RegisterBlock, Response};
    let mut values = heapless::Vec::new();
    for a in 0..56u16 {
        let _ = values.push(sim.register(a));
    }
    let first = values.iter().position(|&v| v != 0).unwrap_or(0);
    if let Some(c) = values.get_mut(first) {
        *c = c.wrapping_add(10);
    }
    let resp = Response::Registers(RegisterBlock { start: 0, values });
    let Ok(req) = Request::read_registers(0, 56) else {
        return Vec::new();
    };
    let Ok(frame) = resp.to_frame(&req) else {
        return Vec::new();
    };
    let mut buf = vec![0u8; frame.encoded_len().unwrap_or(0)];
    match frame.encode(&mut buf) {
        Ok(n) => buf.truncate(n),
        Err(_) => buf.clear(),
    }
    buf
}

fn print_link(h: &Harness) {
    let s = h.bridge().link_stats();
    let secs = h.now as f64 / 1e6;
    let live_reply = 3 + 2 * 56 + 2;
    let live_request = 8;
    println!("--- link ---");
    println!("{}", tinybms_firmware::Report::LinkStats(s));
    println!(
        "bytes on the wire per live snapshot on a clean line: {} request + {} reply = {} ({:.1} ms at 115200 8N1)",
        live_request,
        live_reply,
        live_request + live_reply,
        (live_request + live_reply) as f64 * BYTE_TIME_US as f64 / 1000.0
    );
    if let Some(l) = h.live_latency() {
        println!(
            "snapshot latency (first request byte of the live read -> snapshot published): min {:.2} ms, mean {:.2} ms, max {:.2} ms over {} snapshots",
            l.0 as f64 / 1000.0,
            l.1 as f64 / 1000.0,
            l.2 as f64 / 1000.0,
            l.3
        );
    }
    let per = |n: u64| {
        if n == 0 {
            "never".to_string()
        } else {
            format!("every {:.2} s", secs / n as f64)
        }
    };
    println!(
        "schedule: {:.1} snapshots/s; event-log reads {} ({}), statistics read passes {} ({}; a confirmed read is two)",
        h.live_latencies.len() as f64 / secs.max(1e-9),
        h.event_reads,
        per(h.event_reads),
        h.stats_reads,
        per(h.stats_reads)
    );
    let busy = (h.tx_bytes + h.rx_bytes) as f64 * BYTE_TIME_US as f64;
    println!(
        "bus utilisation: {:.1} % ({} bytes sent, {} received in {secs:.1} s); reading {} registers per request at the end",
        100.0 * busy / h.now.max(1) as f64,
        h.tx_bytes,
        h.rx_bytes,
        h.bridge().piece_registers()
    );
}

fn main() -> ExitCode {
    tinybms_desk::end_quietly_on_a_closed_pipe();
    let o = parse_args();
    if let Some(n) = o.packs.filter(|_| o.mqtt.is_some() || o.bridge_pty) {
        return run_packs_live(&o, n);
    }
    if o.pty || o.bridge_pty || o.mqtt.is_some() {
        return run_realtime(&o);
    }
    if let (Some(protocol), Some(n)) = (o.inverter, o.packs) {
        return run_packs(&o, protocol, n);
    }
    if let Some(points) = o.sweep {
        return run_sweep(&o, points);
    }
    if let Some(protocol) = o.inverter {
        return run_inverter(&o, protocol);
    }
    let mut t = Totals::default();
    for seed in o.seeds.0..=o.seeds.1 {
        if let Err(e) = run_seed(&o, seed, &mut t) {
            eprintln!("sim: {e}");
            return ExitCode::from(2);
        }
    }
    let seeds = o.seeds.1 - o.seeds.0 + 1;
    println!("--- summary ---");
    println!(
        "{seeds} seed(s) x {:.1} h of virtual time at fault rate {} ({:.1} h in all; {} faults injected)",
        o.duration_us as f64 / 3.6e9,
        o.fault_rate,
        t.seconds / 3600.0,
        t.faults
    );
    println!(
        "snapshots published {} ({:.2}/s), flagged {}; blocks checked against the BMS {}",
        t.published,
        t.published as f64 / t.seconds.max(1e-9),
        t.flagged,
        t.blocks
    );
    println!("wrong values published: {}", t.wrong);
    for e in &t.examples {
        println!("  {e}");
    }
    let outcomes: Vec<String> = t.outcomes.iter().map(|(k, v)| format!("{k} {v}")).collect();
    println!(
        "write outcomes: {} (follow-ups {}); false successes {}; reported failed but applied {}",
        if outcomes.is_empty() {
            "none".to_string()
        } else {
            outcomes.join(", ")
        },
        t.follow_ups,
        t.false_successes,
        t.false_failures
    );
    println!("offline transitions: {}", t.offline);
    println!(
        "longest telemetry gap: {:.1} s{}",
        t.longest_gap_us as f64 / 1e6,
        if t.never_ready > 0 {
            format!(
                " ({} seed(s) never completed the initial sync)",
                t.never_ready
            )
        } else {
            String::new()
        }
    );
    println!(
        "events: {} logged after the start-up history ({} in it), {} reported exactly once, {} missing, {} duplicated, {} invented, {} logged in the last minute not reported yet",
        t.logged, t.history, t.reported_once, t.missing, t.duplicated, t.invented, t.pending
    );
    println!(
        "history in flash: {} records written, {} given up, {} flash operations (each stalled the clock as on the chip)",
        t.flash_history.0, t.flash_history.1, t.flash_history.2
    );
    println!(
        "log: {} lines, {} warnings ({:.1} per hour)",
        t.lines,
        t.warn_lines,
        t.warn_lines as f64 / (t.seconds / 3600.0).max(1e-9)
    );
    if t.wrong > 0 || t.false_successes > 0 {
        println!("FAIL: a value or a write success the BMS never sent was reported");
        return ExitCode::from(1);
    }
    ExitCode::SUCCESS
}

/// `--pty` / `--bridge-pty`: real time on a pseudo-terminal (logic in
/// `host_tests::real_time`).
fn run_realtime(o: &Options) -> ExitCode {
    let sim = SimOptions {
        pack: o.pack,
        config: SimConfig {
            start_asleep: o.asleep,
            faults: FaultConfig::all(o.fault_rate),
            ..SimOptions::default().config
        },
        seed: o.seeds.0,
        settings: if o.pty { o.profile.clone() } else { Vec::new() },
    };
    let duration = o
        .duration_given
        .then(|| std::time::Duration::from_micros(o.duration_us));
    let stop = std::sync::atomic::AtomicBool::new(false);
    let mut out = std::io::stdout();
    let result = match sim.build() {
        Err(e) => Err(e),
        Ok(bms) if o.pty => {
            let freeze = o.freeze.map(|(a, f)| {
                (
                    std::time::Duration::from_micros(a),
                    std::time::Duration::from_micros(f),
                )
            });
            serve_sim_pty(bms, duration, freeze, &stop, &mut out).map_err(|e| e.to_string())
        }
        Ok(bms) => {
            let opts = BridgePtyOptions {
                config: o.config.clone(),
                flash: o.flash.as_ref().map(std::path::PathBuf::from),
                boot_button: o.boot_button_us.map(|at| {
                    (
                        std::time::Duration::from_micros(at),
                        std::time::Duration::from_secs(6),
                    )
                }),
                pty: o.bridge_pty,
                no_wifi: o.no_wifi,
                board: o.board.clone(),
                update_port: o.update_port,
                wifi_networks: o.wifi_networks.clone(),
                bms_silent: o.bms_silent.map(|(a, f)| {
                    (
                        std::time::Duration::from_micros(a),
                        std::time::Duration::from_micros(f),
                    )
                }),
                can_log: o.can_log.as_ref().map(std::path::PathBuf::from),
                mqtt: o.mqtt.clone(),
                profile: o.profile.clone(),
                bridge: Timing {
                    snapshot_log_period_us: o.snapshot_every_us,
                    live_period_us: o.live_period_us,
                    ..Timing::default()
                },
                log: !o.quiet,
                freeze: o.freeze.map(|(a, f)| {
                    (
                        std::time::Duration::from_micros(a),
                        std::time::Duration::from_micros(f),
                    )
                }),
                bms_fault: o.bms_fault.map(|(a, f)| {
                    (
                        std::time::Duration::from_micros(a),
                        std::time::Duration::from_micros(f),
                    )
                }),
            };
            serve_bridge_pty(bms, &opts, duration, &stop, &mut out).map_err(|e| e.to_string())
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("sim: {e}");
            ExitCode::from(2)
        }
    }
}

/// `--packs N` with `--mqtt HOST:PORT` and/or `--bridge-pty`: the packs in
/// real time, each bridge publishing, pack 1's host link on a pty (logic in
/// `host_tests::packs_mqtt`).
fn run_packs_live(o: &Options, n: usize) -> ExitCode {
    use host_tests::packs_mqtt::{record, PacksOnMqtt};
    let record = match record(&o.config) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("sim: {e}");
            return ExitCode::from(2);
        }
    };
    let config = InverterConfig {
        protocol: o.inverter.unwrap_or(Protocol::Victron),
        ..record.inverter()
    };
    let broker = o.mqtt.as_ref().map(|(h, p)| (h.as_str(), *p));
    let mut packs = match PacksOnMqtt::start(
        n,
        config,
        (broker, o.bridge_pty),
        &record,
        o.seeds.0,
        !o.quiet,
    ) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("sim: {e}");
            return ExitCode::from(2);
        }
    };
    let pty = if o.bridge_pty {
        match host_tests::pty::Pty::open_announced(&mut std::io::stdout()) {
            Ok(p) => Some(p),
            Err(e) => {
                eprintln!("sim: {e}");
                return ExitCode::from(2);
            }
        }
    } else {
        None
    };
    let mut side = pty
        .as_ref()
        .map(host_tests::real_time_station::PtySide::new);
    let duration = o
        .duration_given
        .then(|| std::time::Duration::from_micros(o.duration_us));
    let stop = std::sync::atomic::AtomicBool::new(false);
    let host = side.as_mut().map(|s| s as &mut dyn tinybms_desk::HostSide);
    match packs.run(duration, &stop, host) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("sim: {e}");
            ExitCode::from(2)
        }
    }
}

fn open_log(path: &Option<String>) -> Result<Option<Box<dyn std::io::Write>>, String> {
    match path {
        None => Ok(None),
        Some(p) => std::fs::File::create(p)
            .map(|f| Some(Box::new(std::io::BufWriter::new(f)) as Box<dyn std::io::Write>))
            .map_err(|e| format!("{p}: {e}")),
    }
}

/// The inverter output of the closed loops: `protocol`, the stale policy and
/// stop_by_soc as given, the rest at the defaults.
fn inverter_config(o: &Options, protocol: Protocol) -> InverterConfig {
    let d = InverterConfig::default();
    InverterConfig {
        protocol,
        stale_policy: o.stale_policy.0,
        stale_hold_us: o.stale_policy.1,
        stop_by_soc: o.stop_by_soc.unwrap_or(d.stop_by_soc),
        ..d
    }
}

/// `--sweep`: BMS silences started along each curve, for the dialects and
/// simulated inverters given (or all), with and without the BMS's own
/// switch. Exits 1 if any row broke the rule.
fn run_sweep(o: &Options, points: u32) -> ExitCode {
    use host_tests::harsh::{sweep, sweep_row, Curve, HARSH, SWEEP_HEADER};
    use tinybms_firmware::inverter::dialect::PROTOCOLS;
    let protocols: Vec<Protocol> = match o.inverter_given {
        Some(p) => vec![p],
        None => PROTOCOLS.to_vec(),
    };
    let harsh: Vec<_> = if o.harsh.1 {
        vec![o.harsh.0]
    } else {
        HARSH.to_vec()
    };
    let switches: &[bool] = if o.bms_switch {
        &[true]
    } else {
        &[false, true]
    };
    println!("{SWEEP_HEADER}");
    let mut all_ok = true;
    for p in &protocols {
        for h in &harsh {
            for &sw in switches {
                let w = sweep(*p, h, sw, &Curve::ALL, points, o.seeds.0);
                println!("{}", sweep_row(*p, h, sw, &w));
                for f in &w.failures {
                    println!("  FAIL: {f}");
                }
                all_ok &= w.ok();
            }
        }
    }
    if all_ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    }
}

/// Packs in parallel: one scenario or all of them with `n` packs. Prints each
/// pack's figures; exits 1 if any pack went past its own cutoffs, two bridges
/// spoke, or the inverter was without limits too long.
fn run_packs(o: &Options, protocol: Protocol, n: usize) -> ExitCode {
    use host_tests::multi_pack;
    let config = inverter_config(o, protocol);
    let names: Vec<String> = match &o.scenario {
        None => vec!["full-charge".to_string()],
        Some(s) if s == "all" => multi_pack::SCENARIOS
            .iter()
            .map(|s| s.to_string())
            .collect(),
        Some(s) if multi_pack::SCENARIOS.contains(&s.as_str()) => vec![s.clone()],
        Some(s) => {
            eprintln!(
                "sim: `{s}` is a single-pack scenario; with --packs: {}",
                multi_pack::SCENARIOS.join(", ")
            );
            return ExitCode::from(2);
        }
    };
    let mut can_log = match open_log(&o.can_log) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("sim: {e}");
            return ExitCode::from(2);
        }
    };
    let mut all_ok = true;
    for name in names {
        let start = |l: &mut multi_pack::MultiLoop| {
            l.can_log = can_log.take();
            o.harsh.0.apply(&mut l.model);
        };
        let Some((mut l, end)) = multi_pack::run_scenario(&name, n, config, start) else {
            eprintln!("sim: unknown scenario `{name}`");
            return ExitCode::from(2);
        };
        print!("{}", multi_pack::table(&name, &l, end));
        let problems = multi_pack::problems(&l, config.charge.ceiling_margin_mv);
        for p in &problems {
            println!("  FAIL: {p}");
        }
        all_ok &= problems.is_empty();
        can_log = l.can_log.take();
        if let Some(w) = can_log.as_mut() {
            let _ = w.flush();
        }
    }
    if all_ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    }
}

/// The closed loop: one scenario, all of them, or a plain charge for
/// `--duration`. Prints the figures; exits 1 if a cell went over the ceiling or
/// a CVL was 0 or per-cell-sized.
fn run_inverter(o: &Options, protocol: Protocol) -> ExitCode {
    let config = inverter_config(o, protocol);
    // A 48 V hybrid inverter's protocol: the safety table, with the deep
    // discharge, against the pack's truth.
    let safety = protocol.low_voltage_family() || o.harsh.1 || o.bms_switch;
    let all: &[&str] = if safety {
        &SAFETY_SCENARIOS
    } else {
        &SCENARIOS
    };
    let names: Vec<String> = match &o.scenario {
        Some(s) if s == "all" => all.iter().map(|s| s.to_string()).collect(),
        Some(s) => vec![s.clone()],
        None => vec![String::new()],
    };
    let (can_log, json_log) = match (open_log(&o.can_log), open_log(&o.json)) {
        (Ok(c), Ok(j)) => (c, j),
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("sim: {e}");
            return ExitCode::from(2);
        }
    };
    let mut can_log = can_log;
    let mut json_log = json_log;
    println!(
        "{}",
        if safety {
            SAFETY_HEADER
        } else {
            SCENARIO_HEADER
        }
    );
    let mut all_ok = true;
    for name in names {
        let mut start = |l: &mut ClosedLoop| {
            l.can_log = can_log.take();
            l.json_log = json_log.take();
            l.h.echo = !o.quiet;
            o.harsh.0.apply(&mut l.model);
            l.bms_switch = o.bms_switch;
        };
        let (mut l, end) = if name.is_empty() {
            let mut l = ClosedLoop::new(o.pack, o.seeds.0, config, 100.0);
            start(&mut l);
            l.h.sim.set_soc_percent(20.0);
            l.run_until(o.duration_us);
            (l, o.duration_us)
        } else {
            match run_scenario(&name, config, start) {
                Some(r) => r,
                None => {
                    eprintln!("sim: unknown scenario `{name}`");
                    return ExitCode::from(2);
                }
            }
        };
        let label = if name.is_empty() {
            "charge"
        } else {
            name.as_str()
        };
        let (row, ok) = if safety {
            safety_row(label, &l, end)
        } else {
            scenario_row(label, &l, end, config)
        };
        all_ok &= ok;
        println!("{row}");
        can_log = l.can_log.take();
        json_log = l.json_log.take();
        if let Some(w) = can_log.as_mut() {
            let _ = w.flush();
        }
        if let Some(w) = json_log.as_mut() {
            let _ = w.flush();
        }
    }
    if all_ok {
        ExitCode::SUCCESS
    } else {
        println!(
            "{}",
            if safety {
                "FAIL: a cell or a current past the BMS's cutoff (the BMS would trip), or a CVL outside the cells' cutoffs"
            } else {
                "FAIL: a cell above the ceiling, or a CVL of 0 or per-cell size"
            },
        );
        ExitCode::from(1)
    }
}
