//! The multi-pack scenarios (`sim --packs N --scenario NAME`): each one's
//! packs, bus and event, run to its end; what broke a rule; the figures.

use super::*;

/// Scenario names of the multi-pack loop (`sim --packs N --scenario NAME`).
/// The first six with packs alike; the others with [`PackSpec::uneven`]
/// packs, pack 1 the small one on the short cable (the one that takes the
/// most when another leaves).
pub const SCENARIOS: [&str; 16] = [
    "full-charge",
    "joined",
    "pack-fault",
    "uart-lost",
    "primary-lost",
    "bus-off",
    "uneven-charge",
    "uneven-discharge",
    "fault-charge",
    "fault-discharge",
    "bridge-lost-charge",
    "bridge-lost-discharge",
    "stale-charge",
    "stale-discharge",
    "cold-start",
    "lossy-bus",
];

/// Runs one multi-pack scenario with `n` packs (2..=8; see [`SCENARIOS`]) to
/// its end; the loop and its duration, µs. `None` for an unknown name.
pub fn run_scenario(
    name: &str,
    n: usize,
    inverter: InverterConfig,
    on_start: impl FnMut(&mut MultiLoop),
) -> Option<(MultiLoop, u64)> {
    run_scenario_at(name, n, inverter, None, on_start)
}

/// [`run_scenario`] with the moment of its event (the fault, the lost
/// bridge, the stale link) at `event_us` instead of the scenario's own.
pub fn run_scenario_at(
    name: &str,
    n: usize,
    inverter: InverterConfig,
    event_us: Option<u64>,
    mut on_start: impl FnMut(&mut MultiLoop),
) -> Option<(MultiLoop, u64)> {
    const S: u64 = 1_000_000;
    const MIN: u64 = 60 * S;
    const H: u64 = 3600 * S;
    let n = n.clamp(2, 8);
    let alike = |soc: &dyn Fn(usize) -> f64| PackSpec::alike(n, soc);
    // (packs, charger, load, end, the event's default moment)
    let (specs, load, end, at): (Vec<PackSpec>, f64, u64, u64) = match name {
        "full-charge" => (alike(&|k| 60.0 + 2.0 * k as f64), 0.0, 4 * H, 0),
        "joined" => (
            alike(&|k| if k == n - 1 { 20.0 } else { 80.0 }),
            0.0,
            3 * H,
            0,
        ),
        "pack-fault" => (alike(&|k| 50.0 + k as f64), 1000.0, 20 * MIN, 5 * MIN),
        "uart-lost" | "primary-lost" | "bus-off" => {
            (alike(&|k| 50.0 + k as f64), 0.0, 20 * MIN, 5 * MIN)
        }
        "uneven-charge" | "lossy-bus" => (PackSpec::uneven(n, 30.0), 0.0, 5 * H, 0),
        "fault-charge" | "bridge-lost-charge" | "stale-charge" => {
            (PackSpec::uneven(n, 30.0), 0.0, 150 * MIN, 40 * MIN)
        }
        "uneven-discharge" => (PackSpec::uneven(n, 95.0), 1000.0, 5 * H, 0),
        "fault-discharge" | "bridge-lost-discharge" | "stale-discharge" => {
            (PackSpec::uneven(n, 95.0), 1000.0, 90 * MIN, 20 * MIN)
        }
        "cold-start" => (PackSpec::uneven(n, 60.0), 0.0, 2 * MIN, 0),
        _ => return None,
    };
    let at = event_us.unwrap_or(at);
    let mut l = MultiLoop::with_packs(inverter, &specs, 200.0, 1);
    l.model.load_a = load;
    if name == "cold-start" {
        // At rest: a charger that is there but has nothing to do.
        l.model.charger_max_a = 0.0;
    }
    if name == "lossy-bus" {
        l.bus = BusFaults::lossy(0.15);
    }
    for (k, p) in l.nodes.iter_mut().enumerate() {
        p.h.sim.set_cell_offset_mv(k % 16, 5.0 + k as f64);
    }
    on_start(&mut l);
    if l.model.island && load > 0.0 {
        // "What the battery allows" is no load an island inverter knows: it
        // feeds its loads whatever the limit but 0. The house draws what the
        // battery's limits allow with every pack in; a pack that drops out
        // leaves the others past their cutoffs, which their bridges must
        // stop before their BMSes trip.
        let keep = f64::from(100u8.saturating_sub(inverter.charge.current_margin_pct)) / 100.0;
        l.model.load_a = l
            .nodes
            .iter()
            .map(|p| keep * f64::from(p.h.sim.register(317)))
            .sum();
    }
    match name {
        "pack-fault" => {
            // Full load: the loads draw what the battery allows, then pack 2's
            // BMS faults and opens its switch.
            l.run_until(at);
            if let Some(p) = l.nodes.get_mut(1) {
                p.h.sim
                    .inject_fault_event(EventId::DischargingOverCurrentCutoff);
            }
            l.run_until(at + 7 * MIN);
            if let Some(p) = l.nodes.get_mut(1) {
                p.h.sim.clear_fault();
            }
        }
        "fault-charge" | "fault-discharge" => {
            // A big pack's BMS faults (its switch opens) and recovers 7 min
            // later; discharging, a second one faults 2 min after the first.
            let id = if load > 0.0 {
                EventId::DischargingOverCurrentCutoff
            } else {
                EventId::ChargingOverCurrentCutoff
            };
            l.run_until(at);
            if let Some(p) = l.nodes.get_mut(1) {
                p.h.sim.inject_fault_event(id);
            }
            if load > 0.0 {
                l.run_until(at + 2 * MIN);
                if let Some(p) = l.nodes.get_mut(2) {
                    p.h.sim.inject_fault_event(id);
                }
            }
            l.run_until(at + 7 * MIN);
            for p in l.nodes.iter_mut().skip(1).take(2) {
                p.h.sim.clear_fault();
            }
        }
        "uart-lost" => {
            l.run_until(at);
            if let Some(p) = l.nodes.get_mut(1) {
                p.h.sim.set_silent_until(at + 5 * MIN);
            }
        }
        "stale-charge" | "stale-discharge" => {
            // The strongest pack's BMS link goes quiet for 30 min: its bridge
            // still sends its summary (stale), the pack still conducts.
            l.run_until(at);
            if let Some(p) = l.nodes.get_mut(0) {
                p.h.sim.set_silent_until(at + 30 * MIN);
            }
        }
        "primary-lost" | "bridge-lost-charge" | "bridge-lost-discharge" => {
            // Node 1's bridge is lost for good (in the uneven scenarios: the
            // strongest pack's); its pack stays on the bus.
            l.run_until(at);
            l.nodes[0].bridge_on = false;
        }
        "bus-off" => {
            l.run_until(at);
            // The speaker goes bus-off, later another node.
            l.bus_off(1, 20 * S);
            l.run_until(at + 5 * MIN);
            l.bus_off(2, 20 * S);
        }
        _ => {}
    }
    l.run_until(end);
    Some((l, end))
}

