//! The poll schedule: what to ask the BMS next, and when.
//!
//! [`Schedule`] owns the timers (live block, event log, statistics, the offline
//! probe, the hold after a restart), the block reads in progress — the live block
//! and one confirmed block (version, settings, statistics or the event log) — with
//! the line's quality that sets their piece size, and the live share.
//!
//! `State::next_request` (below) is the priority list, read top to
//! bottom: a hold sends nothing; an offline link gets only the probe; the sync
//! phase its steps ([`super::sync`]); running, in this order —
//! 1. the live read in progress, while it has turns left ([`timing::LIVE_SHARE`],
//!    [`timing::LIVE_SHARE_OVERDUE`] when no snapshot came for twice the usual
//!    time, [`timing::live_overdue_after_us`]);
//! 2. a due live read, between two settings of a group;
//! 3. the confirmed read in progress, then the settings read after writes;
//! 4. the command queue ([`super::writes`]); a reset or clear owns the link;
//! 5. the first snapshot after a (re)sync (for up to
//!    [`timing::FIRST_SNAPSHOT_PRIORITY_US`]);
//! 6. the event log and the statistics when due;
//! 7. the live read (in progress, or due);
//! 8. a 0x1D limits read left over from the sync.
//!
//! Whatever goes out after step 2 gives the live read its next turns, so that
//! neither the live data nor the slower reads starve.

use protocol_core::request::{Request, SettingsOption};
use protocol_core::response::{RegisterBlock, Response};

use super::events::slot_request;
use super::job::JobNext;
use super::purpose::{Ask, Aux, Purpose};
use super::sync::{limits_request, version_request, Phase, SyncStep};
use super::State;
use crate::bms::link::{Failure, Silence};
use crate::bms::reader::{self, Assembled, BlockRead, LineQuality, Mode};
use crate::bms::timing::{self, Timing};
use crate::Instant;

/// `*slot = request`, for the requests that are built whole (the block reads'
/// pieces are written into the slot directly).
fn ask(slot: &mut Request, request: Request, silence: Silence, purpose: Purpose) -> Ask {
    *slot = request;
    (silence, purpose)
}

/// The timers and the block reads in progress.
#[derive(Debug, Clone)]
pub(super) struct Schedule {
    /// Nothing is sent before this (a restart in progress, a read-back retry).
    pub(super) hold_until: Instant,
    pub(super) next_live: Instant,
    pub(super) next_events: Instant,
    pub(super) next_stats: Instant,
    /// Offline: the next probe.
    pub(super) next_probe: Instant,
    /// Sets the piece size of the block reads.
    pub(super) quality: LineQuality,
    /// The live read (reused from one snapshot to the next, see
    /// [`BlockRead::reset`]); in progress while `live_active`.
    live_read: BlockRead,
    live_active: bool,
    aux_read: Option<(Aux, BlockRead)>,
    /// Live requests left before the other reads get a turn.
    live_turns: u8,
    /// The last snapshot seen, and the running mean of the time between
    /// snapshots (see [`timing::live_overdue_after_us`]).
    last_snapshot: Option<Instant>,
    typical_interval_us: Instant,
}

impl Schedule {
    pub(super) fn new(config: &Timing, now: Instant) -> Self {
        Self {
            hold_until: now,
            next_live: now,
            next_events: now,
            next_stats: now,
            next_probe: now,
            quality: LineQuality::default(),
            live_read: BlockRead::new(
                reader::LIVE_SEGMENTS,
                Mode::Window(config.live_period_us),
                now,
            ),
            live_active: false,
            aux_read: None,
            live_turns: 0,
            last_snapshot: None,
            typical_interval_us: 0,
        }
    }

    /// The sync is done: the live data, the event log and the statistics are
    /// due at once.
    pub(super) fn start_running(&mut self, now: Instant) {
        self.next_live = now;
        self.next_events = now;
        self.next_stats = now;
    }

    /// A (re)sync: the reads in progress are dropped.
    pub(super) fn forget_reads(&mut self) {
        self.aux_read = None;
        self.live_active = false;
    }

    /// Starts a live read (its pieces are confirmed against the published
    /// registers or a second read, see [`BlockRead::confirm_pieces`] and
    /// [`on_piece`]).
    fn start_live(&mut self, now: Instant, config: &Timing, slot: &mut Request) -> Ask {
        self.next_live = now.saturating_add(config.live_period_us);
        let window = config.live_assembly_window_us.max(config.live_period_us);
        self.live_read
            .reset(reader::LIVE_SEGMENTS, Mode::Window(window), now);
        self.live_read.confirm_pieces();
        self.live_active = true;
        // A new read uses up a turn, it does not start a fresh share: at a live
        // period shorter than a read, live reads follow each other back to back,
        // and the event log and the statistics get their turn every
        // LIVE_SHARE live requests all the same.
        self.live_turns = self.live_turns.saturating_sub(1);
        self.live_piece(now, slot)
    }

