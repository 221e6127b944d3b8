//! Several packs, one battery: the summary frames, the table of what was
//! heard, the election of one speaker and the battery's limits, through the
//! library's sans-IO interface.

use proptest::prelude::*;
use tinybms_firmware::inverter::control::{ChargeConfig, Conditions, Limits, PackState};
use tinybms_firmware::inverter::packs::{
    aggregate, aggregate_with, from_id, summary_id, Battery, BatteryLimits, Election, Member,
    Packs, Received, Shares, Summary, SummaryError, DEAF_GUARD_US, LISTEN_US, PACK_LOST_US,
    PARTIAL_MAX_US, SHARE_WINDOW, SPEAKER_LOST_US, SUMMARY_BASE_ID, SUMMARY_LAST_ID,
};

const S: u64 = 1_000_000;
const STALE: tinybms_firmware::freshness::Freshness =
    tinybms_firmware::freshness::Freshness::new(5 * S);

fn summary() -> Summary {
    Summary {
        voltage_cv: 5320,
        current_da: 123,
        soc_cpct: 6543,
        soh_pct: 98,
        min_cell_mv: 3301,
        max_cell_mv: 3320,
        min_temp_dc: 215,
        max_temp_dc: 248,
        age_ds: 3,
        capacity_dah: 2800,
        limits: Limits {
            cvl_dv: 552,
            ccl_da: 1000,
            dcl_da: 1500,
            discharge_dv: 480,
        },
        conditions: Conditions {
            high_voltage: 1,
            cell_imbalance: 2,
            ..Conditions::default()
        },
        fault: false,
        charge_blocked: false,
        speaking: true,
    }
}

fn arb_conditions() -> impl Strategy<Value = Conditions> {
    proptest::collection::vec(0u8..=2, 10).prop_map(|v| Conditions {
        high_voltage: v[0],
        low_voltage: v[1],
        high_temperature: v[2],
        low_temperature: v[3],
        high_temperature_charge: v[4],
        low_temperature_charge: v[5],
        high_discharge_current: v[6],
        high_charge_current: v[7],
        bms_internal: v[8],
        cell_imbalance: v[9],
    })
}

prop_compose! {
    /// A summary a TinyBMS can report: every field within its range, a pack
    /// voltage its cells can make.
    fn arb_summary()(
        v_frac in 0.0f64..=1.0, current_da in -10_000i16..=10_000, soc_cpct in 0u16..=10_000,
        soh_pct in 0u8..=100, cells in (0u16..=5000, 0u16..=5000),
        temps in (-550i16..=1500, -550i16..=1500), age_ds in any::<u8>(),
        capacity_dah in 0u16..=6550,
        l in (0u16..=800, 0u16..=7500, 0u16..=7500, 0u16..=800),
        conditions in arb_conditions(),
        flags in any::<[bool; 3]>(),
    ) -> Summary {
        let (lo, hi) = (cells.0.min(cells.1), cells.0.max(cells.1));
        let (lo_mv, hi_mv) = (4.0 * f64::from(lo), 16.0 * f64::from(hi));
        let voltage_cv = ((lo_mv + v_frac * (hi_mv - lo_mv)) / 10.0).floor().min(8000.0) as u16;
        Summary {
            voltage_cv, current_da, soc_cpct, soh_pct,
            min_cell_mv: lo, max_cell_mv: hi,
            min_temp_dc: temps.0.min(temps.1), max_temp_dc: temps.0.max(temps.1),
            age_ds, capacity_dah,
            limits: Limits { cvl_dv: l.0, ccl_da: l.1, dcl_da: l.2, discharge_dv: l.3 },
            conditions, fault: flags[0], charge_blocked: flags[1], speaking: flags[2],
        }
    }
}

prop_compose! {
    /// Any summary of the wire format's values, possible or not.
    fn arb_any_summary()(
        voltage_cv in any::<u16>(), current_da in any::<i16>(), soc_cpct in 0u16..=10_000,
        soh_pct in 0u8..=100, cells in (any::<u16>(), any::<u16>()),
        temps in (any::<i16>(), any::<i16>()), age_ds in any::<u8>(),
        capacity_dah in any::<u16>(), l in any::<[u16; 4]>(), conditions in arb_conditions(),
        flags in any::<[bool; 3]>(),
    ) -> Summary {
        Summary {
            voltage_cv, current_da, soc_cpct, soh_pct,
            min_cell_mv: cells.0.min(cells.1), max_cell_mv: cells.0.max(cells.1),
            min_temp_dc: temps.0.min(temps.1), max_temp_dc: temps.0.max(temps.1),
            age_ds, capacity_dah,
            limits: Limits { cvl_dv: l[0], ccl_da: l[1], dcl_da: l[2], discharge_dv: l[3] },
            conditions, fault: flags[0], charge_blocked: flags[1], speaking: flags[2],
        }
    }
}

/// Feeds frames; returns what the last one did.
fn feed(
    p: &mut Packs,
    now: u64,
    frames: &[tinybms_firmware::inverter::dialect::CanFrame],
) -> Received {
    let mut last = Received::NotSummary;
    for f in frames {
        last = p.on_frame(now, f.id, f.bytes());
    }
    last
}

#[test]
fn the_identifiers_are_the_documented_range_and_outside_the_inverter_protocols() {
    assert_eq!(SUMMARY_BASE_ID, 0x6A0);
    assert_eq!(SUMMARY_LAST_ID, 0x6BF);
    assert_eq!(summary_id(1, 0), Some(0x6A0));
    assert_eq!(summary_id(8, 3), Some(0x6BF));
    assert_eq!(summary_id(0, 0), None);
    assert_eq!(summary_id(9, 0), None);
    assert_eq!(summary_id(1, 4), None);
    for id in 0u16..0x800 {
        match from_id(id) {
            Some((n, k)) => assert_eq!(summary_id(n, k), Some(id)),
            None => assert!(!(SUMMARY_BASE_ID..=SUMMARY_LAST_ID).contains(&id)),
        }
    }
    // Every identifier either protocol sends or the GX sends.
    for id in [
        0x305, 0x307, 0x351, 0x355, 0x356, 0x359, 0x35A, 0x35B, 0x35C, 0x35E, 0x35F, 0x370, 0x371,
        0x372, 0x373, 0x374, 0x375, 0x376, 0x377, 0x378, 0x379, 0x380, 0x381, 0x382,
    ] {
        assert_eq!(from_id(id), None, "{id:#x}");
    }
}

#[test]
fn a_summary_is_taken_only_when_all_four_frames_of_one_sequence_arrived() {
    let mut p = Packs::new(1);
    let a = summary();
    let b = Summary {
        soc_cpct: 1234,
        current_da: -50,
        ..a
    };
    let fa = a.frames(2, 5).unwrap();
    let fb = b.frames(2, 6).unwrap();
    // Three of a, then the last of b: nothing complete.
    assert_eq!(feed(&mut p, 0, &fa[..3]), Received::Partial);
    assert_eq!(feed(&mut p, 0, &fb[3..]), Received::Partial);
    assert!(p.alive(0, 2).is_none());
    // The rest of b completes b, never a mixture.
    assert_eq!(feed(&mut p, 0, &fb[..3]), Received::Complete(2));
    assert_eq!(p.alive(0, 2), Some(&b));
    // Lost after PACK_LOST_US.
    assert!(p.alive(PACK_LOST_US, 2).is_some());
    assert!(p.alive(PACK_LOST_US + 1, 2).is_none());
}

