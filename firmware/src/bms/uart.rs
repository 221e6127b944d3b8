//! The UART to the TinyBMS as the chip shell sets it up and reads it: its
//! rate, the receive FIFO's interrupt level, how many reads drain it at a
//! deadline, and what becomes of the driver's receive errors (counted, logged
//! at most once a [`super::timing::LINK_ERROR_LOG_PERIOD_US`]). The driver's
//! calls are the shell's (`src/chip/station.rs`); the numbers are decided here.

use super::timing::{BYTE_TIME_US, LINK_ERROR_LOG_PERIOD_US};
use crate::Instant;

/// The TinyBMS's rate, 8N1 (Rev D §1; 8N1 is the ESP UART driver's default
/// frame format).
pub const BAUD: u32 = 115_200;

/// Bytes the ESP32's UART receive FIFO holds.
pub const RX_FIFO_BYTES: u16 = 128;

/// The receive FIFO's "full" interrupt level, bytes. The driver's default
/// (120) leaves 8 bytes, 0.7 ms, between the interrupt and an overflow, and
/// replies longer than 120 bytes exist (a 0x03 read of 58 registers or more,
/// packetized events); an overflow resets the FIFO: a CRC error and a retry.
/// At 64 the station task has 64 bytes, 5.5 ms, to read.
pub const RX_FIFO_FULL_THRESHOLD: u16 = 64;

/// Most driver reads that drain the FIFO when the station's deadline wins
/// the race against a read (bytes below the FIFO's interrupt level that its
/// receive timeout has not signalled yet go in before the deadline is
/// handled). The bound only guards against a line that keeps delivering: one
/// read takes the whole 128-byte FIFO.
pub const DEADLINE_DRAIN_READS: usize = 4;

/// The time the station task has to read the FIFO once its interrupt fired.
pub const fn fifo_margin_us() -> Instant {
    (RX_FIFO_BYTES - RX_FIFO_FULL_THRESHOLD) as Instant * BYTE_TIME_US
}

/// Why [`write_all`] stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WriteError<E> {
    /// The driver's error.
    Driver(E),
    /// The driver took nothing of a non-empty buffer (a broken driver: the
    /// rest is dropped rather than tried for ever).
    TookNothing,
}

/// Writes all of `bytes` through a driver's `write`, which may take only a
/// part of what it is given; stops at the driver's first error, or at a write
/// that takes nothing.
pub async fn write_all<E>(
    bytes: &[u8],
    mut write: impl AsyncFnMut(&[u8]) -> Result<usize, E>,
) -> Result<(), WriteError<E>> {
    let mut rest = bytes;
    while !rest.is_empty() {
        match write(rest).await {
            Ok(0) => return Err(WriteError::TookNothing),
            Ok(n) => rest = rest.get(n..).unwrap_or(&[]),
            Err(e) => return Err(WriteError::Driver(e)),
        }
    }
    Ok(())
}

/// The driver's receive errors (overflow, framing, parity, noise): counted
/// as they happen, logged when the station logs (never while a reply is
/// arriving) and at most once a [`LINK_ERROR_LOG_PERIOD_US`], with the count
/// so far. `E` is the driver's error (its words are the driver's).
#[derive(Debug, Clone, Copy)]
pub struct RxErrors<E> {
    count: u32,
    last: Option<E>,
    next_log: Instant,
}

impl<E: Copy> RxErrors<E> {
    /// None yet.
    pub const fn new() -> Self {
        Self {
            count: 0,
            last: None,
            next_log: 0,
        }
    }

    /// One error.
    pub fn record(&mut self, e: E) {
        self.count = self.count.wrapping_add(1);
        self.last = Some(e);
    }

    /// The error to log now, with the count so far, if one is waiting and
    /// the period allows it.
    pub fn due(&mut self, now: Instant) -> Option<(E, u32)> {
        let e = self.last?;
        if now < self.next_log {
            return None;
        }
        self.next_log = now.saturating_add(LINK_ERROR_LOG_PERIOD_US);
        self.last = None;
        Some((e, self.count))
    }
}

impl<E: Copy> Default for RxErrors<E> {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{MS, SECOND};

    #[test]
    fn the_fifo_leaves_over_five_ms_and_a_whole_reply_of_live_data_is_read_in_pieces() {
        assert!(fifo_margin_us() >= 5 * MS);
        assert!(RX_FIFO_FULL_THRESHOLD < RX_FIFO_BYTES);
        // A 56-register live reply (117 bytes) fits the drain's reads.
        assert!(DEADLINE_DRAIN_READS * RX_FIFO_BYTES as usize >= 117);
    }

    extern crate std;
    use std::vec::Vec;

    #[test]
    fn every_byte_goes_through_partial_writes_and_a_stuck_driver_ends_it() {
        let bytes: Vec<u8> = (0..=255u8).collect();
        for take in 1..=9usize {
            let mut got = Vec::new();
            let r = embassy_futures::block_on(write_all(&bytes, async |b: &[u8]| {
                let n = b.len().min(take);
                got.extend_from_slice(&b[..n]);
                Ok::<usize, ()>(n)
            }));
            assert_eq!(r, Ok(()));
            assert_eq!(got, bytes);
        }
        let r = embassy_futures::block_on(write_all(&bytes, async |_: &[u8]| Ok::<usize, ()>(0)));
        assert_eq!(r, Err(WriteError::TookNothing));
        let mut calls = 0;
        let r = embassy_futures::block_on(write_all(&bytes, async |b: &[u8]| {
            calls += 1;
            if calls == 3 {
                Err(7)
            } else {
                Ok(b.len().min(10))
            }
        }));
        assert_eq!(r, Err(WriteError::Driver(7)));
        assert_eq!(
            embassy_futures::block_on(write_all(&[], async |_: &[u8]| Err::<usize, u8>(1))),
            Ok(())
        );
    }

    #[test]
    fn errors_are_counted_always_and_logged_once_a_period() {
        let mut r = RxErrors::<u8>::new();
        assert_eq!(r.due(0), None);
        r.record(1);
        r.record(2);
        assert_eq!(r.due(0), Some((2, 2)), "the last one, with the count");
        r.record(3);
        assert_eq!(r.due(SECOND), None, "inside the period");
        assert_eq!(r.due(LINK_ERROR_LOG_PERIOD_US), Some((3, 3)));
        assert_eq!(r.due(3 * LINK_ERROR_LOG_PERIOD_US), None, "nothing new");
    }
}
