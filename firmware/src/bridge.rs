//! The bridge: poll schedule, telemetry model and write/verify state machine on
//! top of the [`Link`].
//!
//! ## Phases
//! 1. **Sync** — at start-up, after reconnection, after a reset and after every
//!    settings write: version (0x03 500-509), settings (0x03 300-343), the BMS's
//!    own min and max (0x1D options 1 and 2). Telemetry is not published before
//!    this completes ("ready").
//! 2. **Running** — the live block (0x03 0-55) every [`Config::live_period_us`],
//!    newest events (0x11) and statistics (0x03 100-117) slower; queued commands
//!    (settings groups, reset, clear) run one at a time and take priority.
//!
//! While the link is offline only a probe (the version block) is sent, at
//! [`Config::offline_probe_period_us`].
//!
//! ## Write/verify
//! For each setting of a group: validate against Rev D and the BMS-reported
//! min/max → read the current value → skip when equal → write with 0x10 (byte
//! fields read-modify-write, keeping the other byte) → echo, or NACK reported with
//! its code → settle → read back → compare (0xFFFF counts as accepted for 323 and
//! 328). A write to 340 restarts the BMS: the read-back waits for the restart. When
//! the write's reply is lost, the read-back still decides: success is only ever
//! reported with a matching read-back.

use heapless::{Deque, Vec};
use protocol_core::events::{Event, EventId};
use protocol_core::request::{Request, ResetOption, SettingsOption};
use protocol_core::response::{RegisterBlock, Response};
use protocol_core::settings::{Setting, SettingId, ACCEPTED_MARKER};
use protocol_core::views::{LiveSnapshot, Statistics, VersionInfo};

use crate::config::{self, Config};
use crate::link::{Completion, Failure, Link, LinkStep, Silence, Transmit};
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

