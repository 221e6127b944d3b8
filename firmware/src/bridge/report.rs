//! What the bridge tells the world: log-worthy happenings, each with a level.
//! The chip shell turns them into `defmt` lines; the host simulator prints them
//! with [`core::fmt::Display`] in the same words.

use core::fmt;

use protocol_core::events::{Event, OnlineStatus, Severity};
use protocol_core::frame::NackCode;
use protocol_core::settings::{Setting, SettingError, SettingId};
use protocol_core::views::VersionInfo;

use crate::bms::checks::Check;
use crate::bms::link::{Failure, LinkStats};

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
            Report::ResetDone { confirmed: false } | Report::Cleared { ok: false, .. } => {
                Level::Warn
            }
            _ => Level::Info,
        }
    }
}

/// A document name, or `unknown_0xNN` for a value no table knows (one style
/// everywhere: the log, `replay`, the simulator).
struct Name(&'static str, Option<u16>);

impl fmt::Display for Name {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.1 {
            Some(raw) => write!(f, "unknown_0x{raw:02X}"),
            None => f.write_str(self.0),
        }
    }
}

fn status(s: OnlineStatus) -> Name {
    match s {
        OnlineStatus::Unknown(raw) => Name("", Some(raw)),
        known => Name(known.name(), None),
    }
}

fn event(id: protocol_core::events::EventId) -> Name {
    match id {
        protocol_core::events::EventId::Unknown(raw) => Name("", Some(u16::from(raw))),
        known => Name(known.name(), None),
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

struct OptC(Option<f32>);
impl fmt::Display for OptC {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(v) => write!(f, "{v:.1}C"),
            None => f.write_str("--"),
        }
    }
}

fn setting_name(id: SettingId) -> &'static str {
    id.name()
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Report::Snapshot(s) => write!(
                f,
                "pack {:.2}V {:.2}A soc {:.1}% min #{} {:.4}V max #{} {:.4}V temp {:.1}C ext {} {} status {}",
                s.pack_v,
                s.current_a,
                s.soc_percent,
                s.min_cell.0,
                s.min_cell.1,
                s.max_cell.0,
                s.max_cell.1,
                s.internal_c,
                OptC(s.external_c.0),
                OptC(s.external_c.1),
                status(s.status)
            ),
            Report::StatusChanged { from, to } => match from {
                Some(from) => write!(f, "status {} -> {}", status(*from), status(*to)),
                None => write!(f, "status {}", status(*to)),
            },
            Report::NewEvent(e) => write!(
                f,
                "event {} t={}s 0x{:02X} {}",
                e.id.severity().name(),
                e.timestamp_s,
                e.id.raw(),
                event(e.id)
            ),
            Report::EventHistory { count, newest } => {
                write!(f, "event log: {count} recent events")?;
                if let Some(e) = newest {
                    write!(
                        f,
                        ", newest t={}s 0x{:02X} {}",
                        e.timestamp_s,
                        e.id.raw(),
                        event(e.id)
                    )?;
                }
                Ok(())
            }
            Report::LinkError {
                command,
                failure,
                suppressed,
            } => {
                write!(f, "link error cmd 0x{command:02X}: {}", failure.name())?;
                if let Failure::Nack(code) = failure {
                    write!(f, " code 0x{:02X}", code.to_u8())?;
                }
                if *suppressed > 0 {
                    write!(f, " (+{suppressed} more since the last line)")?;
                }
                Ok(())
            }
            Report::Offline { failures } => {
                write!(f, "BMS offline after {failures} failed requests")
            }
            Report::Online => f.write_str("BMS online; re-reading version and settings"),
            Report::Version(v) => {
                write!(
                    f,
                    "version hw {}.{} fw {} ({}) bootloader {} profile {} serial ",
                    v.hardware, v.hardware_changes, v.firmware_public, v.firmware_internal,
                    v.bootloader, v.profile
                )?;
                for b in v.serial {
                    write!(f, "{b:02X}")?;
                }
                Ok(())
            }
            Report::Ready { series_cells } => {
                write!(f, "settings and limits read ({series_cells} cells): ready")
            }
            Report::Write { setting, outcome } | Report::WriteFollowUp { setting, outcome } => {
                let follow = matches!(self, Report::WriteFollowUp { .. });
                write!(
                    f,
                    "write {}{} ({}) = {}: {}",
                    if follow { "follow-up " } else { "" },
                    setting_name(setting.id),
                    setting.id.address(),
                    setting.value,
                    outcome.name()
                )?;
                match outcome {
                    WriteOutcome::Rejected(e) => write!(f, " ({})", e.reason()),
                    WriteOutcome::Mismatch { read_back } => write!(f, " (read back {read_back})"),
                    WriteOutcome::Nacked(c) => write!(f, " (code 0x{:02X})", c.to_u8()),
                    WriteOutcome::Failed(e)
                    | WriteOutcome::Unconfirmed(e)
                    | WriteOutcome::NotWritten(e) => {
                        write!(f, " ({})", e.name())
                    }
                    _ => Ok(()),
                }
            }
            Report::ResetDone { confirmed } => write!(
                f,
                "BMS reset {}",
                if *confirmed { "confirmed (reg 114 = software reset)" } else { "not confirmed" }
            ),
            Report::Cleared { option, ok } => write!(
                f,
                "clear {} {}",
                if *option == 1 { "events" } else { "statistics" },
                if *ok { "ok" } else { "failed" }
            ),
            Report::LinkStats(s) => write!(
                f,
                "link: req {} rep {} timeouts {} wake {} retries {} crc {} framing {} invalid {} nack {}/{}/{} skipped {} unsolicited {} failures {} latency {}/{}/{} us",
                s.requests,
                s.replies,
                s.timeouts,
                s.wakeup_resends,
                s.retries,
                s.crc_errors,
                s.framing_errors,
                s.invalid_replies,
                s.nacks_command,
                s.nacks_crc,
                s.nacks_other,
                s.skipped_bytes,
                s.unsolicited,
                s.failures,
                s.latency_min_us,
                s.latency_mean_us(),
                s.latency_max_us
            ),
            Report::Dropped(n) => write!(f, "{n} log reports dropped"),
            Report::Flagged(Some(c)) => write!(
                f,
                "live data confirmed by a second read but fails check {}: published, flagged",
                c.name()
            ),
            Report::Flagged(None) => f.write_str("live data passes every check again"),
            Report::Refused { check, count } => write!(
                f,
                "{count} live block(s) failed check {} and were not confirmed: not published",
                check.map(|c| c.name()).unwrap_or("first_read")
            ),
            Report::LineQuality {
                attempts,
                clean,
                piece_registers,
                snapshots,
            } => write!(
                f,
                "line quality: {}.{} % of {attempts} reads answered at the first attempt; reading {piece_registers} registers per request; {snapshots} snapshots",
                permille(*clean, *attempts) / 10,
                permille(*clean, *attempts) % 10
            ),
        }
    }
}
