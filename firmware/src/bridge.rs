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
use protocol_core::events::{EventId, OnlineStatus};
use protocol_core::request::{Request, ResetOption, SettingsOption};
use protocol_core::response::{RegisterBlock, Response};
use protocol_core::settings::{Setting, SettingId};
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
    Send,
    Confirm { attempts: u8 },
}

#[derive(Debug, Clone, PartialEq, Eq)]
enum Job {
    Write(WriteJob),
    Reset(ResetStep),
    Clear(ResetOption),
}

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
            return Some((req, Silence::Failure, Purpose::Sync(step)));
        }
        // Running.
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

    fn start_job(&mut self, cmd: Command) -> Option<Job> {
        match cmd {
            Command::ResetBms => Some(Job::Reset(ResetStep::Send)),
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
            Job::Reset(ResetStep::Send) => JobNext::Send(
                Request::ResetClear(ResetOption::ResetBms),
                Silence::Expected,
            ),
            Job::Reset(ResetStep::Confirm { .. }) => JobNext::Send(block(114, 1), Silence::Failure),
            Job::Write(w) => {
                let Some(item) = w.items.get(w.index).copied() else {
                    let wrote = w.wrote_any;
                    if wrote {
                        self.resync();
                    }
                    return JobNext::Finished;
                };
                let reg_count = usize::from(item.id.register_count());
                match w.step {
                    WriteStep::ReadCurrent | WriteStep::ReadBack => {
                        JobNext::Send(block(item.id.address(), reg_count), Silence::Failure)
                    }
                    WriteStep::Settle(until) => {
                        if now < until {
                            JobNext::Wait
                        } else {
                            w.step = WriteStep::ReadBack;
                            JobNext::Send(block(item.id.address(), reg_count), Silence::Failure)
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
                        match Request::write_registers(item.id.address(), &values) {
                            Ok(req) => JobNext::Send(req, Silence::Failure),
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
            let quiet = matches!(f, Failure::Silent)
                || (!online && self.purpose == Purpose::Probe)
                || self.purpose == Purpose::Job;
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
                Some(SyncStep::LimitsMin)
            }
            (SyncStep::LimitsMin, Ok(Response::Settings { values, .. })) => {
                self.telemetry.limits_min = Some(values);
                Some(SyncStep::LimitsMax)
            }
            (SyncStep::LimitsMax, Ok(Response::Settings { values, .. })) => {
                self.telemetry.limits_max = Some(values);
                None
            }
            // A BMS without 0x1D: go on without its limits (it still checks writes).
            (SyncStep::LimitsMin | SyncStep::LimitsMax, Err(Failure::Nack(_))) => {
                self.telemetry.limits_min = None;
                self.telemetry.limits_max = None;
                None
            }
            _ => {
                self.sync_retry_at = now + self.config.live_period_us;
                return;
            }
        };
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
            self.next_snapshot_log = now + self.config.snapshot_log_period_us;
            self.report(Report::Snapshot(snapshot_line(&snap)));
        }
        self.telemetry.snapshot = Some(snap);
        self.telemetry.snapshot_at = Some(now);
        self.telemetry.snapshot_seq = self.telemetry.snapshot_seq.wrapping_add(1);
    }

    fn on_events(&mut self, events: &[protocol_core::events::Event]) {
        let newest = self.newest_event;
        let mut max = newest;
        for e in events {
            let key = (e.timestamp_s, e.id.raw());
            let is_new = match newest {
                None => true,
                Some(n) => {
                    e.timestamp_s > n
                        || (e.timestamp_s == n && !self.seen.iter().any(|k| *k == key))
                }
            };
            if is_new && !self.seen.iter().any(|k| *k == key) {
                if self.seen.is_full() {
                    let _oldest = self.seen.pop_front();
                }
                let _room = self.seen.push_back(key);
                self.report(Report::NewEvent(*e));
            }
            max = Some(max.map_or(e.timestamp_s, |m: u32| m.max(e.timestamp_s)));
        }
        self.newest_event = max;
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
            Job::Reset(ResetStep::Send) => {
                // ACK or silence are both normal (HARDWARE-NOTES); a NACK is not.
                if matches!(c.result, Err(Failure::Nack(_))) {
                    self.job = None;
                    self.report(Report::ResetDone { confirmed: false });
                } else {
                    self.hold_until = now + self.config.reboot_wait_us;
                    *job = Job::Reset(ResetStep::Confirm {
                        attempts: config::REBOOT_READBACK_ATTEMPTS,
                    });
                }
            }
            Job::Reset(ResetStep::Confirm { attempts }) => {
                let confirmed = match &c.result {
                    Ok(Response::Registers(b)) => b.get(114).map(|v| v & 0xFF == 0x04),
                    _ => None,
                };
                match confirmed {
                    Some(ok) => {
                        self.job = None;
                        self.report(Report::ResetDone { confirmed: ok });
                        self.resync();
                    }
                    None if *attempts > 1 => {
                        *attempts -= 1;
                        self.hold_until = now + self.config.live_period_us;
                    }
                    None => {
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
                match (w.step, c.result) {
                    (WriteStep::ReadCurrent, Ok(Response::Registers(b))) => {
                        let a = item.id.address();
                        let (Some(first), second) = (b.get(a), b.get(a + 1)) else {
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
                        let restart = item.id.restarts_bms();
                        match result {
                            Ok(Response::WriteEcho { .. }) => {}
                            Err(Failure::Nack(code)) => {
                                self.finish_item(item, WriteOutcome::Nacked(code));
                                return;
                            }
                            // No confirmation: the read-back will tell what happened.
                            Err(f) => w.unconfirmed = Some(f),
                            Ok(_) => w.unconfirmed = Some(Failure::Timeout),
                        }
                        if restart {
                            self.hold_until = now + self.config.reboot_wait_us;
                            w.readback_attempts = config::REBOOT_READBACK_ATTEMPTS;
                            w.step = WriteStep::ReadBack;
                        } else {
                            w.readback_attempts = 1;
                            w.step = WriteStep::Settle(now + self.config.write_settle_us);
                        }
                    }
                    (WriteStep::ReadBack, Ok(Response::Registers(b))) => {
                        let a = item.id.address();
                        let Some(first) = b.get(a) else {
                            self.finish_item(item, WriteOutcome::Failed(Failure::Timeout));
                            return;
                        };
                        let second = b.get(a + 1);
                        let outcome = if item.matches_readback(first, second) {
                            WriteOutcome::Verified
                        } else if let Some(f) = w.unconfirmed {
                            WriteOutcome::Failed(f)
                        } else {
                            WriteOutcome::Mismatch { read_back: first }
                        };
                        self.finish_item(item, outcome);
                    }
                    (WriteStep::ReadBack, Err(f)) => {
                        if w.readback_attempts > 1 {
                            w.readback_attempts -= 1;
                            self.hold_until = now + self.config.live_period_us;
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

/// True for the statuses worth a warning.
pub fn is_fault(status: OnlineStatus) -> bool {
    status == OnlineStatus::Fault
}

/// True for event IDs worth a warning.
pub fn is_alarm(id: EventId) -> bool {
    matches!(
        id.severity(),
        protocol_core::events::Severity::Fault | protocol_core::events::Severity::Warning
    )
}
