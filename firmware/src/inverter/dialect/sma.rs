//! SMA Sunny Island, byte by byte: Victron's layouts for 0x351 and 0x355
//! (clarkni5/tinybms `tiny2si`, madsci1016/SMAVenusDriver), 0x356 with the
//! current's sign turned round, 0x35A with one flag per even bit, 0x35F with
//! the chemistry. `host-tests/can/tinybms-sma.dbc` describes the same.
//!
//! A Sunny Island keeps obeying the last 0x351 until 0x355 has been missing
//! for 60 s, and any alarm flag puts it in standby until a manual restart:
//! a stop is said by CCL/DCL 0 every period until the data is back
//! ([`OnSilence::RunsOn`]), and alarms are raised only for real faults.

use super::shared::{push, put2, CanFrame, Frames, Period, Protected, Say, Told};
use super::victron::{self, field_level, Field, FIELDS_35A};
use super::{Dialect, OnSilence, Protocol};
use crate::inverter::control::Conditions;

/// The row of this dialect.
pub const DIALECT: Dialect = Dialect {
    protocol: Protocol::SmaSunnyIsland,
    key: "sma",
    title: "SMA Sunny Island",
    spec: "SMA Sunny Island (external BMS, Li-Ion)",
    heartbeat: &[victron::ID_GX_KEEPALIVE, victron::ID_GX_KEEPALIVE_2],
    answers_only: false,
    ignores_zero: false,
    on_silence: (
        OnSilence::RunsOn,
        "SMA: the Sunny Island obeys the last 0x351 until 0x355 has been missing for 60 s",
    ),
    frames,
    read_back,
};

/// 0x356 as Victron's with the current's sign turned round (positive =
/// discharging), as clarkni5/tinybms `tiny2si` sends it and its design notes
/// describe; the Sunny Island uses its own shunt for control.
pub const CURRENT_SIGN: f32 = -1.0;

/// 0x35A: one flag per even bit, the same field order as Victron's; alarm
/// flags only for real faults (any alarm flag stops the Sunny Island until a
/// manual restart): a cell over the over-voltage or under the under-voltage
/// cutoff, over-heat, or a protection the BMS itself tripped on (see
/// [`Protected`]). Everything else is at most a warning (CCL/DCL = 0 already
/// stops it).
pub fn alarms(c: &Conditions, p: &Protected) -> CanFrame {
    let mut d = [0u8; 8];
    let real = |f: Field| match f {
        Field::HighVoltage => c.high_voltage >= 2 || p.over_voltage,
        Field::LowVoltage => c.low_voltage >= 2 || p.under_voltage,
        Field::HighTemperature => c.high_temperature >= 2 || p.over_temperature,
        _ => false,
    };
    let general =
        real(Field::HighVoltage) || real(Field::LowVoltage) || real(Field::HighTemperature);
    for (f, byte, bit) in FIELDS_35A {
        let Some(l) = field_level(c, &Protected::default(), f) else {
            continue;
        };
        let alarm = if f == Field::General {
            general
        } else {
            real(f)
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
    victron::frame(victron::ID_ALARMS, &d)
}

/// 0x35F: chemistry "Li" (2 ASCII), hardware version u16, capacity u16 Ah,
/// software version u16.
pub fn info(hardware: u16, capacity_ah: u16, software: u16) -> CanFrame {
    let mut d = [0u8; 8];
    d[0] = b'L';
    d[1] = b'i';
    put2(&mut d, 2, hardware.to_le_bytes());
    put2(&mut d, 4, capacity_ah.to_le_bytes());
    put2(&mut d, 6, software.to_le_bytes());
    victron::frame(victron::ID_INFO, &d)
}

/// One period: 0x351, 0x35A, 0x355, and while the data is fresh 0x356 and
/// (every fifth) 0x35E and 0x35F. Without fresh data the Sunny Island gets
/// the limits, the alarms and the SOC told (it stands by when 0x355 stops).
pub fn frames(p: &Period<'_>, out: &mut Frames) {
    let s: &Say = p.say;
    push(out, victron::limits(&s.limits));
    push(out, alarms(p.conditions, &s.protected));
    push(out, victron::soc(s.soc_pct, p.state.soh_pct));
    if !s.fresh {
        return;
    }
    push(out, victron::measurements(p.state, CURRENT_SIGN));
    if p.slow {
        push(out, victron::name());
        push(out, info(p.hardware, p.capacity_ah, p.firmware));
    }
}

/// What a frame of the Sunny Island's tells: the limits, the SOC, any alarm.
pub fn read_back(f: &CanFrame, t: &mut Told) {
    match f.id {
        victron::ID_LIMITS => t.limits = victron::limits_of(f).or(t.limits),
        victron::ID_SOC if f.len >= 2 => {
            t.soc_pct = Some(u16::from_le_bytes(f.pair(0)).min(255) as u8);
        }
        victron::ID_ALARMS if f.len >= 8 => {
            t.protection = Some((0..4).any(|i| f.byte(i) & 0x55 != 0));
        }
        _ => {}
    }
}
