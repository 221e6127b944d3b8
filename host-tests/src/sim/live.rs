//! The live pack model: a slow current model (discharge / idle / charge
//! phases), SOC integrated over the capacity, cell voltages from an
//! open-circuit-voltage curve plus I·R, fixed per-cell offsets and noise,
//! temperatures that drift and warm with current, balancing bits, statistics
//! maxima. Stepped once per virtual second; every draw comes from its own seeded
//! stream, so the values depend on the seed and the virtual time only (not on
//! how often the caller polls, nor on the protocol traffic).

use super::config::PackModel;
use super::rng::Rng;
use protocol_core::events::EventId;

/// Step of the model, µs.
pub(crate) const STEP_US: u64 = 1_000_000;

/// Online status values (Rev D §3.1, register 50).
pub(crate) const STATUS_CHARGING: u16 = 0x91;
pub(crate) const STATUS_FULLY_CHARGED: u16 = 0x92;
pub(crate) const STATUS_DISCHARGING: u16 = 0x93;
pub(crate) const STATUS_IDLE: u16 = 0x97;
pub(crate) const STATUS_FAULT: u16 = 0x9B;

/// |current| below this is "idle", A.
const IDLE_BAND_A: f64 = 0.5;

/// Disconnected external sensor (Rev D §1.1.18).
pub(crate) const SENSOR_DISCONNECTED: u16 = 0x8000;

/// Open-circuit voltage (V) against SOC (%), per chemistry.
const OCV_LFP: &[(f64, f64)] = &[
    (0.0, 2.90),
    (5.0, 3.15),
    (10.0, 3.22),
    (20.0, 3.26),
    (30.0, 3.28),
    (40.0, 3.29),
    (50.0, 3.30),
    (60.0, 3.31),
    (70.0, 3.32),
    (80.0, 3.33),
    (90.0, 3.34),
    (95.0, 3.37),
    (100.0, 3.50),
];
const OCV_NMC: &[(f64, f64)] = &[
    (0.0, 3.30),
    (5.0, 3.45),
    (10.0, 3.52),
    (20.0, 3.60),
    (30.0, 3.66),
    (40.0, 3.72),
    (50.0, 3.79),
    (60.0, 3.86),
    (70.0, 3.93),
    (80.0, 4.00),
    (90.0, 4.08),
    (100.0, 4.18),
];

fn ocv(curve: &[(f64, f64)], soc: f64) -> f64 {
    let mut prev = (0.0, 0.0);
    for (i, &(s, v)) in curve.iter().enumerate() {
        if soc <= s {
            if i == 0 {
                return v;
            }
            let f = (soc - prev.0) / (s - prev.0);
            return prev.1 + f * (v - prev.1);
        }
        prev = (s, v);
    }
    prev.1
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    Discharge,
    Idle,
    Charge,
}

/// Settings the model reads from the register file at every step.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Params {
    /// Register 306, Ah.
    pub capacity_ah: f64,
    /// Register 303, mV.
    pub early_balancing_mv: u16,
    /// Register 308, mV.
    pub allowed_disbalance_mv: u16,
    /// Register 304, A.
    pub charge_finished_a: f64,
    /// Register 317, A.
    pub discharge_cutoff_a: f64,
    /// Register 318, A.
    pub charge_cutoff_a: f64,
    /// A fault is latched: the switches are open, no current flows.
    pub fault: bool,
}

impl Params {
    pub(crate) fn from_registers(regs: &[u16], fault: bool) -> Self {
        let g = |a: usize| regs.get(a).copied().unwrap_or(0);
        Self {
            capacity_ah: (f64::from(g(306)) * 0.01).max(0.1),
            early_balancing_mv: g(303),
            allowed_disbalance_mv: g(308),
            charge_finished_a: f64::from(g(304)) * 0.001,
            discharge_cutoff_a: f64::from(g(317)).max(1.0),
            charge_cutoff_a: f64::from(g(318)).max(1.0),
            fault,
        }
    }
}

