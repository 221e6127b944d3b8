//! The bridge's configuration in the closed loop (bridge, inverter output and
//! an inverter/charger model against the simulated pack, virtual time): a charge
//! cap set at run time over the host link bounds every CCL sent from then on,
//! and a protocol switch takes effect after a restart — the record kept in
//! flash across it.

use host_tests::closed_loop::ClosedLoop;
use host_tests::sim::PackModel;
use serde_json::{json, Value};
use tinybms_desk::flash::RamFlash;
use tinybms_firmware::inverter::dialect::victron as frames;
use tinybms_firmware::inverter::Protocol;

const S: u64 = 1_000_000;
const MIN: u64 = 60 * S;

fn lines_of<'a>(l: &'a ClosedLoop, ty: &str) -> Vec<&'a Value> {
    l.host
        .as_ref()
        .unwrap()
        .lines
        .iter()
        .filter(|v| v["type"] == ty)
        .collect()
}

fn charging_loop(flash: RamFlash) -> ClosedLoop {
    let mut l = ClosedLoop::from_flash(PackModel::LiFePO4_16S, 3, flash, 100.0);
    l.h.sim.set_soc_percent(30.0);
    l
}

#[test]
fn a_charge_cap_set_at_run_time_bounds_every_ccl_sent_after_it() {
    let mut l = charging_loop(RamFlash::new());
    l.run_until(5 * MIN);
    let before = l.sent_limits.iter().map(|x| x.2).max().unwrap();
    assert!(
        before > 300,
        "the loop charged at {before} dA before the cap"
    );
    let at = l.h.now;
    l.host_line(
        &json!({"cmd":"set_config","req":1,"fields":{"charge_current_cap":"30 A"}}).to_string(),
    );
    l.run_until(15 * MIN);
    let o = lines_of(&l, "config_outcome");
    assert_eq!(o[0]["outcome"], "applied", "{o:?}");
    assert_eq!(lines_of(&l, "config_done")[0]["saved"], true);
    // Every limits frame after the change obeys the cap; the next one already.
    let after: Vec<_> = l.sent_limits.iter().filter(|x| x.0 > at).collect();
    assert!(after.len() > 500, "{}", after.len());
    for &&(t, _, ccl, _) in &after {
        assert!(ccl <= 300, "CCL {ccl} dA at {t} µs, after a 30 A cap");
    }
    assert!(
        after[0].0 <= at + 2 * S,
        "first frame {} µs after",
        after[0].0 - at
    );
    // And the charger followed: the pack current stayed at the cap or below.
    let i = l.model.current_a;
    assert!(i <= 30.0 + 1e-6, "charger at {i} A");
    println!(
        "cap 30 A set at {} s: CCL before up to {} dA, {} frames after it, at most {} dA",
        at / S,
        before,
        after.len(),
        after.iter().map(|x| x.2).max().unwrap()
    );
}

fn ids(l: &ClosedLoop, since_us: u64) -> std::collections::BTreeSet<u16> {
    l.ids_since(since_us)
}

#[test]
fn a_protocol_switch_applies_after_a_restart_and_survives_it() {
    let flash = RamFlash::new();
    let mut l = charging_loop(flash.clone());
    l.run_until(2 * MIN);
    l.host_line(
        &json!({"cmd":"set_config","req":2,"fields":{"inverter_protocol":"sma"}}).to_string(),
    );
    let switch_at = l.h.now;
    l.run_until(4 * MIN);
    let o = lines_of(&l, "config_outcome");
    assert_eq!(o[0]["outcome"], "at_restart", "{o:?}");
    assert_eq!(lines_of(&l, "config_done")[0]["restart_needed"], 1);
    // Still Victron until the restart: its module and cell frames go on.
    let victron = ids(&l, switch_at);
    assert!(victron.contains(&frames::ID_MODULES), "{victron:?}");
    assert!(victron.contains(&frames::ID_CELL_EXTREMES));
    // Restart: a new bridge on the same flash.
    let mut l2 = charging_loop(flash.copy());
    assert_eq!(l2.inverter().config().protocol, Protocol::SmaSunnyIsland);
    l2.run_until(2 * MIN);
    let sma = ids(&l2, 0);
    assert!(
        sma.contains(&frames::ID_LIMITS) && sma.contains(&frames::ID_SOC),
        "{sma:?}"
    );
    assert!(!sma.contains(&frames::ID_MODULES), "{sma:?}");
    assert!(!sma.contains(&frames::ID_CELL_EXTREMES));
    // The charger still obeys it (0x351 is common to both).
    assert!(l2
        .sent_limits
        .iter()
        .all(|x| x.2 <= l2.h.sim.register(318) * 10));
}
