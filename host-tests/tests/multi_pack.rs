//! Several packs in parallel, one battery: the closed loop with N simulated
//! packs whose current splits by physics, N bridges on one virtual CAN bus and
//! the inverter model — every scenario of `sim --packs 4 --scenario NAME`.
//! In every one, no pack goes past its own cutoffs (cells, charge and discharge
//! current: the packs' truth, not what the bridges said), never two bridges
//! speak, and the inverter is never without limits for the 3 s a GX waits.

use host_tests::multi_pack::{
    problems, run_scenario, run_scenario_at, table, BatteryFigures, BusFaults, MultiLoop, PackSpec,
    SCENARIOS,
};
use protocol_core::events::EventId;
use tinybms_firmware::inverter::control::ChargeConfig;
use tinybms_firmware::inverter::{InverterConfig, InverterReport, Protocol};

const S: u64 = 1_000_000;
const MIN: u64 = 60 * S;

fn run(name: &str, n: usize, protocol: Protocol) -> (MultiLoop, u64) {
    let config = InverterConfig {
        protocol,
        ..InverterConfig::default()
    };
    let (l, end) = run_scenario(name, n, config, |_| {}).unwrap();
    println!("{}", table(name, &l, end));
    let p = problems(&l, ChargeConfig::default().ceiling_margin_mv);
    assert!(p.is_empty(), "{name}: {p:#?}");
    (l, end)
}

/// Capacity (Ah) and packs taking part in the speaker's battery at `t`.
fn battery_at(l: &MultiLoop, t: u64) -> (u32, u8) {
    let e = l.figures.timeline.iter().rev().find(|e| e.0 <= t).unwrap();
    (e.2 / 10, e.3)
}

/// Capacity (Ah) of `n` of the packs (register 306, 0.01 Ah; all alike).
fn packs_ah(l: &MultiLoop, n: u32) -> u32 {
    u32::from(l.nodes[0].h.sim.register(306)) / 100 * n
}

fn dcl_at(l: &MultiLoop, t: u64) -> u16 {
    l.sent_limits
        .iter()
        .rev()
        .find(|e| e.0 <= t)
        .unwrap()
        .2
        .dcl_da
}

#[test]
fn four_packs_charge_to_float_sharing_the_current_by_physics() {
    let (l, _) = run("full-charge", 4, Protocol::Victron);
    let b = &l.figures;
    assert!(b.float_at_us.is_some(), "the battery never reached float");
    assert_eq!(b.speaker_changes.len(), 1, "node 1 spoke throughout");
    assert_eq!(b.speaker_changes[0].1, 1);
    // The battery asked for what three packs can carry (one may drop out):
    // at most 3 × 48 A (each pack's 60 A cutoff less the 20 % margin), and it
    // did use most of it.
    assert!(b.highest_ccl_da <= 1440, "{}", b.highest_ccl_da);
    assert!(b.highest_ccl_da >= 1200, "{}", b.highest_ccl_da);
    // The battery's capacity is the four packs'.
    assert_eq!(battery_at(&l, 60 * MIN), (packs_ah(&l, 4), 4));
    // CVL never rose after float (the step down into float: with no load the
    // packs rest near their absorption voltage, and CVL stays at or above it).
    let float_at = b.float_at_us.unwrap_or(0);
    let after: Vec<u16> = l
        .sent_limits
        .iter()
        .filter(|s| s.0 >= float_at)
        .map(|s| s.2.cvl_dv)
        .collect();
    assert!(
        !after.is_empty() && after.windows(2).all(|w| w[1] <= w[0]),
        "{after:?}"
    );
    // The bus: four summaries of four frames a second and the inverter frames.
    assert!(b.bus_load_percent(4 * 3600 * S) < 1.0);
}

