//! A day of the pack: what it took and gave, how low and high its cells went
//! and when, how its charge ended, how long each charge stage lasted — one
//! [`DayRecord`] of [`DAY_BYTES`] bytes a day, filled by the [`DayBook`].
//!
//! **A day is 24 h of the bridge's running time**, counted from the start of
//! its history: time the bridge was switched off does not count (it has no
//! clock of its own; the date, when the station knows it, is written at the
//! day's end). A restart loses nothing saved: the station saves a
//! [`DayBook::checkpoint`] every hour, and [`DayBook::resume`] goes on with
//! its counters and its seconds covered — the day is then flagged "cut by a
//! restart" (what happened while the bridge was off, and since the last
//! checkpoint, is not in it).
//!
//! The counters follow [`crate::energy`]'s rule: only an interval between
//! two good snapshots at most [`MAX_GAP_US`] apart counts, at the value of its
//! first snapshot (a flagged snapshot counts nothing on either side, a longer
//! gap counts nothing). Charge is counted in mA × µs, energy in mW × µs, in
//! whole units plus the rest (exact integers; the snapshot's f32 values
//! rounded to the mA and the mW).
//!
//! ## The encoding (little-endian, [`DAY_BYTES`] = 56 bytes)
//!
//! | bytes | what |
//! | --- | --- |
//! | 0 | format version ([`DAY_VERSION`]) |
//! | 1 | bit 0 cut by a restart, bit 1 partial (a checkpoint), bit 2 reserved (0), bits 3-7 the cell that ran ahead at the top of charge (1-based, 0 = none) |
//! | 2-5 | day number (u32, days of running since the history began) |
//! | 6-9 | date at the day's end, unix seconds (u32, 0 = unknown) |
//! | 10-12 | seconds covered (u24, at most 86 400) |
//! | 13-15, 16-18 | energy in, out, Wh (u24 each) |
//! | 19-21, 22-24 | charge in, out, 0.01 Ah (u24 each) |
//! | 25-26, 27-29 | lowest cell, mV; when, s into the day (u24) |
//! | 30-31, 32-34 | highest cell, mV; when |
//! | 35-36 | spread at the top of charge, mV |
//! | 37-46 | minutes in bulk, absorption, balance held, float (and the step into it), other (idle, SOC ceiling, no charge control), u16 each |
//! | 47-48, 49-50, 51-52 | the TinyBMS statistics at the day's end: charging count (cycles), full charge count, max cell difference (0.1 mV) |
//! | 53-54 | the day's capacity estimate, 0.01 Ah (0 = none) |
//! | 55 | its uncertainty, 0.1 % (saturates at 25.5 %) |
//!
//! Values beyond their field saturate when encoded (a day of more than
//! 16 777 kWh, say); [`DayRecord::decode`] refuses a record that cannot be
//! one ([`DayError`]).

use protocol_core::views::{LiveSnapshot, Statistics};

use super::capacity::Estimate;
use crate::inverter::control::PackSettings;
use crate::inverter::finish::Stage;
use crate::{Instant, SECOND};

/// The encoded record's size, bytes.
pub const DAY_BYTES: usize = 56;
/// The format version (byte 0).
pub const DAY_VERSION: u8 = 1;
/// A day, s.
pub const DAY_S: u32 = 86_400;
/// A day of running, µs.
pub const DAY_US: Instant = DAY_S as Instant * SECOND;
/// A gap between two snapshots longer than this counts nothing, µs.
pub const MAX_GAP_US: Instant = crate::energy::MAX_GAP_US;
/// A pack current above this charges (the top-of-charge spread), A.
pub const CHARGING_A: f32 = 0.5;

const CUT: u8 = 1;
const PARTIAL: u8 = 2;
const RESERVED: u8 = 4;
const U24: u32 = 0xFF_FFFF;
/// mW·µs in one mWh, mA·µs in 0.01 Ah.
const MW_US_PER_MWH: u64 = 3_600_000_000;
const MA_US_PER_CAH: u64 = 36_000_000_000;

/// Minutes in each charge stage.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StageMinutes {
    /// Bulk (towards the absorption target).
    pub bulk: u16,
    /// Absorption.
    pub absorption: u16,
    /// Absorption held for the balance.
    pub balance_held: u16,
    /// Float and the step into it.
    pub float: u16,
    /// Anything else: the SOC ceiling, no charge control, gaps.
    pub other: u16,
}

impl StageMinutes {
    fn as_array(self) -> [u16; 5] {
        [
            self.bulk,
            self.absorption,
            self.balance_held,
            self.float,
            self.other,
        ]
    }
    fn from_array(a: [u16; 5]) -> Self {
        let [bulk, absorption, balance_held, float, other] = a;
        Self {
            bulk,
            absorption,
            balance_held,
            float,
            other,
        }
    }
}