#[derive(Debug, Clone)]
pub(crate) struct Live {
    curve: &'static [(f64, f64)],
    cells: usize,
    first_reg: usize,
    /// Per-cell internal resistance, Ω.
    r_cell: f64,
    soc: f64,
    current: f64,
    phase: Phase,
    phase_left_s: u32,
    amplitude: f64,
    full: bool,
    offsets_v: [f64; 16],
    cells_raw: [u16; 16],
    ambient: f64,
    t_int: f64,
    t_ext1: f64,
    ext2_connected: bool,
    pub(crate) lifetime_s: u32,
    rng: Rng,
    /// Closed loop: the current is imposed from outside (an inverter model), A.
    pub(crate) forced_current: Option<f64>,
    /// Closed loop: the temperatures are imposed, °C.
    pub(crate) forced_temp: Option<f64>,
    /// Charge pushed in past 100 % SOC, Ah: the voltage knee of a full cell.
    over_ah: f64,
    /// Charge drawn out past 0 % SOC, Ah: the voltage knee of an empty cell
    /// (closed loop only: an inverter that keeps discharging).
    under_ah: f64,
    /// What the BMS's SOC reads above the truth, % (its estimate drifted).
    pub(crate) soc_bias: f64,
    capacity_ah: f64,
}

impl Live {
    pub(crate) fn new(model: PackModel, mut rng: Rng, capacity_ah: f64, lifetime_s: u32) -> Self {
        let (curve, r_cell, soc, ambient) = match model {
            PackModel::LiFePO4_16S => (OCV_LFP, 0.0003, 65.0, 24.0),
            PackModel::LiIon_14S => (OCV_NMC, 0.0015, 62.0, 22.0),
        };
        let mut offsets_v = [0.0; 16];
        for o in offsets_v.iter_mut() {
            *o = rng.range_f64(-0.004, 0.004);
        }
        let amplitude = (rng.range_f64(0.04, 0.12) * capacity_ah).clamp(2.0, 40.0);
        let phase_left_s = rng.range_u64(900, 1800) as u32;
        let mut live = Self {
            curve,
            cells: model.cell_count(),
            first_reg: usize::from(model.first_cell_register()),
            r_cell,
            soc,
            current: -amplitude,
            phase: Phase::Discharge,
            phase_left_s,
            amplitude,
            full: false,
            offsets_v,
            cells_raw: [0; 16],
            ambient,
            t_int: ambient + 3.0,
            t_ext1: ambient + 0.5,
            ext2_connected: model == PackModel::LiFePO4_16S,
            lifetime_s,
            rng,
            forced_current: None,
            forced_temp: None,
            over_ah: 0.0,
            under_ah: 0.0,
            soc_bias: 0.0,
            capacity_ah,
        };
        live.compute_cells(0.0);
        live
    }

    /// Sets the SOC (a write to register 328 took effect), percent.
    pub(crate) fn set_soc(&mut self, soc: f64) {
        self.soc = soc.clamp(0.0, 100.0);
        self.full = self.soc >= 99.9;
    }

    /// Open-circuit voltage of the pack now (the cells' OCV at this SOC, the
    /// knee of a full cell and the fixed offsets, no I·R), V.
    pub(crate) fn open_circuit_v(&self) -> f64 {
        let base = ocv(self.curve, self.soc) + self.knees();
        (0..self.cells.min(16))
            .map(|i| base + self.offsets_v.get(i).copied().unwrap_or(0.0))
            .sum()
    }

    /// The knees of a full and of an empty cell, V: +0.15 V per 0.1 % of
    /// capacity pushed in past full (at most 1.5 V), −0.05 V per 0.1 %
    /// drawn out past empty (at most 2.5 V).
    fn knees(&self) -> f64 {
        if self.capacity_ah <= 0.0 {
            return 0.0;
        }
        let per_mille = |ah: f64| ah / self.capacity_ah * 1000.0;
        (per_mille(self.over_ah) * 0.15).min(1.5) - (per_mille(self.under_ah) * 0.05).min(2.5)
    }

    /// Internal resistance of the pack (cells in series), Ω.
    pub(crate) fn resistance_ohm(&self) -> f64 {
        self.r_cell * self.cells as f64
    }

    /// Sets the internal resistance of every cell, Ω.
    pub(crate) fn set_cell_resistance(&mut self, ohm: f64) {
        self.r_cell = ohm.max(0.0);
    }

    /// Sets the fixed offset of cell `i` (a runner), volts.
    pub(crate) fn set_offset(&mut self, i: usize, v: f64) {
        if let Some(o) = self.offsets_v.get_mut(i) {
            *o = v;
        }
        self.compute_cells(0.0);
    }

    fn compute_cells(&mut self, noise_v: f64) {
        // A full cell's voltage climbs steeply with every Ah pushed past 100 %
        // (the knee at the top of the OCV curve): 0.15 V per 0.1 % of capacity.
        let base = ocv(self.curve, self.soc) + self.knees() + self.current * self.r_cell;
        for i in 0..self.cells.min(16) {
            let noise = if noise_v > 0.0 {
                self.rng.range_f64(-noise_v, noise_v)
            } else {
                0.0
            };
            let off = self.offsets_v.get(i).copied().unwrap_or(0.0);
            let v = (base + off + noise).clamp(0.0, 6.5);
            if let Some(c) = self.cells_raw.get_mut(i) {
                *c = (v * 10_000.0).round() as u16;
            }
        }
    }