#[test]
fn a_low_pack_joined_to_three_full_ones_takes_the_most_and_stays_within_its_cutoffs() {
    let (l, end) = run("joined", 4, Protocol::Victron);
    let low = &l.nodes[3];
    let others = l.nodes[..3]
        .iter()
        .map(|p| p.figures.highest_charge_a)
        .fold(0.0, f64::max);
    assert!(
        low.figures.highest_charge_a > 2.0 * others,
        "the split is by physics: {} A against {} A",
        low.figures.highest_charge_a,
        others
    );
    // The full packs gave current to the low one at first (no charger needed).
    assert!(l.nodes[0].figures.highest_discharge_a > 5.0);
    // And it was charged.
    let soc = low.h.sim.register(46);
    assert!(soc > 0, "{soc}");
    assert!(
        low.h
            .bridge()
            .telemetry()
            .snapshot
            .as_ref()
            .unwrap()
            .soc_percent()
            > 40.0
    );
    let _ = end;
}

#[test]
fn a_pack_that_faults_at_full_load_leaves_at_once_and_comes_back_after_the_hold() {
    let (l, _) = run("pack-fault", 4, Protocol::Victron);
    // Full load before the fault: the battery's DCL is more than two packs'
    // current (47.0 A usable each: 60 A less the 20 % margin, less 2 %) and
    // less than three — the reserve for one pack opening, with the learnt
    // shares and their margins; the loads draw it.
    let before = dcl_at(&l, 5 * MIN - S);
    assert!((2 * 470..3 * 470).contains(&before), "{before}");
    assert_eq!(battery_at(&l, 5 * MIN - S), (packs_ah(&l, 4), 4));
    // Within 3 s of the fault the pack is out of the sums and the limit fell.
    assert_eq!(battery_at(&l, 5 * MIN + 3 * S), (packs_ah(&l, 3), 3));
    let after = dcl_at(&l, 5 * MIN + 3 * S);
    assert!(after < before, "DCL {before} → {after}");
    // The BMS clears its fault at 12 min: the pack comes back; the limit
    // does not rise for the hold (30 s), then ramps.
    let back = l
        .figures
        .timeline
        .iter()
        .find(|e| e.0 > 12 * MIN && e.3 == 4)
        .unwrap()
        .0;
    assert!(back < 12 * MIN + 10 * S, "{back}");
    let at_back = dcl_at(&l, back);
    let hold = ChargeConfig::default().limit_hold_us;
    for e in l
        .sent_limits
        .iter()
        .filter(|e| e.0 > back && e.0 < back + hold - 2 * S)
    {
        assert!(
            e.2.dcl_da <= at_back,
            "rose during the hold at {} s",
            e.0 / S
        );
    }
    assert!(dcl_at(&l, back + hold + 60 * S) > at_back);
    // The faulted pack's current stopped (its switch is open).
    let faulted = &l.nodes[1];
    assert!(faulted.h.sim.fault().is_none(), "cleared at the end");
}

#[test]
fn a_bridge_that_loses_its_bms_takes_its_pack_out_of_the_battery() {
    let (l, _) = run("uart-lost", 4, Protocol::Victron);
    assert_eq!(battery_at(&l, 5 * MIN - S), (packs_ah(&l, 4), 4));
    // Stale after 5 s: out of the sums.
    assert_eq!(battery_at(&l, 5 * MIN + 10 * S), (packs_ah(&l, 3), 3));
    assert_eq!(battery_at(&l, 9 * MIN), (packs_ah(&l, 3), 3));
    // Back once its BMS answers again.
    assert_eq!(battery_at(&l, 10 * MIN + 30 * S), (packs_ah(&l, 4), 4));
    let reports: Vec<_> = l
        .figures
        .reports
        .iter()
        .filter(|(_, n, r)| *n == 2 && matches!(r, InverterReport::Stale { .. }))
        .collect();
    assert_eq!(reports.len(), 1);
}

