//! Charge control in a closed loop: the firmware's bridge and inverter output
//! against the simulated TinyBMS and an inverter/charger model that obeys the
//! CAN frames (host_tests::closed_loop). Each scenario checks the limits sent and
//! the cells that result.

use host_tests::closed_loop::ClosedLoop;
use host_tests::sim::PackModel;
use protocol_core::events::EventId;
use tinybms_firmware::inverter::control::Phase;
use tinybms_firmware::inverter::finish::Stage;
use tinybms_firmware::inverter::{InverterConfig, InverterReport, Protocol, StaleMode};

const S: u64 = 1_000_000;
const MIN: u64 = 60 * S;
const H: u64 = 3600 * S;

/// 16S LiFePO4 of the simulator: 300 = 3650 mV, 315 = 3650 mV, 316 = 2500 mV,
/// 318 = 60 A (internal resistor sensor), 319 = 60 °C, 320 = 0 °C. Ceiling
/// margin 50 mV: no cell above 3600 mV. Absorption 100 mV below 315: 3550 mV,
/// CVL 56.8 V; float 15/16 of it: 3328 mV, CVL 53.2 V.
const MAX_CELL_MV: u16 = 3600;
const CELLS: u16 = 16;
const CVL_ABSORPTION_DV: u16 = 568;
const CVL_FLOAT_DV: u16 = 532;

/// The largest CCL: the charge over-current cutoff less the default
/// current margin (20 %).
fn ccl_max_da(l: &ClosedLoop) -> u16 {
    l.h.sim.register(318) * 10 * 80 / 100
}

fn lfp(seed: u64, charger_a: f64) -> ClosedLoop {
    ClosedLoop::new(
        PackModel::LiFePO4_16S,
        seed,
        InverterConfig::default(),
        charger_a,
    )
}

/// The invariants every scenario keeps: no cell above (315 − margin), CVL never
/// 0 and never per-cell-sized (always within cells × [316, 315]), CCL ≤ 318.
fn invariants(l: &ClosedLoop) {
    assert!(
        l.figures.max_cell_mv <= MAX_CELL_MV,
        "highest cell {} mV",
        l.figures.max_cell_mv
    );
    for &(t, cvl, ccl, dcl) in &l.sent_limits {
        assert!(
            (CELLS * 25..=CELLS * 37).contains(&cvl),
            "CVL {cvl} dV at {t}"
        );
        assert!(
            ccl <= ccl_max_da(l) && dcl <= l.h.sim.register(317) * 10,
            "CCL {ccl} DCL {dcl} at {t}"
        );
    }
    assert!(!l.sent_limits.is_empty());
}

#[test]
fn a_full_charge_from_20_percent_ends_in_float_with_no_cell_over_the_limit() {
    let mut l = lfp(1, 100.0);
    l.h.sim.set_soc_percent(20.0);
    l.run_until(6 * H);
    invariants(&l);
    let float_at = l.figures.float_at_us.expect("reached float");
    assert!(float_at < 5 * H, "float at {float_at}");
    assert_eq!(l.inverter().phase(), Phase::Float);
    // Absorption at 16 × 3.55 V, then the step down into float: CVL never
    // rises on the way, and with no load the pack rests near its absorption
    // voltage, so CVL stays at or above the pack's voltage (an inverter that
    // pulls the pack down to CVL finds nothing to pull).
    assert!(l.sent_limits.iter().any(|s| s.1 == CVL_ABSORPTION_DV));
    let after: Vec<u16> = l
        .sent_limits
        .iter()
        .filter(|s| s.0 >= float_at)
        .map(|s| s.1)
        .collect();
    assert!(after.windows(2).all(|w| w[1] <= w[0]), "{after:?}");
    let last = l.sent_limits.last().unwrap();
    assert!(
        f64::from(last.1) / 10.0 >= l.true_pack_v() - 0.05,
        "{last:?} below the pack's {} V",
        l.true_pack_v()
    );
    assert!(
        matches!(
            l.inverter().stage(),
            Some(Stage::StepDown { .. } | Stage::Float)
        ),
        "{:?}",
        l.inverter().stage()
    );
    // CVL changed rarely: never more often than once per 20 s when rising.
    assert!(l.figures.cvl_changes_per_hour(6 * H) < 60.0);
}

/// The policy before the step (`float_step=0`): float at 16 × 3.328 V at once.
#[test]
fn with_float_step_0_cvl_drops_to_float_at_once() {
    let mut config = InverterConfig::default();
    config.charge.float_step_mv_per_min = 0;
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 1, config, 100.0);
    l.h.sim.set_soc_percent(20.0);
    l.run_until(6 * H);
    invariants(&l);
    assert_eq!(l.inverter().phase(), Phase::Float);
    let last = l.sent_limits.last().unwrap();
    assert_eq!(last.1, CVL_FLOAT_DV, "{last:?}");
    assert_eq!(l.inverter().stage(), Some(Stage::Float));
}

