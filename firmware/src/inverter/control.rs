//! Charge control: the limits an inverter/charger must obey (CVL, CCL, DCL) and
//! the alarms and warnings it is told about, from the BMS's own values.
//!
//! This is where a bridge can hurt a battery, so every rule is here, in one
//! deterministic function of its inputs and a little state, with its reason:
//!
//! * **CVL = cells × per-cell target** — never a per-cell value, never 0, always
//!   within cells × [316, 315]. The absorption target defaults to the BMS's own
//!   "fully charged voltage" (300), kept [`ChargeConfig::absorption_margin_mv`]
//!   below the over-voltage cutoff (315); the float target is configurable
//!   (default 15/16 of absorption). No cell is ever pushed above the *ceiling*,
//!   315 − [`ChargeConfig::ceiling_margin_mv`].
//! * **Absorption → float** once the highest cell is at the target and the current
//!   has tapered below [`ChargeConfig::tail_current_a`] for
//!   [`ChargeConfig::full_hold_us`]; back to absorption below
//!   [`ChargeConfig::rebulk_soc_pct`].
//! * **A cell running ahead** lowers CVL: while the highest cell is above the
//!   target, CVL = cells × (target − its lead over the average cell, less
//!   [`ChargeConfig::runner_tolerance_mv`]), so the runner — not the average —
//!   settles at the target; released once the runner is 5 mV below the target
//!   (and then only as fast as CVL may rise). A whole pack above a lower target
//!   (float after absorption) is no runner: CVL stays cells × target.
//! * **CCL** from the charge over-current cutoff (318), **DCL** from 317,
//!   each [`ChargeConfig::current_margin_pct`] (20 %) below it — an inverter
//!   that overshoots a limit (real ones do, by up to 20 %) must not trip the
//!   BMS — and capped by configuration. Never from the statistics registers
//!   102/103 (peaks seen).
//! * **Tapers:** CCL goes linearly to 0 as the highest cell climbs through the
//!   [`ChargeConfig::charge_taper_mv`] window below the ceiling (so a cell at the
//!   ceiling gets no current at all); DCL to 0 as the lowest cell falls through
//!   [`ChargeConfig::discharge_taper_mv`] above 316 + [`ChargeConfig::discharge_margin_mv`].
//! * **Temperature:** no charge at or below the low-temperature charge cutoff
//!   (320) nor at or above over-heat (319), linear in between over
//!   [`ChargeConfig::temperature_margin_c`]; DCL derated the same way near over-heat.
//! * **Faults:** BMS status "fault" → CCL 0 and DCL 0 (the BMS has opened its
//!   switches: nothing to ask of the inverter); a charge-side fault event (over-
//!   voltage, charge over-current, low temperature) → CCL 0 until it recovers.
//! * **A current past its cutoff** (an inverter that ignores a limit other
//!   than 0 — a Multi in island mode feeding its loads): CCL 0 at once past
//!   318, DCL 0 once a discharge past 317 lasted a second (half the BMS's
//!   timeout, 330's high byte, when that is shorter) — well before the BMS
//!   would trip — then the hold and the ramp.
//! * **Hold and ramp:** after a cut (a limit forced to 0: fault, temperature,
//!   a cell at the ceiling), the limit comes back only [`ChargeConfig::limit_hold_us`]
//!   after the cause ended, and then rises at most [`ChargeConfig::ramp_rate_da_per_s`];
//!   lowering is always immediate. A loss of the BMS's data is no such cause:
//!   when fresh data from a healthy battery is back, the discharge limit is
//!   back at once and the charge limit ramps from 0 without the hold
//!   ([`ChargeControl::resume`]). CVL is raised at most
//!   once per [`ChargeConfig::cvl_raise_interval_us`]; lowering is immediate.
//! * **Alarms and warnings** from cells vs cutoffs, temperatures vs cutoffs,
//!   currents vs cutoffs, cell imbalance (308), BMS fault status and link loss;
//!   warnings come before alarms (a margin inside each cutoff).

use protocol_core::views::cell_mv;

use super::finish::{Finish, Stage};
use super::why::{Reasons, Why};
use crate::Instant;

/// Charge control settings; [`Default`] gives the documented defaults.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ChargeConfig {
    /// Absorption target per cell, mV; `None` = the BMS's "fully charged
    /// voltage" (300). Always kept [`ChargeConfig::absorption_margin_mv`] below
    /// 315.
    pub absorption_voltage_mv: Option<u16>,
    /// How far below the over-voltage cutoff (315) the absorption target stays
    /// at least, mV.
    pub absorption_margin_mv: u16,
    /// Float target per cell, mV; `None` = 15/16 of the absorption target.
    pub float_voltage_mv: Option<u16>,
    /// The ceiling: how far below the over-voltage cutoff (315) the highest cell
    /// is always kept (CCL is 0 there), mV.
    pub ceiling_margin_mv: u16,
    /// How far above the under-voltage cutoff (316) discharge stops, mV.
    pub discharge_margin_mv: u16,
    /// CCL goes from full to 0 over this window below (315 − margin), mV.
    pub charge_taper_mv: u16,
    /// DCL goes from full to 0 over this window above (316 + margin), mV.
    pub discharge_taper_mv: u16,
    /// The highest cell may sit this far above the target before CVL is lowered
    /// for it (the ordinary spread of a balanced pack), mV.
    pub runner_tolerance_mv: u16,
    /// Charge current below which a full pack counts as tapered, A.
    pub tail_current_a: f32,
    /// How long the pack must be at the target and tapered before float, µs.
    pub full_hold_us: Instant,
    /// Below this SOC the float phase ends, %.
    pub rebulk_soc_pct: f32,
    /// Absorption is held at most this long per charge (for each day since
    /// the last full charge, up to `full_charge_days` times) while the BMS
    /// balances and the spread is above 308, µs; 0 = never
    /// ([`super::finish`]).
    pub balance_hold_us: Instant,
    /// A full charge every this many days (float ends for it, an SOC
    /// ceiling waits for it); 0 = off.
    pub full_charge_days: u16,
    /// CVL steps down into float at most this fast, mV per cell per minute;
    /// 0 = at once.
    pub float_step_mv_per_min: u16,
    /// Charging pauses at this SOC, % (100 = no ceiling), except for a due
    /// full charge.
    pub soc_ceiling_pct: u8,
    /// Cap on CCL, 0.1 A (`None` = 318 alone).
    pub charge_current_cap_da: Option<u16>,
    /// Cap on DCL, 0.1 A (`None` = 317 alone).
    pub discharge_current_cap_da: Option<u16>,
    /// Temperature derating window inside each cutoff, °C.
    pub temperature_margin_c: i16,
    /// After a limit was lowered, how long before it may rise again, µs.
    pub limit_hold_us: Instant,
    /// How fast a limit may rise, 0.1 A per second.
    pub ramp_rate_da_per_s: u16,
    /// CVL is raised at most this often, µs (lowering is immediate).
    pub cvl_raise_interval_us: Instant,
    /// Warnings start this far inside a voltage cutoff, mV.
    pub warn_margin_mv: u16,
    /// Warnings start at this fraction of a current cutoff, percent.
    pub warn_current_pct: u8,
    /// The largest current limits stay this share below the BMS's
    /// over-current cutoffs (318, 317), percent: an inverter that overshoots
    /// a limit by as much never trips the BMS.
    pub current_margin_pct: u8,
}

