//! The CAN frames of the two inverter protocols, byte by byte. Every identifier
//! and field is a named constant whose doc line names its public source; the
//! DBC files `host-tests/can/tinybms-victron.dbc` and `tinybms-sma.dbc` describe the
//! same layouts and a host test checks that they agree. All multi-byte fields little-endian.

use super::control::{Conditions, Limits, PackState};

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
    /// The data bytes.
    pub fn bytes(&self) -> &[u8] {
        self.data.get(..usize::from(self.len.min(8))).unwrap_or(&[])
    }
}

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
/// Victron: module counts — online, blocking charge, blocking discharge,
/// offline (u16 each).
pub const ID_MODULES: u16 = 0x372;
/// Victron: min cell mV, max cell mV, min cell temperature K, max cell
/// temperature K (u16 each).
pub const ID_CELL_EXTREMES: u16 = 0x373;
/// Victron: installed capacity, u16 Ah.
pub const ID_CAPACITY: u16 = 0x379;
/// Victron GX keep-alive (all zeros), about every second.
pub const ID_GX_KEEPALIVE: u16 = 0x305;
/// Victron GX keep-alive ("VIC"), about every second.
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

fn field_level(c: &Conditions, f: Field) -> Option<u8> {
    Some(match f {
        Field::General => c.all().into_iter().max().unwrap_or(0),
        Field::HighVoltage => c.high_voltage,
        Field::LowVoltage => c.low_voltage,
        Field::HighTemperature => c.high_temperature,
        Field::LowTemperature => c.low_temperature,
        Field::HighTemperatureCharge => c.high_temperature_charge,
        Field::LowTemperatureCharge => c.low_temperature_charge,
        Field::HighDischargeCurrent => c.high_discharge_current,
        Field::HighChargeCurrent => c.high_charge_current,
        Field::Contactor | Field::ShortCircuit => return None,
        Field::BmsInternal => c.bms_internal,
        Field::CellImbalance => c.cell_imbalance,
    })
}

fn frame(id: u16, bytes: &[u8]) -> CanFrame {
    let mut data = [0u8; 8];
    for (d, b) in data.iter_mut().zip(bytes) {
        *d = *b;
    }
    CanFrame {
        id,
        len: bytes.len().min(8) as u8,
        data,
    }
}

fn put16(out: &mut [u8; 8], at: usize, v: u16) {
    put2(out, at, v.to_le_bytes());
}

/// Two bytes into a frame's data at `at` (nothing past byte 7).
pub(super) fn put2(out: &mut [u8; 8], at: usize, bytes: [u8; 2]) {
    if let Some(s) = out.get_mut(at..at + 2) {
        s.copy_from_slice(&bytes);
    }
}

/// Rounded half away from zero and saturated to a u16 (NaN: 0).
pub(super) fn clamp_u16(v: f32) -> u16 {
    // A NaN or a negative value saturates to 0 in the cast.
    (v + 0.5).clamp(0.0, f32::from(u16::MAX)) as u16
}

/// Rounded half away from zero and saturated to an i16 (NaN: 0).
pub(super) fn clamp_i16(v: f32) -> i16 {
    if v.is_nan() {
        0
    } else {
        // Round half away from zero (no_std: no f32::round).
        let r = if v >= 0.0 { v + 0.5 } else { v - 0.5 };
        r.clamp(f32::from(i16::MIN), f32::from(i16::MAX)) as i16
    }
}

/// 0x351 from the limits (both current limits sent positive).
pub fn limits(l: &Limits) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, l.cvl_dv);
    put16(&mut d, 2, l.ccl_da.min(i16::MAX as u16));
    put16(&mut d, 4, l.dcl_da.min(i16::MAX as u16));
    put16(&mut d, 6, l.discharge_dv);
    frame(ID_LIMITS, &d)
}

/// The limits a 0x351 frame carries (`None` for another frame).
pub fn limits_of(f: &CanFrame) -> Option<Limits> {
    if f.id != ID_LIMITS || f.len < 8 {
        return None;
    }
    let g = |i: usize| {
        let b = |k: usize| f.data.get(k).copied().unwrap_or(0);
        u16::from_le_bytes([b(i), b(i + 1)])
    };
    Some(Limits {
        cvl_dv: g(0),
        ccl_da: g(2),
        dcl_da: g(4),
        discharge_dv: g(6),
    })
}

/// 0x355: SOC and SOH in whole percent (rounded down, so 100 % means really
/// full), high-resolution SOC in 0.01 %.
pub fn soc(p: &PackState) -> CanFrame {
    let mut d = [0u8; 8];
    let soc = p.soc_pct.clamp(0.0, 100.0);
    put16(&mut d, 0, soc as u16);
    put16(&mut d, 2, p.soh_pct.clamp(0.0, 100.0) as u16);
    put16(&mut d, 4, (soc * 100.0) as u16);
    frame(ID_SOC, &d[..6])
}

/// 0x356: pack voltage 0.01 V, current 0.1 A (Victron: positive = charging,
/// as the TinyBMS reports it), the highest sensor temperature 0.1 °C.
pub fn measurements(p: &PackState) -> CanFrame {
    measurements_signed(p, 1.0)
}

