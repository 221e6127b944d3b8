//! Several packs in parallel, one battery, on the desk: N simulated TinyBMS
//! packs on one bus voltage — each with its own SOC, internal resistance, cable
//! and cell spread, so the current splits by physics — N bridges (the
//! firmware's bridge and inverter output, each with its node number), one
//! virtual CAN bus that delivers every frame to every other node in
//! arbitration order (lowest identifier first), and the inverter model of
//! [`crate::closed_loop`], which obeys whichever 0x351 it hears.
//!
//! The split: pack k is an open-circuit voltage E_k (its cells' OCV at its
//! SOC, the knee of a full cell, its cell offsets) behind a resistance R_k (its
//! cells and its cable). On a bus at voltage V it takes I_k = (V − E_k) / R_k,
//! and the currents add up to what the inverter delivers, so
//! V = (I + Σ E_k/R_k) / Σ 1/R_k. A pack whose BMS has opened its switch takes
//! nothing.
//!
//! The figures are the ground truth of the simulated packs, not what the
//! bridges reported: every pack's highest cell and highest charge and
//! discharge current against its own BMS's cutoffs (315, 318, 317).

use std::io::Write;

use protocol_core::views::cell_mv;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::store::{Loaded, Source};
use tinybms_firmware::config::Config;
use tinybms_firmware::inverter::control::{Limits, Phase};
use tinybms_firmware::inverter::frames::{self, CanFrame};
use tinybms_firmware::inverter::{Inverter, InverterConfig, InverterReport};
use tinybms_firmware::station::{Logged, Setup, Station};

use crate::closed_loop::{candump_line, frame_bits, InverterModel, STEP_US};
use crate::harness::Harness;
use crate::sim::{PackProfile, SimBms, SimConfig};

/// What one pack went through.
#[derive(Debug, Clone, Default)]
pub struct PackFigures {
    /// Highest cell, mV (truth).
    pub highest_cell_mv: u16,
    /// Its BMS's over-voltage cutoff (315), mV.
    pub ov_cutoff_mv: u16,
    /// Highest charge current, A (truth).
    pub highest_charge_a: f64,
    /// Its BMS's charge over-current cutoff (318), A.
    pub charge_cutoff_a: f64,
    /// Highest discharge current, A (truth, positive).
    pub highest_discharge_a: f64,
    /// Its BMS's discharge over-current cutoff (317), A.
    pub discharge_cutoff_a: f64,
    /// When its own charge control went to float.
    pub float_at_us: Option<u64>,
}

impl PackFigures {
    /// No cell at or past the over-voltage cutoff, no current past either
    /// current cutoff.
    pub fn within_cutoffs(&self) -> bool {
        self.highest_cell_mv < self.ov_cutoff_mv
            && self.highest_charge_a <= self.charge_cutoff_a
            && self.highest_discharge_a <= self.discharge_cutoff_a
    }
}

/// One pack with its bridge.
pub struct PackNode {
    /// Node number (1..=8).
    pub node: u8,
    /// Its station (bridge and inverter output) and simulated BMS.
    pub h: Harness,
    /// Resistance of its cables and fuse to the common bus, Ω.
    pub cable_ohm: f64,
    /// The bridge runs (false: it is lost — no poll, no CAN; the pack stays on
    /// the bus and its BMS still protects it).
    pub bridge_on: bool,
    /// Its current now, A (truth, positive = charging).
    pub current_a: f64,
    /// What it went through.
    pub figures: PackFigures,
}

impl PackNode {
    /// Its bridge's inverter output.
    pub fn inverter(&self) -> &Inverter {
        self.h
            .station
            .inverter()
            .expect("a loop's station is built with its CAN output")
    }
}

