//! The station's side of the queue to the host port's writer: a line goes in
//! whole or not at all.
//!
//! The queue on the chip is a ring buffer (`embassy_sync::pipe::Pipe`), and a
//! ring buffer's `try_write` takes only up to its wrap point: handing it a line
//! once and ignoring the count cut every line that crossed the wrap and fused
//! its start with the next line (seen on an emulated ESP32-C3: one telemetry
//! line in four). [`hand_off`] offers the rest until all of it is in, after
//! checking that all of it fits, so nothing is ever left half-written.
//! `host-tests/tests/host_queue.rs` runs it against the real pipe at every
//! wrap offset, and against a full one.

/// A byte queue that may take fewer bytes than it is offered.
pub trait ByteQueue {
    /// Bytes it can take now, in all (across its wrap point).
    fn free(&self) -> usize;
    /// Takes a prefix of `bytes` (possibly shorter: up to a wrap point);
    /// how many bytes it took, 0 when it took none.
    fn offer(&mut self, bytes: &[u8]) -> usize;
}

/// What became of a line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HandOff {
    /// All of it is in the queue.
    Whole,
    /// It does not fit: nothing of it went in (the caller keeps it or counts
    /// it dropped).
    NoRoom,
    /// The queue took less than it said it had room for (another writer took
    /// the room meanwhile): `taken` bytes went in, the rest did not. Never
    /// happens with one writer; counted as a dropped line when it does.
    Cut {
        /// Bytes of the line in the queue.
        taken: usize,
    },
}

/// Puts `line` in `queue` whole, or nothing of it when it does not fit.
pub fn hand_off(queue: &mut impl ByteQueue, line: &[u8]) -> HandOff {
    if queue.free() < line.len() {
        return HandOff::NoRoom;
    }
    let mut rest = line;
    while !rest.is_empty() {
        let n = queue.offer(rest);
        if n == 0 {
            return HandOff::Cut {
                taken: line.len() - rest.len(),
            };
        }
        rest = rest.get(n..).unwrap_or(&[]);
    }
    HandOff::Whole
}

/// The chip's queue (and the tests'): embassy-sync's pipe.
#[cfg(feature = "pipe")]
impl<M: embassy_sync::blocking_mutex::raw::RawMutex, const N: usize> ByteQueue
    for &embassy_sync::pipe::Pipe<M, N>
{
    fn free(&self) -> usize {
        self.free_capacity()
    }

    fn offer(&mut self, bytes: &[u8]) -> usize {
        self.try_write(bytes).unwrap_or(0)
    }
}