#[test]
fn bad_summaries_are_refused_whole_and_counted() {
    let good = summary().frames(3, 1).unwrap();
    let cases: Vec<(usize, usize, u8, SummaryError)> = vec![
        (0, 5, 0x27, SummaryError::Soc),      // SOC 0x2700 + ... > 10000
        (0, 6, 101, SummaryError::Soc),       // SOH 101 %
        (1, 3, 0x00, SummaryError::Order),    // max cell below min
        (2, 6, 0b11, SummaryError::Reserved), // a condition of 3
        (1, 7, 0x11, SummaryError::Reserved), // a reserved nibble
        (0, 7, 0x81, SummaryError::Reserved), // a reserved flag
        (3, 7, 0xC1, SummaryError::Reserved), // condition bits 18-19 = 3
    ];
    for (k, byte, value, want) in cases {
        let mut p = Packs::new(1);
        let mut f = good;
        f[k].data[byte] = value;
        assert_eq!(
            feed(&mut p, 0, &f),
            Received::Refused(3, want),
            "{k} {byte} {value:#x}"
        );
        assert!(p.alive(0, 3).is_none());
        assert_eq!(p.refused(), 1);
    }
    // A short frame is refused and drops what was collected.
    let mut p = Packs::new(1);
    feed(&mut p, 0, &good[..2]);
    assert_eq!(
        p.on_frame(0, good[2].id, &good[2].data[..7]),
        Received::Refused(3, SummaryError::Length)
    );
    assert_eq!(feed(&mut p, 0, &good[2..]), Received::Partial);
    assert!(p.alive(0, 3).is_none());
    // Our own node number from another bridge: a whole summary is counted,
    // never taken.
    let mut p = Packs::new(3);
    assert_eq!(feed(&mut p, 0, &good), Received::DuplicateNode);
    assert_eq!(p.duplicates(), 1);
    assert!(p.alive(0, 3).is_none());
    // Issue 24: one stray frame on our own identifier is no duplicate.
    let mut p = Packs::new(3);
    assert_eq!(feed(&mut p, 0, &good[..1]), Received::Partial);
    assert_eq!(p.duplicates(), 0);
    // A lone bridge (node 0) hears nobody.
    let mut p = Packs::new(0);
    assert_eq!(feed(&mut p, 0, &good), Received::NotSummary);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, .. ProptestConfig::default() })]

    #[test]
    fn every_valid_summary_round_trips(s in arb_summary(), node in 1u8..=8, seq in 0u8..16) {
        let mut p = Packs::new(if node == 1 { 2 } else { 1 });
        let f = s.frames(node, seq).unwrap();
        prop_assert!(f.iter().all(|f| f.len == 8));
        prop_assert_eq!(feed(&mut p, 7, &f), Received::Complete(node));
        prop_assert_eq!(p.alive(7, node), Some(&s));
    }

    /// Issue 24: a summary no TinyBMS can send is refused, whatever field is
    /// impossible; a possible one is taken.
    #[test]
    fn an_impossible_summary_is_refused(s in arb_any_summary(), node in 1u8..=8) {
        let mut p = Packs::new(if node == 1 { 2 } else { 1 });
        let got = feed(&mut p, 7, &s.frames(node, 3).unwrap());
        if s.plausible() {
            prop_assert_eq!(got, Received::Complete(node));
        } else {
            prop_assert_eq!(got, Received::Refused(node, SummaryError::Range));
            prop_assert_eq!(p.alive(7, node), None);
        }
    }

    /// Frames of two summaries interleaved in any order, some dropped: what is
    /// taken is always one of the two whole, never a mixture.
    #[test]
    fn interleaved_and_dropped_frames_never_make_a_mixture(
        a in arb_summary(), b in arb_summary(), seq in 0u8..15,
        order in proptest::collection::vec(0usize..8, 0..40),
    ) {
        let fa = a.frames(5, seq).unwrap();
        let fb = b.frames(5, seq + 1).unwrap();
        let all: Vec<_> = fa.iter().chain(fb.iter()).copied().collect();
        let mut p = Packs::new(1);
        for i in order {
            let f = all[i];
            if let Received::Complete(_) = p.on_frame(0, f.id, f.bytes()) {
                let got = *p.alive(0, 5).unwrap();
                prop_assert!(got == a || got == b, "{got:?}");
            }
        }
    }

    #[test]
    fn any_bytes_on_the_summary_ids_never_panic(
        frames in proptest::collection::vec((SUMMARY_BASE_ID..=SUMMARY_LAST_ID, proptest::collection::vec(any::<u8>(), 0..9)), 0..64),
    ) {
        let mut p = Packs::new(4);
        for (i, (id, d)) in frames.iter().enumerate() {
            let _ = p.on_frame(i as u64, *id, d);
        }
        for (_, m) in p.known(64) {
            let s = m.summary;
            prop_assert!(s.soc_cpct <= 10_000 && s.min_cell_mv <= s.max_cell_mv);
        }
    }
}

/// Nodes on one bus: each sends its summary every second (the speaking flag
/// from its election), everyone hears everyone unless cut off.
struct Bus {
    nodes: Vec<(Packs, Election, bool)>, // table, election, on the bus
}

impl Bus {
    fn new(n: u8, start: u64) -> Self {
        Self {
            nodes: (1..=n)
                .map(|i| (Packs::new(i), Election::new(start), true))
                .collect(),
        }
    }

    /// One second at `now`: returns the speakers.
    fn second(&mut self, now: u64, seq: u8) -> Vec<u8> {
        let mut sent = Vec::new();
        for (i, (_, e, on)) in self.nodes.iter().enumerate() {
            if *on {
                let s = Summary {
                    speaking: e.speaking(),
                    ..summary()
                };
                sent.push(s.frames(i as u8 + 1, seq).unwrap());
            }
        }
        let mut speakers = Vec::new();
        for (i, (p, e, on)) in self.nodes.iter_mut().enumerate() {
            if !*on {
                continue;
            }
            for f in &sent {
                feed(p, now, f);
            }
            if e.update(now, p, true) {
                speakers.push(i as u8 + 1);
            }
        }
        speakers
    }
}

