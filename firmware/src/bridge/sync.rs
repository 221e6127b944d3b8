//! The sync phase: what the bridge must know before it publishes anything.
//!
//! At start-up, after a reconnection, after a reset and after a write to 340 the
//! bridge reads, in this order, the version block (500-509), the settings
//! (300-343) and the BMS's own minimum and maximum of each setting (0x1D options
//! 1 and 2). Then it is *ready* ([`super::Telemetry::ready`]) and running.
//!
//! The 0x1D limits are believed only when two replies in a row are identical. A
//! BMS that NACKs 0x1D does not support it: the bridge goes on without its limits
//! for good (Rev D's ranges still apply). One that gives no valid answer
//! [`SYNC_LIMITS_ATTEMPTS`] times in a row is not waited for: the limits are
//! asked for again later, while running ([`SyncState::limits_due`]). The settings
//! read after writes also asks for them again.
//!
//! [`SyncState`] owns the phase and these retries; the version and settings
//! blocks themselves are confirmed block reads of the schedule
//! ([`super::schedule`]).

use protocol_core::request::{Request, SettingsOption};
use protocol_core::response::{RegisterBlock, Response};

use super::purpose::{Ask, Purpose};
use super::telemetry::Telemetry;
use crate::bms::link::{Failure, Silence};
use crate::bms::timing::Timing;
use crate::Instant;

/// Failed attempts at reading the BMS's settings limits (0x1D) before the bridge
/// goes on without them (and tries again later, at the statistics period).
const SYNC_LIMITS_ATTEMPTS: u8 = 3;

/// The step of the sync phase, in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum SyncStep {
    Version,
    Settings,
    LimitsMin,
    LimitsMax,
}

/// Syncing, or running (ready).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Phase {
    Sync(SyncStep),
    Running,
}

/// The phase and what the sync still has to learn.
#[derive(Debug, Clone)]
pub(super) struct SyncState {
    pub(super) phase: Phase,
    /// Syncing: the next sync request is not sent before this.
    pub(super) retry_at: Instant,
    failures: u8,
    /// The BMS NACKed 0x1D: it is not asked again.
    pub(super) limits_unsupported: bool,
    /// A 0x1D read to make while running, and when.
    pub(super) limits_due: Option<(SettingsOption, Instant)>,
    /// The first of two 0x1D replies that must agree.
    limits_candidate: Option<RegisterBlock>,
    /// Settings were written: read them again before the next command.
    pub(super) settings_stale: bool,
    /// When the last sync completed.
    pub(super) ready_at: Instant,
}

impl SyncState {
    pub(super) fn new(now: Instant) -> Self {
        Self {
            phase: Phase::Sync(SyncStep::Version),
            retry_at: now,
            failures: 0,
            limits_unsupported: false,
            limits_due: None,
            limits_candidate: None,
            settings_stale: false,
            ready_at: now,
        }
    }

    pub(super) fn syncing(&self) -> bool {
        matches!(self.phase, Phase::Sync(_))
    }

    /// Start again from the version block.
    pub(super) fn restart(&mut self) {
        self.phase = Phase::Sync(SyncStep::Version);
        self.failures = 0;
        self.limits_candidate = None;
        self.settings_stale = false;
    }

    /// A sync block read failed: its next piece waits a little.
    pub(super) fn retry_later(&mut self, now: Instant, config: &Timing) {
        if self.syncing() {
            self.retry_at = now.saturating_add(config.live_period_us.min(crate::SECOND));
        }
    }

    /// The version block is read.
    pub(super) fn on_version(&mut self, now: Instant) {
        self.next(now, SyncStep::Settings);
    }

    /// The settings are read (in the sync, or after writes). True when this
    /// completes the sync (see [`Self::done`]).
    pub(super) fn on_settings(&mut self, now: Instant, telemetry: &mut Telemetry) -> bool {
        self.settings_stale = false;
        if self.phase == Phase::Running {
            if !self.limits_unsupported {
                self.limits_candidate = None;
                self.limits_due = Some((SettingsOption::Min, now));
            }
            false
        } else if self.limits_unsupported {
            // Known not to answer 0x1D: do not ask at every sync.
            self.done(now, telemetry)
        } else {
            self.next(now, SyncStep::LimitsMin);
            false
        }
    }

    fn next(&mut self, now: Instant, step: SyncStep) {
        if let Phase::Sync(_) = self.phase {
            self.failures = 0;
            self.retry_at = now;
            self.phase = Phase::Sync(step);
        }
    }

    /// Ends the sync: running, ready. False when it was not syncing. The caller
    /// restarts the running timers and reports [`crate::bridge::report::Report::Ready`].
    fn done(&mut self, now: Instant, telemetry: &mut Telemetry) -> bool {
        if !self.syncing() {
            return false;
        }
        self.failures = 0;
        self.phase = Phase::Running;
        telemetry.ready = true;
        self.ready_at = now;
        true
    }

    /// 0x1D replies: believed when two in a row are identical. True when this
    /// completes the sync (see [`Self::done`]).
    pub(super) fn on_limits(
        &mut self,
        now: Instant,
        option: SettingsOption,
        result: &Result<Response, Failure>,
        config: &Timing,
        telemetry: &mut Telemetry,
    ) -> bool {
        let in_sync = self.syncing();
        let next = match result {
            Ok(Response::Settings { values, .. }) => {
                if self.limits_candidate.as_ref() != Some(values) {
                    // First of two, or two that differ: ask again.
                    self.limits_candidate = Some(values.clone());
                    Some((option, now))
                } else {
                    self.limits_candidate = None;
                    self.failures = 0;
                    if option == SettingsOption::Min {
                        telemetry.limits_min = Some(values.clone());
                        Some((SettingsOption::Max, now))
                    } else {
                        telemetry.limits_max = Some(values.clone());
                        None
                    }
                }
            }
            // A BMS without 0x1D: go on without its limits for good; Rev D's
            // ranges still apply and the BMS still checks writes itself.
            Err(Failure::Nack(_)) => {
                self.limits_unsupported = true;
                telemetry.limits_min = None;
                telemetry.limits_max = None;
                None
            }
            _ => {
                self.failures = self.failures.saturating_add(1);
                if self.failures >= SYNC_LIMITS_ATTEMPTS {
                    // No valid answer on this line for now: go on without the
                    // limits (or with the ones read before) and ask again later.
                    self.failures = 0;
                    self.limits_candidate = None;
                    let later = now.saturating_add(config.stats_period_us);
                    if in_sync {
                        self.limits_due = Some((option, later));
                        return self.done(now, telemetry);
                    }
                    Some((option, later))
                } else {
                    Some((option, now.saturating_add(config.live_period_us)))
                }
            }
        };
        if in_sync {
            match next {
                Some((SettingsOption::Max, t)) => {
                    self.phase = Phase::Sync(SyncStep::LimitsMax);
                    self.retry_at = t;
                    false
                }
                Some((_, t)) => {
                    self.retry_at = t;
                    false
                }
                None => self.done(now, telemetry),
            }
        } else {
            self.limits_due = next;
            false
        }
    }
}

/// The version block (500-509), also the probe of an offline link.
pub(super) fn version_request() -> Request {
    Request::ReadRegisters {
        start: 500,
        count: 10,
    }
}

/// A 0x1D read of the BMS's own limits. Silence is tolerated: a BMS that does
/// not answer 0x1D is not absent (its other answers prove it is there).
pub(super) fn limits_request(option: SettingsOption, slot: &mut Request) -> Ask {
    *slot = Request::ReadSettings { option, count: 44 };
    (Silence::Tolerated, Purpose::Limits(option))
}
