//! The Pylontech LV family, byte by byte: Pylon LV V1.2 (2018-04-08; Deye's
//! copy of it is the same text with another name), Sol-Ark LV V1.3 and
//! Luxpower V04.2 — three rows of the dialects' table, one file, since they
//! differ only in a few fields. All little-endian, 11-bit identifiers,
//! 500 kbit/s, the whole set every second; the inverter answers with 0x305.
//! Each field's doc line names the spec's table; `docs/can-frames.md` and the
//! DBC files `host-tests/can/tinybms-{pylon,solark,luxpower}.dbc` describe the
//! same.
//!
//! Where a spec is silent this module chose, and says so: the Pylon frames'
//! lengths (the spec prints none: 0x351 8 — the discharge voltage in bytes
//! 6-7, as real Pylontech packs send it and Sol-Ark's and Luxpower's
//! specifications print it —, 0x355 4, 0x356 6, 0x359 8, 0x35C 2, 0x35E 8),
//! the name padded with spaces, the current positive when charging.
//!
//! These inverters may ignore a current limit of 0 A (Deye and Solis keep
//! charging: Battery-Emulator #1534, diyBMS #216, YamBMS #184), and Deye,
//! Sunsynk and Sol-Ark stop on a lost battery only when their owner enabled
//! it: so a stop is said with every signal they obey (the output decides it:
//! see [`Say`]), and once the data is lost it goes out every period until it
//! is back ([`OnSilence::RunsOn`]), with the last measurements the BMS sent in
//! 0x356 (a Deye answers 0x305 only after 0x356).

use super::shared::{
    clamp_i16, clamp_u16, limit_i16, push, put2, CanFrame, Frames, Period, Protected, Say, Told,
};
use super::{Dialect, OnSilence, Protocol};
use crate::inverter::control::{Conditions, Limits, PackState};
use crate::Instant;

/// The row of Pylon LV V1.2.
pub const PYLON: Dialect = Dialect {
    protocol: Protocol::Pylon,
    key: "pylon",
    title: "Pylontech LV (V1.2)",
    spec: "Pylontech LV CAN protocol V1.2 (2018-04-08); Deye's copy: the same text",
    heartbeat: &[ID_HEARTBEAT],
    answers_only: false,
    ignores_zero: true,
    on_silence: (OnSilence::RunsOn, RUNS_ON),
    frames: pylon_frames,
    read_back: pylon_read_back,
};

/// The row of Sol-Ark LV V1.3.
pub const SOLARK: Dialect = Dialect {
    protocol: Protocol::SolArk,
    key: "solark",
    title: "Sol-Ark LV (V1.3)",
    spec: "Sol-Ark LV CAN Bus Protocol V1.3 (2023-01-20)",
    heartbeat: &[ID_HEARTBEAT],
    answers_only: false,
    ignores_zero: true,
    on_silence: (OnSilence::RunsOn, RUNS_ON),
    frames: solark_frames,
    read_back: solark_read_back,
};

/// The row of Luxpower V04.2.
pub const LUXPOWER: Dialect = Dialect {
    protocol: Protocol::Luxpower,
    key: "luxpower",
    title: "Luxpower (V04.2)",
    spec: "Luxpower Battery CANBUS Protocol V04.2 (2023-09-05)",
    heartbeat: &[ID_HEARTBEAT],
    answers_only: false,
    ignores_zero: true,
    on_silence: (OnSilence::RunsOn, RUNS_ON),
    frames: luxpower_frames,
    read_back: luxpower_read_back,
};

/// Why the family gets a stop every period once the data is lost.
const RUNS_ON: &str = "Deye, Sunsynk and Sol-Ark stop on a lost battery only with \
     \"BMS_Err_Stop\" enabled; owners report inverters that kept discharging";

/// Which of the three: what differs between them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Variant {
    /// Pylon LV V1.2.
    Pylon,
    /// Sol-Ark LV V1.3: 8-byte frames, 0x356 in 0.1 V, 0x379, byte 3 bit 3
    /// of 0x359 "critical system error".
    SolArk,
    /// Luxpower V04.2: cell extremes in 0x355 and 0x356, the capacity in
    /// 0x359, the cycle count in 0x35C.
    Luxpower,
}