#[test]
fn one_speaker_the_lowest_node_and_a_deterministic_takeover() {
    let mut bus = Bus::new(3, 0);
    let mut log = Vec::new();
    for t in 0..80u64 {
        match t {
            10 => bus.nodes[0].2 = false, // the primary falls silent
            30 => {
                bus.nodes[0].2 = true; // and comes back (restarted)
                bus.nodes[0].0 = Packs::new(1);
                bus.nodes[0].1 = Election::new(t * S);
            }
            50 => bus.nodes[1].2 = false, // the speaker falls silent
            _ => {}
        }
        let speakers = bus.second(t * S, (t % 16) as u8);
        assert!(speakers.len() <= 1, "two speakers at {t} s: {speakers:?}");
        log.push(speakers.first().copied());
    }
    let first = |n: u8, from: usize| {
        log.iter()
            .skip(from)
            .position(|s| *s == Some(n))
            .map(|i| i + from)
    };
    // Node 1 speaks once it has listened.
    assert_eq!(first(1, 0), Some((LISTEN_US / S) as usize));
    // Node 2 takes over once node 1 is lost (its last summary at 9 s).
    // The first whole second past SPEAKER_LOST_US after node 1's last summary.
    let after = 9 + SPEAKER_LOST_US / S + 1;
    let takeover = first(2, 10).unwrap();
    assert_eq!(takeover as u64, after, "{log:?}");
    assert!(takeover as u64 - 9 < 3, "within the 3 s a GX waits");
    // Node 1 comes back, finds a speaker and stays quiet: no handover, no gap.
    assert!(log[takeover..50].iter().all(|s| *s == Some(2)), "{log:?}");
    // Node 2 falls silent: node 1 (the lowest heard) takes over, node 3 never.
    let after = (49 + SPEAKER_LOST_US / S + 1) as usize;
    assert_eq!(first(1, 50), Some(after));
    assert!(log[after..].iter().all(|s| *s == Some(1)));
    assert_eq!(first(3, 0), None);
}

#[test]
fn a_returning_node_waits_for_a_quiet_bus_and_two_speakers_resolve_at_once() {
    // Node 2 speaks; node 1 comes back: it stays quiet while node 2 speaks,
    // and starts only once node 2 is heard saying it stopped or is lost.
    let mut p1 = Packs::new(1);
    let mut e1 = Election::new(0);
    let speaking = Summary {
        speaking: true,
        ..summary()
    };
    let quiet = Summary {
        speaking: false,
        ..summary()
    };
    feed(&mut p1, 4 * S, &speaking.frames(2, 0).unwrap());
    assert!(!e1.update(4 * S, &p1, true), "a speaker is heard");
    feed(&mut p1, 5 * S, &quiet.frames(2, 1).unwrap());
    assert!(e1.update(5 * S, &p1, true));
    // A speaker that hears a higher node speaking goes on; one that hears a
    // lower speaker stops.
    feed(&mut p1, 6 * S, &speaking.frames(2, 2).unwrap());
    assert!(e1.update(6 * S, &p1, true));
    let mut p3 = Packs::new(3);
    let mut e3 = Election::new(0);
    assert!(e3.update(4 * S, &p3, true), "alone on the bus");
    feed(&mut p3, 6 * S, &speaking.frames(1, 0).unwrap());
    assert!(!e3.update(6 * S, &p3, true));
    // A bus-off recovery listens again.
    e1.restart(7 * S);
    feed(&mut p1, 7 * S, &quiet.frames(2, 3).unwrap());
    assert!(!e1.update(7 * S, &p1, true));
    assert!(!e1.update(7 * S + LISTEN_US - 1, &p1, true));
    assert!(e1.update(7 * S + LISTEN_US, &p1, true));
    // A lone bridge (node 0) never speaks for a battery.
    let p0 = Packs::new(0);
    assert!(!Election::new(0).update(10 * S, &p0, true));
}

fn member(s: Summary) -> Member {
    Member {
        summary: s,
        alive: true,
        heard_ago_us: 0,
        closed_limits: None,
    }
}

#[test]
fn the_battery_adds_up_its_packs() {
    let a = Summary {
        capacity_dah: 1000,
        soc_cpct: 8000,
        soh_pct: 100,
        current_da: 100,
        ..summary()
    };
    let b = Summary {
        capacity_dah: 3000,
        soc_cpct: 4000,
        soh_pct: 80,
        current_da: 300,
        min_cell_mv: 3290,
        max_cell_mv: 3350,
        min_temp_dc: 100,
        max_temp_dc: 300,
        limits: Limits {
            cvl_dv: 548,
            ccl_da: 800,
            dcl_da: 900,
            discharge_dv: 490,
        },
        conditions: Conditions {
            low_voltage: 2,
            ..Conditions::default()
        },
        ..summary()
    };
    let bat = aggregate(&[member(a), member(b)], STALE).unwrap();
    assert_eq!(bat.capacity_dah, 4000);
    assert_eq!(bat.state.soc_pct, 50.0); // (1000·80 + 3000·40) / 4000
    assert_eq!(bat.state.soh_pct, 85.0);
    assert_eq!(bat.state.current_a, 40.0);
    assert_eq!((bat.state.min_cell_mv, bat.state.max_cell_mv), (3290, 3350));
    assert_eq!((bat.state.min_temp_c, bat.state.max_temp_c), (10.0, 30.0));
    assert_eq!(bat.limits.cvl_dv, 548);
    assert_eq!(bat.limits.discharge_dv, 490);
    // Each limit counts 2 % less (usable): a 98 A, b 78.4 A.
    // CCL: present 40 A + the smallest headroom (b: 78.4 − 30 = 48.4 A) = 88.4 A;
    // but should a go, b takes all: 78.4 A × (40 − 10) / 30 = 78.4 A.
    assert_eq!(bat.limits.ccl_da, 784);
    // DCL while the battery charges: from 0 current, the smallest pack's
    // (88.2 A) — never a 0 computed from the charge current.
    assert_eq!(bat.limits.dcl_da, 882);
    assert_eq!(bat.conditions.low_voltage, 2);
    assert_eq!(bat.conditions.high_voltage, 1);
    assert_eq!(bat.conditions.cell_imbalance, 2);
    assert_eq!((bat.online, bat.offline), (2, 0));

    // A faulted pack, a silent one and a stale one leave the sums; each shows
    // as a warning.
    let faulted = member(Summary { fault: true, ..b });
    let silent = Member {
        alive: false,
        ..member(b)
    };
    let stale = member(Summary { age_ds: 51, ..b });
    for m in [faulted, silent, stale] {
        let bat = aggregate(&[member(a), m], STALE).unwrap();
        assert_eq!(bat.capacity_dah, 1000);
        assert_eq!(bat.state.soc_pct, 80.0);
        assert_eq!((bat.online, bat.offline), (1, 1));
        assert_eq!(bat.limits.cvl_dv, 552);
        assert_eq!(bat.conditions.bms_internal, 1, "a warning");
        assert_eq!(bat.conditions.low_voltage, 0, "b's alarm left with it");
    }
    assert_eq!(aggregate(&[silent, stale, faulted], STALE), None);
    assert_eq!(aggregate(&[], STALE), None);
}

