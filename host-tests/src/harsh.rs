//! Inverters as harsh as real ones, and BMS silences started at every point
//! of a charge and a discharge: the safety rule of the inverter output —
//! no cell past its cutoff, no charge outside its temperature window, whatever
//! the inverter does and whenever the BMS's data stops — held to the
//! simulated pack's truth, with the bridge's **default** configuration.
//!
//! [`HARSH`] names the simulated inverters (each a set of the behaviours of
//! [`InverterModel`]); [`sweep`] runs one dialect against one of them over
//! three curves (a full charge, a deep discharge with a drifted SOC, a cold
//! pack a charger wants to charge), with a silence of each of
//! [`GAP_LENGTHS_S`] started at evenly spaced points of each curve (a
//! branch of the one run per point: [`ClosedLoop::fork`]).

use protocol_core::settings::SettingId;
use tinybms_firmware::inverter::{InverterConfig, Protocol};

use crate::closed_loop::{
    discharge_over_current_timeout_us, ClosedLoop, InverterModel, NOISE_A, TEMPERATURE_GRACE_US,
};
use crate::sim::PackModel;

const S: u64 = 1_000_000;
const MIN: u64 = 60 * S;

/// A simulated inverter's behaviour: which of [`InverterModel`]'s it has.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Harsh {
    /// Its name (`sim --inverter-model`).
    pub name: &'static str,
    /// What it stands for.
    pub what: &'static str,
    /// Ignores a current limit of 0 A and the enable bits.
    pub ignores_zero: bool,
    /// Obeys only the SOC told.
    pub soc_only: bool,
    /// Ignores a discharge limit other than 0.
    pub island: bool,
    /// Keeps its last limits when the frames stop.
    pub runs_on: bool,
    /// Overshoots every limit by this share.
    pub overshoot: f64,
    /// Sends its heartbeat only after a 0x356.
    pub heartbeat_after_measurements: bool,
}

impl Harsh {
    /// Gives `m` these behaviours.
    pub fn apply(&self, m: &mut InverterModel) {
        m.ignores_zero = self.ignores_zero;
        m.soc_only = self.soc_only;
        m.island = self.island;
        m.runs_on = self.runs_on;
        m.overshoot = self.overshoot;
        m.heartbeat_after_measurements = self.heartbeat_after_measurements;
    }
}

const PLAIN: Harsh = Harsh {
    name: "obeys",
    what: "obeys every limit and enable bit, stops 3 s after the frames stop (a GX)",
    ignores_zero: false,
    soc_only: false,
    island: false,
    runs_on: false,
    overshoot: 0.0,
    heartbeat_after_measurements: false,
};

/// The simulated inverters, plain first.
pub const HARSH: [Harsh; 7] = [
    PLAIN,
    Harsh {
        name: "island",
        what: "ignores a discharge limit other than 0, feeding its loads (a Multi in island mode)",
        island: true,
        ..PLAIN
    },
    Harsh {
        name: "ignores-zero",
        what: "ignores a limit of 0 A and the enable bits; obeys the charge voltage and the SOC (Deye, Solis)",
        ignores_zero: true,
        ..PLAIN
    },
    Harsh {
        name: "overshoots",
        what: "draws 20 % more than every limit it follows (YamBMS #184: 125.9 A for 108 A)",
        overshoot: 0.2,
        ..PLAIN
    },
    Harsh {
        name: "runs-on",
        what: "keeps its last limits when the frames stop (no BMS_Err_Stop)",
        runs_on: true,
        ..PLAIN
    },
    Harsh {
        name: "soc-only",
        what: "obeys only the SOC told, charging to its own 3.55 V a cell (an off-grid Deye)",
        soc_only: true,
        runs_on: true,
        ..PLAIN
    },
    Harsh {
        name: "deye",
        what: "all of a Deye's: ignores 0 A, overshoots 20 %, runs on, answers 0x305 only after 0x356",
        ignores_zero: true,
        overshoot: 0.2,
        runs_on: true,
        heartbeat_after_measurements: true,
        ..PLAIN
    },
];

/// The harsh inverter named `name`.
pub fn harsh(name: &str) -> Option<Harsh> {
    HARSH.iter().find(|h| h.name == name).copied()
}

/// The silences the sweep starts at each point, s: within the hold and
/// past it.
pub const GAP_LENGTHS_S: [u64; 2] = [110, 300];

