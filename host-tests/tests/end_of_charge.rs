//! End-of-charge control (issue 53): each rule of
//! `tinybms_firmware::inverter::finish` on charge control itself, and a
//! shortened simulated year (`host_tests::year`; the full year is the `year`
//! report, its figures in docs/performance.md).

use host_tests::year::{self, InverterKind, Policy};
use tinybms_firmware::inverter::control::{ChargeConfig, ChargeControl, PackState, Phase};
use tinybms_firmware::inverter::finish::{Stage, DAY_US};

const S: u64 = 1_000_000;

/// A 16-cell pack at `max`/`min` mV, `current` A, SOC `soc`, balancing `bits`.
fn pack(min: u16, max: u16, current: f32, soc: f32, bits: u16) -> PackState {
    PackState {
        min_cell_mv: min,
        max_cell_mv: max,
        pack_v: (u32::from(min) + u32::from(max)) as f32 * 8.0 / 1000.0,
        current_a: current,
        soc_pct: soc,
        soh_pct: 100.0,
        min_temp_c: 25.0,
        max_temp_c: 25.0,
        fault: false,
        charge_blocked: false,
        balancing: bits,
    }
}

/// Runs `c` at the absorption target (3550 mV), tapered, for `secs` s from `from`;
/// returns the time after.
fn at_target(c: &mut ChargeControl, from: u64, secs: u64, spread: u16, bits: u16) -> u64 {
    let s = year::settings();
    let mut t = from;
    for _ in 0..secs {
        c.update(t, &s, &pack(3550 - spread, 3550, 2.0, 99.5, bits));
        t += S;
    }
    t
}

#[test]
fn absorption_is_held_while_the_bms_balances_and_never_longer_than_its_bound() {
    let mut c = ChargeControl::new(ChargeConfig::default());
    // Cells 3 and 7 balancing, spread 24 mV (308 = 15): held past full_hold.
    let t = at_target(&mut c, 0, 600, 24, (1 << 2) | (1 << 6));
    assert_eq!(c.phase(), Phase::Absorption);
    let Stage::BalanceHeld { spread_mv, .. } = c.stage() else {
        panic!("{:?}", c.stage())
    };
    assert_eq!(spread_mv, 24);
    assert!(c
        .stage()
        .text()
        .as_str()
        .starts_with("absorption held: cells 3 and 7 balancing, spread 24 mV"));
    // Bounded: float once balance_hold (60 min) is over, balancing or not.
    let t = at_target(&mut c, t, 3600, 24, 1 << 2);
    assert_eq!(c.phase(), Phase::Float, "{:?}", c.stage());
    // The spread within 308: no hold at all.
    let mut c = ChargeControl::new(ChargeConfig::default());
    at_target(&mut c, t, 200, 12, 1 << 2);
    assert_eq!(c.phase(), Phase::Float);
    // Nothing balancing: no hold either.
    let mut c = ChargeControl::new(ChargeConfig::default());
    at_target(&mut c, t, 200, 40, 0);
    assert_eq!(c.phase(), Phase::Float);
    // 0 = never held.
    let mut c = ChargeControl::new(ChargeConfig {
        balance_hold_us: 0,
        ..ChargeConfig::default()
    });
    at_target(&mut c, t, 200, 40, 1);
    assert_eq!(c.phase(), Phase::Float);
}

#[test]
fn a_full_charge_comes_every_n_days_and_the_ceiling_waits_for_it() {
    let s = year::settings();
    let config = ChargeConfig {
        soc_ceiling_pct: 80,
        full_charge_days: 7,
        ..ChargeConfig::default()
    };
    let mut c = ChargeControl::new(config);
    // At boot a full charge is due: the ceiling waits.
    let (l, _) = c.update(0, &s, &pack(3330, 3335, 20.0, 85.0, 0));
    assert!(l.ccl_da > 0, "{l:?}");
    assert_eq!(c.stage(), Stage::Bulk { full_due: true });
    // The full charge done (float), the pack used down below rebulk: the
    // ceiling now pauses the charge at 80 %.
    let t = at_target(&mut c, S, 300, 5, 0);
    assert_eq!(c.phase(), Phase::Float);
    let mut t = t;
    c.update(t, &s, &pack(3300, 3305, -10.0, 70.0, 0));
    assert_eq!(c.phase(), Phase::Absorption);
    t += 60 * S;
    let (l, _) = c.update(t, &s, &pack(3330, 3335, 20.0, 81.0, 0));
    assert_eq!(l.ccl_da, 0, "paused at the ceiling");
    assert_eq!(c.stage(), Stage::Ceiling { ceiling_pct: 80 });
    assert!(c.stage().text().as_str().contains("SOC ceiling (80 %)"));
    // Seven days after the last full charge: due, the ceiling set aside.
    t = 8 * DAY_US;
    let mut ccl = 0;
    for k in 0..120 {
        ccl = c
            .update(t + k * S, &s, &pack(3330, 3335, 20.0, 81.0, 0))
            .0
            .ccl_da;
    }
    assert!(ccl > 0);
    assert_eq!(c.stage(), Stage::Bulk { full_due: true });
    // A float lasting the N days ends for the full charge.
    let mut c = ChargeControl::new(ChargeConfig::default());
    let t = at_target(&mut c, 0, 300, 5, 0);
    assert_eq!(c.phase(), Phase::Float);
    c.update(t + 6 * DAY_US, &s, &pack(3400, 3405, 0.0, 99.0, 0));
    assert_eq!(c.phase(), Phase::Float);
    c.update(t + 7 * DAY_US, &s, &pack(3400, 3405, 0.0, 99.0, 0));
    assert_eq!(c.phase(), Phase::Absorption);
}

