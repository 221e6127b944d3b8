//! What every dialect shares, and nothing of any one of them: the frame, the
//! byte helpers, what one period says ([`Say`], decided once by the output for
//! every dialect) and what it is made of ([`Period`]), why a side stops
//! ([`Stops`]), and what the frames sent tell when read back ([`Told`]). Every
//! dialect imports this module; it imports none of them.

use crate::inverter::control::{Conditions, Limits, PackSettings, PackState};
use protocol_core::events::EventId;

/// One classic CAN frame with an 11-bit identifier.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct CanFrame {
    /// 11-bit identifier.
    pub id: u16,
    /// Data length, 0-8.
    pub len: u8,
    /// Data (bytes past `len` are 0).
    pub data: [u8; 8],
}

impl CanFrame {
    /// A frame of `len` bytes of `data`.
    pub const fn new(id: u16, len: u8, data: [u8; 8]) -> Self {
        Self { id, len, data }
    }

    /// The data bytes.
    pub fn bytes(&self) -> &[u8] {
        self.data.get(..usize::from(self.len.min(8))).unwrap_or(&[])
    }

    /// Byte `i` of the data (0 past its length).
    pub fn byte(&self, i: usize) -> u8 {
        self.bytes().get(i).copied().unwrap_or(0)
    }

    /// Bytes `i` and `i + 1` (0 past the length).
    pub fn pair(&self, i: usize) -> [u8; 2] {
        [self.byte(i), self.byte(i + 1)]
    }
}

/// Frames of one period at most (Victron's slow period: nine).
pub const MAX_FRAMES: usize = 12;

/// The frames of one period.
pub type Frames = heapless::Vec<CanFrame, MAX_FRAMES>;

/// Adds `f` to `out`. [`MAX_FRAMES`] holds every dialect's largest period (a
/// test of each dialect shows it), so nothing is ever left out.
pub fn push(out: &mut Frames, f: CanFrame) {
    let _ = out.push(f);
}

/// Two bytes into a frame's data at `at` (nothing past byte 7).
pub fn put2(out: &mut [u8; 8], at: usize, bytes: [u8; 2]) {
    if let Some(s) = out.get_mut(at..at + 2) {
        s.copy_from_slice(&bytes);
    }
}

/// Rounded half away from zero and saturated to a u16 (NaN: 0).
pub fn clamp_u16(v: f32) -> u16 {
    // A NaN or a negative value saturates to 0 in the cast.
    (v + 0.5).clamp(0.0, f32::from(u16::MAX)) as u16
}

/// Rounded half away from zero and saturated to an i16 (NaN: 0).
pub fn clamp_i16(v: f32) -> i16 {
    if v.is_nan() {
        0
    } else {
        // Round half away from zero (no_std: no f32::round).
        let r = if v >= 0.0 { v + 0.5 } else { v - 0.5 };
        r.clamp(f32::from(i16::MIN), f32::from(i16::MAX)) as i16
    }
}

/// A current limit, 0.1 A, as a frame's signed 16-bit field carries it.
pub fn limit_i16(da: u16) -> i16 {
    da.min(i16::MAX as u16) as i16
}

/// Why charging (or discharging) must stop now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StopWhy {
    /// The BMS reports a fault (or a charge-side fault event is latched).
    Fault,
    /// A cell at the top: the ceiling below the over-voltage cutoff.
    CellHigh,
    /// A cell at the bottom: the discharge stop above the under-voltage cutoff.
    CellLow,
    /// A temperature at or past its cutoff.
    Temperature,
    /// A current at its cutoff.
    Current,
    /// The BMS's data is stale (a stop the gap decided: the hold is over, or
    /// its discharge budget is spent).
    LinkLost,
    /// The inverter asked the battery to shut down (Luxpower's 0x300).
    InverterAsked,
    /// Charge control holds the limit at 0 (after a cut, a cap, a ramp).
    Limit,
}

impl StopWhy {
    /// In words, for the log and the monitor.
    pub const fn text(self) -> &'static str {
        match self {
            Self::Fault => "BMS fault",
            Self::CellHigh => "a cell at its ceiling",
            Self::CellLow => "a cell at its discharge stop",
            Self::Temperature => "temperature",
            Self::Current => "current at its cutoff",
            Self::LinkLost => "BMS data lost",
            Self::InverterAsked => "the inverter asked to shut down",
            Self::Limit => "limit held at 0",
        }
    }

    /// As the host link and MQTT write it.
    pub const fn key(self) -> &'static str {
        match self {
            Self::Fault => "fault",
            Self::CellHigh => "cell_high",
            Self::CellLow => "cell_low",
            Self::Temperature => "temperature",
            Self::Current => "current",
            Self::LinkLost => "link_lost",
            Self::InverterAsked => "inverter_asked",
            Self::Limit => "limit",
        }
    }
}

