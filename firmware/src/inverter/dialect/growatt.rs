//! Growatt's low-voltage protocol (BMS CAN-Bus protocol, low voltage,
//! V1.04, 2019-02-22), byte by byte: 500 kbit/s, 11-bit identifiers,
//! **big-endian** ("the high byte of a value is stored at the lower
//! address"), and request/response: "after the storage inverter sends a
//! query … the battery-pack device responds". The battery never sends
//! unasked: the frames a period computes are kept and sent only when the
//! inverter's 0x301 comes (see `super::super::Inverter::on_received`); a
//! silent inverter hears nothing. While the data is lost the answer is a
//! stop, to every query until the data is back ([`OnSilence::RunsOn`]).
//!
//! Where the spec is silent this module chose, and says so: every frame 8
//! bytes; the optional cell frames 0x315-0x318 not sent ("do not need to be
//! reported when the battery is connected in parallel"); the numbers of the
//! highest and lowest cell (0x319 bytes 5-6) and the cycle count (0x314) 0:
//! the bridge does not know them; the date of 0x320 a fixed valid one
//! ([`INFO_DATE`]: the bridge has no clock); the maker code "TB".
//! `docs/can-frames.md` and `host-tests/can/tinybms-growatt.dbc` describe
//! the same.

use super::shared::{
    clamp_i16, clamp_u16, push, put2, CanFrame, Frames, Period, Protected, Say, Told,
};
use super::{Dialect, OnSilence, Protocol};
use crate::inverter::control::{Conditions, Limits, PackSettings, PackState};

/// The row of this dialect.
pub const DIALECT: Dialect = Dialect {
    protocol: Protocol::Growatt,
    key: "growatt",
    title: "Growatt LV (V1.04)",
    spec: "Growatt BMS CAN-Bus protocol, low voltage, V1.04 (2019-02-22)",
    heartbeat: &[ID_QUERY],
    answers_only: true,
    ignores_zero: true,
    on_silence: (
        OnSilence::RunsOn,
        "Growatt: the inverter keeps asking; a hybrid may run on without an answer",
    ),
    frames,
    read_back,
};

/// From the inverter, every second: the query (its bytes are not relied on:
/// the spec's example is 11-22-33-44-55-66-77-88, and real inverters send
/// other bytes).
pub const ID_QUERY: u16 = 0x301;
/// Charge voltage u16 0.1 V, charge current limit u16 0.1 A, discharge
/// current limit u16 0.1 A, status (spec p.4, table 1).
pub const ID_LIMITS: u16 = 0x311;
/// Protection (bytes 0-1), alarm (bytes 2-3), pack number, maker code, total
/// cell number (p.5, tables 1-4).
pub const ID_ALARMS: u16 = 0x312;
/// Voltage s16 0.01 V, current s16 0.1 A, highest cell temperature s16
/// 0.1 °C, SOC u8 %, SOH (p.6).
pub const ID_MEASUREMENTS: u16 = 0x313;
/// Remaining and full-charge capacity u16 10 mAh, cell delta u16 mV, cycle
/// count (p.6).
pub const ID_CAPACITY: u16 = 0x314;
/// Request flags and battery type, highest and lowest cell u16 mV and their
/// numbers, protect pack id (p.6-7, table 5).
pub const ID_FLAGS: u16 = 0x319;
/// Maker (2 ASCII), hardware and software version, date & time (p.7).
pub const ID_INFO: u16 = 0x320;
/// Firmware-update status (p.8, table 6): 0 = normal.
pub const ID_UPDATE: u16 = 0x321;

/// The maker code of 0x312 and 0x320: "the battery maker's abbreviation in
/// capital letters".
pub const MAKER: [u8; 2] = *b"TB";

