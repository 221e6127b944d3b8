//! # A simulated year of a TinyBMS pack behind a solar inverter
//!
//! The measure of end-of-charge control ([`tinybms_firmware::inverter::finish`]):
//! the firmware's own [`ChargeControl`] runs a pack of cells that drift apart,
//! balanced by the TinyBMS's balancer ([`crate::sim::balancer`]), through days
//! of sun and cloud and a house's loads, behind an inverter — for a year, in
//! seconds (quiet hours are stepped over a minute at a time, the knee of a
//! full cell a second at a time, the rest 5 s at a time).
//!
//! ## The pack
//! 16 LiFePO4 cells of 280 Ah (the simulator's default pack: 300 = 3650 mV,
//! 303 = 3400 mV, 308 = 15 mV, 315 = 3650 mV, 316 = 2500 mV, 318 = 150 A), each
//! with its own capacity (±2 %), self-discharge (2 % a month ± 15 %) and
//! resistance; a cell's voltage is its open-circuit voltage at its own SOC —
//! with the steep knee of a full LiFePO4 cell — plus I·R. The year starts
//! with one cell [`START_LEAD_PCT`] % of charge ahead: the first charge ends
//! at least [`START_IMBALANCE_MV`] apart.
//!
//! ## The days
//! Sunny, mixed (clouds passing) or overcast, drawn per day from the seed;
//! the day's length follows the season. The house draws a base load, a
//! morning and an evening peak, and random appliances.
//!
//! ## The inverter
//! Solar first to the house, the rest to the battery within CCL (and its
//! own maximum), constant voltage at CVL; the battery feeds the house within
//! DCL. Variants: [`InverterKind::Exporter`] — when the pack is above CVL (by
//! more than [`EXPORT_DEADBAND_V`]) it pulls it down to CVL into the grid (a Deye did so when CVL dropped at
//! once), [`InverterKind::Overshoot`] — every current limit exceeded by 20 %,
//! [`InverterKind::IgnoresZero`] — a charge limit of 0 A is taken as 10 A
//! (charging then stops only at CVL).
//!
//! ## The capacity measure ([`run_capacity`])
//! The same year (today's control, an inverter that obeys) with three
//! additions, none of which changes a draw of the year above: each cell loses
//! [`FADE_PER_YEAR`] of its capacity a year (±30 % per cell, its own draw
//! from the seed); deep spells (every 18-35 days, 2-3 overcast days with a
//! heater's 8-14 A more load, their own draws) take the pack down to its
//! knee, which the ordinary days never reach; and the firmware's
//! [`tinybms_firmware::history`] is fed with what a TinyBMS would report
//! every [`FEED_S`] s — a `LiveSnapshot` of the cells, the pack's voltage and
//! current and the status "fully charged" once the highest cell reached 300
//! with the charge current below [`CHARGE_FINISHED_A`], until the pack
//! discharges — which at the pack's 300 of 3650 mV never happens behind the
//! bridge (its absorption target is 3550 mV), so the full points are the
//! bridge's own ends of charge ([`charge_finished`](tinybms_firmware::history::capacity::charge_finished)),
//! handed in as "fully charged" as the station does. Each estimate is held
//! against the weakest cell's capacity at that moment.

use tinybms_firmware::inverter::control::{
    ChargeConfig, ChargeControl, PackSettings, PackState, Phase,
};
use tinybms_firmware::inverter::finish::Stage;

use protocol_core::events::OnlineStatus;
use protocol_core::views::{Cells, LiveSnapshot};
use tinybms_firmware::history::capacity::{Capacity, Estimate, LFP_KNEE_MV};
use tinybms_firmware::history::day::{DayBook, DayRecord};

use crate::sim::balancer;
use crate::sim::rng::Rng;

/// Series cells.
pub const CELLS: usize = 16;
/// Nominal cell capacity, Ah (register 306).
pub const CAPACITY_AH: f64 = 280.0;
/// The spread of the cells at the end of the first charge is at least this,
/// mV (the starting imbalance).
pub const START_IMBALANCE_MV: u16 = 80;
/// The runner's lead in charge when the year starts, % of its capacity (the
/// others between it and the lowest): the first charge ends 125-137 mV apart
/// (seeds 1-3; the knee of a full cell widens it), at least
/// [`START_IMBALANCE_MV`] (held by `host-tests/tests/end_of_charge.rs`).
pub const START_LEAD_PCT: f64 = 0.33;
/// A day, s.
pub const DAY_S: u64 = 86_400;
/// What an inverter that ignores 0 A charges with at 0 A, A.
pub const IGNORED_CHARGE_A: f64 = 10.0;
/// An exporter pulls the pack down once it is this far above CVL, V: the
/// resolution of the CVL it is told (0.1 V), finer than any inverter
/// measures the battery's voltage (±0.5 % is 0.27 V at 54 V).
pub const EXPORT_DEADBAND_V: f64 = 0.1;
/// The inverter's own largest charge current, A.
pub const CHARGER_MAX_A: f64 = 100.0;

