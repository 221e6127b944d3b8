//! A stale episode of the inverter output: from the first period whose
//! newest snapshot is too old (see [`super::InverterConfig::freshness`]) to
//! the first fresh one again, with the hold's budget (see [`super::hold`]),
//! the end of the hold noted once, the periods of the stop said blind
//! counted, and a stale policy given meanwhile kept for the next episode.
//! Sans-IO and time-free but for the instants given.

use super::hold::HoldBudget;
use super::StaleMode;
use crate::Instant;

/// A stale policy with its hold time, µs.
pub type Policy = (StaleMode, Instant);

/// The episode's state. See the module documentation.
#[derive(Debug, Clone, Default)]
pub struct StaleEpisode {
    since: Option<Instant>,
    hold_ended: bool,
    /// A policy given during the episode: it applies from the next one.
    deferred: Option<Policy>,
    /// The hold's budget, decided when the episode began.
    budget: Option<HoldBudget>,
    /// Periods of the stop said blind so far (saturating).
    stop_periods: u8,
}

impl StaleEpisode {
    /// An episode is going on.
    pub fn ongoing(&self) -> bool {
        self.since.is_some()
    }

    /// Stale at `now`: when the episode began (`now` when it begins now).
    pub fn stale_at(&mut self, now: Instant) -> Instant {
        *self.since.get_or_insert(now)
    }

    /// Stale at `now`: `true` when this begins an episode.
    pub fn starts(&mut self, now: Instant) -> bool {
        let new = self.since.is_none();
        if new {
            self.since = Some(now);
        }
        new
    }

    /// Fresh again: `true` when this ends an episode.
    pub fn ends(&mut self) -> bool {
        self.budget = None;
        self.stop_periods = 0;
        self.since.take().is_some()
    }

    /// The hold's budget of this episode, decided by `make` the first time.
    pub fn budget(&mut self, make: impl FnOnce() -> HoldBudget) -> HoldBudget {
        *self.budget.get_or_insert_with(make)
    }

    /// One more period of the stop said blind: how many were said before.
    pub fn stop_period(&mut self) -> u8 {
        let n = self.stop_periods;
        self.stop_periods = n.saturating_add(1);
        n
    }

    /// The hold is over: `true` the first time in an episode.
    pub fn hold_ends(&mut self) -> bool {
        let first = !self.hold_ended;
        self.hold_ended = true;
        first
    }

    /// A bridge alone back to fresh data after an episode: the hold's end
    /// forgotten, and the policy given meanwhile, if any, to apply now.
    pub fn resume(&mut self) -> Option<Policy> {
        self.hold_ended = false;
        self.deferred.take()
    }

    /// A new configuration with `new` policy while `current` applies: the one
    /// that applies now. During an episode a different policy is kept for
    /// the next one (switching in the middle of one could re-allow a
    /// discharge the inverter has already stopped).
    pub fn reconfigure(&mut self, current: Policy, new: Policy) -> Policy {
        if self.ongoing() && new != current {
            self.deferred = Some(new);
            current
        } else {
            self.deferred = None;
            new
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOLD: Policy = (StaleMode::Hold, 120);
    const STOP: Policy = (StaleMode::Stop, 0);

    #[test]
    fn an_episode_begins_once_and_ends_once() {
        let mut s = StaleEpisode::default();
        assert!(!s.ends());
        assert_eq!(s.stale_at(10), 10);
        assert_eq!(s.stale_at(20), 10, "still the episode of time 10");
        assert!(!s.starts(30));
        assert!(s.ends());
        assert!(!s.ongoing());
        assert!(s.starts(40));
        assert_eq!(s.stale_at(50), 40);
    }

    #[test]
    fn the_budget_and_the_stop_periods_belong_to_one_episode() {
        let b = |mah| HoldBudget {
            dcl_da: 100,
            budget_mah: mah,
            spend_us: 5,
        };
        let mut s = StaleEpisode::default();
        s.stale_at(0);
        assert_eq!(s.budget(|| b(7)).budget_mah, 7);
        assert_eq!(s.budget(|| b(9)).budget_mah, 7, "decided once");
        assert_eq!((s.stop_period(), s.stop_period()), (0, 1));
        assert!(s.ends());
        s.stale_at(10);
        assert_eq!(s.budget(|| b(9)).budget_mah, 9);
        assert_eq!(s.stop_period(), 0);
    }

    #[test]
    fn the_hold_ends_once_per_episode() {
        let mut s = StaleEpisode::default();
        s.stale_at(0);
        assert!(s.hold_ends());
        assert!(!s.hold_ends());
        assert!(s.ends());
        assert_eq!(s.resume(), None);
        s.stale_at(5);
        assert!(s.hold_ends(), "a new episode, a new hold");
    }

    #[test]
    fn a_policy_given_during_an_episode_waits_for_the_next() {
        let mut s = StaleEpisode::default();
        assert_eq!(s.reconfigure(HOLD, STOP), STOP, "no episode: at once");
        s.stale_at(0);
        assert_eq!(s.reconfigure(STOP, HOLD), STOP, "kept during the episode");
        assert_eq!(s.reconfigure(STOP, STOP), STOP);
        assert!(s.ends());
        assert_eq!(s.resume(), None, "given back: nothing deferred");
        s.stale_at(1);
        assert_eq!(s.reconfigure(STOP, HOLD), STOP);
        assert!(s.ends());
        assert_eq!(s.resume(), Some(HOLD));
        assert_eq!(s.resume(), None);
    }
}