#[test]
fn a_pack_past_its_limit_cuts_the_battery_at_once() {
    let a = Summary {
        current_da: 1100,
        ..summary()
    }; // 110 A against CCL 100 A
    let b = Summary {
        current_da: 300,
        ..summary()
    };
    let bat = aggregate(&[member(a), member(b)], STALE).unwrap();
    // (98 A usable of 100.) Headroom: 140 A − 2 × 12 A = 116 A; should b go,
    // a takes it all: 98 A × (140 − 30) / 110 = 98 A.
    assert_eq!(bat.limits.ccl_da, 980);
    // Four packs, one of them past its limit: 200 A + 4 × (98 − 110) = 152 A
    // by headroom; should one of the others go, all of its 30 A may go to a:
    // 200 − 30 + (98 − 110) = 158 A.
    let bat = aggregate(&[member(a), member(b), member(b), member(b)], STALE).unwrap();
    assert_eq!(bat.limits.ccl_da, 1520);
    // Never above the sum of the packs' limits, never below 0.
    let idle = aggregate(
        &[member(Summary {
            current_da: 0,
            ..summary()
        })],
        STALE,
    )
    .unwrap();
    assert_eq!(idle.limits.ccl_da, 980);
    let far = Summary {
        current_da: 3000,
        limits: Limits {
            ccl_da: 100,
            ..summary().limits
        },
        ..summary()
    };
    assert_eq!(
        aggregate(&[member(far), member(b)], STALE)
            .unwrap()
            .limits
            .ccl_da,
        0
    );
}

/// Packs in parallel on one bus voltage: V = (I + Σ G·OCV) / Σ G, I_k = G_k (V − OCV_k).
struct Parallel {
    ocv_v: Vec<f64>,
    r_ohm: Vec<f64>,
}

/// `v` without its element `j`.
fn without(v: &[f64], j: usize) -> Vec<f64> {
    v.iter()
        .enumerate()
        .filter(|(k, _)| *k != j)
        .map(|(_, x)| *x)
        .collect()
}

impl Parallel {
    /// The same packs without pack `j` (its switch open).
    fn without(&self, j: usize) -> Self {
        Self {
            ocv_v: without(&self.ocv_v, j),
            r_ohm: without(&self.r_ohm, j),
        }
    }

    fn split(&self, total_a: f64) -> Vec<f64> {
        let g: Vec<f64> = self.r_ohm.iter().map(|r| 1.0 / r).collect();
        let gs: f64 = g.iter().sum();
        let v = (total_a + g.iter().zip(&self.ocv_v).map(|(g, o)| g * o).sum::<f64>()) / gs;
        g.iter()
            .zip(&self.ocv_v)
            .map(|(g, o)| g * (v - o))
            .collect()
    }
}

fn pack_summary(current_a: f64, ccl_a: f64) -> Summary {
    Summary {
        current_da: (current_a * 10.0).round() as i16,
        limits: Limits {
            ccl_da: (ccl_a * 10.0) as u16,
            ..summary().limits
        },
        ..summary()
    }
}

/// The split rule in a loop: a charger delivering min(CCL, its maximum) into
/// packs of different voltages and resistances, the battery's CCL recomputed
/// every second from the measured currents (with the single pack's ramp).
/// No pack ever takes more than its own CCL.
#[test]
fn uneven_packs_in_parallel_are_never_pushed_past_their_own_limits() {
    let cases = [
        // one pack lower than three others (at rest it takes their current)
        (
            vec![52.6, 52.8, 52.8, 52.8],
            vec![0.010, 0.010, 0.010, 0.010],
            vec![50.0, 50.0, 50.0, 50.0],
        ),
        // equal voltages, one pack of a third of the resistance
        (
            vec![52.0, 52.0, 52.0],
            vec![0.004, 0.012, 0.012],
            vec![60.0, 60.0, 60.0],
        ),
        // a small pack with a small limit
        (vec![52.0, 52.1], vec![0.020, 0.008], vec![20.0, 100.0]),
    ];
    for (ocv, r, ccl) in cases {
        let model = Parallel {
            ocv_v: ocv.clone(),
            r_ohm: r.clone(),
        };
        let mut ramp = BatteryLimits::new();
        let c = ChargeConfig::default();
        let mut total = 0.0f64;
        let mut highest = vec![f64::MIN; ocv.len()];
        let mut last_ccl = 0.0;
        for t in 0..600u64 {
            let currents = model.split(total);
            for (h, i) in highest.iter_mut().zip(&currents) {
                *h = h.max(*i);
            }
            let members: Vec<Member> = currents
                .iter()
                .zip(&ccl)
                .map(|(i, l)| member(pack_summary(*i, *l)))
                .collect();
            let bat: Battery = aggregate(&members, STALE).unwrap();
            let lim = ramp.step(t * S, &bat, 0b1111, &c);
            last_ccl = f64::from(lim.ccl_da) / 10.0;
            total = last_ccl.min(400.0); // the charger obeys at once
        }
        for (k, (h, l)) in highest.iter().zip(&ccl).enumerate() {
            assert!(
                *h <= l + 0.15,
                "pack {k}: {h:.2} A against its CCL {l} A ({ocv:?} {r:?})"
            );
        }
        // Should any one pack open its switch at this total, the others stay
        // within their limits (its current shared out by physics) — and the
        // battery is not starved: one of them would be within 35 % of its
        // limit, or is now (nothing is learnt of the shares here: the bound
        // that needs no knowledge gives a pack all of a leaving pack's current).
        let currents = model.split(total);
        let mut edge = currents
            .iter()
            .zip(&ccl)
            .map(|(i, l)| (l - i) / l)
            .fold(f64::MAX, f64::min);
        for j in 0..ocv.len() {
            for (i, l) in model.without(j).split(total).iter().zip(&without(&ccl, j)) {
                assert!(
                    *i <= l + 0.5,
                    "without pack {j}: {i:.2} A against {l} A (CCL {last_ccl} A)"
                );
                edge = edge.min((l - i) / l);
            }
        }
        assert!(edge < 0.35, "CCL {last_ccl} A, currents {currents:?}");
    }
}

#[test]
fn a_pack_leaving_drops_the_limits_at_once_and_they_come_back_after_the_hold() {
    let c = ChargeConfig::default();
    let mut ramp = BatteryLimits::new();
    let idle = |ccl_a| member(pack_summary(0.0, ccl_a));
    let two = aggregate(&[idle(50.0), idle(50.0)], STALE).unwrap();
    let l = ramp.step(0, &two, 0b11, &c);
    assert_eq!(l.ccl_da, 490);
    // Both packs take 20 A and their own limits rose to 100 A: the target is
    // min(40 + 80, 100 × (40 − 20) / 20) = 100 A, reached at the ramp rate.
    let busy = aggregate(
        &[
            member(pack_summary(20.0, 100.0)),
            member(pack_summary(20.0, 100.0)),
        ],
        STALE,
    )
    .unwrap();
    let l = ramp.step(S, &busy, 0b11, &c);
    assert_eq!(l.ccl_da, 490 + c.ramp_rate_da_per_s);
    // Pack 2 is lost: at once its share goes.
    let one = aggregate(&[member(pack_summary(40.0, 50.0))], STALE).unwrap();
    let l = ramp.step(2 * S, &one, 0b01, &c);
    assert_eq!(l.ccl_da, 490, "40 A + 9 A headroom (49 A usable of 50)");
    // Then nothing rises for the hold, whatever the target.
    // (the pack's own CCL rose to 80 A meanwhile)
    let light = aggregate(&[member(pack_summary(10.0, 80.0))], STALE).unwrap();
    for t in 3..(2 + c.limit_hold_us / S) {
        let l = ramp.step(t * S, &light, 0b01, &c);
        assert_eq!(l.ccl_da, 490, "at {t} s");
    }
    let after = ramp.step(2 * S + c.limit_hold_us, &light, 0b01, &c);
    assert!(after.ccl_da > 490, "{after:?}");
    assert!(after.ccl_da <= 490 + c.ramp_rate_da_per_s);
    // A cut starts from 0.
    ramp.cut(100 * S);
    let l = ramp.step(101 * S, &light, 0b01, &c);
    assert_eq!(l.ccl_da, 0);
}