/// A curve the silences are started along.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Curve {
    /// A full charge from 20 % SOC with a 100 A charger, into float.
    Charge,
    /// A 55 A load (within the BMS's 60 A cutoff, above the 48 A limit) from
    /// 12 % SOC with the BMS's SOC reading 15 % high, through the empty knee
    /// to the discharge stop and past it.
    Discharge,
    /// A pack at −5 °C at 50 % SOC that a 100 A charger wants to charge,
    /// with a small load coming and going.
    Cold,
}

impl Curve {
    /// Every curve.
    pub const ALL: [Curve; 3] = [Curve::Charge, Curve::Discharge, Curve::Cold];

    /// Its name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Charge => "charge",
            Self::Discharge => "discharge",
            Self::Cold => "cold",
        }
    }

    /// How long the curve runs, µs.
    pub const fn length_us(self) -> u64 {
        match self {
            Self::Charge => 6 * 60 * MIN,
            Self::Discharge => 80 * MIN,
            Self::Cold => 30 * MIN,
        }
    }

    /// A loop at the curve's start.
    fn start(self, protocol: Protocol, h: &Harsh, bms_switch: bool, seed: u64) -> ClosedLoop {
        let config = InverterConfig {
            protocol,
            ..InverterConfig::default()
        };
        let mut l = ClosedLoop::new(PackModel::LiFePO4_16S, seed, config, 100.0);
        h.apply(&mut l.model);
        l.bms_switch = bms_switch;
        match self {
            Self::Charge => l.h.sim.set_soc_percent(20.0),
            Self::Discharge => {
                l.h.sim.set_soc_bias(15.0);
                l.h.sim.set_soc_percent(12.0);
                l.model.load_a = 55.0;
            }
            Self::Cold => {
                l.h.sim.set_soc_percent(50.0);
                l.h.sim.force_temperature(Some(-5.0));
            }
        }
        l
    }

    /// What the curve does at `t` (the cold pack's load comes and goes).
    fn at(self, l: &mut ClosedLoop, t: u64) {
        if self == Self::Cold {
            l.model.load_a = if (t / (5 * MIN)) % 2 == 1 { 20.0 } else { 0.0 };
        }
    }
}

/// What the pack went through, against its BMS's cutoffs.
#[derive(Debug, Clone, Default)]
pub struct Worst {
    /// Runs (the base run and its branches).
    pub runs: u32,
    /// Highest cell, mV.
    pub max_cell_mv: u16,
    /// Lowest cell, mV.
    pub min_cell_mv: u16,
    /// The BMS's over-voltage cutoff (315), mV.
    pub ov_mv: u16,
    /// The BMS's under-voltage cutoff (316), mV.
    pub uv_mv: u16,
    /// Largest charge and discharge current, A.
    pub max_charge_a: f64,
    /// Largest discharge current, A.
    pub max_discharge_a: f64,
    /// The BMS's charge and discharge over-current cutoffs (318, 317), A.
    pub cutoffs_a: (f64, f64),
    /// Longest charge while a sensor was past a charge temperature cutoff, µs.
    pub charge_out_of_temperature_us: u64,
    /// Energy into and out of the pack during the silences (until the data
    /// was fresh again), Wh: the largest of any one branch.
    pub gap_wh: (f64, f64),
    /// Trips of the BMS at its own cutoffs (with its switch).
    pub trips: u32,
    /// What broke the rule, one line each (empty: none).
    pub failures: Vec<String>,
}

impl Worst {
    /// The rule held.
    pub fn ok(&self) -> bool {
        self.failures.is_empty()
    }

