//! Writes the doctor's fixtures (`host_tests::doctor_fixtures`) to
//! `host-tests/can/doctor/` (or the folder given), one candump log each,
//! and prints the verdicts the doctor gives on each beside the ones it must.

use std::process::ExitCode;

use host_tests::doctor_fixtures::{make, manifest, verdicts, CASES};

fn main() -> ExitCode {
    let dir = std::env::args()
        .nth(1)
        .unwrap_or_else(|| concat!(env!("CARGO_MANIFEST_DIR"), "/can/doctor").to_string());
    if let Err(e) = std::fs::create_dir_all(&dir) {
        eprintln!("doctor-fixtures: {dir}: {e}");
        return ExitCode::from(2);
    }
    let mut wrong = 0;
    if let Err(e) = std::fs::write(format!("{dir}/expected.txt"), manifest()) {
        eprintln!("doctor-fixtures: {dir}/expected.txt: {e}");
        return ExitCode::from(2);
    }
    for case in CASES {
        let log = make(case);
        let path = format!("{dir}/{}.log", case.name);
        if let Err(e) = std::fs::write(&path, &log) {
            eprintln!("doctor-fixtures: {path}: {e}");
            return ExitCode::from(2);
        }
        let got =
            verdicts(case.protocol, &log).unwrap_or_else(|e| vec![Box::leak(e.into_boxed_str())]);
        let ok = got == case.expect;
        wrong += usize::from(!ok);
        println!(
            "{:<36} {:>4} lines  {:<9} got {:?}{}",
            case.name,
            log.lines().count(),
            case.protocol.key(),
            got,
            if ok {
                String::new()
            } else {
                format!("  ** expected {:?}", case.expect)
            }
        );
    }
    if wrong > 0 {
        eprintln!("{wrong} fixture(s) without their verdicts");
        return ExitCode::from(1);
    }
    ExitCode::SUCCESS
}