/// One day of the pack. See the module documentation for its bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DayRecord {
    /// Days of running since the history began (0 = the first).
    pub day: u32,
    /// The date at the day's end, unix seconds; 0 = unknown.
    pub date_unix_s: u32,
    /// The day was cut by a restart (resumed from a checkpoint).
    pub cut_by_restart: bool,
    /// The day so far (a checkpoint), not a closed day.
    pub partial: bool,
    /// Running seconds the day covers (86 400 for a closed day).
    pub covered_s: u32,
    /// Energy into the pack, Wh.
    pub energy_in_wh: u32,
    /// Energy out of the pack, Wh.
    pub energy_out_wh: u32,
    /// Charge into the pack, 0.01 Ah.
    pub charge_in_cah: u32,
    /// Charge out of the pack, 0.01 Ah.
    pub charge_out_cah: u32,
    /// The lowest cell of the day, mV (0 with no snapshot).
    pub lowest_cell_mv: u16,
    /// When, s into the day.
    pub lowest_at_s: u32,
    /// The highest cell of the day, mV (0 with no snapshot).
    pub highest_cell_mv: u16,
    /// When, s into the day.
    pub highest_at_s: u32,
    /// Highest less lowest cell when the highest cell was at its highest of
    /// the day while charging, mV.
    pub top_spread_mv: u16,
    /// The cell that ran ahead then, 1-based (0 = no charge seen).
    pub top_cell: u8,
    /// Minutes in each charge stage.
    pub stages: StageMinutes,
    /// Statistics at the day's end: charging count (cycles, register 111).
    pub cycles: u16,
    /// Full charge count (112).
    pub full_charges: u16,
    /// Max cell difference (104), 0.1 mV.
    pub max_cell_difference_raw: u16,
    /// The day's capacity estimate, 0.01 Ah; 0 = none qualified.
    pub capacity_cah: u16,
    /// Its uncertainty, 0.1 %.
    pub capacity_uncertainty_permille: u8,
}

/// Why bytes are no [`DayRecord`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DayError {
    /// Not [`DAY_BYTES`] bytes.
    WrongLength,
    /// Byte 0 is not [`DAY_VERSION`].
    UnknownVersion,
    /// The reserved flag is set.
    UnknownFlags,
    /// The cell that ran ahead is beyond 16.
    CellOutOfRange,
    /// More than 86 400 s covered.
    CoveredOverDay,
    /// A time of the lowest or highest cell after the seconds covered.
    WhenOutOfDay,
    /// The lowest cell above the highest.
    LowestAboveHighest,
    /// The spread at the top above the highest cell.
    SpreadAboveHighest,
    /// More minutes in the stages than the seconds covered hold.
    StagesOverDay,
    /// An uncertainty without a capacity.
    UncertaintyWithoutCapacity,
}

impl DayError {
    /// In words, for the log.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::WrongLength => "wrong length",
            Self::UnknownVersion => "unknown version",
            Self::UnknownFlags => "unknown flags",
            Self::CellOutOfRange => "cell out of range",
            Self::CoveredOverDay => "more than a day covered",
            Self::WhenOutOfDay => "a time outside the day",
            Self::LowestAboveHighest => "lowest cell above the highest",
            Self::SpreadAboveHighest => "spread above the highest cell",
            Self::StagesOverDay => "hours in stages over the day",
            Self::UncertaintyWithoutCapacity => "uncertainty without a capacity",
        }
    }
}

fn put(out: &mut [u8; DAY_BYTES], at: usize, bytes: &[u8]) {
    if let Some(dst) = out.get_mut(at..at + bytes.len()) {
        dst.copy_from_slice(bytes);
    }
}

fn u24(v: u32) -> [u8; 3] {
    let [a, b, c, _] = v.min(U24).to_le_bytes();
    [a, b, c]
}

/// `N` bytes of `b` at `at` (zeros when short: the length is checked first).
fn take<const N: usize>(b: &[u8], at: usize) -> [u8; N] {
    let mut out = [0u8; N];
    if let Some(src) = b.get(at..at + N) {
        out.copy_from_slice(src);
    }
    out
}

fn get_u24(b: &[u8], at: usize) -> u32 {
    let [x, y, z] = take::<3>(b, at);
    u32::from_le_bytes([x, y, z, 0])
}

fn get_u16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes(take(b, at))
}

impl DayRecord {
    /// Whether the day was whole: closed, never cut by a restart.
    pub fn is_whole(&self) -> bool {
        !self.cut_by_restart && !self.partial
    }

