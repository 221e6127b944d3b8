//! End to end: the built `tinybms` binary against `sim --pty` (direct mode: the
//! firmware's bridge runs inside the tool, on a real tty) and `sim
//! --bridge-pty` (through the bridge: the firmware's bridge and host link in the
//! sim process, the tool on the host link's pty).
//!
//! Robust on a busy machine: every wait is generous and bounded, nothing
//! asserts on timing, and every child is killed when its guard drops.

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;
use common::*;

/// A user without access to the port (here: `nobody`, through `setpriv`, on a
/// pty slave that is `crw--w----` root:tty) gets the sentence on how to get it.
/// Needs root to switch users; the CI machine runs as root.
/// Whether the tool can be run as another user here (root, with `setpriv`); says
/// why a test is skipped when not.
fn can_run_as_nobody() -> bool {
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    let ok = root && std::path::Path::new("/usr/bin/setpriv").exists();
    if !ok {
        eprintln!("skipped: needs root and /usr/bin/setpriv to run the tool as another user");
    }
    ok
}

/// `tinybms version PORT` run as `nobody`, from a copy of the binary named `copy`
/// (one `nobody` may execute wherever the target directory is).
fn version_as_nobody(copy: &str, port: &str) -> std::process::Output {
    let bin = tmp(copy);
    std::fs::copy(tinybms_bin(), &bin).unwrap();
    Command::new("/usr/bin/setpriv")
        .args(["--reuid=65534", "--regid=65534", "--clear-groups"])
        .arg(&bin)
        .args(["version", port])
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

#[test]
fn permission_denied_explains_access() {
    if !can_run_as_nobody() {
        return;
    }
    let sim = Sim::start(&["--pty"]);
    let out = version_as_nobody("tinybms-for-nobody", &sim.path);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(
        stderr.contains(&format!("permission denied on `{}`", sim.path)),
        "{stderr}"
    );
    assert!(stderr.contains("dialout"), "{stderr}");
}

/// A port another program holds (opened exclusively, as `serialport` and most
/// serial monitors do) is named as such. The holder is root here, so the tool
/// runs as `nobody` (root ignores the exclusive flag); the pty is made
/// world-writable so that permissions are not what stops it.
#[test]
fn port_held_by_another_program_is_named() {
    if !can_run_as_nobody() {
        return;
    }
    use std::os::unix::fs::PermissionsExt;
    let sim = Sim::start(&["--pty"]);
    std::fs::set_permissions(&sim.path, std::fs::Permissions::from_mode(0o666)).unwrap();
    let holder = serialport::new(&sim.path, 115_200).open().unwrap();
    let out = version_as_nobody("tinybms-for-nobody-2", &sim.path);
    drop(holder);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(
        stderr.contains(&format!("`{}` is in use by another program", sim.path)),
        "{stderr}"
    );
}

#[test]
fn direct_monitor_json_and_screen() {
    let sim = Sim::start(&["--pty"]);
    let o = tinybms(&[
        "monitor", &sim.path, "--json", "--count", "3", "--period", "200ms",
    ]);
    assert_eq!(o.code, 0, "{o}");
    let lines = json_lines(&o.stdout);
    assert_eq!(lines.len(), 3, "{o}");
    for t in &lines {
        assert_eq!(t["type"], "telemetry", "{t}");
        assert_eq!(
            t["cell_voltages_v"].as_array().map(Vec::len),
            Some(16),
            "{t}"
        );
        let v = t["pack_voltage_v"].as_f64().unwrap();
        assert!((40.0..60.0).contains(&v), "{t}");
        assert!(t["soc_percent"].is_number(), "{t}");
    }
    // Piped: plain text, no escape codes.
    let o = tinybms(&["monitor", &sim.path, "--count", "2", "--period", "200ms"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(!o.stdout.contains('\x1b'), "an escape code in a pipe: {o}");
    for part in [
        "Pack",
        "SOC",
        "SOH",
        "Cells (16)",
        "Temperatures",
        "Data age",
        "direct",
    ] {
        assert!(o.stdout.contains(part), "{part}: {o}");
    }
}

#[test]
fn direct_monitor_logs_csv() {
    let sim = Sim::start(&["--pty"]);
    let log = tmp("monitor.csv");
    let _ = std::fs::remove_file(&log);
    let o = tinybms(&[
        "monitor",
        &sim.path,
        "--log",
        log.to_str().unwrap(),
        "--every",
        "200ms",
        "--count",
        "2",
        "--period",
        "100ms",
    ]);
    assert_eq!(o.code, 0, "{o}");
    let text = std::fs::read_to_string(&log).unwrap();
    let rows: Vec<&str> = text.lines().collect();
    assert_eq!(rows.len(), 3, "{text}");
    assert!(rows[0].starts_with("time,seq,"), "{text}");
    assert!(rows[0].ends_with("cell_16_v"), "{text}");
    assert_eq!(
        rows[1].split(',').count(),
        rows[0].split(',').count(),
        "{text}"
    );
    // Appending goes on under the same header; a file with other columns is
    // refused rather than mixed.
    let run = |path: &std::path::Path| {
        tinybms(&[
            "monitor",
            &sim.path,
            "--log",
            path.to_str().unwrap(),
            "--every",
            "200ms",
            "--count",
            "1",
            "--period",
            "100ms",
        ])
    };
    let o = run(&log);
    assert_eq!(o.code, 0, "{o}");
    let text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(text.lines().count(), 4, "{text}");
    assert_eq!(text.lines().filter(|l| l.starts_with("time,")).count(), 1);
    let other = tmp("other.csv");
    std::fs::write(&other, "time,seq,cell_1_v\n").unwrap();
    let o = run(&other);
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stderr.contains("other columns"), "{o}");
    assert_eq!(
        std::fs::read_to_string(&other).unwrap(),
        "time,seq,cell_1_v\n"
    );
}

#[test]
fn direct_settings_dump_save_apply_verify() {
    let sim = Sim::start(&["--pty"]);
    let profile = tmp("settings.txt");
    let o = tinybms(&["settings", &sim.path, "--save", profile.to_str().unwrap()]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("over_voltage_cutoff"), "{o}");
    assert!(o.stdout.contains("allowed range"), "{o}");
    let saved = std::fs::read_to_string(&profile).unwrap();
    let parsed = host_tests::profile::parse_profile(&saved).unwrap();
    assert!(parsed.len() > 20, "{saved}");
    let ov = parsed
        .iter()
        .find(|(id, _)| *id == protocol_core::settings::SettingId::OverVoltageCutoff)
        .unwrap()
        .1;
    // Change one setting by editing the saved profile, apply it.
    let new = if ov == 3700 { 3710 } else { 3700 }; // above fully_charged (3.65 V)
    let edited = saved.replace(
        &format!("over_voltage_cutoff = {ov} "),
        &format!("over_voltage_cutoff = {new} "),
    );
    assert_ne!(edited, saved);
    std::fs::write(&profile, &edited).unwrap();
    let o = tinybms(&["apply", &sim.path, profile.to_str().unwrap(), "--dry-run"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("1 to change"), "{o}");
    assert!(o.stdout.contains("dry run"), "{o}");
    let o = tinybms(&["apply", &sim.path, profile.to_str().unwrap()]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("over_voltage_cutoff"), "{o}");
    assert!(o.stdout.contains("verified"), "{o}");
    // Read back by another run.
    let o = tinybms(&["apply", &sim.path, profile.to_str().unwrap(), "--dry-run"]);
    assert!(o.stdout.contains("0 to change"), "{o}");
}

#[test]
fn direct_refused_value_and_physical_set() {
    let sim = Sim::start(&["--pty"]);
    let o = tinybms(&["set", &sim.path, "over_voltage_cutoff=9.9V"]);
    assert_eq!(o.code, 1, "{o}");
    assert!(
        o.stderr.contains("nothing written")
            && o.stderr
                .contains("outside the range the TinyBMS allows (allowed 1.2 V..4.5 V"),
        "{o}"
    );
    let o = tinybms(&["set", &sim.path, "over_voltage_cutoff=3.72V"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("3.72 V"), "{o}");
    assert!(o.stdout.contains("verified"), "{o}");
    // A setting that restarts the BMS asks first; refused, nothing is sent.
    let o = tinybms_with_input(&["set", &sim.path, "operation_mode=1"], "no\n");
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stdout.contains("operation_mode restarts the BMS"), "{o}");
    assert!(o.stderr.contains("not confirmed: nothing written"), "{o}");
    assert!(!o.stdout.contains("verified"), "{o}");
}

/// Issue 26: a setting that contradicts another is refused before anything
/// is written, by the tool (with `--dry-run` too) and by the bridge behind it.
#[test]
fn a_setting_against_another_is_refused_before_any_write() {
    for mode in [&["--pty"][..], &["--bridge-pty"][..]] {
        let sim = Sim::start(mode);
        let o = tinybms(&["set", &sim.path, "over_voltage_cutoff=2.4V"]);
        assert_eq!(o.code, 1, "{o}");
        assert!(
            o.stderr.contains("nothing written")
                && o.stderr.contains(
                    "under_voltage_cutoff must stay below over_voltage_cutoff (under_voltage_cutoff is 2.5 V)"
                ),
            "{o}"
        );
        let o = tinybms(&["set", &sim.path, "fully_charged_voltage=4.2V", "--dry-run"]);
        assert_eq!(o.code, 1, "{o}");
        assert!(
            o.stderr.contains(
                "fully_charged_voltage may not exceed over_voltage_cutoff (over_voltage_cutoff is 3.65 V)"
            ),
            "{o}"
        );
        assert!(!o.stdout.contains("verified"), "{o}");
        // Both moved together: fine.
        let o = tinybms(&[
            "set",
            &sim.path,
            "under_voltage_cutoff=2.6V",
            "fully_discharged_voltage=2.9V",
        ]);
        assert_eq!(o.code, 0, "{o}");
        assert!(o.stdout.contains("verified"), "{o}");
    }
}

#[test]
fn direct_events_stats_version() {
    let sim = Sim::start(&["--pty"]);
    let o = tinybms(&["version", &sim.path, "--mode", "direct"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("serial_number"), "{o}");
    let o = tinybms(&["events", &sim.path, "--mode", "direct"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.lines().count() >= 1, "{o}");
    let o = tinybms(&["stats", &sim.path, "--mode", "direct"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("full charges"), "{o}");
    // Refused without confirmation, done with it.
    let o = tinybms_with_input(&["clear-events", &sim.path, "--mode", "direct"], "no\n");
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stderr.contains("not confirmed"), "{o}");
    let o = tinybms_with_input(&["clear-events", &sim.path, "--mode", "direct"], "yes\n");
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("cleared"), "{o}");
}

#[test]
fn direct_record_replays() {
    let sim = Sim::start(&["--pty"]);
    record_and_check(&sim.path, "direct.tbms", "direct");
}

/// `tinybms record` for 3 s into a temporary `name`: exits 0, says which mode it
/// used (`mode` in its output), and the capture replays (see [`check_capture`]).
fn record_and_check(port: &str, name: &str, mode: &str) {
    let file = tmp(name);
    let o = tinybms(&["record", port, file.to_str().unwrap(), "--duration", "3s"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains(mode), "{o}");
    check_capture(&file);
}

fn check_capture(file: &std::path::Path) {
    let text = std::fs::read_to_string(file).unwrap();
    let out = host_tests::replay::replay_text(&text).unwrap();
    let lines = json_lines(&out);
    let live = lines
        .iter()
        .filter(|l| l["dir"] == "rx" && l["values"]["cell_count"] == 16)
        .count();
    assert!(live >= 1, "no live block replayed from:\n{text}");
    let summary = lines.last().unwrap();
    assert_eq!(summary["kind"], "summary");
    assert!(summary["frames"].as_u64().unwrap() >= 2, "{summary}");
}

#[test]
fn nothing_answers_explains_the_wiring() {
    // A pty nobody answers on: no hello, and the direct bridge hears nothing.
    let pty = host_tests::pty::Pty::open().unwrap();
    let path = pty.path().to_str().unwrap().to_string();
    let o = tinybms(&["version", &path, "--timeout", "3s"]);
    assert_eq!(o.code, 3, "{o}");
    assert!(o.stderr.contains("nothing answers"), "{o}");
    assert!(o.stderr.contains("TX and RX"), "{o}");
    assert!(o.stderr.contains("ground"), "{o}");
}

#[test]
fn different_device_is_named() {
    // A pty that answers every byte with text that is neither JSON nor frames.
    let pty = host_tests::pty::Pty::open().unwrap();
    let path = pty.path().to_str().unwrap().to_string();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let s = stop.clone();
    let chatter = std::thread::spawn(move || {
        let mut buf = [0u8; 256];
        while !s.load(std::sync::atomic::Ordering::Relaxed) {
            if pty.read(&mut buf, Duration::from_millis(50)).unwrap_or(0) > 0 {
                let _ = pty.write(b"AT OK garbage \x01\x02\x03 ERROR\r\n");
            }
        }
    });
    let o = tinybms(&["version", &path, "--timeout", "4s"]);
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    chatter.join().unwrap();
    assert_eq!(o.code, 3, "{o}");
    assert!(o.stderr.contains("not with TinyBMS frames"), "{o}");
}

/// A fake bridge on a pty: answers every `{"cmd":"hello"}` with `answer`
/// (when given) and pushes `pushed` every 100 ms; returns every byte the tool
/// wrote to it once `tinybms version` has ended.
fn against_fake_bridge(
    answer: Option<&'static str>,
    pushed: Option<&'static str>,
) -> (Out, Vec<u8>) {
    let pty = host_tests::pty::Pty::open().unwrap();
    let path = pty.path().to_str().unwrap().to_string();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let s = stop.clone();
    let fake = std::thread::spawn(move || {
        let (mut heard, mut buf, mut line) = (Vec::new(), [0u8; 256], Vec::new());
        let mut last_push = Instant::now();
        // Bounded: the test stops it, and it never runs past 30 s.
        let end = Instant::now() + Duration::from_secs(30);
        while !s.load(std::sync::atomic::Ordering::Relaxed) && Instant::now() < end {
            let n = pty.read(&mut buf, Duration::from_millis(20)).unwrap_or(0);
            heard.extend_from_slice(&buf[..n]);
            for &b in &buf[..n] {
                if b != b'\n' {
                    line.push(b);
                } else if std::mem::take(&mut line) == br#"{"cmd":"hello"}"# {
                    if let Some(a) = answer {
                        let _ = pty.write(format!("{a}\n").as_bytes());
                    }
                }
            }
            if let Some(p) = pushed {
                if last_push.elapsed() >= Duration::from_millis(100) {
                    let _ = pty.write(format!("{p}\n").as_bytes());
                    last_push = Instant::now();
                }
            }
        }
        heard
    });
    let o = tinybms(&["version", &path, "--timeout", "3s"]);
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    (o, fake.join().unwrap())
}

/// What the tool wrote is hello commands and newlines only: no TinyBMS frame
/// (0xAA ...) and no other command reached the fake bridge.
fn only_hellos(heard: &[u8]) -> bool {
    String::from_utf8_lossy(heard)
        .split('\n')
        .all(|l| l.is_empty() || l == r#"{"cmd":"hello"}"#)
}

#[test]
fn a_bridge_of_another_protocol_is_named_and_left_alone() {
    // A hello this tool's line types do not read (an older firmware's,
    // without `features` and `build`).
    let old = r#"{"type":"hello","protocol":1,"firmware":"0.0.9","chip":"esp32c3","board":"ESP32-C3 SuperMini","record_version":1,"read_only":false,"stream_period_ms":1000,"dropped_lines":0}"#;
    // A complete hello of a protocol this tool does not speak.
    let newer = r#"{"type":"hello","protocol":2,"firmware":"9.0.0","build":"v9.0.0","chip":"esp32c6","board":"ESP32-C6 DevKitC-1","features":["can","host-link"],"record_version":9,"read_only":false,"stream_period_ms":1000,"dropped_lines":0}"#;
    for (hello, protocol, firmware) in [
        (old, "protocol 1", "firmware 0.0.9"),
        (newer, "protocol 2", "firmware 9.0.0"),
    ] {
        let (o, heard) = against_fake_bridge(Some(hello), None);
        assert_eq!(o.code, 3, "{o}");
        assert!(
            o.stderr
                .contains("another version of the host-link protocol"),
            "{o}"
        );
        assert!(
            o.stderr.contains(protocol) && o.stderr.contains(firmware),
            "{o}"
        );
        assert!(
            !heard.is_empty() && only_hellos(&heard),
            "{:?}",
            String::from_utf8_lossy(&heard)
        );
    }
    // A bridge that pushes lines but never answers the hello is not taken
    // for a TinyBMS (no frames sent at it).
    let telemetry = r#"{"type":"telemetry","seq":1,"age_ms":0,"online":false,"ready":false}"#;
    let (o, heard) = against_fake_bridge(None, Some(telemetry));
    assert_eq!(o.code, 3, "{o}");
    assert!(o.stderr.contains("writes JSON lines"), "{o}");
    assert!(only_hellos(&heard), "{:?}", String::from_utf8_lossy(&heard));
}

#[test]
fn bridge_monitor_settings_set_record() {
    let sim = Sim::start(&["--bridge-pty", "--stream-period", "200ms"]);
    let o = tinybms(&["monitor", &sim.path, "--json", "--count", "2"]);
    assert_eq!(o.code, 0, "{o}");
    let lines = json_lines(&o.stdout);
    assert_eq!(lines.len(), 2, "{o}");
    assert!(lines.iter().all(|t| t["type"] == "telemetry"), "{o}");
    let o = tinybms(&["monitor", &sim.path, "--count", "1"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("through the bridge"), "{o}");
    assert!(o.stdout.contains("Cells (16)"), "{o}");
    let o = tinybms(&["settings", &sim.path, "--mode", "bridge"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("over_voltage_cutoff"), "{o}");
    let o = tinybms(&["set", &sim.path, "--raw", "charger_startup_delay=21"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("verified"), "{o}");
    let o = tinybms(&["set", &sim.path, "--raw", "over_voltage_cutoff=9999"]);
    assert_ne!(o.code, 0, "{o}");
    record_and_check(&sim.path, "bridge.tbms", "through the bridge");
}

#[test]
fn read_only_bridge_refuses_writes() {
    let sim = Sim::start(&["--bridge-pty", "--read-only"]);
    let o = tinybms(&["set", &sim.path, "over_voltage_cutoff=3.7"]);
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stderr.contains("the bridge is read-only"), "{o}");
    assert!(o.stderr.contains("BOOT button"), "{o}");
    // Reading still works.
    let o = tinybms(&["version", &sim.path]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("serial_number"), "{o}");
}

#[test]
fn malformed_and_over_long_lines_into_the_bridge() {
    let sim = Sim::start(&["--bridge-pty", "--stream-period", "0"]);
    let mut port = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&sim.path)
        .unwrap();
    let long = format!("{{\"cmd\":\"get\",\"what\":\"{}\"}}\n", "x".repeat(400));
    let input = format!(
        "this is not json\n{{\"cmd\":\"fly\",\"req\":7}}\n{long}{{\"cmd\":\"get\",\"what\":\"version\",\"bogus\":1,\"req\":8}}\n{{\"cmd\":\"hello\",\"req\":9}}\n"
    );
    port.write_all(input.as_bytes()).unwrap();
    let (tx, rx) = mpsc::channel();
    let reader = port.try_clone().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(reader).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let mut errors = Vec::new();
    let end = Instant::now() + Duration::from_secs(60);
    let mut hello = false;
    while Instant::now() < end && !hello {
        let Ok(line) = rx.recv_timeout(Duration::from_secs(1)) else {
            continue;
        };
        let Ok(v) = serde_json::from_str::<Value>(&line) else {
            continue;
        };
        if v["type"] == "error" {
            errors.push(v.clone());
        }
        hello = v["type"] == "hello" && v["req"] == 9;
    }
    assert!(
        hello,
        "the bridge went on answering after the bad lines: {errors:?}"
    );
    let codes: Vec<&str> = errors.iter().filter_map(|e| e["error"].as_str()).collect();
    assert!(codes.contains(&"malformed_json"), "{errors:?}");
    assert!(codes.contains(&"line_too_long"), "{errors:?}");
    assert!(codes.contains(&"unknown_command"), "{errors:?}");
    assert!(codes.contains(&"unknown_field"), "{errors:?}");
    let unknown = errors
        .iter()
        .find(|e| e["error"] == "unknown_command")
        .unwrap();
    assert_eq!(unknown["req"], 7, "{unknown}");
}

/// Issue 26: `tinybms monitor PORT | head -1` (and `--json`, and `log`) ends
/// when the reader is gone and lets go of the port: the next command works.
#[test]
fn a_reader_that_goes_away_ends_the_command_and_frees_the_port() {
    use std::io::BufRead;
    let sim = Sim::start(&["--bridge-pty"]);
    for args in [
        vec!["monitor", sim.path.as_str(), "--plain"],
        vec!["monitor", sim.path.as_str(), "--json"],
        vec!["log", sim.path.as_str()],
    ] {
        let mut child = std::process::Command::new(tinybms_bin())
            .args(&args)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let out = child.stdout.take().unwrap();
        if args[0] == "log" {
            // A log line comes when the bridge has something to say: ask.
            let _ = tinybms(&["config", &sim.path, "charge_current_cap=41"]);
        }
        let mut first = String::new();
        let mut reader = std::io::BufReader::new(out);
        let _ = reader.read_line(&mut first);
        drop(reader); // `head -1` exits: the pipe closes
        if args[0] == "log" {
            let _ = tinybms(&["config", &sim.path, "charge_current_cap=42"]);
        }
        let start = std::time::Instant::now();
        let status = loop {
            if let Some(s) = child.try_wait().unwrap() {
                break Some(s);
            }
            if start.elapsed() > std::time::Duration::from_secs(15) {
                let _ = child.kill();
                let _ = child.wait();
                break None;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        };
        assert!(
            status.is_some(),
            "{args:?} kept running after its reader went"
        );
        let o = tinybms(&["version", &sim.path]);
        assert_eq!(o.code, 0, "{args:?}: the port was not freed: {o}");
    }
}

#[test]
fn doctor_reads_the_bridges_capture_and_says_why() {
    let sim = Sim::start(&["--bridge-pty", "--stream-period", "200ms"]);
    // A few seconds of frames both ways first.
    std::thread::sleep(std::time::Duration::from_secs(4));
    let out = tmp("doctor-capture.log");
    let o = tinybms(&["doctor", &sim.path, "--out", out.to_str().unwrap()]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("inverter: victron on CAN"), "{o}");
    assert!(o.stdout.contains("BMS wire: the wire is healthy"), "{o}");
    assert!(
        o.stdout.contains("CCL ") && o.stdout.contains("DCL "),
        "{o}"
    );
    assert!(
        o.stdout
            .contains("no verdict: the capture shows nothing wrong"),
        "{o}"
    );
    let saved = std::fs::read_to_string(&out).unwrap();
    assert!(saved.lines().count() >= 8, "{saved}");
    assert!(
        saved
            .lines()
            .any(|l| l.ends_with(" T") && l.contains(" can0 351#")),
        "{saved}"
    );
    assert!(
        saved
            .lines()
            .any(|l| l.ends_with(" R") && l.contains(" can0 305#")),
        "{saved}"
    );
    // The saved capture reads the same offline.
    let o = tinybms(&[
        "doctor",
        "--capture",
        out.to_str().unwrap(),
        "--protocol",
        "victron",
    ]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("no verdict"), "{o}");
    // A damaged capture is refused with its line.
    std::fs::write(&out, "(1.0) can0 351#00\n").unwrap();
    let o = tinybms(&["doctor", "--capture", out.to_str().unwrap()]);
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stderr.contains("line 1: no direction flag"), "{o}");
    let o = tinybms(&["doctor"]);
    assert_eq!(o.code, 2, "{o}");
}

#[test]
fn history_lists_the_bridges_own_events_and_says_where_it_is_kept() {
    let sim = Sim::start(&["--bridge-pty"]);
    std::thread::sleep(std::time::Duration::from_secs(3));
    let o = tinybms(&["history", &sim.path]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("event=started"), "{o}");
    // The first listing told the bridge the date: the second shows it.
    std::thread::sleep(std::time::Duration::from_secs(1));
    let o = tinybms(&["history", &sim.path, "--format", "csv"]);
    assert_eq!(o.code, 0, "{o}");
    let mut lines = o.stdout.lines();
    assert_eq!(
        lines.next(),
        Some("id,boot,uptime_s,date,event,what"),
        "{o}"
    );
    assert!(o.stdout.contains(",time_set,date set (usb)"), "{o}");
    let o = tinybms(&["history", &sim.path, "--format", "json"]);
    assert_eq!(o.code, 0, "{o}");
    let rows: Vec<serde_json::Value> = o
        .stdout
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect();
    let started = rows
        .iter()
        .find(|r| r["event"] == "started")
        .expect("started");
    assert!(
        started["what"].as_str().unwrap().contains("reset reason"),
        "{started}"
    );
    assert!(rows.iter().any(|r| r["date"].is_string()), "{o}");
    // No day has passed yet.
    let o = tinybms(&["history", &sim.path, "--days"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("no days in the history yet"), "{o}");
    let o = tinybms(&["history", &sim.path, "--format", "xml"]);
    assert_eq!(o.code, 2, "{o}");
    let o = tinybms(&["version", &sim.path]);
    assert_eq!(o.code, 0, "{o}");
    assert!(
        o.stdout.contains("kept in flash (tinybms history PORT)"),
        "{o}"
    );
}

#[test]
fn doctor_over_the_update_port_reads_the_capture() {
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let addr = format!("127.0.0.1:{port}");
    let _sim = Sim::start(&["--bridge-pty", "--update-port", &addr]);
    std::thread::sleep(std::time::Duration::from_secs(4));
    let out = tmp("doctor-tcp.log");
    let o = tinybms(&["doctor", &addr, "--out", out.to_str().unwrap()]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("the bridge speaking Victron"), "{o}");
    let saved = std::fs::read_to_string(&out).unwrap();
    assert!(saved.lines().any(|l| l.ends_with(" T")), "{saved}");
}