#[test]
fn the_primary_lost_node_2_takes_over_within_the_time_a_gx_waits() {
    let (l, _) = run("primary-lost", 4, Protocol::Victron);
    let changes = &l.figures.speaker_changes;
    assert_eq!(changes.len(), 2, "{changes:?}");
    assert_eq!(changes[1].1, 2);
    assert!(changes[1].0 > 5 * MIN && changes[1].0 < 5 * MIN + 3 * S);
    // Node 1's pack is no longer reported: 3 packs.
    assert_eq!(battery_at(&l, 6 * MIN), (packs_ah(&l, 3), 3));
}

#[test]
fn bus_off_of_the_speaker_hands_over_and_a_recovered_node_stays_quiet() {
    let (l, _) = run("bus-off", 4, Protocol::Victron);
    let changes: Vec<u8> = l.figures.speaker_changes.iter().map(|c| c.1).collect();
    // Node 1 speaks, goes bus-off at 5 min: node 2; node 1 recovers and stays
    // quiet; node 2 goes bus-off at 10 min: node 1 again.
    assert_eq!(changes, vec![1, 2, 1]);
    assert!(l.figures.speaker_changes[2].0 > 10 * MIN);
}

#[test]
fn every_scenario_with_a_sunny_island_and_with_two_and_eight_packs() {
    for name in SCENARIOS {
        run(name, 4, Protocol::SmaSunnyIsland);
    }
    for n in [2, 8] {
        for name in ["full-charge", "pack-fault", "primary-lost"] {
            run(name, n, Protocol::Victron);
        }
    }
}

/// Issue 24, item 4: a cold start never tells a healthy battery CCL 0 /
/// DCL 0 (a DCL of 0 switches a Multi off): the first limits go out at once
/// from the packs heard, without the hold a cut would start.
#[test]
fn a_cold_start_never_tells_a_healthy_battery_zero() {
    let mut l = MultiLoop::new(
        InverterConfig::default(),
        &[60.0, 61.0, 62.0, 63.0],
        &[0.0003; 4],
        &[0.02; 4],
        0.0,
        5,
    );
    l.run_until(60 * S);
    let limits: Vec<_> = l
        .sent_limits
        .iter()
        .filter(|(t, _, _)| *t <= 60 * S)
        .collect();
    assert!(!limits.is_empty(), "the battery's limits go out");
    let zero: Vec<_> = limits
        .iter()
        .filter(|(_, _, x)| x.ccl_da == 0 && x.dcl_da == 0)
        .collect();
    assert!(zero.is_empty(), "0/0 at {:?}", zero.first());
    let first = limits[0];
    assert!(first.0 <= 5 * S, "first limits at {} µs", first.0);
    assert!(first.2.dcl_da > 0 && first.2.ccl_da > 0, "{first:?}");
}

/// Issue 24: packs that differ the way real ones do (a 100 Ah pack on a
/// short cable beside 200–280 Ah packs on long ones), a fault, a second
/// fault, a lost bridge, a stale BMS link on the strongest pack, a cold start,
/// a lossy bus: no pack past its own cutoffs, no BMS trip, one speaker, never
/// 0x351 missing 2.5 s, never "offline". Before this issue the fault, the lost
/// bridge and the stale link pushed the small pack to 109–223 % of its cutoff
/// with its BMS tripping again and again.
#[test]
fn uneven_packs_stay_within_their_own_cutoffs_whatever_happens() {
    // The uneven scenarios (after the six with packs alike) but the lossy
    // bus, which has a test of its own.
    for name in SCENARIOS.into_iter().skip(6).filter(|n| *n != "lossy-bus") {
        let (l, _) = run(name, 4, Protocol::Victron);
        let (charged, discharged) = BatteryFigures::energy_ah(&l.nodes);
        assert!(
            charged + discharged > 0.0 || name == "cold-start",
            "{name}: nothing moved"
        );
    }
}