    fn live_piece(&mut self, now: Instant, slot: &mut Request) -> Ask {
        let piece = self.quality.piece();
        if self.live_active {
            self.live_read.request_into(now, piece, slot);
        } else {
            *slot = Request::ReadRegisters {
                start: 0,
                count: 56,
            };
        }
        (Silence::Failure, Purpose::Live)
    }

    fn aux_piece(&mut self, now: Instant, aux: Aux, slot: &mut Request) -> Ask {
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
        read.request_into(now, piece, slot);
        (Silence::Failure, Purpose::Aux(aux))
    }

    /// True when the live data is overdue at `now`, given when the last
    /// snapshot was published (`None`: none yet).
    fn live_overdue(&mut self, now: Instant, snapshot_at: Option<Instant>) -> bool {
        let Some(at) = snapshot_at else {
            return true;
        };
        if self.last_snapshot != Some(at) {
            if let Some(prev) = self.last_snapshot.filter(|&p| p < at) {
                // Running mean over about 8 snapshots.
                let interval = at - prev;
                self.typical_interval_us = if self.typical_interval_us == 0 {
                    interval
                } else {
                    (self.typical_interval_us * 7 + interval) / 8
                };
            }
            self.last_snapshot = Some(at);
        }
        now.saturating_sub(at) > timing::live_overdue_after_us(self.typical_interval_us)
    }

    /// The live read, while one is in progress.
    pub(super) fn live_read(&mut self) -> Option<&mut BlockRead> {
        self.live_active.then_some(&mut self.live_read)
    }

    /// The live read is complete.
    pub(super) fn live_done(&mut self) {
        self.live_active = false;
    }

    /// The confirmed read in progress, if it is the one for `aux`.
    pub(super) fn aux_read(&mut self, aux: Aux) -> Option<&mut BlockRead> {
        match &mut self.aux_read {
            Some((a, r)) if *a == aux => Some(r),
            _ => None,
        }
    }

    /// The confirmed read is complete.
    pub(super) fn aux_done(&mut self) {
        self.aux_read = None;
    }
}

/// Hands a piece's reply to its block read; `published` are the registers of
/// the published snapshot, what pieces of the live read are confirmed against
/// (see [`BlockRead::confirm_pieces`]).
pub(super) fn on_piece<'r>(
    read: &'r mut BlockRead,
    now: Instant,
    result: &'r Result<Response, Failure>,
    published: Option<&RegisterBlock>,
) -> Option<Assembled<'r>> {
    match result {
        Ok(Response::Registers(b)) => read.on_block(now, b),
        Ok(Response::Individual(pairs)) => read.on_pairs(now, pairs, published),
        _ => None,
    }
}

/// The decision over every part: see the module documentation.
impl State {
    /// When [`Self::next_request`] may have something to send.
    pub(super) fn next_wake(&self, now: Instant) -> Instant {
        let sc = &self.schedule;
        if now < sc.hold_until {
            return sc.hold_until;
        }
        if !self.link_online {
            return sc.next_probe;
        }
        match self.sync.phase {
            Phase::Sync(_) => self.sync.retry_at,
            Phase::Running => {
                let mut t = sc.next_live.min(sc.next_events).min(sc.next_stats);
                if let Some(s) = self.writes.settle_until() {
                    t = t.min(s);
                }
                if let Some((_, r)) = self.sync.limits_due {
                    t = t.min(r);
                }
                t
            }
        }
        .max(now)
    }

    /// The next request to send at `now`, if any, written into `slot`.
    pub(super) fn next_request(&mut self, now: Instant, slot: &mut Request) -> Option<Ask> {
        if now < self.schedule.hold_until {
            return None;
        }
        if !self.link_online {
            if now < self.schedule.next_probe {
                return None;
            }
            self.schedule.next_probe = now.saturating_add(self.config.offline_probe_period_us);
            return Some(ask(
                slot,
                version_request(),
                Silence::Failure,
                Purpose::Probe,
            ));
        }
        if let Phase::Sync(step) = self.sync.phase {
            if now < self.sync.retry_at {
                return None;
            }
            return Some(match step {
                SyncStep::Version => self.schedule.aux_piece(now, Aux::Version, slot),
                SyncStep::Settings => self.schedule.aux_piece(now, Aux::Settings, slot),
                // A BMS that does not answer 0x1D is not absent: its other answers
                // prove it is there, so that silence does not count towards offline.
                SyncStep::LimitsMin => limits_request(SettingsOption::Min, slot),
                SyncStep::LimitsMax => limits_request(SettingsOption::Max, slot),
            });
        }
        self.running_request(now, slot)
    }

