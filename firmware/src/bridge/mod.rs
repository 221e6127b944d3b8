//! The bridge: poll schedule, telemetry model and write/verify state machine on
//! top of the [`Link`].
//!
//! ## For consumers: one narrow interface
//! Whatever uses the BMS — the chip's CAN output to an inverter, a line protocol
//! to a computer, the host simulator — goes through these, and nothing else:
//! * **read** — [`Bridge::telemetry`] gives the published picture
//!   ([`Telemetry`]: the live snapshot with its age and how it was read, the
//!   statistics, version, settings and the BMS's limits, `online`, `ready`);
//!   [`Bridge::link_stats`] the link counters; [`Bridge::config`] the settings
//!   the bridge runs with (periods, timeouts).
//! * **act** — [`Bridge::submit`] queues a [`Command`] (write settings, reset,
//!   clear); [`Bridge::submit_profile`] queues a settings profile;
//!   [`Bridge::busy`] says whether one is still queued or running.
//! * **hear outcomes** — [`Bridge::next_report`] gives what happened, oldest
//!   first: the outcome of every command ([`Report::Write`],
//!   [`Report::WriteFollowUp`], [`Report::ResetDone`], [`Report::Cleared`]), new
//!   events, status changes, link and line quality.
//!
//! The owner of the bridge (the chip's bridge task, the host harness) also moves
//! bytes and time: [`Bridge::handle_rx`] and [`Bridge::poll`]. On the chip only
//! the bridge task owns the `Bridge`: it publishes what [`Bridge::telemetry`]
//! returns through an embassy-sync `Watch` for the other tasks (`src/chip/`), and a
//! command from another task reaches [`Bridge::submit`] through the bridge task
//! (a bounded channel is the intended shape).
//!
//! ## Where things are
//! | file | what |
//! | --- | --- |
//! | `mod.rs` | this coordinator: the interface above, the link, which part each answer goes to |
//! | `schedule.rs` | what to ask the BMS next and when: timers, the block reads in progress, the live share |
//! | `sync.rs` | the sync phase: version, settings, the BMS's 0x1D limits |
//! | `telemetry.rs` | the published picture, the checks a live block passes, the snapshot line |
//! | `writes.rs` | the command queue and its jobs: write/verify, clear |
//! | `reset.rs` | the reset job and its proof (a newer "System Started" event) |
//! | `report_queue.rs` | the report queue and the periodic, rate-limited lines |
//! | `events.rs` | the BMS event log replies, every event reported once |
//!
//! ## Phases
//! 1. **Sync** — at start-up, after reconnection, after a reset and after every
//!    settings write: version (500-509), settings (300-343), the BMS's own min and
//!    max (0x1D options 1 and 2). Telemetry is not published before this
//!    completes ("ready").
//! 2. **Running** — the live block (0-55) every [`Timing::live_period_us`], the
//!    event log and statistics (100-117) slower; queued commands (settings
//!    groups, reset, clear) run one at a time between live reads.
//!
//! While the link is offline only a probe (the version block) is sent, at
//! [`Timing::offline_probe_period_us`].
//!
//! ## Only what the BMS sent
//! * Register blocks are read through [`BlockRead`](crate::bms::reader::BlockRead):
//!   whole on a clean line, in pieces on a bad one
//!   ([`LineQuality`](crate::bms::reader::LineQuality)). Blocks that do not change by
//!   themselves (version, settings, 0x1D limits, statistics, the event log) are
//!   believed only when two complete reads in a row are identical.
//! * A live block must pass [`checks::check_live`](crate::bms::checks::check_live)
//!   and, against the last published snapshot,
//!   [`checks::check_jump`](crate::bms::checks::check_jump). One that fails is read
//!   again at once; it is published only if an independent second read agrees
//!   with it (no jump between the two, the same verdict), and then flagged with
//!   the check it failed ([`Report::Flagged`]). The first snapshot after a
//!   (re)sync is always confirmed by a second read.
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

mod events;
mod job;
mod purpose;
pub mod report;
mod report_queue;
mod reset;
mod schedule;
mod sync;
mod telemetry;
mod writes;

use heapless::Vec;
use protocol_core::request::Request;
use protocol_core::response::{RegisterBlock, Response};
use protocol_core::settings::{Setting, SettingId};
use protocol_core::views::{Statistics, VersionInfo};

