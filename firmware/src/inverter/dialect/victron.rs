//! Victron's "CAN-bus BMS" protocol (a GX device on its BMS-Can or VE.Can
//! port), byte by byte. Every identifier and field is a named constant whose
//! doc line names its public source; the DBC file
//! `host-tests/can/tinybms-victron.dbc` describes the same layouts and a host
//! test checks that they agree. All multi-byte fields little-endian.
//!
//! A GX obeys CCL and DCL (DVCC) and stops charging and discharging 3 s after
//! the last 0x351: a stop is said by the limits, and once the data is lost for
//! good the bridge says the stop, then goes quiet ([`OnSilence::Stops`]). The
//! charge voltage is not lowered for an ordinary charge stop (Victron: "a CVL
//! far below the pack voltage makes the system discharge the battery"), nor
//! the SOC changed — unless the inverter was seen ignoring a stop, or the data
//! is lost (see `super::super::say`).

use super::shared::{
    clamp_i16, limit_i16, push, put2, CanFrame, Frames, Period, Protected, Say, Told,
};
use super::{Dialect, OnSilence, Protocol};
use crate::inverter::control::{Conditions, PackState};

/// The row of this dialect.
pub const DIALECT: Dialect = Dialect {
    protocol: Protocol::Victron,
    key: "victron",
    title: "Victron",
    spec: "Victron CAN-bus BMS protocol (a GX: \"CAN-bus BMS LV 500 kbit/s\")",
    heartbeat: &[ID_GX_KEEPALIVE, ID_GX_KEEPALIVE_2],
    answers_only: false,
    ignores_zero: false,
    on_silence: (
        OnSilence::Stops,
        "Victron: the system stops charging and discharging when 0x351 is missing for 3 s",
    ),
    frames,
    read_back,
};

/// Charge/discharge limits: CVL u16 0.1 V, CCL s16 0.1 A, DCL s16 0.1 A,
/// discharge voltage u16 0.1 V. Victron "CAN-bus BMS" protocol (as listed in
/// shared/spec/INVERTER-CAN.md; diyBMS `victron_canbus.cpp`, bsc_fw `Canbus.cpp`);
/// SMA Sunny Island uses the same layout (clarkni5/tinybms `tiny2si`).
pub const ID_LIMITS: u16 = 0x351;
/// SOC u16 1 %, SOH u16 1 %, SOC u16 0.01 % (same sources).
pub const ID_SOC: u16 = 0x355;
/// Voltage s16 0.01 V, current s16 0.1 A (positive = charging), temperature
/// s16 0.1 °C (same sources).
pub const ID_MEASUREMENTS: u16 = 0x356;
/// Alarms (bytes 0-3) and warnings (bytes 4-7), 2-bit fields (Victron) or one
/// flag per even bit (SMA). Field order: see [`FIELDS_35A`].
pub const ID_ALARMS: u16 = 0x35A;
/// Manufacturer / battery name, 8 ASCII bytes.
pub const ID_NAME: u16 = 0x35E;
/// Battery info (Victron: model, firmware, online capacity; SMA: chemistry,
/// hardware version, capacity, software version).
pub const ID_INFO: u16 = 0x35F;
/// Module counts — online, blocking charge, blocking discharge, offline
/// (u16 each).
pub const ID_MODULES: u16 = 0x372;
/// Min cell mV, max cell mV, min cell temperature K, max cell temperature K
/// (u16 each).
pub const ID_CELL_EXTREMES: u16 = 0x373;
/// Installed capacity, u16 Ah.
pub const ID_CAPACITY: u16 = 0x379;
/// GX keep-alive (all zeros), about every second.
pub const ID_GX_KEEPALIVE: u16 = 0x305;
/// GX keep-alive ("VIC"), about every second.
pub const ID_GX_KEEPALIVE_2: u16 = 0x307;

