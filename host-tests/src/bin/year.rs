//! `year`: a simulated year of end-of-charge control per seed, the policy
//! before it and today's side by side, behind four inverters (see
//! `host_tests::year`). Prints one row per run; `docs/performance.md` keeps
//! the figures.
//!
//! ```text
//! year [--days N] [--seeds 1,2,3] [--inverters obeys,exporter,overshoot-20%,ignores-0A]
//! year --capacity [--points] [--days N] [--seeds 1,2,3]
//! ```
//!
//! `--capacity`: the capacity measure instead (`host_tests::year::run_capacity`):
//! per seed, the deep days, the knee crossings, the full charges, the runs that
//! qualified, the worst and mean error of their estimates against the weakest
//! cell's capacity then, the capacity reported at the end, the truth at the start
//! and at the last estimate, the day records that came back from their bytes;
//! `--points` adds each estimate.

use host_tests::year::{self, InverterKind, Policy};

fn main() {
    let mut days = 365u64;
    let mut seeds = vec![1u64, 2, 3];
    let mut kinds = InverterKind::ALL.to_vec();
    let capacity = std::env::args().any(|a| a == "--capacity");
    let points = std::env::args().any(|a| a == "--points");
    let mut args = std::env::args()
        .skip(1)
        .filter(|a| a != "--capacity" && a != "--points");
    while let Some(a) = args.next() {
        let v = args.next().unwrap_or_default();
        match a.as_str() {
            "--days" => days = v.parse().unwrap_or(days),
            "--seeds" => seeds = v.split(',').filter_map(|s| s.parse().ok()).collect(),
            "--inverters" => {
                kinds = InverterKind::ALL
                    .into_iter()
                    .filter(|k| v.split(',').any(|n| n == k.name()))
                    .collect()
            }
            _ => {
                eprintln!("usage: year [--days N] [--seeds 1,2,3] [--inverters obeys,exporter,overshoot-20%,ignores-0A]");
                std::process::exit(2);
            }
        }
    }
    if capacity {
        println!(
            "{days} days, cells fading {} %/year (±30 % per cell), deep spells; estimates against the weakest cell's capacity",
            year::FADE_PER_YEAR * 100.0
        );
        println!("{}", year::capacity_header());
        for &seed in &seeds {
            let started = std::time::Instant::now();
            let f = year::run_capacity(seed, days, true);
            println!(
                "{}  ({:.1} s)",
                year::capacity_row(seed, &f),
                started.elapsed().as_secs_f64()
            );
            if points {
                for p in &f.points {
                    println!(
                        "     day {:>3}: run {:>7.2} Ah ±{:>4.1}% ({:>+6.2}%), reported {:>7.2} Ah ({:>+6.2}%), truth {:>7.2} Ah, usable from full {:>7.2} Ah",
                        p.day,
                        f64::from(p.estimate.cah) / 100.0,
                        f64::from(p.estimate.uncertainty_permille) / 10.0,
                        p.error_pct(),
                        f64::from(p.median.cah) / 100.0,
                        p.median_error_pct(),
                        p.truth_ah,
                        p.usable_ah
                    );
                }
            }
        }
        return;
    }
    let limit = year::settings().allowed_disbalance_mv;
    println!(
        "{days} days, one cell {} % of charge ahead at the start (the first charge ends at least {} mV apart); spreads after day 30; sunFl = sunny days that reached float",
        year::START_LEAD_PCT,
        year::START_IMBALANCE_MV
    );
    println!("{}", year::header());
    for kind in kinds {
        for policy in [Policy::Before, Policy::Now, Policy::Ceiling90] {
            for &seed in &seeds {
                let started = std::time::Instant::now();
                let f = year::run(seed, days, policy.config(), kind);
                let label = format!("{} / {} / {seed}", policy.name(), kind.name());
                println!(
                    "{}  ({:.1} s)",
                    year::row(&label, &f, 30, limit),
                    started.elapsed().as_secs_f64()
                );
            }
        }
    }
}