    /// Its bytes (see the module documentation).
    pub fn encode(&self) -> [u8; DAY_BYTES] {
        let mut o = [0u8; DAY_BYTES];
        let flags = (u8::from(self.cut_by_restart) * CUT)
            | (u8::from(self.partial) * PARTIAL)
            | (self.top_cell.min(31) << 3);
        put(&mut o, 0, &[DAY_VERSION, flags]);
        put(&mut o, 2, &self.day.to_le_bytes());
        put(&mut o, 6, &self.date_unix_s.to_le_bytes());
        put(&mut o, 10, &u24(self.covered_s));
        put(&mut o, 13, &u24(self.energy_in_wh));
        put(&mut o, 16, &u24(self.energy_out_wh));
        put(&mut o, 19, &u24(self.charge_in_cah));
        put(&mut o, 22, &u24(self.charge_out_cah));
        put(&mut o, 25, &self.lowest_cell_mv.to_le_bytes());
        put(&mut o, 27, &u24(self.lowest_at_s));
        put(&mut o, 30, &self.highest_cell_mv.to_le_bytes());
        put(&mut o, 32, &u24(self.highest_at_s));
        put(&mut o, 35, &self.top_spread_mv.to_le_bytes());
        for (i, m) in self.stages.as_array().iter().enumerate() {
            put(&mut o, 37 + 2 * i, &m.to_le_bytes());
        }
        put(&mut o, 47, &self.cycles.to_le_bytes());
        put(&mut o, 49, &self.full_charges.to_le_bytes());
        put(&mut o, 51, &self.max_cell_difference_raw.to_le_bytes());
        put(&mut o, 53, &self.capacity_cah.to_le_bytes());
        put(&mut o, 55, &[self.capacity_uncertainty_permille]);
        o
    }

    /// A record from its bytes, checked.
    pub fn decode(b: &[u8]) -> Result<DayRecord, DayError> {
        if b.len() != DAY_BYTES {
            return Err(DayError::WrongLength);
        }
        let [version, flags] = take::<2>(b, 0);
        if version != DAY_VERSION {
            return Err(DayError::UnknownVersion);
        }
        if flags & RESERVED != 0 {
            return Err(DayError::UnknownFlags);
        }
        let mut stages = [0u16; 5];
        for (i, m) in stages.iter_mut().enumerate() {
            *m = get_u16(b, 37 + 2 * i);
        }
        let r = DayRecord {
            day: u32::from_le_bytes(take(b, 2)),
            date_unix_s: u32::from_le_bytes(take(b, 6)),
            cut_by_restart: flags & CUT != 0,
            partial: flags & PARTIAL != 0,
            covered_s: get_u24(b, 10),
            energy_in_wh: get_u24(b, 13),
            energy_out_wh: get_u24(b, 16),
            charge_in_cah: get_u24(b, 19),
            charge_out_cah: get_u24(b, 22),
            lowest_cell_mv: get_u16(b, 25),
            lowest_at_s: get_u24(b, 27),
            highest_cell_mv: get_u16(b, 30),
            highest_at_s: get_u24(b, 32),
            top_spread_mv: get_u16(b, 35),
            top_cell: flags >> 3,
            stages: StageMinutes::from_array(stages),
            cycles: get_u16(b, 47),
            full_charges: get_u16(b, 49),
            max_cell_difference_raw: get_u16(b, 51),
            capacity_cah: get_u16(b, 53),
            capacity_uncertainty_permille: take::<1>(b, 55)[0],
        };
        r.check()?;
        Ok(r)
    }

    /// Whether the values can be a day's (what [`DayRecord::decode`] asks).
    pub fn check(&self) -> Result<(), DayError> {
        let minutes: u32 = self.stages.as_array().iter().map(|&m| u32::from(m)).sum();
        if usize::from(self.top_cell) > protocol_core::registers::MAX_CELLS {
            Err(DayError::CellOutOfRange)
        } else if self.covered_s > DAY_S {
            Err(DayError::CoveredOverDay)
        } else if self.lowest_at_s > self.covered_s || self.highest_at_s > self.covered_s {
            Err(DayError::WhenOutOfDay)
        } else if self.lowest_cell_mv > self.highest_cell_mv {
            Err(DayError::LowestAboveHighest)
        } else if self.top_spread_mv > self.highest_cell_mv {
            Err(DayError::SpreadAboveHighest)
        } else if minutes * 60 > self.covered_s {
            Err(DayError::StagesOverDay)
        } else if self.capacity_cah == 0 && self.capacity_uncertainty_permille != 0 {
            Err(DayError::UncertaintyWithoutCapacity)
        } else {
            Ok(())
        }
    }
}

