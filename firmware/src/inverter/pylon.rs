//! The Pylontech LV family, byte by byte: Pylon LV V1.2 (2018-04-08; Deye's
//! copy of it is the same text with another name), Sol-Ark LV V1.3 and
//! Luxpower V04.2. All little-endian, 11-bit identifiers, 500 kbit/s, the
//! whole set every second; the inverter answers with 0x305. Each field's doc
//! line names the spec's table; `docs/can-frames.md` and the DBC files
//! `host-tests/can/tinybms-{pylon,solark,luxpower}.dbc` describe the same.
//!
//! Where a spec is silent this module chose, and says so: the Pylon frames'
//! lengths (the spec prints none: 0x351 6, 0x355 4, 0x356 6, 0x359 8, 0x35C 2,
//! 0x35E 8), the name padded with spaces, the current positive when charging.
//!
//! These inverters may ignore a current limit of 0 A (Deye and Solis keep
//! charging: Battery-Emulator #1534, diyBMS #216, YamBMS #184). So when
//! charging (discharging) must stop, [`Stops`] also clears the enable bit of
//! 0x35C, lowers the charge voltage to the pack's present voltage, and — when
//! the owner turns it on (`stop_by_soc`) — reports SOC 100 % (0 %): what such
//! inverters obey.

use super::control::{Conditions, Limits, PackState};
use super::frames::CanFrame;
use super::protocol::{Period, Protocol};
use crate::Instant;

/// Limits: charge voltage u16 0.1 V, charge current limit s16 0.1 A,
/// discharge current limit s16 0.1 A (Pylon V1.2 p.3-4); Sol-Ark and
/// Luxpower add the discharge voltage limit u16 0.1 V in bytes 6-7.
pub const ID_LIMITS: u16 = 0x351;
/// SOC u16 1 %, SOH u16 1 % (Pylon p.4); Luxpower adds the highest and
/// lowest cell, u16 1 mV.
pub const ID_SOC: u16 = 0x355;
/// Voltage s16 0.01 V (Sol-Ark: 0.1 V), current s16 0.1 A, temperature s16
/// 0.1 °C (Pylon, Sol-Ark: one; Luxpower: the highest and the lowest cell's).
pub const ID_MEASUREMENTS: u16 = 0x356;
/// Protection (bytes 0-1), alarm (bytes 2-3), module count (byte 4), "PN"
/// (bytes 5-6; Luxpower: capacity u16 1 Ah) (Pylon p.3, tables 1-4).
pub const ID_ALARMS: u16 = 0x359;
/// Request flags (byte 0, Pylon table 5); Luxpower: cycle count u16 in
/// bytes 2-3.
pub const ID_FLAGS: u16 = 0x35C;
/// Manufacturer name, ASCII (Pylon p.5: "PYLON"; Deye's copy: "DEYE").
pub const ID_NAME: u16 = 0x35E;
/// Sol-Ark: the bank's capacity, u16 1 Ah (Sol-Ark V1.3 p.5).
pub const ID_CAPACITY: u16 = 0x379;
/// From the inverter, 8 zero bytes: "Inverter reply every second" (Pylon
/// p.2); Sol-Ark: after each data set it received.
pub const ID_HEARTBEAT: u16 = 0x305;
/// From a Luxpower inverter: byte 0 bit 0 = 1 "Shutdown battery" (Luxpower
/// V04.2 p.3, "Remote command from storage inverter").
pub const ID_REMOTE: u16 = 0x300;

/// The name 0x35E says by default: what Pylontech's spec prints, and what
/// Deye, Sunsynk, Sofar, Growatt SPF, EG4 and MidNite recognise.
pub const DEFAULT_NAME: [u8; 8] = *b"PYLON   ";

/// 0x359 byte 0 (protection) and byte 2 (alarm): cell or module over-voltage.
pub const BIT_OVER_VOLTAGE: u8 = 1 << 1;
/// Cell or module under-voltage.
pub const BIT_UNDER_VOLTAGE: u8 = 1 << 2;
/// Cell over-temperature.
pub const BIT_OVER_TEMPERATURE: u8 = 1 << 3;
/// Cell under-temperature.
pub const BIT_UNDER_TEMPERATURE: u8 = 1 << 4;
/// Discharge over-current.
pub const BIT_DISCHARGE_OVER_CURRENT: u8 = 1 << 7;
/// 0x359 byte 1 (protection) and byte 3 (alarm): charge over-current.
pub const BIT_CHARGE_OVER_CURRENT: u8 = 1 << 0;
/// Byte 1: "System error"; byte 3: "Internal communication fail" (Pylon,
/// Luxpower) or "Critical System Error" (Sol-Ark).
pub const BIT_SYSTEM: u8 = 1 << 3;

