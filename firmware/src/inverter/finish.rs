//! The end of a charge, made for the TinyBMS's slow balance.
//!
//! The TinyBMS balances passively (up to 150 mA a cell, Energus's
//! datasheet), only while charging and only above its early-balancing
//! threshold (303). A charge that drops to float as soon as the current has
//! tapered cuts that balance short day after day, and the cell that runs
//! ahead then ends every charge. So, driven by what the BMS reports:
//!
//! * **Absorption held while the BMS balances**: at the target and tapered,
//!   while register 52 says cells are balancing and the spread is above the
//!   allowed disbalance (308), the switch to float waits — at most
//!   [`super::control::ChargeConfig::balance_hold_us`] per charge (0 = never),
//!   times the whole days since the last full charge (at most
//!   `full_charge_days` times): the periodic full charge after days of an
//!   SOC ceiling gets those days' balancing time.
//! * **A full charge every N days**
//!   ([`super::control::ChargeConfig::full_charge_days`], 0 = off): when the
//!   last charge that reached float is that old, float ends (as below the
//!   rebulk SOC) and an SOC ceiling is set aside until the charge is done. The
//!   count starts at every boot with a charge due: the bridge does not know
//!   when the last full charge was.
//! * **A gradual step down into float**
//!   ([`super::control::ChargeConfig::float_step_mv_per_min`] per cell per
//!   minute, 0 = at once): CVL falls from the absorption value at most that
//!   fast, never rises on the way, waits while the pack discharges, and at
//!   rest never goes below the pack's own voltage — an inverter that pulls the battery
//!   down to CVL (a Deye exported the battery to the grid when CVL dropped at
//!   once) has nothing to pull. Only this descent is stepped: a stop still
//!   goes out at once with every signal ([`super::say`]), and the charge
//!   limit's taper below the ceiling does not wait for it.
//! * **An SOC ceiling** for daily cycling
//!   ([`super::control::ChargeConfig::soc_ceiling_pct`], 100 = off): the charge
//!   current is 0 from the ceiling until the SOC is [`CEILING_RESUME_PCT`]
//!   below it — except while a full charge is due.
//!
//! Each decision is a [`Stage`], said in words by [`Stage::text`] in the log,
//! `monitor` and Home Assistant.

use crate::log_line::Line;
use crate::Instant;

/// With an SOC ceiling, charging resumes this far below it, %.
pub const CEILING_RESUME_PCT: f32 = 3.0;

/// The cells balancing are named up to this many; more are counted.
pub const CELLS_NAMED: u32 = 4;

/// A day, µs (the full-charge interval's unit).
pub const DAY_US: Instant = 24 * 3600 * crate::SECOND;

/// Where a charge is, and why: the reason behind CVL and a charge limit of 0
/// at the top of a charge.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Stage {
    /// Charging towards the absorption target; `full_due`: a periodic full
    /// charge is due (an SOC ceiling waits for it).
    Bulk {
        /// A full charge is due.
        full_due: bool,
    },
    /// At the absorption target, the current tapering (the `full_hold`
    /// before float).
    Absorption,
    /// Absorption held: the BMS balances and the spread is above 308.
    BalanceHeld {
        /// Register 52: the cells being balanced (bit 0 = cell 1).
        balancing: u16,
        /// Highest less lowest cell, mV.
        spread_mv: u16,
        /// How long the hold may still last, s.
        left_s: u32,
    },
    /// Stepping CVL down into float.
    StepDown {
        /// CVL now, 0.1 V.
        cvl_dv: u16,
        /// The float CVL it steps to, 0.1 V.
        float_dv: u16,
    },
    /// Holding the float target.
    Float,
    /// Charging paused at the owner's SOC ceiling.
    Ceiling {
        /// The ceiling, %.
        ceiling_pct: u8,
    },
}