/// 0x320's date and time (p.7: seconds bits 0-5, minutes 6-11, hours 12-16,
/// day 17-21, month 22-25, years since 2000 26-31): 2026-01-01 00:00:00, a
/// fixed date within the specification's ranges (day and month start at 1;
/// an all-zero field is none). The bridge has no clock.
pub const INFO_DATE: u32 = (26 << 26) | (1 << 22) | (1 << 17);

/// 0x311 status bits 0-1 (table 1).
pub const STATE_STANDBY: u16 = 0b01;
/// Charging.
pub const STATE_CHARGING: u16 = 0b10;
/// Discharging.
pub const STATE_DISCHARGING: u16 = 0b11;
/// Bit 2: the error bytes of 0x312 are valid.
pub const STATUS_ERROR: u16 = 1 << 2;
/// Bit 3: cell balance status, 1 "balance" (the cells within the BMS's
/// allowed disbalance: no imbalance warning), 0 "unbalance".
pub const STATUS_BALANCED: u16 = 1 << 3;
/// Bit 5: output discharge enabled.
pub const STATUS_DISCHARGE: u16 = 1 << 5;
/// Bit 6: output charge enabled.
pub const STATUS_CHARGE: u16 = 1 << 6;
/// Bits 8-9 = 01: the master box runs in parallel (several packs).
pub const STATUS_PARALLEL: u16 = 0b01 << 8;

/// Current below which the pack counts as at rest (standby), A.
const REST_A: f32 = 0.5;

fn frame(id: u16, d: [u8; 8]) -> CanFrame {
    CanFrame::new(id, 8, d)
}

/// Rounded and saturated to an i16, big-endian.
fn s16(v: f32) -> [u8; 2] {
    clamp_i16(v).to_be_bytes()
}

/// Rounded and saturated to a u16, big-endian.
fn u16be(v: f32) -> [u8; 2] {
    clamp_u16(v).to_be_bytes()
}

/// 0x311: the limits told and the status word (`current_a`: the pack's
/// current now, positive charging; `None`: no current of now is known).
pub fn limits_frame(say: &Say, current_a: Option<f32>, c: &Conditions, parallel: bool) -> CanFrame {
    let l = &say.limits;
    let mut d = [0u8; 8];
    put2(&mut d, 0, l.cvl_dv.to_be_bytes());
    put2(&mut d, 2, l.ccl_da.to_be_bytes());
    put2(&mut d, 4, l.dcl_da.to_be_bytes());
    let mut status = match current_a {
        Some(i) if i > REST_A => STATE_CHARGING,
        Some(i) if i < -REST_A => STATE_DISCHARGING,
        _ => STATE_STANDBY,
    };
    if c.all().iter().any(|&v| v > 0) || say.protected.any() || say.link_lost {
        status |= STATUS_ERROR;
    }
    if c.cell_imbalance == 0 {
        status |= STATUS_BALANCED;
    }
    if say.stops.discharge.is_none() {
        status |= STATUS_DISCHARGE;
    }
    if say.stops.charge.is_none() {
        status |= STATUS_CHARGE;
    }
    if parallel {
        status |= STATUS_PARALLEL;
    }
    put2(&mut d, 6, status.to_be_bytes());
    frame(ID_LIMITS, d)
}

/// The limits a 0x311 tells.
pub fn limits_of(f: &CanFrame) -> Option<Limits> {
    if f.id != ID_LIMITS || f.len < 6 {
        return None;
    }
    let w = |i: usize| u16::from_be_bytes(f.pair(i));
    Some(Limits {
        cvl_dv: w(0),
        ccl_da: w(2),
        dcl_da: w(4),
        discharge_dv: 0,
    })
}