/// A stop's key for the host link and MQTT: its cause, or `none`.
pub const fn stop_key(why: Option<StopWhy>) -> &'static str {
    match why {
        Some(w) => w.key(),
        None => "none",
    }
}

/// What must stop now, and why: charging when the charge current limit is 0,
/// discharging when the discharge current limit is 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Stops {
    /// Charging must stop.
    pub charge: Option<StopWhy>,
    /// Discharging must stop.
    pub discharge: Option<StopWhy>,
}

impl Stops {
    /// From the limits computed and the reasons the data gives.
    pub fn of(limits: &Limits, state: &PackState, c: &Conditions) -> Self {
        Self {
            charge: (limits.ccl_da == 0).then_some(charge_why(state, c)),
            discharge: (limits.dcl_da == 0).then_some(discharge_why(state, c)),
        }
    }

    /// Both stop: the inverter asked the battery to shut down.
    pub const fn shutdown() -> Self {
        Self {
            charge: Some(StopWhy::InverterAsked),
            discharge: Some(StopWhy::InverterAsked),
        }
    }

    /// The keys of both sides for the host link and MQTT ([`stop_key`]).
    pub const fn keys(&self) -> (&'static str, &'static str) {
        (stop_key(self.charge), stop_key(self.discharge))
    }

    /// Nothing must stop.
    pub const fn none(&self) -> bool {
        self.charge.is_none() && self.discharge.is_none()
    }

    /// The SOC told to stop a side, %: 100 while only charging must stop, 0
    /// while discharging must; when both must, 100 if the charge's stop is
    /// the one to say (`charge_first`: see `crate::inverter::say::charge_first`),
    /// else 0 — the charge is then stopped by its limit, its enable bit and
    /// the charge voltage; `real` when nothing stops.
    pub fn soc_pct(&self, real: f32, charge_first: bool) -> f32 {
        match (self.charge, self.discharge) {
            (Some(_), None) => 100.0,
            (Some(_), Some(_)) if charge_first => 100.0,
            (_, Some(_)) => 0.0,
            (None, None) => real,
        }
    }
}

/// Why charging must stop, from the data: a fault, a cell at the top, a
/// temperature, a current; else charge control's own hold.
fn charge_why(state: &PackState, c: &Conditions) -> StopWhy {
    if state.fault || c.bms_internal >= 2 || state.charge_blocked {
        StopWhy::Fault
    } else if c.high_voltage > 0 {
        StopWhy::CellHigh
    } else if c.high_temperature_charge > 0
        || c.low_temperature_charge > 0
        || c.high_temperature >= 2
        || c.low_temperature >= 1
    {
        StopWhy::Temperature
    } else if c.high_charge_current >= 2 {
        StopWhy::Current
    } else {
        StopWhy::Limit
    }
}

/// Why discharging must stop, from the data (as [`charge_why`]).
fn discharge_why(state: &PackState, c: &Conditions) -> StopWhy {
    if state.fault || c.bms_internal >= 2 {
        StopWhy::Fault
    } else if c.low_voltage > 0 {
        StopWhy::CellLow
    } else if c.high_temperature >= 2 {
        StopWhy::Temperature
    } else if c.high_discharge_current >= 2 {
        StopWhy::Current
    } else {
        StopWhy::Limit
    }
}

/// What the inverter must treat as a protection trip now: the cutoff the
/// BMS itself tripped on (its fault status and the event that said why),
/// or — when the inverter was seen ignoring a stop, or the data is lost and
/// a stop is decided blind — the cause of that stop. The protection bits of
/// the Pylontech family and Growatt, the alarms of Victron's 0x35A, come from
/// this alone: a normal charge, however close to a limit, raises none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Protected {
    /// A cell over-voltage.
    pub over_voltage: bool,
    /// A cell under-voltage.
    pub under_voltage: bool,
    /// Over-temperature.
    pub over_temperature: bool,
    /// Under-temperature (charging).
    pub under_temperature: bool,
    /// Charge over-current.
    pub charge_over_current: bool,
    /// Discharge over-current.
    pub discharge_over_current: bool,
    /// Another fault of the BMS, or the BMS's data lost.
    pub system: bool,
}