#[test]
fn a_runner_cell_30_mv_high_stays_under_the_limit() {
    let mut l = lfp(2, 100.0);
    l.h.sim.set_soc_percent(60.0);
    l.h.sim.set_cell_offset_mv(7, 30.0);
    l.run_until(5 * H);
    invariants(&l);
    // CVL was lowered below 16 × 3.55 V for the runner.
    assert!(
        l.figures.min_cvl_dv.unwrap() < CVL_ABSORPTION_DV,
        "{:?}",
        l.figures.min_cvl_dv
    );
}

#[test]
fn a_cold_morning_blocks_charging_until_it_warms_up() {
    let mut l = lfp(3, 100.0);
    l.h.sim.set_soc_percent(40.0);
    l.h.sim.force_temperature(Some(-5.0));
    l.run_until(10 * MIN);
    invariants(&l);
    // (The first snapshot may predate the cold: its frames are left out.)
    assert!(l
        .sent_limits
        .iter()
        .filter(|s| s.0 > 10 * S)
        .all(|&(_, _, ccl, _)| ccl == 0));
    assert!(l.model.current_a.abs() < 0.01);
    // Warming up through the 5 °C derating window.
    for k in 0..20 {
        l.h.sim.force_temperature(Some(f64::from(k)));
        let t = l.h.now + 3 * MIN;
        l.run_until(t);
    }
    invariants(&l);
    let last = *l.sent_limits.last().unwrap();
    assert_eq!(last.2, ccl_max_da(&l), "full CCL when warm: {last:?}");
    assert!(l.model.current_a > 40.0);
}

#[test]
fn a_hot_pack_stops_charging_at_the_over_heat_cutoff() {
    let mut l = lfp(4, 100.0);
    l.h.sim.set_soc_percent(40.0);
    l.h.sim.force_temperature(Some(30.0));
    l.run_until(5 * MIN);
    let full = ccl_max_da(&l);
    assert_eq!(l.sent_limits.last().unwrap().2, full);
    l.h.sim.force_temperature(Some(57.5));
    l.run_until(10 * MIN);
    let (_, _, ccl, dcl) = *l.sent_limits.last().unwrap();
    assert!(ccl > 0 && ccl < full, "derated: {ccl}");
    assert!(
        dcl > 0 && dcl < l.h.sim.register(317) * 10,
        "derated: {dcl}"
    );
    l.h.sim.force_temperature(Some(61.0));
    l.run_until(15 * MIN);
    let (_, _, ccl, dcl) = *l.sent_limits.last().unwrap();
    assert_eq!((ccl, dcl), (0, 0));
    invariants(&l);
}

#[test]
fn a_bms_fault_cuts_both_limits_and_they_come_back_slowly() {
    let mut l = lfp(5, 100.0);
    l.h.sim.set_soc_percent(40.0);
    l.run_until(5 * MIN);
    l.h.sim
        .inject_fault_event(EventId::DischargingOverCurrentCutoff);
    l.run_until(7 * MIN);
    let (_, _, ccl, dcl) = *l.sent_limits.last().unwrap();
    assert_eq!((ccl, dcl), (0, 0));
    let cleared_at = l.h.now;
    l.h.sim.clear_fault();
    l.run_until(cleared_at + 20 * S);
    // Held for 30 s after the cut...
    assert_eq!(l.sent_limits.last().unwrap().2, 0);
    l.run_until(cleared_at + 2 * MIN);
    // ...then ramped, never jumped: at most 2 A/s.
    let after: Vec<_> = l.sent_limits.iter().filter(|s| s.0 > cleared_at).collect();
    for w in after.windows(2) {
        let dt_s = (w[1].0 - w[0].0) as f64 / 1e6;
        assert!(
            f64::from(w[1].2) - f64::from(w[0].2) <= 20.0 * dt_s + 1.0,
            "{w:?}"
        );
    }
    assert_eq!(l.sent_limits.last().unwrap().2, ccl_max_da(&l));
    invariants(&l);
}

#[test]
fn a_lost_uart_link_stops_the_frames_and_the_inverter() {
    // The stop policy, chosen (the default holds: the next tests).
    let config = InverterConfig {
        stale_policy: StaleMode::Stop,
        ..InverterConfig::default()
    };
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 6, config, 100.0);
    l.h.sim.set_soc_percent(40.0);
    l.run_until(5 * MIN);
    assert!(l.model.current_a > 40.0);
    let lost_at = l.h.now;
    l.h.sim.set_silent_until(lost_at + 30 * S);
    l.run_until(lost_at + 25 * S);
    // On stale data a GX hears the stop (CCL 0, DCL 0) for a few periods,
    // then nothing (it stops on silence); the inverter stopped.
    assert_eq!(
        l.figures.stale_frames,
        u64::from(tinybms_firmware::inverter::dialect::STOP_BEFORE_QUIET)
    );
    assert!(l
        .sent_limits
        .iter()
        .filter(|s| s.0 > lost_at + 6 * S)
        .all(|s| s.2 == 0 && s.3 == 0));
    assert_eq!(l.model.current_a, 0.0);
    assert!(l.figures.reports.iter().any(|(_, r)| matches!(
        r,
        InverterReport::Stale {
            policy: StaleMode::Stop,
            ..
        }
    )));
    l.run_until(lost_at + 2 * MIN);
    assert!(l
        .figures
        .reports
        .iter()
        .any(|(_, r)| *r == InverterReport::Fresh));
    assert!(l.model.current_a > 40.0, "charging again");
    invariants(&l);
}

