//! The wire to the BMS in figures and in words: what the link counters
//! ([`LinkStats`]) say about a window of time (the bridge uses the line quality
//! period, [`crate::bms::timing::LINE_QUALITY_LOG_PERIOD_US`]), and what to
//! check.
//!
//! Sans-IO: [`WireFigures::between`] takes two copies of the counters,
//! [`WireWindow::verdict`] decides, [`WireVerdict::text`] says it.
//!
//! ## Figures
//! Every figure is per thousand **sends**: the attempts put on the wire in the
//! window (transactions started + wake-up resends + retries), since each
//! attempt ends in a valid reply, a corrupted one or silence.
//! * `corrupted_permille` — frames that arrived damaged: CRC errors, framing
//!   errors (bad length, truncation, packet sequence) and CRC-valid frames that
//!   did not fit the request.
//! * `lost_permille` — attempts that ended in silence or an incomplete reply at
//!   the deadline (timeouts).
//! * `resent_permille` — sends that repeated an earlier one (retries and
//!   wake-up resends).
//!
//! Each is capped at 1000 (an attempt can see a damaged frame and then time
//! out: it is counted in both).
//!
//! ## Verdict, first rule that holds
//! 1. [`WireVerdict::Silent`] — requests went out and nothing at all came back
//!    in the window: no reply, no damaged frame, not one stray byte.
//! 2. [`WireVerdict::Asleep`] — the BMS answers, few replies are damaged (below
//!    [`NOISY_CORRUPTED_PERMILLE`]), but at least [`ASLEEP_WAKEUP_PERCENT`] % of
//!    the requests were only answered after a wake-up resend: it falls asleep
//!    between requests.
//! 3. [`WireVerdict::BadWire`] — the BMS answers, and at least
//!    [`BAD_CORRUPTED_PERMILLE`] ‰ (one in ten) of the sends came back damaged.
//! 4. [`WireVerdict::Noisy`] — at least [`NOISY_CORRUPTED_PERMILLE`] ‰ damaged,
//!    or at least [`NOISY_LOST_PERMILLE`] ‰ lost, or at least
//!    [`NOISY_RESENT_PERMILLE`] ‰ resent.
//! 5. [`WireVerdict::Healthy`] — below all of these (also a window in which
//!    nothing was sent: no evidence of anything wrong).

use crate::bms::link::LinkStats;
use crate::log_line::Line;

/// Damaged frames per thousand sends from which the wire is bad.
pub const BAD_CORRUPTED_PERMILLE: u16 = 100;
/// Damaged frames per thousand sends from which the wire is noisy.
pub const NOISY_CORRUPTED_PERMILLE: u16 = 10;
/// Lost replies per thousand sends from which the wire is noisy.
pub const NOISY_LOST_PERMILLE: u16 = 20;
/// Resends per thousand sends from which the wire is noisy.
pub const NOISY_RESENT_PERMILLE: u16 = 20;
/// Share of requests that needed a wake-up resend from which a BMS whose
/// replies are clean is asleep between requests, %.
pub const ASLEEP_WAKEUP_PERCENT: u32 = 50;

/// The link in a window, per thousand sends (see the module documentation).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct WireFigures {
    /// Valid replies (NACKs included) in the window.
    pub replies: u32,
    /// Damaged frames (CRC, framing, invalid) per thousand sends.
    pub corrupted_permille: u16,
    /// Timeouts per thousand sends.
    pub lost_permille: u16,
    /// Retries and wake-up resends per thousand sends.
    pub resent_permille: u16,
}

/// What the figures of a window say about the wire.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WireVerdict {
    /// Few damaged or lost replies, few resends.
    #[default]
    Healthy,
    /// Some replies damaged or lost: the bridge copes (smaller pieces, retries).
    Noisy {
        /// Damaged frames per thousand sends.
        corrupted_permille: u16,
        /// Timeouts per thousand sends.
        lost_permille: u16,
    },
    /// The BMS answers, but one reply in ten or more arrives damaged.
    BadWire {
        /// Damaged frames per thousand sends.
        corrupted_permille: u16,
    },
    /// Nothing at all came back.
    Silent,
    /// The BMS answers cleanly, but mostly only after a wake-up resend.
    Asleep {
        /// Resends per thousand sends.
        resent_permille: u16,
    },
}