/// Everything a multi-pack run must hold to; one line per failure (empty: ok).
/// `ceiling_margin_mv`: how far below its over-voltage cutoff every cell must
/// stay (charge control's `ceiling_margin_mv`).
pub fn problems(l: &MultiLoop, ceiling_margin_mv: u16) -> Vec<String> {
    let mut out = Vec::new();
    for p in &l.nodes {
        let f = &p.figures;
        let ceiling = f.ov_cutoff_mv.saturating_sub(ceiling_margin_mv);
        if f.highest_cell_mv > ceiling {
            out.push(format!(
                "pack {}: a cell at {} mV, above the ceiling {ceiling} mV",
                p.node, f.highest_cell_mv
            ));
        }
        if f.highest_charge_a > f.charge_cutoff_a {
            out.push(format!(
                "pack {}: charged at {:.1} A, past its cutoff {} A",
                p.node, f.highest_charge_a, f.charge_cutoff_a
            ));
        }
        // An island inverter's loads stay on a pack until its limit says 0:
        // past the cutoff for a moment is its nature, a trip (below) is not.
        if f.highest_discharge_a > f.discharge_cutoff_a && !l.model.island {
            out.push(format!(
                "pack {}: discharged at {:.1} A, past its cutoff {} A",
                p.node, f.highest_discharge_a, f.discharge_cutoff_a
            ));
        }
        if f.lowest_cell_mv <= f.uv_cutoff_mv {
            out.push(format!(
                "pack {}: a cell at {} mV, at or below its cutoff {} mV",
                p.node, f.lowest_cell_mv, f.uv_cutoff_mv
            ));
        }
        if let Some((at, why)) = f.trips.first() {
            out.push(format!(
                "pack {}: its BMS opened its switch {} times, first at {:.1} s ({why:?})",
                p.node,
                f.trips.len(),
                *at as f64 / 1e6
            ));
        }
    }
    let b = &l.figures;
    if b.two_speaker_seconds > 0 {
        out.push(format!(
            "two bridges sent 0x351 in {} seconds",
            b.two_speaker_seconds
        ));
    }
    if b.offline_flags > 0 {
        out.push(format!(
            "{} alarm frames told the GX the battery is offline",
            b.offline_flags
        ));
    }
    if l.sent_limits.is_empty() {
        out.push("no 0x351 was sent".into());
    }
    if b.zero_limits_frames > 0 {
        out.push(format!(
            "{} frames 0x351 said CCL 0 and DCL 0 (a DCL of 0 switches a Multi off)",
            b.zero_limits_frames
        ));
    }
    // A protocol that answers queries (Growatt's, once a second) waits one
    // query more after a handover.
    let query_us = if l.model.dialect.answers_only() {
        crate::closed_loop::HEARTBEAT_US
    } else {
        0
    };
    if b.longest_without_limits_us > 2_500_000 + query_us {
        out.push(format!(
            "the inverter went {:.1} s without limits (a GX stops after 3 s)",
            b.longest_without_limits_us as f64 / 1e6
        ));
    }
    out
}