/// The pack's BMS settings (the simulator's defaults for the LiFePO4 pack).
pub fn settings() -> PackSettings {
    PackSettings {
        fully_charged_mv: 3650,
        capacity_cah: (CAPACITY_AH * 100.0) as u16,
        cells: CELLS as u16,
        allowed_disbalance_mv: 15,
        ov_cutoff_mv: 3650,
        uv_cutoff_mv: 2500,
        discharge_cutoff_a: 150,
        charge_cutoff_a: 150,
        discharge_cutoff_s: 5,
        overheat_c: 60,
        low_temp_charge_c: 0,
    }
}

/// Register 303, mV.
pub const EARLY_BALANCING_MV: u16 = 3400;

/// Open-circuit voltage of a LiFePO4 cell against its SOC, %: V.
const OCV: &[(f64, f64)] = &[
    (0.0, 2.60),
    (2.0, 2.95),
    (5.0, 3.12),
    (10.0, 3.20),
    (20.0, 3.25),
    (40.0, 3.29),
    (60.0, 3.31),
    (80.0, 3.33),
    (90.0, 3.34),
    (95.0, 3.36),
    (98.0, 3.38),
    (99.0, 3.40),
    (99.5, 3.42),
    (100.0, 3.45),
];
/// Past 100 %: the knee goes on, V per % over.
const OVER_V_PER_PCT: f64 = 1.5;
/// Polarisation: how fast it follows the current, s.
const POLARISATION_TAU_S: f64 = 1200.0;
/// Polarisation resistance below the knee, Ω, and its rise through the knee
/// (98 % to 100 %), Ω: near full, a cell's voltage under a small charge
/// current stands well above its rest (3.55 V at the tail current, 3.45 V
/// an hour after).
const POLARISATION_OHM: (f64, f64) = (0.0005, 0.02);
/// Polarisation is at most this, V (charging) and this (discharging).
const POLARISATION_MAX_V: (f64, f64) = (0.12, -0.05);

fn ocv(soc: f64) -> f64 {
    if soc >= 100.0 {
        return 3.45 + (soc - 100.0) * OVER_V_PER_PCT;
    }
    let mut prev = (0.0, OCV[0].1);
    for &(s, v) in OCV {
        if soc <= s {
            if s <= prev.0 {
                return v;
            }
            return prev.1 + (soc - prev.0) / (s - prev.0) * (v - prev.1);
        }
        prev = (s, v);
    }
    prev.1
}

/// One cell.
#[derive(Debug, Clone, Copy)]
struct Cell {
    capacity_ah: f64,
    charge_ah: f64,
    /// Self-discharge, Ah per second.
    leak_ah_s: f64,
    r_ohm: f64,
    /// Polarisation now, V.
    pol_v: f64,
    /// Capacity fade, share of the capacity per second (0: none; only the
    /// capacity measure fades its cells, see [`run_capacity`]).
    fade_per_s: f64,
}

impl Cell {
    fn soc(&self) -> f64 {
        self.charge_ah / self.capacity_ah * 100.0
    }
    fn volts(&self, current_a: f64) -> f64 {
        self.rest() + current_a * self.r_ohm
    }
    /// The voltage with no current through it now (polarisation still on), V.
    fn rest(&self) -> f64 {
        ocv(self.soc()) + self.pol_v
    }
    fn polarise(&mut self, current_a: f64, dt_s: f64) {
        let knee = ((self.soc() - 98.0) / 2.0).clamp(0.0, 1.0);
        let ohm = POLARISATION_OHM.0 + POLARISATION_OHM.1 * knee;
        let target = (current_a * ohm).clamp(POLARISATION_MAX_V.1, POLARISATION_MAX_V.0);
        self.pol_v += (target - self.pol_v) * (1.0 - (-dt_s / POLARISATION_TAU_S).exp());
    }
}

/// The cells and their balancer.
#[derive(Debug, Clone)]
pub struct Pack {
    cells: [Cell; CELLS],
    /// Pack current, A (+ = charging).
    pub current_a: f64,
    /// Registers 51 and 52 as the BMS last reported them.
    pub balance_bits: (u16, u16),
    /// Ah bled by the balancer, all cells.
    pub balanced_ah: f64,
}

impl Pack {
    /// A pack from `seed`: the cells' spreads, and the imbalance at the top.
    pub fn new(seed: u64, soc_pct: f64) -> Self {
        let mut rng = Rng::new(seed ^ 0xCE11);
        let month_s = 30.0 * DAY_S as f64;
        let mut cells = [Cell {
            capacity_ah: CAPACITY_AH,
            charge_ah: 0.0,
            leak_ah_s: 0.0,
            r_ohm: 0.0005,
            pol_v: 0.0,
            fade_per_s: 0.0,
        }; CELLS];
        for c in &mut cells {
            c.capacity_ah = CAPACITY_AH * rng.range_f64(0.98, 1.02);
            c.leak_ah_s = c.capacity_ah * 0.02 * rng.range_f64(0.85, 1.15) / month_s;
            c.r_ohm = rng.range_f64(0.0004, 0.0006);
            c.charge_ah = c.capacity_ah * soc_pct / 100.0;
        }
        // The imbalance: the runner START_LEAD_PCT of charge ahead, the others
        // between it and the lowest (the first charge ends at least
        // START_IMBALANCE_MV apart).
        let lead_pct = START_LEAD_PCT;
        for (i, c) in cells.iter_mut().enumerate() {
            let f = if i == 0 { 1.0 } else { rng.next_f64() * 0.6 };
            c.charge_ah += c.capacity_ah * lead_pct / 100.0 * f;
        }
        Self {
            cells,
            current_a: 0.0,
            balance_bits: (0, 0),
            balanced_ah: 0.0,
        }
    }