impl Default for ChargeConfig {
    fn default() -> Self {
        Self {
            absorption_voltage_mv: None,
            absorption_margin_mv: 100,
            float_voltage_mv: None,
            ceiling_margin_mv: 50,
            discharge_margin_mv: 100,
            charge_taper_mv: 100,
            discharge_taper_mv: 200,
            runner_tolerance_mv: 10,
            tail_current_a: 5.0,
            full_hold_us: 120 * crate::SECOND,
            rebulk_soc_pct: 90.0,
            balance_hold_us: 60 * 60 * crate::SECOND,
            full_charge_days: 7,
            float_step_mv_per_min: 5,
            soc_ceiling_pct: 100,
            charge_current_cap_da: None,
            discharge_current_cap_da: None,
            temperature_margin_c: 5,
            limit_hold_us: 30 * crate::SECOND,
            ramp_rate_da_per_s: 20,
            cvl_raise_interval_us: 20 * crate::SECOND,
            warn_margin_mv: 50,
            warn_current_pct: 90,
            current_margin_pct: 20,
        }
    }
}

/// The BMS settings charge control needs (Rev D §3.4), as read from 300-343.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PackSettings {
    /// 300: fully charged voltage per cell, mV.
    pub fully_charged_mv: u16,
    /// 306: capacity, 0.01 Ah.
    pub capacity_cah: u16,
    /// 307: series cells.
    pub cells: u16,
    /// 308: allowed disbalance, mV.
    pub allowed_disbalance_mv: u16,
    /// 315: over-voltage cutoff per cell, mV.
    pub ov_cutoff_mv: u16,
    /// 316: under-voltage cutoff per cell, mV.
    pub uv_cutoff_mv: u16,
    /// 317: discharge over-current cutoff, A.
    pub discharge_cutoff_a: u16,
    /// 318: charge over-current cutoff, A.
    pub charge_cutoff_a: u16,
    /// 330 high byte: how long a discharge past 317 lasts before the BMS
    /// trips, s.
    pub discharge_cutoff_s: u8,
    /// 319: over-heat cutoff, °C.
    pub overheat_c: i16,
    /// 320: low-temperature charger cutoff, °C.
    pub low_temp_charge_c: i16,
}

impl PackSettings {
    /// From a settings block (registers 300-343); `None` when a needed register
    /// is missing or the values make no sense (no cells, cutoffs inverted).
    pub fn from_registers(b: &protocol_core::response::RegisterBlock) -> Option<Self> {
        use protocol_core::settings::SettingId as S;
        let get = |id: S| u16::try_from(id.read(b)?).ok();
        let signed = |id: S| i16::try_from(id.read(b)?).ok();
        let s = Self {
            fully_charged_mv: get(S::FullyChargedVoltage)?,
            capacity_cah: get(S::BatteryCapacity)?,
            cells: get(S::NumberOfSeriesCells)?,
            allowed_disbalance_mv: get(S::AllowedDisbalance)?,
            ov_cutoff_mv: get(S::OverVoltageCutoff)?,
            uv_cutoff_mv: get(S::UnderVoltageCutoff)?,
            discharge_cutoff_a: get(S::DischargeOverCurrentCutoff)?,
            charge_cutoff_a: get(S::ChargeOverCurrentCutoff)?,
            discharge_cutoff_s: u8::try_from(S::DischargeOverCurrentTimeout.read(b)?).ok()?,
            overheat_c: signed(S::OverHeatCutoff)?,
            low_temp_charge_c: signed(S::LowTemperatureChargerCutoff)?,
        };
        let sane = (1..=MAX_SERIES_CELLS).contains(&s.cells)
            && s.charge_cutoff_a >= 1
            && s.discharge_cutoff_a >= 1
            && s.uv_cutoff_mv >= SANE_CUTOFF_MV.0
            && s.ov_cutoff_mv > s.uv_cutoff_mv
            && s.ov_cutoff_mv <= SANE_CUTOFF_MV.1
            && s.overheat_c > s.low_temp_charge_c;
        sane.then_some(s)
    }
}

/// What charge control reads from a live snapshot.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PackState {
    /// Lowest cell, mV.
    pub min_cell_mv: u16,
    /// Highest cell, mV.
    pub max_cell_mv: u16,
    /// Pack voltage, V.
    pub pack_v: f32,
    /// Pack current, A (positive = charging).
    pub current_a: f32,
    /// SOC, %.
    pub soc_pct: f32,
    /// SOH, %.
    pub soh_pct: f32,
    /// Lowest temperature of the sensors, °C.
    pub min_temp_c: f32,
    /// Highest temperature of the sensors, °C.
    pub max_temp_c: f32,
    /// BMS status register 50 says "fault".
    pub fault: bool,
    /// A charge-side fault event is latched (over-voltage, charge over-current,
    /// low-temperature cutoff) and not yet recovered.
    pub charge_blocked: bool,
    /// Register 52: the cells the BMS is balancing now (bit 0 = cell 1).
    pub balancing: u16,
}

