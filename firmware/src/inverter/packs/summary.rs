//! A pack's summary on the bus: its wire format (four frames per node on
//! 0x6A0-0x6BF) and its checks.

use crate::inverter::control::{Conditions, Limits, PackState};
use crate::inverter::dialect::CanFrame;
use crate::Instant;

/// Identifier of node 1's first summary frame.
pub const SUMMARY_BASE_ID: u16 = 0x6A0;
/// Highest node number.
pub const MAX_NODES: u8 = 8;
/// Frames per summary.
pub const SUMMARY_FRAMES: usize = 4;
/// Sequence numbers are 4 bits (0..=15, in the low bits of byte 7): the mask
/// that keeps one in range, and wraps the next one round.
pub const SEQ_MASK: u8 = 0x0F;
/// Last identifier of the summary range.
pub const SUMMARY_LAST_ID: u16 = SUMMARY_BASE_ID + (MAX_NODES as u16) * 4 - 1;

/// One pack's summary, in the integer units of the frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Summary {
    /// Pack voltage, 0.01 V.
    pub voltage_cv: u16,
    /// Pack current, 0.1 A (positive = charging).
    pub current_da: i16,
    /// SOC, 0.01 % (0..=10000).
    pub soc_cpct: u16,
    /// SOH, % (0..=100).
    pub soh_pct: u8,
    /// Lowest cell, mV.
    pub min_cell_mv: u16,
    /// Highest cell, mV.
    pub max_cell_mv: u16,
    /// Lowest temperature, 0.1 °C.
    pub min_temp_dc: i16,
    /// Highest temperature, 0.1 °C.
    pub max_temp_dc: i16,
    /// Age of the pack's data when sent, 0.1 s (255 = 25.5 s or more).
    pub age_ds: u8,
    /// Capacity (BMS register 306), 0.1 Ah.
    pub capacity_dah: u16,
    /// The pack's own limits as its bridge computed them.
    pub limits: Limits,
    /// The pack's alarms and warnings (its data's age is `age_ds`).
    pub conditions: Conditions,
    /// BMS status "fault" (its switch is open).
    pub fault: bool,
    /// A charge-side fault is latched (charge switch open).
    pub charge_blocked: bool,
    /// The sending bridge speaks to the inverter.
    pub speaking: bool,
}

/// Why a summary was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SummaryError {
    /// Not 8 data bytes.
    Length,
    /// SOC above 100 %, SOH above 100 %.
    Soc,
    /// Lowest cell above the highest, or temperatures the other way round.
    Order,
    /// A condition field holds 3 (only 0, 1, 2 exist) or a reserved bit is set.
    Reserved,
    /// A value no TinyBMS can report (see [`Summary::from_frames`]): a
    /// current or limit past the largest cutoff, a cell past 5 V, a pack
    /// voltage its cells cannot make, a capacity past register 306's range.
    Range,
}

impl SummaryError {
    /// In words.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::Length => "not 8 data bytes",
            Self::Soc => "SOC or SOH above 100 %",
            Self::Order => "lowest cell or temperature above the highest",
            Self::Reserved => "a reserved bit or condition value",
            Self::Range => "a value no TinyBMS can report",
        }
    }
}

/// The largest current a TinyBMS's limits can name, 0.1 A: its largest
/// charge and discharge over-current cutoff (registers 317/318, 750 A with
/// the largest external sensor).
pub const LIMIT_MAX_DA: u16 = 7500;
/// The largest current a summary may report, 0.1 A: a third above the largest
/// cutoff (a peak before the cutoff acts).
pub const CURRENT_MAX_DA: i16 = 10_000;
/// The highest cell voltage a summary may report, mV (Rev D's highest
/// over-voltage cutoff is 4.5 V).
pub const CELL_MAX_MV: u16 = 5000;
/// Cells in series a TinyBMS manages (register 307: 4-16).
pub const CELLS: (u32, u32) = (4, 16);
/// The highest capacity register 306 holds (655.00 Ah), 0.1 Ah.
pub const CAPACITY_MAX_DAH: u16 = 6550;
/// Temperatures a summary may report, 0.1 °C.
pub const TEMP_RANGE_DC: (i16, i16) = (-550, 1500);

/// The 10 conditions carried (all of [`Conditions`]), 2 bits each.
fn conditions_bits(c: &Conditions) -> u32 {
    let all = c.all();
    let mut bits = 0u32;
    for (i, v) in all.iter().take(10).enumerate() {
        bits |= u32::from((*v).min(2)) << (2 * i);
    }
    bits
}