/// `part` per thousand of `whole`, at most 1000 (0 when `whole` is 0).
fn per_thousand(part: u32, whole: u32) -> u16 {
    if whole == 0 {
        return 0;
    }
    (u64::from(part) * 1000 / u64::from(whole)).min(1000) as u16
}

/// The wire over a window: the figures and, kept to decide the verdict, the
/// counts behind them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct WireWindow {
    /// The figures.
    pub figures: WireFigures,
    /// Transactions started.
    pub requests: u32,
    /// Attempts put on the wire.
    pub sends: u32,
    /// Wake-up resends.
    pub wakeups: u32,
    /// Damaged frames.
    pub corrupted: u32,
    /// Bytes skipped by the decoder and frames that answered nothing (any sign
    /// of life that is not a reply).
    pub stray: u32,
}

impl WireFigures {
    /// The window from `before` to `after` (counters wrap: differences are
    /// taken modulo 2^32).
    pub fn between(before: &LinkStats, after: &LinkStats) -> WireWindow {
        let d = |a: u32, b: u32| a.wrapping_sub(b);
        let requests = d(after.requests, before.requests);
        let wakeups = d(after.wakeup_resends, before.wakeup_resends);
        let retries = d(after.retries, before.retries);
        let sends = requests.saturating_add(wakeups).saturating_add(retries);
        let corrupted = d(after.crc_errors, before.crc_errors)
            .saturating_add(d(after.framing_errors, before.framing_errors))
            .saturating_add(d(after.invalid_replies, before.invalid_replies));
        let lost = d(after.timeouts, before.timeouts);
        let stray = d(after.skipped_bytes, before.skipped_bytes)
            .saturating_add(d(after.unsolicited, before.unsolicited));
        WireWindow {
            figures: WireFigures {
                replies: d(after.replies, before.replies),
                corrupted_permille: per_thousand(corrupted, sends),
                lost_permille: per_thousand(lost, sends),
                resent_permille: per_thousand(wakeups.saturating_add(retries), sends),
            },
            requests,
            sends,
            wakeups,
            corrupted,
            stray,
        }
    }
}

impl WireWindow {
    /// The verdict (rules in the module documentation).
    pub fn verdict(&self) -> WireVerdict {
        let f = &self.figures;
        if self.sends == 0 {
            return WireVerdict::Healthy;
        }
        if f.replies == 0 && self.corrupted == 0 && self.stray == 0 {
            return WireVerdict::Silent;
        }
        let asleep = f.replies > 0
            && f.corrupted_permille < NOISY_CORRUPTED_PERMILLE
            && u64::from(self.wakeups) * 100
                >= u64::from(self.requests) * u64::from(ASLEEP_WAKEUP_PERCENT);
        if asleep {
            return WireVerdict::Asleep {
                resent_permille: f.resent_permille,
            };
        }
        if f.corrupted_permille >= BAD_CORRUPTED_PERMILLE && f.replies > 0 {
            return WireVerdict::BadWire {
                corrupted_permille: f.corrupted_permille,
            };
        }
        if f.corrupted_permille >= NOISY_CORRUPTED_PERMILLE
            || f.lost_permille >= NOISY_LOST_PERMILLE
            || f.resent_permille >= NOISY_RESENT_PERMILLE
        {
            return WireVerdict::Noisy {
                corrupted_permille: f.corrupted_permille,
                lost_permille: f.lost_permille,
            };
        }
        WireVerdict::Healthy
    }
}

