//! The words of the log (`tinybms_firmware::text`): what the chip prints is what
//! these tests see, so each line reads as a person reads it — units, "not
//! connected", physical values next to raw ones — and no line is ever cut.

use proptest::prelude::*;
use protocol_core::events::{Event, EventId, OnlineStatus};
use protocol_core::frame::NackCode;
use protocol_core::settings::{Setting, SettingId};
use tinybms_firmware::bms::link::{Failure, LinkStats};
use tinybms_firmware::bridge::report::{SnapshotLine, WriteOutcome};
use tinybms_firmware::inverter::control::Limits;
use tinybms_firmware::inverter::dialect::{OnSilence, StopWhy, Stops, Told};
use tinybms_firmware::inverter::hold::HoldBudget;
use tinybms_firmware::inverter::ignored::{Ignored, Side};
use tinybms_firmware::inverter::{InverterReport, StaleMode};
use tinybms_firmware::text::{self, Line, LINE_MAX};
use tinybms_firmware::{Level, Report, SECOND};

fn said(r: &Report) -> String {
    let mut l = Line::new();
    text::report(r, &mut l);
    l.as_str().to_string()
}

fn said_inverter(r: &InverterReport) -> String {
    let mut l = Line::new();
    text::inverter(r, &mut l);
    l.as_str().to_string()
}

fn snapshot() -> SnapshotLine {
    SnapshotLine {
        pack_v: 52.9079,
        current_a: -12.34,
        soc_percent: 45.25,
        min_cell: (3, 3.3039),
        max_cell: (7, 3.3121),
        internal_c: 24.5,
        external_c: (Some(24.800_001), None),
        status: OnlineStatus::Discharging,
    }
}

#[test]
fn a_snapshot_reads_in_units_and_says_not_connected() {
    let line = said(&Report::Snapshot(snapshot()));
    assert_eq!(
        line,
        "pack 52.91 V -12.3 A, SOC 45.3 %, cells 3.304 V (#3) to 3.312 V (#7), BMS 24.5 °C, \
         sensors 24.8 °C / not connected, Discharging"
    );
    assert!(!line.contains("Some("), "{line}");
    assert!(!line.contains("None"), "{line}");
}

#[test]
fn display_is_the_same_text() {
    let r = Report::Snapshot(snapshot());
    assert_eq!(r.to_string(), said(&r));
}

#[test]
fn a_write_shows_the_physical_value_next_to_the_raw_one() {
    let s = Setting {
        id: SettingId::OverVoltageCutoff,
        value: 3650,
    };
    let ok = said(&Report::Write {
        setting: s,
        outcome: WriteOutcome::Verified,
    });
    assert_eq!(
        ok,
        "write Over-Voltage Cutoff (315) = 3650 (3.650 V): verified"
    );
    let bad = said(&Report::WriteFollowUp {
        setting: s,
        outcome: WriteOutcome::Mismatch { read_back: 3600 },
    });
    assert_eq!(
        bad,
        "write follow-up Over-Voltage Cutoff (315) = 3650 (3.650 V): mismatch (read back 3600)"
    );
    let nack = said(&Report::Write {
        setting: s,
        outcome: WriteOutcome::Nacked(NackCode::CrcError),
    });
    assert!(nack.ends_with(": nacked (code 0x01)"), "{nack}");
}

#[test]
fn unknown_values_are_named_in_hex() {
    let r = Report::StatusChanged {
        from: Some(OnlineStatus::Idle),
        to: OnlineStatus::Unknown(0x9C),
    };
    assert_eq!(said(&r), "status Idle -> unknown_0x9C");
    let e = Report::NewEvent(Event {
        timestamp_s: 1234,
        id: EventId::Unknown(0xEE),
    });
    assert!(said(&e).ends_with("0xEE unknown_0xEE"), "{}", said(&e));
}

#[test]
fn link_errors_say_the_command_and_what_was_not_logged() {
    let r = Report::LinkError {
        command: 0x03,
        failure: Failure::Nack(NackCode::CommandError),
        suppressed: 4,
    };
    assert_eq!(
        said(&r),
        "link error, command 0x03: nack (code 0x00) (+4 more since the last line)"
    );
    assert_eq!(r.level(), Level::Warn);
}

#[test]
fn line_quality_is_a_percentage_with_one_decimal() {
    let r = Report::LineQuality {
        attempts: 1000,
        clean: 987,
        piece_registers: 56,
        snapshots: 240,
    };
    assert!(
        said(&r).starts_with("line quality: 98.7 % of 1000 reads"),
        "{}",
        said(&r)
    );
}

