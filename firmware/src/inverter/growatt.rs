//! Growatt's low-voltage protocol (BMS CAN-Bus protocol, low voltage,
//! V1.04, 2019-02-22), byte by byte: 500 kbit/s, 11-bit identifiers,
//! **big-endian** ("the high byte of a value is stored at the lower
//! address"), and request/response: "after the storage inverter sends a
//! query … the battery-pack device responds". The battery never sends
//! unasked: the frames a period computes are kept and sent only when the
//! inverter's 0x301 comes (see `super::Inverter::on_received`); a silent
//! inverter hears nothing.
//!
//! Where the spec is silent this module chose, and says so: every frame 8
//! bytes; the optional cell frames 0x315-0x318 not sent ("do not need to be
//! reported when the battery is connected in parallel"); the numbers of the
//! highest and lowest cell (0x319 bytes 5-6), the cycle count (0x314) and the
//! date (0x320) 0: the bridge does not know them; the maker code "TB".
//! `docs/can-frames.md` and `host-tests/can/tinybms-growatt.dbc` describe
//! the same.

use super::control::{Conditions, Limits, PackSettings, PackState};
use super::frames::CanFrame;
use super::protocol::Period;
use super::pylon::Extras;

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

/// 0x311 status bits 0-1 (table 1).
pub const STATE_STANDBY: u16 = 0b01;
/// Charging.
pub const STATE_CHARGING: u16 = 0b10;
/// Discharging.
pub const STATE_DISCHARGING: u16 = 0b11;
/// Bit 2: the error bytes of 0x312 are valid.
pub const STATUS_ERROR: u16 = 1 << 2;
/// Bit 3: cell balance status, 1 "balance" (the cells within the BMS's
/// allowed disbalance), 0 "unbalance".
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
    CanFrame {
        id,
        len: 8,
        data: d,
    }
}

use super::frames::put2 as put;

/// Rounded and saturated to an i16, big-endian.
fn s16(v: f32) -> [u8; 2] {
    super::frames::clamp_i16(v).to_be_bytes()
}

/// Rounded and saturated to a u16, big-endian.
fn u16be(v: f32) -> [u8; 2] {
    super::frames::clamp_u16(v).to_be_bytes()
}

/// 0x311: the limits told and the status word (`current_a`: the pack's
/// current, positive charging).
pub fn limits_frame(
    l: &Limits,
    current_a: f32,
    c: &Conditions,
    x: &Extras,
    parallel: bool,
) -> CanFrame {
    let mut d = [0u8; 8];
    put(&mut d, 0, l.cvl_dv.to_be_bytes());
    put(&mut d, 2, l.ccl_da.to_be_bytes());
    put(&mut d, 4, l.dcl_da.to_be_bytes());
    let mut status = if current_a > REST_A {
        STATE_CHARGING
    } else if current_a < -REST_A {
        STATE_DISCHARGING
    } else {
        STATE_STANDBY
    };
    if c.all().iter().any(|&v| v > 0) {
        status |= STATUS_ERROR;
    }
    if c.cell_imbalance == 0 {
        status |= STATUS_BALANCED;
    }
    if x.stops.discharge.is_none() {
        status |= STATUS_DISCHARGE;
    }
    if x.stops.charge.is_none() {
        status |= STATUS_CHARGE;
    }
    if parallel {
        status |= STATUS_PARALLEL;
    }
    put(&mut d, 6, status.to_be_bytes());
    frame(ID_LIMITS, d)
}

/// The limits a 0x311 tells.
pub fn limits_of(f: &CanFrame) -> Option<Limits> {
    if f.id != ID_LIMITS || f.len < 6 {
        return None;
    }
    let b = |k: usize| f.data.get(k).copied().unwrap_or(0);
    let w = |i: usize| u16::from_be_bytes([b(i), b(i + 1)]);
    Some(Limits {
        cvl_dv: w(0),
        ccl_da: w(2),
        dcl_da: w(4),
        discharge_dv: 0,
    })
}