/// Limits: charge voltage u16 0.1 V, charge current limit s16 0.1 A,
/// discharge current limit s16 0.1 A (Pylon V1.2 p.3-4), discharge voltage
/// limit u16 0.1 V in bytes 6-7 (Sol-Ark, Luxpower; real Pylontech packs).
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

pub use super::shared::{
    FLAG_CHARGE_ENABLE, FLAG_DISCHARGE_ENABLE, FLAG_FORCE_CHARGE_1, FLAG_FORCE_CHARGE_2,
    FLAG_FULL_CHARGE,
};

/// The full-charge request's SOC, % ("≥ 97%").
pub const FULL_SOC_PCT: f32 = 97.0;
/// The full-charge request's time without it, µs (30 days).
pub const FULL_CHARGE_AFTER_US: Instant = 30 * 24 * 3600 * crate::SECOND;

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
    CanFrame::new(id, len, data)
}

/// Rounded and saturated to an i16, little-endian.
fn s16(v: f32) -> [u8; 2] {
    clamp_i16(v).to_le_bytes()
}

/// Rounded and saturated to a u16, little-endian.
fn u16le(v: f32) -> [u8; 2] {
    clamp_u16(v).to_le_bytes()
}

/// The length of `v`'s frames: Sol-Ark and Luxpower always 8; Pylon as
/// given (`pylon`).
fn len(v: Variant, pylon: u8) -> u8 {
    if v == Variant::Pylon {
        pylon
    } else {
        8
    }
}

/// 0x351 for the limits told, 8 bytes for every variant.
pub fn limits_frame(l: &Limits) -> CanFrame {
    let mut d = [0u8; 8];
    put2(&mut d, 0, l.cvl_dv.to_le_bytes());
    put2(&mut d, 2, limit_i16(l.ccl_da).to_le_bytes());
    put2(&mut d, 4, limit_i16(l.dcl_da).to_le_bytes());
    put2(&mut d, 6, l.discharge_dv.to_le_bytes());
    frame(ID_LIMITS, 8, d)
}

/// The limits a 0x351 of the family tells (6 bytes or more; the discharge
/// voltage 0 when absent). Negative limits read as 0.
pub fn limits_of(f: &CanFrame) -> Option<Limits> {
    if f.id != ID_LIMITS || f.len < 6 {
        return None;
    }
    let discharge_dv = if f.len >= 8 {
        u16::from_le_bytes(f.pair(6))
    } else {
        0
    };
    Some(Limits {
        cvl_dv: u16::from_le_bytes(f.pair(0)),
        ccl_da: i16::from_le_bytes(f.pair(2)).max(0) as u16,
        dcl_da: i16::from_le_bytes(f.pair(4)).max(0) as u16,
        discharge_dv,
    })
}

/// 0x355: the SOC told and the SOH; Luxpower: and the cell extremes.
pub fn soc_frame(v: Variant, s: &PackState, soc_pct: f32) -> CanFrame {
    let mut d = [0u8; 8];
    put2(&mut d, 0, u16le(soc_pct.clamp(0.0, 100.0)));
    put2(&mut d, 2, u16le(s.soh_pct.clamp(0.0, 100.0)));
    if v == Variant::Luxpower {
        put2(&mut d, 4, s.max_cell_mv.to_le_bytes());
        put2(&mut d, 6, s.min_cell_mv.to_le_bytes());
    }
    frame(ID_SOC, len(v, 4), d)
}

/// 0x356: voltage (Sol-Ark 0.1 V, else 0.01 V), current, temperature(s).
pub fn measurements_frame(v: Variant, s: &PackState) -> CanFrame {
    let mut d = [0u8; 8];
    let volts = if v == Variant::SolArk {
        s.pack_v * 10.0
    } else {
        s.pack_v * 100.0
    };
    put2(&mut d, 0, s16(volts));
    put2(&mut d, 2, s16(s.current_a * 10.0));
    if v == Variant::Luxpower {
        put2(&mut d, 4, s16(s.max_temp_c * 10.0));
        put2(&mut d, 6, s16(s.min_temp_c * 10.0));
    } else {
        put2(&mut d, 4, s16((s.min_temp_c + s.max_temp_c) * 5.0));
    }
    frame(ID_MEASUREMENTS, len(v, 6), d)
}

