//! The `replay` binary: output, standard input, exit codes and error messages.

use std::io::Write;
use std::path::Path;
use std::process::{Command, Output, Stdio};

fn replay(args: &[&str], stdin: Option<&[u8]>) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_replay"))
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run replay");
    {
        let mut input = child.stdin.take().expect("stdin");
        if let Some(bytes) = stdin {
            input.write_all(bytes).expect("write stdin");
        }
    }
    child.wait_with_output().expect("replay output")
}

fn captures() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("captures")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

#[test]
fn file_argument_prints_the_golden_output() {
    let capture = captures().join("rev_d_examples.tbms");
    let out = replay(&[capture.to_str().expect("utf-8 path")], None);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let golden = std::fs::read_to_string(captures().join("rev_d_examples.expected.jsonl"))
        .expect("golden file");
    assert_eq!(text(&out.stdout), golden);
    assert!(out.stderr.is_empty());
}

#[test]
fn dash_reads_standard_input() {
    let out = replay(
        &["-"],
        Some(b"> AA 1B 3F 1B\n< AA 1B 06 16 01 14 01 16 01 0E 4E\n"),
    );
    assert!(out.status.success(), "{}", text(&out.stderr));
    let lines: Vec<serde_json::Value> = text(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("JSON line"))
        .collect();
    assert_eq!(lines.len(), 3);
    assert_eq!(lines[1]["values"]["internal_temperature_c"], 27.8);
    assert_eq!(lines[2]["kind"], "summary");
}

#[test]
fn decode_errors_are_data_not_failures() {
    let out = replay(
        &["-"],
        Some(b"> AA 14 3F 1B\n< AA 1B 06 16 01 14 01 16 01 0E 4F\n< AA\n"),
    );
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        text(&out.stdout).contains(r#""errors":3"#),
        "{}",
        text(&out.stdout)
    );
}

#[test]
fn malformed_capture_names_the_line() {
    let out = replay(&["-"], Some(b"# ok\n> AA 14 7F 1F\n< AA 1 4\n"));
    assert_eq!(out.status.code(), Some(1));
    let err = text(&out.stderr);
    assert!(err.contains("<stdin>:3:"), "{err}");
    assert!(err.contains("`1` has 1 hex digit"), "{err}");
    assert!(
        out.stdout.is_empty(),
        "no partial output on a malformed file"
    );
    let out = replay(&["-"], Some(b"> AA 14\n\xFF\n"));
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("<stdin>:2: not valid UTF-8"));
}

#[test]
fn unreadable_file_and_usage_errors() {
    let out = replay(&["/nonexistent/capture.tbms"], None);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("cannot read /nonexistent/capture.tbms"));
    let out = replay(&[], None);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("usage: replay FILE"));
    let out = replay(&["a", "b"], None);
    assert_eq!(out.status.code(), Some(2));
    let out = replay(&["--help"], None);
    assert!(out.status.success());
}
