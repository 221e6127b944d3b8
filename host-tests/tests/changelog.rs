//! The owners' changelog (docs/changelog.md): what a release's notes are made
//! of. Its newest section is `## Unreleased`, every entry is a short line or a
//! few (no commit subjects of 200 characters), and the release workflow's
//! script finds a version's section and refuses a version without one.

use std::path::Path;
use std::process::Command;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap()
}

#[test]
fn the_changelog_is_written_for_owners() {
    let text = std::fs::read_to_string(root().join("docs/changelog.md")).unwrap();
    let sections: Vec<&str> = text.lines().filter(|l| l.starts_with("## ")).collect();
    assert_eq!(sections.first(), Some(&"## Unreleased"), "{sections:?}");
    for l in text.lines() {
        assert!(l.chars().count() <= 90, "a line over 90 characters: {l}");
    }
    // Every entry is at most four lines.
    let mut entry = 0;
    for l in text.lines() {
        if l.starts_with("* ") {
            entry = 1;
        } else if l.starts_with("  ") && entry > 0 {
            entry += 1;
            assert!(entry <= 4, "an entry over four lines, at: {l}");
        } else {
            entry = 0;
        }
    }
}

#[test]
fn the_release_notes_are_a_versions_section_and_none_means_no_release() {
    let dir = std::env::temp_dir().join(format!("changelog-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("changelog.md");
    std::fs::write(
        &file,
        "# Changes\n\nintro\n\n## v0.2.0\n\n### Fixed\n\n* two\n\n## v0.1.0\n\n* one\n",
    )
    .unwrap();
    let script = root().join(".github/changelog-section.sh");
    let run = |v: &str| {
        Command::new("bash")
            .arg(&script)
            .arg(v)
            .arg(&file)
            .output()
            .unwrap()
    };
    let o = run("v0.2.0");
    assert!(o.status.success());
    assert_eq!(String::from_utf8_lossy(&o.stdout), "### Fixed\n\n* two\n");
    let o = run("v0.1.0");
    assert_eq!(String::from_utf8_lossy(&o.stdout), "* one\n");
    let o = run("v9.9.9");
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("no \"## v9.9.9\" section"));
    // The real changelog's newest section is there.
    let o = Command::new("bash")
        .arg(&script)
        .arg("Unreleased")
        .output()
        .unwrap();
    assert!(o.status.success(), "{o:?}");
}