/// 0x312: protection bits (bytes 0-1) only for a protection (see
/// [`Protected`]), alarm bits (bytes 2-3) for a warning or worse — only
/// those the spec defines; byte 3 bit 0 the BMS's data lost; the pack
/// number, the maker code, the total cell number.
pub fn alarms_frame(say: &Say, c: &Conditions, packs: u16, cells: u16) -> CanFrame {
    let on = |x: bool, bit: u8| if x { bit } else { 0 };
    let p: &Protected = &say.protected;
    let mut d = [0u8; 8];
    d[0] = on(p.discharge_over_current, 1 << 7)
        | on(p.charge_over_current, 1 << 6)
        | on(p.over_voltage, 1 << 4)
        | on(p.under_voltage, 1 << 3);
    d[1] = on(p.over_temperature, 1 << 7)
        | on(p.over_temperature, 1 << 6)
        | on(p.under_temperature, 1 << 4)
        | on(p.system, 1 << 3);
    let w = |v: u8| v >= 1;
    d[2] = on(w(c.high_discharge_current), 1 << 7)
        | on(w(c.high_charge_current), 1 << 6)
        | on(w(c.high_voltage), 1 << 4)
        | on(w(c.low_voltage), 1 << 3);
    d[3] = on(w(c.high_temperature), 1 << 7)
        | on(w(c.high_temperature.max(c.high_temperature_charge)), 1 << 6)
        | on(w(c.low_temperature), 1 << 5)
        | on(w(c.low_temperature.max(c.low_temperature_charge)), 1 << 4)
        | on(w(c.cell_imbalance), 1 << 2)
        | on(say.link_lost, 1);
    d[4] = packs.clamp(1, 254) as u8;
    d[5] = MAKER[0];
    d[6] = MAKER[1];
    d[7] = cells.min(254) as u8;
    frame(ID_ALARMS, d)
}

/// 0x313: voltage, current, highest temperature, SOC (as told), SOH.
pub fn measurements_frame(s: &PackState, soc_pct: f32) -> CanFrame {
    let mut d = [0u8; 8];
    put2(&mut d, 0, s16(s.pack_v * 100.0));
    put2(&mut d, 2, s16(s.current_a * 10.0));
    put2(&mut d, 4, s16(s.max_temp_c * 10.0));
    d[6] = (soc_pct.clamp(0.0, 100.0) + 0.5) as u8;
    d[7] = ((s.soh_pct.clamp(0.0, 100.0) + 0.5) as u8) & 0x7F;
    frame(ID_MEASUREMENTS, d)
}

/// 0x314: remaining capacity (the SOC told of the full one: an inverter
/// that works its SOC out of these two sees the same stop) and full-charge
/// capacity (10 mAh, saturated at 655.35 Ah), the cell delta, the cycle
/// count (unknown: 0).
pub fn capacity_frame(s: &PackState, soc_pct: f32, capacity_ah: u16) -> CanFrame {
    let mut d = [0u8; 8];
    let full = f32::from(capacity_ah) * 100.0;
    put2(&mut d, 0, u16be(full * soc_pct.clamp(0.0, 100.0) / 100.0));
    put2(&mut d, 2, u16be(full));
    put2(
        &mut d,
        4,
        s.max_cell_mv.saturating_sub(s.min_cell_mv).to_be_bytes(),
    );
    frame(ID_CAPACITY, d)
}

/// The battery type of 0x319 bits 1-0 from the over-voltage cutoff: LTO
/// (2) up to 2.9 V, LiFePO4 (0) up to 3.8 V, NCM (1) above.
pub fn battery_type(settings: Option<&PackSettings>) -> u8 {
    match settings.map(|s| s.ov_cutoff_mv) {
        Some(mv) if mv <= 2900 => 0b10,
        Some(mv) if mv > 3800 => 0b01,
        _ => 0b00,
    }
}

/// 0x319: the flags (as the Pylontech family's 0x35C bits 7-4) and the
/// battery type, the cell extremes (their numbers unknown: 0), the protect
/// pack id (0).
pub fn flags_frame(s: &PackState, c: &Conditions, say: &Say, kind: u8) -> CanFrame {
    let mut d = [0u8; 8];
    d[0] = (say.flags(c) & 0xF0) | (kind & 0b11);
    put2(&mut d, 1, s.max_cell_mv.to_be_bytes());
    put2(&mut d, 3, s.min_cell_mv.to_be_bytes());
    frame(ID_FLAGS, d)
}

