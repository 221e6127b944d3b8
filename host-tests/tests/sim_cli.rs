//! The `sim` command: help, a checked soak with its figures, usage errors
//! (unknown options, bad values, options that do not go together).

mod common;

use std::process::Command;

/// Runs `sim args` to its end; one still running after 5 minutes (an option
/// taken that was meant to be refused: a real-time run) is killed and fails
/// the test, so no test waits for ever.
fn sim(args: &[&str]) -> (i32, String, String) {
    let running = common::Captured::start(Command::new(env!("CARGO_BIN_EXE_sim")).args(args));
    let (status, out, err) = running
        .wait(std::time::Duration::from_secs(300))
        .unwrap_or_else(|| panic!("sim {args:?} still ran after 5 minutes"));
    (status.code().unwrap_or(-1), out, err)
}

/// Every option of `sim`, as `--help` lists it.
const OPTIONS: [&str; 33] = [
    "--duration",
    "--fault-rate",
    "--profile",
    "--set",
    "--pack",
    "--seed",
    "--seeds",
    "--asleep",
    "--snapshot-every",
    "--live-period",
    "--write-every",
    "--forge-every",
    "--quiet",
    "--pty",
    "--bridge-pty",
    "--flash",
    "--config",
    "--no-wifi",
    "--wifi-network",
    "--read-only",
    "--stream-period",
    "--boot-button",
    "--bms-fault",
    "--bms-silent",
    "--freeze",
    "--mqtt",
    "--inverter",
    "--scenario",
    "--can-log",
    "--json",
    "--stale-policy",
    "--packs",
    "--help",
];

/// Whether `help` has an entry for `option`: a line of its own that starts
/// with it (`  -h, --help`, `      --seed <N>`), not a mention in a
/// description (`--seed` is also in `--seeds`, `--pty` in `--bridge-pty`).
fn lists(help: &str, option: &str) -> bool {
    help.lines().any(|l| {
        let entry = l.trim_start();
        let entry = entry.strip_prefix("-h, ").unwrap_or(entry);
        l.len() - l.trim_start().len() <= 6
            && entry
                .strip_prefix(option)
                .is_some_and(|rest| rest.is_empty() || rest.starts_with(' '))
    })
}

#[test]
fn help_exits_0_and_documents_every_option() {
    for flag in ["--help", "-h"] {
        let (code, out, err) = sim(&[flag]);
        assert_eq!(code, 0, "{flag}: {err}");
        for option in OPTIONS {
            assert!(lists(&out, option), "{flag}: {option}\n{out}");
        }
        for text in [
            "exit status",
            "real time, on a pseudo-terminal",
            "inverter output",
            "lifepo4-16s",
            "AT+FOR",
        ] {
            assert!(out.contains(text), "{flag}: {text}\n{out}");
        }
    }
}

#[test]
fn a_checked_soak_prints_its_figures_and_exits_0() {
    let (code, out, err) = sim(&[
        "--duration",
        "10m",
        "--fault-rate",
        "0.05",
        "--seeds",
        "1..2",
        "--write-every",
        "1m",
        "--quiet",
    ]);
    assert_eq!(code, 0, "{out}{err}");
    for figure in [
        "2 seed(s) x 0.2 h",
        "wrong values published: 0",
        "false successes 0",
        "offline transitions: 0",
        "longest telemetry gap:",
        "events:",
        "write outcomes:",
    ] {
        assert!(out.contains(figure), "{figure}\n{out}");
    }
}

/// Runs `sim` with `args`, which must be a usage error: exit 2, nothing on
/// stdout, and every one of `words` in the message on stderr.
fn refused(args: &[&str], words: &[&str]) {
    let (code, out, err) = sim(args);
    assert_eq!(code, 2, "{args:?}\n{out}{err}");
    assert!(out.is_empty(), "{args:?}: stdout\n{out}");
    for w in words {
        assert!(err.contains(w), "{args:?}: `{w}` not in\n{err}");
    }
}

#[test]
fn an_unknown_option_exits_2_and_is_named() {
    refused(&["--bogus"], &["'--bogus'"]);
    refused(
        &["--duration", "5s", "--seeds-from", "3"],
        &["'--seeds-from'"],
    );
    // An option without its value.
    refused(&["--duration"], &["--duration", "value is required"]);
}