#[test]
fn the_own_summary_rounds_and_carries_the_conditions() {
    let p = PackState {
        min_cell_mv: 3300,
        max_cell_mv: 3310,
        pack_v: 52.916,
        current_a: -12.34,
        soc_pct: 55.555,
        soh_pct: 99.6,
        min_temp_c: -5.04,
        max_temp_c: 24.96,
        fault: false,
        charge_blocked: true,
        balancing: 0,
    };
    let cond = Conditions {
        high_voltage: 1,
        ..Conditions::default()
    };
    let s = Summary::own(&p, 1_250_000, &summary().limits, &cond, 28_000, false);
    assert_eq!(s.voltage_cv, 5292);
    assert_eq!(s.current_da, -123);
    assert_eq!(s.soc_cpct, 5556);
    assert_eq!(s.soh_pct, 100);
    assert_eq!((s.min_temp_dc, s.max_temp_dc), (-50, 250));
    assert_eq!(s.age_ds, 12);
    assert_eq!(s.capacity_dah, 2800);
    assert_eq!(s.conditions, cond);
    assert!(s.charge_blocked);
    let old = Summary::own(&p, 3_600 * S, &summary().limits, &cond, 28_000, false);
    assert_eq!(old.age_ds, 255);
}

mod through_the_inverter_output {
    use super::S;
    use host_tests::sim::{PackModel, SimBms, SimConfig};
    use protocol_core::response::RegisterBlock;
    use protocol_core::views::LiveSnapshot;
    use tinybms_firmware::inverter::control::PackSettings;
    use tinybms_firmware::inverter::dialect::{victron::ID_LIMITS, CanFrame};
    use tinybms_firmware::inverter::packs::from_id;
    use tinybms_firmware::inverter::{
        Inverter, InverterAction, InverterConfig, InverterReport, Protocol, TxResult,
    };

    fn inputs() -> (LiveSnapshot, PackSettings) {
        let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 1);
        let block = |first: u16, n: u16| RegisterBlock {
            start: first,
            values: (first..first + n).map(|a| sim.register(a)).collect(),
        };
        let snap = LiveSnapshot::from_registers(&block(0, 56)).unwrap();
        let settings = PackSettings::from_registers(&block(300, 44)).unwrap();
        (snap, settings)
    }

    /// Two bridges on a bus for `secs`, fed fresh snapshots until `fresh_until`;
    /// the frames each sent, with the time.
    fn two(protocol: Protocol, secs: u64, fresh_until: u64) -> [Vec<(u64, CanFrame)>; 2] {
        let (snap, settings) = inputs();
        let mut nodes: Vec<Inverter> = (1..=2)
            .map(|node| {
                Inverter::new(
                    InverterConfig {
                        protocol,
                        node,
                        ..InverterConfig::default()
                    },
                    0,
                )
            })
            .collect();
        let mut sent = [Vec::new(), Vec::new()];
        for t in 0..secs * 10 {
            let now = t * S / 10;
            let mut bus = Vec::new();
            for (k, inv) in nodes.iter_mut().enumerate() {
                if now <= fresh_until && t % 2 == 0 {
                    inv.on_snapshot(now, &snap, Some(settings), None);
                }
                while let InverterAction::Send(f) = inv.poll(now) {
                    inv.on_tx(now, TxResult::Sent);
                    bus.push((k, f));
                    sent[k].push((now, f));
                }
            }
            for (from, f) in &bus {
                let to = 1 - from;
                nodes[to].on_received(now, f.id, f.bytes());
            }
        }
        sent
    }

    /// Issue 42, item 11: a lone primary (pack_node 1, no other pack on the
    /// bus yet) logged "no pack takes part in the battery" at every start,
    /// before its own data was read. A bridge that never had a battery says
    /// nothing; one that had and lost it still says so.
    #[test]
    fn a_lone_primary_warns_of_nothing_at_its_start() {
        let (snap, settings) = inputs();
        let mut inv = Inverter::new(
            InverterConfig {
                node: 1,
                ..InverterConfig::default()
            },
            0,
        );
        let mut warnings = Vec::new();
        for t in 0..300u64 {
            let now = t * S / 10;
            // Its own data from 2 s on, until 20 s; then none (stale at 25 s).
            if (20..200).contains(&t) && t % 2 == 0 {
                inv.on_snapshot(now, &snap, Some(settings), None);
            }
            while let InverterAction::Send(_) = inv.poll(now) {
                inv.on_tx(now, TxResult::Sent);
            }
            while let Some(r) = inv.next_report() {
                if r.level() == tinybms_firmware::Level::Warn {
                    warnings.push((now, r));
                }
            }
        }
        let before_data: Vec<_> = warnings.iter().filter(|(t, _)| *t < 2 * S).collect();
        assert!(before_data.is_empty(), "{before_data:?}");
        assert!(
            warnings
                .iter()
                .any(|(_, r)| matches!(r, InverterReport::BatteryLost)),
            "a battery lost after it was there is still said: {warnings:?}"
        );
    }

    #[test]
    fn only_node_1_sends_the_inverter_frames_and_both_send_summaries() {
        let [a, b] = two(Protocol::Victron, 20, u64::MAX);
        assert!(a.iter().any(|(_, f)| f.id == ID_LIMITS));
        assert!(
            !b.iter().any(|(_, f)| from_id(f.id).is_none()),
            "node 2 only summarises"
        );
        for frames in [&a, &b] {
            let summaries = frames
                .iter()
                .filter(|(_, f)| from_id(f.id).is_some())
                .count();
            assert!((19 * 4..=21 * 4).contains(&summaries), "{summaries}");
        }
        // Not before node 1 has listened for 3 s.
        let first = a.iter().find(|(_, f)| f.id == ID_LIMITS).unwrap().0;
        assert!(first >= 3 * S, "{first}");
    }

    #[test]
    fn when_no_pack_takes_part_the_stop_is_said_as_each_inverter_needs() {
        // Fresh until 10 s, stale after 15 s (5 s stale age).
        let [victron, _] = two(Protocol::Victron, 30, 10 * S);
        let stale: Vec<_> = victron
            .iter()
            .filter(|(t, f)| *t > 16 * S && f.id == ID_LIMITS)
            .collect();
        // A GX stops on silence: the stop (CCL 0, DCL 0) a few periods, then
        // nothing.
        assert!(
            !stale.is_empty()
                && stale.len()
                    <= usize::from(tinybms_firmware::inverter::dialect::STOP_BEFORE_QUIET),
            "{}",
            stale.len()
        );
        for (_, f) in &stale {
            assert_eq!(&f.data[2..6], &[0, 0, 0, 0], "CCL 0 and DCL 0");
        }
        let last = stale.last().unwrap().0;
        assert!(last <= 23 * S, "limits sent on stale data at {last}");
        // A Sunny Island obeys the last limits: the stop every period.
        let [sma, _] = two(Protocol::SmaSunnyIsland, 30, 10 * S);
        let late: Vec<_> = sma
            .iter()
            .filter(|(t, f)| *t > 17 * S && f.id == ID_LIMITS)
            .collect();
        assert!(late.len() > 10, "{}", late.len());
        for (_, f) in late {
            assert_eq!(&f.data[2..6], &[0, 0, 0, 0], "CCL 0 and DCL 0");
        }
        // No measurement frames on stale data.
        assert!(!sma.iter().any(|(t, f)| *t > 17 * S && f.id == 0x356));
    }

    #[test]
    fn a_bridge_without_bms_data_never_speaks_and_the_other_does() {
        // Node 1 gets no snapshot at all: node 2 speaks, node 1 never.
        let (snap, settings) = inputs();
        let mut nodes: Vec<Inverter> = (1..=2)
            .map(|node| {
                Inverter::new(
                    InverterConfig {
                        node,
                        ..InverterConfig::default()
                    },
                    0,
                )
            })
            .collect();
        let mut limits_from = [0u32; 2];
        for t in 0..200u64 {
            let now = t * S / 10;
            let mut bus = Vec::new();
            for (k, inv) in nodes.iter_mut().enumerate() {
                if k == 1 && t % 2 == 0 {
                    inv.on_snapshot(now, &snap, Some(settings), None);
                }
                while let InverterAction::Send(f) = inv.poll(now) {
                    inv.on_tx(now, TxResult::Sent);
                    if f.id == ID_LIMITS {
                        limits_from[k] += 1;
                    }
                    bus.push((k, f));
                }
            }
            for (from, f) in &bus {
                nodes[1 - from].on_received(now, f.id, f.bytes());
            }
        }
        assert_eq!(limits_from[0], 0);
        assert!(limits_from[1] > 10, "{limits_from:?}");
    }

    #[test]
    fn a_bus_off_ends_speaking_and_the_battery_shown() {
        let (snap, settings) = inputs();
        let mut a = Inverter::new(
            InverterConfig {
                node: 1,
                ..InverterConfig::default()
            },
            0,
        );
        for t in 0..6u64 {
            a.on_snapshot(t * S, &snap, Some(settings), None);
            while let InverterAction::Send(_) = a.poll(t * S) {
                a.on_tx(t * S, TxResult::Sent);
            }
        }
        assert!(a.speaking());
        assert!(a.battery_view(6 * S).unwrap().battery.is_some());
        a.on_bus_off(6 * S);
        assert!(!a.speaking());
        let v = a.battery_view(6 * S).unwrap();
        assert!(!v.speaking && v.battery.is_none());
    }

    #[test]
    fn two_bridges_with_one_node_number_say_so_once() {
        let (snap, settings) = inputs();
        let config = InverterConfig {
            node: 3,
            ..InverterConfig::default()
        };
        let mut a = Inverter::new(config, 0);
        let mut b = Inverter::new(config, 0);
        for t in 0..5u64 {
            let now = t * S;
            a.on_snapshot(now, &snap, Some(settings), None);
            while let InverterAction::Send(f) = a.poll(now) {
                a.on_tx(now, TxResult::Sent);
                b.on_received(now, f.id, f.bytes());
            }
        }
        let mut dup = 0;
        while let Some(r) = b.next_report() {
            if r == InverterReport::DuplicateNode(3) {
                dup += 1;
            }
        }
        assert_eq!(dup, 1);
        // One per whole summary heard (5 s, one a second).
        assert_eq!(b.packs().duplicates(), 5);
        // b falls silent (and never speaks) until it restarts.
        for t in 5..10u64 {
            b.on_snapshot(t * S, &snap, Some(settings), None);
            while let InverterAction::Send(f) = b.poll(t * S) {
                b.on_tx(t * S, TxResult::Sent);
                assert!(from_id(f.id).is_none() && f.id != ID_LIMITS, "{:#x}", f.id);
            }
        }
        assert!(!b.speaking());
    }
}

