//! Replays every capture of `host-tests/captures/*.tbms` and compares the output
//! with the golden file beside it, `X.tbms` -> `X.expected.jsonl`.
//!
//! After an intended change of the replay output (or of a capture), re-bless:
//!
//! ```text
//! BLESS=1 cargo test -p host-tests --test corpus
//! ```
//!
//! which rewrites the golden files; review them with `git diff` before committing.

use std::path::{Path, PathBuf};

use host_tests::replay::replay_text;

fn captures_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("captures")
}

fn golden_path(capture: &Path) -> PathBuf {
    capture.with_extension("expected.jsonl")
}

fn blessing() -> bool {
    std::env::var_os("BLESS").is_some_and(|v| !v.is_empty() && v != "0")
}

/// The first line where `want` and `got` differ, shown both ways.
fn first_difference(want: &str, got: &str) -> String {
    let (w, g): (Vec<&str>, Vec<&str>) = (want.lines().collect(), got.lines().collect());
    for i in 0..w.len().max(g.len()) {
        let (a, b) = (w.get(i), g.get(i));
        if a != b {
            let show = |l: Option<&&str>| l.map_or("<no line>".to_owned(), |s| (*s).to_owned());
            // Point at the first differing character to help with long lines.
            let col = match (a, b) {
                (Some(a), Some(b)) => a
                    .chars()
                    .zip(b.chars())
                    .position(|(x, y)| x != y)
                    .unwrap_or(a.len().min(b.len())),
                _ => 0,
            };
            return format!(
                "first difference at output line {} (column {}):\n  expected: {}\n  actual:   {}",
                i + 1,
                col + 1,
                show(a),
                show(b)
            );
        }
    }
    "outputs differ only in line endings".to_owned()
}

#[test]
fn corpus_matches_golden_files() {
    let dir = captures_dir();
    let mut captures: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
        .map(|e| e.expect("directory entry").path())
        .filter(|p| p.extension().is_some_and(|x| x == "tbms"))
        .collect();
    captures.sort();
    assert!(
        captures.len() >= 10,
        "expected the capture corpus in {}",
        dir.display()
    );

    let bless = blessing();
    let mut failures = Vec::new();
    for capture in &captures {
        let name = capture
            .file_name()
            .map(|n| n.to_string_lossy().into_owned());
        let name = name.unwrap_or_default();
        let text = std::fs::read_to_string(capture).expect("capture readable");
        let got = match replay_text(&text) {
            Ok(out) => out,
            Err(e) => {
                failures.push(format!("{name}: malformed capture: {e}"));
                continue;
            }
        };
        let golden = golden_path(capture);
        if bless {
            std::fs::write(&golden, &got).expect("write golden file");
            continue;
        }
        match std::fs::read_to_string(&golden) {
            Err(_) => failures.push(format!(
                "{name}: no golden file {}; create it with BLESS=1 cargo test -p host-tests --test corpus",
                golden.display()
            )),
            Ok(want) if want != got => {
                failures.push(format!("{name}: {}", first_difference(&want, &got)));
            }
            Ok(_) => {}
        }
    }

    // A golden file whose capture is gone is stale.
    for entry in std::fs::read_dir(&dir).expect("list captures") {
        let path = entry.expect("directory entry").path();
        let file = path.file_name().map(|n| n.to_string_lossy().into_owned());
        if let Some(stem) = file
            .as_deref()
            .and_then(|f| f.strip_suffix(".expected.jsonl"))
        {
            if !dir.join(format!("{stem}.tbms")).exists() {
                failures.push(format!("{stem}.expected.jsonl has no {stem}.tbms"));
            }
        }
    }

    assert!(
        failures.is_empty(),
        "{} of {} captures differ from their golden files:\n\n{}\n\n\
         If the change is intended: BLESS=1 cargo test -p host-tests --test corpus, then review git diff.",
        failures.len(),
        captures.len(),
        failures.join("\n\n")
    );
}

#[test]
fn first_difference_is_readable() {
    let d = first_difference("a\nbcd\n", "a\nbxd\n");
    assert!(d.contains("output line 2 (column 2)"), "{d}");
    assert!(
        d.contains("expected: bcd") && d.contains("actual:   bxd"),
        "{d}"
    );
    let d = first_difference("a\n", "a\nb\n");
    assert!(d.contains("expected: <no line>"), "{d}");
}

/// Members of `values` that are replay's own (no host-link line has them):
/// a partial cell read, the event log and its clock, settings by name, the
/// extended version's register map.
const REPLAY_ONLY: &[&str] = &[
    "cell_register_voltages_v",
    "events",
    "bms_timestamp_s",
    "settings",
    "register_map_version",
];

/// Every other member replay prints is a member of the firmware's own lines,
/// named once in `host_link::schema` (the register tables): a name replay
/// spells differently (the single-value commands, 0x14 to 0x1F, spell theirs)
/// fails here.
#[test]
fn every_value_replay_prints_is_named_by_the_firmware_lines() {
    use tinybms_firmware::host_link::schema::{
        SNAPSHOT_REGISTERS, STATISTICS_REGISTERS, VERSION_REGISTERS,
    };
    let known: std::collections::BTreeSet<&str> = SNAPSHOT_REGISTERS
        .iter()
        .chain(STATISTICS_REGISTERS)
        .chain(VERSION_REGISTERS)
        .map(|(m, _)| *m)
        .chain(REPLAY_ONLY.iter().copied())
        .collect();
    let mut seen = 0;
    for entry in std::fs::read_dir(captures_dir()).unwrap() {
        let path = entry.unwrap().path();
        if !path.to_string_lossy().ends_with(".expected.jsonl") {
            continue;
        }
        for line in std::fs::read_to_string(&path).unwrap().lines() {
            let v: serde_json::Value = serde_json::from_str(line).unwrap();
            let Some(values) = v.get("values").and_then(|x| x.as_object()) else {
                continue;
            };
            for k in values.keys() {
                assert!(
                    known.contains(k.as_str()),
                    "{}: replay prints `{k}`, which no firmware line names",
                    path.display()
                );
                seen += 1;
            }
        }
    }
    assert!(seen > 100, "only {seen} values in the golden files");
}