/// 0x320: the maker, hardware and software version 1, [`INFO_DATE`].
pub fn info_frame() -> CanFrame {
    let [a, b, c, e] = INFO_DATE.to_be_bytes();
    frame(ID_INFO, [MAKER[0], MAKER[1], 1, 1, a, b, c, e])
}

/// 0x321: no update running.
pub fn update_frame() -> CanFrame {
    frame(ID_UPDATE, [0; 8])
}

/// The answer to one query: 0x311, 0x312, 0x313, 0x314, 0x319, 0x320,
/// 0x321 — fresh or not (without fresh data the measurements are the last
/// the BMS sent, the state standby, the communication fault flagged).
pub fn frames(p: &Period<'_>, out: &mut Frames) {
    let s = p.say;
    let packs = p.modules.0.max(1);
    let cells = p.settings.map_or(0, |x| x.cells.saturating_mul(packs));
    let now = s.fresh.then_some(p.state.current_a);
    push(out, limits_frame(s, now, p.conditions, packs > 1));
    push(out, alarms_frame(s, p.conditions, packs, cells));
    push(out, measurements_frame(p.state, s.soc_pct));
    push(out, capacity_frame(p.state, s.soc_pct, p.capacity_ah));
    push(
        out,
        flags_frame(p.state, p.conditions, s, battery_type(p.settings)),
    );
    push(out, info_frame());
    push(out, update_frame());
}

/// What a frame of Growatt's tells: the limits and the enable bits (0x311),
/// the protection and the communication fault (0x312), the SOC (0x313).
pub fn read_back(f: &CanFrame, t: &mut Told) {
    match f.id {
        ID_LIMITS if f.len >= 8 => {
            t.limits = limits_of(f);
            let status = u16::from_be_bytes(f.pair(6));
            t.charge_enabled = Some(status & STATUS_CHARGE != 0);
            t.discharge_enabled = Some(status & STATUS_DISCHARGE != 0);
        }
        ID_ALARMS if f.len >= 4 => {
            t.protection = Some(f.byte(0) != 0 || f.byte(1) != 0);
            t.link_lost = Some(f.byte(3) & 1 != 0);
        }
        ID_MEASUREMENTS if f.len >= 7 => t.soc_pct = Some(f.byte(6)),
        _ => {}
    }
}

