//! The maps a new maintainer reads first stay true to the tree: every file of
//! the firmware's library, of protocol-core and of the desktop side is named in
//! `docs/architecture.md`, and every module of the firmware's library is on its
//! front page (`firmware/src/lib.rs`). A module added
//! without its line in the map fails here.

use std::path::Path;

fn root() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// Every `.rs` file under `dir`, as paths relative to it.
fn sources(dir: &Path, under: &Path, out: &mut Vec<String>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            sources(&p, under, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(
                p.strip_prefix(under)
                    .unwrap()
                    .to_string_lossy()
                    .replace('\\', "/"),
            );
        }
    }
}

/// How the map may name `file` (a path under `firmware/src`): its file name
/// in backticks, its folder for a `mod.rs`, or its path.
fn named(doc: &str, file: &str) -> bool {
    let path = Path::new(file);
    let name = path.file_name().unwrap().to_string_lossy();
    let key = if name == "mod.rs" {
        let folder = path
            .parent()
            .unwrap()
            .file_name()
            .unwrap()
            .to_string_lossy();
        format!("`{folder}/`")
    } else {
        format!("`{name}`")
    };
    doc.contains(&key) || doc.contains(file)
}

/// The files of `dir` (under the repository) the map does not name.
fn unnamed(doc: &str, dir: &str, at_least: usize) -> Vec<String> {
    let src = root().join(dir);
    let mut files = Vec::new();
    sources(&src, &src, &mut files);
    assert!(files.len() >= at_least, "{dir}: {} files", files.len());
    files.into_iter().filter(|f| !named(doc, f)).collect()
}

#[test]
fn every_file_of_the_firmware_is_on_the_architecture_map() {
    let doc = std::fs::read_to_string(root().join("docs/architecture.md")).unwrap();
    let missing = unnamed(&doc, "firmware/src", 50);
    assert!(
        missing.is_empty(),
        "docs/architecture.md does not name {missing:?}: add each to the table of the firmware's modules"
    );
}

#[test]
fn every_file_of_protocol_core_and_the_desktop_side_is_on_the_map() {
    let doc = std::fs::read_to_string(root().join("docs/architecture.md")).unwrap();
    for (dir, at_least) in [
        ("protocol-core/src", 10),
        ("host-tests/src", 40),
        ("host-tests/desk/src", 5),
        ("host-tests/tool/src", 20),
        ("host-tests/rules/src", 5),
    ] {
        let missing = unnamed(&doc, dir, at_least);
        assert!(
            missing.is_empty(),
            "docs/architecture.md does not name {missing:?} of {dir}: add each to the table of protocol-core's and the desktop side's modules"
        );
    }
}

#[test]
fn every_module_of_the_library_is_on_its_front_page() {
    let lib = std::fs::read_to_string(root().join("firmware/src/lib.rs")).unwrap();
    let front: String = lib
        .lines()
        .filter_map(|l| l.strip_prefix("//!"))
        .collect::<Vec<_>>()
        .join("\n");
    let modules: Vec<&str> = lib
        .lines()
        .filter_map(|l| l.strip_prefix("pub mod "))
        .map(|l| l.trim_end_matches(';'))
        .collect();
    assert!(modules.len() > 10, "{modules:?}");
    let missing: Vec<&&str> = modules
        .iter()
        .filter(|m| !front.contains(&format!("[`{m}`]")))
        .collect();
    assert!(
        missing.is_empty(),
        "firmware/src/lib.rs's front page does not name {missing:?}"
    );
}

/// The check itself: a file the map does not name is found.
#[test]
fn a_file_left_off_the_map_is_found() {
    let doc = "| side | `bridge/` | the coordinator (`mod.rs`), jobs (`job.rs`) |";
    assert!(named(doc, "bridge/job.rs"));
    assert!(named(doc, "bridge/mod.rs"));
    assert!(!named(doc, "bridge/writes.rs"));
    assert!(!named(doc, "inverter/mod.rs"));
}

/// The path dependencies of the `[dependencies]` tables (the target-specific
/// ones too) of the manifest at `path`, as written (`"../desk"`).
fn path_dependencies(manifest: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut in_deps = false;
    for line in manifest.lines() {
        let line = line.trim();
        if line.starts_with('[') {
            in_deps = line == "[dependencies]"
                || (line.starts_with("[target.") && line.ends_with(".dependencies]"));
            continue;
        }
        if !in_deps {
            continue;
        }
        if let Some(i) = line.find("path = \"") {
            let rest = &line[i + 8..];
            out.push(rest[..rest.find('"').unwrap_or(rest.len())].to_string());
        }
    }
    out
}

/// The path dependencies `manifest` (under `dir` of the repository) has
/// that reach the simulator's crate (`host-tests` itself).
fn reaches_the_simulator(dir: &str, manifest: &str) -> Vec<String> {
    path_dependencies(manifest)
        .into_iter()
        .filter(|p| {
            let target = root().join(dir).join(p);
            target.canonicalize().ok() == root().join("host-tests").canonicalize().ok()
        })
        .collect()
}

/// The desktop tool installs alone: neither it nor the desktop station it
/// runs in direct mode depends on `host-tests` (the simulator).
#[test]
fn the_tool_and_the_desktop_station_never_depend_on_the_simulator() {
    for dir in ["host-tests/tool", "host-tests/desk"] {
        let manifest = std::fs::read_to_string(root().join(dir).join("Cargo.toml")).unwrap();
        assert!(
            !path_dependencies(&manifest).is_empty(),
            "{dir}: no path dependency read"
        );
        let bad = reaches_the_simulator(dir, &manifest);
        assert!(
            bad.is_empty(),
            "{dir}/Cargo.toml depends on the simulator: {bad:?}"
        );
    }
    // The check itself: a manifest with host-tests among its dependencies.
    let broken = "[dependencies]\nhost-tests = { path = \"..\" }\n";
    assert_eq!(reaches_the_simulator("host-tests/tool", broken), [".."]);
}
