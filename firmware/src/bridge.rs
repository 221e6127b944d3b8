//! The bridge: poll schedule, telemetry model and write/verify state machine on
//! top of the [`Link`].
//!
//! ## Phases
//! 1. **Sync** — at start-up, after reconnection, after a reset and after every
//!    settings write: version (500-509), settings (300-343), the BMS's own min and
//!    max (0x1D options 1 and 2). Telemetry is not published before this
//!    completes ("ready").
//! 2. **Running** — the live block (0-55) every [`Config::live_period_us`], the
//!    event log and statistics (100-117) slower; queued commands (settings
//!    groups, reset, clear) run one at a time between live reads.
//!
//! While the link is offline only a probe (the version block) is sent, at
//! [`Config::offline_probe_period_us`].
//!
//! ## Only what the BMS sent
//! * Register blocks are read through [`BlockRead`]: whole on a clean line, in
//!   pieces on a bad one ([`LineQuality`]). Blocks that do not change by
//!   themselves (version, settings, 0x1D limits, statistics, the event log) are
//!   believed only when two complete reads in a row are identical.
//! * A live block must pass [`checks::check_live`] and, against the last
//!   published snapshot, [`checks::check_jump`]. One that fails is read again at
//!   once; it is published only if an independent second read agrees with it (no
//!   jump between the two, the same verdict), and then flagged with the check it
//!   failed ([`Report::Flagged`]). The first snapshot after a (re)sync is always
//!   confirmed by a second read.
//!
//! ## Write/verify
//! For each setting of a group: validate against Rev D and the BMS-reported
//! min/max → read the current value → skip when equal → write with 0x10 (byte
//! fields read-modify-write, keeping the other byte) → echo, or NACK reported with
//! its code → settle → read back → compare (0xFFFF counts as accepted for 323 and
//! 328). A write to 340 restarts the BMS: the read-back waits for the restart.
//! Success is only ever reported with a matching read-back; "failed" only when
//! the write never went out or the read-back shows the old value; when nothing
//! could be read back the outcome is "unconfirmed" and the settings read that
//! follows every write decides ([`Report::WriteFollowUp`]).

use heapless::{Deque, Vec};
use protocol_core::events::{Event, EventId};
use protocol_core::request::{Request, ResetOption, SettingsOption};
use protocol_core::response::{RegisterBlock, Response};
use protocol_core::settings::{Setting, SettingId, ACCEPTED_MARKER};
use protocol_core::views::{event_log, LiveSnapshot, Statistics, VersionInfo};

use crate::checks::{self, Check};
use crate::config::{self, Config};
use crate::event_log::{EventTracker, Found};
use crate::link::{Completion, Failure, Link, Next, Silence, Transmit};
use crate::reader::{self, Assembled, BlockRead, LineQuality, Mode};
use crate::report::{Report, SnapshotLine, WriteOutcome};
use crate::Instant;

/// What the caller must do next.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// Write these bytes to the UART now, then call [`Bridge::poll`] again.
    Transmit(Transmit),
    /// Wait for received bytes ([`Bridge::handle_rx`]) or until this time, then
    /// call [`Bridge::poll`] again.
    WaitUntil(Instant),
}

/// A request from the rest of the firmware.
#[derive(Debug, Clone, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Command {
    /// Write and verify these settings, one by one.
    ApplySettings(Vec<Setting, { config::MAX_SETTINGS_GROUP }>),
    /// Restart the BMS (0x02 option 0x05).
    ResetBms,
    /// Clear the event log (0x02 option 0x01).
    ClearEvents,
    /// Clear the statistics (0x02 option 0x02).
    ClearStatistics,
}

/// How the published live snapshot was obtained.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LiveMeta {
    /// Requests the block was assembled from (1 on a clean line).
    pub pieces: u8,
    /// First piece asked for to last piece received, µs.
    pub span_us: u32,
    /// A check the snapshot fails although a second read confirmed it.
    pub flagged: Option<Check>,
}

/// The bridge's picture of the BMS.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Telemetry {
    /// Latest live snapshot.
    pub snapshot: Option<LiveSnapshot>,
    /// Registers 0-55 it was decoded from (reserved registers read as 0 when the
    /// block was assembled from pieces).
    pub live_registers: Option<RegisterBlock>,
    /// How it was read.
    pub live: LiveMeta,
    /// When it was decoded.
    pub snapshot_at: Option<Instant>,
    /// Incremented at every new snapshot.
    pub snapshot_seq: u32,
    /// Latest statistics.
    pub statistics: Option<Statistics>,
    /// Registers 100-117 they were decoded from.
    pub statistics_registers: Option<RegisterBlock>,
    /// Version block.
    pub version: Option<VersionInfo>,
    /// Settings 300-343 as last read.
    pub settings: Option<RegisterBlock>,
    /// BMS-reported minimum of each setting (0x1D option 1).
    pub limits_min: Option<RegisterBlock>,
    /// BMS-reported maximum of each setting (0x1D option 2).
    pub limits_max: Option<RegisterBlock>,
    /// The link is up.
    pub online: bool,
    /// Version, settings and limits are read since the last (re)connection.
    pub ready: bool,
}