/// Figures of the whole run.
#[derive(Debug, Clone, Default)]
pub struct BatteryFigures {
    /// Frames on the bus.
    pub frames: u64,
    /// Bits on the bus (stuffing estimated).
    pub bits: u64,
    /// Summary frames on the bus.
    pub summary_frames: u64,
    /// 0x351 frames heard, by node.
    pub limits_frames: [u64; 9],
    /// Seconds in which two nodes sent 0x351.
    pub two_speaker_seconds: u64,
    /// Longest time without a 0x351 after the first, µs.
    pub longest_without_limits_us: u64,
    /// The node that sent the last 0x351 and when the speaker changed.
    pub speaker_changes: Vec<(u64, u8)>,
    /// Highest CCL sent, 0.1 A.
    pub highest_ccl_da: u16,
    /// Victron 0x35A frames that said "system offline" while packs took part.
    pub offline_flags: u64,
    /// The first pack in float: the battery's CVL goes to float (the lowest
    /// CVL of the packs), µs.
    pub float_at_us: Option<u64>,
    /// Every second: the speaker's battery — (time, speaker, capacity 0.1 Ah,
    /// packs taking part, limits it sends).
    pub timeline: Vec<(u64, u8, u32, u8, Limits)>,
    /// Reports of every node's inverter output, with the node.
    pub reports: Vec<(u64, u8, InverterReport)>,
}

impl BatteryFigures {
    /// Bus load at 500 kbit/s over `duration_us`, %.
    pub fn bus_load_percent(&self, duration_us: u64) -> f64 {
        if duration_us == 0 {
            return 0.0;
        }
        self.bits as f64 / (duration_us as f64 / 1e6 * 500_000.0) * 100.0
    }
}

/// The packs, their bridges, the bus and the inverter.
pub struct MultiLoop {
    /// The packs with their bridges, node 1 first.
    pub nodes: Vec<PackNode>,
    /// The inverter/charger.
    pub model: InverterModel,
    /// Figures so far.
    pub figures: BatteryFigures,
    /// The bus voltage now, V.
    pub bus_v: f64,
    /// A candump log of the bus being written.
    pub can_log: Option<Box<dyn Write>>,
    /// Every limits frame the inverter obeyed: (time, node, limits).
    pub sent_limits: Vec<(u64, u8, Limits)>,
    now: u64,
    last_limits: Option<(u64, u8)>,
    second_speakers: (u64, u16),
}

/// Scenario names of the multi-pack loop (`sim --packs N --scenario NAME`).
pub const SCENARIOS: [&str; 6] = [
    "full-charge",
    "joined",
    "pack-fault",
    "uart-lost",
    "primary-lost",
    "bus-off",
];

impl MultiLoop {
    /// `n` packs (16S LiFePO4, 100 Ah, 30 A charge and 60 A discharge cutoff)
    /// with SOCs `soc`, cell resistances `r_cell_ohm` and cables `cable_ohm`,
    /// bridges with node numbers 1..=n, and a charger of `charger_max_a`.
    pub fn new(
        inverter: InverterConfig,
        soc: &[f64],
        r_cell_ohm: &[f64],
        cable_ohm: &[f64],
        charger_max_a: f64,
        seed: u64,
    ) -> Self {
        let n = soc.len().min(8);
        let nodes = (0..n)
            .map(|k| {
                let mut sim = SimBms::new(
                    PackProfile::LiFePO4_16S,
                    SimConfig::default(),
                    seed + k as u64,
                );
                sim.set_external_current(Some(0.0));
                sim.set_soc_percent(soc[k]);
                if let Some(r) = r_cell_ohm.get(k) {
                    sim.set_cell_resistance_ohm(*r);
                }
                let regs = sim.registers();
                let figures = PackFigures {
                    ov_cutoff_mv: regs[315],
                    charge_cutoff_a: f64::from(regs[318]),
                    discharge_cutoff_a: f64::from(regs[317]),
                    ..PackFigures::default()
                };
                let node = k as u8 + 1;
                let setup = Setup {
                    timing: Timing::default(),
                    chip: "sim",
                    host_link: false,
                    can: true,
                    inverter: Some(InverterConfig { node, ..inverter }),
                };
                let loaded = Loaded {
                    config: Config::default(),
                    source: Source::Empty,
                };
                let mut h = Harness::with_station(sim, Station::new(setup, loaded, 0));
                h.retain = true;
                h.can.attached = true;
                h.finish_at_end = true;
                PackNode {
                    node,
                    h,
                    cable_ohm: cable_ohm.get(k).copied().unwrap_or(0.005),
                    bridge_on: true,
                    current_a: 0.0,
                    figures,
                }
            })
            .collect::<Vec<_>>();
        let r_pack = 0.016 * 0.0003 + 0.005;
        let mut l = Self {
            nodes,
            model: InverterModel::new(charger_max_a, r_pack / n.max(1) as f64),
            figures: BatteryFigures::default(),
            bus_v: 0.0,
            can_log: None,
            sent_limits: Vec::new(),
            now: 0,
            last_limits: None,
            second_speakers: (0, 0),
        };
        l.bus_v = l.split(0.0).0;
        l
    }