/// A fault at many moments of a charge and of a discharge (the second
/// discharge fault 2 min after the first), with three and four packs.
#[test]
fn a_fault_at_any_moment_keeps_the_others_within_their_cutoffs() {
    for n in [3, 4] {
        for at_min in [20, 40, 60, 80, 100, 120] {
            let at = Some(at_min * MIN);
            let (l, end) =
                run_scenario_at("fault-charge", n, InverterConfig::default(), at, |_| {}).unwrap();
            let p = problems(&l, ChargeConfig::default().ceiling_margin_mv);
            assert!(
                p.is_empty(),
                "{n} packs, fault at {at_min} min: {p:#?}\n{}",
                table("fault-charge", &l, end)
            );
        }
        for at_min in [5, 10, 20, 30, 45] {
            let at = Some(at_min * MIN);
            let (l, end) =
                run_scenario_at("fault-discharge", n, InverterConfig::default(), at, |_| {})
                    .unwrap();
            let p = problems(&l, ChargeConfig::default().ceiling_margin_mv);
            assert!(
                p.is_empty(),
                "{n} packs, faults at {at_min} min: {p:#?}\n{}",
                table("fault-discharge", &l, end)
            );
        }
    }
}

/// A pack whose bridge is lost still conducts: it stays in the sums (counted
/// as unknown) with its last limits, and the battery is kept where it stays
/// within them; the owner sees it as lost.
#[test]
fn a_pack_without_data_stays_in_the_safety_sums() {
    let (l, _) = run("bridge-lost-charge", 4, Protocol::Victron);
    let speaker = l
        .nodes
        .iter()
        .find(|p| p.bridge_on && p.inverter().speaking())
        .unwrap();
    let (battery, _) = speaker.inverter().battery().unwrap();
    assert_eq!(
        (battery.online, battery.offline, battery.unknown),
        (3, 1, 1)
    );
    let view = speaker.inverter().battery_view(l.now()).unwrap();
    let lost = view.packs.iter().find(|p| p.node == 1).unwrap();
    assert_eq!(lost.part.name(), "lost");
    // The lost pack kept charging (its switch is closed), within its cutoff.
    let f = &l.nodes[0].figures;
    assert!(f.charged_ah > 5.0, "{}", f.charged_ah);
    assert!(f.highest_charge_a <= f.charge_cutoff_a);
}

/// A bus that loses 15 % of the frames at every receiver, doubles 2 %, delays
/// 5 %, reorders within a tick, leaves one receiver deaf for 10 s and carries
/// a ghost node: still one speaker, and it still charges — at least 75 % of
/// the charge a clean bus moves in the same time (before: 36 %).
#[test]
fn a_lossy_bus_still_charges() {
    let (clean, _) = run("uneven-charge", 4, Protocol::Victron);
    let (lossy, _) = run("lossy-bus", 4, Protocol::Victron);
    let (c, _) = BatteryFigures::energy_ah(&clean.nodes);
    let (x, _) = BatteryFigures::energy_ah(&lossy.nodes);
    println!(
        "clean bus {c:.1} Ah, lossy bus {x:.1} Ah ({:.0} %)",
        x / c * 100.0
    );
    assert!(x >= 0.75 * c, "lossy {x:.1} Ah against clean {c:.1} Ah");
    assert!(lossy.figures.lost_frames > 100_000);
    let refused = lossy
        .figures
        .reports
        .iter()
        .filter(|(_, _, r)| matches!(r, InverterReport::SummaryRefused(7, _)))
        .count();
    assert!(refused >= 1, "the ghost is refused and reported");
}

/// Adversarial: random packs (capacity, cutoffs, cable, cell resistance,
/// SOC), a random load and charger changing every few minutes, a random pack
/// faulting at a random moment, sometimes a lost bridge, sometimes a lossy
/// bus. Checked against the simulated truth: no pack past its own cutoffs and
/// no trip.
#[test]
fn random_packs_and_events_never_push_a_pack_past_its_own_cutoffs() {
    for case in 0..10u64 {
        let (l, log) = random_case(case, 1);
        let p = problems(&l, ChargeConfig::default().ceiling_margin_mv);
        assert!(
            p.is_empty(),
            "case {case}: {log}\n{p:#?}\n{}",
            table("random", &l, l.now())
        );
    }
}

