//! Issue 51: what an owner reads and runs, held to the code. The docs'
//! flash offsets against the partition table, the image file names against
//! what `firmware/make-images.sh` makes, every `tinybms config` command in
//! them against the configuration's rules, every way of flashing from source
//! against the partition table it is given (nothing is flashed: the commands
//! are read), the README's first screen against the dialects, and the shell
//! completions against the configuration's fields.

mod common;

use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Every guide an owner reads: README.md and docs/*.md, with their text.
fn guides() -> Vec<(String, String)> {
    let mut out = vec![(
        "README.md".to_string(),
        std::fs::read_to_string(root().join("README.md")).unwrap(),
    )];
    let mut docs: Vec<_> = std::fs::read_dir(root().join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    for p in docs {
        let name = format!("docs/{}", p.file_name().unwrap().to_string_lossy());
        // The changelog tells history: old offsets stay true of old images.
        if name != "docs/changelog.md" {
            out.push((name, std::fs::read_to_string(&p).unwrap()));
        }
    }
    out
}

/// The partition table every image and every flashing path uses.
fn table() -> esp_idf_part::PartitionTable {
    let csv = std::fs::read_to_string(root().join("firmware/partitions.csv")).unwrap();
    esp_idf_part::PartitionTable::try_from_str(csv).unwrap()
}

/// Where each of the image files is written.
fn offset_of(kind: &str) -> u32 {
    let t = table();
    match kind {
        "boot" | "merged" => 0,
        "otadata" => t.find("otadata").unwrap().offset(),
        "app" => t.find("ota_0").unwrap().offset(),
        other => panic!("{other}"),
    }
}

/// The kind of an image file name: `tinybms-…-app.bin` → app, and so on.
fn kind_of(file: &str) -> Option<&'static str> {
    let f = file.trim_matches(|c| c == '`' || c == '*');
    if !f.ends_with(".bin") || !f.contains("tinybms") {
        return None;
    }
    Some(if f.ends_with("-app.bin") {
        "app"
    } else if f.ends_with("-boot.bin") {
        "boot"
    } else if f.ends_with("-otadata.bin") {
        "otadata"
    } else {
        "merged"
    })
}

fn hex(s: &str) -> Option<u32> {
    let s = s.trim_matches(|c: char| c == '`' || c == ',' || c == '.' || c == ')');
    u32::from_str_radix(s.strip_prefix("0x")?, 16).ok()
}

/// Issue 51, item 6: `docs/troubleshooting.md` said to write the app at
/// 0x10000 (now `otadata`), `docs/browser.md` that the installer writes it
/// there. Every offset a guide gives an image file — in a command (`0x20000
/// tinybms-…-app.bin`), in a sentence (`-app.bin` … at 0x20000, the firmware
/// at …) or in a table row — is the one the partition table gives it.
#[test]
fn every_offset_the_guides_give_an_image_is_the_partition_table_s() {
    let mut checked = 0;
    let mut wrong = Vec::new();
    for (name, text) in guides() {
        for (n, line) in text.lines().enumerate() {
            let words: Vec<&str> = line.split_whitespace().collect();
            let mut say = |kind: &str, at: u32, how: &str| {
                checked += 1;
                if at != offset_of(kind) {
                    wrong.push(format!(
                        "{name}:{}: {kind} at {at:#x} ({how}), the table says {:#x}: {line}",
                        n + 1,
                        offset_of(kind)
                    ));
                }
            };
            // A command: `0xN FILE`.
            for w in words.windows(2) {
                if let (Some(at), Some(kind)) = (hex(w[0]), kind_of(w[1])) {
                    say(kind, at, "a command");
                }
            }
            // A sentence: a file, then `at 0xN` within a few words.
            for (i, w) in words.iter().enumerate() {
                let kind = kind_of(w.trim_end_matches([',', ')', ';'])).or_else(|| {
                    let l = w.to_ascii_lowercase();
                    (l == "firmware" || l == "app").then_some("app")
                });
                let Some(kind) = kind else { continue };
                let near = &words[i + 1..words.len().min(i + 4)];
                if let Some(at) = near
                    .windows(2)
                    .find(|p| p[0] == "at")
                    .and_then(|p| hex(p[1]))
                {
                    say(kind, at, "a sentence");
                }
            }
            // A table row: a file in its first cell, the first cell that
            // starts with an offset ("`0x20000` (`ota_0`)").
            let cells: Vec<&str> = line.split('|').map(str::trim).collect();
            if line.starts_with('|') && cells.len() > 2 {
                if let Some(kind) = kind_of(cells[1]) {
                    if let Some(at) = cells[2..]
                        .iter()
                        .find_map(|c| c.split_whitespace().next().and_then(hex))
                    {
                        say(kind, at, "a table row");
                    }
                }
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    assert!(
        checked >= 10,
        "only {checked} offsets found: the check reads nothing"
    );
}

/// The image files a guide names are the ones the script makes:
/// `tinybms-BOARD[-wifi]{.bin,-app.bin,-boot.bin,-otadata.bin,.tbu,.elf}`
/// and `manifest-BOARD[-wifi].json`, for a board that exists.
#[test]
fn every_image_file_a_guide_names_is_one_the_script_makes() {
    let cargo = std::fs::read_to_string(root().join("firmware/Cargo.toml")).unwrap();
    let boards: Vec<String> = cargo
        .lines()
        .filter_map(|l| l.strip_prefix("board-"))
        .filter_map(|l| l.split_once(" = [\"esp32c"))
        .map(|(b, _)| b.to_string())
        .collect();
    assert!(boards.len() >= 7, "{boards:?}");
    let placeholders = ["BOARD", "<board>", "<b>", "B"];
    let known = |board: &str| boards.iter().any(|b| b == board) || placeholders.contains(&board);
    let mut names = 0;
    let mut wrong = Vec::new();
    for (name, text) in guides() {
        for token in text.split(|c: char| c.is_whitespace() || "`()|,;:\"'[]".contains(c)) {
            let t = token.trim_end_matches('.');
            let stem = if let Some(s) = t.strip_prefix("tinybms-") {
                s
            } else if let Some(s) = t.strip_prefix("manifest-") {
                if let Some(board) = s.strip_suffix(".json") {
                    names += 1;
                    let b = board.strip_suffix("-wifi").unwrap_or(board);
                    if !known(b) {
                        wrong.push(format!("{name}: {t}"));
                    }
                }
                continue;
            } else {
                continue;
            };
            let Some(rest) = [
                ".bin",
                "-app.bin",
                "-boot.bin",
                "-otadata.bin",
                ".tbu",
                ".elf",
            ]
            .iter()
            .filter_map(|suffix| stem.strip_suffix(suffix))
            .min_by_key(|r| r.len()) else {
                continue;
            };
            names += 1;
            let board = rest.strip_suffix("-wifi").unwrap_or(rest);
            if !known(board) && !board.ends_with("firmware") {
                wrong.push(format!("{name}: {t}"));
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    assert!(names >= 20, "only {names} names found");
}

/// Issue 51, item 7: the README had `inverter_name=DEYE` where the tables
/// say PYLON. Every `tinybms config PORT NAME=VALUE…` command in a guide is
/// one the bridge takes: the field exists and the value is one of its
/// values.
#[test]
fn every_config_command_in_the_guides_is_taken() {
    let mut checked = 0;
    let mut wrong = Vec::new();
    for (name, text) in guides() {
        for line in text.lines() {
            let code = line.split('#').next().unwrap_or("");
            let words: Vec<&str> = code.split_whitespace().collect();
            let Some(at) = words
                .windows(2)
                .position(|w| w[0] == "tinybms" && w[1] == "config")
            else {
                continue;
            };
            for w in &words[at + 2..] {
                let w = w.trim_matches('`');
                let Some((field, value)) = w.split_once('=') else {
                    continue;
                };
                if field.is_empty()
                    || !field.bytes().all(|b| b.is_ascii_lowercase() || b == b'_')
                    || value.starts_with('<')
                    || value.chars().all(|c| c.is_ascii_uppercase() || c == '…')
                        && !value.is_empty()
                        && field != "inverter_name"
                {
                    continue; // a placeholder (`update_key=<public key>`, `X=VALUE`)
                }
                checked += 1;
                if let Err(e) = tinybms_rules::config::check_assignment(field, value) {
                    wrong.push(format!("{name}: `{w}`: {e}"));
                }
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    assert!(checked >= 8, "only {checked} assignments found");
}

/// Issue 51, item 5: the build-from-source paths flashed without the
/// partition table (no second slot: no update without a cable). Every way
/// of flashing from source writes the table of every image: the runners
/// (`--idf-partition-table`), espflash in `firmware/` (`espflash.toml`), and
/// every `espflash flash` a guide gives runs there or names the table.
#[test]
fn every_way_of_flashing_from_source_writes_the_partition_table() {
    let t = table();
    for (label, offset) in [
        ("otadata", 0x10000),
        ("ota_0", 0x20000),
        ("ota_1", 0x1D0000),
        ("history", 0x380000),
    ] {
        assert_eq!(t.find(label).map(|p| p.offset()), Some(offset), "{label}");
    }
    let config = std::fs::read_to_string(root().join("firmware/.cargo/config.toml")).unwrap();
    let runners: Vec<&str> = config.lines().filter(|l| l.starts_with("runner")).collect();
    assert_eq!(runners.len(), 2, "{runners:?}");
    for r in runners {
        assert!(r.contains("--idf-partition-table partitions.csv"), "{r}");
    }
    let espflash = std::fs::read_to_string(root().join("firmware/espflash.toml")).unwrap();
    let section = espflash
        .lines()
        .skip_while(|l| l.trim() != "[idf]")
        .find(|l| l.starts_with("partition_table"));
    assert_eq!(
        section.map(|l| l.replace(' ', "")),
        Some("partition_table=\"partitions.csv\"".into()),
        "{espflash}"
    );
    let mut commands = 0;
    for (name, text) in guides() {
        for line in text.lines().filter(|l| l.contains("espflash flash ")) {
            commands += 1;
            assert!(
                line.contains("--partition-table") || line.contains("target/riscv32"),
                "{name}: not run in firmware/ nor given the table: {line}"
            );
        }
    }
    assert!(commands >= 1);
}

/// Issue 51: the README's first screen says which inverter takes which
/// protocol, every protocol the firmware has, and what the output starts
/// as.
#[test]
fn the_readme_s_first_screen_says_which_protocol_for_which_inverter() {
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    let first: String = readme.lines().take(45).collect::<Vec<_>>().join("\n");
    for p in tinybms_firmware::inverter::dialect::PROTOCOLS {
        assert!(
            first.contains(&format!("| `{}`", p.key())),
            "{} missing: {first}",
            p.key()
        );
    }
    let default = tinybms_firmware::inverter::InverterConfig::default()
        .protocol
        .key();
    assert!(first.contains(&format!("starts as `{default}`")), "{first}");
    assert!(first.contains("Deye"), "{first}");
}

/// Issue 51: shell completions know the configuration's field names (bash
/// and zsh; fish's generator leaves positional values out).
#[test]
fn completions_know_the_configuration_s_fields() {
    for shell in ["bash", "zsh"] {
        let out = common::tinybms(&["completions", shell]);
        assert_eq!(out.code, 0, "{out}");
        for f in tinybms_firmware::config::FIELDS {
            assert!(
                out.stdout.contains(&format!("{}=", f.name)),
                "{shell}: {}",
                f.name
            );
        }
    }
}

/// Issue 51, item 10: `sim --board` and `--update-port` were missing from
/// the guides. Every option `sim --help` lists is in a guide's table or text.
#[test]
fn every_option_of_the_simulator_is_in_a_guide() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_sim"))
        .arg("--help")
        .output()
        .unwrap();
    let help = String::from_utf8_lossy(&out.stdout);
    let options: Vec<String> = help
        .lines()
        .filter_map(|l| {
            // An option's own line (`      --seed <N>`, `  -h, --help`), not
            // a description that begins with one (indented deeper).
            let indent = l.len() - l.trim_start().len();
            let t = l.trim_start();
            let t = t.strip_prefix("-h, ").unwrap_or(t);
            (indent <= 6 && t.starts_with("--")).then(|| {
                t.split(|c: char| !(c.is_ascii_alphanumeric() || c == '-'))
                    .next()
                    .unwrap_or("")
                    .to_string()
            })
        })
        .collect();
    assert!(options.len() >= 30, "{options:?}");
    let docs: String = ["docs/desktop-tool.md", "docs/simulator.md", "docs/trust.md"]
        .iter()
        .map(|d| std::fs::read_to_string(root().join(d)).unwrap())
        .collect();
    let missing: Vec<&String> = options
        .iter()
        .filter(|o| *o != "--help" && !docs.contains(&format!("`{o}")))
        .collect();
    assert!(missing.is_empty(), "not in a guide: {missing:?}");
}
