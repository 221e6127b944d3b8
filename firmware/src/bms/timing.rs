//! The link's and the poll schedule's timing: every default as a named, documented
//! constant, and [`Timing`], the run-time set the bridge is built with.

use crate::{Instant, MS, SECOND};

/// Wire time of one byte at 115200 8N1 (10 bits), rounded up: 86.8 µs.
pub const BYTE_TIME_US: Instant = 87;

/// How long to wait for the complete reply after the last request byte left.
/// HARDWARE-NOTES: the BMS answers 1-2 ms after the request; the reply's own wire
/// time is added on top (a 56-register 0x03 reply is 117 bytes = 10.2 ms).
pub const RESPONSE_TIMEOUT_US: Instant = 100 * MS;

/// Response timeout of a piece (a 0x09 read of at most 15 registers, only used
/// on a bad line): the BMS answers 1-2 ms after the request (HARDWARE-NOTES) and
/// such a reply takes at most 6 ms on the wire; waiting 100 ms for an answer that
/// was lost would cost more than the read itself.
pub const PIECE_RESPONSE_TIMEOUT_US: Instant = 30 * MS;

/// Live pieces sent per piece of another block read when both are in progress
/// (the live data keeps flowing while statistics or the event log are read).
pub const LIVE_SHARE: u8 = 6;

/// Live pieces sent per piece of another block read while the live data is
/// overdue (see [`live_overdue_after_us`]): on a bad line the other reads
/// (statistics, the event log, settings, writes) still get a turn, but the
/// live read gets most of the line until a snapshot is in (issue 54).
pub const LIVE_SHARE_OVERDUE: u8 = 30;

/// The live data is never overdue sooner than this after the last snapshot.
pub const LIVE_OVERDUE_MIN_US: Instant = 2 * SECOND;

/// When the live data is overdue: twice the usual time between snapshots
/// (`typical_us`, a running mean), at least [`LIVE_OVERDUE_MIN_US`]. Only a
/// read that takes unusually long gets the line: at a fault rate of 0.1 a
/// snapshot takes 3-4 s, and a fixed 2 s would keep the statistics read,
/// which never ends there, taking the event log's turns.
pub const fn live_overdue_after_us(typical_us: Instant) -> Instant {
    let twice = typical_us.saturating_mul(2);
    if twice > LIVE_OVERDUE_MIN_US {
        twice
    } else {
        LIVE_OVERDUE_MIN_US
    }
}

/// After a (re)sync, how long the first snapshot has the link to itself before
/// the event log and statistics reads start.
pub const FIRST_SNAPSHOT_PRIORITY_US: Instant = 10 * SECOND;

/// Once bytes of a reply have started to arrive, this much silence ends the
/// attempt early (a corrupt reply need not wait for the full timeout). Replies
/// stream back to back: 10 ms is over 100 byte times.
pub const REPLY_IDLE_GAP_US: Instant = 10 * MS;

/// As [`REPLY_IDLE_GAP_US`], for a piece (a 0x09 read of at most 15
/// registers: a reply of at most 63 bytes, below the UART's 64-byte receive
/// FIFO level, so the chip's driver hands it over in one go at its receive
/// timeout). On a bad line a reply that lost a byte or was cut short waited
/// 10 ms for bytes that never come; 4 ms is still 46 byte times (issue 54:
/// at fault rate 0.05 a snapshot every 0.96 s instead of 1.23 s).
pub const PIECE_REPLY_IDLE_GAP_US: Instant = 4 * MS;

/// Retries of a read after a failed attempt (CRC error, timeout after the wake-up
/// resend, bad length). Writes follow the same count but are never re-sent after
/// an ACK or a NACK.
pub const MAX_RETRIES: u8 = 2;

/// Consecutive silent transactions (each: request, wake-up resend and retries all
/// unanswered) after which the BMS is considered offline.
pub const OFFLINE_AFTER_FAILURES: u8 = 3;

/// Probe period while offline.
pub const OFFLINE_PROBE_PERIOD_US: Instant = 2 * SECOND;

/// Link errors are logged at most once per this period; the line says how many
/// were not logged in between (the log stays readable on a noisy line).
pub const LINK_ERROR_LOG_PERIOD_US: Instant = 10 * SECOND;

/// Period of the live block read (registers 0-55, one 0x03 request).
pub const LIVE_PERIOD_US: Instant = 250 * MS;

/// Period of the statistics read (registers 100-117).
pub const STATS_PERIOD_US: Instant = 30 * SECOND;

/// Period of the newest-events read (0x11).
pub const EVENTS_PERIOD_US: Instant = 5 * SECOND;

