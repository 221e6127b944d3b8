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
/// [`super::OUT_LINE_MAX`] bytes is 33 packets of 64 bytes, which a reading
/// host takes in 33 ms.
pub const LINE_WRITE_US: Instant = 100 * crate::MS;
/// An absent host is tried again this often.
pub const PROBE_PERIOD_US: Instant = crate::SECOND;
/// While a line waits to start, the port is tried for room this often.
pub const PROBE_STEP_US: Instant = crate::MS;
/// Bytes the writer takes from the queue at once (one USB packet).
pub const CHUNK: usize = 64;

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

/// Splits what the writer reads from the queue into pieces of lines: each
/// piece ends at a newline or at the end of what was read, and says whether
/// it starts a line and whether it ends one. The station hands out lines
/// whole, so once a line has begun its rest is in the queue already.
#[derive(Debug, Clone)]
pub struct Pieces {
    buf: [u8; CHUNK],
    start: usize,
    end: usize,
    at_line_start: bool,
}

/// One piece of a line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Piece<'a> {
    /// Its bytes (never empty).
    pub bytes: &'a [u8],
    /// It is the start of a line.
    pub starts_line: bool,
    /// It ends with the line's newline.
    pub ends_line: bool,
}

impl Pieces {
    /// Nothing read yet.
    pub const fn new() -> Self {
        Self {
            buf: [0; CHUNK],
            start: 0,
            end: 0,
            at_line_start: true,
        }
    }

    /// Where to read from the queue, when every piece read so far has been
    /// taken (then [`Pieces::filled`] says how many bytes came).
    pub fn space(&mut self) -> Option<&mut [u8]> {
        (self.start >= self.end).then_some(&mut self.buf[..])
    }

    /// Whether a piece is waiting (else read into [`Pieces::space`]).
    pub const fn has_piece(&self) -> bool {
        self.start < self.end
    }

    /// `n` bytes were read into [`Pieces::space`].
    pub fn filled(&mut self, n: usize) {
        self.start = 0;
        self.end = n.min(CHUNK);
    }

    /// The next piece, if any bytes are left.
    pub fn take(&mut self) -> Option<Piece<'_>> {
        let rest = self.buf.get(self.start..self.end).unwrap_or(&[]);
        if rest.is_empty() {
            return None;
        }
        let len = rest
            .iter()
            .position(|&b| b == b'\n')
            .map_or(rest.len(), |i| i + 1);
        let bytes = rest.get(..len).unwrap_or(&[]);
        self.start += len;
        let starts_line = self.at_line_start;
        let ends_line = bytes.last() == Some(&b'\n');
        self.at_line_start = ends_line;
        Some(Piece {
            bytes,
            starts_line,
            ends_line,
        })
    }
}

impl Default for Pieces {
    fn default() -> Self {
        Self::new()
    }
}

/// The rule of a writer on a port that always drains (UART0 to a USB-UART
/// bridge: it sends whether anyone listens): a write that fails or takes
/// longer than [`LINE_WRITE_US`] drops the rest of its line, which is then
/// ended with a newline (so the piece is a line of its own that a host
/// rejects), and the line counts as dropped.
#[derive(Debug, Clone, Default)]
pub struct DrainingPort {
    dropping: bool,
}

impl DrainingPort {
    /// Nothing dropped.
    pub const fn new() -> Self {
        Self { dropping: false }
    }

    /// Whether the current line's pieces are still written.
    pub const fn writing(&self) -> bool {
        !self.dropping
    }

    /// A write of the current line failed: its rest is dropped. True the
    /// first time (the newline that ends the cut line is written then).
    pub fn failed(&mut self) -> bool {
        !core::mem::replace(&mut self.dropping, true)
    }

    /// The current line's last piece went by: the lines dropped (0 or 1).
    pub fn line_ended(&mut self) -> u32 {
        u32::from(core::mem::take(&mut self.dropping))
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::{vec, vec::Vec};

    use super::*;
    use crate::{MS, SECOND};

    /// Every piece of every read, as the writer sees it.
    fn pieces_of(reads: &[&[u8]]) -> Vec<(Vec<u8>, bool, bool)> {
        let mut p = Pieces::new();
        let mut out = Vec::new();
        for r in reads {
            let space = p.space().expect("every piece taken");
            space[..r.len()].copy_from_slice(r);
            p.filled(r.len());
            while let Some(x) = p.take() {
                assert!(!x.bytes.is_empty());
                out.push((x.bytes.to_vec(), x.starts_line, x.ends_line));
            }
        }
        out
    }

    #[test]
    fn pieces_end_at_newlines_and_know_where_lines_start() {
        let got = pieces_of(&[b"{\"a\":1}\n{\"b\"", b":2}\n\n", b"x"]);
        let want: Vec<(Vec<u8>, bool, bool)> = vec![
            (b"{\"a\":1}\n".to_vec(), true, true),
            (b"{\"b\"".to_vec(), true, false),
            (b":2}\n".to_vec(), false, true),
            (b"\n".to_vec(), true, true),
            (b"x".to_vec(), true, false),
        ];
        assert_eq!(got, want);
        // Nothing read: nothing to write; a read of 0 bytes gives no piece.
        let mut p = Pieces::new();
        assert!(p.take().is_none());
        p.filled(0);
        assert!(p.take().is_none());
        assert!(p.space().is_some());
    }

    #[test]
    fn a_draining_port_drops_the_rest_of_a_failed_line_once() {
        let mut d = DrainingPort::new();
        assert!(d.writing());
        assert_eq!(d.line_ended(), 0);
        assert!(d.failed(), "the first failure ends the line with a newline");
        assert!(!d.writing());
        assert!(!d.failed(), "one newline per cut line");
        assert_eq!(d.line_ended(), 1);
        assert!(d.writing(), "the next line is written");
        assert_eq!(d.line_ended(), 0);
    }

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
