//! The way out of read-only that needs no computer: hold the board's BOOT
//! button down for [`UNLOCK_HOLD_US`] while the bridge runs. Read-only is then
//! lifted, now and in flash ([`super::state::ConfigState::unlock`]).
//!
//! (Holding BOOT *while the chip resets* starts the ROM's download mode
//! instead — the way to flash it — so the button is read only once the
//! firmware runs; `erase-region` of the store is the other way out, see the
//! docs/configuration.md.)
//!
//! The shell samples the button every [`SAMPLE_PERIOD_US`]; a press that
//! lets go, or a sample that is missed for longer than two periods, starts
//! the count again, so a bouncing contact or a stalled task never unlocks.

use crate::{Instant, MS, SECOND};

/// How long the button must be held.
pub const UNLOCK_HOLD_US: Instant = 5 * SECOND;

/// How often the shell reads the button.
pub const SAMPLE_PERIOD_US: Instant = 50 * MS;

/// Counts how long the button has been held.
#[derive(Debug, Clone, Default)]
pub struct Hold {
    /// Held since (the first sample of this press).
    since: Option<Instant>,
    /// The last sample.
    last: Option<Instant>,
    /// This press has unlocked already.
    fired: bool,
}

impl Hold {
    /// Not held.
    pub const fn new() -> Self {
        Self {
            since: None,
            last: None,
            fired: false,
        }
    }

    /// One sample at `now`: `pressed` or not. True once per press, when it has
    /// been held for [`UNLOCK_HOLD_US`].
    pub fn sample(&mut self, now: Instant, pressed: bool) -> bool {
        let gap = self
            .last
            .is_some_and(|t| now.saturating_sub(t) > 2 * SAMPLE_PERIOD_US);
        self.last = Some(now);
        if !pressed || gap {
            self.since = pressed.then_some(now);
            self.fired = false;
            return false;
        }
        let since = *self.since.get_or_insert(now);
        if !self.fired && now.saturating_sub(since) >= UNLOCK_HOLD_US {
            self.fired = true;
            return true;
        }
        false
    }
}

/// Which of the shell's samples reach the station: every one while the button
/// is down, and the one that says it came up, so that a button nobody touches
/// never wakes the station.
#[derive(Debug, Clone, Copy, Default)]
pub struct Samples {
    was_pressed: bool,
}

impl Samples {
    /// Not pressed.
    pub const fn new() -> Self {
        Self { was_pressed: false }
    }

    /// A sample: `Some(pressed)` when the station should hear it.
    pub fn take(&mut self, pressed: bool) -> Option<bool> {
        let heard = (pressed || self.was_pressed).then_some(pressed);
        self.was_pressed = pressed;
        heard
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_pressed_button_and_its_release_reach_the_station() {
        let mut s = Samples::new();
        assert_eq!(s.take(false), None);
        assert_eq!(s.take(true), Some(true));
        assert_eq!(s.take(true), Some(true));
        assert_eq!(s.take(false), Some(false), "the release, once");
        assert_eq!(s.take(false), None);
    }

    #[test]
    fn samples_held_long_enough_unlock_once() {
        let mut s = Samples::new();
        let mut h = Hold::new();
        let mut unlocked = 0;
        for i in 0..200u64 {
            if let Some(p) = s.take(i < 150) {
                unlocked += u32::from(h.sample(i * SAMPLE_PERIOD_US, p));
            }
        }
        assert_eq!(unlocked, 1, "7.5 s held: one unlock");
    }
}