mod what_review_found {
    use super::*;

    #[test]
    fn data_is_judged_by_its_age_now_and_the_top_of_the_field_is_never_fresh() {
        let s = Summary {
            age_ds: 30,
            ..summary()
        };
        let m = |ago| Member {
            summary: s,
            alive: true,
            heard_ago_us: ago,
            closed_limits: None,
        };
        assert!(
            m(S).takes_part(tinybms_firmware::freshness::Freshness::new(5 * S)),
            "3 s + 1 s"
        );
        assert!(
            !m(2_400_000).takes_part(tinybms_firmware::freshness::Freshness::new(5 * S)),
            "3 s + 2.4 s is past 5 s"
        );
        // 25.5 s or more: never fresh, whatever the stale age (up to 60 s).
        let old = Member::now(Summary {
            age_ds: 255,
            ..summary()
        });
        assert!(!old.takes_part(tinybms_firmware::freshness::Freshness::new(60 * S)));
        assert_eq!(old.data_age_us(), None);
    }

    #[test]
    fn a_battery_charging_still_offers_a_discharge_limit_and_the_other_way_round() {
        // 4 packs charging 34 A each, DCL 100 A each: the DCL is one pack's.
        let charging = member(Summary {
            current_da: 340,
            limits: Limits {
                dcl_da: 1000,
                ..summary().limits
            },
            ..summary()
        });
        let b = aggregate(&[charging; 4], STALE).unwrap();
        assert_eq!(b.limits.dcl_da, 980);
        // 2 packs discharging 50 A each, CCL 50 A each: the CCL is one pack's.
        let discharging = member(Summary {
            current_da: -500,
            limits: Limits {
                ccl_da: 500,
                ..summary().limits
            },
            ..summary()
        });
        let b = aggregate(&[discharging; 2], STALE).unwrap();
        assert_eq!(b.limits.ccl_da, 490);
    }

    #[test]
    fn a_faulted_pack_gone_silent_counts_with_what_it_takes_closed() {
        // Two packs charging 10 A each; a third, last heard with its switch
        // open (a fault: limits 0), has no fresh data now: it may have
        // closed, and takes at most its limits from before the fault.
        let charging = member(Summary {
            current_da: 100,
            ..summary()
        });
        let faulted = Summary {
            fault: true,
            age_ds: 200,
            current_da: 0,
            limits: Limits {
                ccl_da: 0,
                dcl_da: 0,
                ..summary().limits
            },
            ..summary()
        };
        let silent = Member {
            closed_limits: Some((400, 500)),
            ..member(faulted)
        };
        let b = aggregate(&[charging, charging, silent], STALE).unwrap();
        assert_eq!((b.online, b.offline, b.unknown), (2, 1, 1));
        // Never the 0 of its fault: the DCL is its closed 50 A (usable 49 A),
        // and the CCL is bounded by its closed 40 A beyond the others.
        assert_eq!(b.limits.dcl_da, 490, "{:?}", b.limits);
        assert!(b.limits.ccl_da > 0, "{:?}", b.limits);
        // Without its closed limits (never seen closed), its 0 still counts.
        let unknown_closed = member(faulted);
        let b = aggregate(&[charging, charging, unknown_closed], STALE).unwrap();
        assert_eq!(b.limits.dcl_da, 0);
    }

