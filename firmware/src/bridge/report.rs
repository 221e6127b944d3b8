//! What the bridge tells the world: log-worthy happenings, each with a level.
//! Their words are [`crate::text::report`]'s: the chip shell logs that text with
//! `defmt`, the host simulator prints it ([`core::fmt::Display`]).

use protocol_core::events::{Event, OnlineStatus, Severity};
use protocol_core::frame::NackCode;
use protocol_core::settings::{Setting, SettingError};
use protocol_core::views::VersionInfo;

use crate::bms::checks::Check;
use crate::bms::link::{Failure, LinkStats};
use crate::bms::wire::{WireFigures, WireVerdict};

/// Log level of a report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Level {
    /// Routine.
    Info,
    /// Needs attention.
    Warn,
}

/// A compact summary of one live snapshot, for the log line.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct SnapshotLine {
    /// Volts.
    pub pack_v: f32,
    /// Amps.
    pub current_a: f32,
    /// Percent.
    pub soc_percent: f32,
    /// 1-based index of the lowest cell and its voltage in volts.
    pub min_cell: (u8, f32),
    /// 1-based index of the highest cell and its voltage in volts.
    pub max_cell: (u8, f32),
    /// Internal temperature, °C.
    pub internal_c: f32,
    /// External sensors, °C (`None` when disconnected).
    pub external_c: (Option<f32>, Option<f32>),
    /// Online status.
    pub status: OnlineStatus,
}

/// Result of one setting through the write/verify machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WriteOutcome {
    /// Written and read back equal (or 0xFFFF for 323/328).
    Verified,
    /// Already had the value: nothing written.
    Unchanged,
    /// Refused before any byte was sent.
    Rejected(SettingError),
    /// Written (ACKed) but the read-back differs.
    Mismatch {
        /// Raw value read back (first register).
        read_back: u16,
    },
    /// The BMS refused the write.
    Nacked(NackCode),
    /// Not written: the link failed before the write went out (the current value
    /// could not be read); the BMS keeps whatever it held.
    NotWritten(Failure),
    /// Not applied: the read-back after the write shows the old value.
    Failed(Failure),
    /// Written, but nothing could be read back: the next settings read decides
    /// (a [`Report::WriteFollowUp`] follows).
    Unconfirmed(Failure),
}

impl WriteOutcome {
    /// Short snake_case name.
    pub const fn name(&self) -> &'static str {
        match self {
            Self::Verified => "verified",
            Self::Unchanged => "unchanged",
            Self::Rejected(_) => "rejected",
            Self::Mismatch { .. } => "mismatch",
            Self::Nacked(_) => "nacked",
            Self::NotWritten(_) => "not_written",
            Self::Failed(_) => "failed",
            Self::Unconfirmed(_) => "unconfirmed",
        }
    }
    /// True for verified and unchanged: the BMS holds the value.
    pub const fn is_success(&self) -> bool {
        matches!(self, Self::Verified | Self::Unchanged)
    }
}

/// Everything the bridge reports.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Report {
    /// Periodic snapshot line.
    Snapshot(SnapshotLine),
    /// The online status changed.
    StatusChanged {
        /// Before (None at the first snapshot).
        from: Option<OnlineStatus>,
        /// Now.
        to: OnlineStatus,
    },
    /// An event not seen before.
    NewEvent(Event),
    /// The first events read after start-up: the log's recent history, in one line.
    EventHistory {
        /// Events in that first reply.
        count: u8,
        /// The newest of them.
        newest: Option<Event>,
    },
    /// A transaction failed.
    LinkError {
        /// Command code of the request.
        command: u8,
        /// Why.
        failure: Failure,
        /// Link errors not logged since the previous line (rate limit).
        suppressed: u32,
    },
    /// The BMS stopped answering.
    Offline {
        /// Consecutive failures.
        failures: u8,
    },
    /// The BMS answers again (version and settings are being re-read).
    Online,
    /// Version block read.
    Version(VersionInfo),
    /// Settings, their BMS limits and the version are known: telemetry is trusted.
    Ready {
        /// Cells configured (register 307).
        series_cells: u16,
    },
    /// Outcome of one setting.
    Write {
        /// The setting and value asked for.
        setting: Setting,
        /// What happened.
        outcome: WriteOutcome,
    },
    /// A reset was sent; whether register 114 confirmed a software reset.
    ResetDone {
        /// Register 114 low byte read 0x04 after the restart.
        confirmed: bool,
    },
    /// Events or statistics cleared (ACKed).
    Cleared {
        /// 0x01 events, 0x02 statistics.
        option: u8,
        /// ACKed.
        ok: bool,
    },
    /// Periodic link statistics.
    LinkStats(LinkStats),
    /// Reports were dropped because nobody drained the queue.
    Dropped(u32),
    /// The outcome of an earlier [`WriteOutcome::Unconfirmed`] write, from the
    /// settings read that followed.
    WriteFollowUp {
        /// The setting and value asked for.
        setting: Setting,
        /// Verified, failed (old value), mismatch, or still unconfirmed.
        outcome: WriteOutcome,
    },
    /// Snapshots are published flagged (`Some`): a live block failed a check and
    /// an independent second reply confirmed it (a broken sense wire, a cell at
    /// 0 V...). `None`: they pass every check again.
    Flagged(Option<Check>),
    /// Live blocks that failed a check and were not confirmed: not published.
    Refused {
        /// The last check failed.
        check: Option<Check>,
        /// Blocks refused since the previous line.
        count: u32,
    },
    /// How well replies get through (logged when anything failed in the period).
    LineQuality {
        /// Block read requests in the period.
        attempts: u32,
        /// Answered at the first send.
        clean: u32,
        /// Registers per request now (the live block is 56).
        piece_registers: u16,
        /// Snapshots published in the period.
        snapshots: u32,
    },
    /// The wire in the line quality period, when it is not healthy: the
    /// figures and what to check ([`crate::bms::wire`]).
    Wire {
        /// Damaged, lost and resent per thousand sends, valid replies.
        figures: WireFigures,
        /// What they say.
        verdict: WireVerdict,
    },
}

impl Report {
    /// Level under which it is logged.
    pub fn level(&self) -> Level {
        match self {
            Report::StatusChanged { to, .. } if *to == OnlineStatus::Fault => Level::Warn,
            Report::NewEvent(e)
                if matches!(e.id.severity(), Severity::Fault | Severity::Warning) =>
            {
                Level::Warn
            }
            Report::LinkError { .. } | Report::Offline { .. } | Report::Dropped(_) => Level::Warn,
            Report::Write { outcome, .. } | Report::WriteFollowUp { outcome, .. }
                if !outcome.is_success() =>
            {
                Level::Warn
            }
            Report::Flagged(Some(_)) | Report::Refused { .. } => Level::Warn,
            Report::LineQuality {
                attempts, clean, ..
            } if u64::from(*clean) * 10 < u64::from(*attempts) * 9 => Level::Warn,
            Report::Wire {
                verdict: WireVerdict::BadWire { .. } | WireVerdict::Silent,
                ..
            } => Level::Warn,
            Report::ResetDone { confirmed: false } | Report::Cleared { ok: false, .. } => {
                Level::Warn
            }
            _ => Level::Info,
        }
    }
}

/// `part` of `whole` in per mille (1000 when `whole` is 0: nothing failed). The
/// line quality figure, shared by the log of the chip and of the simulator.
pub fn permille(part: u32, whole: u32) -> u32 {
    if whole == 0 {
        1000
    } else {
        (u64::from(part) * 1000 / u64::from(whole)).min(1000) as u32
    }
}
