//! Cross-field consistency checks: what a live block from a real TinyBMS always
//! satisfies, so that a block that does not is not published on the strength of
//! its CRC alone.
//!
//! Why: a CRC-16 accepts a damaged frame with probability 2^-16. On a noisy line a
//! damaged reply that runs into the start of a repeated one produces, now and then,
//! a "valid" frame of the right length made of shifted bytes (seen in soaks: a
//! pack of 806 669 647 872 V, SOC 352 %, 18 cells on a 16S pack, 76.1 °C). Each
//! check below names the property of real units it relies on. A block that fails
//! one is re-read at once; the bridge publishes it only when an independent second
//! reply confirms it (see the bridge, `crate::bridge`), flagged with the check it failed.

use protocol_core::events::OnlineStatus;
use protocol_core::registers::MAX_CELLS;
use protocol_core::response::RegisterBlock;
use protocol_core::views::{cell_mv, LiveSnapshot};

use crate::Instant;

/// A check a block failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Check {
    /// Register 53 (detected cells) outside 1-16, or not the configured series
    /// cell count (register 307) when that is known.
    CellCount,
    /// A non-zero cell register outside the block of detected cells (unused
    /// inputs read 0, HARDWARE-NOTES).
    CellOutsideBlock,
    /// A cell outside [`CELL_MIN_RAW`]..=[`CELL_MAX_RAW`] (0.1 mV).
    CellVoltage,
    /// Registers 40/41 (min/max cell, mV) disagree with the cells.
    MinMaxCell,
    /// Pack voltage (36-37) disagrees with the sum of the cells.
    PackVoltage,
    /// Pack current (38-39) not a finite number within [`MAX_CURRENT_A`].
    Current,
    /// SOC above 100 %.
    Soc,
    /// SOH above 100 %.
    Soh,
    /// Status (register 50) not one of Rev D's codes.
    Status,
    /// A temperature outside the sensors' range and not the "not connected" marker.
    Temperature,
    /// SOC moved faster than [`SOC_RATE_PERCENT_PER_S`] since the last snapshot.
    SocJump,
    /// A temperature moved faster than [`TEMP_RATE_DC_PER_S`].
    TemperatureJump,
    /// A cell moved more than [`CELL_JUMP_RAW`].
    CellJump,
    /// The lifetime counter (32-33) went backwards or ran ahead of the clock.
    LifetimeJump,
}

impl Check {
    /// Short snake_case name.
    pub const fn name(self) -> &'static str {
        match self {
            Check::CellCount => "cell_count",
            Check::CellOutsideBlock => "cell_outside_block",
            Check::CellVoltage => "cell_voltage",
            Check::MinMaxCell => "min_max_cell",
            Check::PackVoltage => "pack_voltage",
            Check::Current => "current",
            Check::Soc => "soc",
            Check::Soh => "soh",
            Check::Status => "status",
            Check::Temperature => "temperature",
            Check::SocJump => "soc_jump",
            Check::TemperatureJump => "temperature_jump",
            Check::CellJump => "cell_jump",
            Check::LifetimeJump => "lifetime_jump",
        }
    }
}