impl PackState {
    /// From a published snapshot.
    pub fn from_snapshot(s: &protocol_core::views::LiveSnapshot) -> Self {
        let mut min_t = s.internal_c();
        let mut max_t = min_t;
        for t in [s.external1_c(), s.external2_c()].into_iter().flatten() {
            min_t = min_t.min(t);
            max_t = max_t.max(t);
        }
        Self {
            min_cell_mv: s
                .cells
                .min()
                .map(|(_, r)| cell_mv(r))
                .unwrap_or(s.min_cell_mv),
            max_cell_mv: s
                .cells
                .max()
                .map(|(_, r)| cell_mv(r))
                .unwrap_or(s.max_cell_mv),
            pack_v: s.pack_voltage_v,
            current_a: s.pack_current_a,
            soc_pct: s.soc_percent(),
            soh_pct: s.soh_percent(),
            min_temp_c: min_t,
            max_temp_c: max_t,
            fault: s.status == protocol_core::events::OnlineStatus::Fault,
            charge_blocked: false,
            balancing: s.real_balancing_bits,
        }
    }
}

/// Absorption or float.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Phase {
    /// Charging to the absorption target.
    Absorption,
    /// Holding the float target.
    Float,
}

/// Level of one alarm/warning condition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Level {
    /// Fine.
    Ok,
    /// Near a limit.
    Warning,
    /// At or past a limit.
    Alarm,
}

/// The conditions inverters are told about (the fields of 0x35A).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Conditions {
    /// Cells vs the over-voltage cutoff.
    pub high_voltage: u8,
    /// Cells vs the under-voltage cutoff.
    pub low_voltage: u8,
    /// Temperatures vs over-heat.
    pub high_temperature: u8,
    /// Temperatures vs the low-temperature cutoff (any current).
    pub low_temperature: u8,
    /// Charging while hot.
    pub high_temperature_charge: u8,
    /// Charging while cold.
    pub low_temperature_charge: u8,
    /// Discharge current vs 317.
    pub high_discharge_current: u8,
    /// Charge current vs 318.
    pub high_charge_current: u8,
    /// BMS fault status.
    pub bms_internal: u8,
    /// Spread of the cells vs 308.
    pub cell_imbalance: u8,
}

impl Conditions {
    /// The level of a field (0 ok, 1 warning, 2 alarm).
    pub fn level(v: u8) -> Level {
        match v {
            0 => Level::Ok,
            1 => Level::Warning,
            _ => Level::Alarm,
        }
    }
    /// Every field, for "any alarm" / "any warning".
    pub fn all(&self) -> [u8; 10] {
        [
            self.high_voltage,
            self.low_voltage,
            self.high_temperature,
            self.low_temperature,
            self.high_temperature_charge,
            self.low_temperature_charge,
            self.high_discharge_current,
            self.high_charge_current,
            self.bms_internal,
            self.cell_imbalance,
        ]
    }
    /// Highest level of any field.
    pub fn worst(&self) -> Level {
        Self::level(self.all().into_iter().max().unwrap_or(0))
    }
}

fn level(alarm: bool, warning: bool) -> u8 {
    if alarm {
        2
    } else if warning {
        1
    } else {
        0
    }
}

/// The limits sent to the inverter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Limits {
    /// Charge voltage limit for the pack, 0.1 V.
    pub cvl_dv: u16,
    /// Charge current limit, 0.1 A (≥ 0).
    pub ccl_da: u16,
    /// Discharge current limit, 0.1 A (≥ 0).
    pub dcl_da: u16,
    /// Discharge voltage (cells × (316 + margin)), 0.1 V.
    pub discharge_dv: u16,
}

/// Absorption is reached when the highest cell is within this of the target
/// (mV; with the current tapered below the tail current).
pub const AT_TARGET_CELL_MV: u16 = 10;
/// Or when the average cell is within this of it (the pack held at CVL), mV.
pub const AT_TARGET_AVERAGE_MV: i32 = 15;
/// A runner's CVL offset is released once the highest cell is this far below
/// the target, mV (hysteresis against the tolerance it was set with).
pub const RUNNER_RELEASE_MV: u16 = 5;
/// Float without a configured value: this fraction of absorption (15/16:
/// 3.45 V → 3.23 V per LiFePO4 cell).
pub const FLOAT_OF_ABSORPTION: (u32, u32) = (15, 16);
/// The pack counts as charging above this current, A (below: noise, or rest).
pub const CHARGING_ABOVE_A: f32 = 0.5;
/// The current limits ramp over at most this much time in one update, µs
/// (the time since the last update, capped: see `ChargeControl::ramp_interval`).
pub const MAX_RAMP_INTERVAL_US: Instant = 60 * crate::SECOND;
/// Series cells a TinyBMS manages at most (307 is 1..=16).
pub const MAX_SERIES_CELLS: u16 = protocol_core::registers::MAX_CELLS as u16;
/// Cutoffs a pack's settings must lie within to be taken at all, mV: an
/// under-voltage cutoff from 1 V, an over-voltage cutoff up to 5 V (every
/// lithium chemistry's cells, and the pack summaries' cell range,
/// [`super::packs::CELL_MAX_MV`]); outside, the block is misread, not a pack.
pub const SANE_CUTOFF_MV: (u16, u16) = (1000, super::packs::CELL_MAX_MV);
/// Cell imbalance alarm: the spread of the cells at this multiple of the
/// allowed disbalance (308).
pub const IMBALANCE_ALARM_OF_ALLOWED: u16 = 4;
/// Cell imbalance warning: the spread at this multiple of 308.
pub const IMBALANCE_WARNING_OF_ALLOWED: u16 = 2;

/// mV per V.
const MV_PER_V: f32 = 1000.0;
/// mV per 0.1 V (the unit of CVL and the discharge voltage).
const MV_PER_DV: u32 = 100;
/// 0.1 A per A (the unit of CCL and DCL).
const DA_PER_A: u32 = 10;
/// 0.1 °C per °C (temperatures are compared in tenths).
const DC_PER_C: i32 = 10;
/// A whole, in per mille (the taper factors).
const PERMILLE: u32 = 1000;
/// A whole, in percent.
const PERCENT: u32 = 100;