#[test]
fn the_step_into_float_is_bounded_and_never_below_the_pack_at_rest() {
    let s = year::settings();
    let mut c = ChargeControl::new(ChargeConfig::default());
    let t = at_target(&mut c, 0, 300, 5, 0);
    assert_eq!(c.phase(), Phase::Float);
    // The pack at rest at 55.0 V: CVL from 56.8 V down at most 16 × 5 mV a
    // minute, never below 55.0 V, never up.
    let mut last = 568u16;
    let mut seen = Vec::new();
    for k in 0..3600u64 {
        let p = PackState {
            pack_v: 55.0,
            ..pack(3430, 3445, 0.0, 99.0, 0)
        };
        let (l, _) = c.update(t + k * S, &s, &p);
        assert!(l.cvl_dv <= last, "CVL rose: {} after {last}", l.cvl_dv);
        assert!(l.cvl_dv >= 550, "below the pack's 55.0 V: {}", l.cvl_dv);
        if k >= 60 {
            // 60 s: at most 80 mV (+0.1 V of rounding) below where it was.
            let minute_ago = seen[(k - 60) as usize];
            assert!(minute_ago - l.cvl_dv <= 1, "{minute_ago} → {}", l.cvl_dv);
        }
        seen.push(l.cvl_dv);
        last = l.cvl_dv;
    }
    assert_eq!(last, 550);
    assert!(matches!(c.stage(), Stage::StepDown { cvl_dv: 550, .. }));
    // Discharging: no step at all.
    let (l, _) = c.update(t + 3601 * S, &s, &pack(3300, 3310, -20.0, 98.0, 0));
    assert_eq!(l.cvl_dv, 550);
    // 0 = at once (the policy before).
    let mut c = ChargeControl::new(ChargeConfig {
        float_step_mv_per_min: 0,
        ..ChargeConfig::default()
    });
    let t = at_target(&mut c, 0, 300, 5, 0);
    let (l, _) = c.update(t, &s, &pack(3430, 3445, 0.0, 99.0, 0));
    assert_eq!(l.cvl_dv, 532, "float 16 × 3328 mV at once");
    assert_eq!(c.stage(), Stage::Float);
}

/// 75 days (the first 30 left out of the spreads), seed 1: the policy before
/// and today's, behind each inverter, and with an SOC ceiling of 90 %. The
/// full year: `year`.
#[test]
fn seventy_five_days_balance_the_pack_and_no_cell_passes_its_cutoff() {
    let days = 75;
    let s = year::settings();
    let before = year::run(1, days, Policy::Before.config(), InverterKind::Obeys);
    let now = year::run(1, days, Policy::Now.config(), InverterKind::Obeys);
    // The start: at least the 80 mV apart at the end of the first charge.
    for f in [&before, &now] {
        let first = f.end_spreads.first().map(|d| d.1).unwrap_or(0);
        assert!(first >= year::START_IMBALANCE_MV, "{first} mV");
    }
    eprintln!("{}", year::header());
    eprintln!("{}", year::row("before / obeys", &before, 30, 15));
    eprintln!("{}", year::row("end-of-charge / obeys", &now, 30, 15));
    assert!(
        now.within_pct(30, s.allowed_disbalance_mv) >= 90.0,
        "{}",
        year::row("now", &now, 30, 15)
    );
    assert!(
        before.within_pct(30, s.allowed_disbalance_mv) < 50.0,
        "the policy before does not balance: the measure can tell"
    );
    assert!(now.sunny_float_pct() >= 95.0);
    // No cell at its cutoff behind any inverter, also with an SOC ceiling
    // (the charge limit 0 every day: what an inverter ignoring 0 A ignores).
    for kind in InverterKind::ALL {
        let c = year::run(1, days, Policy::Ceiling90.config(), kind);
        eprintln!(
            "{}",
            year::row(&format!("ceiling / {}", kind.name()), &c, 30, 15)
        );
        assert!(
            c.max_cell_mv < s.ov_cutoff_mv,
            "{}: {} mV",
            kind.name(),
            c.max_cell_mv
        );
        let f = year::run(1, days, Policy::Now.config(), kind);
        eprintln!("{}", year::row(kind.name(), &f, 30, 15));
        assert!(
            f.max_cell_mv < s.ov_cutoff_mv,
            "{}: {} mV",
            kind.name(),
            f.max_cell_mv
        );
        if kind == InverterKind::Exporter {
            let b = year::run(1, days, Policy::Before.config(), kind);
            assert!(b.exported_wh > 10_000.0, "before: {}", b.exported_wh);
            assert!(f.exported_wh < 10.0, "the step: {}", f.exported_wh);
        }
    }
}
