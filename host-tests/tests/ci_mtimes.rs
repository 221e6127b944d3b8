//! `.ci/mtimes.py`, CI's restoring of file times: a file whose content is the
//! one of the previous run gets that run's time back, so cargo rebuilds only
//! what changed; a changed file, a new file and a file edited in the working
//! copy never get an old time. Unix only (git, python3).
#![cfg(unix)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, SystemTime};

mod common;
use common::git;

/// Runs the script in `dir` with `record`; its summary line.
fn restore(dir: &Path, record: &Path) -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../.ci/mtimes.py");
    let o = Command::new("python3")
        .arg(script)
        .arg(record)
        .current_dir(dir)
        .env("GIT_CEILING_DIRECTORIES", dir.parent().unwrap())
        .output()
        .unwrap();
    assert!(o.status.success(), "{o:?}");
    String::from_utf8(o.stdout).unwrap()
}

fn mtime(p: &Path) -> SystemTime {
    std::fs::metadata(p).unwrap().modified().unwrap()
}

fn set_mtime(p: &Path, t: SystemTime) {
    std::fs::File::options()
        .write(true)
        .open(p)
        .unwrap()
        .set_modified(t)
        .unwrap();
}

/// A repository with files `names`, committed; every file's time set to `t`.
fn clone_at(root: &Path, name: &str, files: &[(&str, &str)], t: SystemTime) -> PathBuf {
    let dir = root.join(name);
    std::fs::create_dir_all(&dir).unwrap();
    git(&dir, &["init", "-q"]);
    for (f, body) in files {
        std::fs::write(dir.join(f), body).unwrap();
    }
    git(&dir, &["add", "-A"]);
    git(&dir, &["commit", "-q", "-m", "x"]);
    for (f, _) in files {
        set_mtime(&dir.join(f), t);
    }
    dir
}

#[test]
fn only_unchanged_content_gets_the_previous_runs_time_back() {
    let root = std::env::temp_dir().join(format!("tinybms-mtimes-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).unwrap();
    let record = root.join("mtimes.tsv");
    let then = SystemTime::UNIX_EPOCH + Duration::from_secs(1_600_000_000);
    let now = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);

    // The previous run's clone: every file at `then`.
    let first = clone_at(
        &root,
        "first",
        &[("same.rs", "a"), ("changed.rs", "b"), ("edited.rs", "c")],
        then,
    );
    let line = restore(&first, &record);
    assert!(line.starts_with("0 files as in the previous run"), "{line}");

    // A fresh clone of the next commit: every file at `now`.
    let next = clone_at(
        &root,
        "next",
        &[
            ("same.rs", "a"),
            ("changed.rs", "B"),
            ("edited.rs", "c"),
            ("new.rs", "d"),
        ],
        now,
    );
    // Edited in the working copy after the clone: its blob id is not its content.
    std::fs::write(next.join("edited.rs"), "C").unwrap();
    set_mtime(&next.join("edited.rs"), now);
    let line = restore(&next, &record);
    assert!(line.starts_with("1 files as in the previous run"), "{line}");
    assert!(line.contains("3 new or changed"), "{line}");
    assert_eq!(
        mtime(&next.join("same.rs")),
        then,
        "unchanged content: the old time"
    );
    for f in ["changed.rs", "edited.rs", "new.rs"] {
        assert_eq!(mtime(&next.join(f)), now, "{f}: never an old time");
    }

    // The record is now the second clone's: a third clone with `changed.rs`
    // as the second had it gets the second's time.
    let third = clone_at(
        &root,
        "third",
        &[("changed.rs", "B")],
        now + Duration::from_secs(9),
    );
    let line = restore(&third, &record);
    assert!(line.starts_with("1 files as in the previous run"), "{line}");
    assert_eq!(mtime(&third.join("changed.rs")), now);

    // A damaged record restores nothing and is rewritten.
    std::fs::write(&record, "garbage\tnot-a-time\tchanged.rs\nshort\n").unwrap();
    set_mtime(&third.join("changed.rs"), now + Duration::from_secs(9));
    let line = restore(&third, &record);
    assert!(line.starts_with("0 files as in the previous run"), "{line}");
    assert_eq!(
        mtime(&third.join("changed.rs")),
        now + Duration::from_secs(9)
    );
    let _ = std::fs::remove_dir_all(&root);
}