    /// Takes in one run `l`, `label` naming it in a failure.
    fn add(&mut self, l: &ClosedLoop, label: &str) {
        let reg = |id: SettingId| l.h.sim.register(id.address());
        let t = &l.figures.truth;
        let (ov, uv) = (
            reg(SettingId::OverVoltageCutoff),
            reg(SettingId::UnderVoltageCutoff),
        );
        let cutoffs = (
            f64::from(reg(SettingId::ChargeOverCurrentCutoff)),
            f64::from(reg(SettingId::DischargeOverCurrentCutoff)),
        );
        let min_cell = t.min_cell_mv.unwrap_or(u16::MAX);
        if self.runs == 0 {
            self.min_cell_mv = u16::MAX;
        }
        self.runs += 1;
        self.ov_mv = ov;
        self.uv_mv = uv;
        self.cutoffs_a = cutoffs;
        self.max_cell_mv = self.max_cell_mv.max(t.max_cell_mv);
        self.min_cell_mv = self.min_cell_mv.min(min_cell);
        self.max_charge_a = self.max_charge_a.max(t.max_charge_a);
        self.max_discharge_a = self.max_discharge_a.max(t.max_discharge_a);
        self.charge_out_of_temperature_us = self
            .charge_out_of_temperature_us
            .max(t.charge_out_of_temperature_us);
        self.gap_wh.0 = self.gap_wh.0.max(l.gap_wh.0);
        self.gap_wh.1 = self.gap_wh.1.max(l.gap_wh.1);
        self.trips += l.trips.len() as u32;
        let mut fail = |what: String| {
            if self.failures.len() < 20 {
                self.failures.push(format!("{label}: {what}"));
            }
        };
        if t.max_cell_mv >= ov {
            fail(format!(
                "a cell at {} mV, the cutoff {ov} mV",
                t.max_cell_mv
            ));
        }
        if min_cell <= uv {
            fail(format!("a cell at {min_cell} mV, the cutoff {uv} mV"));
        }
        if t.max_charge_a > cutoffs.0 + NOISE_A {
            fail(format!(
                "a charge of {:.1} A past the cutoff {} A",
                t.max_charge_a, cutoffs.0
            ));
        }
        let doc_timeout = discharge_over_current_timeout_us(&l.h.sim);
        if t.discharge_over_current_us >= doc_timeout {
            fail(format!(
                "a discharge of {:.1} A past the cutoff {} A for {:.1} s (the BMS trips after {} s)",
                t.max_discharge_a,
                cutoffs.1,
                t.discharge_over_current_us as f64 / 1e6,
                doc_timeout / S
            ));
        }
        if t.charge_out_of_temperature_us > TEMPERATURE_GRACE_US {
            fail(format!(
                "charged for {:.1} s below the charge temperature cutoff",
                t.charge_out_of_temperature_us as f64 / 1e6
            ));
        }
        if let Some((at, why)) = l.trips.first() {
            fail(format!(
                "the BMS tripped at {:.0} s: {why:?}",
                *at as f64 / 1e6
            ));
        }
    }
}

/// One sweep: `protocol` behind `harsh` (with or without the BMS's own
/// switch), silences of each of [`GAP_LENGTHS_S`] started at `points`
/// evenly spaced moments of each of `curves`.
pub fn sweep(
    protocol: Protocol,
    harsh: &Harsh,
    bms_switch: bool,
    curves: &[Curve],
    points: u32,
    seed: u64,
) -> Worst {
    let mut worst = Worst::default();
    for &curve in curves {
        let mut base = curve.start(protocol, harsh, bms_switch, seed);
        let len = curve.length_us();
        let step = len / u64::from(points.max(1) + 1);
        for k in 1..=u64::from(points) {
            let at = k * step;
            run_curve(curve, &mut base, at);
            for gap_s in GAP_LENGTHS_S {
                let mut branch = base.fork();
                branch.bms_silent(gap_s * S);
                let end = at + gap_s * S + 4 * MIN;
                run_curve(curve, &mut branch, end);
                let label = format!(
                    "{} silent {gap_s} s from {:.0} s",
                    curve.name(),
                    at as f64 / 1e6
                );
                worst.add(&branch, &label);
            }
        }
        run_curve(curve, &mut base, len);
        worst.add(&base, curve.name());
    }
    worst
}

/// Runs `l` along `curve` until `end`, µs.
fn run_curve(curve: Curve, l: &mut ClosedLoop, end: u64) {
    while l.h.now < end {
        let t = l.h.now;
        curve.at(l, t);
        l.run_until((t + MIN).min(end));
    }
}

/// The head of the sweep's table.
pub const SWEEP_HEADER: &str = "dialect   inverter      switch  runs  max cell  OV cut  min cell  UV cut  charge A  disch A  cold s  gap in Wh  gap out Wh  trips   ok";

/// One row of the sweep's table.
pub fn sweep_row(protocol: Protocol, harsh: &Harsh, bms_switch: bool, w: &Worst) -> String {
    format!(
        "{:<9} {:<13} {:<6} {:>5} {:>6} mV {:>4} mV {:>6} mV {:>4} mV {:>8.1} {:>8.1} {:>7.1} {:>10.1} {:>11.1} {:>6} {:>4}",
        protocol.key(),
        harsh.name,
        if bms_switch { "yes" } else { "no" },
        w.runs,
        w.max_cell_mv,
        w.ov_mv,
        w.min_cell_mv,
        w.uv_mv,
        w.max_charge_a,
        w.max_discharge_a,
        w.charge_out_of_temperature_us as f64 / 1e6,
        w.gap_wh.0,
        w.gap_wh.1,
        w.trips,
        if w.ok() { "yes" } else { "NO" },
    )
}