/// A signed flow (mA, mW) integrated both ways: whole units and the rest.
#[derive(Debug, Clone, Copy, Default)]
struct Flow {
    /// Whole units in, out.
    total: [u64; 2],
    /// What did not make a whole unit yet, value·µs.
    rest: [u64; 2],
    /// The previous good snapshot's time and value.
    last: Option<(Instant, i64)>,
}

impl Flow {
    /// A snapshot at `at` with `value` (`None`: flagged or nonsense).
    fn on(&mut self, at: Instant, value: Option<i64>, per_unit: u64) {
        let Some(v) = value else {
            self.last = None;
            return;
        };
        if let Some((t0, v0)) = self.last {
            let dt = at.saturating_sub(t0);
            if dt > 0 && dt <= MAX_GAP_US {
                let i = usize::from(v0 < 0);
                if let (Some(total), Some(rest)) = (self.total.get_mut(i), self.rest.get_mut(i)) {
                    let sum = rest.saturating_add(v0.unsigned_abs().saturating_mul(dt));
                    *total = total.saturating_add(sum / per_unit);
                    *rest = sum % per_unit;
                }
            }
        }
        self.last = Some((at, v));
    }

    /// A new day: totals at 0, the last snapshot kept (the interval across
    /// the day's end counts in the new day).
    fn restart(&mut self) {
        self.total = [0; 2];
        self.rest = [0; 2];
    }
}

/// `x` (a finite f32, |x| < 1e12) as the nearest integer.
fn nearest(x: f32) -> Option<i64> {
    let away = if x < 0.0 { x - 0.5 } else { x + 0.5 };
    (x.is_finite() && x.abs() < 1e12).then_some(away as i64)
}

/// The stage's slot in [`StageMinutes`].
fn slot(stage: Option<&Stage>) -> usize {
    match stage {
        Some(Stage::Bulk { .. }) => 0,
        Some(Stage::Absorption) => 1,
        Some(Stage::BalanceHeld { .. }) => 2,
        Some(Stage::StepDown { .. } | Stage::Float) => 3,
        Some(Stage::Ceiling { .. }) | None => 4,
    }
}

/// The accumulator of the day under way. See the module documentation.
#[derive(Debug, Clone)]
pub struct DayBook {
    day: u32,
    /// When this stretch of running began.
    began: Instant,
    /// Running time of the day before it (a checkpoint's), µs.
    before_us: Instant,
    cut: bool,
    energy: Flow,
    charge: Flow,
    /// A checkpoint's counters: mWh in, out; 0.01 Ah in, out.
    base_mwh: [u64; 2],
    base_cah: [u64; 2],
    /// (mV, s into the day).
    low: Option<(u16, u32)>,
    high: Option<(u16, u32)>,
    /// The highest cell while charging, the spread and the cell then.
    top: Option<(u16, u16, u8)>,
    stage_us: [u64; 5],
    stage_base_min: [u16; 5],
    last_stage: Option<(Instant, usize)>,
    /// Charging count, full charge count, max cell difference.
    stats: (u16, u16, u16),
    capacity: Option<Estimate>,
}

impl DayBook {
    /// The first day of a history, beginning at `now`.
    pub fn new(now: Instant) -> Self {
        Self {
            day: 0,
            began: now,
            before_us: 0,
            cut: false,
            energy: Flow::default(),
            charge: Flow::default(),
            base_mwh: [0; 2],
            base_cah: [0; 2],
            low: None,
            high: None,
            top: None,
            stage_us: [0; 5],
            stage_base_min: [0; 5],
            last_stage: None,
            stats: (0, 0, 0),
            capacity: None,
        }
    }

    /// The day of `rec` (a checkpoint) going on from `now` after a restart:
    /// its counters and its seconds covered, flagged cut by a restart.
    pub fn resume(rec: &DayRecord, now: Instant) -> Self {
        let mut b = Self::new(now);
        b.day = rec.day;
        b.before_us = Instant::from(rec.covered_s.min(DAY_S)) * SECOND;
        b.cut = true;
        b.base_mwh = [
            u64::from(rec.energy_in_wh) * 1000,
            u64::from(rec.energy_out_wh) * 1000,
        ];
        b.base_cah = [u64::from(rec.charge_in_cah), u64::from(rec.charge_out_cah)];
        if rec.highest_cell_mv != 0 {
            b.low = Some((rec.lowest_cell_mv, rec.lowest_at_s));
            b.high = Some((rec.highest_cell_mv, rec.highest_at_s));
        }
        if rec.top_cell != 0 {
            b.top = Some((rec.highest_cell_mv, rec.top_spread_mv, rec.top_cell));
        }
        b.stage_base_min = rec.stages.as_array();
        b.stats = (rec.cycles, rec.full_charges, rec.max_cell_difference_raw);
        if rec.capacity_cah != 0 {
            b.capacity = Some(Estimate {
                cah: u32::from(rec.capacity_cah),
                uncertainty_permille: u16::from(rec.capacity_uncertainty_permille),
                runs: 0,
            });
        }
        b
    }