/// Lowest plausible cell reading, 0.1 mV (1.0 V: below any lithium or LTO cell
/// that is still connected; a 0 V cell is a broken sense wire — real, but to be
/// confirmed and flagged).
pub const CELL_MIN_RAW: u16 = 10_000;
/// Highest plausible cell reading, 0.1 mV (5.0 V: above every chemistry the
/// s516 is set up for; Rev D's over-voltage cutoff range ends at 4.5 V).
pub const CELL_MAX_RAW: u16 = 50_000;
/// Registers 40/41 are the min/max cell in mV, computed by the BMS from the same
/// measurement as the cells: they agree to the mV rounding. Allowed difference
/// for one block read in one reply, mV.
pub const MIN_MAX_TOLERANCE_MV: u16 = 5;
/// The same for a block assembled from pieces read at different times (cells
/// move under load between the reads), mV.
pub const MIN_MAX_TOLERANCE_ASSEMBLED_MV: u16 = 150;
/// Pack voltage vs sum of cells: the BMS derives the pack voltage from the same
/// cell measurements; allowed difference is this many mV plus
/// [`PACK_TOLERANCE_PERMILLE`] of the sum (margin for a separate pack
/// measurement on other firmware).
pub const PACK_TOLERANCE_MV: u32 = 500;
/// See [`PACK_TOLERANCE_MV`].
pub const PACK_TOLERANCE_PERMILLE: u32 = 20;
/// Extra pack tolerance for an assembled block, mV per cell.
pub const PACK_TOLERANCE_ASSEMBLED_MV_PER_CELL: u32 = 150;
/// Largest plausible pack current magnitude, A (the largest external sensor
/// setting of Rev D is 750 A; this leaves a wide margin).
pub const MAX_CURRENT_A: f32 = 5_000.0;
/// Temperature sensor range, 0.1 °C (internal sensor and NTC inputs: −40 °C to
/// +125 °C).
pub const TEMP_RANGE_DC: (i16, i16) = (-400, 1250);
/// Fastest plausible SOC change, % per second (10C, far beyond any pack the
/// BMS's sensors can measure) plus [`SOC_JUMP_SLACK_PERCENT`].
pub const SOC_RATE_PERCENT_PER_S: u32 = 1;
/// See [`SOC_RATE_PERCENT_PER_S`].
pub const SOC_JUMP_SLACK_PERCENT: u32 = 2;
/// Fastest plausible temperature change of a sensor, 0.1 °C per second, plus
/// [`TEMP_JUMP_SLACK_DC`] (sensors have thermal mass).
pub const TEMP_RATE_DC_PER_S: u32 = 10;
/// See [`TEMP_RATE_DC_PER_S`].
pub const TEMP_JUMP_SLACK_DC: u32 = 50;
/// Largest plausible change of one cell between two snapshots, 0.1 mV (1.0 V: a
/// load step through a cell's internal resistance moves it by tenths of a volt).
pub const CELL_JUMP_RAW: u16 = 10_000;
/// Lifetime counter slack, seconds (it counts seconds; the read is not atomic
/// with our clock).
pub const LIFETIME_SLACK_S: u64 = 10;

/// What the checks know besides the block itself.
#[derive(Debug, Clone, Copy, Default)]
pub struct Context {
    /// Register 307 (series cells), once the settings are read.
    pub series_cells: Option<u16>,
    /// The block was assembled from pieces read at different times.
    pub assembled: bool,
}

/// Static checks of a live block (registers 0-55) and its decoded view.
pub fn check_live(block: &RegisterBlock, s: &LiveSnapshot, ctx: Context) -> Result<(), Check> {
    // Cell count: register 53 counts detected cells; the s516 has 16 inputs.
    if s.cell_count == 0 || usize::from(s.cell_count) > MAX_CELLS {
        return Err(Check::CellCount);
    }
    if let Some(n) = ctx.series_cells {
        if n != s.cell_count {
            return Err(Check::CellCount);
        }
    }
    // Unused inputs read 0: every non-zero cell register is inside the block.
    let first = usize::from(s.cells.first_register);
    let last = first + usize::from(s.cell_count).min(MAX_CELLS);
    if any_nonzero(block, 0, first) || any_nonzero(block, last, MAX_CELLS) {
        return Err(Check::CellOutsideBlock);
    }
    // One pass over the cells: lowest, highest, sum; every cell is in range
    // when the lowest and the highest are.
    let (Some(&c0), Some(rest)) = (s.cells.raw.first(), s.cells.raw.get(1..)) else {
        return Err(Check::CellCount);
    };
    let (mut lo, mut hi, mut sum) = (c0, c0, u32::from(c0));
    for &c in rest {
        lo = lo.min(c);
        hi = hi.max(c);
        sum += u32::from(c);
    }
    if lo < CELL_MIN_RAW || hi > CELL_MAX_RAW {
        return Err(Check::CellVoltage);
    }
    // Registers 40/41 against the cells.
    let tol = if ctx.assembled {
        MIN_MAX_TOLERANCE_ASSEMBLED_MV
    } else {
        MIN_MAX_TOLERANCE_MV
    };
    if cell_mv(lo).abs_diff(s.min_cell_mv) > tol || cell_mv(hi).abs_diff(s.max_cell_mv) > tol {
        return Err(Check::MinMaxCell);
    }
    // Pack voltage against the sum of the cells.
    let sum_mv: u32 = sum / 10;
    let pack = s.pack_voltage_v;
    if !pack.is_finite() || !(0.0..=100.0).contains(&pack) {
        return Err(Check::PackVoltage);
    }
    let pack_mv = (pack * 1000.0) as u32;
    let mut pack_tol = PACK_TOLERANCE_MV + sum_mv * PACK_TOLERANCE_PERMILLE / 1000;
    if ctx.assembled {
        pack_tol += PACK_TOLERANCE_ASSEMBLED_MV_PER_CELL * u32::from(s.cell_count);
    }
    if pack_mv.abs_diff(sum_mv) > pack_tol {
        return Err(Check::PackVoltage);
    }
    let i = s.pack_current_a;
    if !i.is_finite() || i.abs() > MAX_CURRENT_A {
        return Err(Check::Current);
    }
    // SOC is 0.000001 % units: 100 % = 100 000 000. SOH is 0.002 %: 100 % = 50 000.
    if s.soc_raw > 100_000_000 {
        return Err(Check::Soc);
    }
    if s.soh_raw > 50_000 {
        return Err(Check::Soh);
    }
    if !OnlineStatus::KNOWN.contains(&s.status) {
        return Err(Check::Status);
    }
    let in_range = |dc: i16| (TEMP_RANGE_DC.0..=TEMP_RANGE_DC.1).contains(&dc);
    // External sensors: `None` is the "not connected" marker (-32768).
    if !in_range(s.internal_dc)
        || s.external1_dc.is_some_and(|t| !in_range(t))
        || s.external2_dc.is_some_and(|t| !in_range(t))
    {
        return Err(Check::Temperature);
    }
    Ok(())
}