/// The name sent in 0x35E. Not "PYLON": the GX applies Pylontech-specific caps
/// to that name (victronenergy/dbus-systemcalc-py `delegates/dvcc.py`).
pub const NAME: [u8; 8] = *b"TINYBMS ";

/// The fields of 0x35A, in order: byte index and bit offset of each (alarms in
/// bytes 0-3; the matching warning four bytes later). Victron's order as given
/// in shared/spec/INVERTER-CAN.md and as diyBMS's code fills it (its comment
/// text swaps bits 2-3 and 4-5 of byte 0, its code does not).
pub const FIELDS_35A: [(Field, u8, u8); 13] = [
    (Field::General, 0, 0),
    (Field::HighVoltage, 0, 2),
    (Field::LowVoltage, 0, 4),
    (Field::HighTemperature, 0, 6),
    (Field::LowTemperature, 1, 0),
    (Field::HighTemperatureCharge, 1, 2),
    (Field::LowTemperatureCharge, 1, 4),
    (Field::HighDischargeCurrent, 1, 6),
    (Field::HighChargeCurrent, 2, 0),
    (Field::Contactor, 2, 2),
    (Field::ShortCircuit, 2, 4),
    (Field::BmsInternal, 2, 6),
    (Field::CellImbalance, 3, 0),
];

/// A 0x35A field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Field {
    /// Any alarm / warning.
    General,
    /// Cell over-voltage.
    HighVoltage,
    /// Cell under-voltage.
    LowVoltage,
    /// Over-temperature.
    HighTemperature,
    /// Under-temperature.
    LowTemperature,
    /// Charging while hot.
    HighTemperatureCharge,
    /// Charging while cold.
    LowTemperatureCharge,
    /// Discharge over-current.
    HighDischargeCurrent,
    /// Charge over-current.
    HighChargeCurrent,
    /// Contactor (not known to the TinyBMS: "not supported").
    Contactor,
    /// Short circuit (not known: "not supported").
    ShortCircuit,
    /// BMS internal fault.
    BmsInternal,
    /// Cell imbalance.
    CellImbalance,
}

/// Victron 2-bit value as transmitted: condition active. diyBMS
/// (`victron_canbus.cpp`, `BIT01_ALARM = 0b01`) and bsc_fw agree.
pub const VICTRON_ACTIVE: u8 = 0b01;
/// Victron 2-bit value: condition OK (diyBMS `BIT01_OK = 0b10`).
pub const VICTRON_OK: u8 = 0b10;
/// Victron 2-bit value: not supported (diyBMS leaves those fields 0).
pub const VICTRON_UNSUPPORTED: u8 = 0b00;
/// Byte 7 bits 2-3 of the Victron 0x35A: system online/offline (diyBMS and
/// bsc_fw use it): set active when the BMS link is lost.
pub const VICTRON_SYSTEM_STATUS: (u8, u8) = (7, 2);

/// The level of field `f` (0 ok, 1 warning, 2 alarm) for these conditions
/// and protections (a protection is an alarm); `None`: not supported.
pub fn field_level(c: &Conditions, p: &Protected, f: Field) -> Option<u8> {
    let with = |level: u8, protected: bool| if protected { 2 } else { level };
    Some(match f {
        Field::General => c
            .all()
            .into_iter()
            .max()
            .unwrap_or(0)
            .max(if p.any() { 2 } else { 0 }),
        Field::HighVoltage => with(c.high_voltage, p.over_voltage),
        Field::LowVoltage => with(c.low_voltage, p.under_voltage),
        Field::HighTemperature => with(c.high_temperature, p.over_temperature),
        Field::LowTemperature => c.low_temperature,
        Field::HighTemperatureCharge => c.high_temperature_charge,
        Field::LowTemperatureCharge => with(c.low_temperature_charge, p.under_temperature),
        Field::HighDischargeCurrent => with(c.high_discharge_current, p.discharge_over_current),
        Field::HighChargeCurrent => with(c.high_charge_current, p.charge_over_current),
        Field::Contactor | Field::ShortCircuit => return None,
        Field::BmsInternal => with(c.bms_internal, p.system),
        Field::CellImbalance => c.cell_imbalance,
    })
}