/// The bridge's picture of the BMS.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Telemetry {
    /// Latest live snapshot.
    pub snapshot: Option<LiveSnapshot>,
    /// When it was decoded.
    pub snapshot_at: Option<Instant>,
    /// Incremented at every new snapshot.
    pub snapshot_seq: u32,
    /// Latest statistics.
    pub statistics: Option<Statistics>,
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

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Purpose {
    Sync(SyncStep),
    Live,
    Events,
    Stats,
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
    /// The write got no confirmation: the read-back decides, a mismatch is a failure.
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

/// Failed attempts at reading the BMS's settings limits (0x1D) before the bridge
/// goes on without them.
const SYNC_LIMITS_ATTEMPTS: u8 = 3;

/// Most event (timestamp, id) pairs remembered to recognise events already logged.
const SEEN_EVENTS: usize = 64;

/// The bridge. See the module documentation.
#[derive(Debug, Clone)]
pub struct Bridge {
    config: Config,
    link: Link,
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
    sync_retry_at: Instant,
    sync_failures: u8,
    limits_unsupported: bool,
    newest_event: Option<u32>,
    next_error_log: Instant,
    suppressed_errors: u32,
    seen: Deque<(u32, u8), SEEN_EVENTS>,
    was_online: bool,
}

impl Bridge {
    /// A bridge at time `now`, about to sync with the BMS.
    pub fn new(config: Config, now: Instant) -> Self {
        Self {
            config,
            link: Link::new(config),
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
            next_link_log: now + config.link_stats_log_period_us,
            sync_retry_at: now,
            sync_failures: 0,
            limits_unsupported: false,
            newest_event: None,
            next_error_log: now,
            suppressed_errors: 0,
            seen: Deque::new(),
            was_online: true,
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

    /// The current picture of the BMS.
    pub fn telemetry(&self) -> &Telemetry {
        &self.telemetry
    }

    /// Link counters.
    pub fn link_stats(&self) -> crate::link::LinkStats {
        self.link.stats()
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
            self.dropped += 1;
        }
        let _room = self.reports.push_back(r);
    }

    /// Bytes received from the UART at `now`.
    pub fn handle_rx(&mut self, now: Instant, bytes: &[u8]) {
        self.link.on_bytes(now, bytes);
    }

    /// What to do next at `now`.
    pub fn poll(&mut self, now: Instant) -> Action {
        if now >= self.next_link_log {
            self.next_link_log = now + self.config.link_stats_log_period_us;
            let s = self.link.stats();
            self.report(Report::LinkStats(s));
        }
        for _ in 0..16 {
            match self.link.step(now) {
                LinkStep::Send(b) => return Action::Transmit(b),
                LinkStep::Done(c) => self.on_completion(now, c),
                LinkStep::WaitUntil(t) => return Action::WaitUntil(t.min(self.next_link_log)),
                LinkStep::Idle => match self.next_request(now) {
                    Some((req, silence, purpose)) => {
                        self.purpose = purpose;
                        self.link.start(now, req, silence);
                    }
                    None => return Action::WaitUntil(self.next_wake(now).min(self.next_link_log)),
                },
            }
        }
        Action::WaitUntil(now)
    }

    fn next_wake(&self, now: Instant) -> Instant {
        if now < self.hold_until {
            return self.hold_until;
        }
        if !self.link.is_online() {
            return self.next_probe;
        }
        match self.phase {
            Phase::Sync(_) => self.sync_retry_at,
            Phase::Running => {
                if let Some(Job::Write(WriteJob {
                    step: WriteStep::Settle(t),
                    ..
                })) = &self.job
                {
                    return *t;
                }
                self.next_live.min(self.next_events).min(self.next_stats)
            }
        }
        .max(now)
    }

    fn next_request(&mut self, now: Instant) -> Option<(Request, Silence, Purpose)> {
        if now < self.hold_until {
            return None;
        }
        if !self.link.is_online() {
            if now < self.next_probe {
                return None;
            }
            self.next_probe = now + self.config.offline_probe_period_us;
            return Some((version_request(), Silence::Failure, Purpose::Probe));
        }
        if let Phase::Sync(step) = self.phase {
            if now < self.sync_retry_at {
                return None;
            }
            let req = match step {
                SyncStep::Version => version_request(),
                SyncStep::Settings => block(300, 44),
                SyncStep::LimitsMin => Request::ReadSettings {
                    option: SettingsOption::Min,
                    count: 44,
                },
                SyncStep::LimitsMax => Request::ReadSettings {
                    option: SettingsOption::Max,
                    count: 44,
                },
            };
            // A BMS that does not answer 0x1D is not absent: its other answers
            // prove it is there, so that silence does not count towards offline.
            let silence = match step {
                SyncStep::LimitsMin | SyncStep::LimitsMax => Silence::Tolerated,
                _ => Silence::Failure,
            };
            return Some((req, silence, Purpose::Sync(step)));
        }
        // Running. Between two settings of a group (or before a job starts) the
        // live block still gets its turn, so a long group does not blind the bridge.
        if now >= self.next_live && self.at_job_boundary() {
            self.next_live = now + self.config.live_period_us;
            return Some((block(0, 56), Silence::Failure, Purpose::Live));
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
                JobNext::Wait => return None,
                JobNext::Finished => {
                    self.job = None;
                    if matches!(self.phase, Phase::Sync(_)) {
                        // Re-read settings before the next command runs.
                        return self.next_request(now);
                    }
                }
            }
        }
        if now >= self.next_live {
            self.next_live = now + self.config.live_period_us;
            return Some((block(0, 56), Silence::Failure, Purpose::Live));
        }
        if now >= self.next_events {
            self.next_events = now + self.config.events_period_us;
            return Some((Request::ReadNewestEvents, Silence::Failure, Purpose::Events));
        }
        if now >= self.next_stats {
            self.next_stats = now + self.config.stats_period_us;
            return Some((block(100, 18), Silence::Failure, Purpose::Stats));
        }
        None
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

    /// Rev D range and enumerations, then the BMS's own min/max when it reported
    /// them (it may not support 0x1D; it still checks writes itself and NACKs).
    fn check_setting(&self, s: &Setting) -> Result<(), protocol_core::settings::SettingError> {
        s.validate()?;
        if let (Some(min), Some(max)) = (&self.telemetry.limits_min, &self.telemetry.limits_max) {
            if let Some((lo, hi)) = s.id.limits(min, max) {
                s.check_limits(lo, hi)?;
            }
        }
        Ok(())
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
                    if wrote {
                        self.resync();
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

    fn resync(&mut self) {
        self.phase = Phase::Sync(SyncStep::Version);
        self.telemetry.ready = false;
    }

    fn on_completion(&mut self, now: Instant, c: Completion) {
        let online = self.link.is_online();
        if self.was_online && !online {
            self.report(Report::Offline {
                failures: self.link.consecutive_failures(),
            });
            self.telemetry.online = false;
            self.resync();
            self.next_probe = now + self.config.offline_probe_period_us;
            self.abort_job(c.result.clone().err().unwrap_or(Failure::Timeout));
        } else if !self.was_online && online {
            self.report(Report::Online);
            self.telemetry.online = true;
            self.resync();
        }
        self.was_online = online;
        if let Err(f) = &c.result {
            let limits = matches!(
                self.purpose,
                Purpose::Sync(SyncStep::LimitsMin | SyncStep::LimitsMax)
            );
            let quiet = matches!(f, Failure::Silent)
                || (!online && self.purpose == Purpose::Probe)
                || self.purpose == Purpose::Job
                || (limits && self.limits_unsupported);
            if !quiet {
                if now >= self.next_error_log {
                    self.next_error_log = now + self.config.link_error_log_period_us;
                    let suppressed = core::mem::take(&mut self.suppressed_errors);
                    self.report(Report::LinkError {
                        command: c.request.command(),
                        failure: *f,
                        suppressed,
                    });
                } else {
                    self.suppressed_errors += 1;
                }
            }
        }
        match self.purpose {
            Purpose::Sync(step) => self.on_sync(now, step, c.result),
            Purpose::Live => {
                if let Ok(Response::Registers(b)) = c.result {
                    self.on_live(now, &b);
                }
            }
            Purpose::Events => {
                if let Ok(Response::Events(list)) = c.result {
                    self.on_events(&list.events);
                }
            }
            Purpose::Stats => {
                if let Ok(Response::Registers(b)) = c.result {
                    if let Ok(s) = Statistics::from_registers(&b) {
                        self.telemetry.statistics = Some(s);
                    }
                }
            }
            Purpose::Probe => {}
            Purpose::Job => {
                if online {
                    self.on_job(now, c);
                }
            }
        }
    }

    fn abort_job(&mut self, failure: Failure) {
        match self.job.take() {
            Some(Job::Write(w)) => {
                for s in w.items.iter().skip(w.index) {
                    self.report(Report::Write {
                        setting: *s,
                        outcome: WriteOutcome::Failed(failure),
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

    fn on_sync(&mut self, now: Instant, step: SyncStep, result: Result<Response, Failure>) {
        let next = match (step, result) {
            (SyncStep::Version, Ok(Response::Registers(b))) => {
                if let Ok(v) = VersionInfo::from_registers(&b) {
                    self.telemetry.version = Some(v);
                    self.report(Report::Version(v));
                }
                Some(SyncStep::Settings)
            }
            (SyncStep::Settings, Ok(Response::Registers(b))) => {
                self.telemetry.settings = Some(b);
                if self.limits_unsupported {
                    None // known not to answer 0x1D: do not ask at every sync
                } else {
                    Some(SyncStep::LimitsMin)
                }
            }
            (SyncStep::LimitsMin, Ok(Response::Settings { values, .. })) => {
                self.telemetry.limits_min = Some(values);
                Some(SyncStep::LimitsMax)
            }
            (SyncStep::LimitsMax, Ok(Response::Settings { values, .. })) => {
                self.telemetry.limits_max = Some(values);
                None
            }
            // A BMS without 0x1D (NACK, or no valid answer after a few tries): go on
            // without its limits; Rev D's ranges still apply and the BMS still
            // checks writes itself.
            (SyncStep::LimitsMin | SyncStep::LimitsMax, Err(f))
                if matches!(f, Failure::Nack(_))
                    || self.sync_failures + 1 >= SYNC_LIMITS_ATTEMPTS =>
            {
                self.limits_unsupported = true;
                self.telemetry.limits_min = None;
                self.telemetry.limits_max = None;
                None
            }
            _ => {
                self.sync_failures = self.sync_failures.saturating_add(1);
                self.sync_retry_at = now + self.config.live_period_us;
                return;
            }
        };
        self.sync_failures = 0;
        match next {
            Some(s) => self.phase = Phase::Sync(s),
            None => {
                self.phase = Phase::Running;
                self.telemetry.ready = true;
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
        }
    }

    fn on_live(&mut self, now: Instant, b: &RegisterBlock) {
        let Ok(snap) = LiveSnapshot::from_registers(b) else {
            return;
        };
        let previous = self.telemetry.snapshot.as_ref().map(|s| s.status);
        if previous != Some(snap.status) {
            self.report(Report::StatusChanged {
                from: previous,
                to: snap.status,
            });
        }
        if now >= self.next_snapshot_log {
            // Keep to the period's grid (a line every 10 s, not every 10.25 s).
            let period = self.config.snapshot_log_period_us.max(1);
            while self.next_snapshot_log <= now {
                self.next_snapshot_log += period;
            }
            self.report(Report::Snapshot(snapshot_line(&snap)));
        }
        self.telemetry.snapshot = Some(snap);
        self.telemetry.snapshot_at = Some(now);
        self.telemetry.snapshot_seq = self.telemetry.snapshot_seq.wrapping_add(1);
    }

    fn on_events(&mut self, events: &[Event]) {
        let first_read = self.newest_event.is_none() && self.seen.is_empty();
        let mut newest = self.newest_event;
        let mut fresh = 0u8;
        for e in events {
            let key = (e.timestamp_s, e.id.raw());
            if self.seen.iter().any(|k| *k == key) {
                continue;
            }
            // Older than what was already seen: history, not news.
            if let Some(n) = self.newest_event {
                if ts_newer(n, e.timestamp_s) {
                    continue;
                }
            }
            if self.seen.is_full() {
                let _oldest = self.seen.pop_front();
            }
            let _room = self.seen.push_back(key);
            if newest.is_none_or(|n| ts_newer(e.timestamp_s, n)) {
                newest = Some(e.timestamp_s);
            }
            fresh = fresh.saturating_add(1);
            if !first_read {
                self.report(Report::NewEvent(*e));
            }
        }
        self.newest_event = newest;
        if first_read {
            // The log's history at start-up: one line, not a burst of old faults.
            let last = events.iter().copied().reduce(|a, b| {
                if ts_newer(b.timestamp_s, a.timestamp_s) {
                    b
                } else {
                    a
                }
            });
            self.report(Report::EventHistory {
                count: fresh,
                newest: last,
            });
        }
    }

    fn on_job(&mut self, now: Instant, c: Completion) {
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
                    self.hold_until = now + self.config.reboot_wait_us;
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
                        self.hold_until = now + self.config.live_period_us * 2;
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
                match (w.step, c.result) {
                    (WriteStep::ReadCurrent, Ok(Response::Individual(pairs))) => {
                        let (Some(first), second) = (pair(&pairs, a), pair(&pairs, a + 1)) else {
                            self.finish_item(item, WriteOutcome::Failed(Failure::Timeout));
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
                        self.finish_item(item, WriteOutcome::Failed(f));
                    }
                    (WriteStep::ReadCurrent, Ok(_)) => {
                        self.finish_item(item, WriteOutcome::Failed(Failure::Timeout));
                    }
                    (WriteStep::Write, result) => {
                        w.wrote_any = true;
                        match result {
                            Ok(Response::WriteEcho { .. }) => {}
                            // Refused at the first attempt: nothing was written.
                            Err(Failure::Nack(code)) if c.sends <= 1 => {
                                self.finish_item(item, WriteOutcome::Nacked(code));
                                return;
                            }
                            // No clear confirmation (lost, damaged, or a NACK after an
                            // unanswered first attempt that may have been applied):
                            // the read-back decides.
                            Err(Failure::Silent) => w.unconfirmed = Some(Failure::Timeout),
                            Err(f) => w.unconfirmed = Some(f),
                            Ok(_) => w.unconfirmed = Some(Failure::Timeout),
                        }
                        if item.id.restarts_bms() {
                            self.hold_until = now + self.config.reboot_wait_us;
                            w.readback_attempts = config::REBOOT_READBACK_ATTEMPTS;
                            w.step = WriteStep::ReadBack;
                        } else {
                            w.readback_attempts = 1;
                            w.step = WriteStep::Settle(now + self.config.write_settle_us);
                        }
                    }
                    (WriteStep::ReadBack, Ok(Response::Individual(pairs))) => {
                        let Some(first) = pair(&pairs, a) else {
                            self.finish_item(item, WriteOutcome::Failed(Failure::Timeout));
                            return;
                        };
                        let second = pair(&pairs, a + 1);
                        // 323/328 read 0xFFFF once a write is accepted; when they
                        // already did before and the write was not confirmed, the
                        // marker proves nothing.
                        let marker_was_there = item.id.reads_back_marker()
                            && w.current.map(|(f, _)| f) == Some(ACCEPTED_MARKER);
                        let proof = item.matches_readback(first, second)
                            && !(marker_was_there && w.unconfirmed.is_some());
                        let outcome = if proof {
                            WriteOutcome::Verified
                        } else {
                            match w.unconfirmed {
                                Some(Failure::Nack(code)) => WriteOutcome::Nacked(code),
                                Some(f) => WriteOutcome::Failed(f),
                                None => WriteOutcome::Mismatch { read_back: first },
                            }
                        };
                        self.finish_item(item, outcome);
                    }
                    (WriteStep::ReadBack, Err(f)) => {
                        if w.readback_attempts > 1 {
                            w.readback_attempts -= 1;
                            self.hold_until = now + self.config.live_period_us * 2;
                        } else {
                            self.finish_item(item, WriteOutcome::Failed(f));
                        }
                    }
                    (WriteStep::ReadBack, Ok(_)) | (WriteStep::Settle(_), _) => {
                        self.finish_item(item, WriteOutcome::Failed(Failure::Timeout));
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

fn block(start: u16, count: usize) -> Request {
    Request::ReadRegisters {
        start,
        count: count as u8,
    }
}

fn version_request() -> Request {
    block(500, 10)
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