fn conditions_from(bits: u32) -> Option<Conditions> {
    let f = |i: u32| -> Option<u8> {
        let v = ((bits >> (2 * i)) & 3) as u8;
        (v <= 2).then_some(v)
    };
    Some(Conditions {
        high_voltage: f(0)?,
        low_voltage: f(1)?,
        high_temperature: f(2)?,
        low_temperature: f(3)?,
        high_temperature_charge: f(4)?,
        low_temperature_charge: f(5)?,
        high_discharge_current: f(6)?,
        high_charge_current: f(7)?,
        bms_internal: f(8)?,
        cell_imbalance: f(9)?,
    })
}

const FLAG_SPEAKING: u8 = 1;
const FLAG_FAULT: u8 = 2;
const FLAG_CHARGE_BLOCKED: u8 = 4;

fn put16(d: &mut [u8; 8], at: usize, v: u16) {
    let b = v.to_le_bytes();
    if let Some(s) = d.get_mut(at..at + 2) {
        s.copy_from_slice(&b);
    }
}

fn get16(d: &[u8; 8], at: usize) -> u16 {
    match d.get(at..at + 2) {
        Some(&[a, b]) => u16::from_le_bytes([a, b]),
        _ => 0,
    }
}

/// The identifier of frame `k` of `node`'s summary (`None` outside 1..=8, 0..=3).
pub const fn summary_id(node: u8, k: u8) -> Option<u16> {
    if node == 0 || node > MAX_NODES || k as usize >= SUMMARY_FRAMES {
        return None;
    }
    Some(SUMMARY_BASE_ID + (node as u16 - 1) * 4 + k as u16)
}

/// Node and frame index of a summary identifier.
pub const fn from_id(id: u16) -> Option<(u8, u8)> {
    if id < SUMMARY_BASE_ID || id > SUMMARY_LAST_ID {
        return None;
    }
    let off = id - SUMMARY_BASE_ID;
    Some(((off / 4) as u8 + 1, (off % 4) as u8))
}

impl Summary {
    /// The four frames of `node`'s summary with sequence number `seq` (0..=15);
    /// `None` for a node outside 1..=8.
    ///
    /// | frame | bytes 0-1 | 2-3 | 4-5 | 6 | 7 |
    /// |---|---|---|---|---|---|
    /// | 0 | voltage u16 0.01 V | current s16 0.1 A | SOC u16 0.01 % | SOH u8 % | seq (bits 0-3), flags (4-7) |
    /// | 1 | min cell u16 mV | max cell u16 mV | min temperature s16 0.1 °C | data age u8 0.1 s | seq |
    /// | 2 | max temperature s16 0.1 °C | capacity u16 0.1 Ah | discharge voltage u16 0.1 V | conditions bits 0-7 | seq |
    /// | 3 | CVL u16 0.1 V | CCL u16 0.1 A | DCL u16 0.1 A | conditions bits 8-15 | seq, conditions bits 16-19 (4-7) |
    pub fn frames(&self, node: u8, seq: u8) -> Option<[CanFrame; SUMMARY_FRAMES]> {
        let seq = seq & SEQ_MASK;
        let mut out = [CanFrame {
            id: 0,
            len: 8,
            data: [0; 8],
        }; SUMMARY_FRAMES];
        let cond = conditions_bits(&self.conditions);
        let mut flags = 0;
        for (on, flag) in [
            (self.speaking, FLAG_SPEAKING),
            (self.fault, FLAG_FAULT),
            (self.charge_blocked, FLAG_CHARGE_BLOCKED),
        ] {
            if on {
                flags |= flag;
            }
        }
        for (k, f) in out.iter_mut().enumerate() {
            f.id = summary_id(node, k as u8)?;
            let d = &mut f.data;
            match k {
                0 => {
                    put16(d, 0, self.voltage_cv);
                    put16(d, 2, self.current_da as u16);
                    put16(d, 4, self.soc_cpct);
                    d[6] = self.soh_pct;
                    d[7] = seq | (flags << 4);
                }
                1 => {
                    put16(d, 0, self.min_cell_mv);
                    put16(d, 2, self.max_cell_mv);
                    put16(d, 4, self.min_temp_dc as u16);
                    d[6] = self.age_ds;
                    d[7] = seq;
                }
                2 => {
                    put16(d, 0, self.max_temp_dc as u16);
                    put16(d, 2, self.capacity_dah);
                    put16(d, 4, self.limits.discharge_dv);
                    d[6] = cond as u8;
                    d[7] = seq;
                }
                _ => {
                    put16(d, 0, self.limits.cvl_dv);
                    put16(d, 2, self.limits.ccl_da);
                    put16(d, 4, self.limits.dcl_da);
                    d[6] = (cond >> 8) as u8;
                    d[7] = seq | ((((cond >> 16) & 0x0F) as u8) << 4);
                }
            }
        }
        Some(out)
    }

