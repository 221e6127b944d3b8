//! Issue 42: the docs' samples of output, checked against the tools that
//! print them. A sample drifts silently when the output changes (the monitor
//! lost its min/max line, `saved 38 settings` became 36, a table's figure
//! moved): here each is compared with what today's build prints, either
//! exactly (figures that do not move from run to run) or by its shape (the
//! words and the layout, every number standing for any number).

mod common;

use host_tests::closed_loop::{run_scenario, scenario_row, SCENARIOS, SCENARIO_HEADER};
use tinybms_firmware::inverter::{InverterConfig, Protocol};

fn doc(name: &str) -> String {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../docs")
        .join(name);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The lines a sample shows after the console line `$ <command>`, up to the
/// next `$ ` line or the end of its block.
fn sample<'a>(text: &'a str, command: &str) -> Vec<&'a str> {
    let mut lines = text.lines();
    lines
        .by_ref()
        .find(|l| l.starts_with("$ ") && l[2..].trim_start().starts_with(command))
        .unwrap_or_else(|| panic!("no `$ {command}` in the docs"));
    lines
        .take_while(|l| !l.starts_with("$ ") && !l.starts_with("```"))
        .collect()
}

/// A line's shape: every number (digits, with a point, a sign or a unit's
/// letters glued on as they come) stands for any number, runs of spaces for
/// one, a pseudo-terminal for any; the lowest and highest cells' marks (`<`,
/// `>` after a cell's volts) for none, since which cell is lowest moves from
/// run to run.
fn shape(line: &str) -> String {
    let line = line
        .replace("/dev/pts/", "/dev/pts/#")
        .replace(" V<", " V ")
        .replace(" V>", " V ");
    let mut out = String::new();
    let mut in_number = false;
    for c in line.trim_end().chars() {
        let digit = c.is_ascii_digit();
        let joins = in_number && (c == '.' || digit);
        if digit || joins {
            if !in_number {
                out.push('#');
                in_number = true;
            }
            continue;
        }
        in_number = false;
        if c == ' ' && out.ends_with(' ') {
            continue;
        }
        out.push(c);
    }
    out
}

/// The sample's lines are the output's, by shape and in order (blank lines
/// too): nothing left out, nothing added.
fn assert_same_shape(what: &str, sample: &[&str], output: &str) {
    let want: Vec<String> = sample.iter().map(|l| shape(l)).collect();
    let got: Vec<String> = output.lines().map(shape).collect();
    let trim = |v: &[String]| -> Vec<String> {
        let mut v = v.to_vec();
        while v.last().is_some_and(|l| l.is_empty()) {
            v.pop();
        }
        v
    };
    assert_eq!(
        trim(&want),
        trim(&got),
        "{what}: the docs' sample no longer matches the output\n--- output\n{output}"
    );
}

/// docs/simulator.md's table of the closed-loop scenarios is what `sim
/// --scenario all` prints: the same function makes each row, and the
/// simulation is deterministic (seed 1, virtual time).
#[test]
fn the_scenario_table_of_the_simulator_guide() {
    let text = doc("simulator.md");
    let rows = sample(
        &text,
        "cargo run --release -p host-tests --bin sim -- --scenario all --quiet",
    );
    assert_eq!(rows.first().copied(), Some(SCENARIO_HEADER));
    assert_eq!(rows.len(), SCENARIOS.len() + 1, "{rows:#?}");
    let config = InverterConfig {
        protocol: Protocol::Victron,
        ..InverterConfig::default()
    };
    for (name, want) in SCENARIOS.iter().zip(&rows[1..]) {
        let (l, end) = run_scenario(name, config, |_| {}).unwrap();
        let (row, ok) = scenario_row(name, &l, end, config);
        assert!(ok, "{row}");
        assert_eq!(&row, want, "docs/simulator.md's row of {name}");
    }
}

