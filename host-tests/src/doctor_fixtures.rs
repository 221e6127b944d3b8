//! The doctor's fixtures: captures of the bridge's own CAN ring
//! ([`tinybms_firmware::inverter::capture`]) after a closed loop with a
//! simulated inverter and a fault, as candump logs, each with the verdicts
//! the doctor must give on it — and healthy ones that must give none.
//! `cargo run -p host-tests --bin doctor-fixtures` writes them to
//! `host-tests/can/doctor/`; the test `doctor` checks the verdicts on the
//! files and that the simulator still makes the same files.

use tinybms_firmware::inverter::capture::{parse_line, Seen};
use tinybms_firmware::inverter::doctor::Doctor;
use tinybms_firmware::inverter::{InverterConfig, Protocol};
use tinybms_firmware::log_line::Line;

use crate::closed_loop::ClosedLoop;
use crate::sim::PackModel;

const S: u64 = 1_000_000;

/// One fixture: its file name (without `.log`), the protocol the bridge
/// speaks, and the verdicts (keys, in the doctor's order) it must give.
#[derive(Debug, Clone, Copy)]
pub struct Case {
    /// File name without `.log`.
    pub name: &'static str,
    /// The bridge's `inverter_protocol`.
    pub protocol: Protocol,
    /// The verdicts it must give ([`tinybms_firmware::inverter::doctor::Verdict::key`]).
    pub expect: &'static [&'static str],
    setup: fn(&mut InverterConfig, &mut Setup),
}

/// What a case changes in the loop.
#[derive(Debug, Clone, Default)]
pub struct Setup {
    /// The simulated inverter speaks this instead of the bridge's protocol.
    pub dialect: Option<Protocol>,
    /// Its load, A (a discharge).
    pub load_a: f64,
    /// Nothing acknowledges the bridge's frames.
    pub unattached: bool,
    /// The inverter sends nothing.
    pub silent: bool,
    /// A bus-off of this long, µs, 60 s in.
    pub bus_off_us: u64,
    /// Its heartbeat skips (every, gap) µs.
    pub heartbeat_gap: Option<(u64, u64)>,
    /// It obeys the SOC only (its own 40 A).
    pub soc_only: bool,
    /// A Multi in island mode: feeds its loads whatever DCL says.
    pub island: bool,
    /// Its voltmeter's offset, V.
    pub voltage_offset_v: f64,
    /// It exports to pull the pack down to CVL; the run goes on to float.
    pub exports: bool,
    /// SOC at the start, %.
    pub soc_pct: f64,
}

fn nothing(_: &mut InverterConfig, _: &mut Setup) {}

/// Every fixture.
pub const CASES: &[Case] = &[
    Case {
        name: "healthy-victron-charge",
        protocol: Protocol::Victron,
        expect: &[],
        setup: nothing,
    },
    Case {
        name: "healthy-victron-discharge",
        protocol: Protocol::Victron,
        expect: &[],
        setup: |_, s| s.load_a = 40.0,
    },
    Case {
        name: "healthy-sma-charge",
        protocol: Protocol::SmaSunnyIsland,
        expect: &[],
        setup: nothing,
    },
    Case {
        name: "healthy-pylon-charge",
        protocol: Protocol::Pylon,
        expect: &[],
        setup: nothing,
    },
    Case {
        name: "healthy-solark-discharge",
        protocol: Protocol::SolArk,
        expect: &[],
        setup: |_, s| s.load_a = 30.0,
    },
    Case {
        name: "healthy-luxpower-charge",
        protocol: Protocol::Luxpower,
        expect: &[],
        setup: nothing,
    },
    Case {
        name: "healthy-growatt-charge",
        protocol: Protocol::Growatt,
        expect: &[],
        setup: nothing,
    },
    Case {
        name: "no-ack-victron",
        protocol: Protocol::Victron,
        expect: &["no_ack"],
        setup: |_, s| {
            s.unattached = true;
            s.silent = true
        },
    },
    Case {
        name: "no-ack-pylon",
        protocol: Protocol::Pylon,
        expect: &["no_ack"],
        setup: |_, s| {
            s.unattached = true;
            s.silent = true
        },
    },
    Case {
        name: "bus-off-victron",
        protocol: Protocol::Victron,
        expect: &["bus_off"],
        setup: |_, s| s.bus_off_us = 5 * S,
    },
    Case {
        name: "bus-off-sma",
        protocol: Protocol::SmaSunnyIsland,
        expect: &["bus_off"],
        setup: |_, s| s.bus_off_us = 5 * S,
    },
    Case {
        name: "no-inverter-victron",
        protocol: Protocol::Victron,
        expect: &["no_inverter"],
        setup: |_, s| s.silent = true,
    },
    Case {
        name: "no-inverter-sma",
        protocol: Protocol::SmaSunnyIsland,
        expect: &["no_inverter"],
        setup: |_, s| s.silent = true,
    },
    Case {
        name: "no-inverter-pylon",
        protocol: Protocol::Pylon,
        expect: &["no_inverter"],
        setup: |_, s| s.silent = true,
    },
    Case {
        name: "heartbeat-late-victron",
        protocol: Protocol::Victron,
        expect: &["heartbeat_late"],
        setup: |_, s| s.heartbeat_gap = Some((20 * S, 4 * S)),
    },
    Case {
        name: "heartbeat-late-pylon",
        protocol: Protocol::Pylon,
        expect: &["heartbeat_late"],
        setup: |_, s| s.heartbeat_gap = Some((25 * S, 5 * S)),
    },
    Case {
        name: "other-dialect-growatt-on-pylon",
        protocol: Protocol::Pylon,
        expect: &["no_inverter", "other_dialect"],
        setup: |_, s| s.dialect = Some(Protocol::Growatt),
    },
    Case {
        name: "other-dialect-gx-on-sma",
        protocol: Protocol::SmaSunnyIsland,
        expect: &["other_dialect"],
        setup: |_, s| s.dialect = Some(Protocol::Victron),
    },
    Case {
        name: "other-dialect-growatt-on-victron",
        protocol: Protocol::Victron,
        expect: &["no_inverter", "other_dialect"],
        setup: |_, s| s.dialect = Some(Protocol::Growatt),
    },
    Case {
        name: "over-limit-charge-victron",
        protocol: Protocol::Victron,
        expect: &["over_limit"],
        setup: |c, s| {
            c.charge.charge_current_cap_da = Some(100);
            s.soc_only = true
        },
    },
    Case {
        name: "over-limit-charge-pylon",
        protocol: Protocol::Pylon,
        expect: &["over_limit"],
        setup: |c, s| {
            c.charge.charge_current_cap_da = Some(100);
            s.soc_only = true
        },
    },
    Case {
        name: "over-limit-discharge-island",
        protocol: Protocol::Victron,
        expect: &["over_limit"],
        setup: |c, s| {
            c.charge.discharge_current_cap_da = Some(300);
            s.island = true;
            s.load_a = 50.0
        },
    },
    Case {
        name: "voltage-disagrees-sma-high",
        protocol: Protocol::SmaSunnyIsland,
        expect: &["voltage_disagrees"],
        setup: |_, s| s.voltage_offset_v = 2.5,
    },
    Case {
        name: "voltage-disagrees-sma-low",
        protocol: Protocol::SmaSunnyIsland,
        expect: &["voltage_disagrees"],
        setup: |_, s| {
            s.voltage_offset_v = -1.6;
            s.load_a = 30.0
        },
    },
    Case {
        name: "unknown-name-pylon",
        protocol: Protocol::Pylon,
        expect: &["unknown_name"],
        setup: |c, _| c.name = *b"TINYBMS ",
    },
    Case {
        name: "unknown-name-luxpower",
        protocol: Protocol::Luxpower,
        expect: &["unknown_name"],
        setup: |c, _| c.name = *b"ENERGUS ",
    },
    Case {
        name: "export-after-step-victron",
        protocol: Protocol::Victron,
        expect: &["export_after_step"],
        setup: |c, s| {
            c.charge.float_step_mv_per_min = 0;
            s.exports = true;
            s.soc_pct = 97.0
        },
    },
    Case {
        name: "export-after-step-pylon",
        protocol: Protocol::Pylon,
        expect: &["export_after_step"],
        setup: |c, s| {
            c.charge.float_step_mv_per_min = 0;
            s.exports = true;
            s.soc_pct = 97.0
        },
    },
];