#[test]
fn the_wire_says_its_figures_and_what_to_check() {
    use tinybms_firmware::bms::wire::{WireFigures, WireVerdict};
    let figures = WireFigures {
        replies: 1200,
        corrupted_permille: 104,
        lost_permille: 230,
        resent_permille: 310,
    };
    let r = Report::Wire {
        figures,
        verdict: WireVerdict::BadWire {
            corrupted_permille: 104,
        },
    };
    assert_eq!(
        said(&r),
        "wire: one reply in 10 corrupted: check the ground and the cable length; the BMS answers \
         (1200 replies; per 1000 sends 104 corrupted, 230 lost, 310 resent)"
    );
    assert_eq!(r.level(), Level::Warn);
    let r = Report::Wire {
        figures,
        verdict: WireVerdict::Noisy {
            corrupted_permille: 40,
            lost_permille: 30,
        },
    };
    assert!(said(&r).starts_with("wire: a noisy line: 4.0 % of replies corrupted, 3.0 % lost"));
    assert_eq!(r.level(), Level::Info);
    let r = Report::Wire {
        figures: WireFigures::default(),
        verdict: WireVerdict::Silent,
    };
    assert!(said(&r).starts_with("wire: the BMS does not answer: check its power"));
    assert_eq!(r.level(), Level::Warn);
}

#[test]
fn inverter_lines_read_in_volts_amps_and_seconds() {
    let l = InverterReport::Limits(Limits {
        cvl_dv: 552,
        ccl_da: 1000,
        dcl_da: 5,
        discharge_dv: 500,
    });
    assert_eq!(
        said_inverter(&l),
        "CAN limits: charge voltage 55.2 V, charge current 100.0 A, discharge current 0.5 A"
    );
    let s = InverterReport::Stale {
        age_ms: 5230,
        policy: StaleMode::Hold,
        hold: Some(HoldBudget {
            dcl_da: 480,
            budget_mah: 3640,
            spend_us: 120 * SECOND,
        }),
    };
    assert_eq!(
        said_inverter(&s),
        "CAN: BMS data 5.2 s old: charge stopped; discharge for at most 2 min 0 s, its limit falling to 0 (the last data proves 3.64 Ah above the discharge stop)"
    );
    assert_eq!(s.level(), Level::Warn);
    assert_eq!(InverterReport::Fresh.level(), Level::Info);
    let none = InverterReport::Stale {
        age_ms: 5230,
        policy: StaleMode::Hold,
        hold: Some(HoldBudget {
            dcl_da: 0,
            budget_mah: 0,
            spend_us: 0,
        }),
    };
    assert!(said_inverter(&none).ends_with(
        "charge and discharge stopped (the last data proves no charge above the discharge stop)"
    ));
    assert_eq!(
        said_inverter(&InverterReport::StaleHoldEnded(OnSilence::RunsOn)),
        "CAN: hold over: charge and discharge stopped, said every way every second until the BMS data is back"
    );
    assert_eq!(
        said_inverter(&InverterReport::StaleHoldEnded(OnSilence::Stops)),
        "CAN: hold over: charge and discharge stopped, said every way for 5 s, then nothing (the inverter stops on silence)"
    );
}

/// What the log says of a stop is what the frames told, read back.
#[test]
fn a_protection_line_says_what_was_told() {
    let told = Told {
        limits: Some(Limits {
            cvl_dv: 521,
            ccl_da: 0,
            dcl_da: 480,
            discharge_dv: 416,
        }),
        soc_pct: Some(100),
        charge_enabled: Some(false),
        discharge_enabled: Some(true),
        protection: Some(false),
        link_lost: Some(true),
        name: Some(*b"PYLON   "),
    };
    let r = InverterReport::Protection {
        stops: Stops {
            charge: Some(StopWhy::Temperature),
            discharge: None,
        },
        told,
    };
    assert_eq!(
        said_inverter(&r),
        "CAN protection active: charge stopped (temperature); told: charge current 0.0 A, discharge current 48.0 A, charge voltage 52.1 V, charge enable off, discharge enable on, SOC 100 %, BMS data lost flagged"
    );
    assert_eq!(r.level(), Level::Warn);
    // The all-clear is news, not a warning.
    let clear = InverterReport::Protection {
        stops: Stops::default(),
        told,
    };
    assert_eq!(clear.level(), Level::Info);
    let e = InverterReport::IgnoresStop(Ignored {
        side: Side::Charge,
        current_da: 98,
        for_s: 3,
    });
    assert_eq!(
        said_inverter(&e),
        "CAN: the inverter ignores the charge stop: 9.8 A for 3 s; every stop now goes out with every signal (SOC, charge voltage, protection bits)"
    );
    // The longest fits its line.
    let every = InverterReport::Protection {
        stops: Stops {
            charge: Some(StopWhy::InverterAsked),
            discharge: Some(StopWhy::InverterAsked),
        },
        told: Told {
            limits: Some(Limits {
                cvl_dv: u16::MAX,
                ccl_da: u16::MAX,
                dcl_da: u16::MAX,
                discharge_dv: u16::MAX,
            }),
            protection: Some(true),
            ..told
        },
    };
    let line = said_inverter(&every);
    assert!(!line.ends_with('…'), "cut: {line}");
}

