//! The desktop tool as a newcomer meets it, end to end (the built `tinybms`
//! against `sim --pty` and `sim --bridge-pty`): every way it could mislead or
//! hang that a first session found, each with the behaviour it has now. Run
//! with `TINYBMS_BIN=<an older tinybms>` to see them fail there.
//!
//! Every wait is bounded; nothing asserts on timing.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::*;

/// `tinybms apply FILE PORT` (swapped) waited forever reading the port as a
/// profile; now it says the order.
#[test]
fn apply_with_port_and_file_swapped_says_so_instead_of_hanging() {
    let sim = Sim::start(&["--bridge-pty"]);
    let profile = tmp("swapped.txt");
    std::fs::write(&profile, "charger_startup_delay = 21\n").unwrap();
    let o = tinybms_limited(
        &["apply", profile.to_str().unwrap(), &sim.path, "--dry-run"],
        "",
        Duration::from_secs(30),
    )
    .expect("tinybms apply FILE PORT hangs");
    assert_eq!(o.code, 2, "{o}");
    assert!(
        o.stderr.contains("the order is `tinybms apply PORT FILE`"),
        "{o}"
    );
}

/// A plain number is taken in the unit `settings` prints: `3600` for a
/// voltage is 3600 V — refused with the range, and the hint that 3600 raw is
/// 3.6 V. Enumeration names and unit suffixes are accepted.
#[test]
fn a_refused_value_shows_the_range_and_the_raw_hint_and_names_are_accepted() {
    let sim = Sim::start(&["--pty"]);
    let o = tinybms(&["set", &sim.path, "over_voltage_cutoff=3600"]);
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stderr.contains("allowed 1.2 V..4.5 V"), "{o}");
    assert!(
        o.stderr.contains("raw value 3600 (3.6 V)? add --raw"),
        "{o}"
    );
    let o = tinybms(&[
        "set",
        &sim.path,
        "charger_type=CC/CV",
        "over_voltage_cutoff=3700mV",
    ]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("CC/CV (1)"), "{o}");
}

/// `--dry-run` checks what the real run checks (a value out of range showed a
/// diff and exit 0; the real apply was then refused), and a setting twice in
/// a profile is an error (it was taken silently, and miscounted).
#[test]
fn dry_run_checks_ranges_and_a_setting_twice_is_an_error() {
    let sim = Sim::start(&["--pty"]);
    let bad = tmp("out-of-range.txt");
    std::fs::write(&bad, "over_voltage_cutoff = 9999\n").unwrap();
    let o = tinybms(&["apply", &sim.path, bad.to_str().unwrap(), "--dry-run"]);
    assert_eq!(o.code, 1, "{o}");
    assert!(
        o.stderr.contains("outside the range the TinyBMS allows"),
        "{o}"
    );
    let twice = tmp("twice.txt");
    std::fs::write(
        &twice,
        "charger_startup_delay = 21\ncharger_startup_delay = 22\n",
    )
    .unwrap();
    let o = tinybms(&["apply", &sim.path, twice.to_str().unwrap(), "--dry-run"]);
    // A profile's content is no usage error (issue 51): exit 1.
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stderr.contains("given twice (also on line 1)"), "{o}");
    let units = tmp("units.txt");
    std::fs::write(
        &units,
        "over_voltage_cutoff = 3.71 V\ncharger_type = CC/CV\n",
    )
    .unwrap();
    let o = tinybms(&["apply", &sim.path, units.to_str().unwrap(), "--dry-run"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("3710 (3.71 V)"), "{o}");
}

