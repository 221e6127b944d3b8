//! The tool's command line as a user meets it, with no bridge: usage errors
//! (exit 2, with a hint and a suggestion), a port that is not there or is no
//! serial port (exit 3), help and completions. The binary is this crate's
//! own; the end-to-end runs against a simulated bridge are in `host-tests`
//! (they need the simulator).

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Longest one run may take before the test fails (a bound so a hang fails
/// instead of blocking CI, not a timing assertion).
const RUN_LIMIT: Duration = Duration::from_secs(60);

/// What a run of the tool did.
struct Out {
    code: i32,
    stdout: String,
    stderr: String,
}

impl std::fmt::Display for Out {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "exit {}\n--- stdout\n{}\n--- stderr\n{}",
            self.code, self.stdout, self.stderr
        )
    }
}

/// Runs this build's `tinybms args` (stdin empty), killed after [`RUN_LIMIT`].
fn tinybms(args: &[&str]) -> Out {
    let mut child = Command::new(env!("CARGO_BIN_EXE_tinybms"))
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start tinybms");
    let read = |mut r: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut s = Vec::new();
            let _ = r.read_to_end(&mut s);
            String::from_utf8_lossy(&s).into_owned()
        })
    };
    let out = read(Box::new(child.stdout.take().unwrap()));
    let err = read(Box::new(child.stderr.take().unwrap()));
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if start.elapsed() > RUN_LIMIT {
            let _ = child.kill();
            panic!("tinybms {args:?} did not finish within {RUN_LIMIT:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Out {
        code: status.code().unwrap_or(-1),
        stdout: out.join().unwrap(),
        stderr: err.join().unwrap(),
    }
}

/// A path in a scratch directory of this test run.
fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("tinybms-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn missing_port_lists_the_ports() {
    let o = tinybms(&["monitor", "/dev/tinybms-no-such-port"]);
    assert_eq!(o.code, 3, "{o}");
    assert!(
        o.stderr
            .contains("there is no serial port `/dev/tinybms-no-such-port`"),
        "{o}"
    );
    assert!(
        o.stderr.contains("Serial ports present") || o.stderr.contains("No serial port"),
        "{o}"
    );
}

#[test]
fn usage_errors_exit_2() {
    let o = tinybms(&["frobnicate"]);
    assert_eq!(o.code, 2, "{o}");
    let o = tinybms(&["set", "/dev/null", "no_such_setting=1"]);
    assert_eq!(o.code, 2, "{o}");
    assert!(o.stderr.contains("no such setting"), "{o}");
    let o = tinybms(&["--help"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("Record the raw UART exchange"), "{o}");
    let o = tinybms(&["record", "--help"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(o.stdout.contains("<PORT> <FILE.tbms>"), "{o}");
}

/// `set` naming one setting twice (by any of its names) is refused before
/// anything is sent: the command object would keep one value, and the tool then
/// waited for two outcomes and blamed the bridge ("no answer") after a write
/// that went through.
#[test]
fn set_naming_one_setting_twice_is_a_usage_error() {
    for args in [
        [
            "set",
            "/dev/null",
            "over_voltage_cutoff=3.6",
            "over_voltage_cutoff=3.65",
        ],
        ["set", "/dev/null", "over_voltage_cutoff=3.6", "315=3.65"],
    ] {
        let o = tinybms(&args);
        assert_eq!(o.code, 2, "{o}");
        assert!(o.stderr.contains("twice"), "{o}");
    }
}

/// Item 10: two styles of usage error (clap's `error: …` and the tool's own
/// `tinybms: …` with another hint), and an errno's raw words for a file that
/// is no serial port ("cannot open /dev/null: Not a typewriter").
#[test]
fn usage_errors_read_alike_and_a_non_port_is_named() {
    let clap = tinybms(&["monitr", "/dev/null"]);
    let own = tinybms(&["config", "/dev/null", "no_such_field=1"]);
    for o in [&clap, &own] {
        assert_eq!(o.code, 2, "{o}");
        assert!(o.stderr.starts_with("error: "), "{o}");
        assert!(
            o.stderr.contains("For more information, try '--help'."),
            "{o}"
        );
    }
    let o = tinybms(&["version", "/dev/null"]);
    assert_eq!(o.code, 3, "{o}");
    assert!(o.stderr.contains("is not a serial port"), "{o}");
    assert!(!o.stderr.contains("typewriter"), "{o}");
}

/// Options that belong to another command are refused (they were silently
/// accepted: `stats PORT --save x.txt` exited 0 and wrote nothing).
#[test]
fn misplaced_options_are_refused_and_typos_get_a_suggestion() {
    let save = tmp("never-written.txt");
    for args in [
        vec!["stats", "/dev/null", "--save", save.to_str().unwrap()],
        vec!["version", "/dev/null", "--dry-run"],
        vec!["version", "/dev/null", "--raw"],
        vec!["events", "/dev/null", "--log", "f"],
        vec!["monitor", "/dev/null", "--every", "5s"],
    ] {
        let o = tinybms(&args);
        assert_eq!(o.code, 2, "{args:?}: {o}");
        assert!(
            o.stderr.contains("unexpected argument") || o.stderr.contains("required"),
            "{o}"
        );
    }
    assert!(!save.exists());
    let o = tinybms(&["monitr", "/dev/null"]);
    assert_eq!(o.code, 2, "{o}");
    assert!(o.stderr.contains("'monitor'"), "{o}");
    let o = tinybms(&["set", "/dev/null", "over_volatge_cutoff=3.6"]);
    assert_eq!(o.code, 2, "{o}");
    assert!(
        o.stderr.contains("did you mean `over_voltage_cutoff`"),
        "{o}"
    );
    let o = tinybms(&["completions", "bash"]);
    assert_eq!(o.code, 0, "{o}");
    assert!(
        o.stdout.contains("tinybms") && o.stdout.contains("monitor"),
        "{o}"
    );
}