#[test]
fn the_longest_line_fits() {
    let max = LinkStats {
        requests: u32::MAX,
        replies: u32::MAX,
        timeouts: u32::MAX,
        wakeup_resends: u32::MAX,
        retries: u32::MAX,
        crc_errors: u32::MAX,
        framing_errors: u32::MAX,
        invalid_replies: u32::MAX,
        nacks_command: u32::MAX,
        nacks_crc: u32::MAX,
        nacks_other: u32::MAX,
        skipped_bytes: u32::MAX,
        unsolicited: u32::MAX,
        failures: u32::MAX,
        latency_min_us: u32::MAX,
        latency_max_us: u32::MAX,
        latency_sum_us: u64::MAX,
    };
    let line = said(&Report::LinkStats(max));
    assert!(!line.ends_with('…'), "cut: {line}");
    assert!(line.len() < LINE_MAX, "{}", line.len());
}

#[test]
fn a_line_past_its_room_is_cut_with_a_mark_never_a_panic() {
    let mut l = Line::new();
    for _ in 0..100 {
        l.push("0123456789");
    }
    assert!(l.as_str().ends_with('…'));
    assert!(l.as_str().len() <= LINE_MAX);
    // Multi-byte characters are never split.
    let mut l = Line::new();
    for _ in 0..200 {
        l.push("°C");
    }
    assert!(l.as_str().ends_with('…'));
}

#[test]
fn numbers_print_exactly() {
    let mut l = Line::new();
    l.fixed(3304, 3)
        .push(" ")
        .fixed(-5, 1)
        .push(" ")
        .fixed(0, 2)
        .push(" ")
        .int(i64::MIN)
        .push(" ")
        .hex(0x5)
        .push(" ")
        .hex(0x1234)
        .push(" ")
        .real(f32::NAN, 1)
        .push(" ")
        .real(1e30, 1)
        .push(" ")
        .real(-0.04, 1);
    assert_eq!(
        l.as_str(),
        "3.304 -0.5 0.00 -9223372036854775808 0x05 0x1234 ? ? 0.0"
    );
    let mut d = Line::new();
    d.duration_s(45)
        .push(", ")
        .duration_s(725)
        .push(", ")
        .duration_s(12_000)
        .push(", ")
        .duration_s(1_054_800);
    assert_eq!(d.as_str(), "45 s, 12 min 5 s, 3 h 20 min, 12 d 5 h");
}

proptest! {
    /// Fixed-point output parses back to the value it stands for.
    #[test]
    fn fixed_round_trips(raw in any::<i32>(), decimals in 0u32..6) {
        let mut l = Line::new();
        l.fixed(i64::from(raw), decimals);
        let back: f64 = l.as_str().parse().unwrap();
        let want = f64::from(raw) / 10f64.powi(decimals as i32);
        prop_assert!((back - want).abs() <= 1e-9 * want.abs().max(1.0), "{} vs {}", l.as_str(), want);
    }

    /// Rounding of reals agrees with std's formatting (half away from zero on
    /// the f64 value) wherever std's result is not a tie.
    #[test]
    fn real_matches_std(x in -1.0e6f32..1.0e6, decimals in 0u32..4) {
        let mut l = Line::new();
        l.real(x, decimals);
        let scaled = f64::from(x) * 10f64.powi(decimals as i32);
        prop_assume!((scaled - scaled.trunc()).abs() != 0.5);
        let std = format!("{:.*}", decimals as usize, f64::from(x));
        // std prints "-0.0" for a small negative; the log says 0.0.
        let std = std.strip_prefix('-').filter(|t| t.bytes().all(|b| b == b'0' || b == b'.')).unwrap_or(&std);
        prop_assert_eq!(l.as_str(), std);
    }
}

#[test]
fn the_lines_of_packs_in_parallel() {
    let l = Limits {
        cvl_dv: 552,
        ccl_da: 1764,
        dcl_da: 3528,
        discharge_dv: 500,
    };
    let cases = [
        (
            InverterReport::BatteryLimits(l),
            "CAN limits of the battery (all packs): charge voltage 55.2 V, charge current 176.4 A, discharge current 352.8 A",
            Level::Info,
        ),
        (
            InverterReport::Speaker(true),
            "CAN: this bridge now speaks to the inverter for the battery",
            Level::Info,
        ),
        (
            InverterReport::Speaker(false),
            "CAN: this bridge no longer speaks to the inverter",
            Level::Info,
        ),
        (
            InverterReport::Packs {
                online: 3,
                offline: 1,
            },
            "CAN: battery of 3 packs, 1 left (lost, stale or faulted)",
            Level::Info,
        ),
        (
            InverterReport::Packs {
                online: 1,
                offline: 0,
            },
            "CAN: battery of 1 pack",
            Level::Info,
        ),
        (
            InverterReport::BatteryLost,
            "CAN: no pack takes part in the battery: the inverter is stopped",
            Level::Warn,
        ),
        (
            InverterReport::DuplicateNode(2),
            "CAN: another bridge sends summaries as node 2: give each bridge its own pack_node (this one sends no summary until it restarts)",
            Level::Warn,
        ),
    ];
    for (r, text, level) in cases {
        assert_eq!(said_inverter(&r), text);
        assert_eq!(r.level(), level, "{text}");
    }
}