    /// Cell voltages now, mV.
    pub fn cells_mv(&self) -> [u16; CELLS] {
        self.cells_mv_at(self.current_a)
    }

    /// Cell voltages with `current_a` through them now, mV.
    pub fn cells_mv_at(&self, current_a: f64) -> [u16; CELLS] {
        let mut out = [0u16; CELLS];
        for (o, c) in out.iter_mut().zip(&self.cells) {
            *o = (c.volts(current_a) * 1000.0).round().clamp(0.0, 6500.0) as u16;
        }
        out
    }

    /// Pack voltage, V.
    pub fn volts(&self) -> f64 {
        self.cells.iter().map(|c| c.volts(self.current_a)).sum()
    }

    /// The pack's voltage with no current through it now, V.
    pub fn rest_volts(&self) -> f64 {
        self.cells.iter().map(Cell::rest).sum()
    }

    /// Pack voltage with `current_a` through it now, V.
    pub fn volts_at(&self, current_a: f64) -> f64 {
        self.cells.iter().map(|c| c.volts(current_a)).sum()
    }

    /// The cells' capacities now, Ah.
    pub fn capacities_ah(&self) -> [f64; CELLS] {
        self.cells.map(|c| c.capacity_ah)
    }

    /// The cells' charges now, Ah.
    pub fn charges_ah(&self) -> [f64; CELLS] {
        self.cells.map(|c| c.charge_ah)
    }

    /// Gives each cell a capacity fade of [`FADE_PER_YEAR`] varied by ±30 %
    /// per cell, drawn from `seed` (a draw of its own: the pack is otherwise
    /// the same as without).
    pub fn fade(&mut self, seed: u64) {
        let mut rng = Rng::new(seed ^ 0xFADE);
        let year_s = 365.0 * DAY_S as f64;
        for c in &mut self.cells {
            c.fade_per_s = FADE_PER_YEAR * rng.range_f64(0.7, 1.3) / year_s;
        }
    }

    /// Resistance of the pack, Ω.
    pub fn r_ohm(&self) -> f64 {
        self.cells.iter().map(|c| c.r_ohm).sum()
    }

    /// The BMS's SOC, %: the charge of the pack over its capacity (the
    /// weakest cell's share sets what is left).
    pub fn soc(&self) -> f64 {
        self.cells
            .iter()
            .map(Cell::soc)
            .fold(f64::INFINITY, f64::min)
            .clamp(0.0, 100.0)
    }

    /// `dt_s` at `current_a`: charge, leaks, the balancer.
    pub fn step(&mut self, current_a: f64, dt_s: f64) {
        self.current_a = current_a;
        let mv = self.cells_mv();
        let s = settings();
        self.balance_bits =
            balancer::bits(&mv, EARLY_BALANCING_MV, s.allowed_disbalance_mv, current_a);
        for (i, c) in self.cells.iter_mut().enumerate() {
            let mut ah = current_a * dt_s / 3600.0 - c.leak_ah_s * dt_s;
            if self.balance_bits.1 & (1 << i) != 0 {
                let bled = balancer::BALANCE_CURRENT_A * dt_s / 3600.0;
                ah -= bled;
                self.balanced_ah += bled;
            }
            c.charge_ah = (c.charge_ah + ah).max(0.0);
            c.polarise(current_a, dt_s);
            if c.fade_per_s > 0.0 {
                // Capacity lost, the charge with it (the SOC stays).
                let k = 1.0 - c.fade_per_s * dt_s;
                c.capacity_ah *= k;
                c.charge_ah *= k;
            }
        }
    }

    /// What the BMS reports, as charge control reads it.
    pub fn state(&self) -> PackState {
        let mv = self.cells_mv();
        PackState {
            min_cell_mv: mv.iter().copied().min().unwrap_or(0),
            max_cell_mv: mv.iter().copied().max().unwrap_or(0),
            pack_v: self.volts() as f32,
            current_a: self.current_a as f32,
            soc_pct: self.soc() as f32,
            soh_pct: 100.0,
            min_temp_c: 25.0,
            max_temp_c: 25.0,
            fault: false,
            charge_blocked: false,
            balancing: self.balance_bits.1,
        }
    }
}

/// The kind of day.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sky {
    /// Clear.
    Sunny,
    /// Clouds passing.
    Mixed,
    /// Overcast.
    Overcast,
}

/// One day's weather and loads.
#[derive(Debug, Clone)]
pub struct Day {
    /// The sky.
    pub sky: Sky,
    sunrise_s: f64,
    sunset_s: f64,
    peak_a: f64,
    /// Clouds: (start, end) of each cloud, s of the day, and how much sun
    /// they leave.
    clouds: Vec<(f64, f64, f64)>,
    /// Appliances: (start, end, A).
    appliances: Vec<(f64, f64, f64)>,
    /// A load on all day (a deep day's heater), A.
    extra_load_a: f64,
}