    /// Virtual time now, µs.
    pub fn now(&self) -> u64 {
        self.now
    }

    /// The bus voltage and each pack's current for a total of `total_a`.
    fn split(&self, total_a: f64) -> (f64, Vec<f64>) {
        let connected: Vec<(f64, f64)> = self
            .nodes
            .iter()
            .map(|p| {
                if p.h.sim.fault().is_some() {
                    (0.0, 0.0)
                } else {
                    let r = p.h.sim.internal_resistance_ohm() + p.cable_ohm;
                    (1.0 / r.max(1e-6), p.h.sim.open_circuit_v())
                }
            })
            .collect();
        let g: f64 = connected.iter().map(|(g, _)| g).sum();
        if g <= 0.0 {
            return (0.0, vec![0.0; self.nodes.len()]);
        }
        let v = (total_a + connected.iter().map(|(g, e)| g * e).sum::<f64>()) / g;
        (v, connected.iter().map(|(g, e)| g * (v - e)).collect())
    }

    /// Runs until virtual time `end_us`.
    pub fn run_until(&mut self, end_us: u64) {
        while self.now < end_us {
            let t = (self.now + STEP_US).min(end_us);
            for p in &mut self.nodes {
                if p.bridge_on {
                    p.h.run_until(t);
                } else {
                    p.h.sim.advance(t);
                    p.h.can.outbox.clear();
                }
            }
            self.pump_can(t);
            let total = self.model.step(t, self.bus_v);
            let (v, currents) = self.split(total);
            self.bus_v = v;
            for (p, i) in self.nodes.iter_mut().zip(currents) {
                p.current_a = i;
                p.h.sim.set_external_current(Some(i));
                let f = &mut p.figures;
                f.highest_charge_a = f.highest_charge_a.max(i);
                f.highest_discharge_a = f.highest_discharge_a.max(-i);
                let first = usize::from(PackProfile::LiFePO4_16S.first_cell_register());
                let regs = p.h.sim.registers();
                for r in regs.iter().skip(first).take(16) {
                    f.highest_cell_mv = f.highest_cell_mv.max(cell_mv(*r));
                }
                if f.float_at_us.is_none()
                    && p.h
                        .station
                        .inverter()
                        .is_some_and(|i| i.phase() == Phase::Float)
                {
                    f.float_at_us = Some(t);
                }
            }
            if self.figures.float_at_us.is_none()
                && self.nodes.iter().any(|p| p.figures.float_at_us.is_some())
            {
                self.figures.float_at_us = Some(t);
            }
            if t.is_multiple_of(1_000_000) {
                let speaker = self
                    .nodes
                    .iter()
                    .find(|p| p.bridge_on && p.inverter().speaking());
                if let Some((p, (b, lim))) =
                    speaker.and_then(|p| p.inverter().battery().map(|b| (p, b)))
                {
                    self.figures
                        .timeline
                        .push((t, p.node, b.capacity_dah, b.online, *lim));
                }
            }
            self.now = t;
        }
    }