    #[test]
    fn a_bridge_that_sends_no_summary_never_speaks() {
        let p = Packs::new(1);
        let mut e = Election::new(0);
        assert!(!e.update(10 * S, &p, false));
        assert!(e.update(10 * S, &p, true));
        assert!(!e.update(11 * S, &p, false), "stops at once");
    }

    #[test]
    fn one_incomplete_summary_of_the_speaker_does_not_start_a_takeover() {
        let mut p = Packs::new(2);
        let mut e = Election::new(0);
        let speaking = Summary {
            speaking: true,
            ..summary()
        };
        feed(&mut p, 3 * S, &speaking.frames(1, 0).unwrap());
        assert!(!e.update(3 * S, &p, true));
        // Its next summary loses a frame; the one after too: its other frames
        // still say it is there.
        let f = speaking.frames(1, 1).unwrap();
        feed(&mut p, 4 * S, &f[..3]);
        let f = speaking.frames(1, 2).unwrap();
        feed(&mut p, 5 * S, &f[1..]);
        assert!(!e.update(5 * S + 500_000, &p, true));
        // Silent: the takeover.
        assert!(e.update(5 * S + SPEAKER_LOST_US + 1, &p, true));
    }

    #[test]
    fn frames_of_two_sends_with_one_sequence_never_make_a_summary() {
        let a = summary();
        let b = Summary {
            soc_cpct: 1111,
            current_da: -77,
            ..summary()
        };
        let fa = a.frames(3, 0).unwrap();
        let fb = b.frames(3, 0).unwrap();
        // A bridge restarts in the middle of a burst and sends seq 0 again,
        // losing a frame: 0, 1, 2 of a; then 0, 1, 3 of b.
        let mut p = Packs::new(1);
        feed(&mut p, 0, &fa[..3]);
        feed(&mut p, 1000, &[fb[0], fb[1], fb[3]]);
        assert!(p.alive(1000, 3).is_none(), "no mixture");
        // A summary incomplete for longer than a burst is dropped.
        let mut p = Packs::new(1);
        feed(&mut p, 0, &fa[..3]);
        assert_eq!(
            p.on_frame(PARTIAL_MAX_US + 1, fa[3].id, fa[3].bytes()),
            Received::Partial
        );
        assert!(p.alive(PARTIAL_MAX_US + 1, 3).is_none());
    }
}

/// Issue 24: the ghost of the report (a node nobody uses, limits of 6553.5 A,
/// a current of ±3276.7 A) is refused, reported once, and never raises the
/// battery's limits.
#[test]
fn a_ghost_node_with_impossible_values_is_refused_and_reported() {
    use tinybms_firmware::inverter::{Inverter, InverterConfig, InverterReport};
    let ghost = Summary {
        current_da: i16::MAX,
        limits: Limits {
            cvl_dv: 552,
            ccl_da: u16::MAX,
            dcl_da: u16::MAX,
            discharge_dv: 480,
        },
        ..summary()
    };
    assert!(!ghost.plausible());
    assert!(summary().plausible());
    let mut p = Packs::new(1);
    assert_eq!(
        feed(&mut p, 0, &ghost.frames(7, 1).unwrap()),
        Received::Refused(7, SummaryError::Range)
    );
    assert_eq!(p.alive(0, 7), None);
    // Through the inverter output: one report, however often it comes.
    let mut inv = Inverter::new(
        InverterConfig {
            node: 1,
            ..InverterConfig::default()
        },
        0,
    );
    for k in 0..5u64 {
        for f in ghost.frames(7, (k % 16) as u8).unwrap() {
            inv.on_received(k * S, f.id, f.bytes());
        }
    }
    let mut reports = Vec::new();
    while let Some(r) = inv.next_report() {
        reports.push(r);
    }
    let refused: Vec<_> = reports
        .iter()
        .filter(|r| matches!(r, InverterReport::SummaryRefused(7, SummaryError::Range)))
        .collect();
    assert_eq!(refused.len(), 1, "{reports:?}");
    let mut l = tinybms_firmware::text::Line::new();
    tinybms_firmware::text::inverter(refused[0], &mut l);
    assert_eq!(
        l.as_str(),
        "CAN: a summary of node 7 refused (a value no TinyBMS can report): it counts nowhere"
    );
    assert!(inv
        .battery_view(5 * S)
        .is_none_or(|v| v.packs.iter().all(|p| p.node != 7)));
}

/// Currents of packs in parallel at a total, with the true shares of a change.
fn shares_of(model: &Parallel) -> Vec<f64> {
    let g: Vec<f64> = model.r_ohm.iter().map(|r| 1.0 / r).collect();
    let gs: f64 = g.iter().sum();
    g.iter().map(|g| g / gs).collect()
}

fn sample(model: &Parallel, total_a: f64) -> Vec<(u8, i16)> {
    model
        .split(total_a)
        .iter()
        .enumerate()
        .map(|(k, i)| (k as u8 + 1, (i * 10.0).round() as i16))
        .collect()
}

/// Issue 24, item 1: the share of a change each pack takes is learnt from
/// how its current moves with the total — here a ramp with the packs'
/// open-circuit voltages apart, so a pack's share of the current now is not
/// its share of a change.
#[test]
fn the_shares_of_a_change_are_learnt_from_a_ramp() {
    let model = Parallel {
        ocv_v: vec![53.4, 52.9, 52.8],
        r_ohm: vec![0.008, 0.035, 0.045],
    };
    let truth = shares_of(&model);
    let mut sh = Shares::new();
    for t in 0..u64::from(SHARE_WINDOW) {
        assert!(sh.of(1).is_none(), "nothing before a whole window");
        sh.update(&sample(&model, 20.0 + 2.0 * t as f64), false);
    }
    for (k, a) in truth.iter().enumerate() {
        let got = f64::from(sh.of(k as u8 + 1).unwrap());
        assert!((got - a).abs() < 0.02, "pack {}: {got} against {a}", k + 1);
    }
    // Present shares (current over total) are far from it: the full pack
    // takes less now than its share of a change.
    let now = model.split(20.0 + 2.0 * 31.0);
    assert!(now[0] / now.iter().sum::<f64>() < truth[0] - 0.1, "{now:?}");
    // Kept through a long stretch at one current, and through a time when a
    // pack had no data; learning starts again when the packs change.
    for _ in 0..100 {
        sh.update(&sample(&model, 80.0), false);
    }
    sh.update(&[], true);
    assert!(sh.of(1).is_some());
    sh.update(&sample(&model, 80.0)[..2], false);
    assert!(sh.of(1).is_none());
}