impl Day {
    /// Day `n` of the year from `rng`.
    fn new(n: u64, rng: &mut Rng) -> Self {
        // Day length 9 h (winter) to 15 h (summer); the year starts in spring.
        let season = (2.0 * std::f64::consts::PI * n as f64 / 365.0).sin();
        let length_h = 12.0 + 3.0 * season;
        let noon = 13.0 * 3600.0;
        let r = rng.next_f64();
        let sky = if r < 0.55 {
            Sky::Sunny
        } else if r < 0.85 {
            Sky::Mixed
        } else {
            Sky::Overcast
        };
        // Solar peak into the inverter's DC side, A at the battery's voltage:
        // a 6 kWp array, less in winter.
        let peak_a = (90.0 + 25.0 * season)
            * match sky {
                Sky::Sunny => 1.0,
                Sky::Mixed => 0.85,
                Sky::Overcast => 0.2,
            };
        let mut clouds = Vec::new();
        if sky == Sky::Mixed {
            for _ in 0..rng.below(12) + 4 {
                let at = rng.range_f64(noon - length_h * 1800.0, noon + length_h * 1800.0);
                clouds.push((
                    at,
                    at + rng.range_f64(300.0, 2400.0),
                    rng.range_f64(0.1, 0.5),
                ));
            }
        }
        let mut appliances = Vec::new();
        for _ in 0..rng.below(4) + 1 {
            let at = rng.range_f64(6.0 * 3600.0, 23.0 * 3600.0);
            appliances.push((
                at,
                at + rng.range_f64(600.0, 3600.0),
                rng.range_f64(5.0, 25.0),
            ));
        }
        Self {
            sky,
            sunrise_s: noon - length_h * 1800.0,
            sunset_s: noon + length_h * 1800.0,
            peak_a,
            clouds,
            appliances,
            extra_load_a: 0.0,
        }
    }

    /// Makes it a deep day: overcast, and `extra_a` more load all day.
    fn deepen(&mut self, extra_a: f64) {
        let sun = match self.sky {
            Sky::Sunny => 0.2,
            Sky::Mixed => 0.2 / 0.85,
            Sky::Overcast => 1.0,
        };
        self.peak_a *= sun;
        self.sky = Sky::Overcast;
        self.clouds.clear();
        self.extra_load_a = extra_a;
    }

    /// Solar current at `t` s of the day, A.
    fn sun_a(&self, t: f64) -> f64 {
        if t <= self.sunrise_s || t >= self.sunset_s {
            return 0.0;
        }
        let x = (t - self.sunrise_s) / (self.sunset_s - self.sunrise_s);
        let mut a = self.peak_a * (std::f64::consts::PI * x).sin().powf(1.5);
        for &(from, to, left) in &self.clouds {
            if t >= from && t < to {
                a *= left;
            }
        }
        a
    }

    /// House load at `t` s of the day, A.
    fn load_a(&self, t: f64) -> f64 {
        let h = t / 3600.0;
        let mut a = 3.0 + self.extra_load_a;
        if (6.5..8.5).contains(&h) {
            a += 8.0;
        }
        if (18.0..22.0).contains(&h) {
            a += 12.0;
        }
        for &(from, to, amps) in &self.appliances {
            if t >= from && t < to {
                a += amps;
            }
        }
        a
    }

    /// Whether `t` is a quiet hour: no sun, so nothing at the top of a charge.
    fn quiet(&self, t: f64) -> bool {
        t < self.sunrise_s - 600.0 || t > self.sunset_s + 600.0
    }
}

/// How the inverter treats the limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InverterKind {
    /// Obeys them; above CVL it stops charging.
    Obeys,
    /// Obeys them, and above CVL pulls the pack down to CVL into the grid.
    Exporter,
    /// Every current limit exceeded by 20 %.
    Overshoot,
    /// A charge limit of 0 A taken as [`IGNORED_CHARGE_A`].
    IgnoresZero,
}

impl InverterKind {
    /// Every kind.
    pub const ALL: [Self; 4] = [
        Self::Obeys,
        Self::Exporter,
        Self::Overshoot,
        Self::IgnoresZero,
    ];
    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Obeys => "obeys",
            Self::Exporter => "exporter",
            Self::Overshoot => "overshoot-20%",
            Self::IgnoresZero => "ignores-0A",
        }
    }
}

/// The end-of-charge policy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Policy {
    /// Before end-of-charge control: float at the tail current, CVL at once,
    /// no balance hold, no periodic full charge.
    Before,
    /// The defaults of today's firmware.
    Now,
    /// Today's defaults with an SOC ceiling of 90 % for daily cycling.
    Ceiling90,
}

impl Policy {
    /// Charge control's settings for it.
    pub fn config(self) -> ChargeConfig {
        match self {
            Self::Before => ChargeConfig {
                balance_hold_us: 0,
                full_charge_days: 0,
                float_step_mv_per_min: 0,
                soc_ceiling_pct: 100,
                ..ChargeConfig::default()
            },
            Self::Now => ChargeConfig::default(),
            Self::Ceiling90 => ChargeConfig {
                soc_ceiling_pct: 90,
                ..ChargeConfig::default()
            },
        }
    }
    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Before => "before",
            Self::Now => "end-of-charge",
            Self::Ceiling90 => "soc_ceiling=90",
        }
    }
}