/// Runs `case` in a closed loop and returns the bridge's capture at its
/// end as a candump log.
pub fn make(case: &Case) -> String {
    let mut config = InverterConfig {
        protocol: case.protocol,
        ..InverterConfig::default()
    };
    let mut setup = Setup {
        soc_pct: 50.0,
        ..Setup::default()
    };
    (case.setup)(&mut config, &mut setup);
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 1, config, 50.0);
    l.h.sim.set_soc_percent(setup.soc_pct);
    let m = &mut l.model;
    if let Some(d) = setup.dialect {
        m.dialect = d;
    }
    m.load_a = setup.load_a;
    m.silent = setup.silent;
    m.heartbeat_gap = setup.heartbeat_gap;
    m.soc_only = setup.soc_only;
    m.island = setup.island;
    m.voltage_offset_v = setup.voltage_offset_v;
    m.exports = setup.exports;
    if setup.unattached {
        l.h.can.attached = false;
    }
    if setup.exports {
        // On to the step into float, then half a minute of what follows.
        let mut end = None;
        while l.h.now < 4 * 3600 * S && end.is_none_or(|e| l.h.now < e) {
            let t = l.h.now + 10 * S;
            l.run_until(t);
            let stepped = l.sent_limits.windows(2).any(|w| w[1].1 + 2 <= w[0].1);
            if stepped && end.is_none() {
                end = Some(l.h.now + 40 * S);
            }
        }
    } else {
        l.run_until(60 * S);
        if setup.bus_off_us > 0 {
            l.bus_off(setup.bus_off_us);
        }
        l.run_until(120 * S);
    }
    let mut out = String::new();
    if let Some(i) = l.h.station.inverter() {
        for e in i.capture().iter() {
            let mut line = Line::new();
            e.write_candump(&mut line);
            out.push_str(line.as_str());
            out.push('\n');
        }
    }
    out
}

/// The doctor's verdicts (keys) on a candump log for a bridge speaking
/// `protocol`; a malformed line is an error with its number.
pub fn verdicts(protocol: Protocol, log: &str) -> Result<Vec<&'static str>, String> {
    let mut d = Doctor::new(protocol);
    for (k, line) in log.lines().enumerate() {
        let (at, seen): (u64, Seen) =
            parse_line(line).map_err(|e| format!("line {}: {}", k + 1, e.text()))?;
        d.on_entry(at, seen);
    }
    Ok(d.verdicts(None).iter().map(|v| v.key()).collect())
}

/// `expected.txt`: a line a fixture — its name, the protocol the bridge
/// speaks, the verdicts it must give (`-` for none).
pub fn manifest() -> String {
    let mut out = String::from(
        "# fixture protocol verdicts... (written by `cargo run -p host-tests --bin doctor-fixtures`)\n",
    );
    for c in CASES {
        let v = if c.expect.is_empty() {
            "-".to_string()
        } else {
            c.expect.join(" ")
        };
        out.push_str(&format!("{} {} {}\n", c.name, c.protocol.key(), v));
    }
    out
}