impl Telemetry {
    /// Age of the snapshot at `now`, µs.
    pub fn snapshot_age_us(&self, now: Instant) -> Option<Instant> {
        self.snapshot_at.map(|t| now.saturating_sub(t))
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SyncStep {
    Version,
    Settings,
    LimitsMin,
    LimitsMax,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    Sync(SyncStep),
    Running,
}

/// What a confirmed block read is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Aux {
    Version,
    Settings,
    Stats,
    Events,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Purpose {
    Live,
    Aux(Aux),
    Limits(SettingsOption),
    NewestEvents,
    EventSlot,
    Probe,
    Job,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum WriteStep {
    ReadCurrent,
    Write,
    Settle(Instant),
    ReadBack,
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct WriteJob {
    items: Vec<Setting, { config::MAX_SETTINGS_GROUP }>,
    index: usize,
    step: WriteStep,
    current: Option<(u16, Option<u16>)>,
    /// The write got no confirmation: the read-back decides.
    unconfirmed: Option<Failure>,
    readback_attempts: u8,
    wrote_any: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ResetStep {
    /// Read the event log: the newest "System Started" before the reset.
    Before,
    /// Send 0x02 option 0x05.
    Send { last_start: Option<u32> },
    /// Read the event log again: a newer "System Started" proves the restart.
    Confirm {
        attempts: u8,
        last_start: Option<u32>,
    },
}

#[derive(Debug, Clone, PartialEq, Eq)]
enum Job {
    Write(WriteJob),
    Reset(ResetStep),
    Clear(ResetOption),
}

/// A write whose outcome the next settings read decides.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Unresolved {
    setting: Setting,
    /// First register before the write, when it was read.
    old: Option<u16>,
}

/// A live block that failed a check, waiting for a second read.
#[derive(Debug, Clone, PartialEq)]
struct Suspect {
    snapshot: LiveSnapshot,
    at: Instant,
    verdict: Result<(), Check>,
    tries: u8,
}

/// Failed attempts at reading the BMS's settings limits (0x1D) before the bridge
/// goes on without them (and tries again later, at the statistics period).
const SYNC_LIMITS_ATTEMPTS: u8 = 3;

/// Second reads of a suspect live block before it is dropped.
const SUSPECT_TRIES: u8 = 3;

/// Writes awaiting a follow-up outcome.
const UNRESOLVED: usize = config::MAX_SETTINGS_GROUP;

/// The bridge. See the module documentation.
///
/// The link and the rest are apart so that a finished transaction (a whole
/// `Response`, hundreds of bytes) is handled by reference where the link keeps
/// it, instead of being moved out to satisfy the borrow of `&mut self`.
#[derive(Debug, Clone)]
pub struct Bridge {
    link: Link,
    s: State,
}

/// Everything of the bridge but the link.
#[derive(Debug, Clone)]
struct State {
    config: Config,
    /// `Link::is_online`, refreshed after every call into the link.
    link_online: bool,
    /// `Link::consecutive_failures`, refreshed with `link_online`.
    link_failures: u8,
    phase: Phase,
    purpose: Purpose,
    telemetry: Telemetry,
    reports: Deque<Report, { config::REPORT_QUEUE }>,
    dropped: u32,
    commands: Deque<Command, { config::COMMAND_QUEUE }>,
    job: Option<Job>,
    hold_until: Instant,
    next_live: Instant,
    next_events: Instant,
    next_stats: Instant,
    next_probe: Instant,
    next_snapshot_log: Instant,
    next_link_log: Instant,
    next_quality_log: Instant,
    sync_retry_at: Instant,
    sync_failures: u8,
    limits_unsupported: bool,
    /// A 0x1D read to make while running, and when.
    limits_due: Option<(SettingsOption, Instant)>,
    /// Settings were written: read them again before the next command.
    settings_stale: bool,
    limits_candidate: Option<RegisterBlock>,
    next_error_log: Instant,
    suppressed_errors: u32,
    was_online: bool,
    quality: LineQuality,
    /// The live read (reused from one snapshot to the next, see
    /// [`BlockRead::reset`]); in progress while `live_active`.
    live_read: BlockRead,
    live_active: bool,
    aux_read: Option<(Aux, BlockRead)>,
    live_turns: u8,
    suspect: Option<Suspect>,
    refused: u32,
    refused_check: Option<Check>,
    snapshots_in_window: u32,
    flagged: Option<Check>,
    events: EventTracker,
    unresolved: Vec<Unresolved, UNRESOLVED>,
    /// The published snapshot is from the current sync: jumps are checked
    /// against it.
    live_base_valid: bool,
    /// When the last sync completed.
    ready_at: Instant,
}

impl Bridge {
    /// A bridge at time `now`, about to sync with the BMS.
    pub fn new(config: Config, now: Instant) -> Self {
        let link = Link::new(config);
        let mut s = State::new(config, now);
        s.link_online = link.is_online();
        s.link_failures = link.consecutive_failures();
        Self { link, s }
    }

    /// Queues a command; gives it back when the queue is full.
    #[allow(clippy::result_large_err)] // the command itself is handed back
    pub fn submit(&mut self, command: Command) -> Result<(), Command> {
        self.s.submit(command)
    }

    /// Queues the settings of a profile (see [`crate::profile`]) as one group. An
    /// empty profile queues nothing. Entries beyond [`config::MAX_SETTINGS_GROUP`]
    /// are queued as further groups.
    #[allow(clippy::result_large_err)] // the command itself is handed back
    pub fn submit_profile(&mut self, profile: &[(SettingId, i32)]) -> Result<(), Command> {
        self.s.submit_profile(profile)
    }

    /// The current picture of the BMS.
    pub fn telemetry(&self) -> &Telemetry {
        &self.s.telemetry
    }

    /// Link counters.
    pub fn link_stats(&self) -> crate::link::LinkStats {
        self.link.stats()
    }

    /// Registers per request the block reads use now (the line's quality).
    pub fn piece_registers(&self) -> u16 {
        self.s.quality.piece()
    }

    /// Replaces the link counters (see [`Link::preset_stats`]).
    pub fn preset_link_stats(&mut self, stats: crate::link::LinkStats) {
        self.link.preset_stats(stats);
    }

    /// True while a command is queued or running.
    pub fn busy(&self) -> bool {
        self.s.busy()
    }

    /// The next report to log, oldest first.
    pub fn next_report(&mut self) -> Option<Report> {
        self.s.next_report()
    }

    /// Bytes received from the UART at `now`.
    pub fn handle_rx(&mut self, now: Instant, bytes: &[u8]) {
        self.link.on_bytes(now, bytes);
        self.refresh_link();
    }

    fn refresh_link(&mut self) {
        self.s.link_online = self.link.is_online();
        self.s.link_failures = self.link.consecutive_failures();
    }

    /// What to do next at `now`.
    pub fn poll(&mut self, now: Instant) -> Action {
        self.refresh_link();
        let s = &mut self.s;
        if now >= s.next_link_log {
            s.next_link_log = now.saturating_add(s.config.link_stats_log_period_us);
            let stats = self.link.stats();
            s.report(Report::LinkStats(stats));
        }
        if now >= s.next_quality_log {
            s.next_quality_log = now.saturating_add(s.config.line_quality_log_period_us);
            s.log_quality();
        }
        let next_log = s.next_link_log.min(s.next_quality_log);
        for _ in 0..16 {
            let next = self.link.next(now);
            self.refresh_link();
            match next {
                Next::Send => {
                    if let Some(b) = self.link.transmit() {
                        return Action::Transmit(b.clone());
                    }
                }
                Next::Done => {
                    // Handled where the link keeps it, then dropped.
                    if let Some(c) = self.link.completion() {
                        self.s.on_completion(now, c);
                    }
                    self.link.clear_completion();
                }
                Next::WaitUntil(t) => return Action::WaitUntil(t.min(next_log)),
                Next::Idle => match self.s.next_request(now) {
                    Some((req, silence, purpose)) => {
                        self.s.purpose = purpose;
                        // Pieces (0x09 block reads on a bad line, event slots)
                        // are small: a lost answer is not waited for as long.
                        let piece = matches!(
                            purpose,
                            Purpose::Live | Purpose::Aux(_) | Purpose::EventSlot
                        ) && matches!(req, Request::ReadIndividual(_));
                        let timeout = if piece {
                            self.s.config.piece_response_timeout_us
                        } else {
                            self.s.config.response_timeout_us
                        };
                        self.link.start_with_timeout(now, req, silence, timeout);
                    }
                    None => return Action::WaitUntil(self.s.next_wake(now).min(next_log)),
                },
            }
        }
        Action::WaitUntil(now)
    }
}

impl State {
    fn new(config: Config, now: Instant) -> Self {
        Self {
            config,
            link_online: true,
            link_failures: 0,
            phase: Phase::Sync(SyncStep::Version),
            purpose: Purpose::Probe,
            telemetry: Telemetry {
                online: true,
                ..Telemetry::default()
            },
            reports: Deque::new(),
            dropped: 0,
            commands: Deque::new(),
            job: None,
            hold_until: now,
            next_live: now,
            next_events: now,
            next_stats: now,
            next_probe: now,
            next_snapshot_log: now,
            next_link_log: now.saturating_add(config.link_stats_log_period_us),
            next_quality_log: now.saturating_add(config.line_quality_log_period_us),
            sync_retry_at: now,
            sync_failures: 0,
            limits_unsupported: false,
            limits_due: None,
            settings_stale: false,
            limits_candidate: None,
            next_error_log: now,
            suppressed_errors: 0,
            was_online: true,
            quality: LineQuality::default(),
            live_read: BlockRead::new(
                reader::LIVE_SEGMENTS,
                Mode::Window(config.live_period_us),
                now,
            ),
            live_active: false,
            aux_read: None,
            live_turns: 0,
            suspect: None,
            refused: 0,
            refused_check: None,
            snapshots_in_window: 0,
            flagged: None,
            events: EventTracker::new(),
            unresolved: Vec::new(),
            live_base_valid: false,
            ready_at: now,
        }
    }

    /// Queues a command; gives it back when the queue is full.
    #[allow(clippy::result_large_err)] // the command itself is handed back
    pub fn submit(&mut self, command: Command) -> Result<(), Command> {
        self.commands.push_back(command)
    }

    /// Queues the settings of a profile (see [`crate::profile`]) as one group. An
    /// empty profile queues nothing. Entries beyond [`config::MAX_SETTINGS_GROUP`]
    /// are queued as further groups.
    #[allow(clippy::result_large_err)] // the command itself is handed back
    pub fn submit_profile(&mut self, profile: &[(SettingId, i32)]) -> Result<(), Command> {
        for chunk in profile.chunks(config::MAX_SETTINGS_GROUP) {
            let mut items = Vec::new();
            for &(id, value) in chunk {
                let _fits = items.push(Setting { id, value }); // chunk <= capacity
            }
            self.submit(Command::ApplySettings(items))?;
        }
        Ok(())
    }

    /// True while a command is queued or running.
    pub fn busy(&self) -> bool {
        self.job.is_some() || !self.commands.is_empty()
    }

    /// The next report to log, oldest first.
    pub fn next_report(&mut self) -> Option<Report> {
        if self.dropped > 0 {
            let n = self.dropped;
            self.dropped = 0;
            return Some(Report::Dropped(n));
        }
        self.reports.pop_front()
    }

    fn report(&mut self, r: Report) {
        if self.reports.is_full() {
            let _oldest = self.reports.pop_front();
            self.dropped = self.dropped.wrapping_add(1);
        }
        let _room = self.reports.push_back(r);
    }

    fn log_quality(&mut self) {
        let (attempts, clean) = self.quality.take_window();
        let snapshots = core::mem::take(&mut self.snapshots_in_window);
        if self.refused > 0 {
            let count = core::mem::take(&mut self.refused);
            let check = self.refused_check.take();
            self.report(Report::Refused { check, count });
        }
        // A clean line says nothing; a degraded one says how degraded, once per
        // period, instead of a line per failed request.
        if attempts > clean || self.quality.level > 0 {
            self.report(Report::LineQuality {
                attempts,
                clean,
                piece_registers: self.quality.piece(),
                snapshots,
            });
        }
    }

    fn next_wake(&self, now: Instant) -> Instant {
        if now < self.hold_until {
            return self.hold_until;
        }
        if !self.link_online {
            return self.next_probe;
        }
        match self.phase {
            Phase::Sync(_) => self.sync_retry_at,
            Phase::Running => {
                let mut t = self.next_live.min(self.next_events).min(self.next_stats);
                if let Some(Job::Write(WriteJob {
                    step: WriteStep::Settle(s),
                    ..
                })) = &self.job
                {
                    t = t.min(*s);
                }
                if let Some((_, r)) = self.limits_due {
                    t = t.min(r);
                }
                t
            }
        }
        .max(now)
    }

    fn next_request(&mut self, now: Instant) -> Option<(Request, Silence, Purpose)> {
        if now < self.hold_until {
            return None;
        }
        if !self.link_online {
            if now < self.next_probe {
                return None;
            }
            self.next_probe = now.saturating_add(self.config.offline_probe_period_us);
            return Some((version_request(), Silence::Failure, Purpose::Probe));
        }
        if let Phase::Sync(step) = self.phase {
            if now < self.sync_retry_at {
                return None;
            }
            return Some(match step {
                SyncStep::Version => self.aux_piece(now, Aux::Version),
                SyncStep::Settings => self.aux_piece(now, Aux::Settings),
                // A BMS that does not answer 0x1D is not absent: its other answers
                // prove it is there, so that silence does not count towards offline.
                SyncStep::LimitsMin => limits_request(SettingsOption::Min),
                SyncStep::LimitsMax => limits_request(SettingsOption::Max),
            });
        }
        self.running_request(now)
    }

    /// Running: what to read next. A live read in progress alternates with a
    /// confirmed read in progress; between them, commands, the event log and the
    /// statistics get their turn before the next live read starts, so that no
    /// live period starves them.
    fn running_request(&mut self, now: Instant) -> Option<(Request, Silence, Purpose)> {
        let live_busy = self.live_active;
        if live_busy && self.live_turns > 0 {
            self.live_turns -= 1;
            return Some(self.live_piece(now));
        }
        // Between two settings of a group (or before a job starts) a due live
        // read goes first, so a long group does not blind the bridge.
        if !live_busy && now >= self.next_live && self.at_job_boundary() && self.live_turns > 0 {
            return Some(self.start_live(now));
        }
        // From here on, whatever goes out gives the live read its next turns.
        self.live_turns = config::LIVE_SHARE;
        if let Some((aux, _)) = self.aux_read {
            return Some(self.aux_piece(now, aux));
        }
        if self.settings_stale && self.job.is_none() {
            // Settings are read again after writes before the next command runs.
            return Some(self.aux_piece(now, Aux::Settings));
        }
        for _ in 0..config::COMMAND_QUEUE + 1 {
            if self.job.is_none() {
                let Some(cmd) = self.commands.pop_front() else {
                    break;
                };
                self.job = self.start_job(cmd);
            }
            match self.job_request(now) {
                JobNext::Send(req, silence) => return Some((req, silence, Purpose::Job)),
                JobNext::Wait => break,
                JobNext::Finished => {
                    self.job = None;
                    if matches!(self.phase, Phase::Sync(_)) || self.settings_stale {
                        // Re-read settings before the next command runs.
                        return self.next_request(now);
                    }
                }
            }
        }
        if matches!(self.job, Some(Job::Reset(_) | Job::Clear(_))) {
            // A reset or clear owns the link until it is done.
            return None;
        }
        // After a (re)sync the first snapshot goes before the event log and the
        // statistics (on a bad line those take many requests), unless the live
        // data takes unusually long.
        let first_snapshot_pending = !self.live_base_valid
            && now
                < self
                    .ready_at
                    .saturating_add(config::FIRST_SNAPSHOT_PRIORITY_US);
        if first_snapshot_pending {
            return Some(if live_busy {
                self.live_piece(now)
            } else {
                self.start_live(now)
            });
        }
        if now >= self.next_events {
            self.next_events = now.saturating_add(self.config.events_period_us);
            if self.events.needs_full_read() {
                if let Some(slot) = self.events.scan_slot() {
                    return Some((slot_request(slot), Silence::Failure, Purpose::EventSlot));
                }
                return Some(self.aux_piece(now, Aux::Events));
            }
            return Some((
                Request::ReadNewestEvents,
                Silence::Failure,
                Purpose::NewestEvents,
            ));
        }
        if now >= self.next_stats {
            self.next_stats = now.saturating_add(self.config.stats_period_us);
            return Some(self.aux_piece(now, Aux::Stats));
        }
        if live_busy {
            return Some(self.live_piece(now));
        }
        if now >= self.next_live {
            return Some(self.start_live(now));
        }
        if let Some((option, t)) = self.limits_due {
            if now >= t && self.job.is_none() {
                return Some(limits_request(option));
            }
        }
        None
    }

    fn start_live(&mut self, now: Instant) -> (Request, Silence, Purpose) {
        self.next_live = now.saturating_add(self.config.live_period_us);
        let window = self
            .config
            .live_assembly_window_us
            .max(self.config.live_period_us);
        self.live_read
            .reset(reader::LIVE_SEGMENTS, Mode::Window(window), now);
        self.live_read
            .guard(reader::LIVE_GUARDED, self.telemetry.live_registers.as_ref());
        self.live_active = true;
        // A new read uses up a turn, it does not start a fresh share: at a live
        // period shorter than a read, live reads follow each other back to back,
        // and the event log and the statistics get their turn every
        // LIVE_SHARE live requests all the same.
        self.live_turns = self.live_turns.saturating_sub(1);
        self.live_piece(now)
    }

    fn live_piece(&mut self, now: Instant) -> (Request, Silence, Purpose) {
        let piece = self.quality.piece();
        let req = if self.live_active {
            self.live_read.next_request(now, piece)
        } else {
            block(0, 56)
        };
        (req, Silence::Failure, Purpose::Live)
    }

    fn aux_piece(&mut self, now: Instant, aux: Aux) -> (Request, Silence, Purpose) {
        let piece = self.quality.piece();
        let read = match &mut self.aux_read {
            Some((a, r)) if *a == aux => r,
            _ => {
                let segments = match aux {
                    Aux::Version => reader::VERSION_SEGMENTS,
                    Aux::Settings => reader::SETTINGS_SEGMENTS,
                    Aux::Stats => reader::STATS_SEGMENTS,
                    Aux::Events => reader::EVENTS_SEGMENTS,
                };
                &mut self
                    .aux_read
                    .insert((aux, BlockRead::new(segments, Mode::Confirmed, now)))
                    .1
            }
        };
        let req = read.next_request(now, piece);
        (req, Silence::Failure, Purpose::Aux(aux))
    }

    /// No job, or a settings group between two settings.
    fn at_job_boundary(&self) -> bool {
        match &self.job {
            None => true,
            Some(Job::Write(w)) => w.step == WriteStep::ReadCurrent,
            Some(_) => false,
        }
    }

    fn start_job(&mut self, cmd: Command) -> Option<Job> {
        match cmd {
            Command::ResetBms => Some(Job::Reset(ResetStep::Before)),
            Command::ClearEvents => Some(Job::Clear(ResetOption::ClearEvents)),
            Command::ClearStatistics => Some(Job::Clear(ResetOption::ClearStatistics)),
            Command::ApplySettings(settings) => {
                let mut items = Vec::new();
                for s in settings {
                    match self.check_setting(&s) {
                        Ok(()) => {
                            let _fits = items.push(s); // same capacity
                        }
                        Err(e) => self.report(Report::Write {
                            setting: s,
                            outcome: WriteOutcome::Rejected(e),
                        }),
                    }
                }
                if items.is_empty() {
                    None
                } else {
                    Some(Job::Write(WriteJob {
                        items,
                        index: 0,
                        step: WriteStep::ReadCurrent,
                        current: None,
                        unconfirmed: None,
                        readback_attempts: 0,
                        wrote_any: false,
                    }))
                }
            }
        }
    }

    fn job_request(&mut self, now: Instant) -> JobNext {
        let Some(job) = self.job.as_mut() else {
            return JobNext::Finished;
        };
        match job {
            Job::Clear(opt) => JobNext::Send(Request::ResetClear(*opt), Silence::Failure),
            Job::Reset(ResetStep::Before) => {
                JobNext::Send(Request::ReadAllEvents, Silence::Failure)
            }
            Job::Reset(ResetStep::Send { .. }) => JobNext::Send(
                Request::ResetClear(ResetOption::ResetBms),
                Silence::Expected,
            ),
            Job::Reset(ResetStep::Confirm { .. }) => {
                JobNext::Send(Request::ReadAllEvents, Silence::Tolerated)
            }
            Job::Write(w) => {
                let Some(item) = w.items.get(w.index).copied() else {
                    let wrote = w.wrote_any;
                    let restarted = w.items.iter().any(|s| s.id.restarts_bms());
                    if wrote && restarted {
                        // The BMS restarted (340): everything is read again.
                        self.resync();
                    } else if wrote {
                        // The settings (and the unconfirmed outcomes) are read
                        // again; the live data keeps flowing meanwhile.
                        self.settings_stale = true;
                    }
                    return JobNext::Finished;
                };
                // Reads of a setting use 0x09: its reply echoes the addresses, so a
                // late answer to another read can never pass for this one.
                let read = individual(item.id);
                match w.step {
                    WriteStep::ReadCurrent => JobNext::Send(read, Silence::Failure),
                    WriteStep::ReadBack => {
                        let silence = if item.id.restarts_bms() {
                            Silence::Tolerated
                        } else {
                            Silence::Failure
                        };
                        JobNext::Send(read, silence)
                    }
                    WriteStep::Settle(until) => {
                        if now < until {
                            JobNext::Wait
                        } else {
                            w.step = WriteStep::ReadBack;
                            JobNext::Send(read, Silence::Failure)
                        }
                    }
                    WriteStep::Write => {
                        let current = w.current.map(|(first, _)| first);
                        let words = match item.words(current) {
                            Ok(words) => words,
                            Err(e) => {
                                self.finish_item(item, WriteOutcome::Rejected(e));
                                return self.job_request(now);
                            }
                        };
                        let values: Vec<u16, 2> = words.iter().map(|&(_, v)| v).collect();
                        // A write to 340 restarts the BMS: its answer may never come,
                        // and it must not be sent twice.
                        let silence = if item.id.restarts_bms() {
                            Silence::Expected
                        } else {
                            Silence::Failure
                        };
                        match Request::write_registers(item.id.address(), &values) {
                            Ok(req) => JobNext::Send(req, silence),
                            Err(_) => {
                                let e = protocol_core::settings::SettingError::NotAnOption {
                                    id: item.id,
                                    value: item.value,
                                };
                                self.finish_item(item, WriteOutcome::Rejected(e));
                                self.job_request(now)
                            }
                        }
                    }
                }
            }
        }
    }

    /// Reports the outcome of the current setting and moves to the next one.
    fn finish_item(&mut self, setting: Setting, outcome: WriteOutcome) {
        if let Some(Job::Write(w)) = self.job.as_mut() {
            w.index += 1;
            w.step = WriteStep::ReadCurrent;
            w.current = None;
            w.unconfirmed = None;
            w.readback_attempts = 0;
        }
        self.report(Report::Write { setting, outcome });
    }
    /// Rev D range and enumerations, then the BMS's own min/max when it reported
    /// them (it may not support 0x1D; it still checks writes itself and NACKs).
    /// For the sensor-dependent settings (304, 305, 317, 318) the BMS's limits
    /// replace Rev D's range when known.
    fn check_setting(&self, s: &Setting) -> Result<(), protocol_core::settings::SettingError> {
        let bms = match (&self.telemetry.limits_min, &self.telemetry.limits_max) {
            (Some(min), Some(max)) => s.id.limits(min, max),
            _ => None,
        };
        s.validate_with(bms)
    }

    fn resync(&mut self) {
        self.phase = Phase::Sync(SyncStep::Version);
        self.telemetry.ready = false;
        self.aux_read = None;
        self.live_active = false;
        self.suspect = None;
        self.sync_failures = 0;
        self.limits_candidate = None;
        self.live_base_valid = false;
        self.settings_stale = false;
    }

    fn on_completion(&mut self, now: Instant, c: &Completion) {
        let online = self.link_online;
        if self.was_online && !online {
            self.report(Report::Offline {
                failures: self.link_failures,
            });
            self.telemetry.online = false;
            self.resync();
            self.next_probe = now.saturating_add(self.config.offline_probe_period_us);
            self.abort_job(c.result.clone().err().unwrap_or(Failure::Timeout));
        } else if !self.was_online && online {
            self.report(Report::Online);
            self.telemetry.online = true;
            self.resync();
        }
        self.was_online = online;
        let block_read = matches!(
            self.purpose,
            Purpose::Live | Purpose::Aux(_) | Purpose::EventSlot
        );
        if block_read {
            self.quality.note(c.sends, c.result.is_ok());
        }
        if let Err(f) = &c.result {
            let limits = matches!(self.purpose, Purpose::Limits(_));
            // Failed pieces of block reads are expected on a bad line and retried:
            // they show up in the line quality figure, not one line each.
            let quiet = matches!(f, Failure::Silent)
                || (!online && self.purpose == Purpose::Probe)
                || self.purpose == Purpose::Job
                || block_read
                || (limits && (self.limits_unsupported || self.phase == Phase::Running));
            if !quiet {
                if now >= self.next_error_log {
                    self.next_error_log = now.saturating_add(self.config.link_error_log_period_us);
                    let suppressed = core::mem::take(&mut self.suppressed_errors);
                    self.report(Report::LinkError {
                        command: c.request.command(),
                        failure: *f,
                        suppressed,
                    });
                } else {
                    self.suppressed_errors = self.suppressed_errors.wrapping_add(1);
                }
            }
        }
        if !online {
            return;
        }
        match self.purpose {
            Purpose::Live => match &c.result {
                Ok(Response::Registers(_) | Response::Individual(_)) => {
                    let done = if self.live_active {
                        on_piece(&mut self.live_read, now, &c.result)
                    } else {
                        None
                    };
                    if let Some(a) = done {
                        self.live_active = false;
                        self.on_live(now, a);
                    }
                }
                _ => {
                    if self.live_active {
                        self.live_read.on_failure();
                    }
                }
            },
            Purpose::Aux(aux) => {
                let done = match (&c.result, self.aux_read.as_mut()) {
                    (Ok(Response::Registers(_) | Response::Individual(_)), Some((a, r)))
                        if *a == aux =>
                    {
                        on_piece(r, now, &c.result)
                    }
                    (_, Some((a, r))) if *a == aux => {
                        r.on_failure();
                        if matches!(self.phase, Phase::Sync(_)) {
                            self.sync_retry_at =
                                now.saturating_add(self.config.live_period_us.min(crate::SECOND));
                        }
                        None
                    }
                    _ => None,
                };
                if let Some(a) = done {
                    self.aux_read = None;
                    self.on_aux(now, aux, a.block);
                }
            }
            Purpose::Limits(option) => self.on_limits(now, option, &c.result),
            Purpose::NewestEvents => {
                // The BMS may mark events as read when it answers: a reply that was
                // lost, or a request that went out twice, may have hidden some.
                if c.sends > 1 || c.result.is_err() {
                    self.events.reply_may_be_lost();
                }
                if let Ok(Response::Events(list)) = &c.result {
                    let expected = self.expected_bms_clock(now);
                    let fresh = self.events.fresh_clock(list.bms_timestamp_s);
                    if fresh
                        && EventTracker::plausible(&list.events, list.bms_timestamp_s, expected)
                    {
                        self.events.accept_clock(list.bms_timestamp_s);
                        let mut found: Vec<Found, { protocol_core::response::MAX_EVENTS }> =
                            Vec::new();
                        self.events.on_newest(&list.events, |f| {
                            let _fits = found.push(f);
                        });
                        for f in found {
                            self.on_found(f);
                        }
                    } else {
                        self.events.reply_may_be_lost();
                    }
                }
                if self.events.needs_full_read() {
                    // Fill the gap now rather than at the next events period.
                    self.next_events = now;
                }
            }
            Purpose::EventSlot => {
                if let Ok(Response::Individual(pairs)) = &c.result {
                    if let [(_, first), (_, second)] = pairs.as_slice() {
                        let mut found: Vec<Found, 1> = Vec::new();
                        self.events.on_slot(*first, *second, |f| {
                            let _fits = found.push(f);
                        });
                        for f in found {
                            self.on_found(f);
                        }
                    }
                }
                if self.events.needs_full_read() {
                    self.next_events = now; // go on with the scan / full read
                }
            }
            Purpose::Probe => {}
            Purpose::Job => self.on_job(now, c),
        }
    }

    /// The BMS clock (lifetime counter) now, from the last snapshot.
    fn expected_bms_clock(&self, now: Instant) -> Option<u32> {
        let s = self.telemetry.snapshot.as_ref()?;
        let at = self.telemetry.snapshot_at?;
        let elapsed = now.saturating_sub(at) / crate::SECOND;
        Some(
            s.lifetime_s
                .wrapping_add(elapsed.min(u64::from(u32::MAX)) as u32),
        )
    }

    fn on_found(&mut self, f: Found) {
        match f {
            Found::New(e) => self.report(Report::NewEvent(e)),
            Found::History { count, newest } => self.report(Report::EventHistory { count, newest }),
        }
    }

    fn abort_job(&mut self, failure: Failure) {
        match self.job.take() {
            Some(Job::Write(w)) => {
                for (i, s) in w.items.iter().enumerate().skip(w.index) {
                    // The setting in flight may have been written already.
                    let written = i == w.index
                        && matches!(w.step, WriteStep::Settle(_) | WriteStep::ReadBack);
                    let outcome = if written {
                        self.remember_unresolved(*s, w.current.map(|(f, _)| f));
                        WriteOutcome::Unconfirmed(failure)
                    } else {
                        WriteOutcome::NotWritten(failure)
                    };
                    self.report(Report::Write {
                        setting: *s,
                        outcome,
                    });
                }
            }
            Some(Job::Reset(_)) => self.report(Report::ResetDone { confirmed: false }),
            Some(Job::Clear(opt)) => self.report(Report::Cleared {
                option: opt.to_u8(),
                ok: false,
            }),
            None => {}
        }
    }

    fn remember_unresolved(&mut self, setting: Setting, old: Option<u16>) {
        if self.unresolved.is_full() {
            let _oldest = self.unresolved.remove(0);
        }
        let _fits = self.unresolved.push(Unresolved { setting, old });
    }

    /// A confirmed block read finished.
    fn on_aux(&mut self, now: Instant, aux: Aux, b: RegisterBlock) {
        match aux {
            Aux::Version => {
                if let Ok(v) = VersionInfo::from_registers(&b) {
                    self.telemetry.version = Some(v);
                    self.report(Report::Version(v));
                }
                self.sync_next(now, SyncStep::Settings);
            }
            Aux::Settings => {
                self.resolve_writes(&b);
                self.telemetry.settings = Some(b);
                self.settings_stale = false;
                if self.phase == Phase::Running {
                    if !self.limits_unsupported {
                        self.limits_candidate = None;
                        self.limits_due = Some((SettingsOption::Min, now));
                    }
                } else if self.limits_unsupported {
                    // Known not to answer 0x1D: do not ask at every sync.
                    self.sync_done(now);
                } else {
                    self.sync_next(now, SyncStep::LimitsMin);
                }
            }
            Aux::Stats => {
                if let Ok(s) = Statistics::from_registers(&b) {
                    self.telemetry.statistics = Some(s);
                    self.telemetry.statistics_registers = Some(b);
                }
            }
            Aux::Events => {
                if let Ok(slots) = event_log(&b) {
                    let mut events: Vec<(u8, Event), { protocol_core::registers::EVENT_SLOTS }> =
                        Vec::new();
                    for s in &slots {
                        let _fits = events.push((s.slot, s.event));
                    }
                    let mut found: Vec<Found, { protocol_core::response::MAX_EVENTS }> = Vec::new();
                    self.events.on_full_slots(&events, |f| {
                        let _fits = found.push(f);
                    });
                    for f in found {
                        self.on_found(f);
                    }
                }
            }
        }
    }

    /// The settings read after writes decides the unconfirmed ones.
    fn resolve_writes(&mut self, settings: &RegisterBlock) {
        let pending = core::mem::take(&mut self.unresolved);
        for u in pending {
            let a = u.setting.id.address();
            let Some(first) = settings.get(a) else {
                continue;
            };
            let second = if u.setting.id.register_count() == 2 {
                settings.get(a + 1)
            } else {
                None
            };
            let marker_was_there =
                u.setting.id.reads_back_marker() && u.old == Some(ACCEPTED_MARKER);
            let outcome = if marker_was_there {
                // 0xFFFF before and after: nothing proves either way.
                WriteOutcome::Unconfirmed(Failure::Timeout)
            } else if u.setting.matches_readback(first, second) {
                WriteOutcome::Verified
            } else if u.old == Some(first) {
                WriteOutcome::Failed(Failure::Timeout)
            } else {
                WriteOutcome::Mismatch { read_back: first }
            };
            self.report(Report::WriteFollowUp {
                setting: u.setting,
                outcome,
            });
        }
    }

    fn sync_next(&mut self, now: Instant, step: SyncStep) {
        if let Phase::Sync(_) = self.phase {
            self.sync_failures = 0;
            self.sync_retry_at = now;
            self.phase = Phase::Sync(step);
        }
    }

    fn sync_done(&mut self, now: Instant) {
        if !matches!(self.phase, Phase::Sync(_)) {
            return;
        }
        self.sync_failures = 0;
        self.phase = Phase::Running;
        self.telemetry.ready = true;
        self.ready_at = now;
        self.next_live = now;
        self.next_events = now;
        self.next_stats = now;
        let cells = self
            .telemetry
            .settings
            .as_ref()
            .and_then(|b| b.get(307))
            .unwrap_or(0);
        self.report(Report::Ready {
            series_cells: cells,
        });
    }

    /// 0x1D replies: believed when two in a row are identical.
    fn on_limits(
        &mut self,
        now: Instant,
        option: SettingsOption,
        result: &Result<Response, Failure>,
    ) {
        let in_sync = matches!(self.phase, Phase::Sync(_));
        let next = match result {
            Ok(Response::Settings { values, .. }) => {
                if self.limits_candidate.as_ref() != Some(values) {
                    // First of two, or two that differ: ask again.
                    self.limits_candidate = Some(values.clone());
                    Some((option, now))
                } else {
                    self.limits_candidate = None;
                    self.sync_failures = 0;
                    if option == SettingsOption::Min {
                        self.telemetry.limits_min = Some(values.clone());
                        Some((SettingsOption::Max, now))
                    } else {
                        self.telemetry.limits_max = Some(values.clone());
                        None
                    }
                }
            }
            // A BMS without 0x1D: go on without its limits for good; Rev D's
            // ranges still apply and the BMS still checks writes itself.
            Err(Failure::Nack(_)) => {
                self.limits_unsupported = true;
                self.telemetry.limits_min = None;
                self.telemetry.limits_max = None;
                None
            }
            _ => {
                self.sync_failures = self.sync_failures.saturating_add(1);
                if self.sync_failures >= SYNC_LIMITS_ATTEMPTS {
                    // No valid answer on this line for now: go on without the
                    // limits (or with the ones read before) and ask again later.
                    self.sync_failures = 0;
                    self.limits_candidate = None;
                    let later = now.saturating_add(self.config.stats_period_us);
                    if in_sync {
                        self.limits_due = Some((option, later));
                        self.sync_done(now);
                        return;
                    }
                    Some((option, later))
                } else {
                    Some((option, now.saturating_add(self.config.live_period_us)))
                }
            }
        };
        if in_sync {
            match next {
                Some((SettingsOption::Max, t)) => {
                    self.phase = Phase::Sync(SyncStep::LimitsMax);
                    self.sync_retry_at = t;
                }
                Some((_, t)) => self.sync_retry_at = t,
                None => self.sync_done(now),
            }
        } else {
            self.limits_due = next;
        }
    }

    /// A complete live block: check it, confirm it when it fails, publish it.
    fn on_live(&mut self, now: Instant, a: Assembled) {
        let Ok(snap) = LiveSnapshot::from_registers(&a.block) else {
            return;
        };
        let ctx = checks::Context {
            series_cells: self.telemetry.settings.as_ref().and_then(|b| b.get(307)),
            assembled: a.pieces > 1,
        };
        let at = a.started_at;
        let statics = checks::check_live(&a.block, &snap, ctx);
        let jump = match (&self.telemetry.snapshot, self.telemetry.snapshot_at) {
            (Some(p), Some(p_at)) if self.telemetry.ready && self.suspect_base_valid() => {
                checks::check_jump(p, p_at, &snap, at)
            }
            _ => Ok(()),
        };
        let first = !self.suspect_base_valid();
        let verdict = statics.and(jump);
        let flag = match self.suspect.take() {
            None if verdict.is_ok() && !first => Some(None),
            None => {
                self.suspect = Some(Suspect {
                    snapshot: snap,
                    at,
                    verdict: statics,
                    tries: 1,
                });
                self.next_live = now; // read again at once
                return;
            }
            Some(_) if verdict.is_ok() && !first => Some(None),
            Some(q) => {
                let agrees = q.verdict == statics
                    && checks::check_jump(&q.snapshot, q.at, &snap, at).is_ok();
                if agrees {
                    Some(verdict.err())
                } else if q.tries < SUSPECT_TRIES {
                    self.suspect = Some(Suspect {
                        snapshot: snap,
                        at,
                        verdict: statics,
                        tries: q.tries + 1,
                    });
                    self.next_live = now;
                    return;
                } else {
                    self.refused = self.refused.wrapping_add(1);
                    self.refused_check = verdict.err().or(q.verdict.err());
                    None
                }
            }
        };
        let Some(flag) = flag else {
            return;
        };
        if flag != self.flagged {
            self.flagged = flag;
            self.report(Report::Flagged(flag));
        }
        self.publish(now, snap, a, flag);
    }

    /// True when the last published snapshot is from this sync (jumps are
    /// checked against it).
    fn suspect_base_valid(&self) -> bool {
        self.telemetry.snapshot.is_some() && self.live_base_valid
    }

    fn publish(&mut self, now: Instant, snap: LiveSnapshot, a: Assembled, flag: Option<Check>) {
        let previous = self.telemetry.snapshot.as_ref().map(|s| s.status);
        if previous != Some(snap.status) {
            self.report(Report::StatusChanged {
                from: previous,
                to: snap.status,
            });
        }
        if let Some(next) = snapshot_log_due(
            self.next_snapshot_log,
            now,
            self.config.snapshot_log_period_us,
        ) {
            self.next_snapshot_log = next;
            self.report(Report::Snapshot(snapshot_line(&snap)));
        }
        self.telemetry.snapshot = Some(snap);
        self.telemetry.live_registers = Some(a.block);
        self.telemetry.live = LiveMeta {
            pieces: a.pieces,
            span_us: a.span_us.min(u64::from(u32::MAX)) as u32,
            flagged: flag,
        };
        self.telemetry.snapshot_at = Some(now);
        self.telemetry.snapshot_seq = self.telemetry.snapshot_seq.wrapping_add(1);
        self.snapshots_in_window = self.snapshots_in_window.wrapping_add(1);
        self.live_base_valid = true;
    }

    fn on_job(&mut self, now: Instant, c: &Completion) {
        let Some(job) = self.job.as_mut() else {
            return;
        };
        match job {
            Job::Clear(opt) => {
                let ok = matches!(c.result, Ok(Response::Ack { .. }));
                let option = opt.to_u8();
                self.job = None;
                self.report(Report::Cleared { option, ok });
            }
            Job::Reset(ResetStep::Before) => {
                let last_start = match &c.result {
                    Ok(Response::Events(list)) => newest_start(&list.events),
                    _ => {
                        // Without the log there is no way to prove the restart.
                        self.job = None;
                        self.report(Report::ResetDone { confirmed: false });
                        return;
                    }
                };
                *job = Job::Reset(ResetStep::Send { last_start });
            }
            Job::Reset(ResetStep::Send { last_start }) => {
                let last_start = *last_start;
                // ACK or silence are both normal (HARDWARE-NOTES); a NACK is not.
                if matches!(c.result, Err(Failure::Nack(_))) {
                    self.job = None;
                    self.report(Report::ResetDone { confirmed: false });
                } else {
                    self.hold_until = now.saturating_add(self.config.reboot_wait_us);
                    *job = Job::Reset(ResetStep::Confirm {
                        attempts: config::REBOOT_READBACK_ATTEMPTS,
                        last_start,
                    });
                }
            }
            Job::Reset(ResetStep::Confirm {
                attempts,
                last_start,
            }) => {
                // Proof of this restart: a "System Started" newer than the newest
                // one before the reset.
                let confirmed = match &c.result {
                    Ok(Response::Events(list)) => {
                        Some(match (newest_start(&list.events), *last_start) {
                            (Some(now_start), Some(before)) => ts_newer(now_start, before),
                            (Some(_), None) => true,
                            (None, _) => false,
                        })
                    }
                    _ => None,
                };
                match confirmed {
                    Some(true) => {
                        self.job = None;
                        self.report(Report::ResetDone { confirmed: true });
                        self.resync();
                    }
                    _ if *attempts > 1 => {
                        *attempts -= 1;
                        self.hold_until =
                            now.saturating_add(self.config.live_period_us.saturating_mul(2));
                    }
                    _ => {
                        self.job = None;
                        self.report(Report::ResetDone { confirmed: false });
                        self.resync();
                    }
                }
            }
            Job::Write(w) => {
                let Some(item) = w.items.get(w.index).copied() else {
                    return;
                };
                let a = item.id.address();
                match (w.step, &c.result) {
                    (WriteStep::ReadCurrent, Ok(Response::Individual(pairs))) => {
                        let (Some(first), second) = (pair(pairs, a), pair(pairs, a + 1)) else {
                            self.finish_item(item, WriteOutcome::NotWritten(Failure::Timeout));
                            return;
                        };
                        // Skip only on true equality (not on 323/328's 0xFFFF marker).
                        if item.id.value_from_words(first, second) == Some(item.value) {
                            self.finish_item(item, WriteOutcome::Unchanged);
                        } else {
                            w.current = Some((first, second));
                            w.step = WriteStep::Write;
                        }
                    }
                    (WriteStep::ReadCurrent, Err(f)) => {
                        self.finish_item(item, WriteOutcome::NotWritten(*f));
                    }
                    (WriteStep::ReadCurrent, Ok(_)) => {
                        self.finish_item(item, WriteOutcome::NotWritten(Failure::Timeout));
                    }
                    (WriteStep::Write, result) => {
                        w.wrote_any = true;
                        match result {
                            Ok(Response::WriteEcho { .. }) => {}
                            // Refused at the first attempt: nothing was written.
                            Err(Failure::Nack(code)) if c.sends <= 1 => {
                                self.finish_item(item, WriteOutcome::Nacked(*code));
                                return;
                            }
                            // No clear confirmation (lost, damaged, or a NACK after an
                            // unanswered first attempt that may have been applied):
                            // the read-back decides.
                            Err(Failure::Silent) => w.unconfirmed = Some(Failure::Timeout),
                            Err(f) => w.unconfirmed = Some(*f),
                            Ok(_) => w.unconfirmed = Some(Failure::Timeout),
                        }
                        if item.id.restarts_bms() {
                            self.hold_until = now.saturating_add(self.config.reboot_wait_us);
                            w.readback_attempts = config::REBOOT_READBACK_ATTEMPTS;
                            w.step = WriteStep::ReadBack;
                        } else {
                            w.readback_attempts = 1;
                            w.step =
                                WriteStep::Settle(now.saturating_add(self.config.write_settle_us));
                        }
                    }
                    (WriteStep::ReadBack, Ok(Response::Individual(pairs))) => {
                        let Some(first) = pair(pairs, a) else {
                            let old = w.current.map(|(f, _)| f);
                            self.remember_unresolved(item, old);
                            self.finish_item(item, WriteOutcome::Unconfirmed(Failure::Timeout));
                            return;
                        };
                        let second = pair(pairs, a + 1);
                        // 323/328 read 0xFFFF once a write is accepted; when they
                        // already did before and the write was not confirmed, the
                        // marker proves nothing.
                        let marker_was_there = item.id.reads_back_marker()
                            && w.current.map(|(f, _)| f) == Some(ACCEPTED_MARKER);
                        let proof = item.matches_readback(first, second)
                            && !(marker_was_there && w.unconfirmed.is_some());
                        let old = w.current.map(|(f, _)| f);
                        let outcome = if proof {
                            WriteOutcome::Verified
                        } else if marker_was_there && item.matches_readback(first, second) {
                            // 0xFFFF before and after an unconfirmed write: the
                            // read-back proves nothing either way.
                            let f = w.unconfirmed.unwrap_or(Failure::Timeout);
                            self.remember_unresolved(item, old);
                            WriteOutcome::Unconfirmed(f)
                        } else {
                            match w.unconfirmed {
                                // The read-back shows the old value: not applied.
                                Some(Failure::Nack(code)) if old == Some(first) => {
                                    WriteOutcome::Nacked(code)
                                }
                                Some(f) if old == Some(first) => WriteOutcome::Failed(f),
                                _ => WriteOutcome::Mismatch { read_back: first },
                            }
                        };
                        self.finish_item(item, outcome);
                    }
                    (WriteStep::ReadBack, Err(f)) => {
                        if w.readback_attempts > 1 {
                            w.readback_attempts -= 1;
                            self.hold_until =
                                now.saturating_add(self.config.live_period_us.saturating_mul(2));
                        } else {
                            // Written, nothing read back: the settings read that
                            // follows the group decides.
                            let old = w.current.map(|(f, _)| f);
                            self.remember_unresolved(item, old);
                            self.finish_item(item, WriteOutcome::Unconfirmed(*f));
                        }
                    }
                    (WriteStep::ReadBack, Ok(_)) | (WriteStep::Settle(_), _) => {
                        let old = w.current.map(|(f, _)| f);
                        self.remember_unresolved(item, old);
                        self.finish_item(item, WriteOutcome::Unconfirmed(Failure::Timeout));
                    }
                }
            }
        }
    }
}

enum JobNext {
    Send(Request, Silence),
    Wait,
    Finished,
}

/// Hands a piece's reply to its block read.
fn on_piece(
    read: &mut BlockRead,
    now: Instant,
    result: &Result<Response, Failure>,
) -> Option<Assembled> {
    match result {
        Ok(Response::Registers(b)) => read.on_block(now, b),
        Ok(Response::Individual(pairs)) => read.on_pairs(now, pairs),
        _ => None,
    }
}

/// Whether a snapshot line is due at `now` when the next one was planned for
/// `next`, and when the one after it is: `Some(next line time)` or `None`.
/// Period 0 logs every snapshot. Otherwise lines keep to the period's grid (a
/// line every 10 s, not every 10.25 s), and after a long silence the next grid
/// point is computed at once, not walked to step by step.
pub fn snapshot_log_due(next: Instant, now: Instant, period: Instant) -> Option<Instant> {
    if period == 0 {
        return Some(now);
    }
    if now < next {
        return None;
    }
    let steps = (now - next) / period + 1;
    Some(next.saturating_add(steps.saturating_mul(period)))
}

/// A 0x09 read of one event slot (two registers).
fn slot_request(slot: u8) -> Request {
    let a = protocol_core::registers::EVENTS_FIRST + 2 * u16::from(slot);
    let mut addresses = protocol_core::request::AddressList::new();
    let _ = addresses.push(a);
    let _ = addresses.push(a + 1);
    Request::ReadIndividual(addresses)
}

fn block(start: u16, count: usize) -> Request {
    Request::ReadRegisters {
        start,
        count: count as u8,
    }
}

fn version_request() -> Request {
    block(500, 10)
}

/// A 0x1D read of the BMS's own limits. Silence is tolerated: a BMS that does
/// not answer 0x1D is not absent (its other answers prove it is there).
fn limits_request(option: SettingsOption) -> (Request, Silence, Purpose) {
    (
        Request::ReadSettings { option, count: 44 },
        Silence::Tolerated,
        Purpose::Limits(option),
    )
}

/// A 0x09 read of the register(s) of a setting.
fn individual(id: SettingId) -> Request {
    let a = id.address();
    let mut addresses = protocol_core::request::AddressList::new();
    for i in 0..id.register_count() {
        let _fits = addresses.push(a + i); // at most 2 of 31
    }
    Request::ReadIndividual(addresses)
}

fn pair(pairs: &[(u16, u16)], address: u16) -> Option<u16> {
    pairs.iter().find(|(a, _)| *a == address).map(|(_, v)| *v)
}

/// Event timestamps are 24 bits (Rev D §1.1.9) and wrap after 194 days: compare
/// them as serial numbers (RFC 1982 style), `a` newer than `b`.
pub fn ts_newer(a: u32, b: u32) -> bool {
    let d = a.wrapping_sub(b) & 0x00FF_FFFF;
    d != 0 && d < 0x0080_0000
}

/// Timestamp of the newest "System Started" event in a list.
fn newest_start(events: &[Event]) -> Option<u32> {
    events
        .iter()
        .filter(|e| e.id == EventId::SystemStarted)
        .map(|e| e.timestamp_s)
        .reduce(|a, b| if ts_newer(b, a) { b } else { a })
}

/// The log summary of a snapshot.
pub fn snapshot_line(s: &LiveSnapshot) -> SnapshotLine {
    let volts = |(i, raw): (usize, u16)| ((i + 1) as u8, f32::from(raw) * 0.0001);
    SnapshotLine {
        pack_v: s.pack_voltage_v,
        current_a: s.pack_current_a,
        soc_percent: s.soc_percent(),
        min_cell: s.cells.min().map(volts).unwrap_or((0, 0.0)),
        max_cell: s.cells.max().map(volts).unwrap_or((0, 0.0)),
        internal_c: s.internal_c(),
        external_c: (s.external1_c(), s.external2_c()),
        status: s.status,
    }
}