/// The charge controller. Call [`ChargeControl::update`] with each new snapshot.
#[derive(Debug, Clone, PartialEq)]
pub struct ChargeControl {
    config: ChargeConfig,
    phase: Phase,
    full_since: Option<Instant>,
    /// CVL correction for a runner cell, mV (pack).
    runner_offset_mv: u32,
    last_cvl_dv: Option<u16>,
    last_cvl_raise: Option<Instant>,
    ccl: Ramp,
    dcl: Ramp,
    last_update: Option<Instant>,
    targets: (u16, u16),
    over_current: OverCurrent,
    finish: Finish,
    stage: Stage,
    reasons: Reasons,
}

/// How long a discharge past 317 may last before the bridge stops it, at
/// most, µs: a surge shorter than this passes, and the stop still has
/// the rest of the BMS's timeout (5 s by default) to reach the inverter —
/// through another bridge of the battery, too.
const SURGE_US: Instant = crate::SECOND;

/// A current past its cutoff (317, 318): an inverter that ignores a limit
/// other than 0 (a Multi in island mode feeding its loads) draws what its
/// loads take. The TinyBMS trips on a discharge past 317 once it lasted its
/// timeout (330's high byte) and on a charge past 318; the bridge stops that
/// direction first — a discharge once it lasted [`SURGE_US`] (half the
/// timeout when that is shorter), a charge at once — and the
/// limit comes back after the hold, ramping, as after any cut.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct OverCurrent {
    /// Since when the discharge is past 317 (the snapshot's time).
    since: Option<Instant>,
    /// Past the cutoffs now (the discharge for half the timeout): charge, discharge.
    now: (bool, bool),
    /// A stop not yet seen by an update (so that a stop is never missed
    /// between two snapshots).
    pending: (bool, bool),
}

impl OverCurrent {
    /// A fresh snapshot taken at `at`: returns whether a stop begins with it.
    fn watch(&mut self, at: Instant, s: &PackSettings, p: &PackState) -> bool {
        let charge = p.current_a >= f32::from(s.charge_cutoff_a);
        let discharge = if -p.current_a >= f32::from(s.discharge_cutoff_a) {
            let since = *self.since.get_or_insert(at);
            let timeout = u64::from(s.discharge_cutoff_s) * crate::SECOND;
            let patience = (timeout / 2).min(SURGE_US);
            at.saturating_sub(since) >= patience
        } else {
            self.since = None;
            false
        };
        let begins = (charge && !self.now.0) || (discharge && !self.now.1);
        self.now = (charge, discharge);
        self.pending = (self.pending.0 || charge, self.pending.1 || discharge);
        begins
    }

    /// The stops for this update: charge, discharge.
    fn take(&mut self) -> (bool, bool) {
        let stops = self.pending;
        self.pending = self.now;
        stops
    }
}

/// A limit that falls at once, rises at a bounded rate, and after being cut to
/// 0 waits a hold time before it rises.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Ramp {
    value_da: u16,
    cut_at: Option<Instant>,
    started: bool,
}

impl Ramp {
    pub(crate) const fn new() -> Self {
        Self {
            value_da: 0,
            cut_at: None,
            started: false,
        }
    }

    /// A rise from here on waits the hold, counted from `now` (the value is
    /// kept: a lower target still lowers it at once).
    pub(crate) fn hold_from(&mut self, now: Instant) {
        self.cut_at = Some(now);
    }

    pub(crate) fn step(
        &mut self,
        now: Instant,
        target: u16,
        dt_us: Instant,
        c: &ChargeConfig,
    ) -> u16 {
        if !self.started {
            // First value: allowed at once (nothing was cut before) — but a first
            // value of 0 is a cut like any other.
            self.started = true;
            self.value_da = target;
            if target == 0 {
                self.cut_at = Some(now);
            }
            return target;
        }
        if target == 0 {
            // Cut: the hold runs from the last moment the cause was there.
            self.cut_at = Some(now);
        }
        if target < self.value_da {
            self.value_da = target;
        } else if target > self.value_da {
            let held = self
                .cut_at
                .is_none_or(|t| now.saturating_sub(t) >= c.limit_hold_us);
            if held {
                let step = (u64::from(c.ramp_rate_da_per_s) * dt_us / crate::SECOND).max(1);
                let step = step.min(u64::from(u16::MAX)) as u16;
                self.value_da = self.value_da.saturating_add(step).min(target);
            }
        }
        self.value_da
    }
}

/// Linear factor in 0..=1000 (per mille) that falls with `x`: 1000 at or below
/// `stop − width`, 0 at or above `stop`. A width below 1 counts as 1, so a zero
/// or negative setting can never turn the direction round.
fn falling_permille(x: i32, stop: i32, width: i32) -> u32 {
    let w = i64::from(width.max(1));
    let f = (i64::from(stop) - i64::from(x)) * i64::from(PERMILLE) / w;
    f.clamp(0, i64::from(PERMILLE)) as u32
}

/// Linear factor in 0..=1000 that rises with `x`: 0 at or below `stop`, 1000 at
/// or above `stop + width` (width at least 1).
fn rising_permille(x: i32, stop: i32, width: i32) -> u32 {
    let w = i64::from(width.max(1));
    let f = (i64::from(x) - i64::from(stop)) * i64::from(PERMILLE) / w;
    f.clamp(0, i64::from(PERMILLE)) as u32
}

impl ChargeControl {
    /// A controller in absorption.
    pub const fn new(config: ChargeConfig) -> Self {
        Self {
            config,
            phase: Phase::Absorption,
            full_since: None,
            runner_offset_mv: 0,
            last_cvl_dv: None,
            last_cvl_raise: None,
            ccl: Ramp::new(),
            dcl: Ramp::new(),
            last_update: None,
            targets: (0, 0),
            over_current: OverCurrent {
                since: None,
                now: (false, false),
                pending: (false, false),
            },
            finish: Finish::new(),
            stage: Stage::Bulk { full_due: false },
            reasons: Reasons {
                cvl: Why::Unknown,
                ccl: Why::Unknown,
                dcl: Why::Unknown,
            },
        }
    }

    /// A fresh snapshot taken at `at` (each once): a current past its
    /// cutoff stops that direction (the module's "a current past its
    /// cutoff"). Returns whether a stop begins with it — the inverter is to
    /// hear it now, not a period later.
    pub fn watch_current(&mut self, at: Instant, s: &PackSettings, p: &PackState) -> bool {
        self.over_current.watch(at, s, p)
    }