/// 0x312: protection (level 2) and alarm (level ≥ 1) bits, only those the
/// spec defines; the pack number, the maker code, the total cell number.
pub fn alarms_frame(c: &Conditions, packs: u16, cells: u16) -> CanFrame {
    let on = |v: u8, at: u8, bit: u8| if v >= at { bit } else { 0 };
    let byte0 = |at: u8| {
        on(c.high_discharge_current, at, 1 << 7)
            | on(c.high_charge_current, at, 1 << 6)
            | on(c.high_voltage, at, 1 << 4)
            | on(c.low_voltage, at, 1 << 3)
    };
    let temperatures = |at: u8| {
        on(c.high_temperature, at, 1 << 7)
            | on(
                c.high_temperature.max(c.high_temperature_charge),
                at,
                1 << 6,
            )
            | on(c.low_temperature, at, 1 << 5)
            | on(c.low_temperature.max(c.low_temperature_charge), at, 1 << 4)
    };
    let mut d = [0u8; 8];
    d[0] = byte0(2);
    d[1] = temperatures(2) | on(c.bms_internal, 2, 1 << 3);
    d[2] = byte0(1);
    d[3] = temperatures(1) | on(c.cell_imbalance, 1, 1 << 2) | on(c.link_lost, 1, 1);
    d[4] = packs.clamp(1, 254) as u8;
    d[5] = MAKER[0];
    d[6] = MAKER[1];
    d[7] = cells.min(254) as u8;
    frame(ID_ALARMS, d)
}

/// 0x313: voltage, current, highest temperature, SOC (as told), SOH.
pub fn measurements_frame(s: &PackState, x: &Extras) -> CanFrame {
    let mut d = [0u8; 8];
    put(&mut d, 0, s16(s.pack_v * 100.0));
    put(&mut d, 2, s16(s.current_a * 10.0));
    put(&mut d, 4, s16(s.max_temp_c * 10.0));
    let soc = x.stops.soc_pct(s.soc_pct, x.by_soc);
    d[6] = (soc.clamp(0.0, 100.0) + 0.5) as u8;
    d[7] = ((s.soh_pct.clamp(0.0, 100.0) + 0.5) as u8) & 0x7F;
    frame(ID_MEASUREMENTS, d)
}