/// The check above can fail: with every BMS telling its bridge current
/// cutoffs (317, 318) of twice what it trips at (so the bridges believe
/// there is room that is not there), the same cases push packs past their
/// cutoffs and the loop says so.
#[test]
fn the_truth_check_fails_when_the_bridges_are_misled() {
    let failing = (0..10u64)
        .filter(|case| {
            let (l, _) = random_case(*case, 2);
            problems(&l, ChargeConfig::default().ceiling_margin_mv)
                .iter()
                .any(|p| p.contains("past its cutoff") || p.contains("opened its switch"))
        })
        .count();
    assert!(
        failing >= 5,
        "only {failing} of 10 misled cases were caught"
    );
}

/// One random case of [`random_packs_and_events_never_push_a_pack_past_its_own_cutoffs`].
fn random_case(case: u64, told_cutoffs: u16) -> (MultiLoop, String) {
    let mut x = case.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    let n = 2 + (next() * 4.0) as usize;
    let soc = 20.0 + next() * 60.0;
    let specs: Vec<PackSpec> = (0..n)
        .map(|_| PackSpec {
            capacity_ah: 50.0 + next() * 250.0,
            charge_cutoff_a: 20 + (next() * 60.0) as u16,
            discharge_cutoff_a: 30 + (next() * 70.0) as u16,
            cable_ohm: 0.002 + next() * 0.045,
            cell_ohm: 0.0002 + next() * 0.0008,
            soc_pct: soc + next() * 10.0,
        })
        .collect();
    let mut l = MultiLoop::with_packs(InverterConfig::default(), &specs, 200.0, case + 1);
    for p in &mut l.nodes {
        // What the bridge reads; the truth checks keep the real cutoffs.
        for r in [317, 318] {
            let v = p.h.sim.register(r);
            p.h.sim.set_register(r, v * told_cutoffs);
        }
    }
    if next() < 0.3 {
        l.bus = BusFaults::lossy(0.1);
    }
    let fault_at = (3.0 + next() * 25.0) as u64 * MIN;
    let faulted = (next() * n as f64) as usize % n;
    let lost = (next() < 0.3).then(|| (next() * n as f64) as usize % n);
    let mut log = format!(
        "{n} packs {specs:?}, fault of pack {} at {} min, bridge lost {lost:?}",
        faulted + 1,
        fault_at / MIN
    );
    let mut t = 0;
    while t < 40 * MIN {
        // A new load and charger every 1 to 5 minutes: steps and ramps of
        // the total, charge and discharge.
        let discharge = next() < 0.5;
        l.model.load_a = if discharge { 5.0 + next() * 300.0 } else { 0.0 };
        l.model.charger_max_a = 10.0 + next() * 250.0;
        let _ = std::fmt::Write::write_fmt(
            &mut log,
            format_args!(
                ", {} min: load {:.0} A charger {:.0} A",
                t / MIN,
                l.model.load_a,
                l.model.charger_max_a
            ),
        );
        let until = (t + (1.0 + next() * 4.0) as u64 * MIN).min(40 * MIN);
        while t < until {
            t = (t + 10 * S).min(until);
            l.run_until(t);
            if t >= fault_at && t < fault_at + 10 * S {
                l.nodes[faulted]
                    .h
                    .sim
                    .inject_fault_event(EventId::ChargingOverCurrentCutoff);
                if let Some(k) = lost {
                    l.nodes[k].bridge_on = false;
                }
            }
            if t >= fault_at + 5 * MIN && t < fault_at + 5 * MIN + 10 * S {
                l.nodes[faulted].h.sim.clear_fault();
            }
        }
    }
    (l, log)
}