#[test]
fn a_bad_value_exits_2_with_the_reason() {
    for (args, words) in [
        (&["--packs", "9"][..], &["'9'", "--packs", "2 to 8"][..]),
        (&["--packs", "1"][..], &["'1'", "--packs", "2 to 8"][..]),
        (
            &["--fault-rate", "2"][..],
            &["--fault-rate", "within 0..1"][..],
        ),
        (
            &["--fault-rate", "x"][..],
            &["--fault-rate", "not a number"][..],
        ),
        (&["--seeds", "5..3"][..], &["--seeds", "B < A"][..]),
        (&["--seeds", "5"][..], &["--seeds", "want A..B"][..]),
        (
            &["--stale-policy", "hold:x"][..],
            &["--stale-policy", "bad duration `x`"][..],
        ),
        (
            &["--stale-policy", "keep"][..],
            &["--stale-policy", "stop or hold:"][..],
        ),
        (
            &["--live-period", "0"][..],
            &["--live-period", "above 0"][..],
        ),
        (
            &["--write-every", "0s"][..],
            &["--write-every", "above 0"][..],
        ),
        (
            &["--forge-every", "0"][..],
            &["--forge-every", "above 0"][..],
        ),
        (
            &["--duration", "10x"][..],
            &["--duration", "bad duration unit"][..],
        ),
        (&["--freeze", "5s"][..], &["--freeze", "want AT+FOR"][..]),
        (
            &["--bms-fault", "5s+x"][..],
            &["--bms-fault", "bad duration `x`"][..],
        ),
        (
            &["--mqtt", "localhost"][..],
            &["--mqtt", "want HOST:PORT"][..],
        ),
        (
            &["--mqtt", "localhost:99999"][..],
            &["--mqtt", "the port is not a number"][..],
        ),
        (
            &["--bridge-pty", "--stream-period", "50ms"][..],
            &["--stream-period", "100ms..60s"][..],
        ),
        (
            &["--bridge-pty", "--config", "read_only"][..],
            &["--config", "want NAME=VALUE"][..],
        ),
        (
            &["--scenario", "sunny-day"][..],
            &["--scenario", "unknown scenario"][..],
        ),
        (
            &["--pack", "lead-acid"][..],
            &["--pack", "lifepo4-16s, liion-14s"][..],
        ),
        (
            &["--inverter", "fronius"][..],
            &["--inverter", "victron, sma"][..],
        ),
        (
            &["--set", "no_such_setting=1"][..],
            &["--set", "no such setting"][..],
        ),
        (
            &["--profile", "/nonexistent/profile.txt"][..],
            &["--profile", "/nonexistent/profile.txt"][..],
        ),
        (
            &["--bridge-pty", "--wifi-network", ":x"][..],
            &["--wifi-network", "1 to 32 bytes"][..],
        ),
    ] {
        refused(args, words);
    }
}

#[test]
fn options_that_do_not_go_together_exit_2() {
    let one_bridge = "<--bridge-pty|--mqtt <HOST:PORT>>";
    for (args, words) in [
        (
            &["--pty", "--bridge-pty"][..],
            &["'--pty'", "cannot be used with", "'--bridge-pty'"][..],
        ),
        // Issue 26, item 13: several packs ran one bridge on the pty without
        // a word; since issue 42 `--bridge-pty --packs N` is pack 1's bridge,
        // and one bridge's options are refused with --packs (--duration: it
        // stops by itself should it be taken).
        (
            &[
                "--bridge-pty",
                "--packs",
                "2",
                "--read-only",
                "--duration",
                "1s",
            ][..],
            &["go with one bridge, not with --packs"][..],
        ),
        (
            &["--pty", "--packs", "2"][..],
            &["'--pty'", "cannot be used with", "'--packs <N>'"][..],
        ),
        (
            &["--pty", "--mqtt", "127.0.0.1:1883"][..],
            &["'--pty'", "cannot be used with", "'--mqtt <HOST:PORT>'"][..],
        ),
        (
            &["--seed", "3", "--seeds", "1..2"][..],
            &["'--seed <N>'", "cannot be used with", "'--seeds <A..B>'"][..],
        ),
        (
            &["--freeze", "1s+1s"][..],
            &["not provided", "<--pty|--bridge-pty>"][..],
        ),
        (&["--config", "a=b"][..], &["not provided", one_bridge][..]),
        (&["--read-only"][..], &["not provided", one_bridge][..]),
        (
            &["--stream-period", "2s"][..],
            &["not provided", one_bridge][..],
        ),
        (
            &["--flash", "flash.bin"][..],
            &["not provided", one_bridge][..],
        ),
        (
            &["--boot-button", "5s"][..],
            &["not provided", one_bridge][..],
        ),
        (
            &["--bms-fault", "20s+15s"][..],
            &["not provided", one_bridge][..],
        ),
        (
            &["--pty", "--bms-fault", "20s+15s"][..],
            &["'--bms-fault <AT+FOR>'", "cannot be used with", "'--pty'"][..],
        ),
        (
            &[
                "--packs",
                "2",
                "--mqtt",
                "127.0.0.1:1",
                "--bms-fault",
                "20s+15s",
            ][..],
            &[
                "'--bms-fault <AT+FOR>'",
                "cannot be used with",
                "'--packs <N>'",
            ][..],
        ),
        (
            &[
                "--packs",
                "2",
                "--mqtt",
                "127.0.0.1:1",
                "--scenario",
                "full-charge",
            ][..],
            &["--scenario goes without them"][..],
        ),
    ] {
        refused(args, words);
    }
}

#[test]
fn a_short_run_exits_0_and_a_repeated_option_counts_once() {
    // The last of a repeated option counts, as with the hand-written parser
    // (clap's default would refuse the second --duration).
    let (code, out, err) = sim(&["--duration", "1h", "--duration", "5s", "--quiet", "--quiet"]);
    assert_eq!(code, 0, "{out}{err}");
    assert!(out.contains("1 seed(s) x 0.0 h"), "{out}");
    assert!(out.contains("wrong values published: 0"), "{out}");
    // --quiet: no log line before the figures.
    assert!(out.starts_with("--- link ---\n"), "{out}");
}

#[test]
fn a_forgery_no_bridge_can_detect_is_caught_by_the_checker_and_exits_1() {
    // The self-test of the ground truth: forged live replies that pass every
    // consistency check are published (nothing could tell), and the sim command
    // must say so and fail.
    let (code, out, err) = sim(&["--duration", "2m", "--forge-every", "20s", "--quiet"]);
    assert_eq!(code, 1, "{out}{err}");
    assert!(out.contains("FAIL"), "{out}");
    let wrong: u64 = out
        .lines()
        .find_map(|l| l.strip_prefix("wrong values published: "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap();
    assert!(wrong >= 1, "{out}");
}