    fn start_phase(&mut self, phase: Phase, p: &Params, events: &mut Vec<EventId>) {
        if self.phase == Phase::Charge && phase != Phase::Charge {
            events.push(EventId::ChargerDisconnected);
        }
        self.phase = phase;
        match phase {
            Phase::Discharge => {
                self.phase_left_s = self.rng.range_u64(600, 2400) as u32;
                self.amplitude = (self.rng.range_f64(0.04, 0.2) * p.capacity_ah)
                    .min(0.8 * p.discharge_cutoff_a)
                    .max(1.0);
                if self.soc < 99.0 {
                    self.full = false;
                }
            }
            Phase::Idle => {
                self.phase_left_s = self.rng.range_u64(120, 900) as u32;
                self.amplitude = 0.0;
            }
            Phase::Charge => {
                self.phase_left_s = self.rng.range_u64(1800, 5400) as u32;
                self.amplitude = (self.rng.range_f64(0.05, 0.15) * p.capacity_ah)
                    .min(0.8 * p.charge_cutoff_a)
                    .max(1.0);
                self.full = false;
                events.push(EventId::ChargerConnected);
                events.push(EventId::ChargingStarted);
            }
        }
    }

    /// One step of `STEP_US`. Events the BMS logs are pushed to `events`.
    pub(crate) fn step(&mut self, p: &Params, events: &mut Vec<EventId>) {
        let dt = STEP_US as f64 / 1e6;
        // The knee follows the pack's own capacity (register 306 as it is
        // now), not the capacity it was created with.
        self.capacity_ah = p.capacity_ah;
        self.lifetime_s = self.lifetime_s.wrapping_add(1);
        self.phase_left_s = self.phase_left_s.saturating_sub(1);

        let target = match self.phase {
            Phase::Discharge => {
                if self.soc <= 8.0 || self.phase_left_s == 0 {
                    self.start_phase(Phase::Idle, p, events);
                    0.0
                } else {
                    -self.amplitude
                }
            }
            Phase::Idle => {
                if self.phase_left_s == 0 {
                    let charge = self.soc < 50.0 || (self.soc < 90.0 && self.rng.chance(0.5));
                    let next = if charge {
                        Phase::Charge
                    } else {
                        Phase::Discharge
                    };
                    self.start_phase(next, p, events);
                }
                match self.phase {
                    Phase::Idle => 0.0,
                    Phase::Charge => self.amplitude,
                    Phase::Discharge => -self.amplitude,
                }
            }
            Phase::Charge => {
                // CV taper above 95 %.
                let taper = if self.soc > 95.0 {
                    ((100.0 - self.soc) / 5.0).clamp(0.0, 1.0)
                } else {
                    1.0
                };
                let t = self.amplitude * taper;
                if self.soc >= 99.95 || (self.soc > 95.0 && t < p.charge_finished_a) {
                    self.full = true;
                    events.push(EventId::ChargingDone);
                    self.start_phase(Phase::Idle, p, events);
                    0.0
                } else if self.phase_left_s == 0 && self.soc < 90.0 {
                    // Unplugged before the end; above 90 % the charge runs to
                    // completion (CV phase).
                    self.start_phase(Phase::Idle, p, events);
                    0.0
                } else {
                    t
                }
            }
        };
        let target = if p.fault { 0.0 } else { target };
        if let Some(forced) = self.forced_current {
            // Closed loop: the inverter decides (the BMS's switches still cut
            // it on a fault).
            let i = if p.fault { 0.0 } else { forced };
            self.current = i + self.rng.range_f64(-0.02, 0.02);
            let soc = self.soc + self.current * dt / 3600.0 / p.capacity_ah * 100.0;
            if soc > 100.0 {
                self.over_ah += (soc - 100.0) / 100.0 * p.capacity_ah;
            } else if self.current < 0.0 {
                self.over_ah = (self.over_ah + self.current * dt / 3600.0).max(0.0);
            }
            if soc < 0.0 {
                self.under_ah -= soc / 100.0 * p.capacity_ah;
            } else if self.current > 0.0 {
                self.under_ah = (self.under_ah - self.current * dt / 3600.0).max(0.0);
            }
            if self.current <= 0.05 {
                // Relaxation of the knee at rest, a few minutes.
                self.over_ah *= 0.995;
            }
            self.soc = soc.clamp(0.0, 100.0);
            self.full = self.soc >= 99.9;
            if let Some(t) = self.forced_temp {
                self.t_int = t + 2.0;
                self.t_ext1 = t;
            }
            self.compute_cells(0.0003);
            return;
        }
        let noise_a = if target == 0.0 {
            0.05
        } else {
            0.01 * self.amplitude.max(1.0)
        };
        self.current += (target - self.current) * 0.3 + self.rng.range_f64(-noise_a, noise_a);
        if target == 0.0 && self.current.abs() < 0.2 {
            // Switches open or no load: the sensor reads only its noise.
            self.current = self.rng.range_f64(-0.05, 0.05);
        }

        self.soc =
            (self.soc + self.current * dt / 3600.0 / p.capacity_ah * 100.0).clamp(0.0, 100.0);

        // Temperatures: ambient drifts, the BMS and the pack warm with current.
        self.ambient = (self.ambient + self.rng.range_f64(-0.002, 0.002)).clamp(15.0, 35.0);
        let heat = self.current.abs();
        self.t_int += (self.ambient + 3.0 + heat * 0.04 - self.t_int) / 300.0;
        self.t_ext1 += (self.ambient + 0.5 + heat * 0.02 - self.t_ext1) / 600.0;

        self.compute_cells(0.0003);
    }