/// Whether `id` is the inverter's query.
pub fn is_query(id: u16) -> bool {
    id == ID_QUERY
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inverter::dialect::pylon::tests::{limits, state};
    use crate::inverter::dialect::shared::{StopWhy, Stops};

    fn say() -> Say {
        Say::plain(limits(), state().soc_pct)
    }

    /// 0x311 (p.4): "Battery charge voltage … 0.1V", "Charge current limit
    /// … 0.1A", "Discharge current limit … 0.1A", big-endian; status bits
    /// 0-1 "11 discharging", bit 3 "Cell balance status" 1 balance, bit 5
    /// "Output Discharge status" 1 enable, bit 6 "Output Charge status" 1
    /// enable (bits 0-7 in byte 7).
    #[test]
    fn limits_0x311_big_endian() {
        let f = limits_frame(
            &say(),
            Some(state().current_a),
            &Conditions::default(),
            false,
        );
        // 552 = 0x0228, 1000 = 0x03E8, 1500 = 0x05DC; status 0b0110_1011.
        assert_eq!(
            (f.id, f.bytes()),
            (0x311, &[0x02, 0x28, 0x03, 0xE8, 0x05, 0xDC, 0x00, 0x6B][..])
        );
        assert_eq!(
            limits_of(&f),
            Some(Limits {
                discharge_dv: 0,
                ..limits()
            })
        );
        let s = Say {
            stops: Stops {
                charge: Some(StopWhy::CellHigh),
                discharge: None,
            },
            ..say()
        };
        let f = limits_frame(&s, Some(state().current_a), &Conditions::default(), true);
        // Charge disabled, parallel (bits 8-9 = 01).
        assert_eq!(&f.bytes()[6..], [0x01, 0x2B]);
        // No current of now known (stale): standby; the communication fault
        // makes the error bytes valid (bit 2).
        let lost = Say {
            link_lost: true,
            ..say()
        };
        let f = limits_frame(&lost, None, &Conditions::default(), false);
        assert_eq!(&f.bytes()[6..], [0x00, 0x6D]);
        // Unbalanced: bit 3 clear.
        let spread = Conditions {
            cell_imbalance: 1,
            ..Conditions::default()
        };
        let f = limits_frame(&say(), Some(0.0), &spread, false);
        assert_eq!(f.bytes()[7] & 0x08, 0);
    }

    /// 0x312 (p.5): byte 0 b7 "DisCharge over current", b6 "Charge over
    /// current", b4 "Cell over voltage", b3 "Cell under voltage"; byte 1 b7
    /// OTD, b6 OTC, b5 UTD, b4 UTC, b3 "System error"; alarms in bytes 2-3
    /// (byte 3 b2 "Delta V Fail", b0 "Internal communication fail"); byte 4
    /// "Pack Number"; bytes 5-6 the maker code; byte 7 "Total Cell Number".
    #[test]
    fn alarms_0x312() {
        let c = Conditions {
            high_voltage: 2,
            high_temperature: 1,
            cell_imbalance: 1,
            bms_internal: 2,
            ..Conditions::default()
        };
        let s = Say {
            protected: Protected {
                over_voltage: true,
                system: true,
                ..Protected::default()
            },
            link_lost: true,
            ..say()
        };
        let f = alarms_frame(&s, &c, 2, 32);
        assert_eq!(
            (f.id, f.bytes()),
            (0x312, &[0x10, 0x08, 0x10, 0xC5, 2, b'T', b'B', 32][..])
        );
        // A measurement past its cutoff without a protection: alarm bits only.
        let f = alarms_frame(&say(), &c, 1, 16);
        assert_eq!(&f.bytes()[..4], [0x00, 0x00, 0x10, 0xC4]);
        // Undefined bits stay 0: byte 0 b5-b0 (no short circuit, module or
        // soft start known), byte 1 b2-b0, byte 2 b5 and b2-b0, byte 3 b3.
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
        let every = Say {
            protected: Protected {
                over_voltage: true,
                under_voltage: true,
                over_temperature: true,
                under_temperature: true,
                charge_over_current: true,
                discharge_over_current: true,
                system: true,
            },
            link_lost: true,
            ..say()
        };
        assert_eq!(
            &alarms_frame(&every, &all, 1, 16).bytes()[..4],
            [0xD8, 0xD8, 0xD8, 0xF5]
        );
    }

    /// 0x313 (p.6): voltage 0.01 V Sint16, current 0.1 A Sint16, "Cell
    /// maximum temperature" 0.1 ℃, SOC Uint8 1 %, SOH bits 0-6.
    #[test]
    fn measurements_0x313() {
        let f = measurements_frame(&state(), state().soc_pct);
        // 5321 = 0x14C9; -123 = 0xFF85; 249 = 0x00F9; 65 %; 97 %.
        assert_eq!(
            (f.id, f.bytes()),
            (0x313, &[0x14, 0xC9, 0xFF, 0x85, 0x00, 0xF9, 65, 97][..])
        );
    }

    /// 0x314 (p.6): "Gauge RM" and "Gauge FCC" in 10 mAh, "Delta V" 1 mV.
    #[test]
    fn capacity_0x314() {
        let f = capacity_frame(&state(), state().soc_pct, 280);
        // FCC 280 Ah = 28000 = 0x6D60; RM 65.4 % = 18312 = 0x4788; 44 mV.
        assert_eq!(
            (f.id, f.bytes()),
            (0x314, &[0x47, 0x88, 0x6D, 0x60, 0x00, 0x2C, 0, 0][..])
        );
        // At a discharge stop told by SOC 0 the remaining capacity is 0 too.
        assert_eq!(capacity_frame(&state(), 0.0, 280).bytes()[..2], [0, 0]);
    }

    /// 0x319 (p.6-7, table 5): b7 charge enable, b6 discharge enable, b5-b4
    /// force charge I/II, b1-b0 battery type (00 LiFePO4); "Maximum cell
    /// voltage" in bytes 1-2, "Minimum cell voltage" in bytes 3-4, 1 mV.
    #[test]
    fn flags_0x319() {
        let f = flags_frame(&state(), &Conditions::default(), &say(), 0);
        assert_eq!(
            (f.id, f.bytes()),
            (0x319, &[0xC0, 0x0D, 0x11, 0x0C, 0xE5, 0, 0, 0][..])
        );
        let mut s = say();
        s.full_charge = true;
        // No full-charge request in Growatt's table 5 (bit 3 blank).
        assert_eq!(
            flags_frame(&state(), &Conditions::default(), &s, 1).bytes()[0],
            0xC1
        );
    }

    /// 0x320 (p.7): maker, versions, and a date within the spec's ranges:
    /// 2026-01-01 00:00:00 = year 26 << 26 | month 1 << 22 | day 1 << 17.
    #[test]
    fn info_0x320_has_a_valid_date() {
        let f = info_frame();
        assert_eq!(f.bytes(), [b'T', b'B', 1, 1, 0x68, 0x42, 0x00, 0x00]);
        let d = u32::from_be_bytes([f.byte(4), f.byte(5), f.byte(6), f.byte(7)]);
        let (day, month, year) = ((d >> 17) & 31, (d >> 22) & 15, d >> 26);
        assert!((1..=31).contains(&day) && (1..=12).contains(&month) && year == 26);
    }

    #[test]
    fn battery_type_from_the_cutoff() {
        let mut s = PackSettings {
            fully_charged_mv: 3650,
            capacity_cah: 28_000,
            cells: 16,
            allowed_disbalance_mv: 15,
            ov_cutoff_mv: 3650,
            uv_cutoff_mv: 2800,
            discharge_cutoff_a: 200,
            charge_cutoff_a: 150,
            discharge_cutoff_s: 5,
            overheat_c: 60,
            low_temp_charge_c: 0,
        };
        assert_eq!(battery_type(Some(&s)), 0);
        s.ov_cutoff_mv = 4200;
        assert_eq!(battery_type(Some(&s)), 1);
        s.ov_cutoff_mv = 2850;
        assert_eq!(battery_type(Some(&s)), 2);
        assert_eq!(battery_type(None), 0);
    }

    /// The answer reads back as it was said.
    #[test]
    fn an_answer_reads_back_as_said() {
        let s = Say {
            stops: Stops {
                charge: None,
                discharge: Some(StopWhy::CellLow),
            },
            soc_pct: 0.0,
            ..say()
        };
        let p = Period {
            say: &s,
            state: &state(),
            conditions: &Conditions::default(),
            capacity_ah: 280,
            modules: (1, 0, 1, 0),
            firmware: 0,
            hardware: 0,
            slow: false,
            settings: None,
        };
        let mut out = Frames::new();
        frames(&p, &mut out);
        assert_eq!(out.len(), 7);
        let mut t = Told::default();
        for f in &out {
            read_back(f, &mut t);
        }
        assert_eq!(t.limits.map(|l| l.dcl_da), Some(s.limits.dcl_da));
        assert_eq!(t.soc_pct, Some(0));
        assert_eq!(t.charge_enabled, Some(true));
        assert_eq!(t.discharge_enabled, Some(false));
        assert_eq!(t.link_lost, Some(false));
    }
}
