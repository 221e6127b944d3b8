//! The capacity estimate (issue 55, `tinybms_firmware::history::capacity`)
//! over a simulated year (`host_tests::year::run_capacity`): cells that fade
//! about 3 % a year, deep spells that take the pack down to its knee, the
//! firmware's day book and estimator fed with what the simulated BMS
//! reports. The figures per seed: `year --capacity`, docs/performance.md.

use host_tests::year;

/// Every run's estimate and every reported capacity of seeds 1-3 over a
/// year within 5 % of the weakest cell's capacity then.
#[test]
fn a_year_of_estimates_stays_within_five_percent_of_the_truth() {
    eprintln!("{}", year::capacity_header());
    for seed in 1..=3 {
        let started = std::time::Instant::now();
        let f = year::run_capacity(seed, 365, true);
        eprintln!(
            "{}  ({:.1} s)",
            year::capacity_row(seed, &f),
            started.elapsed().as_secs_f64()
        );
        assert!(f.points.len() >= 5, "seed {seed}: {} runs", f.points.len());
        for p in &f.points {
            assert!(
                p.error_pct().abs() <= 5.0 && p.median_error_pct().abs() <= 5.0,
                "seed {seed} day {}: {} cAh ({:+.2} %), reported {} cAh ({:+.2} %), truth {:.2} Ah",
                p.day,
                p.estimate.cah,
                p.error_pct(),
                p.median.cah,
                p.median_error_pct(),
                p.truth_ah
            );
        }
        // The fade is seen: the truth fell, and the last estimate is below
        // the first run's truth.
        assert!(f.truth_ah.1 < f.truth_ah.0 * 0.985, "{:?}", f.truth_ah);
        assert!(f.last.is_some());
        // Every day closed, and came back from its bytes unchanged.
        assert!(
            f.records.0 >= 364 && f.records.1 == f.records.0,
            "{:?}",
            f.records
        );
    }
}

/// Without deep days the pack never reaches its knee: no run qualifies, and
/// the capacity is unknown (not guessed).
#[test]
fn without_a_qualifying_cycle_the_capacity_is_unknown() {
    let f = year::run_capacity(1, 30, false);
    assert_eq!(f.knee_crossings, 0);
    assert!(f.points.is_empty());
    assert_eq!(f.last, None);
    assert!(f.full_charges > 10, "{}", f.full_charges);
}