/// Right after `set … → verified`, `settings` through the bridge shows the new
/// value (it showed the old one for ~2 s, so a second apply showed the same
/// diff again); `unchanged` is counted as unchanged, not as verified.
#[test]
fn settings_right_after_a_write_and_unchanged_counted_as_such() {
    let sim = Sim::start(&["--bridge-pty"]);
    let o = tinybms(&["set", &sim.path, "--raw", "charger_startup_delay=23"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("1 setting verified"), "{o}");
    let o = tinybms(&["settings", &sim.path, "--json"]);
    assert_eq!(o.code, 0, "{o}");
    let lines = json_lines(&o.stdout);
    let l = lines
        .iter()
        .find(|l| l["name"] == "charger_startup_delay")
        .unwrap_or_else(|| panic!("{o}"));
    assert_eq!(l["raw"], 23, "{l}");
    let o = tinybms(&["set", &sim.path, "charger_startup_delay=23s"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(
        o.stdout.contains("already held that value (unchanged)"),
        "{o}"
    );
    assert!(!o.stdout.contains("verified\n1 setting verified"), "{o}");
}

/// `settings --save` counts what it saved (it said 38 when 2 were comments),
/// settings are grouped, configuration flags shown by their bits' names.
#[test]
fn settings_are_grouped_and_the_save_count_is_what_was_saved() {
    let sim = Sim::start(&["--pty"]);
    let file = tmp("saved.txt");
    let o = tinybms(&["settings", &sim.path, "--save", file.to_str().unwrap()]);
    assert_eq!(o.code, 0, "{o}");
    for g in [
        "\nBattery\n",
        "\nSafety\n",
        "\nBalancing\n",
        "\nCharger\n",
        "\nPeripherals\n",
    ] {
        assert!(o.stdout.contains(g), "{g}: {o}");
    }
    let text = std::fs::read_to_string(&file).unwrap();
    let saved = text
        .lines()
        .filter(|l| !l.trim_start().starts_with('#') && l.contains('='))
        .count();
    assert!(
        o.stdout.contains(&format!("saved {saved} settings")),
        "{saved}: {o}"
    );
    let flags = o
        .stdout
        .lines()
        .find(|l| l.contains("configuration_flags"))
        .unwrap();
    assert!(
        flags.contains("none (0)") || flags.contains(" + ") || flags.contains("Enable"),
        "{flags}"
    );
}

/// `--json` on settings, stats, events and version; events with the
/// wall-clock time from the BMS's clock.
#[test]
fn json_on_every_listing_and_events_with_wall_clock_time() {
    let sim = Sim::start(&["--bridge-pty"]);
    for cmd in ["settings", "stats", "version", "events"] {
        let o = tinybms(&[cmd, &sim.path, "--json"]);
        assert_eq!(o.code, 0, "{cmd}: {o}");
        let lines = json_lines(&o.stdout);
        assert!(!lines.is_empty() || cmd == "events", "{cmd}: {o}");
    }
    let o = tinybms(&["events", &sim.path, "--json"]);
    for e in json_lines(&o.stdout) {
        assert!(
            e["time"].as_str().is_some_and(|t| t.starts_with("20")),
            "{e}"
        );
    }
    let o = tinybms(&["events", &sim.path]);
    assert_eq!(o.code, 0, "{o}");
    if !o.stdout.contains("no events") {
        let first = o.stdout.lines().next().unwrap();
        assert!(first.starts_with("20") && first.contains("BMS"), "{o}");
    }
}

/// The monitor keeps counting the data's age: a bridge that freezes (no byte
/// for 20 s) is shown as NO DATA (it kept showing `Data age 0.2 s … online`);
/// in direct mode, a BMS that falls silent as OFFLINE.
#[test]
fn the_monitor_shows_no_data_and_offline_when_the_data_stops() {
    let bridge = std::thread::spawn(|| {
        let sim = Sim::start(&["--bridge-pty", "--freeze", "5s+20s"]);
        tinybms(&[
            "monitor",
            &sim.path,
            "--duration",
            "14s",
            "--period",
            "500ms",
        ])
    });
    let sim = Sim::start(&["--pty", "--freeze", "5s+30s"]);
    let o = tinybms(&[
        "monitor",
        &sim.path,
        "--duration",
        "20s",
        "--period",
        "500ms",
    ]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("OFFLINE"), "{o}");
    let o = bridge.join().unwrap();
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("Data age"), "{o}");
    assert!(o.stdout.contains("NO DATA"), "{o}");
}

/// A silent port: something is said at once and while it waits (16.8 s of
/// blank screen before).
#[test]
fn a_silent_port_says_what_it_is_doing_while_it_waits() {
    let sim = Sim::start(&["--pty", "--freeze", "0s+600s"]);
    let o = tinybms(&["monitor", &sim.path, "--timeout", "8s"]);
    assert_eq!(o.code, 3, "{o}");
    assert!(
        o.stderr.starts_with(&format!("connecting to {}", sim.path)),
        "{o}"
    );
    assert!(o.stderr.contains("waiting for the BMS ("), "{o}");
    assert!(o.stderr.contains("nothing answers"), "{o}");
}

/// `tinybms log` prints the bridge's own log lines.
#[test]
fn log_prints_the_bridges_log_lines() {
    let sim = Sim::start(&["--bridge-pty"]);
    let o = tinybms(&["log", &sim.path, "--duration", "12s"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("  info  pack "), "{o}");
}

/// Issue 26, item 6: `record --duration 30s` stopped by Ctrl-C after a few
/// seconds says how long it recorded, on the screen and in the file meant for
/// bug reports — never the 30 s asked.
#[test]
fn a_recording_stopped_early_says_how_long_it_recorded() {
    let sim = Sim::start(&["--bridge-pty"]);
    let file = std::env::temp_dir().join(format!("early-{}.tbms", std::process::id()));
    let (_, shown) = ctrl_c_after(
        &[
            "record",
            &sim.path,
            file.to_str().unwrap(),
            "--duration",
            "30s",
        ],
        Duration::from_secs(6),
    );
    let secs: f64 = shown
        .split("recorded ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|x| x.parse().ok())
        .unwrap_or_else(|| panic!("{shown}"));
    assert!(secs > 0.5 && secs < 12.0, "{shown}");
    assert!(
        shown.contains("stopped by Ctrl-C (30.0 s asked)"),
        "{shown}"
    );
    let text = std::fs::read_to_string(&file).unwrap();
    assert!(
        text.contains(&format!(
            "recorded {secs:.1} s of the 30.0 s asked (stopped by Ctrl-C)"
        )),
        "{text}"
    );
    let _ = std::fs::remove_file(&file);
}

/// Ctrl-C in `monitor --period 200ms` gives the bridge its own period back (it
/// kept streaming every 200 ms); the exit status says it was interrupted.
#[test]
fn ctrl_c_gives_the_bridge_its_stream_period_back() {
    let sim = Sim::start(&["--bridge-pty", "--stream-period", "2s"]);
    // Until it shows data (bounded), then SIGINT.
    let (status, shown) = ctrl_c_after(
        &["monitor", &sim.path, "--period", "200ms", "--plain"],
        Duration::from_secs(6),
    );
    assert!(shown.contains("Data age"), "{shown}");
    assert_eq!(status.code(), Some(130), "{shown}");
    // Now listen to the pty without saying hello (a new session would reset
    // the period by itself): telemetry every 2 s, not every 200 ms.
    let mut port = serialport::new(&sim.path, 115_200)
        .timeout(Duration::from_millis(100))
        .open()
        .unwrap();
    let mut buf = [0u8; 4096];
    let mut text = Vec::new();
    let end = Instant::now() + Duration::from_secs(5);
    while Instant::now() < end {
        if let Ok(n) = port.read(&mut buf) {
            text.extend_from_slice(&buf[..n]);
        }
    }
    let text = String::from_utf8_lossy(&text);
    let telemetry = text.matches("\"type\":\"telemetry\"").count();
    assert!(
        telemetry <= 4,
        "{telemetry} telemetry lines in 5 s: still streaming fast"
    );
}

/// `cargo tinybms` works inside `firmware/` (the README sends people there to
/// flash): the alias runs the host tool for this computer, not the chip.
#[test]
fn cargo_tinybms_works_inside_firmware() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let config = std::fs::read_to_string(root.join("firmware/.cargo/config.toml")).unwrap();
    let alias = config
        .lines()
        .find(|l| l.starts_with("tinybms = "))
        .expect("no tinybms alias in firmware/.cargo/config.toml");
    assert!(
        alias.contains("--manifest-path ../host-tests/tool/Cargo.toml"),
        "{alias}"
    );
    assert!(alias.contains("--target host-tuple"), "{alias}");
    assert!(root.join("firmware/../host-tests/tool/Cargo.toml").exists());
}

/// Issue 26, item 10: `cargo tinybms` at the repository's root is a release
/// build (a debug one printed nothing for minutes), as in `firmware/`; the
/// README's first commands work without the tool on PATH.
#[test]
fn cargo_tinybms_at_the_root_is_a_release_build_and_the_readme_uses_it() {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let config = std::fs::read_to_string(format!("{root}/.cargo/config.toml")).unwrap();
    for alias in ["tinybms", "sim"] {
        let line = config
            .lines()
            .find(|l| l.starts_with(&format!("{alias} = ")))
            .unwrap_or_else(|| panic!("no `{alias}` alias"));
        assert!(line.contains("--release"), "{line}");
    }
    let readme = std::fs::read_to_string(format!("{root}/README.md")).unwrap();
    let bare: Vec<&str> = readme
        .lines()
        .filter(|l| l.starts_with("tinybms "))
        .collect();
    assert!(
        bare.is_empty(),
        "commands that need the tool on PATH: {bare:?}"
    );
}

/// Issue 26, item 12: a port where nothing answers is not declared a USB-UART
/// adapter wired to the BMS: an unflashed (or starting) bridge is named first.
#[test]
fn a_port_where_nothing_answers_names_an_unflashed_bridge() {
    let o = tinybms(&["config", "/dev/ptmx"]);
    assert_ne!(o.code, 0, "{o}");
    assert!(o.stderr.contains("not running this firmware yet"), "{o}");
    assert!(!o.stderr.contains("is a USB-UART adapter wired"), "{o}");
}

/// Runs `tinybms args`, sends it SIGINT (Ctrl-C) after `after`, and waits
/// (bounded) for it to exit: its exit status and what it printed.
fn ctrl_c_after(args: &[&str], after: Duration) -> (std::process::ExitStatus, String) {
    let mut child = Command::new(tinybms_bin())
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = child.stdout.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = out.read_to_string(&mut s);
        s
    });
    std::thread::sleep(after);
    // SAFETY: kill(2) on our own child's pid.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "no exit after Ctrl-C"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    (status, reader.join().unwrap())
}

/// Issue 26, item 7: what the inverter is told is visible for one pack —
/// `sim --bridge-pty` runs the firmware's inverter output on a virtual CAN
/// bus with a simulated inverter, every `telemetry` line carries it, and
/// `monitor` shows it in text, JSON and CSV. (Before: nothing showed the
/// limits for one pack, and the try-out ran no inverter output.)
#[test]
fn the_monitor_shows_what_the_inverter_is_told() {
    let sim = Sim::start(&["--bridge-pty"]);
    let text = tinybms(&["monitor", &sim.path, "--count", "3", "--plain"]);
    assert_eq!(text.code, 0, "{text}");
    assert!(
        text.stdout
            .contains("Inverter victron: CAN running, inverter heard   CVL 56.8 V"),
        "{text}"
    );
    let json = tinybms(&["monitor", &sim.path, "--count", "2", "--json"]);
    assert_eq!(json.code, 0, "{json}");
    let last: serde_json::Value =
        serde_json::from_str(json.stdout.lines().last().unwrap()).unwrap();
    let inv = &last["inverter"];
    assert_eq!(inv["protocol"], "victron", "{last}");
    assert_eq!(inv["can"], "running", "{last}");
    assert_eq!(inv["heard"], true, "{last}");
    assert!(inv["ccl_a"].as_f64().unwrap() > 0.0, "{last}");
    let csv = tmp("monitor-inverter.csv");
    let _ = std::fs::remove_file(&csv);
    let o = tinybms(&[
        "monitor",
        &sim.path,
        "--count",
        "2",
        "--plain",
        "--log",
        csv.to_str().unwrap(),
        "--every",
        "200ms",
    ]);
    assert_eq!(o.code, 0, "{o}");
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let row: Vec<&str> = lines.last().unwrap().split(',').collect();
    let at = |name: &str| row[header.iter().position(|h| *h == name).unwrap()];
    assert_eq!(at("cvl_v"), "56.8", "{text}");
    assert_eq!(at("can_state"), "running", "{text}");
}

/// Issue 26, item 16: in direct mode the tool's own bridge runs with a record
/// the tool chose (streaming off); `tinybms log` printed "config: stream_period
/// = off" and "config saved to flash" as if the owner had changed something.
#[test]
fn direct_mode_log_says_nothing_of_a_configuration_it_set_itself() {
    let sim = Sim::start(&["--pty"]);
    let o = tinybms(&["log", &sim.path, "--duration", "3s"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("BMS hardware"), "{o}");
    for l in o.stdout.lines() {
        assert!(!l.contains("config"), "{l}\n{o}");
    }
}

/// Issue 26, item 16: `config --save FILE` printed the whole table before
/// saying it saved; in the file, the comments after the values did not line
/// up (names of different lengths shifted them).
#[test]
fn config_save_prints_no_table_and_its_comments_line_up() {
    let sim = Sim::start(&["--bridge-pty"]);
    let file = tmp("bridge-config.txt");
    let o = tinybms(&["config", &sim.path, "--save", file.to_str().unwrap()]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("saved "), "{o}");
    assert!(!o.stdout.contains("inverter_protocol"), "the table: {o}");
    assert_eq!(o.stdout.lines().count(), 1, "{o}");
    let text = std::fs::read_to_string(&file).unwrap();
    let columns: Vec<(usize, &str)> = text
        .lines()
        .filter(|l| !l.starts_with('#') && l.contains('='))
        // In characters: `°C` is two bytes, one column.
        .map(|l| (l[..l.find(" # ").unwrap_or(0)].chars().count(), l))
        .collect();
    assert!(columns.len() > 20, "{text}");
    let first = columns[0].0;
    for (c, l) in &columns {
        assert_eq!(*c, first, "`{l}`\n{text}");
        assert_eq!(l.find(" = "), columns[0].1.find(" = "), "`{l}`\n{text}");
    }
}

/// Issue 26, item 16: the `settings` header started at column 0 while its
/// rows are indented under their group: every column was off by two.
#[test]
fn the_settings_header_lines_up_with_its_rows() {
    let sim = Sim::start(&["--pty"]);
    let o = tinybms(&["settings", &sim.path]);
    assert_eq!(o.code, 0, "{o}");
    let header = o
        .stdout
        .lines()
        .find(|l| l.contains("allowed range"))
        .unwrap();
    let row = o
        .stdout
        .lines()
        .find(|l| l.contains("fully_charged_voltage"))
        .unwrap();
    assert_eq!(
        header.find("name"),
        row.find("fully_charged_voltage"),
        "{header}\n{row}"
    );
    assert_eq!(header.find("value"), row.find("3.65 V"), "{header}\n{row}");
    // `raw` is right-aligned over the raw values.
    assert_eq!(
        header.find("raw").map(|i| i + 3),
        row.find("3650").map(|i| i + 4),
        "{header}\n{row}"
    );
}

/// Issue 26, item 16: `stats` printed the JSON keys (`over_heat_count`,
/// `stats_cleared_at_s  1877000`) — a BMS timestamp shown as if a counter.
/// Now words with units, and when the statistics were cleared as a time ago.
#[test]
fn stats_are_in_words_and_the_clearing_is_a_time_ago() {
    let sim = Sim::start(&["--pty"]);
    let o = tinybms(&["stats", &sim.path]);
    assert_eq!(o.code, 0, "{o}");
    for raw in ["_count", "stats_cleared_at_s", "_a ", "_c ", "_km"] {
        assert!(!o.stdout.contains(raw), "{raw}: {o}");
    }
    assert!(o.stdout.contains(" A\n"), "{o}");
    assert!(o.stdout.contains(" °C\n"), "{o}");
    let cleared = o
        .stdout
        .lines()
        .find(|l| l.starts_with("statistics cleared"))
        .unwrap_or_else(|| panic!("{o}"));
    // The simulated BMS cleared them 2,000,000 s before its clock at start:
    // 23 days.
    assert!(cleared.contains(" ago (BMS time "), "{cleared}");
    assert!(cleared.contains("23 d "), "{cleared}");
    // --json keeps the keys.
    let o = tinybms(&["stats", &sim.path, "--json"]);
    assert!(o.stdout.contains("\"stats_cleared_at_s\":"), "{o}");
}

/// Issue 26, item 16: docs/inverters.md replays a CAN log on `vcan0`, which
/// does not exist until it is made: the set-up lines come first.
#[test]
fn the_canplayer_step_sets_up_vcan0_first() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let doc = std::fs::read_to_string(root.join("docs/inverters.md")).unwrap();
    let player = doc.find("canplayer").expect("the canplayer step");
    let mut at = 0;
    for line in [
        "sudo modprobe vcan",
        "sudo ip link add dev vcan0 type vcan",
        "sudo ip link set up vcan0",
    ] {
        let i = doc.find(line).unwrap_or_else(|| panic!("{line}"));
        assert!(i > at && i < player, "{line} before canplayer");
        at = i;
    }
}

/// Issue 26, item 8: the boot lines — the image and its board, the CAN
/// output, the host link's wire, the UART to the BMS — went to the chip's
/// defmt log only, and `tinybms log` keeps the latest 4 lines: it started at
/// "BMS hardware …". Now the host link keeps them from boot and gives them
/// to every host after its hello, however late it connects.
#[test]
fn log_shows_the_boot_lines_to_a_host_that_connects_late() {
    let sim = Sim::start(&["--bridge-pty"]);
    // Long enough for many more than four log lines.
    std::thread::sleep(Duration::from_secs(4));
    let o = tinybms(&["log", &sim.path, "--duration", "2s"]);
    assert_eq!(o.code, 0, "{o}");
    let lines: Vec<&str> = o.stdout.lines().collect();
    for (i, start) in [
        "tinybms-firmware ",
        "CAN to the inverter: Victron, 500 kbit/s",
        "host link on ",
        "UART1 115200 8N1 to the BMS",
        "settings profile empty: nothing written",
    ]
    .iter()
    .enumerate()
    {
        let l = lines.get(i).unwrap_or(&"");
        assert!(l.starts_with("at boot     "), "{l}\n{o}");
        assert!(l.contains(&format!("  info  {start}")), "{start}\n{o}");
    }
    assert!(o.stdout.contains("on simulated (sim)"), "{o}");
}

/// Issue 26, item 8: `hello` says where the bridge's configuration store
/// lives (flash size, `nvs` partition); `tinybms version` left it out.
#[test]
fn version_names_where_the_bridge_keeps_its_configuration() {
    let sim = Sim::start(&["--bridge-pty"]);
    let o = tinybms(&["version", &sim.path]);
    assert_eq!(o.code, 0, "{o}");
    let store = o
        .stdout
        .lines()
        .find(|l| l.trim_start().starts_with("store "))
        .unwrap_or_else(|| panic!("{o}"));
    assert!(
        store.ends_with("flash 4096 KiB, nvs partition at 0x9000, 24 KiB (the store needs 8 KiB)"),
        "{store}"
    );
    let o = tinybms(&["version", &sim.path, "--json"]);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).unwrap();
    assert_eq!(v["bridge"]["store"]["partition_offset"], 0x9000, "{o}");
}