/// A single step, or one sample in which some bridges had reported a change
/// and others not yet, or values no pack can have teach nothing.
#[test]
fn a_step_a_skewed_sample_or_nonsense_teaches_nothing() {
    let model = Parallel {
        ocv_v: vec![52.8, 52.8, 52.8],
        r_ohm: vec![0.008, 0.035, 0.045],
    };
    // A step from 0 to 40 A, the first bridge one sample ahead of the others.
    let mut sh = Shares::new();
    let before = sample(&model, 0.0);
    let after = sample(&model, 40.0);
    let skewed = vec![after[0], before[1], before[2]];
    sh.update(&before, false);
    sh.update(&skewed, false);
    for _ in 0..3 * SHARE_WINDOW {
        sh.update(&after, false);
        assert!(sh.of(1).is_none());
    }
    // Currents that do not follow the total (each wanders on its own).
    let mut sh = Shares::new();
    for t in 0..3 * i16::try_from(SHARE_WINDOW).unwrap() {
        let w = (t * 37 % 23) * 10;
        sh.update(&[(1, w), (2, 300 - w * 2), (3, t * 5)], false);
        assert!(sh.of(1).is_none(), "at {t}");
    }
}

/// The learnt rule against packs in parallel: random voltages, resistances
/// and limits; the charger delivers what the sun gives within the battery's
/// CCL, at once; the shares learnt from how the currents move. No pack past its limit now, nor when any one pack opens.
/// With the shares underestimated (half the truth, no margin) the same check
/// finds packs past their limits: it can fail.
static LEARNT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

#[test]
fn learnt_shares_keep_every_pack_within_its_limit_and_the_check_can_fail() {
    let run = |ocv: &[f64], r: &[f64], ccl: &[f64], lie: Option<f64>| -> Option<String> {
        let model = Parallel {
            ocv_v: ocv.to_vec(),
            r_ohm: r.to_vec(),
        };
        let truth = shares_of(&model);
        let mut ramp = BatteryLimits::new();
        let mut sh = Shares::new();
        let c = ChargeConfig::default();
        let mut total = 0.0f64;
        for t in 0..400u64 {
            let currents = model.split(total);
            let members: Vec<Member> = currents
                .iter()
                .zip(ccl)
                .map(|(i, l)| member(pack_summary(*i, *l)))
                .collect();
            sh.update(&sample(&model, total), false);
            if sh.of(1).is_some() {
                LEARNT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
            let shares: Vec<Option<f32>> = (0..ocv.len())
                .map(|k| match lie {
                    // Underestimated and turned back through the margin so
                    // that the rule uses half the true share.
                    Some(f) => Some(((truth[k] * f) as f32 - 0.05) / 1.25),
                    None => sh.of(k as u8 + 1),
                })
                .collect();
            let bat = aggregate_with(&members, STALE, &shares).unwrap();
            let lim = ramp.step(t * S, &bat, 0b1111, &c);
            // What the charger would deliver (the sun moving, loads coming
            // and going), within the battery's CCL.
            let demand = 100.0 + 95.0 * (t as f64 * std::f64::consts::TAU / 150.0).sin();
            total = (f64::from(lim.ccl_da) / 10.0).min(demand);
            for (k, (i, l)) in model.split(total).iter().zip(ccl).enumerate() {
                if *i > l + 0.3 {
                    return Some(format!("at {t} s pack {k}: {i:.1} A against {l} A"));
                }
            }
            for j in 0..ocv.len() {
                for (i, l) in model.without(j).split(total).iter().zip(&without(ccl, j)) {
                    if *i > l + 0.6 {
                        return Some(format!("at {t} s without pack {j}: {i:.1} A against {l} A"));
                    }
                }
            }
        }
        None
    };
    // Deterministic: the same cases on every run (SHARES_CASES=N for more).
    let cases = std::env::var("SHARES_CASES")
        .ok()
        .and_then(|c| c.parse().ok())
        .unwrap_or(48);
    let mut runner = proptest::test_runner::TestRunner::new_with_rng(
        ProptestConfig::with_cases(cases),
        proptest::test_runner::TestRng::deterministic_rng(
            proptest::test_runner::RngAlgorithm::ChaCha,
        ),
    );
    let packs = (2usize..=4).prop_flat_map(|n| {
        (
            proptest::collection::vec(52.6f64..53.2, n),
            proptest::collection::vec(0.004f64..0.05, n),
            proptest::collection::vec(20.0f64..90.0, n),
        )
    });
    runner
        .run(&packs, |(ocv, r, ccl)| {
            // Packs whose voltages are so far apart that they exchange more
            // than half a limit at rest (with all of them, or one gone) are
            // past what any battery limit can protect: physics, not the rule.
            let model = Parallel {
                ocv_v: ocv.clone(),
                r_ohm: r.clone(),
            };
            let calm = |m: &Parallel, l: &[f64]| {
                m.split(0.0).iter().zip(l).all(|(i, l)| i.abs() <= 0.5 * l)
            };
            prop_assume!(calm(&model, &ccl));
            for j in 0..ocv.len() {
                prop_assume!(calm(&model.without(j), &without(&ccl, j)));
            }
            let failure = run(&ocv, &r, &ccl, None);
            prop_assert!(failure.is_none(), "{failure:?} {ocv:?} {r:?} {ccl:?}");
            Ok(())
        })
        .unwrap();
    let learnt = LEARNT.load(std::sync::atomic::Ordering::Relaxed);
    assert!(
        learnt > cases as usize * 50,
        "the shares were learnt in {learnt} steps only"
    );
    // Sabotage: half the true shares.
    let caught = run(
        &[52.8, 52.8, 52.8],
        &[0.008, 0.035, 0.045],
        &[30.0, 50.0, 60.0],
        Some(0.5),
    );
    assert!(caught.is_some(), "half the shares went unnoticed");
}

/// Issue 24, lossy bus: a node that hears two or more others and then none
/// at all waits before it takes over (its own receiver is the likelier
/// cause); one that hears the speaker's inverter frames never takes over.
#[test]
fn a_deaf_receiver_or_lost_summaries_never_make_a_second_speaker() {
    let frames = |p: &mut Packs, node: u8, t: u64, speaking: bool| {
        let s = Summary {
            speaking,
            ..summary()
        };
        for f in s.frames(node, (t / S % 16) as u8).unwrap() {
            p.on_frame(t, f.id, f.bytes());
        }
    };
    // Node 3 hears nodes 1 (speaking) and 2, then nothing at all.
    let mut p = Packs::new(3);
    let mut e = Election::new(0);
    for t in 0..10 {
        frames(&mut p, 1, t * S, true);
        frames(&mut p, 2, t * S, false);
        assert!(!e.update(t * S, &p, true));
    }
    for t in 10..(10 + DEAF_GUARD_US / S) {
        assert!(!e.update(t * S, &p, true), "spoke while deaf at {t} s");
    }
    assert!(
        e.update(12 * S + DEAF_GUARD_US, &p, true),
        "takes over after the guard"
    );
    // Node 2 loses every summary of the speaker but hears its 0x351.
    let mut p = Packs::new(2);
    let mut e = Election::new(0);
    for t in 0..5 {
        frames(&mut p, 1, t * S, true);
        assert!(!e.update(t * S, &p, true));
    }
    for t in 5..60 {
        let limits = tinybms_firmware::inverter::dialect::victron::ID_LIMITS;
        p.on_frame(t * S, limits, &[0; 8]);
        assert!(!e.update(t * S, &p, true), "took over at {t} s");
    }
    // And when the speaker is really gone (one other node): at once.
    assert!(e.update(60 * S + SPEAKER_LOST_US + 1, &p, true));
}