/// docs/simulator.md's safety table of a 48 V hybrid inverter's protocol
/// behind an inverter with all of a Deye's habits (it ignores a limit of 0 A,
/// overshoots, runs on), the bridge at its defaults: each row is what
/// `safety_row` makes of that run, and every row holds.
#[test]
fn the_safety_table_of_the_simulator_guide() {
    use host_tests::closed_loop::{safety_row, SAFETY_HEADER, SAFETY_SCENARIOS};
    let text = doc("simulator.md");
    let rows = sample(
        &text,
        "cargo run --release -p host-tests --bin sim -- --inverter pylon --scenario all --quiet --inverter-model deye",
    );
    assert_eq!(rows.first().copied(), Some(SAFETY_HEADER));
    assert_eq!(rows.len(), SAFETY_SCENARIOS.len() + 1, "{rows:#?}");
    let config = InverterConfig {
        protocol: Protocol::Pylon,
        ..InverterConfig::default()
    };
    let deye = host_tests::harsh::harsh("deye").unwrap();
    for (name, want) in SAFETY_SCENARIOS.iter().zip(&rows[1..]) {
        let (l, end) = run_scenario(name, config, |l| deye.apply(&mut l.model)).unwrap();
        let (row, ok) = safety_row(name, &l, end);
        assert!(ok, "{row}");
        assert_eq!(&row, want, "docs/simulator.md's row of {name}");
    }
}

/// docs/inverters.md's table of the dialects is the firmware's one list
/// (`DIALECTS`): every dialect once, in order, with its specification, what
/// its inverters are known to do and what the bridge does after a hold.
#[test]
fn the_dialects_table_of_the_inverter_guide_is_the_firmwares_list() {
    use tinybms_firmware::inverter::dialect::{OnSilence, DIALECTS, STOP_BEFORE_QUIET};
    let text = doc("inverters.md");
    let start = text
        .find("<!-- dialects:")
        .expect("docs/inverters.md marks its table of the dialects");
    let end = text[start..].find("<!-- end of dialects -->").unwrap() + start;
    let rows: Vec<&str> = text[start..end]
        .lines()
        .filter(|l| l.starts_with("| `") && !l.starts_with("| `inverter_protocol`"))
        .collect();
    let want: Vec<String> = DIALECTS
        .iter()
        .map(|d| {
            let after = match d.on_silence.0 {
                OnSilence::Stops => format!(
                    "the stop for {STOP_BEFORE_QUIET} s, then nothing (the GX then reports the BMS lost)"
                ),
                OnSilence::RunsOn => "the stop every second until the data is back".into(),
            };
            format!(
                "| `{}` | {} | {} | {} | {after} |",
                d.key,
                d.spec,
                if d.ignores_zero { "yes" } else { "no" },
                d.on_silence.1
            )
        })
        .collect();
    assert_eq!(rows, want);
}

/// docs/inverters.md's sweep table is what `sim --sweep` prints: every
/// dialect behind every simulated inverter, with and without the BMS's
/// switch, every row held; two rows run again here to the byte.
#[test]
fn the_sweep_table_of_the_inverter_guide() {
    use host_tests::harsh::{sweep, sweep_row, Curve, HARSH, SWEEP_HEADER};
    use tinybms_firmware::inverter::dialect::PROTOCOLS;
    let text = doc("inverters.md");
    let rows = sample(
        &text,
        "cargo run --release -p host-tests --bin sim -- --sweep",
    );
    assert_eq!(rows.first().copied(), Some(SWEEP_HEADER));
    assert_eq!(
        rows.len(),
        1 + PROTOCOLS.len() * HARSH.len() * 2,
        "{rows:#?}"
    );
    for (k, row) in rows[1..].iter().enumerate() {
        let p = PROTOCOLS[k / (HARSH.len() * 2)];
        let h = &HARSH[k / 2 % HARSH.len()];
        assert!(
            row.starts_with(&format!("{:<9} {:<13}", p.key(), h.name)),
            "{row}"
        );
        assert!(row.ends_with(" yes"), "{row}");
    }
    for (p, h, switch) in [
        (Protocol::Pylon, "deye", false),
        (Protocol::Victron, "ignores-zero", true),
    ] {
        let h = host_tests::harsh::harsh(h).unwrap();
        let w = sweep(p, &h, switch, &Curve::ALL, 12, 1);
        let row = sweep_row(p, &h, switch, &w);
        assert!(
            rows.contains(&row.as_str()),
            "{row} not in docs/inverters.md"
        );
    }
}