    /// The inverter was without limits (stale telemetry, a bus-off): treat it
    /// as a cut, so the current limits come back only after the hold, ramping.
    pub fn cut(&mut self, now: Instant) {
        for r in [&mut self.ccl, &mut self.dcl] {
            r.value_da = 0;
            r.cut_at = Some(now);
            r.started = true;
        }
    }

    /// Fresh data again after a loss of it: the loss itself is no cause the
    /// battery gave, so nothing waits the hold. The charge limit comes back
    /// from 0 at the ramp rate at once (the inverter charged with none
    /// meanwhile); the discharge limit is what the data says at once (a DCL of
    /// 0 would switch a Victron inverter off just as the data is back). A cause
    /// in the fresh data (a fault, a cell at its cutoff, a temperature) still
    /// cuts and holds as ever, and a hold a cause started before the loss runs
    /// on.
    pub fn resume(&mut self) {
        self.ccl.value_da = 0;
        self.ccl.started = true;
    }

    /// The configuration.
    pub fn config(&self) -> &ChargeConfig {
        &self.config
    }

    /// New settings from the next [`ChargeControl::update`] on; the phase, the
    /// ramps and their holds carry on (a limit that falls falls at once).
    pub fn set_config(&mut self, config: ChargeConfig) {
        self.config = config;
    }

    /// Absorption or float.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// Where the charge is and why ([`super::finish`]), as of the last update.
    pub fn stage(&self) -> Stage {
        self.stage
    }

    /// The rule that set each limit of the last update ([`super::why`]).
    pub fn reasons(&self) -> Reasons {
        self.reasons
    }

    /// CCL and DCL of the last update before the hold and ramp, 0.1 A: what
    /// the pack may take now, which a battery of several packs holds and
    /// ramps as a whole (see [`super::packs`]).
    pub fn targets(&self) -> (u16, u16) {
        self.targets
    }

    /// Per-cell targets (absorption, float), mV, for these settings.
    pub fn targets_mv(&self, s: &PackSettings) -> (u16, u16) {
        let top = s
            .ov_cutoff_mv
            .saturating_sub(
                self.config
                    .absorption_margin_mv
                    .max(self.config.ceiling_margin_mv),
            )
            .max(s.uv_cutoff_mv);
        let absorption = self
            .config
            .absorption_voltage_mv
            .unwrap_or(s.fully_charged_mv)
            .max(s.uv_cutoff_mv)
            .min(top);
        let float = self
            .config
            .float_voltage_mv
            .unwrap_or(
                (u32::from(absorption) * FLOAT_OF_ABSORPTION.0 / FLOAT_OF_ABSORPTION.1) as u16,
            )
            .max(s.uv_cutoff_mv)
            .min(absorption);
        (absorption, float)
    }

    /// New limits and conditions from a snapshot taken at `now`: the phase
    /// first (it picks the target), then CVL, the current limits through their
    /// hold and ramp, and the conditions.
    pub fn update(
        &mut self,
        now: Instant,
        s: &PackSettings,
        p: &PackState,
    ) -> (Limits, Conditions) {
        let c = self.config;
        let dt_us = self.ramp_interval(now);
        let n = u32::from(s.cells.clamp(1, MAX_SERIES_CELLS));
        let bounds = PackBounds::of(s, n);
        let due = self.finish.full_due(now, c.full_charge_days);
        let target = self.advance_phase(now, s, p, n, due);
        let cvl_dv = self.charge_voltage_limit(now, p, n, target, bounds, dt_us);
        let temps = Temperatures::of(&c, s, p);
        let ((mut ccl_target, mut dcl_target), (mut ccl_why, mut dcl_why)) =
            current_targets(&c, s, p, temps);
        // (A switch to float in this update leaves the phase Float: `due`,
        // of before it, then asks nothing.)
        let ceiling = self.phase == Phase::Absorption
            && self.finish.ceiling(c.soc_ceiling_pct, p.soc_pct, due);
        if ceiling {
            ccl_target = 0;
            ccl_why = Why::SocCeiling {
                pct: c.soc_ceiling_pct,
            };
            self.stage = Stage::Ceiling {
                ceiling_pct: c.soc_ceiling_pct,
            };
        }
        let (charge_over, discharge_over) = self.over_current.take();
        if charge_over {
            ccl_target = 0;
            ccl_why = Why::OverCurrent {
                cutoff_a: s.charge_cutoff_a,
            };
        }
        if discharge_over {
            dcl_target = 0;
            dcl_why = Why::OverCurrent {
                cutoff_a: s.discharge_cutoff_a,
            };
        }
        self.targets = (ccl_target, dcl_target);
        let ccl_da = self.ccl.step(now, ccl_target, dt_us, &c);
        let dcl_da = self.dcl.step(now, dcl_target, dt_us, &c);
        let ramping = |da: u16, target_da: u16, why: Why| {
            if da < target_da {
                Why::Ramp { target_da }
            } else {
                why
            }
        };
        self.reasons.ccl = ramping(ccl_da, ccl_target, ccl_why);
        self.reasons.dcl = ramping(dcl_da, dcl_target, dcl_why);
        let limits = Limits {
            cvl_dv,
            ccl_da,
            dcl_da,
            discharge_dv: discharge_dv(&c, s, n, bounds),
        };
        (limits, conditions(&c, s, p, temps))
    }

    /// The time the current limits ramp over in this update: since the last
    /// update (one second for the first), at most [`MAX_RAMP_INTERVAL_US`] so
    /// that a long gap between updates (a stalled task, a long silence of
    /// the BMS) is not one big rise. Records `now` as the last update.
    fn ramp_interval(&mut self, now: Instant) -> Instant {
        let dt_us = self
            .last_update
            .map_or(crate::SECOND, |t| now.saturating_sub(t))
            .min(MAX_RAMP_INTERVAL_US);
        self.last_update = Some(now);
        dt_us
    }