    fn pump_can(&mut self, now: u64) {
        // What every node sent up to now; the bus delivers in time order,
        // simultaneous frames in arbitration order (lowest identifier first).
        let mut on_bus: Vec<(u64, u16, usize, CanFrame)> = Vec::new();
        for (k, p) in self.nodes.iter_mut().enumerate() {
            for (at, f) in std::mem::take(&mut p.h.can.outbox) {
                on_bus.push((at, f.id, k, f));
            }
        }
        on_bus.sort_by_key(|(at, id, k, _)| (*at, *id, *k));
        for (at, _, from, f) in &on_bus {
            self.figures.frames += 1;
            self.figures.bits += frame_bits(f.len);
            if tinybms_firmware::inverter::packs::from_id(f.id).is_some() {
                self.figures.summary_frames += 1;
            }
            for (k, p) in self.nodes.iter_mut().enumerate() {
                let listening = p.bridge_on && p.h.can.bus_off_until.is_none_or(|u| now >= u);
                if k != *from && listening {
                    p.h.station.can_received(now, f.id, f.bytes());
                }
            }
            let node = self.nodes[*from].node;
            if f.id == frames::ID_LIMITS {
                self.model.on_frame(*at, f);
                self.limits_heard(*at, node, f);
            }
            let (byte, bit) = frames::VICTRON_SYSTEM_STATUS;
            let offline = (f.data[usize::from(byte)] >> bit) & 3 == frames::VICTRON_ACTIVE;
            let victron = self.nodes[*from].inverter().config().protocol
                == tinybms_firmware::inverter::Protocol::Victron;
            if f.id == frames::ID_ALARMS && victron && offline {
                self.figures.offline_flags += 1;
            }
            if let Some(w) = self.can_log.as_mut() {
                let _ = writeln!(w, "{}", candump_line(*at, f));
            }
        }
        for p in &mut self.nodes {
            for (at, item) in std::mem::take(&mut p.h.other_log) {
                if let Logged::Inverter(r) = item {
                    self.figures.reports.push((at, p.node, r));
                }
            }
        }
    }

    fn limits_heard(&mut self, now: u64, node: u8, f: &CanFrame) {
        let d = f.data;
        let limits = Limits {
            cvl_dv: u16::from_le_bytes([d[0], d[1]]),
            ccl_da: u16::from_le_bytes([d[2], d[3]]),
            dcl_da: u16::from_le_bytes([d[4], d[5]]),
            discharge_dv: u16::from_le_bytes([d[6], d[7]]),
        };
        self.sent_limits.push((now, node, limits));
        self.figures.highest_ccl_da = self.figures.highest_ccl_da.max(limits.ccl_da);
        if let Some(slot) = self.figures.limits_frames.get_mut(usize::from(node)) {
            *slot += 1;
        }
        if let Some((at, last)) = self.last_limits {
            self.figures.longest_without_limits_us =
                self.figures.longest_without_limits_us.max(now - at);
            if last != node {
                self.figures.speaker_changes.push((now, node));
            }
        } else {
            self.figures.speaker_changes.push((now, node));
        }
        self.last_limits = Some((now, node));
        let second = now / 1_000_000;
        let bit = 1u16 << node;
        if self.second_speakers.0 != second {
            self.second_speakers = (second, bit);
        } else if self.second_speakers.1 & bit == 0 {
            if self.second_speakers.1.count_ones() == 1 {
                self.figures.two_speaker_seconds += 1;
            }
            self.second_speakers.1 |= bit;
        }
    }

    /// Node `node`'s CAN controller goes bus-off now for `duration_us`.
    pub fn bus_off(&mut self, node: u8, duration_us: u64) {
        let now = self.now;
        if let Some(p) = self.nodes.iter_mut().find(|p| p.node == node) {
            p.h.station.can_bus_off(now);
            p.h.can.bus_off_until = Some(now + duration_us);
        }
    }

    /// The node that spoke last (sent the last 0x351).
    pub fn speaker(&self) -> Option<u8> {
        self.last_limits.map(|(_, n)| n)
    }
}