impl Protected {
    /// Any protection.
    pub const fn any(&self) -> bool {
        self.over_voltage
            || self.under_voltage
            || self.over_temperature
            || self.under_temperature
            || self.charge_over_current
            || self.discharge_over_current
            || self.system
    }

    /// Both together.
    pub const fn or(self, o: Self) -> Self {
        Self {
            over_voltage: self.over_voltage || o.over_voltage,
            under_voltage: self.under_voltage || o.under_voltage,
            over_temperature: self.over_temperature || o.over_temperature,
            under_temperature: self.under_temperature || o.under_temperature,
            charge_over_current: self.charge_over_current || o.charge_over_current,
            discharge_over_current: self.discharge_over_current || o.discharge_over_current,
            system: self.system || o.system,
        }
    }

    /// The protection a cutoff event of the BMS stands for (`None`: not a
    /// cutoff).
    pub fn of_event(id: EventId) -> Option<Self> {
        let mut p = Self::default();
        match id {
            EventId::UnderVoltageCutoff | EventId::FullyDischargedCutoff => p.under_voltage = true,
            EventId::OverVoltageCutoff => p.over_voltage = true,
            EventId::OverTemperatureCutoff => p.over_temperature = true,
            EventId::LowTemperatureCutoff | EventId::LowTemperatureChargingCutoff => {
                p.under_temperature = true
            }
            EventId::DischargingOverCurrentCutoff => p.discharge_over_current = true,
            EventId::ChargingOverCurrentCutoff | EventId::RegenerationOverCurrentCutoff => {
                p.charge_over_current = true
            }
            EventId::ChargerSwitchError
            | EventId::LoadSwitchError
            | EventId::SinglePortSwitchError => p.system = true,
            _ => return None,
        }
        Some(p)
    }

    /// The protection a stop of charging (`charge`) or discharging for `why`
    /// stands for (`cold`: the temperature is below the charge cutoff).
    pub fn of_stop(why: StopWhy, charge: bool, cold: bool) -> Self {
        let mut p = Self::default();
        match why {
            StopWhy::CellHigh => p.over_voltage = true,
            StopWhy::CellLow => p.under_voltage = true,
            StopWhy::Temperature if cold && charge => p.under_temperature = true,
            StopWhy::Temperature => p.over_temperature = true,
            StopWhy::Current if charge => p.charge_over_current = true,
            StopWhy::Current => p.discharge_over_current = true,
            StopWhy::Fault | StopWhy::LinkLost => p.system = true,
            StopWhy::InverterAsked | StopWhy::Limit => {}
        }
        p
    }
}

/// What the inverter is told this period, decided once for every dialect by
/// the output (`super::super::say`): each dialect only puts it into its own
/// frames, and [`Told`] reads it back from them.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Say {
    /// The limits told: each stopping side at 0, the charge voltage lowered
    /// where a charge stop says so by voltage.
    pub limits: Limits,
    /// The SOC told, %.
    pub soc_pct: f32,
    /// What must stop, and why.
    pub stops: Stops,
    /// The data is current: the measurement frames say now. When it is not,
    /// only what the dialect's inverter needs goes out, with the last values
    /// the BMS sent.
    pub fresh: bool,
    /// The BMS's data is lost (the communication fault of the alarm frame).
    pub link_lost: bool,
    /// The protection bits (see [`Protected`]).
    pub protected: Protected,
    /// The name of 0x35E (`inverter_name`), padded with spaces.
    pub name: [u8; 8],
    /// The Pylontech family's 0x35C bit 3: SOC has not reached 97 % for 30
    /// days.
    pub full_charge: bool,
}

impl Say {
    /// Nothing stops: `limits` and the real SOC, as for a fresh period.
    pub fn plain(limits: Limits, soc_pct: f32) -> Self {
        Self {
            limits,
            soc_pct,
            stops: Stops::default(),
            fresh: true,
            link_lost: false,
            protected: Protected::default(),
            name: *b"PYLON   ",
            full_charge: false,
        }
    }

    /// 0x35C byte 0 (and Growatt's 0x319 bits 7-4): the enable bits, the
    /// force charge requests (I: discharge stopped at a low cell; II: a cell
    /// nearing it, a warning) and the full-charge request; no request to
    /// charge while charging must stop.
    pub fn flags(&self, c: &Conditions) -> u8 {
        let mut b = 0;
        if self.stops.charge.is_none() {
            b |= FLAG_CHARGE_ENABLE;
            if self.stops.discharge == Some(StopWhy::CellLow) {
                b |= FLAG_FORCE_CHARGE_1;
            } else if c.low_voltage == 1 {
                b |= FLAG_FORCE_CHARGE_2;
            }
            if self.full_charge {
                b |= FLAG_FULL_CHARGE;
            }
        }
        if self.stops.discharge.is_none() {
            b |= FLAG_DISCHARGE_ENABLE;
        }
        b
    }
}

