//! The owner's first hour, second round (issue 42): what a new owner met on
//! the desk with the built `tinybms` against `sim --pty` and `sim
//! --bridge-pty`, each with the behaviour it has now. Every wait is bounded;
//! nothing asserts on timing.

mod common;
use common::*;

/// Item 5: with a USB-UART adapter (direct mode) the tool showed an inverter
/// that does not exist ("Inverter victron: CAN waiting (nothing sent yet),
/// inverter not heard") and `tinybms log` printed `CAN limits:` lines.
#[test]
fn direct_mode_shows_no_inverter_and_logs_no_can_limits() {
    let sim = Sim::start(&["--pty"]);
    let m = tinybms(&["monitor", &sim.path, "--count", "3", "--plain"]);
    assert_eq!(m.code, 0, "{m}");
    assert!(m.stdout.contains("Cells"), "{m}");
    assert!(!m.stdout.contains("Inverter"), "{m}");
    let j = tinybms(&["monitor", &sim.path, "--count", "2", "--json"]);
    assert_eq!(j.code, 0, "{j}");
    assert!(!j.stdout.contains("\"inverter\""), "{j}");
    let o = tinybms(&["log", &sim.path, "--duration", "4s"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("BMS hardware"), "{o}");
    assert!(!o.stdout.contains("CAN"), "{o}");
}

/// Item 7: `tinybms mqtt PORT --host homeassistant.local` was stored without
/// a word, although the bridge cannot resolve `.local` names (mDNS): the
/// likeliest thing a Home Assistant owner types. Now it is refused with what
/// to give instead, and nothing is stored.
#[test]
fn a_local_broker_name_is_refused_with_what_to_give_instead() {
    let sim = Sim::start(&["--bridge-pty"]);
    let o = tinybms(&["mqtt", &sim.path, "--host", "homeassistant.local"]);
    assert_ne!(o.code, 0, "{o}");
    let said = format!("{}{}", o.stdout, o.stderr);
    assert!(said.contains("mDNS"), "{o}");
    assert!(said.contains("IP address"), "{o}");
    let c = tinybms(&["config", &sim.path]);
    assert_eq!(c.code, 0, "{c}");
    let line = c
        .stdout
        .lines()
        .find(|l| l.trim_start().starts_with("mqtt_host"))
        .unwrap_or_else(|| panic!("{c}"));
    assert!(line.contains("(empty)"), "{line}");
    // A name a DNS server answers, and an address, are taken.
    let o = tinybms(&["mqtt", &sim.path, "--host", "broker.example.org"]);
    assert_eq!(o.code, 0, "{o}");
}

/// Item 9: a silent port cost 16.8 s and was first called a TinyBMS ("talking
/// to a TinyBMS on it directly"). Now the hello probe ends as soon as the port
/// stays silent, the tool says it is *trying* a TinyBMS, and a port that
/// answers no request either is named within seconds (bounded here at 10 s;
/// the figures: `cargo run --release -p host-tests --example connect_times`).
#[test]
fn a_silent_port_is_named_within_seconds_and_not_called_a_tinybms() {
    let sim = Sim::start(&["--pty", "--freeze", "0s+600s"]);
    let o = tinybms_limited(
        &["version", &sim.path],
        "",
        std::time::Duration::from_secs(10),
    )
    .expect("tinybms version on a silent port took over 10 s");
    assert_eq!(o.code, 3, "{o}");
    assert!(o.stderr.contains("trying a TinyBMS on it directly"), "{o}");
    assert!(!o.stderr.contains("talking to a TinyBMS"), "{o}");
    assert!(o.stderr.contains("nothing answers"), "{o}");
}

/// Runs `tinybms args` with a stdin that stays open (a user at a prompt),
/// sends it SIGINT after `after`, and waits (bounded) for its exit: the
/// status, stdout and stderr.
fn ctrl_c_at(args: &[&str], after: std::time::Duration) -> (Option<i32>, String, String) {
    use std::process::{Command, Stdio};
    let mut cmd = Command::new(tinybms_bin());
    cmd.args(args).stdin(Stdio::piped());
    let running = Captured::start(&mut cmd);
    std::thread::sleep(after);
    // SAFETY: kill(2) on our own child's pid.
    unsafe { libc::kill(running.child.id() as i32, libc::SIGINT) };
    // (stdin stays open until the exit: a user at a prompt.)
    let (status, out, err) = running
        .wait(std::time::Duration::from_secs(10))
        .expect("no exit within 10 s of Ctrl-C");
    (status.code(), out, err)
}

/// Item 10: Ctrl-C at a `Type yes` question did nothing until Enter, then
/// exited 1; `record` exited 0 on Ctrl-C while `log` and `version` exited
/// 130, as the help says. Now Ctrl-C ends every command with 130, a question
/// at once, and nothing is changed.
#[test]
fn ctrl_c_ends_every_command_alike_and_a_question_at_once() {
    use std::time::Duration;
    let sim = Sim::start(&["--bridge-pty"]);
    let before = tinybms(&[
        "config",
        &sim.path,
        "--save",
        tmp("before-ctrl-c.txt").to_str().unwrap(),
    ]);
    assert_eq!(before.code, 0, "{before}");
    let (code, out, err) = ctrl_c_at(&["config", &sim.path, "--reset"], Duration::from_secs(2));
    assert_eq!(code, Some(130), "{out}\n{err}");
    assert!(out.contains("Type `yes`"), "{out}");
    assert!(err.contains("interrupted"), "{err}");
    let c = tinybms(&["config", &sim.path]);
    assert!(
        c.stdout.contains("0 fields differ"),
        "nothing was reset: {c}"
    );
    let file = tmp("ctrl-c.tbms");
    let (code, out, err) = ctrl_c_at(
        &[
            "record",
            &sim.path,
            file.to_str().unwrap(),
            "--duration",
            "60s",
        ],
        Duration::from_secs(4),
    );
    assert_eq!(code, Some(130), "{out}\n{err}");
    assert!(out.contains("stopped by Ctrl-C"), "{out}");
    assert!(file.exists(), "the capture is kept");
}

/// Item 8: refusals named registers and contradicted their own range
/// ("above the BMS's charge over-current cutoff (318)); it takes 0.1 A to
/// 750.0 A" for 70 A, the real limit 60 A never said); a float voltage above
/// the absorption voltage was a usage error (exit 2, a --help hint);
/// `absorption_voltage bms` / `float_voltage auto` never showed the volts
/// they come to.
#[test]
fn refusals_say_what_the_bms_allows_and_bms_values_show_what_they_come_to() {
    let sim = Sim::start(&["--bridge-pty"]);
    // The bridge checks a cap against the BMS's cutoff once it has read the
    // BMS's settings (before, the cap is taken, and the lower of the two
    // applies anyway): `settings` waits for that.
    let o = tinybms(&["settings", &sim.path]);
    assert_eq!(o.code, 0, "{o}");
    let o = tinybms(&["config", &sim.path, "charge_current_cap=70A"]);
    assert_eq!(o.code, 1, "{o}");
    let said = format!("{}{}", o.stdout, o.stderr);
    assert!(said.contains("charge over-current cutoff"), "{o}");
    assert!(said.contains("it takes 0.1 A to 60.0 A"), "{o}");
    assert!(!said.contains("750.0 A") && !said.contains("(318)"), "{o}");
    let o = tinybms(&[
        "config",
        &sim.path,
        "float_voltage=3500",
        "absorption_voltage=3400",
    ]);
    assert_eq!(o.code, 1, "{o}");
    assert!(o.stderr.contains("refused"), "{o}");
    assert!(!o.stderr.contains("--help"), "{o}");
    let c = tinybms(&["config", &sim.path]);
    assert_eq!(c.code, 0, "{c}");
    for (field, word, unit) in [
        ("absorption_voltage", "bms", " mV)"),
        ("float_voltage", "auto", " mV)"),
        ("charge_current_cap", "none", "60.0 A)"),
    ] {
        let line = c
            .stdout
            .lines()
            .find(|l| {
                l.trim_start()
                    .trim_start_matches('*')
                    .trim_start()
                    .starts_with(field)
            })
            .unwrap_or_else(|| panic!("{field}: {c}"));
        assert!(line.contains(&format!("{word} (")), "{line}");
        assert!(line.contains(unit), "{line}");
    }
    // `config --reset --yes` names what it put back.
    let o = tinybms(&["config", &sim.path, "stream_period=2s"]);
    assert_eq!(o.code, 0, "{o}");
    let o = tinybms(&["config", &sim.path, "--reset", "--yes"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(
        o.stdout.contains("stream_period = 1000 ms (was 2000 ms)"),
        "{o}"
    );
}

/// Found while making the docs' samples: `tinybms settings PORT | head -3`
/// panicked ("failed printing to stdout: Broken pipe", a backtrace, exit 101)
/// when `head` had its lines. A closed pipe now ends the tool quietly, as it
/// ends `cat`.
#[cfg(unix)]
#[test]
fn output_into_a_pipe_closed_early_ends_quietly() {
    use std::os::unix::process::ExitStatusExt;
    use std::process::{Command, Stdio};
    let sim = Sim::start(&["--bridge-pty"]);
    let mut child = Command::new(tinybms_bin())
        .args(["settings", &sim.path])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The reader is gone before the first line is written.
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_ne!(out.status.code(), Some(101), "{stderr}");
    assert_eq!(
        out.status.signal(),
        Some(libc_sigpipe()),
        "{:?}",
        out.status
    );
}

/// SIGPIPE's number on the systems the tool is built for (13 on Linux and
/// macOS).
#[cfg(unix)]
fn libc_sigpipe() -> i32 {
    13
}

/// Item 11: the monitor's packs-in-parallel panel could not be tried on the
/// desk (`sim --bridge-pty` ran one bridge). `sim --bridge-pty --packs 3` puts
/// pack 1's bridge on the pty: the battery line and one line per pack show.
#[test]
fn the_packs_panel_can_be_tried_on_the_desk() {
    let sim = Sim::start(&["--bridge-pty", "--packs", "3", "--quiet"]);
    // The packs find each other on the bus within seconds, and the battery's
    // lines come between pictures (bounded wait: at most 3 x 12 pictures).
    let mut last = None;
    for _ in 0..3 {
        let o = tinybms(&["monitor", &sim.path, "--plain", "--count", "12"]);
        assert_eq!(o.code, 0, "{o}");
        let done = o
            .stdout
            .contains("Battery (node 1 speaks to the inverter): 3 of 3 packs");
        last = Some(o);
        if done {
            break;
        }
    }
    let o = last.unwrap();
    assert!(
        o.stdout
            .contains("Battery (node 1 speaks to the inverter): 3 of 3 packs"),
        "{o}"
    );
    for node in 1..=3 {
        assert!(
            o.stdout
                .lines()
                .any(|l| l.trim_start().starts_with(&format!("pack {node}"))),
            "pack {node}: {o}"
        );
    }
    // One bridge's options are refused with --packs, not ignored.
    // (--duration: it stops by itself should it be taken.)
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_sim"))
        .args([
            "--bridge-pty",
            "--packs",
            "3",
            "--read-only",
            "--duration",
            "1s",
        ])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&bad.stderr);
    assert_eq!(bad.status.code(), Some(2), "{said}");
    assert!(said.contains("go with one bridge"), "{said}");
}
