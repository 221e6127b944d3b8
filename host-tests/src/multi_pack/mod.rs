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
//! Packs differ the way real ones do ([`PackSpec`]: capacity, cutoffs, cable,
//! cell resistance, SOC), and each simulated BMS does what a real one does at
//! its own cutoffs: past its charge over-current cutoff (318), past its
//! discharge over-current cutoff (317) for its timeout (330's high byte), or
//! with a cell past its over- or under-voltage cutoff (315, 316), it
//! opens its switch — the others then take its current — and closes it again
//! [`TRIP_RECOVERY_US`] later. Every trip is a failure of the run
//! ([`problems`]).
//!
//! The bus can misbehave ([`BusFaults`]): frames lost, doubled or late at a
//! bridge's receiver, reordered within a tick, a receiver deaf for seconds,
//! and a ghost node sending summaries no TinyBMS can report.
//!
//! The figures are the ground truth of the simulated packs, not what the
//! bridges reported: every pack's highest cell and highest charge and
//! discharge current against its own BMS's cutoffs (315, 318, 317), its trips,
//! and the charge it took and gave.

use std::io::Write;

use protocol_core::views::cell_mv;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::store::{Loaded, Source};
use tinybms_firmware::config::Config;
use tinybms_firmware::identity::{Features, Identity};
use tinybms_firmware::inverter::control::{Limits, Phase};
use tinybms_firmware::inverter::dialect::{victron, CanFrame};
use tinybms_firmware::inverter::{Inverter, InverterConfig, InverterReport};
use tinybms_firmware::station::{Logged, Setup, Station};

use protocol_core::events::EventId;
use tinybms_firmware::inverter::packs::Summary;

use crate::closed_loop::{candump_line, frame_bits, InverterModel, STEP_US};
use crate::sim::rng::Rng;
use crate::sim::{PackModel, SimBms, SimConfig};
use crate::virtual_time::Harness;

mod scenarios;
pub use scenarios::{problems, run_scenario, run_scenario_at, table, SCENARIOS};

/// A BMS that opened its switch at one of its cutoffs closes it again this
/// long after (a real TinyBMS recovers once the cause is gone), µs.
pub const TRIP_RECOVERY_US: u64 = 60_000_000;

/// One pack of a run: what differs between real packs in parallel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PackSpec {
    /// Capacity (306), Ah.
    pub capacity_ah: f64,
    /// Charge over-current cutoff (318), A.
    pub charge_cutoff_a: u16,
    /// Discharge over-current cutoff (317), A.
    pub discharge_cutoff_a: u16,
    /// Switch, fuse and cables to the common bus, Ω.
    pub cable_ohm: f64,
    /// Internal resistance of each cell, Ω.
    pub cell_ohm: f64,
    /// State of charge at the start, %.
    pub soc_pct: f64,
}

impl PackSpec {
    /// `n` packs alike but not equal (the six first scenarios): 280 Ah and
    /// the simulator's cutoffs, cell resistance and cable differing by up to
    /// ±20 %, SOC from `soc(k)`.
    pub fn alike(n: usize, soc: impl Fn(usize) -> f64) -> Vec<Self> {
        (0..n)
            .map(|k| Self {
                capacity_ah: 280.0,
                charge_cutoff_a: 0,
                discharge_cutoff_a: 0,
                cell_ohm: 0.0003 * (0.8 + 0.4 * (k as f64 / n as f64)),
                cable_ohm: 0.020 * (1.2 - 0.4 * (k as f64 / n as f64)),
                soc_pct: soc(k),
            })
            .collect()
    }

