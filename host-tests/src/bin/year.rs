//! `year`: a simulated year of end-of-charge control per seed, the policy
//! before it and today's side by side, behind four inverters (see
//! `host_tests::year`). Prints one row per run; `docs/performance.md` keeps
//! the figures.
//!
//! ```text
//! year [--days N] [--seeds 1,2,3] [--inverters obeys,exporter,overshoot-20%,ignores-0A]
//! ```

use host_tests::year::{self, InverterKind, Policy};

fn main() {
    let mut days = 365u64;
    let mut seeds = vec![1u64, 2, 3];
    let mut kinds = InverterKind::ALL.to_vec();
    let mut args = std::env::args().skip(1);
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