/// A frame of `bytes.len()` bytes (at most 8).
pub(super) fn frame(id: u16, bytes: &[u8]) -> CanFrame {
    let mut data = [0u8; 8];
    for (d, b) in data.iter_mut().zip(bytes) {
        *d = *b;
    }
    CanFrame::new(id, bytes.len().min(8) as u8, data)
}

fn put16(out: &mut [u8; 8], at: usize, v: u16) {
    put2(out, at, v.to_le_bytes());
}

/// 0x351 from the limits told (both current limits sent positive).
pub fn limits(l: &crate::inverter::control::Limits) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, l.cvl_dv);
    put16(&mut d, 2, limit_i16(l.ccl_da) as u16);
    put16(&mut d, 4, limit_i16(l.dcl_da) as u16);
    put16(&mut d, 6, l.discharge_dv);
    frame(ID_LIMITS, &d)
}

/// 0x355: the SOC told and the SOH in whole percent (rounded down, so 100 %
/// means really full), the high-resolution SOC in 0.01 %.
pub fn soc(soc_pct: f32, soh_pct: f32) -> CanFrame {
    let mut d = [0u8; 8];
    let soc = soc_pct.clamp(0.0, 100.0);
    put16(&mut d, 0, soc as u16);
    put16(&mut d, 2, soh_pct.clamp(0.0, 100.0) as u16);
    put16(&mut d, 4, (soc * 100.0) as u16);
    frame(ID_SOC, &d[..6])
}

/// 0x356: pack voltage 0.01 V, current 0.1 A (`sign` 1: positive = charging,
/// as the TinyBMS reports it), the highest sensor temperature 0.1 °C.
pub fn measurements(p: &PackState, sign: f32) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, clamp_i16(p.pack_v * 100.0) as u16);
    put16(&mut d, 2, clamp_i16(sign * p.current_a * 10.0) as u16);
    put16(&mut d, 4, clamp_i16(p.max_temp_c * 10.0) as u16);
    frame(ID_MEASUREMENTS, &d[..6])
}

/// Victron 0x35A: 2 bits per field; alarm bytes carry "active" for an alarm
/// (a cell or a measurement past its cutoff, or a protection: see
/// [`Protected`]), warning bytes for a warning or worse; "not supported" for
/// the fields the TinyBMS does not know. `link_lost` sets the system-status
/// field.
pub fn alarms(c: &Conditions, p: &Protected, link_lost: bool) -> CanFrame {
    let mut d = [0u8; 8];
    for (f, byte, bit) in FIELDS_35A {
        let (alarm, warning) = match field_level(c, p, f) {
            None => (VICTRON_UNSUPPORTED, VICTRON_UNSUPPORTED),
            Some(l) => (
                if l >= 2 { VICTRON_ACTIVE } else { VICTRON_OK },
                if l >= 1 { VICTRON_ACTIVE } else { VICTRON_OK },
            ),
        };
        if let Some(b) = d.get_mut(usize::from(byte)) {
            *b |= alarm << bit;
        }
        if let Some(b) = d.get_mut(usize::from(byte) + 4) {
            *b |= warning << bit;
        }
    }
    let (byte, bit) = VICTRON_SYSTEM_STATUS;
    let status = if link_lost {
        VICTRON_ACTIVE
    } else {
        VICTRON_OK
    };
    if let Some(b) = d.get_mut(usize::from(byte)) {
        *b |= status << bit;
    }
    frame(ID_ALARMS, &d)
}

/// 0x35E: the battery name.
pub fn name() -> CanFrame {
    frame(ID_NAME, &NAME)
}