/// The figures of a run as `sim --packs` prints them.
pub fn table(name: &str, l: &MultiLoop, end_us: u64) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let b = &l.figures;
    let _ = writeln!(
        s,
        "{name}: {} packs, {:.1} h, battery in float {}",
        l.nodes.len(),
        end_us as f64 / 3.6e9,
        b.float_at_us.map_or("never".to_string(), |t| format!(
            "after {:.2} h",
            t as f64 / 3.6e9
        )),
    );
    let (dcl_hi, dcl_lo) = b.dcl_da;
    let _ =
        writeln!(
        s,
        "  told the inverter: charge current up to {:.1} A, discharge current {:.1} to {:.1} A \
         (0 A for {:.1} s in all: an inverter off), longest without limits {:.1} s \
         (a GX stops after 3 s)",
        f64::from(b.highest_ccl_da) / 10.0,
        if dcl_lo == u16::MAX { 0.0 } else { f64::from(dcl_lo) / 10.0 },
        f64::from(dcl_hi) / 10.0,
        b.dcl_zero_us as f64 / 1e6,
        b.longest_without_limits_us as f64 / 1e6,
    );
    let _ = writeln!(
        s,
        "  the bridge that spoke to the inverter: {}; CAN bus load {:.2} % ({} frames, {} of them \
         reports between the bridges)",
        b.speaker_changes
            .iter()
            .map(|(t, n)| format!("pack {n} from {} s", t / 1_000_000))
            .collect::<Vec<_>>()
            .join(", "),
        b.bus_load_percent(end_us),
        b.frames,
        b.summary_frames,
    );
    let (charged, discharged) = BatteryFigures::energy_ah(&l.nodes);
    let worst = l
        .nodes
        .iter()
        .map(|p| {
            let f = &p.figures;
            (f.highest_charge_a / f.charge_cutoff_a)
                .max(f.highest_discharge_a / f.discharge_cutoff_a)
        })
        .fold(0.0f64, f64::max);
    let _ = writeln!(
        s,
        "  charged {charged:.1} Ah, discharged {discharged:.1} Ah, worst pack at {:.0} % \
         of its own cutoff, {} trips, {} frames lost, doubled or late at a receiver",
        worst * 100.0,
        l.nodes.iter().map(|p| p.figures.trips.len()).sum::<usize>(),
        b.lost_frames,
    );
    let _ = writeln!(
        s,
        "  pack    Ah  cells low..high / cutoffs   charge / cutoff   discharge / cutoff   float    its BMS"
    );
    for p in &l.nodes {
        let f = &p.figures;
        let _ = writeln!(
            s,
            "  {:>4}  {:>4.0}  {:>4}..{:>4} / {:>4}..{:>4} mV   {:>6.1} / {:>3} A   \
             {:>9.1} / {:>3} A   {:<7}  {}",
            p.node,
            f64::from(
                p.h.sim
                    .register(protocol_core::settings::SettingId::BatteryCapacity.address())
            ) / 100.0,
            f.lowest_cell_mv,
            f.highest_cell_mv,
            f.uv_cutoff_mv,
            f.ov_cutoff_mv,
            f.highest_charge_a,
            f.charge_cutoff_a,
            f.highest_discharge_a,
            f.discharge_cutoff_a,
            f.float_at_us
                .map_or("-".to_string(), |t| format!("{:.2} h", t as f64 / 3.6e9)),
            // The pack whose BMS cut off, by name (its first trip and when).
            f.trips
                .first()
                .map_or("ok".to_string(), |(at, why)| format!(
                    "cut off at {} s: {}",
                    at / 1_000_000,
                    why.name()
                )),
        );
    }
    s
}