impl Stage {
    /// As the host link and MQTT write it.
    pub const fn key(self) -> &'static str {
        match self {
            Self::Bulk { .. } => "bulk",
            Self::Absorption => "absorption",
            Self::BalanceHeld { .. } => "balance_hold",
            Self::StepDown { .. } => "step_down",
            Self::Float => "float",
            Self::Ceiling { .. } => "soc_ceiling",
        }
    }

    /// Whether `other` is the same stage for the log (the numbers may move).
    pub fn same_kind(self, other: Self) -> bool {
        core::mem::discriminant(&self) == core::mem::discriminant(&other)
            && match (self, other) {
                (Self::Bulk { full_due: a }, Self::Bulk { full_due: b }) => a == b,
                _ => true,
            }
    }

    /// In words: `absorption held: cells 3 and 7 balancing, spread 24 mV (at
    /// most 40 min more)`.
    #[inline(never)]
    pub fn text(self) -> Line {
        let mut out = Line::new();
        self.write(&mut out);
        out
    }

    /// [`Stage::text`] appended to `out` (numbers written without
    /// `core::fmt`, as every log line: see [`crate::text`]).
    #[inline(never)]
    pub fn write(self, out: &mut Line) {
        match self {
            Self::Bulk { full_due: false } => {
                out.push("to the absorption target");
            }
            Self::Bulk { full_due: true } => {
                out.push("full charge due: to the absorption target and its balance");
            }
            Self::Absorption => {
                out.push("absorption: at the target, the current tapering");
            }
            Self::BalanceHeld {
                balancing,
                spread_mv,
                left_s,
            } => {
                out.push("absorption held: ");
                cells_text(out, balancing);
                out.push(" balancing, spread ")
                    .uint(u64::from(spread_mv))
                    .push(" mV (at most ")
                    .uint(u64::from(left_s.div_ceil(60)))
                    .push(" min more)");
            }
            Self::StepDown { cvl_dv, float_dv } => {
                out.push("stepping down to float: ")
                    .fixed(i64::from(cvl_dv), 1)
                    .push(" V, float ")
                    .fixed(i64::from(float_dv), 1)
                    .push(" V");
            }
            Self::Float => {
                out.push("float");
            }
            Self::Ceiling { ceiling_pct } => {
                out.push("charge paused at the SOC ceiling (")
                    .uint(u64::from(ceiling_pct))
                    .push(" %)");
            }
        }
    }
}

/// `cells 3 and 7`, `cell 4`, `cells 1, 2 and 16` (bit 0 = cell 1); more
/// than [`CELLS_NAMED`]: `9 cells`.
fn cells_text(out: &mut Line, bits: u16) {
    let count = bits.count_ones();
    if count > CELLS_NAMED {
        out.uint(u64::from(count)).push(" cells");
        return;
    }
    out.push(if count == 1 { "cell " } else { "cells " });
    let mut seen = 0;
    for i in 0..16u16 {
        if bits & (1 << i) == 0 {
            continue;
        }
        seen += 1;
        if seen > 1 {
            out.push(if seen == count { " and " } else { ", " });
        }
        out.uint(u64::from(i + 1));
    }
}

/// The end-of-charge state charge control keeps besides its phase.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub(super) struct Finish {
    /// Since when this absorption's balance hold runs.
    pub hold_since: Option<Instant>,
    /// When the last charge reached float (`None`: not since the boot).
    pub last_full: Option<Instant>,
    /// The stepped CVL on the way down to float, mV (pack); `None`: not
    /// stepping.
    pub step_mv: Option<u32>,
    /// Paused at the SOC ceiling.
    pub at_ceiling: bool,
}

impl Finish {
    /// Nothing held, no full charge known, not stepping, no ceiling.
    pub const fn new() -> Self {
        Self {
            hold_since: None,
            last_full: None,
            step_mv: None,
            at_ceiling: false,
        }
    }

    /// Whether a periodic full charge is due at `now`.
    pub fn full_due(&self, now: Instant, days: u16) -> bool {
        days > 0
            && self
                .last_full
                .is_none_or(|t| now.saturating_sub(t) >= Instant::from(days) * DAY_US)
    }

    /// How long this charge's balance hold may last at most: `hold_us` for
    /// each whole day since the last full charge (a charge every day gets
    /// `hold_us`; the periodic full charge after a week of an SOC ceiling
    /// gets the week's), at least once and at most `days` times (at most
    /// once with `days` 0, and once at the first charge after a start).
    pub fn hold_bound(&self, now: Instant, hold_us: Instant, days: u16) -> Instant {
        let since = self
            .last_full
            .map_or(1, |t| now.saturating_sub(t) / DAY_US)
            .clamp(1, u64::from(days.max(1)));
        hold_us.saturating_mul(since)
    }

    /// The SOC ceiling's decision for this update: whether the charge is
    /// paused (with hysteresis), never while a full charge is due.
    pub fn ceiling(&mut self, ceiling_pct: u8, soc_pct: f32, due: bool) -> bool {
        let on = ceiling_pct < 100 && !due;
        let c = f32::from(ceiling_pct);
        self.at_ceiling = on
            && if self.at_ceiling {
                soc_pct > c - CEILING_RESUME_PCT
            } else {
                soc_pct >= c
            };
        self.at_ceiling
    }