use self::job::Effect;
use self::purpose::{Aux, Purpose};
use self::report_queue::Reports;
use self::schedule::{on_piece, Schedule};
use self::sync::SyncState;
use self::telemetry::TelemetryModel;
use self::writes::Writes;
use crate::bms::event_log::EventTracker;
use crate::bms::link::{CompletionRef, Failure, Link, LinkStats, Next, Transmit};
use crate::bms::timing::{self, Timing};
use crate::bms::wire::{WireFigures, WireVerdict};
use crate::bridge::report::Report;
use crate::Instant;

pub use self::events::KnownEvents;
pub use self::telemetry::{snapshot_line, snapshot_log_due, LiveMeta, Telemetry};

/// What the caller must do next.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// Write these bytes to the UART now, then call [`Bridge::poll`] again.
    Transmit(Transmit),
    /// Wait for received bytes ([`Bridge::handle_rx`]) or until this time, then
    /// call [`Bridge::poll`] again.
    WaitUntil(Instant),
}

/// What the caller must do next, as [`Action`] without the bytes: they stay in
/// the bridge ([`Bridge::transmit_bytes`]) instead of being copied out (an
/// `Action` is 224 bytes, a `Step` 16).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step {
    /// Write [`Bridge::transmit_bytes`] to the UART now, then call
    /// [`Bridge::step`] again.
    Transmit,
    /// Wait for received bytes ([`Bridge::handle_rx`]) or until this time, then
    /// call [`Bridge::step`] again.
    WaitUntil(Instant),
}

/// A request from the rest of the firmware.
#[derive(Debug, Clone, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Command {
    /// Write and verify these settings, one by one, each checked against the
    /// pack's cell chemistry as said (the relations between settings always).
    ApplySettings(
        Vec<Setting, { timing::MAX_SETTINGS_GROUP }>,
        protocol_core::settings::ChemistryCheck,
    ),
    /// Restart the BMS (0x02 option 0x05).
    ResetBms,
    /// Clear the event log (0x02 option 0x01).
    ClearEvents,
    /// Clear the statistics (0x02 option 0x02).
    ClearStatistics,
}

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

/// Everything of the bridge but the link: one part per concern (see the module
/// documentation), and what the coordinator itself keeps.
#[derive(Debug, Clone)]
struct State {
    config: Timing,
    /// `Link::is_online`, refreshed after every call into the link.
    link_online: bool,
    /// `Link::consecutive_failures`, refreshed with `link_online`.
    link_failures: u8,
    /// The link was online at the last completion.
    was_online: bool,
    /// What the request in flight is for.
    purpose: Purpose,
    schedule: Schedule,
    sync: SyncState,
    model: TelemetryModel,
    writes: Writes,
    events: EventTracker,
    known_events: KnownEvents,
    out: Reports,
    /// The link counters when the line quality period began.
    wire_base: LinkStats,
    /// The wire in the last complete line quality period.
    wire: (WireFigures, WireVerdict),
}

impl Bridge {
    /// A bridge at time `now`, about to sync with the BMS.
    pub fn new(config: Timing, now: Instant) -> Self {
        let link = Link::new(config);
        let mut s = State::new(config, now);
        s.link_online = link.is_online();
        s.link_failures = link.consecutive_failures();
        Self { link, s }
    }

    /// Queues a command; gives it back when the queue is full.
    #[allow(clippy::result_large_err)] // the command itself is handed back
    pub fn submit(&mut self, command: Command) -> Result<(), Command> {
        self.s.writes.submit(command)
    }

    /// Queues the settings of a profile (see [`crate::bms::profile`]) as one group. An
    /// empty profile queues nothing. Entries beyond [`timing::MAX_SETTINGS_GROUP`]
    /// are queued as further groups.
    #[allow(clippy::result_large_err)] // the command itself is handed back
    pub fn submit_profile(&mut self, profile: &[(SettingId, i32)]) -> Result<(), Command> {
        for chunk in profile.chunks(timing::MAX_SETTINGS_GROUP) {
            let mut items = Vec::new();
            for &(id, value) in chunk {
                let _fits = items.push(Setting { id, value }); // chunk <= capacity
            }
            self.submit(Command::ApplySettings(
                items,
                protocol_core::settings::ChemistryCheck::Inferred,
            ))?;
        }
        Ok(())
    }

    /// The current picture of the BMS.
    pub fn telemetry(&self) -> &Telemetry {
        &self.s.model.telemetry
    }

    /// The BMS event log as far as the bridge knows it (the start-up history and
    /// every event since, oldest first).
    pub fn events(&self) -> &KnownEvents {
        &self.s.known_events
    }

