//! How lines reach a host port that may not take them: the writer's rule,
//! sans-IO. The chip's USB writer (`src/chip/usb.rs`) does the driver calls
//! this says; the desktop harness runs the same rule against ports that never
//! drain, drain a byte a second or fail at random
//! (`host-tests/tests/consumers_in_the_way.rs`).
//!
//! * A line is started only when its first byte fits (the port is tried for
//!   at most [`START_WAIT_US`] when the host was reading, once when not), and
//!   the rest gets [`LINE_WRITE_US`]. Nothing waits longer: what the station
//!   hands out meanwhile waits in a bounded pipe, and the station drops whole
//!   lines (counted) when that is full.
//! * A host that took nothing in that time is **absent**: its lines are
//!   dropped whole without touching the port, and one line every
//!   [`PROBE_PERIOD_US`] tries it again. When a line goes through, the host is
//!   back: the station sends `hello` and the current picture.
//! * A line cut by a timeout cannot be taken back (its start is in the port's
//!   FIFO): the next line that goes out starts with a newline, so the piece
//!   is a line of its own that a host rejects, and the count says so.
//!
//! Every dropped or cut line is counted ([`LineWriter::take_dropped`]) into
//! the host link's `dropped_lines`.

use crate::Instant;

/// Longest the writer waits for room to start a line while the host reads.
pub const START_WAIT_US: Instant = 20 * crate::MS;
/// Longest the rest of a started line may take: a line of
/// [`super::OUT_LINE_MAX`] bytes is 16 packets of 64 bytes, which a reading
/// host takes in 16 ms.
pub const LINE_WRITE_US: Instant = 100 * crate::MS;
/// An absent host is tried again this often.
pub const PROBE_PERIOD_US: Instant = crate::SECOND;

/// What to do with the line that is ready.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Start {
    /// Drop it whole: the host is absent (counted).
    Drop,
    /// Try to put the first byte in the port for at most `wait_us` (0: once),
    /// a newline before it when `newline_first` (a cut line to end), then
    /// report with [`LineWriter::started`].
    Try {
        /// How long to keep trying for room.
        wait_us: Instant,
        /// Write a `\n` before the line.
        newline_first: bool,
    },
}

/// The writer's state. See the module documentation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LineWriter {
    present: bool,
    cut: bool,
    next_probe: Instant,
    deadline: Instant,
    dropped: u32,
    back: bool,
}

impl LineWriter {
    /// A writer at start-up: nobody is known to read yet (the first line that
    /// goes through says a host is there).
    pub const fn new() -> Self {
        Self {
            present: false,
            cut: false,
            next_probe: 0,
            deadline: 0,
            dropped: 0,
            back: false,
        }
    }

    /// A host is taking lines.
    pub const fn present(&self) -> bool {
        self.present
    }

    /// A line is ready at `now`.
    pub fn line_ready(&mut self, now: Instant) -> Start {
        if !self.present {
            if now < self.next_probe {
                self.dropped = self.dropped.wrapping_add(1);
                return Start::Drop;
            }
            self.next_probe = now.saturating_add(PROBE_PERIOD_US);
        }
        Start::Try {
            wait_us: if self.present { START_WAIT_US } else { 0 },
            newline_first: self.cut,
        }
    }

    /// The first byte went in (`true`) or found no room; when it went in, the
    /// rest of the line must be written before the returned time.
    pub fn started(&mut self, now: Instant, ok: bool) -> Option<Instant> {
        if !ok {
            self.dropped = self.dropped.wrapping_add(1);
            self.gone(now);
            return None;
        }
        self.cut = false;
        if !self.present {
            self.present = true;
            self.back = true;
        }
        self.deadline = now.saturating_add(LINE_WRITE_US);
        Some(self.deadline)
    }

    /// The rest of the started line went out in time (`true`), or not: then
    /// the line is cut.
    pub fn finished(&mut self, now: Instant, ok: bool) {
        if !ok {
            self.dropped = self.dropped.wrapping_add(1);
            self.cut = true;
            self.gone(now);
        }
    }

    fn gone(&mut self, now: Instant) {
        self.present = false;
        self.next_probe = now.saturating_add(PROBE_PERIOD_US);
    }

    /// Lines dropped or cut since the last call.
    pub fn take_dropped(&mut self) -> u32 {
        core::mem::take(&mut self.dropped)
    }

    /// A host came (back) since the last call: it gets `hello`.
    pub fn take_back(&mut self) -> bool {
        core::mem::take(&mut self.back)
    }
}

impl Default for LineWriter {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{MS, SECOND};

    #[test]
    fn an_absent_host_costs_nothing_until_the_probe_and_a_cut_line_is_ended() {
        let mut w = LineWriter::new();
        // At start: one try, no waiting.
        assert_eq!(
            w.line_ready(0),
            Start::Try {
                wait_us: 0,
                newline_first: false
            }
        );
        assert_eq!(w.started(0, true), Some(LINE_WRITE_US));
        assert!(w.take_back());
        assert!(w.present());
        // The host stops reading in the middle of the next line.
        assert_eq!(
            w.line_ready(10 * MS),
            Start::Try {
                wait_us: START_WAIT_US,
                newline_first: false
            }
        );
        assert!(w.started(10 * MS, true).is_some());
        w.finished(110 * MS, false);
        assert!(!w.present());
        assert_eq!(w.take_dropped(), 1);
        // Absent: lines go without touching the port until the probe.
        for k in 0..9 {
            assert_eq!(w.line_ready(200 * MS + k * 100 * MS), Start::Drop);
        }
        assert_eq!(w.take_dropped(), 9);
        assert_eq!(
            w.line_ready(110 * MS + SECOND),
            Start::Try {
                wait_us: 0,
                newline_first: true
            }
        );
        // Still nobody: another second.
        assert_eq!(w.started(110 * MS + SECOND, false), None);
        assert_eq!(w.line_ready(110 * MS + SECOND + 1), Start::Drop);
        // Back: the cut line is ended first, and the host gets hello.
        assert_eq!(
            w.line_ready(110 * MS + 2 * SECOND),
            Start::Try {
                wait_us: 0,
                newline_first: true
            }
        );
        assert!(w.started(110 * MS + 2 * SECOND, true).is_some());
        assert!(w.take_back());
        assert_eq!(w.take_dropped(), 2);
        assert_eq!(
            w.line_ready(3 * SECOND),
            Start::Try {
                wait_us: START_WAIT_US,
                newline_first: false
            }
        );
    }
}