/// 0x35C byte 0: charge enable.
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

/// While charging must stop, the charge voltage told is this far below the
/// pack's present voltage, 0.1 V (an inverter's constant-voltage stage then
/// has nothing left to charge at once, not after its regulator has wound
/// down).
pub const BELOW_PACK_DV: u16 = 5;

/// The full-charge request's SOC, % ("≥ 97%").
pub const FULL_SOC_PCT: f32 = 97.0;
/// The full-charge request's time without it, µs (30 days).
pub const FULL_CHARGE_AFTER_US: Instant = 30 * 24 * 3600 * crate::SECOND;

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
    /// The BMS's data is stale.
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
    /// From the limits to be sent and the reasons the data gives.
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

    /// The SOC the inverter is told, %: with `by_soc`, 100 while only
    /// charging must stop, 0 while discharging must — with both stopped too
    /// (a charge is then stopped by the charge voltage at the pack's own),
    /// unless a cell at its ceiling stopped the charge; else the real one.
    pub fn soc_pct(&self, real: f32, by_soc: bool) -> f32 {
        if !by_soc {
            return real;
        }
        match (self.charge, self.discharge) {
            (Some(_), None) | (Some(StopWhy::CellHigh), Some(_)) => 100.0,
            (_, Some(_)) => 0.0,
            (None, None) => real,
        }
    }
}

/// Why charging must stop, from the data: the link, a fault, a cell at the
/// top, a temperature, a current; else charge control's own hold.
fn charge_why(state: &PackState, c: &Conditions) -> StopWhy {
    if c.link_lost > 0 {
        StopWhy::LinkLost
    } else if state.fault || c.bms_internal >= 2 || state.charge_blocked {
        StopWhy::Fault
    } else if c.high_voltage > 0 {
        StopWhy::CellHigh
    } else if c.high_temperature_charge > 0
        || c.low_temperature_charge > 0
        || c.high_temperature >= 2
        || c.low_temperature >= 2
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
    if c.link_lost > 0 {
        StopWhy::LinkLost
    } else if state.fault || c.bms_internal >= 2 {
        StopWhy::Fault
    } else if c.low_voltage > 0 {
        StopWhy::CellLow
    } else if c.high_temperature >= 2 || c.low_temperature >= 2 {
        StopWhy::Temperature
    } else if c.high_discharge_current >= 2 {
        StopWhy::Current
    } else {
        StopWhy::Limit
    }
}

/// What the Pylontech family says beyond the limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Extras {
    /// 0x35E (`inverter_name`), padded with spaces.
    pub name: [u8; 8],
    /// What must stop now, and why.
    pub stops: Stops,
    /// Report SOC 100 % / 0 % when charging / discharging must stop
    /// (`stop_by_soc`).
    pub by_soc: bool,
    /// 0x35C bit 3: SOC has not reached 97 % for 30 days.
    pub full_charge: bool,
}

impl Default for Extras {
    fn default() -> Self {
        Self {
            name: DEFAULT_NAME,
            stops: Stops::default(),
            by_soc: false,
            full_charge: false,
        }
    }
}

impl Extras {
    /// The limits the inverter is told: as computed, with the charge voltage
    /// [`BELOW_PACK_DV`] below the pack's present voltage while charging must
    /// stop, so an inverter that ignores a charge current limit of 0 still
    /// stops: it is already past its charge voltage.
    pub fn limits(&self, l: &Limits, state: &PackState) -> Limits {
        let mut out = self.stopped(l);
        if self.stops.charge.is_some() {
            let pack_dv = (state.pack_v * 10.0).max(0.0) as u16;
            if pack_dv > BELOW_PACK_DV {
                out.cvl_dv = out.cvl_dv.min(pack_dv - BELOW_PACK_DV);
            }
        }
        out
    }

