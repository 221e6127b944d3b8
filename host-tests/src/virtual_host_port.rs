//! The host link's port in virtual time, as the chip's writer task drives it:
//! the station puts whole lines into a bounded pipe (only when one fits whole,
//! as `src/chip/station.rs` does), and the writer takes them out under the
//! library's rule ([`tinybms_firmware::host_link::writer::LineWriter`]) into a
//! 64-byte FIFO that the host drains at its own pace — or never. What the host
//! receives is kept, so a test can check that every line it got is whole.

use std::collections::VecDeque;

use tinybms_firmware::host_link::writer::{LineWriter, Start};
use tinybms_firmware::host_link::OUT_LINE_MAX;
use tinybms_firmware::station::Station;

/// The port's FIFO (the USB-Serial-JTAG's IN endpoint), bytes.
pub const FIFO_BYTES: usize = 64;
/// The pipe between the station and the writer, bytes (as on the chip).
pub const PIPE_BYTES: usize = 2 * OUT_LINE_MAX;
/// How often the writer looks for room while it waits, µs (as on the chip).
pub const PROBE_STEP_US: u64 = 1_000;

/// How the host takes bytes out of the FIFO.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Drain {
    /// As fast as they come (a terminal that reads).
    All,
    /// Never (a USB charger, a closed terminal).
    Never,
    /// This many bytes a second.
    BytesPerSecond(u64),
    /// As fast as they come, but each attempt to start a line finds no room
    /// with this probability (a host that reads in fits).
    Fits(f64),
}

/// The port. See the module documentation.
#[derive(Debug, Clone)]
pub struct HostPort {
    /// How the host drains.
    pub drain: Drain,
    writer: LineWriter,
    pipe: VecDeque<Vec<u8>>,
    pipe_bytes: usize,
    /// The writer task's own clock: it is busy until then.
    writer_at: u64,
    /// Bytes in the FIFO, and when the host last took some.
    fifo: usize,
    drained_at: u64,
    /// Everything the host received.
    pub received: Vec<u8>,
    /// Lines the writer dropped or cut.
    pub dropped: u64,
    /// A writer that waits by spinning (the CPU is its while it waits for
    /// room), as a driver that re-polls a flag in a loop would: the station
    /// cannot run meanwhile. Off: the writer waits on the port's interrupt
    /// and a timer, as the chip's does. (On only to show that the tests see
    /// the difference.)
    pub spins: bool,
    /// Without the library's bounds: the writer waits as long as it takes.
    pub unbounded: bool,
    busy_us: u64,
    rng: u64,
}

impl HostPort {
    /// A port whose host drains as `drain` says.
    pub fn new(drain: Drain, seed: u64) -> Self {
        Self {
            drain,
            writer: LineWriter::new(),
            pipe: VecDeque::new(),
            pipe_bytes: 0,
            writer_at: 0,
            fifo: 0,
            drained_at: 0,
            received: Vec::new(),
            dropped: 0,
            spins: false,
            unbounded: false,
            busy_us: 0,
            rng: seed | 1,
        }
    }

    /// What the host has taken out of the FIFO by `t`.
    fn drain_to(&mut self, t: u64) {
        let t = t.max(self.drained_at);
        let can = match self.drain {
            Drain::All | Drain::Fits(_) => self.fifo,
            Drain::Never => 0,
            Drain::BytesPerSecond(n) => ((t - self.drained_at) * n / 1_000_000) as usize,
        };
        let took = can.min(self.fifo);
        if took > 0 || !matches!(self.drain, Drain::BytesPerSecond(_)) {
            self.drained_at = t;
        }
        self.fifo -= took;
    }

    fn room(&mut self, t: u64, first: bool) -> bool {
        self.drain_to(t);
        if let (Drain::Fits(p), true) = (self.drain, first) {
            // xorshift64
            self.rng ^= self.rng << 13;
            self.rng ^= self.rng >> 7;
            self.rng ^= self.rng << 17;
            if (self.rng >> 11) as f64 / (1u64 << 53) as f64 <= p {
                return false;
            }
        }
        self.fifo < FIFO_BYTES
    }