    /// Absorption → float once the pack is at the absorption target with the
    /// current tapered for [`ChargeConfig::full_hold_us`] — and, while the
    /// BMS balances with the spread above 308, once the balance hold is over
    /// ([`super::finish`]); float → absorption below
    /// [`ChargeConfig::rebulk_soc_pct`] or when a periodic full charge is due.
    /// `due`: a periodic full charge is due. Sets the [`Stage`]. Returns the
    /// per-cell target of the phase it is in now, mV.
    fn advance_phase(
        &mut self,
        now: Instant,
        s: &PackSettings,
        p: &PackState,
        n: u32,
        due: bool,
    ) -> u16 {
        let c = self.config;
        let (absorption, float) = self.targets_mv(s);
        match self.phase {
            Phase::Absorption => {
                // At the target: the highest cell there, or the pack held at CVL
                // (the average cell within AT_TARGET_AVERAGE_MV of the target).
                let avg_mv = (p.pack_v * MV_PER_V / n as f32) as i32;
                let at_target = p.max_cell_mv.saturating_add(AT_TARGET_CELL_MV) >= absorption
                    || avg_mv.saturating_add(AT_TARGET_AVERAGE_MV) >= i32::from(absorption);
                let tapered = p.current_a < c.tail_current_a;
                self.stage = Stage::Bulk { full_due: due };
                if at_target && tapered {
                    self.stage = Stage::Absorption;
                    let since = *self.full_since.get_or_insert(now);
                    if now.saturating_sub(since) >= c.full_hold_us {
                        if let Some(held) = self.balance_hold(now, s, p) {
                            self.stage = held;
                        } else {
                            self.enter_float(now);
                        }
                    }
                } else {
                    self.full_since = None;
                }
            }
            Phase::Float => {
                if p.soc_pct < c.rebulk_soc_pct || due {
                    self.phase = Phase::Absorption;
                    self.finish.step_mv = None;
                    self.stage = Stage::Bulk { full_due: due };
                }
            }
        }
        match self.phase {
            Phase::Absorption => absorption,
            Phase::Float => float,
        }
    }

    /// The balance hold at the end of absorption: `Some` while the BMS
    /// balances (register 52), the spread is above the allowed disbalance
    /// (308) and the hold of this charge has time left ([`Finish::hold_bound`]).
    fn balance_hold(&mut self, now: Instant, s: &PackSettings, p: &PackState) -> Option<Stage> {
        let bound = self.finish.hold_bound(
            now,
            self.config.balance_hold_us,
            self.config.full_charge_days,
        );
        let spread_mv = p.max_cell_mv.saturating_sub(p.min_cell_mv);
        if bound == 0 || p.balancing == 0 || spread_mv <= s.allowed_disbalance_mv {
            return None;
        }
        let since = *self.finish.hold_since.get_or_insert(now);
        let held = now.saturating_sub(since);
        (held < bound).then(|| Stage::BalanceHeld {
            balancing: p.balancing,
            spread_mv,
            left_s: ((bound - held) / crate::SECOND) as u32,
        })
    }

    /// The switch to float: the full charge is done; CVL steps down from
    /// where it is.
    fn enter_float(&mut self, now: Instant) {
        self.phase = Phase::Float;
        self.full_since = None;
        self.finish.hold_since = None;
        self.finish.last_full = Some(now);
        self.finish.step_mv = (self.config.float_step_mv_per_min > 0)
            .then(|| self.last_cvl_dv.map(|dv| u32::from(dv) * MV_PER_DV))
            .flatten();
        self.stage = Stage::Float;
    }

    /// CVL, 0.1 V: cells × `target` less the runner offset, kept within the
    /// pack's bounds, in 0.1 V steps, raised at most once per
    /// [`ChargeConfig::cvl_raise_interval_us`]; on the way down into float,
    /// stepped ([`super::finish`]).
    fn charge_voltage_limit(
        &mut self,
        now: Instant,
        p: &PackState,
        n: u32,
        target: u16,
        bounds: PackBounds,
        dt_us: Instant,
    ) -> u16 {
        self.follow_runner(p, n, target);
        let wanted_mv = (n * u32::from(target)).saturating_sub(self.runner_offset_mv);
        let cvl_mv = wanted_mv.max(bounds.floor_mv).min(bounds.ceil_mv);
        let cells = n as u8; // n <= MAX_SERIES_CELLS
        let mut why = match (self.phase, self.stage) {
            (Phase::Absorption, Stage::BalanceHeld { spread_mv, .. }) => {
                Why::BalanceHold { spread_mv }
            }
            (Phase::Absorption, _) => Why::Absorption {
                cell_mv: target,
                cells,
            },
            (Phase::Float, _) => Why::Float {
                cell_mv: target,
                cells,
            },
        };
        if self.runner_offset_mv > 0 {
            why = Why::Runner {
                cell_mv: p.max_cell_mv,
                offset_mv: self.runner_offset_mv,
            };
        }
        if wanted_mv > bounds.ceil_mv {
            why = Why::CutoffCeiling {
                cutoff_mv: (bounds.ceil_mv / n) as u16,
            };
        } else if wanted_mv < bounds.floor_mv {
            why = Why::CutoffFloor {
                cutoff_mv: (bounds.floor_mv / n) as u16,
            };
        }
        let mut cvl_dv = bounds.round_inside_dv(cvl_mv);
        if self.phase == Phase::Float {
            // At rest, the pack's own voltage is the floor of the step: an
            // inverter pulling the pack down to CVL finds nothing. While it
            // charges gently (below the tail current), the inverter's
            // regulator holds the pack at or below CVL, above the pack's
            // rest: no floor needed. While it charges harder or discharges,
            // its rest is unknown (a drop of unknown size): no step at all.
            // Rounded up to the 0.1 V, within the bounds.
            let i = p.current_a;
            let (floor_mv, dt_us) = if i > CHARGING_ABOVE_A && i < self.config.tail_current_a {
                (0, dt_us)
            } else if i.abs() <= CHARGING_ABOVE_A {
                ((p.pack_v.max(0.0) * MV_PER_V) as u32, dt_us)
            } else {
                (u32::MAX, 0)
            };
            let step = self.config.float_step_mv_per_min;
            if let Some(mv) = self.finish.step(cvl_mv, n, step, dt_us, floor_mv) {
                cvl_dv = (mv.div_ceil(MV_PER_DV).min(bounds.ceil_mv / MV_PER_DV)) as u16;
                let float_dv = bounds.round_inside_dv(cvl_mv);
                self.stage = Stage::StepDown { cvl_dv, float_dv };
                why = Why::StepDown { float_dv };
            } else {
                self.stage = Stage::Float;
            }
        }
        let told = self.limit_cvl_raise(now, cvl_dv);
        self.reasons.cvl = if told < cvl_dv { Why::RaiseWait } else { why };
        told
    }

