//! `firmware/make-images.sh`, the ready-made images' script, run with a
//! stand-in `cargo` and `pack-images` (no firmware is built): what build name it
//! gives every image. Unix only (bash, git, sha256sum).
#![cfg(unix)]

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;

mod common;
use common::git;

/// A copy of the script with what it reads (Cargo.toml's board features and
/// version, the build aliases, the firmware's name for the manifests) in a
/// fresh folder, and stand-ins on PATH: `cargo`
/// writes the TINYBMS_BUILD it was run with to `builds.txt` and an empty
/// ELF where the alias puts it; `pack-images` (PACK_IMAGES) writes the two
/// images it is asked for; `tinybms` (TINYBMS) writes the update file its
/// `sign -o` names.
fn scratch(name: &str) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware");
    let dir = std::env::temp_dir().join(format!("tinybms-images-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let fw = dir.join("firmware");
    std::fs::create_dir_all(fw.join(".cargo")).unwrap();
    std::fs::create_dir_all(fw.join("src/improv")).unwrap();
    std::fs::create_dir_all(dir.join("bin")).unwrap();
    for f in [
        "make-images.sh",
        "Cargo.toml",
        ".cargo/config.toml",
        "src/improv/mod.rs",
    ] {
        std::fs::copy(root.join(f), fw.join(f)).unwrap();
    }
    std::fs::write(dir.join(".gitignore"), "target/\n").unwrap();
    let stub = |name: &str, body: &str| {
        let p = dir.join("bin").join(name);
        std::fs::write(&p, format!("#!/usr/bin/env bash\nset -e\n{body}\n")).unwrap();
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
    };
    stub(
        "cargo",
        r#"echo "${TINYBMS_BUILD-<unset>}" >> "$STUB_LOG"
target=riscv32imc-unknown-none-elf
for a in "$@"; do case $a in riscv32imac-unknown-none-elf) target=$a ;; esac; done
mkdir -p "target/$target/release" && : > "target/$target/release/tinybms-firmware""#,
    );
    stub("pack-images", r#": > "$3"; : > "$4""#);
    stub(
        "tinybms",
        r#"while (($#)); do [[ $1 == -o ]] && : > "$2"; shift; done"#,
    );
    dir
}

/// Runs the script in `dir`, with `env` added; the build names its cargo
/// runs got, one per board.
fn run(dir: &Path, env: &[(&str, &str)]) -> Vec<String> {
    let builds = run_some(dir, env);
    assert_eq!(builds.len(), 7, "one build per board: {builds:?}");
    builds
}

/// [`run`] for any number of boards.
fn run_some(dir: &Path, env: &[(&str, &str)]) -> Vec<String> {
    let o = command(dir, env).output().unwrap();
    assert!(
        o.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    let text = std::fs::read_to_string(dir.join("builds.txt")).unwrap();
    text.lines().map(str::to_string).collect()
}

/// The script's command in `dir`, with `env` added.
fn command(dir: &Path, env: &[(&str, &str)]) -> Command {
    let log = dir.join("builds.txt");
    let path = format!(
        "{}:{}",
        dir.join("bin").display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let mut c = Command::new("bash");
    c.arg(dir.join("firmware/make-images.sh"))
        .env("PATH", path)
        .env("STUB_LOG", &log)
        .env("PACK_IMAGES", dir.join("bin/pack-images"))
        .env("TINYBMS", dir.join("bin/tinybms"))
        .env_remove("TINYBMS_SIGNING_KEY_FILE")
        .env_remove("TINYBMS_SIGNING_KEY_MAKE")
        .env_remove("TINYBMS_BUILD")
        // Never a repository above the scratch folder.
        .env("GIT_CEILING_DIRECTORIES", dir.parent().unwrap());
    for (k, v) in env {
        c.env(k, v);
    }
    c
}

/// Issue 51, item 5: an owner's own build for one board (IMAGE_BOARDS), and
/// the signing key's kind checked: a 64-digit key (a public key, or a seed
/// of an older keygen) is refused with words, as a damaged private key.
#[test]
fn one_board_on_request_and_only_a_private_key_signs() {
    let dir = scratch("one");
    let builds = run_some(&dir, &[("IMAGE_BOARDS", "c3-supermini")]);
    assert_eq!(builds.len(), 1, "{builds:?}");
    let o = command(&dir, &[("IMAGE_BOARDS", "c3-nosuch")])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("no board c3-nosuch"));
    // The throwaway key it made: a private key file, 128 hex digits.
    let made = std::fs::read_to_string(dir.join("firmware/target/update-signing-key.hex")).unwrap();
    let digits: String = made.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(digits.len(), 128, "{made}");
    for (name, text, says) in [
        ("public", "ab".repeat(32), "public key"),
        (
            "damaged",
            format!("{}{}", "ab".repeat(32), "cd".repeat(32)),
            "damaged",
        ),
    ] {
        let key = dir.join(format!("{name}.key"));
        std::fs::write(&key, &text).unwrap();
        let o = command(
            &dir,
            &[
                ("IMAGE_BOARDS", "c3-supermini"),
                ("TINYBMS_SIGNING_KEY_FILE", key.to_str().unwrap()),
            ],
        )
        .output()
        .unwrap();
        assert_eq!(o.status.code(), Some(2), "{name}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(says), "{name}: {err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Issue 26, item 8: the ready-made images said `build dev` (nothing set
/// TINYBMS_BUILD): now the tag or commit they were built from, `-dirty` with
/// changes not committed, `unknown` outside git; one given wins.
#[test]
fn every_image_is_named_after_what_it_was_built_from() {
    let dir = scratch("git");
    git(&dir, &["init", "-q"]);
    git(&dir, &["add", "-A"]);
    git(&dir, &["commit", "-q", "-m", "images"]);
    git(&dir, &["tag", "v9.8.7"]);
    let builds = run(&dir, &[]);
    assert!(builds.iter().all(|b| b == "v9.8.7"), "{builds:?}");
    // A change not committed.
    std::fs::write(dir.join("firmware/profile.txt"), "# edited\n").unwrap();
    git(&dir, &["add", "firmware/profile.txt"]);
    let _ = std::fs::remove_file(dir.join("builds.txt"));
    let builds = run(&dir, &[]);
    assert!(builds.iter().all(|b| b == "v9.8.7-dirty"), "{builds:?}");
    // A release names its own build.
    let _ = std::fs::remove_file(dir.join("builds.txt"));
    let builds = run(&dir, &[("TINYBMS_BUILD", "release-1")]);
    assert!(builds.iter().all(|b| b == "release-1"), "{builds:?}");
    let _ = std::fs::remove_dir_all(&dir);

    let dir = scratch("nogit");
    let builds = run(&dir, &[]);
    assert!(builds.iter().all(|b| b == "unknown"), "{builds:?}");
    let _ = std::fs::remove_dir_all(&dir);
}