/// Longest a live block assembled from pieces may take, first piece to last:
/// on a bad line the pieces of one snapshot are all asked for within this
/// window (the oldest are read again until they are), so a snapshot never
/// mixes values further apart.
pub const LIVE_ASSEMBLY_WINDOW_US: Instant = 5 * SECOND;

/// Period of the line quality line in the log (only logged when something failed).
pub const LINE_QUALITY_LOG_PERIOD_US: Instant = 60 * SECOND;

/// Period of the snapshot info line in the log.
pub const SNAPSHOT_LOG_PERIOD_US: Instant = 10 * SECOND;

/// Period of the link statistics line in the log.
pub const LINK_STATS_LOG_PERIOD_US: Instant = 5 * 60 * SECOND;

/// Pause between a write's ACK and its read-back (HARDWARE-NOTES: one client saw
/// the next read time out after a write; EEPROM write in progress?).
pub const WRITE_SETTLE_US: Instant = 200 * MS;

/// Wait after a write to register 340 or a reset before talking to the BMS again
/// (it restarts; HARDWARE-NOTES: expect a communication gap).
pub const REBOOT_WAIT_US: Instant = 3 * SECOND;

/// Attempts to read back after a reboot (each with its own wake-up and retries).
pub const REBOOT_READBACK_ATTEMPTS: u8 = 5;

/// Most settings in one group given to the write/verify machine.
pub const MAX_SETTINGS_GROUP: usize = 16;

/// Queued commands (profile, resets, ...).
pub const COMMAND_QUEUE: usize = 4;

/// Pending reports before the oldest is dropped (and counted).
pub const REPORT_QUEUE: usize = 24;

/// Run-time configuration; [`Default`] gives the constants above.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Timing {
    /// See [`RESPONSE_TIMEOUT_US`].
    pub response_timeout_us: Instant,
    /// See [`PIECE_RESPONSE_TIMEOUT_US`].
    pub piece_response_timeout_us: Instant,
    /// See [`REPLY_IDLE_GAP_US`].
    pub reply_idle_gap_us: Instant,
    /// See [`PIECE_REPLY_IDLE_GAP_US`].
    pub piece_reply_idle_gap_us: Instant,
    /// See [`MAX_RETRIES`].
    pub max_retries: u8,
    /// See [`OFFLINE_AFTER_FAILURES`].
    pub offline_after_failures: u8,
    /// See [`OFFLINE_PROBE_PERIOD_US`].
    pub offline_probe_period_us: Instant,
    /// See [`LINK_ERROR_LOG_PERIOD_US`].
    pub link_error_log_period_us: Instant,
    /// See [`LIVE_PERIOD_US`].
    pub live_period_us: Instant,
    /// See [`STATS_PERIOD_US`].
    pub stats_period_us: Instant,
    /// See [`EVENTS_PERIOD_US`].
    pub events_period_us: Instant,
    /// See [`LIVE_ASSEMBLY_WINDOW_US`] (at least the live period is used).
    pub live_assembly_window_us: Instant,
    /// See [`LINE_QUALITY_LOG_PERIOD_US`].
    pub line_quality_log_period_us: Instant,
    /// See [`SNAPSHOT_LOG_PERIOD_US`]; 0 logs every snapshot.
    pub snapshot_log_period_us: Instant,
    /// See [`LINK_STATS_LOG_PERIOD_US`].
    pub link_stats_log_period_us: Instant,
    /// See [`WRITE_SETTLE_US`].
    pub write_settle_us: Instant,
    /// See [`REBOOT_WAIT_US`].
    pub reboot_wait_us: Instant,
}

impl Default for Timing {
    fn default() -> Self {
        Self {
            response_timeout_us: RESPONSE_TIMEOUT_US,
            piece_response_timeout_us: PIECE_RESPONSE_TIMEOUT_US,
            reply_idle_gap_us: REPLY_IDLE_GAP_US,
            piece_reply_idle_gap_us: PIECE_REPLY_IDLE_GAP_US,
            max_retries: MAX_RETRIES,
            offline_after_failures: OFFLINE_AFTER_FAILURES,
            offline_probe_period_us: OFFLINE_PROBE_PERIOD_US,
            link_error_log_period_us: LINK_ERROR_LOG_PERIOD_US,
            live_period_us: LIVE_PERIOD_US,
            stats_period_us: STATS_PERIOD_US,
            events_period_us: EVENTS_PERIOD_US,
            live_assembly_window_us: LIVE_ASSEMBLY_WINDOW_US,
            line_quality_log_period_us: LINE_QUALITY_LOG_PERIOD_US,
            snapshot_log_period_us: SNAPSHOT_LOG_PERIOD_US,
            link_stats_log_period_us: LINK_STATS_LOG_PERIOD_US,
            write_settle_us: WRITE_SETTLE_US,
            reboot_wait_us: REBOOT_WAIT_US,
        }
    }
}