    /// One step of the descent into float: from the stepped CVL (mV, pack)
    /// towards `float_mv`, at most `step_mv_per_min` × cells per minute over
    /// `dt_us`, never below `floor_mv` (the pack's voltage while it is not
    /// charging) and never up. Returns the new stepped CVL, or `None` once
    /// it reached the float CVL (stepping is over).
    pub fn step(
        &mut self,
        float_mv: u32,
        cells: u32,
        step_mv_per_min: u16,
        dt_us: Instant,
        floor_mv: u32,
    ) -> Option<u32> {
        let from = self.step_mv?;
        if from <= float_mv {
            self.step_mv = None;
            return None;
        }
        let step = u64::from(cells) * u64::from(step_mv_per_min) * dt_us / (60 * crate::SECOND);
        let down = u64::from(from).saturating_sub(step);
        let next = (down as u32).max(float_mv).max(floor_mv.min(from));
        if next <= float_mv {
            self.step_mv = None;
            return None;
        }
        self.step_mv = Some(next);
        Some(next)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn balance_held(balancing: u16, spread_mv: u16, left_s: u32) -> Stage {
        Stage::BalanceHeld {
            balancing,
            spread_mv,
            left_s,
        }
    }

    #[test]
    fn stages_in_words() {
        let held = Stage::BalanceHeld {
            balancing: (1 << 2) | (1 << 6),
            spread_mv: 24,
            left_s: 600,
        };
        assert_eq!(
            held.text().as_str(),
            "absorption held: cells 3 and 7 balancing, spread 24 mV (at most 10 min more)"
        );
        let one = balance_held(1 << 15, 30, 61);
        assert!(one
            .text()
            .as_str()
            .starts_with("absorption held: cell 16 balancing"));
        let three = balance_held(0b111, 30, 0);
        assert!(three.text().as_str().contains("cells 1, 2 and 3 balancing"));
        let many = balance_held(0xFFF0, u16::MAX, u32::MAX);
        assert!(many
            .text()
            .as_str()
            .contains("12 cells balancing, spread 65535 mV"));
        // The longest text fits whole.
        let longest = balance_held(0xF000, u16::MAX, u32::MAX);
        assert!(
            longest.text().as_str().ends_with("min more)"),
            "{}",
            longest.text().as_str()
        );
        let s = Stage::StepDown {
            cvl_dv: 563,
            float_dv: 532,
        };
        assert_eq!(
            s.text().as_str(),
            "stepping down to float: 56.3 V, float 53.2 V"
        );
    }

    #[test]
    fn a_full_charge_is_due_after_its_days_and_at_boot() {
        let mut f = Finish::default();
        assert!(f.full_due(0, 7), "at boot");
        assert!(!f.full_due(0, 0), "0 = off");
        f.last_full = Some(DAY_US);
        assert!(!f.full_due(7 * DAY_US, 7));
        assert!(f.full_due(8 * DAY_US, 7));
    }

    #[test]
    fn the_hold_grows_with_the_days_since_the_last_full_charge() {
        let h = 3600 * crate::SECOND;
        let mut f = Finish::default();
        assert_eq!(f.hold_bound(0, h, 7), h, "the first charge after a start");
        f.last_full = Some(0);
        assert_eq!(f.hold_bound(DAY_US / 2, h, 7), h);
        assert_eq!(f.hold_bound(3 * DAY_US + 5, h, 7), 3 * h);
        assert_eq!(f.hold_bound(30 * DAY_US, h, 7), 7 * h, "at most the days");
        assert_eq!(f.hold_bound(30 * DAY_US, h, 0), h, "no periodic charge");
        assert_eq!(f.hold_bound(30 * DAY_US, 0, 7), 0, "never held");
    }

    #[test]
    fn the_ceiling_pauses_with_hysteresis_and_yields_to_a_due_full_charge() {
        let mut f = Finish::default();
        assert!(!f.ceiling(90, 89.9, false));
        assert!(f.ceiling(90, 90.0, false));
        assert!(f.ceiling(90, 88.0, false), "within the hysteresis");
        assert!(!f.ceiling(90, 86.9, false), "resumed");
        assert!(!f.ceiling(90, 95.0, true), "a full charge is due");
        assert!(!f.ceiling(100, 100.0, false), "100 = off");
    }

    #[test]
    fn the_step_is_bounded_never_rises_and_stops_at_the_pack() {
        let mut f = Finish {
            step_mv: Some(56_800),
            ..Finish::default()
        };
        // 16 cells × 5 mV/min over a minute: 80 mV.
        assert_eq!(f.step(53_200, 16, 5, 60 * crate::SECOND, 0), Some(56_720));
        // The pack at 55.0 V, not charging: no lower than it.
        let mut at = 56_720;
        for _ in 0..100 {
            at = f.step(53_200, 16, 5, 60 * crate::SECOND, 55_000).unwrap();
        }
        assert_eq!(at, 55_000);
        // A pack above the stepped CVL never lifts it.
        assert_eq!(
            f.step(53_200, 16, 5, 60 * crate::SECOND, 56_000),
            Some(55_000)
        );
        // Down to float: stepping is over.
        let mut n = 0;
        while f.step(53_200, 16, 5, 60 * crate::SECOND, 0).is_some() {
            n += 1;
            assert!(n < 100);
        }
        assert_eq!(f.step_mv, None);
    }
}
