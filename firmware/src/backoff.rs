//! How long to wait before trying a connection again, sans-IO: the first
//! retry after [`BACKOFF_MIN_US`], each failure doubles the wait up to
//! [`BACKOFF_MAX_US`], and a connection that held at least that long starts
//! the waits over. The MQTT session and the chip's Wi-Fi task both go by it,
//! so a lost network and a lost broker are retried alike.

use crate::{Instant, SECOND};

/// First wait.
pub const BACKOFF_MIN_US: Instant = SECOND;
/// Longest wait; a connection up this long counts as having held.
pub const BACKOFF_MAX_US: Instant = 60 * SECOND;

/// The waits between tries. See the module documentation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Backoff {
    next_us: Instant,
}

impl Default for Backoff {
    fn default() -> Self {
        Self::new()
    }
}

impl Backoff {
    /// Before the first failure.
    pub const fn new() -> Self {
        Self {
            next_us: BACKOFF_MIN_US,
        }
    }

    /// The wait before the next try, µs (what a log line says).
    pub const fn next_us(&self) -> Instant {
        self.next_us
    }

    /// A try failed or a connection ended: the wait before the next try, µs;
    /// the one after is twice as long, up to [`BACKOFF_MAX_US`].
    pub fn wait(&mut self) -> Instant {
        let w = self.next_us;
        self.next_us = w.saturating_mul(2).min(BACKOFF_MAX_US);
        w
    }

    /// A connection ended after it was up `up_for_us`: one that held at least
    /// [`BACKOFF_MAX_US`] starts the waits over.
    pub fn ended_after(&mut self, up_for_us: Instant) {
        if up_for_us >= BACKOFF_MAX_US {
            self.next_us = BACKOFF_MIN_US;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn waits_double_to_the_longest_and_a_held_connection_starts_over() {
        let mut b = Backoff::new();
        let waits: [Instant; 8] = core::array::from_fn(|_| b.wait() / SECOND);
        assert_eq!(waits, [1, 2, 4, 8, 16, 32, 60, 60]);
        // A connection that dropped soon keeps the long wait.
        b.ended_after(BACKOFF_MAX_US - 1);
        assert_eq!(b.wait(), BACKOFF_MAX_US);
        // One that held starts over.
        b.ended_after(BACKOFF_MAX_US);
        assert_eq!(b.next_us(), BACKOFF_MIN_US);
        assert_eq!(b.wait(), BACKOFF_MIN_US);
        assert_eq!(b.wait(), 2 * SECOND);
    }
}