#[test]
fn with_hold_charge_zero_the_inverter_keeps_discharging_for_a_bounded_time() {
    let config = InverterConfig {
        stale_policy: StaleMode::Hold,
        stale_hold_us: 60 * S,
        ..InverterConfig::default()
    };
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 7, config, 100.0);
    l.h.sim.set_soc_percent(60.0);
    l.model.load_a = 30.0;
    l.run_until(5 * MIN);
    assert!(l.model.current_a < -25.0);
    let lost_at = l.h.now;
    l.h.sim.set_silent_until(lost_at + 10 * MIN);
    l.run_until(lost_at + 40 * S);
    // Still discharging within the falling limit, never charging; CCL 0 in
    // every frame meanwhile, DCL never rising.
    assert!(l.model.current_a < -10.0, "{}", l.model.current_a);
    let held: Vec<_> = l
        .sent_limits
        .iter()
        .filter(|s| s.0 > lost_at + 6 * S)
        .collect();
    assert!(held.iter().all(|s| s.2 == 0));
    assert!(held.windows(2).all(|w| w[1].3 <= w[0].3), "{held:?}");
    assert!(-l.model.current_a <= f64::from(held.last().unwrap().3) / 10.0 + 0.1);
    l.run_until(lost_at + 3 * MIN);
    // After the bounded hold: the stop said, the inverter stopped.
    assert_eq!(l.model.current_a, 0.0);
    assert!(l
        .figures
        .reports
        .iter()
        .any(|(_, r)| matches!(r, InverterReport::StaleHoldEnded(_))));
}

#[test]
fn after_a_hold_the_discharge_limit_is_not_cut_when_the_link_returns() {
    let config = InverterConfig {
        stale_policy: StaleMode::Hold,
        stale_hold_us: 10 * MIN,
        ..InverterConfig::default()
    };
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 7, config, 100.0);
    l.h.sim.set_soc_percent(60.0);
    l.model.load_a = 30.0;
    l.run_until(5 * MIN);
    let lost_at = l.h.now;
    l.h.sim.set_silent_until(lost_at + 40 * S);
    l.run_until(lost_at + 3 * MIN);
    // DCL never 0 (a Victron inverter would switch off), the load kept running.
    assert!(l
        .sent_limits
        .iter()
        .filter(|s| s.0 > lost_at)
        .all(|s| s.3 > 0));
    assert!(l.model.current_a < -25.0);
}

#[test]
fn sma_with_stale_telemetry_is_told_to_stop_at_once() {
    let config = InverterConfig {
        protocol: Protocol::SmaSunnyIsland,
        stale_policy: StaleMode::Stop,
        ..InverterConfig::default()
    };
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 10, config, 100.0);
    l.h.sim.set_soc_percent(40.0);
    l.run_until(3 * MIN);
    assert!(l.model.current_a > 40.0);
    let lost_at = l.h.now;
    l.h.sim.set_silent_until(lost_at + 30 * S);
    l.run_until(lost_at + 15 * S);
    // Limits frames while stale are stop commands only: CCL 0 and DCL 0.
    let stale: Vec<_> = l
        .sent_limits
        .iter()
        .filter(|s| s.0 > lost_at + 6 * S)
        .collect();
    assert!(!stale.is_empty());
    assert!(stale.iter().all(|s| s.2 == 0 && s.3 == 0), "{stale:?}");
    assert_eq!(l.model.current_a, 0.0);
}

#[test]
fn a_can_bus_off_pauses_and_recovers() {
    let mut l = lfp(8, 100.0);
    l.h.sim.set_soc_percent(40.0);
    l.run_until(5 * MIN);
    let at = l.h.now;
    l.bus_off(10 * S);
    l.run_until(at + 8 * S);
    assert_eq!(l.model.current_a, 0.0, "no 0x351 for > 3 s: stopped");
    l.run_until(at + 2 * MIN);
    assert!(l.model.current_a > 40.0, "recovered");
    assert!(l
        .figures
        .reports
        .iter()
        .any(|(_, r)| matches!(r, InverterReport::BusOff { count: 1, .. })));
    invariants(&l);
}

#[test]
fn sma_sunny_island_gets_its_frames() {
    let config = InverterConfig {
        protocol: Protocol::SmaSunnyIsland,
        ..InverterConfig::default()
    };
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 9, config, 100.0);
    l.h.sim.set_soc_percent(40.0);
    l.run_until(2 * MIN);
    invariants(&l);
    assert!(l.model.current_a > 40.0);
}
