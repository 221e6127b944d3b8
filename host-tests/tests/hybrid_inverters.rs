//! Issue 40 in the closed loop: the 48 V hybrid inverters' protocols against
//! simulated inverters that behave as the sources say the real ones do —
//! Growatt's queries (and a silent Growatt: the battery then sends nothing),
//! the Pylontech family's heartbeat, Luxpower's shutdown request, several
//! packs as one battery — and a Deye-like inverter that ignores a current
//! limit of 0 A, held to the simulated pack's truth with adversarial loads,
//! chargers and a drifted SOC.

use proptest::prelude::*;
use tinybms_firmware::inverter::dialect::{StopWhy, Stops};
use tinybms_firmware::inverter::{InverterConfig, InverterReport, Protocol};

use host_tests::closed_loop::{safety_row, ClosedLoop};
use host_tests::sim::PackModel;

const S: u64 = 1_000_000;
const MIN: u64 = 60 * S;

fn lv_loop(protocol: Protocol, stop_by_soc: bool) -> ClosedLoop {
    let config = InverterConfig {
        protocol,
        stop_by_soc,
        ..InverterConfig::default()
    };
    let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 1, config, 100.0);
    l.h.sim.set_soc_percent(50.0);
    l
}

/// The ids of the inverter frames the bridge sent in [from, to).
fn ids(l: &ClosedLoop, from: u64, to: u64) -> Vec<u16> {
    l.sent_ids
        .iter()
        .filter(|(t, _)| (from..to).contains(t))
        .map(|(_, id)| *id)
        .collect()
}

/// Growatt V1.04: "after the storage inverter sends a query … the battery
/// responds". A silent inverter hears nothing; once it queries, each query
/// gets one answer (0x311, 0x312, 0x313, 0x314, 0x319, 0x320, 0x321).
#[test]
fn growatt_answers_each_query_and_a_silent_growatt_hears_nothing() {
    let mut l = lv_loop(Protocol::Growatt, false);
    l.model.silent = true;
    l.run_until(MIN);
    assert!(ids(&l, 0, MIN).is_empty(), "{:?}", ids(&l, 0, MIN));
    assert!(!l.inverter().inverter_heard());
    l.model.silent = false;
    l.run_until(2 * MIN);
    let answered = ids(&l, MIN, 2 * MIN);
    let limits = answered.iter().filter(|id| **id == 0x311).count();
    // One query a second for 60 s (the first answers once data is computed).
    assert!((55..=61).contains(&limits), "{limits}");
    for id in [0x311, 0x312, 0x313, 0x314, 0x319, 0x320, 0x321] {
        assert_eq!(
            answered.iter().filter(|x| **x == id).count(),
            limits,
            "{id:03X}"
        );
    }
    assert!(answered.iter().all(|id| (0x311..=0x321).contains(id)));
    assert!(l.inverter().inverter_heard());
    // Growatt's limits reach the inverter (big-endian 0x311).
    assert!(l.model.last_limits.is_some_and(|(cvl, _, _, _)| cvl > 50.0));
}

/// The Pylontech family: the whole set every second, and the inverter's
/// 0x305 is its heartbeat (heard, then lost when it stops).
#[test]
fn the_pylon_family_sends_every_second_and_hears_the_heartbeat() {
    for (p, set) in [
        (
            Protocol::Pylon,
            vec![0x351, 0x355, 0x356, 0x359, 0x35C, 0x35E],
        ),
        (
            Protocol::SolArk,
            vec![0x351, 0x355, 0x356, 0x359, 0x35C, 0x35E, 0x379],
        ),
        (
            Protocol::Luxpower,
            vec![0x351, 0x355, 0x356, 0x359, 0x35C, 0x35E],
        ),
    ] {
        let mut l = lv_loop(p, false);
        l.run_until(MIN);
        let sent = ids(&l, 30 * S, MIN);
        for id in &set {
            let n = sent.iter().filter(|x| *x == id).count();
            assert!((29..=31).contains(&n), "{p:?} {id:03X} x{n}");
        }
        assert!(sent.iter().all(|id| set.contains(id)), "{p:?}: {sent:?}");
        assert!(l.inverter().inverter_heard(), "{p:?}");
        l.model.silent = true;
        l.run_until(MIN + 10 * S);
        assert!(!l.inverter().inverter_heard(), "{p:?}");
        assert!(l
            .figures
            .reports
            .iter()
            .any(|(_, r)| *r == InverterReport::InverterLost));
    }
}