    /// A summary from its four frames' data, in frame order.
    pub fn from_frames(d: &[[u8; 8]; SUMMARY_FRAMES]) -> Result<Self, SummaryError> {
        let [a, b, c, e] = d;
        let flags = a[7] >> 4;
        if flags & !(FLAG_SPEAKING | FLAG_FAULT | FLAG_CHARGE_BLOCKED) != 0
            || b[7] >> 4 != 0
            || c[7] >> 4 != 0
        {
            return Err(SummaryError::Reserved);
        }
        let cond = u32::from(c[6]) | u32::from(e[6]) << 8 | u32::from(e[7] >> 4) << 16;
        let conditions = conditions_from(cond).ok_or(SummaryError::Reserved)?;
        let s = Self {
            voltage_cv: get16(a, 0),
            current_da: get16(a, 2) as i16,
            soc_cpct: get16(a, 4),
            soh_pct: a[6],
            min_cell_mv: get16(b, 0),
            max_cell_mv: get16(b, 2),
            min_temp_dc: get16(b, 4) as i16,
            age_ds: b[6],
            max_temp_dc: get16(c, 0) as i16,
            capacity_dah: get16(c, 2),
            limits: Limits {
                cvl_dv: get16(e, 0),
                ccl_da: get16(e, 2),
                dcl_da: get16(e, 4),
                discharge_dv: get16(c, 4),
            },
            conditions,
            fault: flags & FLAG_FAULT != 0,
            charge_blocked: flags & FLAG_CHARGE_BLOCKED != 0,
            speaking: flags & FLAG_SPEAKING != 0,
        };
        if s.soc_cpct > 10_000 || s.soh_pct > 100 {
            return Err(SummaryError::Soc);
        }
        if s.min_cell_mv > s.max_cell_mv || s.min_temp_dc > s.max_temp_dc {
            return Err(SummaryError::Order);
        }
        if !s.plausible() {
            return Err(SummaryError::Range);
        }
        Ok(s)
    }

    /// Every field within what a TinyBMS can report (the constants above),
    /// and a pack voltage that 4-16 cells between the lowest and the highest
    /// can make (±1 V for the measurements' own errors).
    pub fn plausible(&self) -> bool {
        let l = &self.limits;
        let pack_mv = u32::from(self.voltage_cv) * 10;
        let lo_mv = CELLS.0 * u32::from(self.min_cell_mv);
        let hi_mv = CELLS.1 * u32::from(self.max_cell_mv);
        let cells_max_dv = (CELLS.1 * u32::from(CELL_MAX_MV) / 100) as u16;
        self.current_da.unsigned_abs() <= CURRENT_MAX_DA.unsigned_abs()
            && l.ccl_da <= LIMIT_MAX_DA
            && l.dcl_da <= LIMIT_MAX_DA
            && l.cvl_dv <= cells_max_dv
            && l.discharge_dv <= cells_max_dv
            && self.max_cell_mv <= CELL_MAX_MV
            && pack_mv + 1000 >= lo_mv
            && pack_mv <= hi_mv + 1000
            && self.capacity_dah <= CAPACITY_MAX_DAH
            && self.min_temp_dc >= TEMP_RANGE_DC.0
            && self.max_temp_dc <= TEMP_RANGE_DC.1
    }

    /// This bridge's own summary: its pack's state (taken `age_us` ago), its
    /// limits and conditions, its capacity (register 306, 0.01 Ah).
    pub fn own(
        p: &PackState,
        age_us: Instant,
        limits: &Limits,
        conditions: &Conditions,
        capacity_cah: u16,
        speaking: bool,
    ) -> Self {
        let round = |x: f32, k: f32| -> f32 {
            let v = x * k;
            if v >= 0.0 {
                v + 0.5
            } else {
                v - 0.5
            }
        };
        let i16_of = |x: f32, k: f32| round(x, k).clamp(-32768.0, 32767.0) as i16;
        let (lo_t, hi_t) = (i16_of(p.min_temp_c, 10.0), i16_of(p.max_temp_c, 10.0));
        let c = *conditions;
        Self {
            voltage_cv: round(p.pack_v.max(0.0), 100.0).min(65535.0) as u16,
            current_da: i16_of(p.current_a, 10.0),
            soc_cpct: round(p.soc_pct.clamp(0.0, 100.0), 100.0).min(10_000.0) as u16,
            soh_pct: round(p.soh_pct.clamp(0.0, 100.0), 1.0).min(100.0) as u8,
            min_cell_mv: p.min_cell_mv.min(p.max_cell_mv),
            max_cell_mv: p.max_cell_mv.max(p.min_cell_mv),
            min_temp_dc: lo_t.min(hi_t),
            max_temp_dc: hi_t.max(lo_t),
            age_ds: (age_us / (100 * crate::MS)).min(255) as u8,
            capacity_dah: capacity_cah / 10,
            limits: *limits,
            conditions: c,
            fault: p.fault,
            charge_blocked: p.charge_blocked,
            speaking,
        }
    }
}