/// 0x314: remaining and full-charge capacity (10 mAh, saturated at
/// 655.35 Ah), the cell delta, the cycle count (unknown: 0).
pub fn capacity_frame(s: &PackState, capacity_ah: u16) -> CanFrame {
    let mut d = [0u8; 8];
    let full = f32::from(capacity_ah) * 100.0;
    put(&mut d, 0, u16be(full * s.soc_pct.clamp(0.0, 100.0) / 100.0));
    put(&mut d, 2, u16be(full));
    put(
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
pub fn flags_frame(s: &PackState, c: &Conditions, x: &Extras, kind: u8) -> CanFrame {
    let mut d = [0u8; 8];
    d[0] = (x.flags(c) & 0xF0) | (kind & 0b11);
    put(&mut d, 1, s.max_cell_mv.to_be_bytes());
    put(&mut d, 3, s.min_cell_mv.to_be_bytes());
    frame(ID_FLAGS, d)
}

/// 0x320: the maker, hardware and software version 1, no date.
pub fn info_frame() -> CanFrame {
    frame(ID_INFO, [MAKER[0], MAKER[1], 1, 1, 0, 0, 0, 0])
}

/// 0x321: no update running.
pub fn update_frame() -> CanFrame {
    frame(ID_UPDATE, [0; 8])
}

/// The answer to one query: 0x311, 0x312, 0x313, 0x314, 0x319, 0x320, 0x321.
pub fn answer_frames(p: &Period<'_>, push: &mut impl FnMut(CanFrame)) {
    let x = &p.lv;
    let packs = p.modules.0.max(1);
    let cells = p.settings.map_or(0, |s| s.cells.saturating_mul(packs));
    push(limits_frame(
        &x.limits(p.limits, p.state),
        p.state.current_a,
        p.conditions,
        x,
        packs > 1,
    ));
    push(alarms_frame(p.conditions, packs, cells));
    push(measurements_frame(p.state, x));
    push(capacity_frame(p.state, p.capacity_ah));
    push(flags_frame(
        p.state,
        p.conditions,
        x,
        battery_type(p.settings),
    ));
    push(info_frame());
    push(update_frame());
}

/// Stale data, as the answer to a query: 0x311 with `limits` (stopped as
/// `x` says) and 0x312 with `c` (the link lost flagged); no measurement.
pub fn stale_frames(limits: &Limits, c: &Conditions, x: &Extras, push: &mut impl FnMut(CanFrame)) {
    // No current of now is known: the status says standby.
    push(limits_frame(&x.stopped(limits), 0.0, c, x, false));
    push(alarms_frame(c, 1, 0));
}

/// Whether `id` is the inverter's query.
pub fn is_query(id: u16) -> bool {
    id == ID_QUERY
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inverter::pylon::tests::state;
    use crate::inverter::pylon::{StopWhy, Stops};

    /// 0x311 (p.4): "Battery charge voltage … 0.1V", "Charge current limit
    /// … 0.1A", "Discharge current limit … 0.1A", big-endian; status bits
    /// 0-1 "11 discharging", bit 3 "Cell balance status" 1 balance, bit 5
    /// "Output Discharge status" 1 enable, bit 6 "Output Charge status" 1
    /// enable (bits 0-7 in byte 7).
    #[test]
    fn limits_0x311_big_endian() {
        let l = Limits {
            cvl_dv: 552,
            ccl_da: 1000,
            dcl_da: 1500,
            discharge_dv: 480,
        };
        let f = limits_frame(
            &l,
            state().current_a,
            &Conditions::default(),
            &Extras::default(),
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
                ..l
            })
        );
        let x = Extras {
            stops: Stops {
                charge: Some(StopWhy::CellHigh),
                discharge: None,
            },
            ..Extras::default()
        };
        let f = limits_frame(&l, state().current_a, &Conditions::default(), &x, true);
        // Charge disabled, parallel (bits 8-9 = 01).
        assert_eq!(&f.bytes()[6..], [0x01, 0x2B]);
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
            link_lost: 1,
            bms_internal: 2,
            ..Conditions::default()
        };
        let f = alarms_frame(&c, 2, 32);
        assert_eq!(
            (f.id, f.bytes()),
            (0x312, &[0x10, 0x08, 0x10, 0xC5, 2, b'T', b'B', 32][..])
        );
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
            link_lost: 2,
        };
        assert_eq!(
            &alarms_frame(&all, 1, 16).bytes()[..4],
            [0xD8, 0xF8, 0xD8, 0xF5]
        );
    }

    /// 0x313 (p.6): voltage 0.01 V Sint16, current 0.1 A Sint16, "Cell
    /// maximum temperature" 0.1 ℃, SOC Uint8 1 %, SOH bits 0-6.
    #[test]
    fn measurements_0x313() {
        let f = measurements_frame(&state(), &Extras::default());
        // 5321 = 0x14C9; -123 = 0xFF85; 249 = 0x00F9; 65 %; 97 %.
        assert_eq!(
            (f.id, f.bytes()),
            (0x313, &[0x14, 0xC9, 0xFF, 0x85, 0x00, 0xF9, 65, 97][..])
        );
    }

    /// 0x314 (p.6): "Gauge RM" and "Gauge FCC" in 10 mAh, "Delta V" 1 mV.
    #[test]
    fn capacity_0x314() {
        let f = capacity_frame(&state(), 280);
        // FCC 280 Ah = 28000 = 0x6D60; RM 65.4 % = 18312 = 0x4788; 44 mV.
        assert_eq!(
            (f.id, f.bytes()),
            (0x314, &[0x47, 0x88, 0x6D, 0x60, 0x00, 0x2C, 0, 0][..])
        );
    }

    /// 0x319 (p.6-7, table 5): b7 charge enable, b6 discharge enable, b5-b4
    /// force charge I/II, b1-b0 battery type (00 LiFePO4); "Maximum cell
    /// voltage" in bytes 1-2, "Minimum cell voltage" in bytes 3-4, 1 mV.
    #[test]
    fn flags_0x319() {
        let f = flags_frame(&state(), &Conditions::default(), &Extras::default(), 0);
        assert_eq!(
            (f.id, f.bytes()),
            (0x319, &[0xC0, 0x0D, 0x11, 0x0C, 0xE5, 0, 0, 0][..])
        );
        let mut x = Extras::default();
        x.full_charge = true;
        // No full-charge request in Growatt's table 5 (bit 3 blank).
        assert_eq!(
            flags_frame(&state(), &Conditions::default(), &x, 1).bytes()[0],
            0xC1
        );
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
}