impl WireVerdict {
    /// A short key (the host link's `wire`, Home Assistant).
    pub const fn key(&self) -> &'static str {
        match self {
            WireVerdict::Healthy => "healthy",
            WireVerdict::Noisy { .. } => "noisy",
            WireVerdict::BadWire { .. } => "bad_wire",
            WireVerdict::Silent => "silent",
            WireVerdict::Asleep { .. } => "asleep",
        }
    }

    /// Not [`WireVerdict::Healthy`].
    pub fn is_degraded(&self) -> bool {
        *self != WireVerdict::Healthy
    }

    /// The verdict in words: what is wrong and what to check.
    pub fn text(&self, out: &mut Line) {
        match *self {
            WireVerdict::Healthy => {
                out.push("the wire is healthy");
            }
            WireVerdict::Noisy {
                corrupted_permille,
                lost_permille,
            } => {
                out.push("a noisy line: ")
                    .fixed(i64::from(corrupted_permille), 1)
                    .push(" % of replies corrupted, ")
                    .fixed(i64::from(lost_permille), 1)
                    .push(" % lost; the BMS answers, the bridge reads in smaller pieces");
            }
            WireVerdict::BadWire { corrupted_permille } => {
                if corrupted_permille >= 500 {
                    out.push("most replies corrupted (")
                        .fixed(i64::from(corrupted_permille), 1)
                        .push(" %)");
                } else {
                    // One in n, rounded: 100 ‰ is one in ten.
                    let c = u32::from(corrupted_permille.max(1));
                    out.push("one reply in ")
                        .uint(u64::from((1000 + c / 2) / c));
                    out.push(" corrupted");
                }
                out.push(": check the ground and the cable length; the BMS answers");
            }
            WireVerdict::Silent => {
                out.push(
                    "the BMS does not answer: check its power, that TX goes to its RX \
                     and RX to its TX, and that it is awake",
                );
            }
            WireVerdict::Asleep { resent_permille } => {
                out.push("the BMS answers only after a wake-up resend (")
                    .fixed(i64::from(resent_permille), 1)
                    .push(" % of sends are resends): it sleeps between requests");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Counters after a window that started from zero.
    fn stats(
        requests: u32,
        replies: u32,
        wakeups: u32,
        retries: u32,
        crc: u32,
        timeouts: u32,
        skipped: u32,
    ) -> LinkStats {
        LinkStats {
            requests,
            replies,
            wakeup_resends: wakeups,
            retries,
            crc_errors: crc,
            timeouts,
            skipped_bytes: skipped,
            ..LinkStats::default()
        }
    }

    fn window(after: LinkStats) -> WireWindow {
        WireFigures::between(&LinkStats::default(), &after)
    }

    fn said(v: WireVerdict) -> heapless::String<384> {
        let mut l = Line::new();
        v.text(&mut l);
        heapless::String::try_from(l.as_str()).unwrap()
    }

    #[test]
    fn a_clean_window_is_healthy() {
        let w = window(stats(1000, 1000, 0, 0, 0, 0, 0));
        assert_eq!(w.figures.replies, 1000);
        assert_eq!(w.figures.corrupted_permille, 0);
        assert_eq!(w.verdict(), WireVerdict::Healthy);
        // A few faults stay healthy.
        let w = window(stats(1000, 1000, 5, 9, 9, 5, 40));
        assert_eq!(w.verdict(), WireVerdict::Healthy);
        // Nothing sent: no evidence.
        assert_eq!(window(LinkStats::default()).verdict(), WireVerdict::Healthy);
    }

    #[test]
    fn figures_are_per_thousand_sends() {
        // 800 requests + 100 wake-ups + 100 retries = 1000 sends.
        let w = window(stats(800, 780, 100, 100, 60, 150, 500));
        assert_eq!(w.sends, 1000);
        assert_eq!(w.figures.corrupted_permille, 60);
        assert_eq!(w.figures.lost_permille, 150);
        assert_eq!(w.figures.resent_permille, 200);
    }

    #[test]
    fn counters_that_wrap_still_give_the_window() {
        let before = stats(u32::MAX - 9, u32::MAX - 9, 0, 0, 0, 0, 0);
        let after = stats(990, 990, 0, 0, 0, 0, 0);
        let w = WireFigures::between(&before, &after);
        assert_eq!(w.requests, 1000);
        assert_eq!(w.verdict(), WireVerdict::Healthy);
    }

    #[test]
    fn many_damaged_replies_are_a_bad_wire() {
        let w = window(stats(1000, 700, 0, 300, 130, 40, 9000));
        assert_eq!(
            w.verdict(),
            WireVerdict::BadWire {
                corrupted_permille: 100
            }
        );
        assert_eq!(
            said(w.verdict()).as_str(),
            "one reply in 10 corrupted: check the ground and the cable length; the BMS answers"
        );
    }

    #[test]
    fn some_damaged_or_lost_replies_are_a_noisy_line() {
        let w = window(stats(1000, 950, 0, 50, 20, 30, 300));
        assert_eq!(
            w.verdict(),
            WireVerdict::Noisy {
                corrupted_permille: 19,
                lost_permille: 28
            }
        );
        assert!(said(w.verdict()).starts_with("a noisy line: 1.9 % of replies corrupted"));
    }

    #[test]
    fn no_byte_at_all_is_a_silent_bms() {
        let w = window(stats(30, 0, 30, 60, 0, 120, 0));
        assert_eq!(w.verdict(), WireVerdict::Silent);
        assert_eq!(
            said(w.verdict()).as_str(),
            "the BMS does not answer: check its power, that TX goes to its RX and RX to its TX, and that it is awake"
        );
        // A single stray byte is a sign of life: not silent (and with nothing
        // but losses, a noisy line).
        let w = window(stats(30, 0, 30, 60, 0, 120, 1));
        assert_ne!(w.verdict(), WireVerdict::Silent);
    }

    #[test]
    fn clean_answers_after_wake_ups_are_an_asleep_bms() {
        // Every request answered, most after a wake-up resend, nothing damaged.
        let w = window(stats(100, 100, 60, 0, 0, 60, 0));
        assert_eq!(
            w.verdict(),
            WireVerdict::Asleep {
                resent_permille: 375
            }
        );
        assert!(said(w.verdict()).ends_with("it sleeps between requests"));
        // The same wake-ups with damaged replies: a bad wire, not sleep.
        let w = window(stats(100, 100, 60, 0, 40, 60, 500));
        assert!(matches!(w.verdict(), WireVerdict::BadWire { .. }));
    }

    /// The thresholds as documented, at their edges: a rule that moves breaks
    /// this test.
    #[test]
    fn thresholds_hold_at_their_edges() {
        // 1000 sends each (no resends), replies always there.
        let at = |crc: u32, timeouts: u32| window(stats(1000, 900, 0, 0, crc, timeouts, 1));
        assert!(matches!(at(100, 0).verdict(), WireVerdict::BadWire { .. }));
        assert!(matches!(at(99, 0).verdict(), WireVerdict::Noisy { .. }));
        assert!(matches!(at(10, 0).verdict(), WireVerdict::Noisy { .. }));
        assert_eq!(at(9, 0).verdict(), WireVerdict::Healthy);
        assert!(matches!(at(0, 20).verdict(), WireVerdict::Noisy { .. }));
        assert_eq!(at(0, 19).verdict(), WireVerdict::Healthy);
        let resent = |r: u32| window(stats(1000 - r, 1000 - r, 0, r, 0, 0, 0)).verdict();
        assert!(matches!(resent(20), WireVerdict::Noisy { .. }));
        assert_eq!(resent(19), WireVerdict::Healthy);
        // Asleep from half the requests woken, clean replies only.
        let woken = |n: u32| window(stats(100, 100, n, 0, 0, n, 0)).verdict();
        assert!(matches!(woken(50), WireVerdict::Asleep { .. }));
        assert!(!matches!(woken(49), WireVerdict::Asleep { .. }));
        assert_eq!(BAD_CORRUPTED_PERMILLE, 100);
        assert_eq!(NOISY_CORRUPTED_PERMILLE, 10);
        assert_eq!(NOISY_LOST_PERMILLE, 20);
        assert_eq!(NOISY_RESENT_PERMILLE, 20);
        assert_eq!(ASLEEP_WAKEUP_PERCENT, 50);
    }

    #[test]
    fn most_replies_corrupted_says_so() {
        let v = WireVerdict::BadWire {
            corrupted_permille: 640,
        };
        assert_eq!(
            said(v).as_str(),
            "most replies corrupted (64.0 %): check the ground and the cable length; the BMS answers"
        );
        let v = WireVerdict::BadWire {
            corrupted_permille: 250,
        };
        assert!(said(v).starts_with("one reply in 4 corrupted"));
    }
}