    /// `n` uneven packs (issue 24's figures): pack 1 a 100 Ah pack on a
    /// 3 mΩ cable with 30 A charge / 40 A discharge cutoffs; the others 200 to
    /// 280 Ah on 30 to 40 mΩ cables with 50 to 60 A cutoffs.
    pub fn uneven(n: usize, soc_pct: f64) -> Vec<Self> {
        (0..n)
            .map(|k| {
                if k == 0 {
                    Self {
                        capacity_ah: 100.0,
                        charge_cutoff_a: 30,
                        discharge_cutoff_a: 40,
                        cable_ohm: 0.003,
                        cell_ohm: 0.0003,
                        soc_pct,
                    }
                } else {
                    let x = (k - 1) as f64 / (n.max(3) - 2) as f64;
                    Self {
                        capacity_ah: 200.0 + 80.0 * x,
                        charge_cutoff_a: 50 + (10.0 * x) as u16,
                        discharge_cutoff_a: 50 + (10.0 * x) as u16,
                        cable_ohm: 0.030 + 0.010 * x,
                        cell_ohm: 0.0003,
                        soc_pct,
                    }
                }
            })
            .collect()
    }
}

/// How the bus misbehaves. Losses apply at each bridge's receiver on its
/// own (an overrun FIFO, a controller that missed a frame); the inverter
/// hears every frame.
#[derive(Debug, Clone, Default)]
pub struct BusFaults {
    /// Chance that a receiver misses a frame.
    pub drop: f64,
    /// Chance that a receiver gets a frame twice (a retransmission).
    pub duplicate: f64,
    /// Chance that a frame reaches a receiver only one tick (100 ms) late.
    pub delay: f64,
    /// The frames of one tick reach each receiver in a shuffled order.
    pub reorder: bool,
    /// Receivers deaf for a while: (node, from µs, until µs).
    pub deaf: Vec<(u8, u64, u64)>,
    /// A node nobody uses (its number) sending, every second, node 1's
    /// summary with a current of 3276.7 A and limits of 6553.5 A.
    pub ghost: Option<u8>,
}

impl BusFaults {
    /// A bus that loses `drop` of the frames at every receiver, doubles 2 %,
    /// delays 5 %, reorders within a tick, leaves node 3 deaf for 10 s at
    /// 30 min, and carries a ghost node 7.
    pub fn lossy(drop: f64) -> Self {
        Self {
            drop,
            duplicate: 0.02,
            delay: 0.05,
            reorder: true,
            deaf: vec![(3, 1_800_000_000, 1_810_000_000)],
            ghost: Some(7),
        }
    }
}

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
    /// Its under-voltage cutoff (316), mV.
    pub uv_cutoff_mv: u16,
    /// Lowest cell, mV (truth).
    pub lowest_cell_mv: u16,
    /// Times its BMS opened its switch at one of its cutoffs: (µs, why).
    pub trips: Vec<(u64, EventId)>,
    /// Charge it took, Ah (truth).
    pub charged_ah: f64,
    /// Charge it gave, Ah (truth).
    pub discharged_ah: f64,
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
    /// Its BMS tripped: it closes its switch again at this time.
    pub recover_at: Option<u64>,
    /// Discharging past its cutoff (317) since (its BMS waits its timeout,
    /// 330's high byte, before it trips).
    over_current_since: Option<u64>,
    /// Frames late for this bridge's receiver (they arrive next tick).
    late: Vec<CanFrame>,
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
    /// Highest and lowest DCL sent, 0.1 A (the lowest: `u16::MAX` before any).
    pub dcl_da: (u16, u16),
    /// Time the inverter was told DCL 0 (a Victron inverter is off then), µs.
    pub dcl_zero_us: u64,
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
    /// 0x351 frames with CCL 0 and DCL 0.
    pub zero_limits_frames: u64,
    /// Frames a receiver missed, got twice or got late (the bus's faults).
    pub lost_frames: u64,
}

impl BatteryFigures {
    /// Charge the battery took and gave, Ah (truth, all packs).
    pub fn energy_ah(nodes: &[PackNode]) -> (f64, f64) {
        nodes.iter().fold((0.0, 0.0), |(c, d), p| {
            (c + p.figures.charged_ah, d + p.figures.discharged_ah)
        })
    }
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
    /// How the bus misbehaves.
    pub bus: BusFaults,
    rng: Rng,
    ghost_seq: u8,
    now: u64,
    last_limits: Option<(u64, u8)>,
    second_speakers: (u64, u16),
}