    /// The settings the bridge runs with.
    pub fn config(&self) -> &Timing {
        &self.s.config
    }

    /// Link counters.
    pub fn link_stats(&self) -> crate::bms::link::LinkStats {
        self.link.stats()
    }

    /// Registers per request the block reads use now (the line's quality).
    pub fn piece_registers(&self) -> u16 {
        self.s.schedule.quality.piece()
    }

    /// Replaces the link counters (see [`Link::preset_stats`]).
    pub fn preset_link_stats(&mut self, stats: crate::bms::link::LinkStats) {
        self.link.preset_stats(stats);
        // The wire's window starts from them.
        self.s.wire_base = stats;
    }

    /// The wire in the last complete line quality period
    /// ([`Timing::line_quality_log_period_us`]): figures and verdict
    /// ([`crate::bms::wire`]). Healthy with no figures before the first period
    /// ends.
    pub fn wire(&self) -> (WireFigures, WireVerdict) {
        self.s.wire
    }

    /// True while a command is queued or running.
    pub fn busy(&self) -> bool {
        self.s.writes.busy()
    }

    /// True when no BMS reply can be on its way at `now` (no request
    /// outstanding, the line quiet): the moment for work that stops the CPU,
    /// such as a flash write ([`crate::config::store`]). Nothing is sent while
    /// the caller does not call [`Bridge::step`] again: the poll is held.
    pub fn quiet(&self, now: Instant) -> bool {
        self.link.quiet(now)
    }

    /// When the link turns quiet if nothing more happens ([`Bridge::quiet`];
    /// `None`: a transaction is under way).
    pub fn quiet_from(&self) -> Option<Instant> {
        self.link.quiet_from()
    }

    /// The next report to log, oldest first.
    pub fn next_report(&mut self) -> Option<Report> {
        self.s.out.next()
    }

    /// Bytes received from the UART at `now`.
    pub fn handle_rx(&mut self, now: Instant, bytes: &[u8]) {
        self.link.on_bytes(now, bytes);
        self.refresh_link();
    }

    /// Where the UART driver can write received bytes directly, instead of
    /// into a buffer of its own for [`Bridge::handle_rx`] to copy: the decoder's
    /// free space. It is the same space until [`Bridge::handle_received`], and
    /// never empty.
    pub fn rx_buffer(&mut self) -> &mut [u8] {
        self.link.rx_buffer()
    }

    /// The first `n` bytes of [`Bridge::rx_buffer`] were received at `now`
    /// (what [`Bridge::handle_rx`] does with them, without the copy).
    pub fn handle_received(&mut self, now: Instant, n: usize) {
        self.link.on_received(now, n);
        self.refresh_link();
    }

    fn refresh_link(&mut self) {
        self.s.link_online = self.link.is_online();
        self.s.link_failures = self.link.consecutive_failures();
    }

    /// What to do next at `now`, with the bytes to send copied out: as
    /// [`Bridge::step`] and [`Bridge::transmit_bytes`].
    pub fn poll(&mut self, now: Instant) -> Action {
        match self.step(now) {
            Step::Transmit => {
                let mut bytes = Transmit::new();
                let _fits = bytes.extend_from_slice(self.transmit_bytes()); // same capacity
                Action::Transmit(bytes)
            }
            Step::WaitUntil(t) => Action::WaitUntil(t),
        }
    }

    /// The bytes to write after [`Step::Transmit`] (empty when there is nothing
    /// to send).
    pub fn transmit_bytes(&self) -> &[u8] {
        self.link.transmit().map(|b| b.as_slice()).unwrap_or(&[])
    }