    /// `l` with the current limit of each side that must stop at 0 (the
    /// charge voltage as it is: with stale data no voltage of now is known).
    pub fn stopped(&self, l: &Limits) -> Limits {
        let mut out = *l;
        if self.stops.charge.is_some() {
            out.ccl_da = 0;
        }
        if self.stops.discharge.is_some() {
            out.dcl_da = 0;
        }
        out
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

/// The name as 0x35E sends it: up to 8 ASCII bytes of `text`, padded with
/// spaces (a byte outside printable ASCII becomes a space).
pub fn name_bytes(text: &str) -> [u8; 8] {
    let mut out = [b' '; 8];
    for (o, b) in out.iter_mut().zip(text.bytes()) {
        if b.is_ascii_graphic() || b == b' ' {
            *o = b;
        }
    }
    out
}

fn frame(id: u16, len: u8, data: [u8; 8]) -> CanFrame {
    CanFrame { id, len, data }
}

use super::frames::put2 as put;

/// Rounded and saturated to an i16, little-endian.
fn s16(v: f32) -> [u8; 2] {
    super::frames::clamp_i16(v).to_le_bytes()
}

/// Rounded and saturated to a u16, little-endian.
fn u16le(v: f32) -> [u8; 2] {
    super::frames::clamp_u16(v).to_le_bytes()
}

/// The length of `p`'s frames: Sol-Ark and Luxpower always 8; Pylon as
/// given (`pylon`).
fn len(p: Protocol, pylon: u8) -> u8 {
    if p == Protocol::Pylon {
        pylon
    } else {
        8
    }
}

/// 0x351 of `p` for the limits told.
pub fn limits_frame(p: Protocol, l: &Limits) -> CanFrame {
    let mut d = [0u8; 8];
    put(&mut d, 0, l.cvl_dv.to_le_bytes());
    put(
        &mut d,
        2,
        (l.ccl_da.min(i16::MAX as u16) as i16).to_le_bytes(),
    );
    put(
        &mut d,
        4,
        (l.dcl_da.min(i16::MAX as u16) as i16).to_le_bytes(),
    );
    if p != Protocol::Pylon {
        put(&mut d, 6, l.discharge_dv.to_le_bytes());
    }
    frame(ID_LIMITS, len(p, 6), d)
}

/// The limits a 0x351 of the family tells (6 bytes or more; the discharge
/// voltage 0 when absent). Negative limits read as 0.
pub fn limits_of(f: &CanFrame) -> Option<Limits> {
    if f.id != ID_LIMITS || f.len < 6 {
        return None;
    }
    let b = |k: usize| f.data.get(k).copied().unwrap_or(0);
    let w = |i: usize| [b(i), b(i + 1)];
    let discharge_dv = if f.len >= 8 {
        u16::from_le_bytes(w(6))
    } else {
        0
    };
    Some(Limits {
        cvl_dv: u16::from_le_bytes(w(0)),
        ccl_da: i16::from_le_bytes(w(2)).max(0) as u16,
        dcl_da: i16::from_le_bytes(w(4)).max(0) as u16,
        discharge_dv,
    })
}

/// 0x355: SOC (as [`Stops::soc_pct`] says) and SOH; Luxpower: and the cell
/// extremes.
pub fn soc_frame(p: Protocol, s: &PackState, x: &Extras) -> CanFrame {
    let mut d = [0u8; 8];
    let soc = x.stops.soc_pct(s.soc_pct, x.by_soc);
    put(&mut d, 0, u16le(soc.clamp(0.0, 100.0)));
    put(&mut d, 2, u16le(s.soh_pct.clamp(0.0, 100.0)));
    if p == Protocol::Luxpower {
        put(&mut d, 4, s.max_cell_mv.to_le_bytes());
        put(&mut d, 6, s.min_cell_mv.to_le_bytes());
    }
    frame(ID_SOC, len(p, 4), d)
}

/// 0x356: voltage (Sol-Ark 0.1 V, else 0.01 V), current, temperature(s).
pub fn measurements_frame(p: Protocol, s: &PackState) -> CanFrame {
    let mut d = [0u8; 8];
    let volts = if p == Protocol::SolArk {
        s.pack_v * 10.0
    } else {
        s.pack_v * 100.0
    };
    put(&mut d, 0, s16(volts));
    put(&mut d, 2, s16(s.current_a * 10.0));
    if p == Protocol::Luxpower {
        put(&mut d, 4, s16(s.max_temp_c * 10.0));
        put(&mut d, 6, s16(s.min_temp_c * 10.0));
    } else {
        put(&mut d, 4, s16((s.min_temp_c + s.max_temp_c) * 5.0));
    }
    frame(ID_MEASUREMENTS, len(p, 6), d)
}

/// The bits of a protection byte (level 2) or an alarm byte (level ≥ 1) of
/// 0x359 byte 0 / byte 2 for `c`.
fn cell_bits(c: &Conditions, at: u8) -> u8 {
    let on = |v: u8, bit: u8| if v >= at { bit } else { 0 };
    on(c.high_voltage, BIT_OVER_VOLTAGE)
        | on(c.low_voltage, BIT_UNDER_VOLTAGE)
        | on(
            c.high_temperature.max(c.high_temperature_charge),
            BIT_OVER_TEMPERATURE,
        )
        | on(
            c.low_temperature.max(c.low_temperature_charge),
            BIT_UNDER_TEMPERATURE,
        )
        | on(c.high_discharge_current, BIT_DISCHARGE_OVER_CURRENT)
}

/// 0x359: protection and alarm bits (only those the spec defines), the
/// module count, "PN" (Luxpower: the capacity, Ah).
pub fn alarms_frame(p: Protocol, c: &Conditions, modules: u16, capacity_ah: u16) -> CanFrame {
    let on = |v: u8, at: u8, bit: u8| if v >= at { bit } else { 0 };
    let mut d = [0u8; 8];
    d[0] = cell_bits(c, 2);
    d[1] =
        on(c.high_charge_current, 2, BIT_CHARGE_OVER_CURRENT) | on(c.bms_internal, 2, BIT_SYSTEM);
    d[2] = cell_bits(c, 1);
    let byte3_bit3 = if p == Protocol::SolArk {
        c.bms_internal
    } else {
        c.link_lost
    };
    d[3] = on(c.high_charge_current, 1, BIT_CHARGE_OVER_CURRENT) | on(byte3_bit3, 1, BIT_SYSTEM);
    d[4] = modules.min(255) as u8;
    if p == Protocol::Luxpower {
        put(&mut d, 5, capacity_ah.to_le_bytes());
    } else {
        d[5] = b'P';
        d[6] = b'N';
    }
    frame(ID_ALARMS, 8, d)
}

/// 0x35C: the request flags (Luxpower: the cycle count, unknown to the
/// bridge: 0).
pub fn flags_frame(p: Protocol, c: &Conditions, x: &Extras) -> CanFrame {
    let mut d = [0u8; 8];
    d[0] = x.flags(c);
    frame(ID_FLAGS, len(p, 2), d)
}

/// 0x35E: the name.
pub fn name_frame(x: &Extras) -> CanFrame {
    frame(ID_NAME, 8, x.name)
}

/// Sol-Ark's 0x379: the bank's capacity, Ah.
pub fn capacity_frame(capacity_ah: u16) -> CanFrame {
    let mut d = [0u8; 8];
    put(&mut d, 0, capacity_ah.to_le_bytes());
    frame(ID_CAPACITY, 8, d)
}

/// One period of `p`: 0x351, 0x355, 0x356, 0x359, 0x35C, 0x35E (Sol-Ark:
/// and 0x379).
pub fn period_frames(p: Protocol, period: &Period<'_>, push: &mut impl FnMut(CanFrame)) {
    let x = &period.lv;
    push(limits_frame(p, &x.limits(period.limits, period.state)));
    push(soc_frame(p, period.state, x));
    push(measurements_frame(p, period.state));
    push(alarms_frame(
        p,
        period.conditions,
        period.modules.0,
        period.capacity_ah,
    ));
    push(flags_frame(p, period.conditions, x));
    push(name_frame(x));
    if p == Protocol::SolArk {
        push(capacity_frame(period.capacity_ah));
    }
}

/// Stale data: 0x351 with `limits` (as [`Extras::limits`] makes them; the
/// charge voltage as last computed: no voltage of now is known), 0x359 with
/// `c` (the link lost flagged), 0x35C with the enable bits cleared.
pub fn stale_frames(
    p: Protocol,
    limits: &Limits,
    c: &Conditions,
    x: &Extras,
    push: &mut impl FnMut(CanFrame),
) {
    push(limits_frame(p, &x.stopped(limits)));
    push(alarms_frame(p, c, 1, 0));
    push(flags_frame(p, c, x));
}

/// Luxpower's 0x300 asks the battery to shut down (byte 0 bit 0).
pub fn shutdown_asked(id: u16, data: &[u8]) -> bool {
    id == ID_REMOTE && data.first().is_some_and(|b| b & 1 == 1)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A 16S pack at 53.21 V, discharging 12.3 A, 65.4 %, its cells
    /// 3.301-3.345 V and its sensors 21.5-24.9 °C (the Growatt tests too).
    pub(crate) fn state() -> PackState {
        PackState {
            min_cell_mv: 3301,
            max_cell_mv: 3345,
            pack_v: 53.21,
            current_a: -12.3,
            soc_pct: 65.4,
            soh_pct: 97.0,
            min_temp_c: 21.5,
            max_temp_c: 24.9,
            fault: false,
            charge_blocked: false,
        }
    }

    fn limits() -> Limits {
        Limits {
            cvl_dv: 552,
            ccl_da: 1000,
            dcl_da: 1500,
            discharge_dv: 480,
        }
    }

    /// Pylon V1.2 p.3-4, 0x351: "Battery charge voltage … Unit: 0.1V … 16
    /// bits unsigned int", "Charge current limit … 0.1A … 16 bits signed
    /// int", "Discharge current limit … 0.1A … 16 bits signed int"; nothing
    /// in bytes 6-7 (6 bytes sent). Sol-Ark V1.3 p.3 and Luxpower V04.2 p.4
    /// add the discharge voltage (0.1 V) in bytes 6-7 (8 bytes).
    #[test]
    fn limits_0x351() {
        let f = limits_frame(Protocol::Pylon, &limits());
        // 55.2 V = 552 = 0x0228; 100.0 A = 1000 = 0x03E8; 150.0 A = 0x05DC.
        assert_eq!(
            (f.id, f.bytes()),
            (0x351, &[0x28, 0x02, 0xE8, 0x03, 0xDC, 0x05][..])
        );
        let f = limits_frame(Protocol::SolArk, &limits());
        // + 48.0 V = 480 = 0x01E0.
        assert_eq!(f.bytes(), [0x28, 0x02, 0xE8, 0x03, 0xDC, 0x05, 0xE0, 0x01]);
        assert_eq!(
            limits_frame(Protocol::Luxpower, &limits()).bytes(),
            f.bytes()
        );
        assert_eq!(limits_of(&f), Some(limits()));
        let pylon = limits_of(&limits_frame(Protocol::Pylon, &limits())).unwrap();
        assert_eq!(
            pylon,
            Limits {
                discharge_dv: 0,
                ..limits()
            }
        );
    }

    /// 0x355 (Pylon p.4): SOC u16 1 %, SOH u16 1 % (4 bytes); Luxpower p.4:
    /// then "Max Cell voltage" and "Min cell voltage", 1 mV.
    #[test]
    fn soc_0x355() {
        let x = Extras::default();
        let f = soc_frame(Protocol::Pylon, &state(), &x);
        // 65.4 % -> 65 = 0x41; 97 % = 0x61.
        assert_eq!((f.id, f.bytes()), (0x355, &[0x41, 0x00, 0x61, 0x00][..]));
        let f = soc_frame(Protocol::Luxpower, &state(), &x);
        // 3345 mV = 0x0D11, 3301 mV = 0x0CE5.
        assert_eq!(f.bytes(), [0x41, 0x00, 0x61, 0x00, 0x11, 0x0D, 0xE5, 0x0C]);
        let f = soc_frame(Protocol::SolArk, &state(), &x);
        assert_eq!(f.bytes(), [0x41, 0x00, 0x61, 0x00, 0, 0, 0, 0]);
    }

    /// 0x356 (Pylon p.4): "Voltage … Unit: 0.01V … 16 bits signed int",
    /// "total current … 0.1A", "Average cell temperature … 0.1℃". Sol-Ark
    /// p.3: the voltage in 0.1 V. Luxpower p.4: "Max Cell temperature", "Min
    /// Cell temperature", 0.1 ℃.
    #[test]
    fn measurements_0x356() {
        let f = measurements_frame(Protocol::Pylon, &state());
        // 53.21 V = 5321 = 0x14C9; -12.3 A = -123 = 0xFF85; (21.5 + 24.9) / 2
        // = 23.2 °C -> 232 = 0x00E8.
        assert_eq!(
            (f.id, f.bytes()),
            (0x356, &[0xC9, 0x14, 0x85, 0xFF, 0xE8, 0x00][..])
        );
        let f = measurements_frame(Protocol::SolArk, &state());
        // 53.2 V = 532 = 0x0214.
        assert_eq!(f.bytes(), [0x14, 0x02, 0x85, 0xFF, 0xE8, 0x00, 0, 0]);
        let f = measurements_frame(Protocol::Luxpower, &state());
        // 24.9 °C = 249 = 0xF9; 21.5 °C = 215 = 0xD7.
        assert_eq!(f.bytes(), [0xC9, 0x14, 0x85, 0xFF, 0xF9, 0x00, 0xD7, 0x00]);
    }

    /// 0x359 (Pylon p.3, tables 1-4): protection byte 0 b1 over-voltage, b2
    /// under-voltage, b3 over-temperature, b4 under-temperature, b7 discharge
    /// over-current; byte 1 b0 charge over-current, b3 system error; alarm
    /// bytes 2-3 the same; byte 4 "Module numbers"; bytes 5-6 "P" "N".
    /// Luxpower p.3: bytes 5-6 the capacity, Ah.
    #[test]
    fn alarms_0x359_set_only_the_bits_the_spec_defines() {
        let all = Conditions {
            high_voltage: 2,
            low_voltage: 2,
            high_temperature: 2,
            low_temperature: 2,
            high_temperature_charge: 2,
            low_temperature_charge: 2,
            high_discharge_current: 2,
            high_charge_current: 2,
            bms_internal: 2,
            cell_imbalance: 2,
            link_lost: 2,
        };
        let f = alarms_frame(Protocol::Pylon, &all, 3, 280);
        assert_eq!(f.id, 0x359);
        assert_eq!(f.bytes(), [0x9E, 0x09, 0x9E, 0x09, 3, b'P', b'N', 0]);
        // Undefined bits are never set (Battery-Emulator's mistakes: byte 1
        // bit 7 for a fault, the under-voltage bit with over-temperature).
        let hot = Conditions {
            high_temperature: 2,
            ..Conditions::default()
        };
        let f = alarms_frame(Protocol::Pylon, &hot, 1, 0);
        assert_eq!(&f.bytes()[..4], [0x08, 0x00, 0x08, 0x00]);
        let warn = Conditions {
            low_voltage: 1,
            high_charge_current: 1,
            ..Conditions::default()
        };
        let f = alarms_frame(Protocol::Pylon, &warn, 1, 0);
        assert_eq!(&f.bytes()[..4], [0x00, 0x00, 0x04, 0x01]);
        let f = alarms_frame(Protocol::Luxpower, &Conditions::default(), 2, 560);
        // 560 Ah = 0x0230.
        assert_eq!(f.bytes(), [0, 0, 0, 0, 2, 0x30, 0x02, 0]);
        // Sol-Ark table 4: byte 3 bit 3 "Critical System Error".
        let internal = Conditions {
            bms_internal: 1,
            ..Conditions::default()
        };
        assert_eq!(
            alarms_frame(Protocol::SolArk, &internal, 1, 0).bytes()[3],
            0x08
        );
        assert_eq!(
            alarms_frame(Protocol::Pylon, &internal, 1, 0).bytes()[3],
            0x00
        );
    }

    /// 0x35C (Pylon table 5): b7 charge enable, b6 discharge enable, b5
    /// force charge I, b4 force charge II, b3 full charge; bits 2-0 blank.
    #[test]
    fn flags_0x35c() {
        let c = Conditions::default();
        let mut x = Extras::default();
        assert_eq!(flags_frame(Protocol::Pylon, &c, &x).bytes(), [0xC0, 0x00]);
        x.full_charge = true;
        assert_eq!(flags_frame(Protocol::Pylon, &c, &x).bytes(), [0xC8, 0x00]);
        x.stops.charge = Some(StopWhy::CellHigh);
        // No charge, and no request to charge.
        assert_eq!(flags_frame(Protocol::Pylon, &c, &x).bytes(), [0x40, 0x00]);
        x = Extras {
            stops: Stops {
                charge: None,
                discharge: Some(StopWhy::CellLow),
            },
            ..Extras::default()
        };
        assert_eq!(
            flags_frame(Protocol::SolArk, &c, &x).bytes(),
            [0xA0, 0, 0, 0, 0, 0, 0, 0]
        );
        let nearing = Conditions {
            low_voltage: 1,
            ..c
        };
        assert_eq!(flags(&Extras::default(), &nearing), 0xD0);
    }

    fn flags(x: &Extras, c: &Conditions) -> u8 {
        x.flags(c)
    }

    /// 0x35E (Pylon p.5): "Manufacturer Name | PYLON | ASCII"; Deye's copy
    /// says "DEYE". Padded with spaces to 8 bytes.
    #[test]
    fn name_0x35e() {
        assert_eq!(name_frame(&Extras::default()).bytes(), *b"PYLON   ");
        assert_eq!(name_bytes("DEYE"), *b"DEYE    ");
        assert_eq!(name_bytes("GOODWE"), *b"GOODWE  ");
        assert_eq!(name_bytes("TOOLONGNAME"), *b"TOOLONGN");
        assert_eq!(name_bytes("a\u{7f}b"), *b"a b     ");
    }

    /// Sol-Ark V1.3 p.5, 0x379: "Battery [Bank] Capacity, low byte, ui16".
    #[test]
    fn capacity_0x379() {
        assert_eq!(capacity_frame(560).bytes(), [0x30, 0x02, 0, 0, 0, 0, 0, 0]);
    }

    /// Luxpower V04.2 p.3, 0x300: byte 0 "Bit0 RSD battery", 0x01 "Shutdown
    /// battery".
    #[test]
    fn luxpower_shutdown_request() {
        assert!(shutdown_asked(0x300, &[1, 0, 0, 0, 0, 0, 0, 0]));
        assert!(!shutdown_asked(0x300, &[0; 8]));
        assert!(!shutdown_asked(0x300, &[]));
        assert!(!shutdown_asked(0x305, &[1]));
    }

    /// Charging must stop: CCL 0, the charge voltage lowered below the
    /// pack's present voltage, the enable bit clear, and with `stop_by_soc`
    /// SOC 100 %; the real SOC otherwise.
    #[test]
    fn a_stop_is_said_every_way_such_inverters_obey() {
        let s = state();
        let l = Limits {
            ccl_da: 0,
            ..limits()
        };
        let high = Conditions {
            high_voltage: 1,
            ..Conditions::default()
        };
        let stops = Stops::of(&l, &s, &high);
        assert_eq!(stops.charge, Some(StopWhy::CellHigh));
        assert_eq!(stops.discharge, None);
        let x = Extras {
            stops,
            ..Extras::default()
        };
        let told = x.limits(&l, &s);
        // 53.21 V -> 532 dV, less 0.5 V.
        assert_eq!((told.cvl_dv, told.ccl_da, told.dcl_da), (527, 0, 1500));
        assert_eq!(x.flags(&high) & FLAG_CHARGE_ENABLE, 0);
        assert_eq!(soc_frame(Protocol::Pylon, &s, &x).bytes()[0], 65);
        let by_soc = Extras { by_soc: true, ..x };
        assert_eq!(soc_frame(Protocol::Pylon, &s, &by_soc).bytes()[0], 100);
        // Discharging must stop: SOC 0 with stop_by_soc.
        let low = Conditions {
            low_voltage: 2,
            ..Conditions::default()
        };
        let l = Limits {
            dcl_da: 0,
            ..limits()
        };
        let stops = Stops::of(&l, &s, &low);
        assert_eq!(stops.discharge, Some(StopWhy::CellLow));
        let x = Extras {
            stops,
            by_soc: true,
            ..Extras::default()
        };
        assert_eq!(soc_frame(Protocol::Pylon, &s, &x).bytes()[0], 0);
        assert_eq!(x.flags(&low) & FLAG_DISCHARGE_ENABLE, 0);
        // Nothing stops: the computed limits, unchanged.
        let x = Extras::default();
        assert_eq!(x.limits(&limits(), &s), limits());
    }
}