impl MultiLoop {
    /// `n` packs (16S LiFePO4 with the simulator's settings) with SOCs
    /// `soc`, cell resistances `r_cell_ohm` and cables `cable_ohm`, bridges
    /// with node numbers 1..=n, and a charger of `charger_max_a`.
    pub fn new(
        inverter: InverterConfig,
        soc: &[f64],
        r_cell_ohm: &[f64],
        cable_ohm: &[f64],
        charger_max_a: f64,
        seed: u64,
    ) -> Self {
        let specs: Vec<PackSpec> = soc
            .iter()
            .enumerate()
            .map(|(k, s)| PackSpec {
                capacity_ah: 0.0,
                charge_cutoff_a: 0,
                discharge_cutoff_a: 0,
                cable_ohm: cable_ohm.get(k).copied().unwrap_or(0.005),
                cell_ohm: r_cell_ohm.get(k).copied().unwrap_or(0.0003),
                soc_pct: *s,
            })
            .collect();
        Self::with_packs(inverter, &specs, charger_max_a, seed)
    }

    /// One pack per spec (at most 8; a capacity or cutoff of 0 keeps the
    /// simulator's own setting), bridges with node numbers 1..=n, and a
    /// charger of `charger_max_a`.
    pub fn with_packs(
        inverter: InverterConfig,
        specs: &[PackSpec],
        charger_max_a: f64,
        seed: u64,
    ) -> Self {
        Self::with_packs_and_host(inverter, specs, charger_max_a, seed, false)
    }

