//! What the inverter output tells the log ([`InverterReport`]), the queue of
//! reports waiting for it, and when changing limits are worth a line.

use heapless::Deque;

use super::control::Limits;
use super::dialect::{OnSilence, Stops, Told};
use super::hold::HoldBudget;
use super::ignored::Ignored;
use super::{packs, StaleMode};
use crate::Instant;

/// What the inverter output tells the log.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum InverterReport {
    /// The inverter's keep-alive is heard.
    InverterSeen,
    /// No keep-alive for the timeout.
    InverterLost,
    /// Telemetry stale: what is being done about it.
    Stale {
        /// Age of the newest snapshot, ms.
        age_ms: u32,
        /// The policy applied.
        policy: StaleMode,
        /// A bridge alone: the hold the pack can afford (see [`super::hold`]; a
        /// spend time of 0: none); `None` for a pack of several, which
        /// leaves the battery.
        hold: Option<HoldBudget>,
    },
    /// The hold is over (its time, or its budget): both sides stop, said
    /// with every signal; then quiet ([`OnSilence::Stops`]: the inverter
    /// stops on silence) or every period until the data is back.
    StaleHoldEnded(OnSilence),
    /// Fresh telemetry again: sending resumed.
    Fresh,
    /// Transmissions fail (no other node acknowledges: error-passive).
    NoAck {
        /// Failed transmissions in a row.
        failures: u32,
    },
    /// Transmissions succeed again.
    BusOk,
    /// The controller went bus-off; recovery is scheduled.
    BusOff {
        /// Bus-offs so far.
        count: u32,
        /// Pause before recovery, ms.
        backoff_ms: u32,
    },
    /// New limits (logged when they change). With a node number: this pack's own.
    Limits(Limits),
    /// The battery's limits this bridge sends as the speaker (logged when
    /// they change).
    BatteryLimits(Limits),
    /// This bridge started or stopped speaking to the inverter for the battery.
    Speaker(bool),
    /// The packs taking part in the battery changed.
    Packs {
        /// Taking part.
        online: u8,
        /// Known but not taking part (lost, stale, faulted).
        offline: u8,
    },
    /// No pack takes part: the speaker says a stop with every signal (then,
    /// towards an inverter that stops on silence, nothing).
    BatteryLost,
    /// What must stop now and why, and what the frames sent tell the
    /// inverter about it, read back from their bytes (logged when it
    /// changes).
    Protection {
        /// What must stop, and why.
        stops: Stops,
        /// What the frames tell.
        told: Told,
    },
    /// The inverter was seen ignoring a stop: from now on every stop goes
    /// out with every signal the dialect has.
    IgnoresStop(Ignored),
    /// The end of a charge moved to another stage ([`super::finish`]).
    Stage(super::finish::Stage),
    /// The rule behind a limit changed ([`super::why`]).
    Reasons(super::why::Reasons),
    /// The doctor found something new on the bus ([`super::doctor`]).
    Doctor(super::doctor::Verdict),
    /// A Luxpower inverter asks the battery to shut down (0x300), or no
    /// longer does: charge and discharge stop meanwhile; the BMS itself is
    /// never switched off.
    ShutdownAsked(bool),
    /// Another bridge sends summaries with this bridge's node number.
    DuplicateNode(u8),
    /// A summary of this node was refused (once until one of it is taken
    /// again); it counts nowhere.
    SummaryRefused(u8, packs::SummaryError),
}

impl InverterReport {
    /// Log level: what needs attention is a warning.
    pub fn level(&self) -> crate::Level {
        match self {
            // The all-clear after a stop (and at start) is news, not a warning.
            Self::Protection { stops, .. } if stops.none() => crate::Level::Info,
            Self::InverterSeen
            | Self::Fresh
            | Self::BusOk
            | Self::Limits(_)
            | Self::BatteryLimits(_)
            | Self::Speaker(_)
            | Self::Stage(_)
            | Self::Reasons(_)
            | Self::Packs { .. } => crate::Level::Info,
            Self::BatteryLost
            | Self::Doctor(_)
            | Self::DuplicateNode(_)
            | Self::SummaryRefused(..)
            | Self::Protection { .. }
            | Self::IgnoresStop(_)
            | Self::ShutdownAsked(_) => crate::Level::Warn,
            Self::InverterLost
            | Self::Stale { .. }
            | Self::StaleHoldEnded(_)
            | Self::NoAck { .. }
            | Self::BusOff { .. } => crate::Level::Warn,
        }
    }
}

/// While the current limits only rise on their way to their targets (a ramp),
/// they are logged at most this often; a limit that falls, and the end of a
/// ramp, are logged at once.
pub const LIMITS_LOG_PERIOD_US: Instant = 10 * crate::SECOND;

/// Whether limits that differ from the ones last logged (at `at`) are logged
/// now: always when one fell or the ramp reached its `targets` (CCL, DCL);
/// on the way up, once a [`LIMITS_LOG_PERIOD_US`].
pub(super) fn limits_log_due(
    last: Option<Limits>,
    at: Instant,
    limits: &Limits,
    targets: (u16, u16),
    now: Instant,
) -> bool {
    let Some(l) = last else {
        return true;
    };
    let rising = limits.ccl_da >= l.ccl_da
        && limits.dcl_da >= l.dcl_da
        && limits.cvl_dv == l.cvl_dv
        && limits.discharge_dv == l.discharge_dv;
    let ramping = limits.ccl_da < targets.0 || limits.dcl_da < targets.1;
    !(rising && ramping) || now.saturating_sub(at) >= LIMITS_LOG_PERIOD_US
}

/// What the inverter output has to log, oldest first; when full, the oldest
/// is dropped.
#[derive(Debug, Clone, Default)]
pub struct Reports(Deque<InverterReport, 8>);

impl Reports {
    /// Adds `r` (dropping the oldest when full).
    pub fn push(&mut self, r: InverterReport) {
        if self.0.is_full() {
            let _ = self.0.pop_front();
        }
        let _ = self.0.push_back(r);
    }

    /// The oldest, taken.
    pub fn pop(&mut self) -> Option<InverterReport> {
        self.0.pop_front()
    }
}
