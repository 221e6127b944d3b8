//! What a shell around the station goes by between its tasks' queues: how
//! long it may sleep (so the watchdog is fed), the host lines it hands the
//! port's writer (whole ones only: [`crate::host_link::queue`]), and what the
//! CAN task reports ([`CanDone`]). The chip's station task
//! (`src/chip/station.rs`) calls these; the tests run them against
//! embassy-sync's pipe, the chip's queue.

use super::Station;
use crate::host_link::queue::{hand_off, ByteQueue, HandOff};
use crate::host_link::OUT_LINE_MAX;
use crate::inverter::port::CanDone;
use crate::inverter::TxResult;
use crate::{Instant, MS, SECOND};

/// The chip's watchdog: a station task that has not come round for this
/// long resets the chip.
pub const WATCHDOG_US: Instant = 4 * SECOND;

/// Longest the station task sleeps without coming round (and feeding the
/// watchdog), whatever the station's own wake time.
pub const MAX_WAIT_US: Instant = 500 * MS;

/// Hands `queue` every line `next` gives while the longest fits, each whole
/// (`buf` holds one line); the lines handed over and those the queue did
/// not take whole (dropped).
pub(super) fn hand_out(
    queue: &mut impl ByteQueue,
    buf: &mut [u8; OUT_LINE_MAX],
    mut next: impl FnMut(&mut [u8]) -> Option<usize>,
) -> (u32, u32) {
    let (mut lines, mut dropped) = (0, 0);
    // A line is taken from the link only when the longest fits.
    while queue.free() >= buf.len() {
        let Some(n) = next(buf) else {
            break;
        };
        match hand_off(queue, buf.get(..n).unwrap_or(&[])) {
            HandOff::Whole => lines += 1,
            HandOff::NoRoom | HandOff::Cut { .. } => dropped += 1,
        }
    }
    (lines, dropped)
}

/// When to wake: the station's time, but never later than [`MAX_WAIT_US`]
/// from now.
pub const fn bounded_wait(until: Instant, now: Instant) -> Instant {
    let cap = now.saturating_add(MAX_WAIT_US);
    if until < cap {
        until
    } else {
        cap
    }
}

impl Station {
    /// Hands the port's writer every host line there is room for, each whole
    /// (`buf` holds one line: [`OUT_LINE_MAX`] bytes). A line the queue did
    /// not take whole is counted dropped. Returns the lines handed over.
    pub fn hand_out_host_lines(
        &mut self,
        now: Instant,
        queue: &mut impl ByteQueue,
        buf: &mut [u8; OUT_LINE_MAX],
    ) -> u32 {
        let (lines, dropped) = hand_out(queue, buf, |b| self.next_host_line(now, b));
        if dropped > 0 {
            self.host_lines_dropped(dropped);
        }
        lines
    }

    /// What the CAN task reports of the last command.
    pub fn can_done(&mut self, now: Instant, done: CanDone) {
        match done {
            CanDone::Sent => self.can_sent(now, TxResult::Sent),
            CanDone::Failed => self.can_sent(now, TxResult::Failed),
            CanDone::BusOff => self.can_bus_off(now),
            CanDone::Recovered(ok) => self.can_recovered(now, ok),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_station_task_comes_round_well_inside_the_watchdog() {
        assert!(4 * MAX_WAIT_US <= WATCHDOG_US);
        assert_eq!(bounded_wait(100, 0), 100);
        assert_eq!(bounded_wait(10 * SECOND, 0), MAX_WAIT_US);
        assert_eq!(bounded_wait(Instant::MAX, Instant::MAX - 1), Instant::MAX);
        assert_eq!(bounded_wait(0, 5 * SECOND), 0, "a time past is now");
    }
}