/// One charge's end.
#[derive(Debug, Clone, Copy)]
struct ChargeEnd {
    spread_mv: u16,
    runner: bool,
}

/// The figures of a run.
#[derive(Debug, Clone, Default)]
pub struct YearFigures {
    /// Days run.
    pub days: u64,
    /// Sunny days.
    pub sunny_days: u64,
    /// Days that reached float.
    pub float_days: u64,
    /// Sunny days that reached float.
    pub sunny_float_days: u64,
    /// The spread at the end of each day's charge (days whose charge reached
    /// the absorption target), mV, with the day.
    pub end_spreads: Vec<(u64, u16)>,
    /// Days the runner cell ended the charge (it, not the pack, at the target).
    pub runner_days: u64,
    /// The highest cell ever, mV.
    pub max_cell_mv: u16,
    /// Energy pushed to the grid by the inverter pulling the pack down to CVL
    /// on the way into float and in float, Wh.
    pub exported_wh: f64,
    /// The same while charging (CVL lowered at once for a runner cell), Wh.
    pub exported_runner_wh: f64,
    /// CVL changes.
    pub cvl_changes: u64,
    /// Hours run.
    pub hours: f64,
    /// Charge bled by the balancer, Ah.
    pub balanced_ah: f64,
    /// Time in the balance hold, h.
    pub held_h: f64,
    /// Energy into the pack, kWh.
    pub charged_kwh: f64,
}

impl YearFigures {
    /// Share of the days after `from_day` whose charge ended with the spread
    /// within `limit_mv`, %.
    pub fn within_pct(&self, from_day: u64, limit_mv: u16) -> f64 {
        let days: Vec<_> = self
            .end_spreads
            .iter()
            .filter(|d| d.0 >= from_day)
            .collect();
        if days.is_empty() {
            return 0.0;
        }
        100.0 * days.iter().filter(|d| d.1 <= limit_mv).count() as f64 / days.len() as f64
    }
    /// The `p`-th percentile of the end spreads after `from_day`, mV.
    pub fn spread_percentile(&self, from_day: u64, p: f64) -> u16 {
        let mut v: Vec<u16> = self
            .end_spreads
            .iter()
            .filter(|d| d.0 >= from_day)
            .map(|d| d.1)
            .collect();
        v.sort_unstable();
        if v.is_empty() {
            return 0;
        }
        let i = ((v.len() - 1) as f64 * p / 100.0).round() as usize;
        v.get(i).copied().unwrap_or(0)
    }
    /// Sunny days that reached float, %.
    pub fn sunny_float_pct(&self) -> f64 {
        100.0 * self.sunny_float_days as f64 / self.sunny_days.max(1) as f64
    }
    /// CVL changes per hour.
    pub fn cvl_changes_per_hour(&self) -> f64 {
        self.cvl_changes as f64 / self.hours.max(1e-9)
    }
}

/// Steps: at the top of a charge and while the sun shines, this long, s.
const BUSY_STEP_S: u64 = 5;
/// In quiet hours, s.
const QUIET_STEP_S: u64 = 60;
/// With a cell in the knee (at or above [`KNEE_MV`]), s: the bridge reads
/// the BMS several times a second, and a cell at the top of its knee moves
/// tens of mV in 5 s at a bulk current.
const KNEE_STEP_S: u64 = 1;
/// Where the knee starts, mV.
const KNEE_MV: u16 = 3450;

/// Runs `days` days of `seed` under `config` behind `kind`.
pub fn run(seed: u64, days: u64, config: ChargeConfig, kind: InverterKind) -> YearFigures {
    run_with(seed, days, config, kind, None)
}

