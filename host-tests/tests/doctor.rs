//! The doctor of the inverter's wire against its fixtures
//! (`host-tests/can/doctor/`): every fixture gives the verdicts it must and
//! no other — a healthy one none — and the simulator still makes the same
//! captures (all of them: the 28 take well under a second).

use host_tests::doctor_fixtures::{make, manifest, verdicts, CASES};

const DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/can/doctor");

fn fixture(name: &str) -> String {
    std::fs::read_to_string(format!("{DIR}/{name}.log")).unwrap_or_else(|e| {
        panic!("{name}.log: {e} (cargo run -p host-tests --bin doctor-fixtures)")
    })
}

#[test]
fn every_fixture_gives_its_verdicts_and_no_other() {
    let mut causes = std::collections::BTreeSet::new();
    for c in CASES {
        let got = verdicts(c.protocol, &fixture(c.name)).expect(c.name);
        assert_eq!(got, c.expect, "{}", c.name);
        causes.extend(c.expect.iter().copied());
    }
    let healthy = CASES.iter().filter(|c| c.expect.is_empty()).count();
    assert!(CASES.len() >= 20 + healthy, "at least 20 failure captures");
    assert!(causes.len() >= 8, "at least 8 causes: {causes:?}");
    assert!(healthy >= 5, "healthy captures of most dialects");
}

#[test]
fn the_manifest_is_the_cases() {
    let on_disk = std::fs::read_to_string(format!("{DIR}/expected.txt")).expect("expected.txt");
    assert_eq!(on_disk, manifest());
}

#[test]
fn the_simulator_still_makes_the_fixtures() {
    for c in CASES {
        assert_eq!(
            make(c),
            fixture(c.name),
            "{} changed: rerun doctor-fixtures",
            c.name
        );
    }
}

#[test]
fn a_verdict_needs_its_evidence_in_the_capture() {
    // The failure captures cut to their first ten lines (a second or two)
    // give none of the verdicts that need time (over the limit, voltages,
    // export, no inverter).
    let sustained = [
        "over_limit",
        "voltage_disagrees",
        "export_after_step",
        "no_inverter",
    ];
    let mut cut = 0;
    for c in CASES
        .iter()
        .filter(|c| c.expect.iter().any(|v| sustained.contains(v)))
    {
        let head: String = fixture(c.name)
            .lines()
            .take(10)
            .map(|l| format!("{l}\n"))
            .collect();
        let got = verdicts(c.protocol, &head).expect(c.name);
        assert!(
            !got.iter().any(|v| sustained.contains(v)),
            "{}: {got:?} from ten lines",
            c.name
        );
        cut += 1;
    }
    assert!(cut >= 8, "{cut}");
}

#[test]
fn a_damaged_capture_is_refused_with_the_line() {
    let mut log = fixture("healthy-victron-charge");
    log.insert_str(0, "(1.000000) can0 351#0102 T\n(2.0) can0 351#00\n");
    let e = verdicts(CASES[0].protocol, &log).unwrap_err();
    assert!(e.starts_with("line 2: no direction"), "{e}");
}

/// The bridge's doctor judges its evidence against the running clock: the
/// capture's milliseconds wrap after 49.7 days, the verdicts must not vanish
/// with them.
#[test]
fn a_verdict_holds_after_fifty_days_of_uptime() {
    use tinybms_firmware::inverter::{Inverter, InverterConfig};
    let fifty_days = 50 * 86_400 * 1_000_000u64;
    let mut i = Inverter::new(InverterConfig::default(), fifty_days);
    i.on_bus_off(fifty_days);
    let keys: Vec<_> = i
        .doctor()
        .verdicts(Some(fifty_days))
        .iter()
        .map(|v| v.key())
        .collect();
    assert_eq!(keys, ["bus_off"]);
    // The capture's line wraps (a log's time), the verdict did not.
    let e = i.capture().iter().last().copied().expect("an entry");
    assert!(e.at_us() < fifty_days);
}
