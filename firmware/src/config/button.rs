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