/// Issue 26, "a friendly pack name": with `pack_name` set, `monitor`'s
/// header names the pack (with two packs the port was all it said).
#[test]
fn the_monitor_names_the_pack_when_it_has_a_name() {
    let sim = Sim::start(&["--bridge-pty", "--config", "pack_name=Garage east"]);
    let o = tinybms(&["monitor", &sim.path, "--plain", "--count", "1"]);
    assert_eq!(o.code, 0, "{o}");
    let first = o.stdout.lines().next().unwrap_or("");
    assert!(first.contains("“Garage east”"), "{first}\n{o}");
    // Without a name, no name.
    let sim = Sim::start(&["--bridge-pty"]);
    let o = tinybms(&["monitor", &sim.path, "--plain", "--count", "1"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(!o.stdout.lines().next().unwrap_or("").contains('“'), "{o}");
}

/// Issue 26, item 2: `fully_charged_voltage=4.2V` (with the cutoff above it)
/// on a LiFePO4 pack passed `--dry-run` and was written. The tool checks cell
/// voltages against the pack's chemistry — inferred from the cutoff the BMS
/// holds, said on stdout — and so does the bridge; `--chemistry` names
/// another, `--force` passes only that check, never a relation.
#[test]
fn set_checks_cell_voltages_against_the_chemistry() {
    let sim = Sim::start(&["--bridge-pty"]);
    let both = ["over_voltage_cutoff=4.25V", "fully_charged_voltage=4.2V"];
    let with = |extra: &[&str]| {
        let mut a = vec!["set", sim.path.as_str()];
        a.extend_from_slice(&both);
        a.extend_from_slice(extra);
        tinybms(&a)
    };
    let o = with(&["--dry-run"]);
    assert_eq!(o.code, 1, "{o}");
    assert!(
        o.stdout.contains(
            "chemistry: LiFePO4 (taken from the over voltage cutoff the BMS holds, 3.65 V)"
        ),
        "{o}"
    );
    assert!(
        o.stderr
            .contains("fully_charged_voltage = 4.2 V: plainly wrong for a LiFePO4 pack"),
        "{o}"
    );
    // Another chemistry said: checked against it.
    let o = with(&["--dry-run", "--chemistry", "li-ion"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(
        o.stdout
            .contains("chemistry: Li-ion (NMC/NCA) (as --chemistry says)"),
        "{o}"
    );
    let o = with(&["--dry-run", "--chemistry", "lto"]);
    assert_eq!(o.code, 1, "{o}");
    // Forced: written and verified by the bridge.
    let o = with(&["--force", "--yes"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("2 settings verified"), "{o}");
    // Never a relation: an over-voltage cutoff under the under-voltage one.
    let o = tinybms(&[
        "set",
        &sim.path,
        "over_voltage_cutoff=2.4V",
        "--force",
        "--dry-run",
    ]);
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stderr.contains("must stay below"), "{o}");
}