/// [`run`], with the capacity measure's additions when `watch` is given.
fn run_with(
    seed: u64,
    days: u64,
    config: ChargeConfig,
    kind: InverterKind,
    mut watch: Option<&mut Watch>,
) -> YearFigures {
    let mut rng = Rng::new(seed);
    let mut pack = Pack::new(seed, 60.0);
    let mut control = ChargeControl::new(config);
    let s = settings();
    if let Some(w) = watch.as_deref_mut() {
        pack.fade(seed);
        w.start(&pack);
    }
    let mut f = YearFigures {
        days,
        ..YearFigures::default()
    };
    let mut last_cvl: Option<u16> = None;
    // The highest cell now (after each step: the next step's choice of length).
    let mut top = pack.cells_mv().iter().copied().max().unwrap_or(0);
    let over = if kind == InverterKind::Overshoot {
        1.2
    } else {
        1.0
    };
    for n in 0..days {
        let mut day = Day::new(n, &mut rng);
        if let Some(w) = watch.as_deref_mut() {
            w.shape(n, &mut day);
        }
        let mut reached_float = false;
        let mut end: Option<ChargeEnd> = None;
        let mut t = 0u64;
        while t < DAY_S {
            let dt = if day.quiet(t as f64) {
                QUIET_STEP_S
            } else if top >= KNEE_MV {
                KNEE_STEP_S
            } else {
                BUSY_STEP_S
            };
            let now_us = (n * DAY_S + t) * 1_000_000;
            let state = pack.state();
            let was = control.phase();
            let (limits, _) = control.update(now_us, &s, &state);
            if was == Phase::Absorption && control.phase() == Phase::Float {
                reached_float = true;
            }
            if last_cvl.is_some_and(|c| c != limits.cvl_dv) {
                f.cvl_changes += 1;
            }
            last_cvl = Some(limits.cvl_dv);
            let stage = control.stage();
            if matches!(stage, Stage::BalanceHeld { .. }) {
                f.held_h += dt as f64 / 3600.0;
            }
            if matches!(stage, Stage::Absorption | Stage::BalanceHeld { .. })
                || (was == Phase::Absorption && control.phase() == Phase::Float)
            {
                let avg = state.pack_v * 1000.0 / CELLS as f32;
                end = Some(ChargeEnd {
                    spread_mv: state.max_cell_mv.saturating_sub(state.min_cell_mv),
                    runner: f32::from(state.max_cell_mv) - avg
                        > f32::from(config.runner_tolerance_mv),
                });
            }

            // The inverter.
            let cvl = f64::from(limits.cvl_dv) / 10.0;
            let mut ccl = f64::from(limits.ccl_da) / 10.0 * over;
            if kind == InverterKind::IgnoresZero && limits.ccl_da == 0 {
                ccl = IGNORED_CHARGE_A;
            }
            let dcl = f64::from(limits.dcl_da) / 10.0 * over;
            let tod = t as f64;
            let surplus = day.sun_a(tod) - day.load_a(tod);
            let rest = pack.rest_volts();
            // Constant voltage: no more than brings the pack to CVL.
            let cv_a = ((cvl - rest) / pack.r_ohm()).max(0.0);
            let mut i = if surplus > 0.0 {
                surplus.min(ccl).min(cv_a).min(CHARGER_MAX_A)
            } else {
                -(-surplus).min(dcl)
            };
            if kind == InverterKind::Exporter && rest > cvl + EXPORT_DEADBAND_V {
                // Pulls the pack down to CVL, into the grid.
                let pull = ((rest - cvl - EXPORT_DEADBAND_V) / pack.r_ohm()).min(dcl);
                if pull > -i {
                    let wh = (pull + i.min(0.0)) * rest * dt as f64 / 3600.0;
                    if control.phase() == Phase::Float {
                        f.exported_wh += wh;
                    } else {
                        f.exported_runner_wh += wh;
                    }
                    i = -pull;
                }
            }
            if i > 0.0 {
                f.charged_kwh += i * pack.volts() * dt as f64 / 3.6e6;
            }
            if let Some(w) = watch.as_deref_mut() {
                w.observe(&pack, i, now_us, dt, &stage, &s);
            }
            pack.step(i, dt as f64);
            top = pack.cells_mv().iter().copied().max().unwrap_or(0);
            f.max_cell_mv = f.max_cell_mv.max(top);
            t += dt;
        }
        f.hours += 24.0;
        if day.sky == Sky::Sunny {
            f.sunny_days += 1;
        }
        if reached_float {
            f.float_days += 1;
            if day.sky == Sky::Sunny {
                f.sunny_float_days += 1;
            }
        }
        if let Some(e) = end {
            f.end_spreads.push((n, e.spread_mv));
            if e.runner {
                f.runner_days += 1;
            }
        }
    }
    f.balanced_ah = pack.balanced_ah;
    f
}

/// One line of figures, as the `year` report and the docs print it.
pub fn row(label: &str, f: &YearFigures, from_day: u64, limit_mv: u16) -> String {
    format!(
        "{label:<34} {:>5.1}% {:>5.1}% {:>4} {:>4} {:>5.1}% {:>4} {:>5} {:>8.1} {:>8.1} {:>5.2} {:>6.1} {:>6.1}",
        f.sunny_float_pct(),
        100.0 * f.float_days as f64 / f.days.max(1) as f64,
        f.spread_percentile(from_day, 50.0),
        f.spread_percentile(from_day, 95.0),
        f.within_pct(from_day, limit_mv),
        f.runner_days,
        f.max_cell_mv,
        f.exported_wh,
        f.exported_runner_wh,
        f.cvl_changes_per_hour(),
        f.balanced_ah,
        f.held_h,
    )
}

/// The header of [`row`].
pub fn header() -> String {
    format!(
        "{:<34} {:>6} {:>6} {:>4} {:>4} {:>6} {:>4} {:>5} {:>8} {:>8} {:>5} {:>6} {:>6}",
        "policy / inverter / seed",
        "sunFl",
        "float",
        "p50",
        "p95",
        "≤308",
        "run",
        "maxmV",
        "floatWh",
        "runnerWh",
        "cvl/h",
        "balAh",
        "heldh"
    )
}

// ---------------------------------------------------------------------------
// The capacity measure (issue 55): the firmware's day book and capacity
// estimate fed with the year's pack, against the simulated truth.

/// Capacity fade of a cell over a year, share (each cell ±30 % of it).
pub const FADE_PER_YEAR: f64 = 0.03;
/// The simulated BMS's "charge finished current" (304), A: with the highest
/// cell at 300 and the charge current below it, the BMS says "fully charged"
/// (status 0x92 once the current is at rest), until the pack discharges.
pub const CHARGE_FINISHED_A: f64 = 5.0;
/// A current within ±this is at rest for the BMS's status, A.
pub const IDLE_BAND_A: f64 = 0.5;
/// The bridge reads the BMS at least this often, s: a step of a minute is
/// fed to the firmware as six snapshots (its current is constant over it).
pub const FEED_S: u64 = 10;