    /// A runner: when the highest cell is above the target because it runs
    /// ahead of the others (not because the whole pack is above a lower float
    /// target), CVL is lowered so that the runner — not the average — settles
    /// at the target (+ tolerance). Released once the runner is clearly below
    /// the target ([`RUNNER_RELEASE_MV`]), and then only as fast as CVL may rise.
    fn follow_runner(&mut self, p: &PackState, n: u32, target: u16) {
        let avg_mv = (p.pack_v.max(0.0) * MV_PER_V / n as f32) as u32;
        let lead_mv = u32::from(p.max_cell_mv).saturating_sub(avg_mv);
        if p.max_cell_mv > target {
            // Deeper at once; shallower only by more than RUNNER_RELEASE_MV a
            // cell: a lead that wobbles by a mV would otherwise move CVL by
            // 0.1 V back and forth (through a long balance hold, every minute).
            let offset = n * lead_mv.saturating_sub(u32::from(self.config.runner_tolerance_mv));
            if offset > self.runner_offset_mv
                || offset + n * u32::from(RUNNER_RELEASE_MV) < self.runner_offset_mv
            {
                self.runner_offset_mv = offset;
            }
        } else if p.max_cell_mv.saturating_add(RUNNER_RELEASE_MV) < target {
            self.runner_offset_mv = 0;
        }
    }

    /// CVL is raised at most once per [`ChargeConfig::cvl_raise_interval_us`]
    /// (an inverter need not chase every 0.1 V of a settling runner); it is
    /// lowered at once. Returns the CVL to send and records it.
    fn limit_cvl_raise(&mut self, now: Instant, mut cvl_dv: u16) -> u16 {
        if let Some(last) = self.last_cvl_dv {
            if cvl_dv > last {
                let may = self
                    .last_cvl_raise
                    .is_none_or(|t| now.saturating_sub(t) >= self.config.cvl_raise_interval_us);
                if may {
                    self.last_cvl_raise = Some(now);
                } else {
                    cvl_dv = last;
                }
            }
        }
        self.last_cvl_dv = Some(cvl_dv);
        cvl_dv
    }
}

/// The pack voltages no limit leaves: cells × [316, 315], mV.
#[derive(Debug, Clone, Copy)]
struct PackBounds {
    /// Cells × the under-voltage cutoff (316).
    floor_mv: u32,
    /// Cells × the over-voltage cutoff (315).
    ceil_mv: u32,
}

impl PackBounds {
    fn of(s: &PackSettings, n: u32) -> Self {
        Self {
            floor_mv: n * u32::from(s.uv_cutoff_mv),
            ceil_mv: n * u32::from(s.ov_cutoff_mv),
        }
    }

    /// A CVL in 0.1 V steps, rounded towards the inside of the bounds (up at
    /// the floor, down elsewhere), never 0 (an inverter would read 0 as "no
    /// limit" or refuse it).
    fn round_inside_dv(self, cvl_mv: u32) -> u16 {
        if cvl_mv <= self.floor_mv {
            cvl_mv.div_ceil(MV_PER_DV)
        } else {
            cvl_mv / MV_PER_DV
        }
        .max(1) as u16
    }
}

/// The temperatures charge control compares, in 0.1 °C (the cutoffs are whole
/// degrees; the measurements keep their tenths).
#[derive(Debug, Clone, Copy)]
struct Temperatures {
    /// Lowest sensor.
    min: i32,
    /// Highest sensor.
    max: i32,
    /// The low-temperature charge cutoff (320).
    cold: i32,
    /// The over-heat cutoff (319).
    hot: i32,
    /// The derating window inside each cutoff ([`ChargeConfig::temperature_margin_c`],
    /// at least 1 °C).
    margin: i32,
}

impl Temperatures {
    fn of(c: &ChargeConfig, s: &PackSettings, p: &PackState) -> Self {
        let dc = |x: f32| (x * DC_PER_C as f32) as i32;
        Self {
            min: dc(p.min_temp_c),
            max: dc(p.max_temp_c),
            cold: i32::from(s.low_temp_charge_c) * DC_PER_C,
            hot: i32::from(s.overheat_c) * DC_PER_C,
            margin: i32::from(c.temperature_margin_c.max(1)) * DC_PER_C,
        }
    }
}

/// A current cutoff in A as the largest limit in 0.1 A: `margin_pct` below
/// the cutoff (saturating at what a frame carries), under the configured
/// cap if any.
fn capped_da(cutoff_a: u16, margin_pct: u8, cap: Option<u16>) -> u16 {
    let keep = PERCENT.saturating_sub(u32::from(margin_pct));
    let da = (u32::from(cutoff_a).saturating_mul(DA_PER_A) * keep / PERCENT)
        .min(u32::from(u16::MAX)) as u16;
    cap.map_or(da, |c| c.min(da))
}

/// `x` scaled by a per-mille factor (rounded down).
fn scale_permille(x: u16, f: u32) -> u16 {
    (u32::from(x) * f / PERMILLE) as u16
}