    /// Running: what to read next. A live read in progress alternates with a
    /// confirmed read in progress; between them, commands, the event log and the
    /// statistics get their turn before the next live read starts, so that no
    /// live period starves them.
    fn running_request(&mut self, now: Instant, slot: &mut Request) -> Option<Ask> {
        let live_busy = self.schedule.live_active;
        if live_busy && self.schedule.live_turns > 0 {
            self.schedule.live_turns -= 1;
            return Some(self.schedule.live_piece(now, slot));
        }
        // Between two settings of a group (or before a job starts) a due live
        // read goes first, so a long group does not blind the bridge.
        if !live_busy
            && now >= self.schedule.next_live
            && self.writes.at_boundary()
            && self.schedule.live_turns > 0
        {
            return Some(self.start_live(now, slot));
        }
        // From here on, whatever goes out gives the live read its next turns:
        // more of them while the live data is overdue.
        let snapshot_at = self.model.telemetry.snapshot_at;
        let overdue = self.schedule.live_overdue(now, snapshot_at);
        self.schedule.live_turns = if overdue {
            timing::LIVE_SHARE_OVERDUE
        } else {
            timing::LIVE_SHARE
        };
        if let Some((aux, _)) = self.schedule.aux_read {
            return Some(self.schedule.aux_piece(now, aux, slot));
        }
        if self.sync.settings_stale && self.writes.idle() {
            // Settings are read again after writes before the next command runs.
            return Some(self.schedule.aux_piece(now, Aux::Settings, slot));
        }
        for _ in 0..timing::COMMAND_QUEUE + 1 {
            if !self.writes.start_next(&self.model.telemetry, &mut self.out) {
                break;
            }
            match self.writes.next_request(now, &mut self.out) {
                JobNext::Send(req, silence) => return Some(ask(slot, req, silence, Purpose::Job)),
                JobNext::Wait => break,
                JobNext::Finished(effect) => {
                    if let Some(e) = effect {
                        self.apply(e);
                    }
                    if self.sync.syncing() || self.sync.settings_stale {
                        // Re-read settings before the next command runs.
                        return self.next_request(now, slot);
                    }
                }
            }
        }
        if self.writes.owns_link() {
            // A reset or clear owns the link until it is done.
            return None;
        }
        // After a (re)sync the first snapshot goes before the event log and the
        // statistics (on a bad line those take many requests), unless the live
        // data takes unusually long.
        let first_snapshot_pending = !self.model.live_base_valid()
            && now
                < self
                    .sync
                    .ready_at
                    .saturating_add(timing::FIRST_SNAPSHOT_PRIORITY_US);
        if first_snapshot_pending {
            return Some(if live_busy {
                self.schedule.live_piece(now, slot)
            } else {
                self.start_live(now, slot)
            });
        }
        if now >= self.schedule.next_events {
            self.schedule.next_events = now.saturating_add(self.config.events_period_us);
            if self.events.needs_full_read() {
                if let Some(event_slot) = self.events.scan_slot() {
                    return Some(ask(
                        slot,
                        slot_request(event_slot),
                        Silence::Failure,
                        Purpose::EventSlot,
                    ));
                }
                return Some(self.schedule.aux_piece(now, Aux::Events, slot));
            }
            return Some(ask(
                slot,
                Request::ReadNewestEvents,
                Silence::Failure,
                Purpose::NewestEvents,
            ));
        }
        if now >= self.schedule.next_stats {
            self.schedule.next_stats = now.saturating_add(self.config.stats_period_us);
            return Some(self.schedule.aux_piece(now, Aux::Stats, slot));
        }
        if live_busy {
            return Some(self.schedule.live_piece(now, slot));
        }
        if now >= self.schedule.next_live {
            return Some(self.start_live(now, slot));
        }
        if let Some((option, t)) = self.sync.limits_due {
            if now >= t && self.writes.idle() {
                return Some(limits_request(option, slot));
            }
        }
        None
    }

    fn start_live(&mut self, now: Instant, slot: &mut Request) -> Ask {
        self.schedule.start_live(now, &self.config, slot)
    }
}