/// One capacity estimate of a run against the truth then.
#[derive(Debug, Clone, Copy)]
pub struct CapacityPoint {
    /// The day it came.
    pub day: u64,
    /// The run's estimate.
    pub estimate: Estimate,
    /// The reported capacity then (the median of the last five).
    pub median: Estimate,
    /// The weakest cell's capacity then, Ah: the truth.
    pub truth_ah: f64,
    /// The weakest cell's charge at the last "fully charged", Ah: what the
    /// pack could give from full.
    pub usable_ah: f64,
}

impl CapacityPoint {
    /// The run's estimate against the truth, %.
    pub fn error_pct(&self) -> f64 {
        (f64::from(self.estimate.cah) / 100.0 - self.truth_ah) / self.truth_ah * 100.0
    }
    /// The reported capacity against the truth, %.
    pub fn median_error_pct(&self) -> f64 {
        (f64::from(self.median.cah) / 100.0 - self.truth_ah) / self.truth_ah * 100.0
    }
}

/// The figures of the capacity measure.
#[derive(Debug, Clone, Default)]
pub struct CapacityFigures {
    /// Days run.
    pub days: u64,
    /// Deep days (overcast, with a heater's load).
    pub deep_days: u64,
    /// Times the lowest cell crossed down through the knee (any current).
    pub knee_crossings: u64,
    /// Times the BMS said "fully charged" after a charge.
    pub full_charges: u64,
    /// Each qualifying run's estimate.
    pub points: Vec<CapacityPoint>,
    /// The reported capacity at the end.
    pub last: Option<Estimate>,
    /// The weakest cell's capacity at the start and at the end, Ah.
    pub truth_ah: (f64, f64),
    /// Day records closed, and how many of them came back from their bytes
    /// unchanged.
    pub records: (u64, u64),
}

impl CapacityFigures {
    /// The largest error of a run's estimate, % (signed).
    pub fn worst_error_pct(&self) -> f64 {
        self.points
            .iter()
            .map(CapacityPoint::error_pct)
            .fold(0.0, |a, e| if e.abs() > a.abs() { e } else { a })
    }
    /// The mean absolute error of the runs' estimates, %.
    pub fn mean_error_pct(&self) -> f64 {
        let n = self.points.len().max(1) as f64;
        self.points.iter().map(|p| p.error_pct().abs()).sum::<f64>() / n
    }
}

/// The capacity measure's side of a run: the deep days, the BMS's status,
/// the firmware's day book and estimator.
struct Watch {
    deep: bool,
    spells: Rng,
    next_spell: u64,
    spell_left: u64,
    extra_a: f64,
    /// The simulated BMS's "fully charged" latch.
    full: bool,
    /// Charge control's stage at the last step.
    last_stage: Option<Stage>,
    usable_ah: f64,
    last_min_mv: u16,
    book: DayBook,
    capacity: Capacity,
    f: CapacityFigures,
}

impl Watch {
    fn new(seed: u64, deep: bool) -> Self {
        let mut spells = Rng::new(seed ^ 0xDEE9);
        let next_spell = spells.range_u64(10, 30);
        Self {
            deep,
            spells,
            next_spell,
            spell_left: 0,
            extra_a: 0.0,
            full: false,
            last_stage: None,
            usable_ah: 0.0,
            last_min_mv: 0,
            book: DayBook::new(0),
            capacity: Capacity::new(),
            f: CapacityFigures::default(),
        }
    }

    fn start(&mut self, pack: &Pack) {
        self.f.truth_ah.0 = pack
            .capacities_ah()
            .into_iter()
            .fold(f64::INFINITY, f64::min);
    }

    /// Deep spells: every 18-35 days, 2-3 overcast days with 8-14 A more
    /// load (a heater), drawn from the seed.
    fn shape(&mut self, n: u64, day: &mut Day) {
        if !self.deep {
            return;
        }
        if self.spell_left == 0 && n >= self.next_spell {
            self.spell_left = self.spells.range_u64(2, 3);
            self.extra_a = self.spells.range_f64(8.0, 14.0);
            self.next_spell = n + self.spell_left + self.spells.range_u64(18, 35);
        }
        if self.spell_left > 0 {
            day.deepen(self.extra_a);
            self.spell_left -= 1;
            self.f.deep_days += 1;
        }
    }