    /// Puts one byte in the FIFO at `t` when there is room (`first`: the
    /// first of a line, which a host reading in fits may refuse).
    fn put(&mut self, t: u64, b: u8, first: bool) -> bool {
        if !self.room(t, first) {
            return false;
        }
        self.fifo += 1;
        self.received.push(b);
        true
    }

    /// Runs the writer up to `now` and moves the station's lines into the pipe
    /// while one fits whole (the chip's `hand_out`), then tells the station what
    /// the writer dropped and whether a host came back. Returns for how long
    /// a spinning writer kept the CPU (0 unless [`HostPort::spins`]).
    pub fn pump(&mut self, now: u64, station: &mut Station) -> u64 {
        self.run_writer(now);
        let mut buf = [0u8; OUT_LINE_MAX];
        while PIPE_BYTES - self.pipe_bytes >= OUT_LINE_MAX {
            let Some(n) = station.next_host_line(now, &mut buf) else {
                break;
            };
            self.pipe_bytes += n;
            self.pipe.push_back(buf[..n].to_vec());
        }
        self.run_writer(now);
        let dropped = self.writer.take_dropped();
        if dropped > 0 {
            self.dropped += u64::from(dropped);
            station.host_lines_dropped(dropped);
        }
        if self.writer.take_back() {
            station.host_connected(now);
        }
        std::mem::take(&mut self.busy_us)
    }

    /// The writer task: every line it could have started by `now`.
    fn run_writer(&mut self, now: u64) {
        while self.writer_at <= now {
            let Some(line) = self.pipe.pop_front() else {
                self.writer_at = now;
                return;
            };
            self.pipe_bytes -= line.len();
            let t0 = self.writer_at;
            self.writer_at = self.write_line(t0, &line);
        }
    }

    /// Writes one line from `t` on; when the writer is done with it.
    fn write_line(&mut self, t: u64, line: &[u8]) -> u64 {
        let Start::Try {
            wait_us,
            newline_first,
        } = self.writer.line_ready(t)
        else {
            return t;
        };
        let first = if newline_first { b'\n' } else { line[0] };
        let mut at = t;
        let ok = loop {
            if self.put(at, first, true) {
                break true;
            }
            if at >= t + wait_us && !self.unbounded {
                break false;
            }
            if self.unbounded && at > t + 3_600_000_000 {
                break false; // an hour: the test is over anyway
            }
            at += PROBE_STEP_US;
        };
        let Some(deadline) = self.writer.started(at, ok) else {
            return self.done(t, at);
        };
        let rest = if newline_first { line } else { &line[1..] };
        for &b in rest {
            loop {
                if self.put(at, b, false) {
                    break;
                }
                // Wait for the host to take some (as the driver's interrupt).
                let step = match self.drain {
                    Drain::BytesPerSecond(n) => 1_000_000 / n.max(1),
                    _ => PROBE_STEP_US,
                };
                at += step;
                if at > deadline && !self.unbounded {
                    self.writer.finished(deadline, false);
                    return self.done(t, deadline);
                }
                if at > t + 3_600_000_000 {
                    self.writer.finished(at, false);
                    return self.done(t, at);
                }
            }
        }
        self.writer.finished(at, true);
        self.done(t, at)
    }

    /// The line took the writer from `t` to `end`; a spinning writer had the
    /// CPU for all of it.
    fn done(&mut self, t: u64, end: u64) -> u64 {
        if self.spins {
            self.busy_us += end - t;
        }
        end
    }

    /// The lines the host received (split at newlines; the last one only when
    /// ended).
    pub fn lines(&self) -> Vec<&[u8]> {
        let mut out: Vec<&[u8]> = self.received.split(|&b| b == b'\n').collect();
        out.pop();
        out
    }
}