    /// Online status for the present state.
    pub(crate) fn status(&self, fault: bool) -> u16 {
        if fault {
            STATUS_FAULT
        } else if self.current > IDLE_BAND_A {
            STATUS_CHARGING
        } else if self.current < -IDLE_BAND_A {
            STATUS_DISCHARGING
        } else if self.full {
            STATUS_FULLY_CHARGED
        } else {
            STATUS_IDLE
        }
    }

    /// Writes every live register (Rev D §3.1) and updates the statistics
    /// maxima (§3.2).
    pub(crate) fn publish(&self, regs: &mut [u16], p: &Params) {
        let cells = self.cells_raw.get(..self.cells.min(16)).unwrap_or(&[]);
        for (i, &c) in cells.iter().enumerate() {
            set_in(regs, self.first_reg + i, c);
        }
        let min_raw = cells.iter().copied().min().unwrap_or(0);
        let max_raw = cells.iter().copied().max().unwrap_or(0);
        let sum: u32 = cells.iter().map(|&c| u32::from(c)).sum();
        // Pack voltage = sum of the cells (0.1 mV each), f32 volts.
        let pack_v = (f64::from(sum) / 10_000.0) as f32;
        set32(regs, 32, self.lifetime_s);
        let time_left = if self.current < -IDLE_BAND_A {
            (self.soc / 100.0 * p.capacity_ah / -self.current * 3600.0) as u32
        } else {
            0
        };
        set32(regs, 34, time_left);
        set32(regs, 36, pack_v.to_bits());
        set32(regs, 38, (self.current as f32).to_bits());
        let reading = (self.soc + self.soc_bias).clamp(0.0, 100.0);
        set32(regs, 46, (reading * 1_000_000.0).round() as u32);
        set32(regs, 54, 0f32.to_bits());
        // Registers 40/41 are in mV, the cells in 0.1 mV: rounded to the nearest mV.
        set_in(regs, 40, raw_to_mv(min_raw));
        set_in(regs, 41, raw_to_mv(max_raw));
        set_in(regs, 42, dc(self.t_ext1));
        let ext2 = if self.ext2_connected {
            dc(self.t_ext1 + 0.3)
        } else {
            SENSOR_DISCONNECTED
        };
        set_in(regs, 43, ext2);
        set_in(regs, 44, 0);
        set_in(regs, 48, dc(self.t_int));
        set_in(regs, 50, self.status(p.fault));
        // Balancing: bit n = n-th detected cell (bit 0 = first cell, Rev D §3.1),
        // as the TinyBMS's balancer decides (see `balancer`).
        let mv: heapless::Vec<u16, 16> = cells.iter().map(|&c| raw_to_mv(c)).collect();
        let (decision, real) = super::balancer::bits(
            &mv,
            p.early_balancing_mv,
            p.allowed_disbalance_mv,
            self.current,
        );
        set_in(regs, 51, decision);
        set_in(regs, 52, real);
        set_in(regs, 53, self.cells as u16);

        // Statistics maxima (Rev D §3.2).
        let g = |regs: &[u16], a: usize| regs.get(a).copied().unwrap_or(0);
        let da = (self.current.abs() * 10.0).round().min(65535.0) as u16;
        if self.current < 0.0 && da > g(regs, 102) {
            set_in(regs, 102, da);
        }
        if self.current > 0.0 && da > g(regs, 103) {
            set_in(regs, 103, da);
        }
        if max_raw - min_raw > g(regs, 104) {
            set_in(regs, 104, max_raw - min_raw);
        }
        let t = self.pack_temp_c();
        let [tmin, tmax] = g(regs, 113).to_le_bytes();
        let (tmin, tmax) = ((tmin as i8).min(t), (tmax as i8).max(t));
        set_in(regs, 113, u16::from_le_bytes([tmin as u8, tmax as u8]));
    }