/// Runs one multi-pack scenario with `n` packs (2..=8; see [`SCENARIOS`]) to
/// its end; the loop and its duration, µs. `None` for an unknown name.
pub fn run_scenario(
    name: &str,
    n: usize,
    inverter: InverterConfig,
    mut on_start: impl FnMut(&mut MultiLoop),
) -> Option<(MultiLoop, u64)> {
    const S: u64 = 1_000_000;
    const MIN: u64 = 60 * S;
    const H: u64 = 3600 * S;
    let n = n.clamp(2, 8);
    // Packs alike but not equal: resistance and cable differ by up to ±20 %,
    // SOC by a few percent, one cell of each pack a little ahead.
    let r_cell: Vec<f64> = (0..n)
        .map(|k| 0.0003 * (0.8 + 0.4 * (k as f64 / n as f64)))
        .collect();
    // Switch, fuse and cables of a pack to the common bus: 20 mΩ ± 20 %.
    let cable: Vec<f64> = (0..n)
        .map(|k| 0.020 * (1.2 - 0.4 * (k as f64 / n as f64)))
        .collect();
    let (soc, charger, end): (Vec<f64>, f64, u64) = match name {
        "full-charge" => (
            (0..n).map(|k| 60.0 + 2.0 * k as f64).collect(),
            200.0,
            4 * H,
        ),
        "joined" => (
            (0..n)
                .map(|k| if k == n - 1 { 20.0 } else { 80.0 })
                .collect(),
            200.0,
            3 * H,
        ),
        "pack-fault" | "uart-lost" | "primary-lost" | "bus-off" => {
            ((0..n).map(|k| 50.0 + k as f64).collect(), 200.0, 20 * MIN)
        }
        _ => return None,
    };
    let mut l = MultiLoop::new(inverter, &soc, &r_cell, &cable, charger, 1);
    for (k, p) in l.nodes.iter_mut().enumerate() {
        p.h.sim.set_cell_offset_mv(k % 16, 5.0 + k as f64);
    }
    on_start(&mut l);
    match name {
        "full-charge" | "joined" => l.run_until(end),
        "pack-fault" => {
            // Full load: the loads draw what the battery allows, then pack 2's
            // BMS faults and opens its switch.
            l.model.load_a = 1000.0;
            l.run_until(5 * MIN);
            if let Some(p) = l.nodes.get_mut(1) {
                p.h.sim.inject_fault_event(
                    protocol_core::events::EventId::DischargingOverCurrentCutoff,
                );
            }
            l.run_until(12 * MIN);
            if let Some(p) = l.nodes.get_mut(1) {
                p.h.sim.clear_fault();
            }
            l.run_until(end);
        }
        "uart-lost" => {
            l.run_until(5 * MIN);
            if let Some(p) = l.nodes.get_mut(1) {
                p.h.sim.set_silent_until(10 * MIN);
            }
            l.run_until(end);
        }
        "primary-lost" => {
            l.run_until(5 * MIN);
            l.nodes[0].bridge_on = false;
            l.run_until(end);
        }
        "bus-off" => {
            l.run_until(5 * MIN);
            // The speaker goes bus-off, later another node.
            l.bus_off(1, 20 * S);
            l.run_until(10 * MIN);
            l.bus_off(2, 20 * S);
            l.run_until(end);
        }
        _ => return None,
    }
    Some((l, end))
}

/// Everything a multi-pack run must hold to; one line per failure (empty: ok).
/// `ceiling_margin_mv`: how far below its over-voltage cutoff every cell must
/// stay (charge control's `ov_margin_mv`).
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
        if f.highest_discharge_a > f.discharge_cutoff_a {
            out.push(format!(
                "pack {}: discharged at {:.1} A, past its cutoff {} A",
                p.node, f.highest_discharge_a, f.discharge_cutoff_a
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
    if b.longest_without_limits_us > 2_500_000 {
        out.push(format!(
            "the inverter went {:.1} s without 0x351 (a GX stops after 3 s)",
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
        "{name}: {} packs, {:.1} h, bus load {:.2} % ({} frames, {} of them summaries), \
         battery in float {}, highest CCL sent {:.1} A, longest without 0x351 {:.1} s, \
         speakers {}",
        l.nodes.len(),
        end_us as f64 / 3.6e9,
        b.bus_load_percent(end_us),
        b.frames,
        b.summary_frames,
        b.float_at_us.map_or("never".to_string(), |t| format!(
            "after {:.2} h",
            t as f64 / 3.6e9
        )),
        f64::from(b.highest_ccl_da) / 10.0,
        b.longest_without_limits_us as f64 / 1e6,
        b.speaker_changes
            .iter()
            .map(|(t, n)| format!("{n} from {} s", t / 1_000_000))
            .collect::<Vec<_>>()
            .join(", "),
    );
    let _ = writeln!(
        s,
        "  pack  highest cell / cutoff   charge / cutoff   discharge / cutoff   float"
    );
    for p in &l.nodes {
        let f = &p.figures;
        let _ = writeln!(
            s,
            "  {:>4}  {:>7} / {:>4} mV   {:>6.1} / {:>3} A   {:>9.1} / {:>3} A   {}",
            p.node,
            f.highest_cell_mv,
            f.ov_cutoff_mv,
            f.highest_charge_a,
            f.charge_cutoff_a,
            f.highest_discharge_a,
            f.discharge_cutoff_a,
            f.float_at_us
                .map_or("-".to_string(), |t| format!("{:.2} h", t as f64 / 3.6e9)),
        );
    }
    s
}