/// The enable and request bits (Pylon table 5, 0x35C byte 0): charge enable.
pub const FLAG_CHARGE_ENABLE: u8 = 1 << 7;
/// Discharge enable.
pub const FLAG_DISCHARGE_ENABLE: u8 = 1 << 6;
/// Request force charge I ("designed for inverter allows battery to shut
/// down, and able to wake battery up to charge it").
pub const FLAG_FORCE_CHARGE_1: u8 = 1 << 5;
/// Request force charge II ("inverter doesn't want battery to shut down,
/// able to charge battery before shut down").
pub const FLAG_FORCE_CHARGE_2: u8 = 1 << 4;
/// Request full charge ("if SOC never higher than 97% in 30 days, will set
/// this flag to 1. And when the SOC is ≥ 97%, the flag will be 0").
pub const FLAG_FULL_CHARGE: u8 = 1 << 3;

/// What one period's frames are made of.
pub struct Period<'a> {
    /// What the inverter is told.
    pub say: &'a Say,
    /// The battery's state as last known (of now when `say.fresh`).
    pub state: &'a PackState,
    /// Its alarms and warnings.
    pub conditions: &'a Conditions,
    /// Its capacity, Ah.
    pub capacity_ah: u16,
    /// Modules (packs): online, blocking charge, blocking discharge, offline.
    pub modules: (u16, u16, u16, u16),
    /// The BMS's public firmware version (register 501).
    pub firmware: u16,
    /// The BMS's hardware version and changes (register 500).
    pub hardware: u16,
    /// This period also carries the slow frames (every fifth).
    pub slow: bool,
    /// The BMS's settings (Growatt's cell count and battery type).
    pub settings: Option<&'a PackSettings>,
}

/// What the frames a dialect sent tell an inverter, read back from the bytes
/// (each dialect's `read_back`): the log, `monitor` and Home Assistant say
/// this, never a second description of the decision. `None`: no frame of the
/// dialect carries it (or none was sent yet).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Told {
    /// The limits frame's limits (CVL 0.1 V, CCL, DCL 0.1 A, discharge
    /// voltage 0.1 V where carried).
    pub limits: Option<Limits>,
    /// The SOC told, %.
    pub soc_pct: Option<u8>,
    /// The charge enable bit.
    pub charge_enabled: Option<bool>,
    /// The discharge enable bit.
    pub discharge_enabled: Option<bool>,
    /// Any protection bit (or Victron/SMA alarm) set.
    pub protection: Option<bool>,
    /// The communication-fault (BMS data lost) bit.
    pub link_lost: Option<bool>,
    /// The name of 0x35E.
    pub name: Option<[u8; 8]>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_soc_told_for_each_stop() {
        let s = |c, d| Stops {
            charge: c,
            discharge: d,
        };
        let (hi, lo) = (Some(StopWhy::CellHigh), Some(StopWhy::CellLow));
        assert_eq!(s(None, None).soc_pct(42.0, false), 42.0);
        assert_eq!(s(hi, None).soc_pct(42.0, false), 100.0);
        assert_eq!(s(None, lo).soc_pct(42.0, true), 0.0);
        assert_eq!(s(hi, lo).soc_pct(42.0, false), 0.0);
        assert_eq!(s(hi, lo).soc_pct(42.0, true), 100.0);
    }

    #[test]
    fn a_stop_stands_for_its_protection() {
        let p = |w, charge, cold| Protected::of_stop(w, charge, cold);
        assert!(p(StopWhy::CellHigh, true, false).over_voltage);
        assert!(p(StopWhy::Temperature, true, true).under_temperature);
        assert!(p(StopWhy::Temperature, false, true).over_temperature);
        assert!(p(StopWhy::Current, true, false).charge_over_current);
        assert!(p(StopWhy::Current, false, false).discharge_over_current);
        assert!(p(StopWhy::LinkLost, false, false).system);
        assert!(!p(StopWhy::Limit, true, false).any());
    }

    #[test]
    fn frames_read_past_their_length_as_zero() {
        let f = CanFrame::new(0x351, 2, [1, 2, 3, 4, 5, 6, 7, 8]);
        assert_eq!(f.bytes(), [1, 2]);
        assert_eq!(f.pair(0), [1, 2]);
        assert_eq!(f.pair(1), [2, 0]);
        assert_eq!(f.byte(9), 0);
    }
}