/// True when a register of `from..to` in `block` is not 0 (registers the block
/// does not hold count as 0).
fn any_nonzero(block: &RegisterBlock, from: usize, to: usize) -> bool {
    let start = usize::from(block.start);
    let (a, b) = (from.saturating_sub(start), to.saturating_sub(start));
    block
        .values
        .get(a..b.min(block.values.len()))
        .is_some_and(|v| v.iter().any(|&x| x != 0))
}

/// Checks that nothing moved faster than physics allows between `prev` (taken
/// at `prev_at`) and `s` (taken at `at`).
pub fn check_jump(
    prev: &LiveSnapshot,
    prev_at: Instant,
    s: &LiveSnapshot,
    at: Instant,
) -> Result<(), Check> {
    let dt_s = at.saturating_sub(prev_at) / crate::SECOND + 1;
    let dt_s32 = dt_s.min(u64::from(u32::MAX / 1000)) as u32;
    // SOC in 0.000001 %.
    let soc_limit = (SOC_RATE_PERCENT_PER_S.saturating_mul(dt_s32) + SOC_JUMP_SLACK_PERCENT)
        .saturating_mul(1_000_000);
    if s.soc_raw.abs_diff(prev.soc_raw) > soc_limit {
        return Err(Check::SocJump);
    }
    let temp_limit = TEMP_RATE_DC_PER_S.saturating_mul(dt_s32) + TEMP_JUMP_SLACK_DC;
    let moved = |a: Option<i16>, b: Option<i16>| match (a, b) {
        (Some(a), Some(b)) => u32::from(a.abs_diff(b)) > temp_limit,
        // A sensor plugged in or out: no rate to check.
        _ => false,
    };
    if moved(Some(prev.internal_dc), Some(s.internal_dc))
        || moved(prev.external1_dc, s.external1_dc)
        || moved(prev.external2_dc, s.external2_dc)
    {
        return Err(Check::TemperatureJump);
    }
    if prev.cells.first_register == s.cells.first_register {
        let jumped = prev
            .cells
            .raw
            .iter()
            .zip(s.cells.raw.iter())
            .any(|(a, b)| a.abs_diff(*b) > CELL_JUMP_RAW);
        if jumped {
            return Err(Check::CellJump);
        }
    }
    let life = u64::from(s.lifetime_s);
    let prev_life = u64::from(prev.lifetime_s);
    if life < prev_life || life > prev_life + dt_s + LIFETIME_SLACK_S {
        return Err(Check::LifetimeJump);
    }
    Ok(())
}