    /// What to do next at `now`. After [`Step::Transmit`], write
    /// [`Bridge::transmit_bytes`].
    pub fn step(&mut self, now: Instant) -> Step {
        self.refresh_link();
        let s = &mut self.s;
        let (link_stats, line_quality) = s.out.periodic_due(now, &s.config);
        if link_stats {
            let stats = self.link.stats();
            s.out.push(Report::LinkStats(stats));
        }
        if line_quality {
            s.log_quality(self.link.stats());
        }
        let next_log = s.out.next_periodic();
        for _ in 0..16 {
            let next = self.link.next(now);
            self.refresh_link();
            match next {
                Next::Send => {
                    if self.link.transmit().is_some() {
                        return Step::Transmit;
                    }
                }
                Next::Done => {
                    // Handled where the link keeps it, then dropped.
                    if let Some(c) = self.link.completion() {
                        self.s.on_completion(now, &c);
                    }
                    self.link.clear_completion();
                }
                Next::WaitUntil(t) => return Step::WaitUntil(t.min(next_log)),
                // The request is written where the link keeps it.
                Next::Idle => match self
                    .link
                    .request_slot()
                    .and_then(|slot| self.s.next_request(now, slot))
                {
                    Some((silence, purpose)) => {
                        self.s.purpose = purpose;
                        // Pieces (0x09 block reads on a bad line, event slots)
                        // are small: a lost or broken answer is not waited
                        // for as long.
                        let piece = matches!(
                            purpose,
                            Purpose::Live | Purpose::Aux(_) | Purpose::EventSlot
                        ) && matches!(self.link.request(), Request::ReadIndividual(_));
                        if piece {
                            self.link.start_written_piece(now, silence);
                        } else {
                            let timeout = self.s.config.response_timeout_us;
                            self.link.start_written(now, silence, timeout);
                        }
                    }
                    None => return Step::WaitUntil(self.s.next_wake(now).min(next_log)),
                },
            }
        }
        Step::WaitUntil(now)
    }
}

impl State {
    fn new(config: Timing, now: Instant) -> Self {
        Self {
            config,
            link_online: true,
            link_failures: 0,
            was_online: true,
            purpose: Purpose::Probe,
            schedule: Schedule::new(&config, now),
            sync: SyncState::new(now),
            model: TelemetryModel::new(now),
            writes: Writes::new(),
            events: EventTracker::new(),
            known_events: KnownEvents::default(),
            out: Reports::new(&config, now),
            wire_base: LinkStats::default(),
            wire: (WireFigures::default(), WireVerdict::Healthy),
        }
    }

    fn log_quality(&mut self, stats: LinkStats) {
        let window = WireFigures::between(&self.wire_base, &stats);
        self.wire_base = stats;
        let verdict = window.verdict();
        self.wire = (window.figures, verdict);
        if verdict.is_degraded() {
            self.out.push(Report::Wire {
                figures: window.figures,
                verdict,
            });
        }
        let (attempts, clean) = self.schedule.quality.take_window();
        let snapshots = self.model.take_window(&mut self.out);
        // A clean line says nothing; a degraded one says how degraded, once per
        // period, instead of a line per failed request.
        if attempts > clean || self.schedule.quality.level > 0 {
            self.out.push(Report::LineQuality {
                attempts,
                clean,
                piece_registers: self.schedule.quality.piece(),
                snapshots,
            });
        }
    }

    /// Everything is read again, from the version block on.
    fn resync(&mut self) {
        self.sync.restart();
        self.model.restart();
        self.schedule.forget_reads();
    }

    /// The sync completed (the sync part is running already).
    fn on_ready(&mut self, now: Instant) {
        self.schedule.start_running(now);
        let cells = self
            .model
            .telemetry
            .settings
            .as_ref()
            .and_then(|b| b.get(SettingId::NumberOfSeriesCells.address()))
            .unwrap_or(0);
        self.out.push(Report::Ready {
            series_cells: cells,
        });
    }

    /// What a job leaves to the rest of the bridge.
    fn apply(&mut self, effect: Effect) {
        match effect {
            Effect::Hold(until) => self.schedule.hold_until = until,
            Effect::Resync => self.resync(),
            Effect::RereadSettings => self.sync.settings_stale = true,
            Effect::EventsCleared => self.known_events.clear(),
            Effect::ReadBack {
                address,
                first,
                second,
            } => {
                if let Some(b) = self.model.telemetry.settings.as_mut() {
                    b.set(address, first);
                    if let Some(s) = second {
                        b.set(address + 1, s);
                    }
                }
            }
        }
    }

    /// The link went offline or came back with this completion.
    fn on_link_change(&mut self, now: Instant, c: &CompletionRef<'_>, online: bool) {
        if self.was_online && !online {
            self.out.push(Report::Offline {
                failures: self.link_failures,
            });
            self.model.telemetry.online = false;
            self.resync();
            self.schedule.next_probe = now.saturating_add(self.config.offline_probe_period_us);
            let failure = c.result.as_ref().err().copied().unwrap_or(Failure::Timeout);
            self.writes.abort(failure, &mut self.out);
        } else if !self.was_online && online {
            self.out.push(Report::Online);
            self.model.telemetry.online = true;
            self.resync();
        }
        self.was_online = online;
    }