/// docs/desktop-tool.md's monitor samples, in both modes: the lines, their
/// words and their order are what `tinybms monitor --count 1` prints.
#[test]
fn the_monitor_samples_of_the_desktop_tool_guide() {
    let text = doc("desktop-tool.md");
    let direct = common::Sim::start(&["--pty", "--seed", "1"]);
    let bridge = common::Sim::start(&["--bridge-pty", "--seed", "1", "--quiet"]);
    for (pts, sim) in [("/dev/pts/0", &direct), ("/dev/pts/1", &bridge)] {
        let want = sample(&text, &format!("tinybms monitor {pts} --count 1"));
        // The sample shows a bridge whose CAN output runs: the first second
        // after a start has no limits sent yet (bounded wait).
        let mut out = common::tinybms(&["monitor", &sim.path, "--count", "1"]);
        for _ in 0..20 {
            if pts.ends_with('0') || out.stdout.contains("CAN running") {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(250));
            out = common::tinybms(&["monitor", &sim.path, "--count", "1"]);
        }
        assert_eq!(out.code, 0, "{out}");
        assert_same_shape(&format!("monitor {pts}"), &want, &out.stdout);
    }
}

/// docs/desktop-tool.md's `settings --save` and `version` samples: how many
/// settings are saved (exactly), and the version's lines through the bridge
/// (by shape), from the pseudo-terminal the sample names.
#[test]
fn the_settings_and_version_samples_of_the_desktop_tool_guide() {
    let text = doc("desktop-tool.md");
    let bridge = common::Sim::start(&["--bridge-pty", "--seed", "1", "--quiet"]);
    let file = common::tmp("doc-sample-settings.txt");
    let _ = std::fs::remove_file(&file);
    let saved = sample(&text, "tinybms settings /dev/pts/1 --save mybms.txt");
    let out = common::tinybms(&["settings", &bridge.path, "--save", file.to_str().unwrap()]);
    assert_eq!(out.code, 0, "{out}");
    let said = out
        .stdout
        .lines()
        .chain(out.stderr.lines())
        .find(|l| l.starts_with("saved "))
        .unwrap_or_else(|| panic!("no `saved` line: {out}"))
        .split(" to ")
        .next()
        .unwrap()
        .to_string();
    let shown = saved
        .iter()
        .find(|l| l.starts_with("saved "))
        .expect("the sample's `saved` line")
        .split(" to ")
        .next()
        .unwrap();
    assert_eq!(shown, said, "docs/desktop-tool.md's `saved` line");
    // The rows the sample says it cut to.
    let head = text
        .lines()
        .find(|l| l.starts_with("$ tinybms settings /dev/pts/1 --save mybms.txt"))
        .unwrap();
    let in_all: usize = head
        .split("(rows cut: ")
        .nth(1)
        .and_then(|t| t.split(' ').next())
        .and_then(|n| n.parse().ok())
        .expect("`(rows cut: N in all)`");
    let rows = out
        .stdout
        .lines()
        .filter(|l| l.starts_with("  ") && !l.trim_start().starts_with("name "))
        .count();
    assert_eq!(in_all, rows, "the settings table's rows\n{out}");
    let _ = std::fs::remove_file(&file);

    let want = sample(&text, "tinybms version /dev/pts/1");
    let out = common::tinybms(&["version", &bridge.path]);
    assert_eq!(out.code, 0, "{out}");
    assert_same_shape("version through the bridge", &want, &out.stdout);
}

#[test]
fn a_shape_stands_for_any_number_and_not_for_a_word() {
    assert_eq!(
        shape("Pack   52.91 V   -25.20 A   seq 1"),
        shape("Pack 3.3 V -1.0 A seq 253")
    );
    assert_ne!(shape("saved 36 settings"), shape("saved 36 values"));
    assert_ne!(shape("Status discharging"), shape("Status unknown"));
    assert_eq!(shape("/dev/pts/0 x"), shape("/dev/pts/17 x"));
    assert_eq!(
        shape("1 3.30 V<   2 3.31 V"),
        shape("1 3.30 V    2 3.31 V>")
    );
}