/// 0x35F: model id u16 (0: not an officially listed battery), firmware
/// version u16 (the BMS's public firmware version), online capacity u16 Ah.
pub fn info(firmware: u16, capacity_ah: u16) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, 0);
    put16(&mut d, 2, firmware);
    put16(&mut d, 4, capacity_ah);
    frame(ID_INFO, &d[..6])
}

/// 0x372: modules online, blocking charge, blocking discharge, offline
/// (one module per pack).
pub fn module_counts((online, charge, discharge, offline): (u16, u16, u16, u16)) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, online);
    put16(&mut d, 2, charge);
    put16(&mut d, 4, discharge);
    put16(&mut d, 6, offline);
    frame(ID_MODULES, &d)
}

/// 0x373: min/max cell mV, min/max temperature in kelvin.
pub fn cell_extremes(p: &PackState) -> CanFrame {
    let mut d = [0u8; 8];
    let kelvin = |c: f32| clamp_i16(c + 273.15).max(0) as u16;
    put16(&mut d, 0, p.min_cell_mv);
    put16(&mut d, 2, p.max_cell_mv);
    put16(&mut d, 4, kelvin(p.min_temp_c));
    put16(&mut d, 6, kelvin(p.max_temp_c));
    frame(ID_CELL_EXTREMES, &d)
}

/// 0x379: installed capacity, Ah.
pub fn capacity(capacity_ah: u16) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, capacity_ah);
    frame(ID_CAPACITY, &d[..2])
}

/// One period: 0x351, 0x35A, 0x355, and while the data is fresh 0x356 and
/// (every fifth) 0x35E, 0x35F, 0x372, 0x373, 0x379. Without fresh data no
/// measurement goes out: a GX needs 0x351 and 0x35A to keep the battery.
pub fn frames(p: &Period<'_>, out: &mut Frames) {
    let s: &Say = p.say;
    push(out, limits(&s.limits));
    push(out, alarms(p.conditions, &s.protected, s.link_lost));
    push(out, soc(s.soc_pct, p.state.soh_pct));
    if !s.fresh {
        return;
    }
    push(out, measurements(p.state, 1.0));
    if p.slow {
        push(out, name());
        push(out, info(p.firmware, p.capacity_ah));
        push(out, module_counts(p.modules));
        push(out, cell_extremes(p.state));
        push(out, capacity(p.capacity_ah));
    }
}

/// The limits a 0x351 of Victron's layout carries (8 bytes).
pub fn limits_of(f: &CanFrame) -> Option<crate::inverter::control::Limits> {
    if f.id != ID_LIMITS || f.len < 8 {
        return None;
    }
    let g = |i: usize| u16::from_le_bytes(f.pair(i));
    Some(crate::inverter::control::Limits {
        cvl_dv: g(0),
        ccl_da: i16::from_le_bytes(f.pair(2)).max(0) as u16,
        dcl_da: i16::from_le_bytes(f.pair(4)).max(0) as u16,
        discharge_dv: g(6),
    })
}

/// What a frame of Victron's tells: the limits (0x351), the SOC (0x355),
/// any alarm and the system status (0x35A).
pub fn read_back(f: &CanFrame, t: &mut Told) {
    match f.id {
        ID_LIMITS => t.limits = limits_of(f).or(t.limits),
        ID_SOC if f.len >= 2 => {
            t.soc_pct = Some(u16::from_le_bytes(f.pair(0)).min(255) as u8);
        }
        ID_ALARMS if f.len >= 8 => {
            let alarm = (0..4).any(|i| {
                let b = f.byte(i);
                (0..4).any(|k| (b >> (2 * k)) & 0b11 == VICTRON_ACTIVE)
            });
            t.protection = Some(alarm);
            let (byte, bit) = VICTRON_SYSTEM_STATUS;
            t.link_lost = Some((f.byte(usize::from(byte)) >> bit) & 0b11 == VICTRON_ACTIVE);
        }
        _ => {}
    }
}