    /// A transaction finished: the link's state first, then the answer goes to
    /// the part its request was for.
    fn on_completion(&mut self, now: Instant, c: &CompletionRef<'_>) {
        let online = self.link_online;
        self.on_link_change(now, c, online);
        let block_read = matches!(
            self.purpose,
            Purpose::Live | Purpose::Aux(_) | Purpose::EventSlot
        );
        if block_read {
            self.schedule.quality.note(c.sends, c.result.is_ok());
        }
        if let Err(f) = &c.result {
            let limits = matches!(self.purpose, Purpose::Limits(_));
            // Failed pieces of block reads are expected on a bad line and retried:
            // they show up in the line quality figure, not one line each.
            let quiet = matches!(f, Failure::Silent)
                || (!online && self.purpose == Purpose::Probe)
                || self.purpose == Purpose::Job
                || block_read
                || (limits && (self.sync.limits_unsupported || !self.sync.syncing()));
            if !quiet {
                self.out.link_error(now, &self.config, c.request, *f);
            }
        }
        if !online {
            return;
        }
        match self.purpose {
            Purpose::Live => match &c.result {
                Ok(Response::Registers(_) | Response::Individual(_)) => {
                    let Some(read) = self.schedule.live_read() else {
                        return; // not a live read in progress (any more)
                    };
                    let published = self.model.telemetry.live_registers.as_ref();
                    // Borrowed where it was assembled: the block is not moved.
                    let again = match &on_piece(read, now, c.result, published) {
                        Some(a) => self.model.on_live(now, a, &self.config, &mut self.out),
                        None => return,
                    };
                    self.schedule.live_done();
                    if again {
                        self.schedule.next_live = now; // read again at once
                    }
                }
                _ => {
                    if let Some(read) = self.schedule.live_read() {
                        read.on_failure();
                    }
                }
            },
            Purpose::Aux(aux) => {
                let done = match (c.result, self.schedule.aux_read(aux)) {
                    (Ok(Response::Registers(_) | Response::Individual(_)), Some(read)) => {
                        // Kept: the next step replaces the read.
                        on_piece(read, now, c.result, None).map(|a| a.block.clone())
                    }
                    (_, Some(read)) => {
                        read.on_failure();
                        self.sync.retry_later(now, &self.config);
                        None
                    }
                    (_, None) => None,
                };
                if let Some(block) = done {
                    self.schedule.aux_done();
                    self.on_aux(now, aux, block);
                }
            }
            Purpose::Limits(option) => {
                let telemetry = &mut self.model.telemetry;
                if self
                    .sync
                    .on_limits(now, option, c.result, &self.config, telemetry)
                {
                    self.on_ready(now);
                }
            }
            Purpose::NewestEvents => {
                let model = &self.model;
                let expected = || model.expected_bms_clock(now);
                events::on_newest(
                    &mut self.events,
                    &mut self.known_events,
                    c,
                    expected,
                    &mut self.out,
                );
                if self.events.needs_full_read() {
                    // Fill the gap now rather than at the next events period.
                    self.schedule.next_events = now;
                }
            }
            Purpose::EventSlot => {
                events::on_slot(
                    &mut self.events,
                    &mut self.known_events,
                    c.result,
                    &mut self.out,
                );
                if self.events.needs_full_read() {
                    self.schedule.next_events = now; // go on with the scan / full read
                }
            }
            Purpose::Probe => {}
            Purpose::Job => {
                if let Some(e) = self.writes.on_reply(now, c, &self.config, &mut self.out) {
                    self.apply(e);
                }
            }
        }
    }

    /// A confirmed block read finished.
    fn on_aux(&mut self, now: Instant, aux: Aux, b: RegisterBlock) {
        match aux {
            Aux::Version => {
                if let Ok(v) = VersionInfo::from_registers(&b) {
                    self.model.telemetry.version = Some(v);
                    self.out.push(Report::Version(v));
                }
                self.sync.on_version(now);
            }
            Aux::Settings => {
                self.writes.resolve(&b, &mut self.out);
                self.model.telemetry.settings = Some(b);
                if self.sync.on_settings(now, &mut self.model.telemetry) {
                    self.on_ready(now);
                }
            }
            Aux::Stats => {
                if let Ok(s) = Statistics::from_registers(&b) {
                    self.model.telemetry.statistics = Some(s);
                    self.model.telemetry.statistics_registers = Some(b);
                }
            }
            Aux::Events => {
                events::on_full(&mut self.events, &mut self.known_events, &b, &mut self.out)
            }
        }
    }
}