    /// [`MultiLoop::with_packs`], with the host link of pack 1's bridge (the
    /// primary) on when `primary_host` (`sim --packs N --bridge-pty`: its USB
    /// port on a pseudo-terminal); the others have none, as in every scenario.
    pub fn with_packs_and_host(
        inverter: InverterConfig,
        specs: &[PackSpec],
        charger_max_a: f64,
        seed: u64,
        primary_host: bool,
    ) -> Self {
        let n = specs.len().min(8);
        let nodes = specs
            .iter()
            .take(n)
            .enumerate()
            .map(|(k, spec)| {
                let mut sim = SimBms::new(
                    PackModel::LiFePO4_16S,
                    SimConfig::default(),
                    seed + k as u64,
                );
                if spec.capacity_ah > 0.0 {
                    sim.set_register(306, (spec.capacity_ah * 100.0).round() as u16);
                }
                if spec.discharge_cutoff_a > 0 {
                    sim.set_register(317, spec.discharge_cutoff_a);
                }
                if spec.charge_cutoff_a > 0 {
                    sim.set_register(318, spec.charge_cutoff_a);
                }
                sim.set_external_current(Some(0.0));
                sim.set_soc_percent(spec.soc_pct);
                sim.set_cell_resistance_ohm(spec.cell_ohm);
                let regs = sim.registers();
                let figures = PackFigures {
                    ov_cutoff_mv: regs[315],
                    uv_cutoff_mv: regs[316],
                    lowest_cell_mv: u16::MAX,
                    charge_cutoff_a: f64::from(regs[318]),
                    discharge_cutoff_a: f64::from(regs[317]),
                    ..PackFigures::default()
                };
                let node = k as u8 + 1;
                let setup = Setup {
                    timing: Timing::default(),
                    identity: Identity::desktop(
                        "sim",
                        Features {
                            can: true,
                            host_link: primary_host && k == 0,
                            ..Features::default()
                        },
                    ),
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
                    cable_ohm: spec.cable_ohm,
                    bridge_on: true,
                    current_a: 0.0,
                    figures,
                    recover_at: None,
                    over_current_since: None,
                    late: Vec::new(),
                }
            })
            .collect::<Vec<_>>();
        let r_pack = 0.016 * 0.0003 + 0.005;
        let mut model = InverterModel::new(charger_max_a, r_pack / n.max(1) as f64);
        model.dialect = inverter.protocol;
        let mut l = Self {
            nodes,
            model,
            figures: BatteryFigures::default(),
            bus_v: 0.0,
            can_log: None,
            sent_limits: Vec::new(),
            bus: BusFaults::default(),
            rng: Rng::new(seed ^ 0x6275_7321),
            ghost_seq: 0,
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
            if let Some((id, data)) = self.model.outgoing(t) {
                // The inverter's heartbeat or query: every bridge on the bus
                // hears it.
                for p in self.nodes.iter_mut().filter(|p| p.bridge_on) {
                    p.h.station.can_received(t, id, &data);
                }
                if let Some(w) = self.can_log.as_mut() {
                    let _ = writeln!(w, "{}", candump_line(t, &CanFrame { id, len: 8, data }));
                }
            }
            let (v, currents) = self.split(total);
            self.bus_v = v;
            let dt_h = (t - self.now) as f64 / 3.6e9;
            for (p, i) in self.nodes.iter_mut().zip(currents) {
                p.current_a = i;
                p.h.sim.set_external_current(Some(i));
                let f = &mut p.figures;
                f.highest_charge_a = f.highest_charge_a.max(i);
                f.highest_discharge_a = f.highest_discharge_a.max(-i);
                f.charged_ah += i.max(0.0) * dt_h;
                f.discharged_ah += (-i).max(0.0) * dt_h;
                let first = usize::from(PackModel::LiFePO4_16S.first_cell_register());
                let regs = p.h.sim.registers();
                let (mut lo, mut hi) = (u16::MAX, 0u16);
                for r in regs.iter().skip(first).take(16) {
                    lo = lo.min(cell_mv(*r));
                    hi = hi.max(cell_mv(*r));
                }
                f.highest_cell_mv = f.highest_cell_mv.max(hi);
                f.lowest_cell_mv = f.lowest_cell_mv.min(lo);
                // The BMS at its own cutoffs, as a real one: it opens its
                // switch (no current from the next step on), and closes it
                // again a while later.
                let over_for = if -i > f.discharge_cutoff_a {
                    t - *p.over_current_since.get_or_insert(t)
                } else {
                    p.over_current_since = None;
                    0
                };
                let timeout = u64::from(p.h.sim.register(330) >> 8) * 1_000_000;
                if p.h.sim.fault().is_none() {
                    let why = if i > f.charge_cutoff_a {
                        Some(EventId::ChargingOverCurrentCutoff)
                    } else if -i > f.discharge_cutoff_a && over_for >= timeout {
                        Some(EventId::DischargingOverCurrentCutoff)
                    } else if hi >= f.ov_cutoff_mv {
                        Some(EventId::OverVoltageCutoff)
                    } else if lo <= f.uv_cutoff_mv {
                        Some(EventId::UnderVoltageCutoff)
                    } else {
                        None
                    };
                    if let Some(why) = why {
                        p.h.sim.inject_fault_event(why);
                        f.trips.push((t, why));
                        p.recover_at = Some(t + TRIP_RECOVERY_US);
                    }
                } else if p.recover_at.is_some_and(|at| t >= at) {
                    p.recover_at = None;
                    p.h.sim.clear_fault();
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
        self.ghost(now, &mut on_bus);
        on_bus.sort_by_key(|(at, id, k, _)| (*at, *id, *k));
        // What each receiver gets this tick: the frames late from the last
        // tick, then this tick's, each maybe lost, doubled or late, maybe
        // shuffled.
        for (k, p) in self.nodes.iter_mut().enumerate() {
            let listening = p.bridge_on && p.h.can.bus_off_until.is_none_or(|u| now >= u);
            let deaf = self
                .bus
                .deaf
                .iter()
                .any(|(n, from, until)| *n == p.node && (*from..*until).contains(&now));
            let mut inbox = std::mem::take(&mut p.late);
            for (_, _, from, f) in &on_bus {
                if *from == k {
                    continue;
                }
                let b = &self.bus;
                if b.drop > 0.0 && self.rng.chance(b.drop) {
                    self.figures.lost_frames += 1;
                } else if b.delay > 0.0 && self.rng.chance(b.delay) {
                    self.figures.lost_frames += 1;
                    p.late.push(*f);
                } else {
                    inbox.push(*f);
                    if b.duplicate > 0.0 && self.rng.chance(b.duplicate) {
                        self.figures.lost_frames += 1;
                        inbox.push(*f);
                    }
                }
            }
            if self.bus.reorder {
                for i in (1..inbox.len()).rev() {
                    let j = self.rng.below(i as u64 + 1) as usize;
                    inbox.swap(i, j);
                }
            }
            if listening && !deaf {
                for f in &inbox {
                    p.h.station.can_received(now, f.id, f.bytes());
                }
            } else {
                p.late.clear();
            }
        }
        for (at, _, from, f) in &on_bus {
            self.figures.frames += 1;
            self.figures.bits += frame_bits(f.len);
            if tinybms_firmware::inverter::packs::from_id(f.id).is_some() {
                self.figures.summary_frames += 1;
            }
            if *from >= self.nodes.len() {
                continue; // the ghost
            }
            let node = self.nodes[*from].node;
            self.model.on_frame(*at, f);
            if let Some(l) = self.model.dialect.limits_of(f) {
                self.limits_heard(*at, node, l);
            }
            let (byte, bit) = victron::VICTRON_SYSTEM_STATUS;
            let offline = (f.data[usize::from(byte)] >> bit) & 3 == victron::VICTRON_ACTIVE;
            let victron = self.nodes[*from].inverter().config().protocol
                == tinybms_firmware::inverter::Protocol::Victron;
            if f.id == victron::ID_ALARMS && victron && offline {
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

    /// The ghost's frames for this tick (once a second): node 1's last
    /// summary as the ghost's, with impossible current and limits.
    fn ghost(&mut self, now: u64, on_bus: &mut Vec<(u64, u16, usize, CanFrame)>) {
        let Some(ghost) = self.bus.ghost else {
            return;
        };
        if !now.is_multiple_of(1_000_000) {
            return;
        }
        let base = self
            .nodes
            .first()
            .and_then(|p| p.h.station.inverter())
            .and_then(|i| i.own_summary());
        let Some(base) = base else {
            return;
        };
        let lie = Summary {
            current_da: i16::MAX,
            limits: Limits {
                ccl_da: u16::MAX,
                dcl_da: u16::MAX,
                ..base.limits
            },
            speaking: false,
            ..base
        };
        self.ghost_seq = (self.ghost_seq + 1) & 0x0F;
        if let Some(fs) = lie.frames(ghost, self.ghost_seq) {
            for f in fs {
                on_bus.push((now, f.id, self.nodes.len(), f));
            }
        }
    }

    fn limits_heard(&mut self, now: u64, node: u8, limits: Limits) {
        if limits.ccl_da == 0 && limits.dcl_da == 0 {
            self.figures.zero_limits_frames += 1;
        }
        if let Some(&(at, _, last)) = self.sent_limits.last() {
            if last.dcl_da == 0 {
                self.figures.dcl_zero_us += now.saturating_sub(at);
            }
        }
        self.sent_limits.push((now, node, limits));
        self.figures.highest_ccl_da = self.figures.highest_ccl_da.max(limits.ccl_da);
        let (hi, lo) = self.figures.dcl_da;
        let lo = if self.sent_limits.len() == 1 {
            u16::MAX
        } else {
            lo
        };
        self.figures.dcl_da = (hi.max(limits.dcl_da), lo.min(limits.dcl_da));
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