/// Luxpower V04.2's 0x300 "Shutdown battery": while the inverter asks,
/// charge and discharge stop every way (limits 0, enable bits clear), it is
/// logged, and the BMS is never written to; 10 s after the last request the
/// battery runs again.
#[test]
fn a_luxpower_shutdown_request_stops_charge_and_discharge_while_it_lasts() {
    let mut l = lv_loop(Protocol::Luxpower, false);
    l.run_until(2 * MIN);
    let settings_before = l.h.sim.registers()[300..344].to_vec();
    let start = l.h.now;
    while l.h.now < start + 20 * S {
        let t = l.h.now;
        l.h.station
            .can_received(t, 0x300, &[1, 0, 0, 0, 0, 0, 0, 0]);
        l.run_until(t + S);
    }
    let asked = l
        .sent_limits
        .iter()
        .filter(|(t, ..)| *t > start + 2 * S && *t < start + 20 * S)
        .collect::<Vec<_>>();
    assert!(!asked.is_empty());
    assert!(
        asked.iter().all(|(_, _, ccl, dcl)| *ccl == 0 && *dcl == 0),
        "{asked:?}"
    );
    assert!(!l.model.enabled.0 && !l.model.enabled.1);
    assert!(l
        .figures
        .reports
        .iter()
        .any(|(_, r)| *r == InverterReport::ShutdownAsked(true)));
    assert!(l
        .figures
        .reports
        .iter()
        .any(|(_, r)| matches!(r, InverterReport::Protection { stops, .. } if *stops == Stops::shutdown())));
    assert_eq!(
        l.h.sim.registers()[300..344],
        settings_before[..],
        "the BMS was written to"
    );
    l.run_until(start + 20 * S + 15 * S);
    assert!(l
        .figures
        .reports
        .iter()
        .any(|(_, r)| *r == InverterReport::ShutdownAsked(false)));
    l.run_until(start + 2 * MIN);
    let (_, _, ccl, dcl) = *l.sent_limits.last().unwrap();
    assert!(ccl > 0 && dcl > 0, "{ccl} {dcl}");
    assert!(l.model.enabled.0 && l.model.enabled.1);
}

/// Charging must stop (a cold pack: below the BMS's low-temperature
/// charger cutoff): the charge current limit is 0, the charge voltage told is
/// at most the pack's voltage, the enable bit is clear, and with stop_by_soc
/// the SOC told is 100 % — and the Deye-like inverter, which ignores the
/// first two, stops charging. Each measure is reported with its cause.
#[test]
fn a_charge_stop_is_said_every_way_and_a_deye_stops() {
    let mut l = lv_loop(Protocol::Pylon, true);
    l.model.ignores_zero = true;
    l.run_until(5 * MIN);
    assert!(
        l.model.current_a > 5.0,
        "charging at first: {}",
        l.model.current_a
    );
    l.h.sim.force_temperature(Some(-5.0));
    l.run_until(10 * MIN);
    assert!(l.figures.reports.iter().any(|(_, r)| {
        matches!(r, InverterReport::Protection { stops, .. } if stops.charge == Some(StopWhy::Temperature))
    }));
    assert!(!l.model.enabled.0, "charge enable still set");
    assert!(l.model.enabled.1, "discharge stays enabled");
    assert_eq!(l.model.told_soc, Some(100.0));
    let pack_dv =
        l.h.bridge()
            .telemetry()
            .snapshot
            .as_ref()
            .map(|s| (s.pack_voltage_v * 10.0) as u16)
            .unwrap();
    let (_, cvl, ccl, _) = *l.sent_limits.last().unwrap();
    assert_eq!(ccl, 0);
    assert!(
        cvl + 4 <= pack_dv,
        "CVL {cvl} not below the pack's {pack_dv} dV"
    );
    assert!(
        l.model.current_a.abs() < 0.5,
        "still charging: {} A",
        l.model.current_a
    );
    // Warm again: charging resumes, the protection says so.
    l.h.sim.force_temperature(Some(20.0));
    l.run_until(20 * MIN);
    assert!(l.model.enabled.0);
    assert!(l
        .figures
        .reports
        .iter()
        .any(|(_, r)| matches!(r, InverterReport::Protection { stops, .. } if stops.none())));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// The safety property against the harsh simulated inverters (one that
    /// ignores a current limit of 0 A and the enable bits, one that
    /// overshoots, one that runs on, one that obeys only the SOC, a Deye with
    /// all of these), behind every dialect, with the bridge's defaults:
    /// whatever the inverter's charger or load, the pack's SOC, how far the
    /// BMS's SOC estimate drifted, and a cold spell below the charger cutoff,
    /// no cell reaches its cutoff, no current passes its cutoff for as long
    /// as the BMS waits, and nothing charges a cold pack (the BMS never has
    /// to trip).
    #[test]
    fn a_limit_ignoring_inverter_never_takes_a_cell_past_its_cutoff(
        discharge in any::<bool>(),
        low_soc in 1.0f64..30.0,
        high_soc in 60.0f64..98.0,
        load in 20.0f64..150.0,
        charger in 20.0f64..200.0,
        bias in 0.0f64..25.0,
        cold in any::<bool>(),
        protocol in prop::sample::select(
            tinybms_firmware::inverter::dialect::PROTOCOLS.to_vec()
        ),
        model in prop::sample::select(host_tests::harsh::HARSH[1..].to_vec()),
    ) {
        let config = InverterConfig {
            protocol,
            ..InverterConfig::default()
        };
        let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, 7, config, charger);
        model.apply(&mut l.model);
        l.h.sim.set_soc_bias(bias);
        if discharge {
            l.h.sim.set_soc_percent(low_soc);
            l.model.load_a = load;
        } else {
            l.h.sim.set_soc_percent(high_soc);
        }
        l.run_until(10 * MIN);
        if cold {
            l.h.sim.force_temperature(Some(-5.0));
        }
        l.run_until(40 * MIN);
        l.h.sim.force_temperature(None);
        l.run_until(90 * MIN);
        let (row, ok) = safety_row("adversarial", &l, l.h.now);
        prop_assert!(ok, "{protocol:?} {} {row}", model.name);
    }
}
