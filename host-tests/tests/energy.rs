//! The energy counters of Home Assistant's Energy dashboard
//! (`tinybms_firmware::energy`): unit cases, and the station's counters
//! against the integral of what the simulated BMS sent, with a lost link in
//! between that must count nothing.

use host_tests::sim::{PackModel, SimBms, SimConfig};
use host_tests::virtual_time::Harness;
use protocol_core::response::RegisterBlock;
use protocol_core::views::LiveSnapshot;
use tinybms_firmware::energy::Energy;
use tinybms_firmware::SECOND;

#[test]
fn one_hour_at_one_kilowatt_each_way() {
    let mut e = Energy::new();
    // 50 V × 20 A = 1 kW for an hour in 0.25 s steps, then the same out.
    let step = SECOND / 4;
    let mut t = 0;
    for _ in 0..=(3600 * 4) {
        e.on_snapshot(t, 50.0, 20.0, true);
        t += step;
    }
    assert_eq!(e.charged_mwh(), 1_000_000);
    for _ in 0..(3600 * 4) {
        e.on_snapshot(t, 50.0, -20.0, true);
        t += step;
    }
    // The first discharge interval began at the last charge sample.
    assert_eq!(e.charged_mwh(), 1_000_069);
    assert_eq!(e.discharged_mwh(), 999_930);
}

#[test]
fn gaps_flagged_snapshots_and_nonsense_count_nothing() {
    let mut e = Energy::new();
    e.on_snapshot(0, 50.0, 100.0, true);
    // 20 s later: the link was lost meanwhile.
    e.on_snapshot(20 * SECOND, 50.0, 100.0, true);
    assert_eq!(e.charged_mwh(), 0);
    // A flagged snapshot counts nothing on either side of it.
    e.on_snapshot(21 * SECOND, 50.0, 100.0, false);
    e.on_snapshot(22 * SECOND, 50.0, 100.0, true);
    assert_eq!(e.charged_mwh(), 0);
    // Nonsense values are no power either: NaN, infinity.
    e.on_snapshot(23 * SECOND, f32::NAN, 100.0, true);
    e.on_snapshot(24 * SECOND, 50.0, 100.0, true);
    e.on_snapshot(25 * SECOND, f32::INFINITY, 100.0, true);
    e.on_snapshot(26 * SECOND, 50.0, 100.0, true);
    assert_eq!(e.charged_mwh(), 0);
    // 1 s at 5 kW between two good snapshots: 1.388 Wh.
    e.on_snapshot(27 * SECOND, 50.0, 100.0, true);
    assert_eq!(e.charged_mwh(), 1_388);
    // Time going back (a clock that restarted) counts nothing.
    e.on_snapshot(SECOND, 50.0, 100.0, true);
    assert_eq!(e.charged_mwh(), 1_388);
    assert_eq!(e.discharged_mwh(), 0);
}

/// What the simulated BMS reports now: pack voltage and current.
fn reported(sim: &SimBms) -> (f64, f64) {
    let block = RegisterBlock {
        start: 0,
        values: (0..56).map(|a| sim.register(a)).collect(),
    };
    let s = LiveSnapshot::from_registers(&block).unwrap();
    (f64::from(s.pack_voltage_v), f64::from(s.pack_current_a))
}

#[test]
fn the_station_counts_what_the_bms_sent_and_nothing_while_the_link_is_lost() {
    let mut sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 3);
    sim.set_external_current(Some(-40.0));
    let mut h = Harness::new(sim);
    h.retain = false;
    // The truth: the BMS's own pack voltage × current, every 100 ms, over the
    // times the bridge could read it.
    let step = SECOND / 10;
    let (mut truth_wh, mut lost_wh) = (0.0, 0.0);
    let silent = (10 * 60 * SECOND, 12 * 60 * SECOND);
    let end = 30 * 60 * SECOND;
    let mut t = 0;
    while t < end {
        if t == silent.0 {
            h.sim.set_silent_until(silent.1);
        }
        h.run_until(t + step);
        let (v, i) = reported(&h.sim);
        let wh = -(v * i) * (step as f64 / 3.6e9);
        if (silent.0..silent.1).contains(&t) {
            lost_wh += wh;
        } else {
            truth_wh += wh;
        }
        t += step;
    }
    let p = h.station.published(end);
    let counted_wh = p.energy_mwh.1 as f64 / 1000.0;
    println!(
        "discharged: counted {counted_wh:.1} Wh, the BMS sent {truth_wh:.1} Wh while read, \
         {lost_wh:.1} Wh while the link was lost"
    );
    assert_eq!(p.energy_mwh.0, 0, "nothing charged");
    // Within 1 % of what the BMS sent while it could be read, and never the
    // energy of the lost two minutes (35 Wh, 9 %).
    assert!(
        (counted_wh - truth_wh).abs() <= truth_wh * 0.01,
        "{counted_wh} vs {truth_wh}"
    );
    assert!(lost_wh > 30.0, "{lost_wh}");
}