/// The alarm bits of 0x359 byte 2 (a warning or worse, level ≥ 1) for `c`.
fn alarm_bits(c: &Conditions) -> u8 {
    let on = |v: u8, bit: u8| if v >= 1 { bit } else { 0 };
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

/// The protection bits of 0x359 bytes 0 and 1 for `p`.
pub fn protection_bytes(p: &Protected) -> [u8; 2] {
    let on = |b: bool, bit: u8| if b { bit } else { 0 };
    [
        on(p.over_voltage, BIT_OVER_VOLTAGE)
            | on(p.under_voltage, BIT_UNDER_VOLTAGE)
            | on(p.over_temperature, BIT_OVER_TEMPERATURE)
            | on(p.under_temperature, BIT_UNDER_TEMPERATURE)
            | on(p.discharge_over_current, BIT_DISCHARGE_OVER_CURRENT),
        on(p.charge_over_current, BIT_CHARGE_OVER_CURRENT) | on(p.system, BIT_SYSTEM),
    ]
}

/// 0x359: protection bits only for a protection (see [`Protected`]), alarm
/// bits for a warning or worse (only those the spec defines; byte 3 bit 3
/// the BMS data lost — Sol-Ark: a BMS fault), the module count, "PN"
/// (Luxpower: the capacity, Ah).
pub fn alarms_frame(
    v: Variant,
    say: &Say,
    c: &Conditions,
    modules: u16,
    capacity_ah: u16,
) -> CanFrame {
    let on = |x: bool, bit: u8| if x { bit } else { 0 };
    let mut d = [0u8; 8];
    let [p0, p1] = protection_bytes(&say.protected);
    d[0] = p0;
    d[1] = p1;
    d[2] = alarm_bits(c);
    let byte3_bit3 = if v == Variant::SolArk {
        c.bms_internal >= 1
    } else {
        say.link_lost
    };
    d[3] = on(c.high_charge_current >= 1, BIT_CHARGE_OVER_CURRENT) | on(byte3_bit3, BIT_SYSTEM);
    d[4] = modules.clamp(1, 255) as u8;
    if v == Variant::Luxpower {
        put2(&mut d, 5, capacity_ah.to_le_bytes());
    } else {
        d[5] = b'P';
        d[6] = b'N';
    }
    frame(ID_ALARMS, 8, d)
}

/// 0x35C: the request flags (Luxpower: the cycle count, unknown to the
/// bridge: 0).
pub fn flags_frame(v: Variant, c: &Conditions, say: &Say) -> CanFrame {
    let mut d = [0u8; 8];
    d[0] = say.flags(c);
    frame(ID_FLAGS, len(v, 2), d)
}

/// 0x35E: the name.
pub fn name_frame(name: &[u8; 8]) -> CanFrame {
    frame(ID_NAME, 8, *name)
}

/// Sol-Ark's 0x379: the bank's capacity, Ah.
pub fn capacity_frame(capacity_ah: u16) -> CanFrame {
    let mut d = [0u8; 8];
    put2(&mut d, 0, capacity_ah.to_le_bytes());
    frame(ID_CAPACITY, 8, d)
}

/// One period of `v`: 0x351, 0x355, 0x356, 0x359, 0x35C, 0x35E (Sol-Ark:
/// and 0x379) — the whole set fresh or not: without fresh data 0x356 carries
/// the last values the BMS sent (the inverter's heartbeat needs it), with
/// the communication fault flagged in 0x359.
pub fn period_frames(v: Variant, p: &Period<'_>, out: &mut Frames) {
    let s = p.say;
    push(out, limits_frame(&s.limits));
    push(out, soc_frame(v, p.state, s.soc_pct));
    push(out, measurements_frame(v, p.state));
    push(
        out,
        alarms_frame(v, s, p.conditions, p.modules.0, p.capacity_ah),
    );
    push(out, flags_frame(v, p.conditions, s));
    push(out, name_frame(&s.name));
    if v == Variant::SolArk {
        push(out, capacity_frame(p.capacity_ah));
    }
}

fn pylon_frames(p: &Period<'_>, out: &mut Frames) {
    period_frames(Variant::Pylon, p, out);
}

fn solark_frames(p: &Period<'_>, out: &mut Frames) {
    period_frames(Variant::SolArk, p, out);
}

fn luxpower_frames(p: &Period<'_>, out: &mut Frames) {
    period_frames(Variant::Luxpower, p, out);
}

/// What a frame of `v` tells: the limits, the SOC, the protection and the
/// communication fault, the enable bits, the name.
pub fn read_back(v: Variant, f: &CanFrame, t: &mut Told) {
    match f.id {
        ID_LIMITS => t.limits = limits_of(f).or(t.limits),
        ID_SOC if f.len >= 2 => {
            t.soc_pct = Some(u16::from_le_bytes(f.pair(0)).min(255) as u8);
        }
        ID_ALARMS if f.len >= 4 => {
            t.protection = Some(f.byte(0) != 0 || f.byte(1) != 0);
            if v != Variant::SolArk {
                t.link_lost = Some(f.byte(3) & BIT_SYSTEM != 0);
            }
        }
        ID_FLAGS if f.len >= 1 => {
            t.charge_enabled = Some(f.byte(0) & FLAG_CHARGE_ENABLE != 0);
            t.discharge_enabled = Some(f.byte(0) & FLAG_DISCHARGE_ENABLE != 0);
        }
        ID_NAME => t.name = Some(f.data),
        _ => {}
    }
}

fn pylon_read_back(f: &CanFrame, t: &mut Told) {
    read_back(Variant::Pylon, f, t);
}

fn solark_read_back(f: &CanFrame, t: &mut Told) {
    read_back(Variant::SolArk, f, t);
}

fn luxpower_read_back(f: &CanFrame, t: &mut Told) {
    read_back(Variant::Luxpower, f, t);
}

/// Luxpower's 0x300 asks the battery to shut down (byte 0 bit 0).
pub fn shutdown_asked(id: u16, data: &[u8]) -> bool {
    id == ID_REMOTE && data.first().is_some_and(|b| b & 1 == 1)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::inverter::dialect::shared::{StopWhy, Stops};

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
            balancing: 0,
        }
    }

    pub(crate) fn limits() -> Limits {
        Limits {
            cvl_dv: 552,
            ccl_da: 1000,
            dcl_da: 1500,
            discharge_dv: 480,
        }
    }

    /// Pylon V1.2 p.3-4, 0x351: "Battery charge voltage … Unit: 0.1V … 16
    /// bits unsigned int", "Charge current limit … 0.1A … 16 bits signed
    /// int", "Discharge current limit … 0.1A … 16 bits signed int". Sol-Ark
    /// V1.3 p.3 and Luxpower V04.2 p.4 add the discharge voltage (0.1 V) in
    /// bytes 6-7, and real Pylontech packs send it too: 8 bytes for all.
    #[test]
    fn limits_0x351() {
        let f = limits_frame(&limits());
        // 55.2 V = 552 = 0x0228; 100.0 A = 1000 = 0x03E8; 150.0 A = 0x05DC;
        // 48.0 V = 480 = 0x01E0.
        assert_eq!(
            (f.id, f.bytes()),
            (0x351, &[0x28, 0x02, 0xE8, 0x03, 0xDC, 0x05, 0xE0, 0x01][..])
        );
        assert_eq!(limits_of(&f), Some(limits()));
        // A 6-byte frame (the PDF's form) reads without the discharge voltage.
        let short = CanFrame::new(0x351, 6, f.data);
        assert_eq!(limits_of(&short).map(|l| l.discharge_dv), Some(0));
    }

    /// 0x355 (Pylon p.4): SOC u16 1 %, SOH u16 1 % (4 bytes); Luxpower p.4:
    /// then "Max Cell voltage" and "Min cell voltage", 1 mV.
    #[test]
    fn soc_0x355() {
        let f = soc_frame(Variant::Pylon, &state(), 65.4);
        // 65.4 % -> 65 = 0x41; 97 % = 0x61.
        assert_eq!((f.id, f.bytes()), (0x355, &[0x41, 0x00, 0x61, 0x00][..]));
        let f = soc_frame(Variant::Luxpower, &state(), 65.4);
        // 3345 mV = 0x0D11, 3301 mV = 0x0CE5.
        assert_eq!(f.bytes(), [0x41, 0x00, 0x61, 0x00, 0x11, 0x0D, 0xE5, 0x0C]);
        let f = soc_frame(Variant::SolArk, &state(), 65.4);
        assert_eq!(f.bytes(), [0x41, 0x00, 0x61, 0x00, 0, 0, 0, 0]);
    }

    /// 0x356 (Pylon p.4): "Voltage … Unit: 0.01V … 16 bits signed int",
    /// "total current … 0.1A", "Average cell temperature … 0.1℃". Sol-Ark
    /// p.3: the voltage in 0.1 V. Luxpower p.4: "Max Cell temperature", "Min
    /// Cell temperature", 0.1 ℃.
    #[test]
    fn measurements_0x356() {
        let f = measurements_frame(Variant::Pylon, &state());
        // 53.21 V = 5321 = 0x14C9; -12.3 A = -123 = 0xFF85; (21.5 + 24.9) / 2
        // = 23.2 °C -> 232 = 0x00E8.
        assert_eq!(
            (f.id, f.bytes()),
            (0x356, &[0xC9, 0x14, 0x85, 0xFF, 0xE8, 0x00][..])
        );
        let f = measurements_frame(Variant::SolArk, &state());
        // 53.2 V = 532 = 0x0214.
        assert_eq!(f.bytes(), [0x14, 0x02, 0x85, 0xFF, 0xE8, 0x00, 0, 0]);
        let f = measurements_frame(Variant::Luxpower, &state());
        // 24.9 °C = 249 = 0xF9; 21.5 °C = 215 = 0xD7.
        assert_eq!(f.bytes(), [0xC9, 0x14, 0x85, 0xFF, 0xF9, 0x00, 0xD7, 0x00]);
    }

    fn say() -> Say {
        Say::plain(limits(), 65.4)
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
        };
        let every = Protected {
            over_voltage: true,
            under_voltage: true,
            over_temperature: true,
            under_temperature: true,
            charge_over_current: true,
            discharge_over_current: true,
            system: true,
        };
        let s = Say {
            protected: every,
            link_lost: true,
            ..say()
        };
        let f = alarms_frame(Variant::Pylon, &s, &all, 3, 280);
        assert_eq!(f.id, 0x359);
        assert_eq!(f.bytes(), [0x9E, 0x09, 0x9E, 0x09, 3, b'P', b'N', 0]);
        // Undefined bits are never set (Battery-Emulator's mistakes: byte 1
        // bit 7 for a fault, the under-voltage bit with over-temperature).
        let hot = Conditions {
            high_temperature: 2,
            ..Conditions::default()
        };
        let f = alarms_frame(Variant::Pylon, &say(), &hot, 1, 0);
        // An alarm past a cutoff the BMS did not trip on: no protection bit.
        assert_eq!(&f.bytes()[..4], [0x00, 0x00, 0x08, 0x00]);
        let tripped = Say {
            protected: Protected {
                over_temperature: true,
                ..Protected::default()
            },
            ..say()
        };
        let f = alarms_frame(Variant::Pylon, &tripped, &hot, 1, 0);
        assert_eq!(&f.bytes()[..4], [0x08, 0x00, 0x08, 0x00]);
        let warn = Conditions {
            low_voltage: 1,
            high_charge_current: 1,
            ..Conditions::default()
        };
        let f = alarms_frame(Variant::Pylon, &say(), &warn, 1, 0);
        assert_eq!(&f.bytes()[..4], [0x00, 0x00, 0x04, 0x01]);
        let f = alarms_frame(Variant::Luxpower, &say(), &Conditions::default(), 2, 560);
        // 560 Ah = 0x0230.
        assert_eq!(f.bytes(), [0, 0, 0, 0, 2, 0x30, 0x02, 0]);
        // Sol-Ark table 4: byte 3 bit 3 "Critical System Error".
        let internal = Conditions {
            bms_internal: 1,
            ..Conditions::default()
        };
        assert_eq!(
            alarms_frame(Variant::SolArk, &say(), &internal, 1, 0).bytes()[3],
            0x08
        );
        assert_eq!(
            alarms_frame(Variant::Pylon, &say(), &internal, 1, 0).bytes()[3],
            0x00
        );
        // Pylon, Luxpower: byte 3 bit 3 "Internal communication fail" = the
        // BMS's data lost.
        let lost = Say {
            link_lost: true,
            ..say()
        };
        let f = alarms_frame(Variant::Pylon, &lost, &Conditions::default(), 1, 0);
        assert_eq!(f.bytes()[3], 0x08);
    }

    /// 0x35C (Pylon table 5): b7 charge enable, b6 discharge enable, b5
    /// force charge I, b4 force charge II, b3 full charge; bits 2-0 blank.
    #[test]
    fn flags_0x35c() {
        let c = Conditions::default();
        let mut s = say();
        assert_eq!(flags_frame(Variant::Pylon, &c, &s).bytes(), [0xC0, 0x00]);
        s.full_charge = true;
        assert_eq!(flags_frame(Variant::Pylon, &c, &s).bytes(), [0xC8, 0x00]);
        s.stops.charge = Some(StopWhy::CellHigh);
        // No charge, and no request to charge.
        assert_eq!(flags_frame(Variant::Pylon, &c, &s).bytes(), [0x40, 0x00]);
        let s = Say {
            stops: Stops {
                charge: None,
                discharge: Some(StopWhy::CellLow),
            },
            ..say()
        };
        assert_eq!(
            flags_frame(Variant::SolArk, &c, &s).bytes(),
            [0xA0, 0, 0, 0, 0, 0, 0, 0]
        );
        let nearing = Conditions {
            low_voltage: 1,
            ..c
        };
        assert_eq!(say().flags(&nearing), 0xD0);
    }

    /// 0x35E (Pylon p.5): "Manufacturer Name | PYLON | ASCII"; Deye's copy
    /// says "DEYE". Padded with spaces to 8 bytes.
    #[test]
    fn name_0x35e() {
        assert_eq!(name_frame(&DEFAULT_NAME).bytes(), *b"PYLON   ");
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

    /// What the frames say reads back as it was said, for each variant.
    #[test]
    fn a_period_reads_back_as_said() {
        let s = Say {
            stops: Stops {
                charge: Some(StopWhy::LinkLost),
                discharge: None,
            },
            soc_pct: 100.0,
            fresh: false,
            link_lost: true,
            protected: Protected {
                system: true,
                ..Protected::default()
            },
            ..say()
        };
        for (v, row) in [
            (Variant::Pylon, &PYLON),
            (Variant::SolArk, &SOLARK),
            (Variant::Luxpower, &LUXPOWER),
        ] {
            let p = Period {
                say: &s,
                state: &state(),
                conditions: &Conditions::default(),
                capacity_ah: 280,
                modules: (1, 1, 0, 0),
                firmware: 0,
                hardware: 0,
                slow: true,
                settings: None,
            };
            let mut out = Frames::new();
            (row.frames)(&p, &mut out);
            assert_eq!(out.len(), if v == Variant::SolArk { 7 } else { 6 });
            let mut t = Told::default();
            for f in &out {
                (row.read_back)(f, &mut t);
            }
            assert_eq!(t.limits, Some(s.limits), "{v:?}");
            assert_eq!(t.soc_pct, Some(100));
            assert_eq!(t.charge_enabled, Some(false));
            assert_eq!(t.discharge_enabled, Some(true));
            assert_eq!(t.protection, Some(true));
            let lost = if v == Variant::SolArk {
                None
            } else {
                Some(true)
            };
            assert_eq!(t.link_lost, lost, "{v:?}");
            assert_eq!(t.name, Some(DEFAULT_NAME));
            // Without fresh data 0x356 still goes (a Deye's heartbeat).
            assert!(out.iter().any(|f| f.id == ID_MEASUREMENTS));
        }
    }
}