    /// The day's number.
    pub fn day(&self) -> u32 {
        self.day
    }

    /// Running time of the day at `now`, µs.
    fn covered_us(&self, now: Instant) -> Instant {
        self.before_us
            .saturating_add(now.saturating_sub(self.began))
    }

    /// Seconds into the day at `now` (at most a day).
    fn when(&self, now: Instant) -> u32 {
        (self.covered_us(now) / SECOND).min(Instant::from(DAY_S)) as u32
    }

    /// A snapshot decoded at `at` (`valid` false for a flagged one), with the
    /// BMS's settings and charge control's stage when known.
    pub fn on_snapshot(
        &mut self,
        at: Instant,
        s: &LiveSnapshot,
        valid: bool,
        _settings: Option<&PackSettings>,
        stage: Option<&Stage>,
    ) {
        let power = nearest(s.pack_voltage_v * s.pack_current_a * 1000.0).filter(|_| valid);
        let current = nearest(s.pack_current_a * 1000.0).filter(|_| valid);
        self.energy.on(at, power, MW_US_PER_MWH);
        self.charge.on(at, current, MA_US_PER_CAH);
        let here = slot(stage);
        if let Some((t0, was)) = self.last_stage {
            let dt = at.saturating_sub(t0);
            if dt <= MAX_GAP_US {
                if let Some(us) = self.stage_us.get_mut(was) {
                    *us = us.saturating_add(dt);
                }
            }
        }
        self.last_stage = valid.then_some((at, here));
        if !valid || s.min_cell_mv > s.max_cell_mv {
            return;
        }
        let when = self.when(at);
        if self.low.is_none_or(|(mv, _)| s.min_cell_mv < mv) {
            self.low = Some((s.min_cell_mv, when));
        }
        if self.high.is_none_or(|(mv, _)| s.max_cell_mv > mv) {
            self.high = Some((s.max_cell_mv, when));
        }
        if s.pack_current_a > CHARGING_A && self.top.is_none_or(|(mv, _, _)| s.max_cell_mv > mv) {
            let cell = s.cells.max().map_or(0, |(i, _)| (i + 1).min(31) as u8);
            self.top = Some((s.max_cell_mv, s.max_cell_mv - s.min_cell_mv, cell));
        }
    }

    /// The TinyBMS's statistics (registers 100-117), as last read.
    pub fn on_statistics(&mut self, st: &Statistics) {
        self.stats = (
            st.charging_count,
            st.full_charge_count,
            st.max_cell_difference_raw,
        );
    }

    /// A capacity estimate that qualified today (the last one is kept).
    pub fn on_estimate(&mut self, e: &Estimate) {
        self.capacity = Some(*e);
    }

    /// The closed day once 24 h of running have passed since it began (with
    /// `date_unix_s`, when the station knows the time); the next day then
    /// begins at the 24 h mark. What arrives between the mark and the poll
    /// counts in the closing day: poll at least every second.
    pub fn poll(&mut self, now: Instant, date_unix_s: Option<u64>) -> Option<DayRecord> {
        if self.covered_us(now) < DAY_US {
            return None;
        }
        let mut rec = self.record(now);
        rec.date_unix_s = date_unix_s.and_then(|d| u32::try_from(d).ok()).unwrap_or(0);
        let mark = self
            .began
            .saturating_add(DAY_US.saturating_sub(self.before_us));
        let (energy, charge, last_stage, stats) =
            (self.energy, self.charge, self.last_stage, self.stats);
        *self = Self::new(mark.min(now));
        self.day = rec.day.saturating_add(1);
        self.energy = energy;
        self.charge = charge;
        self.energy.restart();
        self.charge.restart();
        self.last_stage = last_stage;
        self.stats = stats;
        Some(rec)
    }

    /// The day so far, flagged partial: what the station saves every hour.
    pub fn checkpoint(&self, now: Instant) -> DayRecord {
        DayRecord {
            partial: true,
            ..self.record(now)
        }
    }