    /// A step of `dt` s from `now_us` at `i` A: what the BMS reports, fed to
    /// the firmware every [`FEED_S`] s of it.
    fn observe(
        &mut self,
        pack: &Pack,
        i: f64,
        now_us: u64,
        dt: u64,
        stage: &Stage,
        s: &PackSettings,
    ) {
        let mv = pack.cells_mv_at(i);
        let min = mv.iter().copied().min().unwrap_or(0);
        let max = mv.iter().copied().max().unwrap_or(0);
        if max >= s.fully_charged_mv && (0.0..CHARGE_FINISHED_A).contains(&i) {
            if !self.full {
                self.f.full_charges += 1;
            }
            self.full = true;
        }
        if i < -IDLE_BAND_A {
            self.full = false;
        }
        // The bridge's own end of a charge (the station hands that snapshot
        // to the estimate as "fully charged" too).
        let finished = tinybms_firmware::history::capacity::charge_finished(
            self.last_stage.as_ref(),
            Some(stage),
        );
        self.last_stage = Some(*stage);
        if finished {
            self.f.full_charges += 1;
        }
        let status = if finished {
            OnlineStatus::FullyCharged
        } else if i > IDLE_BAND_A {
            OnlineStatus::Charging
        } else if i < -IDLE_BAND_A {
            OnlineStatus::Discharging
        } else if self.full {
            OnlineStatus::FullyCharged
        } else {
            OnlineStatus::Idle
        };
        let charges = pack.charges_ah();
        if status == OnlineStatus::FullyCharged {
            self.usable_ah = charges.into_iter().fold(f64::INFINITY, f64::min);
        }
        if self.last_min_mv >= LFP_KNEE_MV && min < LFP_KNEE_MV {
            self.f.knee_crossings += 1;
        }
        self.last_min_mv = min;
        let snap = snapshot(&mv, pack.volts_at(i), i, status);
        let mut t = now_us;
        while t < now_us + dt * 1_000_000 {
            self.book.on_snapshot(t, &snap, true, Some(s), Some(stage));
            if let Some(e) = self.capacity.on_snapshot(t, &snap, true, Some(s)) {
                self.book.on_estimate(&e);
                let truth_ah = pack
                    .capacities_ah()
                    .into_iter()
                    .fold(f64::INFINITY, f64::min);
                self.f.points.push(CapacityPoint {
                    day: t / (DAY_S * 1_000_000),
                    estimate: e,
                    median: self.capacity.estimate().unwrap_or(e),
                    truth_ah,
                    usable_ah: self.usable_ah,
                });
            }
            if let Some(r) = self.book.poll(t, None) {
                self.f.records.0 += 1;
                if DayRecord::decode(&r.encode()) == Ok(r) {
                    self.f.records.1 += 1;
                }
            }
            t += FEED_S * 1_000_000;
        }
    }
}

/// What the simulated BMS reports: registers 0-55 as the bridge decodes them.
fn snapshot(mv: &[u16; CELLS], volts: f64, current_a: f64, status: OnlineStatus) -> LiveSnapshot {
    let mut raw = heapless::Vec::new();
    for &v in mv {
        let _fits = raw.push(v.saturating_mul(10));
    }
    LiveSnapshot {
        cells: Cells {
            first_register: 0,
            raw,
        },
        cell_count: CELLS as u16,
        lifetime_s: 0,
        estimated_time_left_s: 0,
        pack_voltage_v: volts as f32,
        pack_current_a: current_a as f32,
        min_cell_mv: mv.iter().copied().min().unwrap_or(0),
        max_cell_mv: mv.iter().copied().max().unwrap_or(0),
        external1_dc: Some(250),
        external2_dc: None,
        distance_left_km: 0,
        soh_raw: 50_000,
        soc_raw: 0,
        internal_dc: 250,
        status,
        balancing_decision_bits: 0,
        real_balancing_bits: 0,
        speed_kmh: 0.0,
    }
}

/// A year of `seed` (today's end-of-charge control, an inverter that obeys)
/// with cells that fade ([`FADE_PER_YEAR`]) and, when `deep`, deep spells
/// that take the pack down to its knee; the firmware's
/// [`tinybms_firmware::history`] fed with what the BMS reports.
pub fn run_capacity(seed: u64, days: u64, deep: bool) -> CapacityFigures {
    let mut w = Watch::new(seed, deep);
    run_with(
        seed,
        days,
        Policy::Now.config(),
        InverterKind::Obeys,
        Some(&mut w),
    );
    w.f.days = days;
    w.f.last = w.capacity.estimate();
    w.f.truth_ah.1 = w.f.points.last().map_or(w.f.truth_ah.0, |p| p.truth_ah);
    w.f
}

/// One line of the capacity measure.
pub fn capacity_row(seed: u64, f: &CapacityFigures) -> String {
    let last = f.last.map_or("unknown".to_string(), |e| {
        format!(
            "{:.1} Ah ±{:.1}%",
            f64::from(e.cah) / 100.0,
            f64::from(e.uncertainty_permille) / 10.0
        )
    });
    format!(
        "{seed:>4} {:>5} {:>5} {:>5} {:>5} {:>+7.2}% {:>6.2}% {:>22} {:>9.1} {:>9.1} {:>7}",
        f.deep_days,
        f.knee_crossings,
        f.full_charges,
        f.points.len(),
        f.worst_error_pct(),
        f.mean_error_pct(),
        last,
        f.truth_ah.0,
        f.truth_ah.1,
        format!("{}/{}", f.records.1, f.records.0),
    )
}

/// The header of [`capacity_row`].
pub fn capacity_header() -> String {
    format!(
        "{:>4} {:>5} {:>5} {:>5} {:>5} {:>8} {:>7} {:>22} {:>9} {:>9} {:>7}",
        "seed",
        "deep",
        "knee",
        "full",
        "runs",
        "worst",
        "mean",
        "reported at the end",
        "truth0 Ah",
        "truth Ah",
        "days"
    )
}