/// SMA 0x356: as [`measurements`] with the current's sign turned round
/// (positive = discharging), as clarkni5/tinybms `tiny2si` sends it and its
/// design notes describe; the Sunny Island uses its own shunt for control.
pub fn sma_measurements(p: &PackState) -> CanFrame {
    measurements_signed(p, -1.0)
}

fn measurements_signed(p: &PackState, sign: f32) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, clamp_i16(p.pack_v * 100.0) as u16);
    put16(&mut d, 2, clamp_i16(sign * p.current_a * 10.0) as u16);
    put16(&mut d, 4, clamp_i16(p.max_temp_c * 10.0) as u16);
    frame(ID_MEASUREMENTS, &d[..6])
}

/// Victron 0x35A: 2 bits per field; alarm bytes carry "active" for level 2,
/// warning bytes for level ≥ 1; "not supported" for the fields the TinyBMS
/// does not know. `link_lost` sets the system-status field.
pub fn victron_alarms(c: &Conditions) -> CanFrame {
    let mut d = [0u8; 8];
    for (f, byte, bit) in FIELDS_35A {
        let (alarm, warning) = match field_level(c, f) {
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
    let status = if c.link_lost > 0 {
        VICTRON_ACTIVE
    } else {
        VICTRON_OK
    };
    if let Some(b) = d.get_mut(usize::from(byte)) {
        *b |= status << bit;
    }
    frame(ID_ALARMS, &d)
}

/// SMA 0x35A: one flag per even bit, the same field order; alarm flags only for
/// real faults (any alarm flag stops the Sunny Island until a manual restart):
/// a cell over the over-voltage or under the under-voltage cutoff, over-heat.
/// Everything else — the BMS's own fault status included, which it clears by
/// itself after an over-current trip or a cold-morning cutoff — is at most a
/// warning (CCL/DCL = 0 already protects the pack).
pub fn sma_alarms(c: &Conditions) -> CanFrame {
    let mut d = [0u8; 8];
    for (f, byte, bit) in FIELDS_35A {
        let Some(l) = field_level(c, f) else {
            continue;
        };
        let real_fault = matches!(
            f,
            Field::HighVoltage | Field::LowVoltage | Field::HighTemperature | Field::General
        );
        let general_alarm = f == Field::General
            && (c.high_voltage >= 2 || c.low_voltage >= 2 || c.high_temperature >= 2);
        let alarm = if f == Field::General {
            general_alarm
        } else {
            real_fault && l >= 2
        };
        if alarm {
            if let Some(b) = d.get_mut(usize::from(byte)) {
                *b |= 1 << bit;
            }
        }
        if l >= 1 {
            if let Some(b) = d.get_mut(usize::from(byte) + 4) {
                *b |= 1 << bit;
            }
        }
    }
    frame(ID_ALARMS, &d)
}

/// 0x35E: the battery name.
pub fn name() -> CanFrame {
    frame(ID_NAME, &NAME)
}

/// Victron 0x35F: model id u16 (0: not an officially listed battery), firmware
/// version u16 (the BMS's public firmware version), online capacity u16 Ah.
pub fn victron_info(firmware: u16, capacity_ah: u16) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, 0);
    put16(&mut d, 2, firmware);
    put16(&mut d, 4, capacity_ah);
    frame(ID_INFO, &d[..6])
}

/// SMA 0x35F: chemistry "Li" (2 ASCII), hardware version u16, capacity u16 Ah,
/// software version u16.
pub fn sma_info(hardware: u16, capacity_ah: u16, software: u16) -> CanFrame {
    let mut d = [0u8; 8];
    d[0] = b'L';
    d[1] = b'i';
    put16(&mut d, 2, hardware);
    put16(&mut d, 4, capacity_ah);
    put16(&mut d, 6, software);
    frame(ID_INFO, &d)
}

/// Victron 0x372: one module (the TinyBMS), online; blocking charge / discharge
/// when the limits say so.
pub fn modules(l: &Limits, online: bool) -> CanFrame {
    module_counts((
        u16::from(online),
        u16::from(online && l.ccl_da == 0),
        u16::from(online && l.dcl_da == 0),
        u16::from(!online),
    ))
}

/// Victron 0x372: modules online, blocking charge, blocking discharge, offline
/// (one module per pack).
pub fn module_counts((online, charge, discharge, offline): (u16, u16, u16, u16)) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, online);
    put16(&mut d, 2, charge);
    put16(&mut d, 4, discharge);
    put16(&mut d, 6, offline);
    frame(ID_MODULES, &d)
}

/// Victron 0x373: min/max cell mV, min/max temperature in kelvin.
pub fn cell_extremes(p: &PackState) -> CanFrame {
    let mut d = [0u8; 8];
    let kelvin = |c: f32| clamp_i16(c + 273.15).max(0) as u16;
    put16(&mut d, 0, p.min_cell_mv);
    put16(&mut d, 2, p.max_cell_mv);
    put16(&mut d, 4, kelvin(p.min_temp_c));
    put16(&mut d, 6, kelvin(p.max_temp_c));
    frame(ID_CELL_EXTREMES, &d)
}

/// Victron 0x379: installed capacity, Ah.
pub fn capacity(capacity_ah: u16) -> CanFrame {
    let mut d = [0u8; 8];
    put16(&mut d, 0, capacity_ah);
    frame(ID_CAPACITY, &d[..2])
}