    /// The record of the day at `now`.
    fn record(&self, now: Instant) -> DayRecord {
        let covered_s = self.when(now);
        let [wh_in, wh_out] = [0, 1].map(|i| {
            let mwh = self.base_mwh.get(i).copied().unwrap_or(0)
                + self.energy.total.get(i).copied().unwrap_or(0);
            u32::try_from(mwh / 1000).unwrap_or(u32::MAX)
        });
        let [cah_in, cah_out] = [0, 1].map(|i| {
            let cah = self.base_cah.get(i).copied().unwrap_or(0)
                + self.charge.total.get(i).copied().unwrap_or(0);
            u32::try_from(cah).unwrap_or(u32::MAX)
        });
        // Minutes per stage, at most the minutes covered (the time between
        // the day's end and the poll is trimmed from the longest).
        let mut minutes = [0u16; 5];
        for ((m, us), base) in minutes
            .iter_mut()
            .zip(&self.stage_us)
            .zip(&self.stage_base_min)
        {
            let new = u16::try_from(us / (60 * SECOND)).unwrap_or(u16::MAX);
            *m = base.saturating_add(new);
        }
        let limit = (covered_s / 60) as u16;
        loop {
            let sum: u32 = minutes.iter().map(|&m| u32::from(m)).sum();
            let Some(longest) = minutes.iter_mut().max() else {
                break;
            };
            if sum <= u32::from(limit) || *longest == 0 {
                break;
            }
            *longest -= (sum - u32::from(limit)).min(u32::from(*longest)) as u16;
        }
        let (low_mv, low_at) = self.low.unwrap_or((0, 0));
        let (high_mv, high_at) = self.high.unwrap_or((0, 0));
        let (_, spread, cell) = self.top.unwrap_or((0, 0, 0));
        let (cah, unc) = self.capacity.map_or((0, 0), |e| {
            (
                u16::try_from(e.cah).unwrap_or(u16::MAX),
                u8::try_from(e.uncertainty_permille).unwrap_or(u8::MAX),
            )
        });
        DayRecord {
            day: self.day,
            date_unix_s: 0,
            cut_by_restart: self.cut,
            partial: false,
            covered_s,
            energy_in_wh: wh_in,
            energy_out_wh: wh_out,
            charge_in_cah: cah_in,
            charge_out_cah: cah_out,
            lowest_cell_mv: low_mv,
            lowest_at_s: low_at.min(covered_s),
            highest_cell_mv: high_mv,
            highest_at_s: high_at.min(covered_s),
            top_spread_mv: spread.min(high_mv),
            top_cell: cell,
            stages: StageMinutes::from_array(minutes),
            cycles: self.stats.0,
            full_charges: self.stats.1,
            max_cell_difference_raw: self.stats.2,
            capacity_cah: if unc != 0 || cah != 0 { cah.max(1) } else { 0 },
            capacity_uncertainty_permille: unc,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::history::capacity::tests::snap;
    use protocol_core::events::OnlineStatus;

    const S: Instant = SECOND;
    const CH: OnlineStatus = OnlineStatus::Charging;

    fn at_volts(v: f32, a: f32) -> LiveSnapshot {
        LiveSnapshot {
            pack_voltage_v: v,
            pack_current_a: a,
            ..snap(3300, 3310, a, CH)
        }
    }

    #[test]
    fn energy_and_charge_against_a_hand_computation() {
        let mut b = DayBook::new(0);
        // 50 V × 20 A for an hour: 1000 Wh, 20 Ah in; then 48 V × −10 A for
        // half an hour: 240 Wh, 5 Ah out (a snapshot a second; the last
        // snapshot of each part counts at its own value for the next second).
        for k in 0..3600 {
            b.on_snapshot(k * S, &at_volts(50.0, 20.0), true, None, None);
        }
        for k in 3600..=5400 {
            b.on_snapshot(k * S, &at_volts(48.0, -10.0), true, None, None);
        }
        let r = b.checkpoint(5400 * S);
        assert_eq!((r.energy_in_wh, r.energy_out_wh), (1000, 240));
        assert_eq!((r.charge_in_cah, r.charge_out_cah), (2000, 500));
        assert_eq!(r.covered_s, 5400);
        assert!(r.partial && !r.cut_by_restart);
        // 1.5 h: 90 minutes, all "other" (no charge control).
        assert_eq!(r.stages.other, 90);
    }

    #[test]
    fn the_gap_rule_counts_nothing_across_a_gap_or_a_flagged_snapshot() {
        let mut b = DayBook::new(0);
        b.on_snapshot(0, &at_volts(50.0, 36.0), true, None, None);
        b.on_snapshot(10 * S, &at_volts(50.0, 36.0), true, None, None);
        // 10 s at 36 A = 0.1 Ah counted; 11 s later nothing.
        b.on_snapshot(21 * S, &at_volts(50.0, 36.0), true, None, None);
        assert_eq!(b.checkpoint(21 * S).charge_in_cah, 10);
        // A flagged one: nothing on either side of it.
        b.on_snapshot(22 * S, &at_volts(50.0, 36.0), false, None, None);
        b.on_snapshot(23 * S, &at_volts(50.0, 36.0), true, None, None);
        b.on_snapshot(33 * S, &at_volts(50.0, 36.0), true, None, None);
        let r = b.checkpoint(33 * S);
        assert_eq!(r.charge_in_cah, 20);
        assert_eq!(r.energy_in_wh, 10, "2 × 10 s × 1800 W");
    }

    #[test]
    fn lowest_and_highest_with_when_and_the_spread_at_the_top() {
        let mut b = DayBook::new(1000 * S);
        let stage = Stage::Bulk { full_due: false };
        b.on_snapshot(1060 * S, &snap(3300, 3320, -5.0, CH), true, None, None);
        b.on_snapshot(1070 * S, &snap(3000, 3310, -5.0, CH), true, None, None);
        // Charging: the top of the charge at 3560 mV (cell 6 runs ahead).
        b.on_snapshot(
            1080 * S,
            &snap(3400, 3560, 10.0, CH),
            true,
            None,
            Some(&stage),
        );
        b.on_snapshot(
            1090 * S,
            &snap(3500, 3540, 10.0, CH),
            true,
            None,
            Some(&stage),
        );
        // Higher but discharging: the highest, not the top of a charge.
        b.on_snapshot(1100 * S, &snap(3500, 3570, -1.0, CH), true, None, None);
        // Flagged: not a low.
        b.on_snapshot(1101 * S, &snap(2000, 3000, -1.0, CH), false, None, None);
        let r = b.checkpoint(1200 * S);
        assert_eq!((r.lowest_cell_mv, r.lowest_at_s), (3000, 70));
        assert_eq!((r.highest_cell_mv, r.highest_at_s), (3570, 100));
        assert_eq!((r.top_spread_mv, r.top_cell), (160, 6));
        // Bulk from 80 s to 100 s: no whole minute.
        assert_eq!(r.stages.bulk, 0);
        assert_eq!(DayRecord::decode(&r.encode()), Ok(r));
    }

    #[test]
    fn the_day_closes_after_24_hours_of_running_and_a_restart_goes_on() {
        let t0 = 5 * S;
        let mut b = DayBook::new(t0);
        let float = Stage::Float;
        let mut t = t0;
        while t < t0 + 20 * 3600 * S {
            b.on_snapshot(t, &at_volts(53.0, 1.0), true, None, Some(&float));
            t += 5 * S;
        }
        assert_eq!(b.poll(t, None), None);
        // 20 h covered, then the bridge is off for 3 days; it resumes.
        let cp = b.checkpoint(t);
        assert_eq!(cp.covered_s, 20 * 3600);
        let bytes = cp.encode();
        let off = t + 3 * 86_400 * S;
        let mut b = DayBook::resume(&DayRecord::decode(&bytes).unwrap(), off);
        let mut t = off;
        while t < off + 4 * 3600 * S - S {
            b.on_snapshot(t, &at_volts(53.0, 1.0), true, None, Some(&float));
            assert_eq!(b.poll(t, Some(1_800_000_000)), None, "{t}");
            t += S;
        }
        let r = b.poll(off + 4 * 3600 * S, Some(1_800_000_000)).unwrap();
        assert_eq!(
            (r.day, r.covered_s, r.date_unix_s),
            (0, 86_400, 1_800_000_000)
        );
        assert!(r.cut_by_restart && !r.partial && !r.is_whole());
        // 1 A for a day less the seconds between snapshots lost at the
        // restart: 24 Ah in, nearly.
        assert!(
            (2390..=2400).contains(&r.charge_in_cah),
            "{}",
            r.charge_in_cah
        );
        assert!((1430..=1440).contains(&r.stages.float), "{:?}", r.stages);
        assert_eq!(DayRecord::decode(&r.encode()), Ok(r));
        // The next day is whole, day 1, and closes 24 h of running later.
        assert_eq!(b.day(), 1);
        let next = off + 4 * 3600 * S + DAY_US;
        assert_eq!(b.poll(next - S, None), None);
        let r = b.poll(next, None).unwrap();
        assert!(r.is_whole());
        assert_eq!((r.day, r.date_unix_s, r.charge_in_cah), (1, 0, 0));
    }

    fn extreme() -> DayRecord {
        DayRecord {
            day: u32::MAX,
            date_unix_s: u32::MAX,
            cut_by_restart: true,
            partial: true,
            covered_s: DAY_S,
            energy_in_wh: U24,
            energy_out_wh: U24,
            charge_in_cah: U24,
            charge_out_cah: U24,
            lowest_cell_mv: 0,
            lowest_at_s: DAY_S,
            highest_cell_mv: u16::MAX,
            highest_at_s: DAY_S,
            top_spread_mv: u16::MAX,
            top_cell: 16,
            stages: StageMinutes {
                bulk: 1440,
                ..StageMinutes::default()
            },
            cycles: u16::MAX,
            full_charges: u16::MAX,
            max_cell_difference_raw: u16::MAX,
            capacity_cah: u16::MAX,
            capacity_uncertainty_permille: u8::MAX,
        }
    }

    #[test]
    fn encode_and_decode_round_trip_at_the_extremes() {
        for r in [
            DayRecord::default(),
            extreme(),
            DayRecord {
                stages: StageMinutes {
                    bulk: 288,
                    absorption: 288,
                    balance_held: 288,
                    float: 288,
                    other: 288,
                },
                top_cell: 1,
                ..extreme()
            },
        ] {
            let b = r.encode();
            assert_eq!(b.len(), DAY_BYTES);
            assert_eq!(b[0], DAY_VERSION);
            assert_eq!(DayRecord::decode(&b), Ok(r));
        }
        // Saturation: a value beyond its field is its field's largest.
        let big = DayRecord {
            energy_in_wh: u32::MAX,
            ..DayRecord::default()
        };
        assert_eq!(DayRecord::decode(&big.encode()).unwrap().energy_in_wh, U24);
    }

    #[test]
    fn decode_refuses_every_malformed_record_with_its_reason() {
        let good = extreme().encode();
        let with = |f: &dyn Fn(&mut DayRecord)| {
            let mut r = extreme();
            f(&mut r);
            DayRecord::decode(&r.encode())
        };
        let cases: [(Result<DayRecord, DayError>, DayError, &str); 10] = [
            (
                DayRecord::decode(&good[..55]),
                DayError::WrongLength,
                "wrong length",
            ),
            (
                DayRecord::decode(&[&good[..], &[0][..]].concat()),
                DayError::WrongLength,
                "wrong length",
            ),
            (
                DayRecord::decode(&[&[2u8][..], &good[1..]].concat()),
                DayError::UnknownVersion,
                "unknown version",
            ),
            (
                DayRecord::decode(&[&good[..1], &[good[1] | 4], &good[2..]].concat()),
                DayError::UnknownFlags,
                "unknown flags",
            ),
            (
                with(&|r| r.top_cell = 17),
                DayError::CellOutOfRange,
                "cell out of range",
            ),
            (
                with(&|r| r.covered_s = DAY_S + 1),
                DayError::CoveredOverDay,
                "more than a day covered",
            ),
            (
                with(&|r| r.covered_s = DAY_S - 1),
                DayError::WhenOutOfDay,
                "a time outside the day",
            ),
            (
                with(&|r| r.highest_cell_mv = 3400),
                DayError::SpreadAboveHighest,
                "spread above the highest cell",
            ),
            (
                with(&|r| r.stages.other = 1),
                DayError::StagesOverDay,
                "hours in stages over the day",
            ),
            (
                with(&|r| r.capacity_cah = 0),
                DayError::UncertaintyWithoutCapacity,
                "uncertainty without a capacity",
            ),
        ];
        for (got, want, words) in cases {
            assert_eq!(got, Err(want));
            assert_eq!(want.reason(), words);
        }
        let low_above = DayRecord {
            lowest_cell_mv: 3300,
            highest_cell_mv: 3200,
            ..DayRecord::default()
        };
        assert_eq!(
            DayRecord::decode(&low_above.encode()),
            Err(DayError::LowestAboveHighest)
        );
        assert_eq!(
            DayError::LowestAboveHighest.reason(),
            "lowest cell above the highest"
        );
    }

    #[test]
    fn any_bytes_decode_without_a_panic() {
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let good = extreme().encode();
        let mut decoded = 0;
        for i in 0..200_000u32 {
            let mut b = [0u8; 64];
            for v in b.iter_mut() {
                *v = next() as u8;
            }
            let len = (next() % 65) as usize;
            // Half of them a good record with one to three bytes changed.
            if i % 2 == 0 {
                b[..DAY_BYTES].copy_from_slice(&good);
                for _ in 0..1 + next() % 3 {
                    b[(next() % DAY_BYTES as u64) as usize] = next() as u8;
                }
            }
            let bytes = if i % 2 == 0 {
                &b[..DAY_BYTES]
            } else {
                &b[..len]
            };
            if let Ok(r) = DayRecord::decode(bytes) {
                assert_eq!(r.check(), Ok(()));
                assert_eq!(&r.encode()[..], bytes);
                decoded += 1;
            }
        }
        assert!(decoded > 1000, "{decoded}");
    }
}

impl DayBook {
    /// Day number `day` of a history, beginning at `now` (the day after the
    /// newest one in flash).
    pub fn starting(day: u32, now: Instant) -> Self {
        let mut b = Self::new(now);
        b.day = day;
        b
    }
}