/// The pack's current limits before the hold and ramp, 0.1 A (CCL, DCL): the
/// cutoffs under their caps, tapered by the cells near their cutoffs and by
/// the temperatures near theirs; CCL and DCL 0 on a BMS fault, CCL 0 while a
/// charge-side fault is latched.
fn current_targets(
    c: &ChargeConfig,
    s: &PackSettings,
    p: &PackState,
    t: Temperatures,
) -> ((u16, u16), (Why, Why)) {
    let ccl_max = capped_da(
        s.charge_cutoff_a,
        c.current_margin_pct,
        c.charge_current_cap_da,
    );
    let dcl_max = capped_da(
        s.discharge_cutoff_a,
        c.current_margin_pct,
        c.discharge_current_cap_da,
    );
    // The base of each: the owner's cap where it is below the cutoff's.
    let base = |cutoff_a: u16, cap: Option<u16>| {
        let uncapped = capped_da(cutoff_a, c.current_margin_pct, None);
        match cap {
            Some(cap_da) if cap_da < uncapped => Why::OwnerCap { cap_da },
            _ => Why::Cutoff {
                cutoff_a,
                margin_pct: c.current_margin_pct,
            },
        }
    };
    // Tapers by cell voltage.
    let stop_mv = i32::from(s.ov_cutoff_mv) - i32::from(c.ceiling_margin_mv);
    let ccl_v = falling_permille(
        i32::from(p.max_cell_mv),
        stop_mv,
        i32::from(c.charge_taper_mv),
    );
    let dcl_v = rising_permille(
        i32::from(p.min_cell_mv),
        discharge_stop_mv(c, s),
        i32::from(c.discharge_taper_mv),
    );
    // Tapers by temperature.
    let ccl_cold = rising_permille(t.min, t.cold, t.margin);
    let ccl_hot = falling_permille(t.max, t.hot, t.margin);
    let dcl_hot = falling_permille(t.max, t.hot, t.margin);
    let mut ccl_target = scale_permille(
        scale_permille(scale_permille(ccl_max, ccl_v), ccl_cold),
        ccl_hot,
    );
    let mut dcl_target = scale_permille(scale_permille(dcl_max, dcl_v), dcl_hot);
    // The reason of each: the taper that cuts deepest, else the base.
    let cell_high = Why::CellHigh {
        cell_mv: p.max_cell_mv,
        stop_mv: stop_mv.clamp(0, i32::from(u16::MAX)) as u16,
    };
    let cell_low = Why::CellLow {
        cell_mv: p.min_cell_mv,
        stop_mv: discharge_stop_mv(c, s).clamp(0, i32::from(u16::MAX)) as u16,
    };
    let dc = |x: i32| x.clamp(i32::from(i16::MIN), i32::from(i16::MAX)) as i16;
    let cold = Why::Cold {
        temp_dc: dc(t.min),
        cutoff_c: dc(t.cold / DC_PER_C),
    };
    let hot = Why::Hot {
        temp_dc: dc(t.max),
        cutoff_c: dc(t.hot / DC_PER_C),
    };
    let mut ccl_why = deepest(
        base(s.charge_cutoff_a, c.charge_current_cap_da),
        &[(ccl_v, cell_high), (ccl_cold, cold), (ccl_hot, hot)],
    );
    let mut dcl_why = deepest(
        base(s.discharge_cutoff_a, c.discharge_current_cap_da),
        &[(dcl_v, cell_low), (dcl_hot, hot)],
    );
    if p.fault {
        ccl_target = 0;
        dcl_target = 0;
        (ccl_why, dcl_why) = (Why::BmsFault, Why::BmsFault);
    }
    if p.charge_blocked {
        ccl_target = 0;
        ccl_why = Why::ChargeBlocked;
    }
    ((ccl_target, dcl_target), (ccl_why, dcl_why))
}

/// The reason of the smallest per-mille factor below a whole, else `base`
/// (the first of equal factors).
fn deepest(base: Why, factors: &[(u32, Why)]) -> Why {
    factors
        .iter()
        .filter(|(f, _)| *f < PERMILLE)
        .fold(None::<(u32, Why)>, |best, &(f, w)| match best {
            Some((b, _)) if b <= f => best,
            _ => Some((f, w)),
        })
        .map_or(base, |(_, w)| w)
}

/// The cell voltage at which discharge stops: 316 + [`ChargeConfig::discharge_margin_mv`], mV.
fn discharge_stop_mv(c: &ChargeConfig, s: &PackSettings) -> i32 {
    i32::from(s.uv_cutoff_mv) + i32::from(c.discharge_margin_mv)
}

/// The discharge voltage sent with the limits: cells × the discharge stop,
/// within the pack's bounds, 0.1 V (rounded down).
fn discharge_dv(c: &ChargeConfig, s: &PackSettings, n: u32, bounds: PackBounds) -> u16 {
    let discharge_mv = (n * u32::from(discharge_stop_mv(c, s).max(0) as u16))
        .max(bounds.floor_mv)
        .min(bounds.ceil_mv);
    (discharge_mv / MV_PER_DV) as u16
}

/// Alarms and warnings: an alarm at or past each cutoff, a warning a margin
/// inside it ([`ChargeConfig::warn_margin_mv`], the temperature window,
/// [`ChargeConfig::warn_current_pct`], half the imbalance alarm).
fn conditions(c: &ChargeConfig, s: &PackSettings, p: &PackState, t: Temperatures) -> Conditions {
    let w = c.warn_margin_mv;
    let pct = |a: u16| u32::from(a) * u32::from(c.warn_current_pct) / PERCENT;
    let spread = p.max_cell_mv.saturating_sub(p.min_cell_mv);
    let charging = p.current_a > CHARGING_ABOVE_A;
    let (hot, cold, m) = (t.hot, t.cold, t.margin);
    Conditions {
        high_voltage: level(
            p.max_cell_mv >= s.ov_cutoff_mv,
            p.max_cell_mv.saturating_add(w) >= s.ov_cutoff_mv,
        ),
        low_voltage: level(
            p.min_cell_mv <= s.uv_cutoff_mv,
            p.min_cell_mv <= s.uv_cutoff_mv.saturating_add(w),
        ),
        high_temperature: level(t.max >= hot, t.max >= hot - m),
        // Rev D has no low-temperature discharge cutoff: below the charge
        // cutoff is a warning (charging is blocked), never an alarm.
        low_temperature: level(false, t.min <= cold),
        high_temperature_charge: level(charging && t.max >= hot, charging && t.max >= hot - m),
        low_temperature_charge: level(charging && t.min <= cold, charging && t.min <= cold + m),
        high_discharge_current: level(
            -p.current_a >= f32::from(s.discharge_cutoff_a),
            -p.current_a >= pct(s.discharge_cutoff_a) as f32,
        ),
        high_charge_current: level(
            p.current_a >= f32::from(s.charge_cutoff_a),
            p.current_a >= pct(s.charge_cutoff_a) as f32,
        ),
        bms_internal: level(p.fault, false),
        cell_imbalance: level(
            s.allowed_disbalance_mv > 0
                && spread
                    >= s.allowed_disbalance_mv
                        .saturating_mul(IMBALANCE_ALARM_OF_ALLOWED),
            s.allowed_disbalance_mv > 0
                && spread
                    >= s.allowed_disbalance_mv
                        .saturating_mul(IMBALANCE_WARNING_OF_ALLOWED),
        ),
    }
}