    /// Pack temperature now, °C (for statistics reset).
    pub(crate) fn pack_temp_c(&self) -> i8 {
        self.t_ext1.round().clamp(-128.0, 127.0) as i8
    }
}

fn set_in(regs: &mut [u16], a: usize, v: u16) {
    if let Some(r) = regs.get_mut(a) {
        *r = v;
    }
}

/// A 32-bit value over two registers, low word at the lower address
/// (HARDWARE-NOTES "Values").
fn set32(regs: &mut [u16], a: usize, v: u32) {
    set_in(regs, a, v as u16);
    set_in(regs, a + 1, (v >> 16) as u16);
}

/// 0.1 mV to mV, rounded to nearest.
pub(crate) fn raw_to_mv(raw: u16) -> u16 {
    ((u32::from(raw) + 5) / 10) as u16
}

/// °C to 0.1 °C, as the i16 bits of a register.
fn dc(t: f64) -> u16 {
    ((t * 10.0).round().clamp(-32767.0, 32767.0) as i16) as u16
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing)]
mod tests {
    use super::*;

    fn params() -> Params {
        Params {
            capacity_ah: 50.0,
            early_balancing_mv: 4000,
            allowed_disbalance_mv: 15,
            charge_finished_a: 1.0,
            discharge_cutoff_a: 50.0,
            charge_cutoff_a: 25.0,
            fault: false,
        }
    }

    #[test]
    fn a_charge_ends_with_charging_done_and_fully_charged() {
        let p = params();
        let mut live = Live::new(PackModel::LiIon_14S, Rng::new(3), 50.0, 1000);
        live.set_soc(96.0);
        let mut events = Vec::new();
        live.start_phase(Phase::Charge, &p, &mut events);
        assert_eq!(
            events,
            [EventId::ChargerConnected, EventId::ChargingStarted]
        );
        events.clear();
        for _ in 0..20_000 {
            live.step(&p, &mut events);
            if !events.is_empty() {
                break;
            }
        }
        assert_eq!(
            events,
            [EventId::ChargingDone, EventId::ChargerDisconnected]
        );
        assert!(live.soc > 99.0, "{}", live.soc);
        for _ in 0..30 {
            live.step(&p, &mut events);
        }
        assert_eq!(live.status(false), STATUS_FULLY_CHARGED);
        assert_eq!(live.status(true), STATUS_FAULT);
    }

    #[test]
    fn a_latched_fault_stops_the_current() {
        let mut p = params();
        p.fault = true;
        let mut live = Live::new(PackModel::LiIon_14S, Rng::new(4), 50.0, 1000);
        let mut events = Vec::new();
        for _ in 0..60 {
            live.step(&p, &mut events);
        }
        assert!(live.current.abs() < IDLE_BAND_A, "{}", live.current);
    }

    #[test]
    fn the_knee_follows_the_capacity_the_pack_has_now() {
        // Both packs created with 280 Ah; one is then set to 100 Ah. The same
        // 20 A past full lifts the small one's knee 2.8 times as fast.
        let knee_after = |capacity_ah: f64| {
            let p = Params {
                capacity_ah,
                ..params()
            };
            let mut live = Live::new(PackModel::LiFePO4_16S, Rng::new(5), 280.0, 1000);
            live.set_soc(100.0);
            live.forced_current = Some(20.0);
            let v0 = live.open_circuit_v();
            let mut events = Vec::new();
            for _ in 0..100 {
                live.step(&p, &mut events);
            }
            live.open_circuit_v() - v0
        };
        let (small, big) = (knee_after(100.0), knee_after(280.0));
        assert!(big > 0.0, "{big}");
        assert!((small / big - 2.8).abs() < 0.1, "{small} V against {big} V");
    }

    #[test]
    fn ocv_interpolates() {
        assert_eq!(ocv(OCV_LFP, 50.0), 3.30);
        assert!((ocv(OCV_NMC, 65.0) - 3.895).abs() < 1e-9);
        assert_eq!(ocv(OCV_NMC, 0.0), 3.30);
        assert_eq!(ocv(OCV_NMC, 120.0), 4.18);
    }
}
