//! The reset command (0x02 option 0x05) and its proof.
//!
//! Read the event log for the newest "System Started" before the reset → send
//! the reset (an ACK or silence are both normal, HARDWARE-NOTES; a NACK is a
//! refusal) → wait [`Timing::reboot_wait_us`] → read the event log again, up to
//! [`timing::REBOOT_READBACK_ATTEMPTS`] times: a "System Started" newer than the
//! one before proves the restart ([`Report::ResetDone`]). Either way everything
//! is read again afterwards (a resync).
//!
//! It runs as a job of [`super::writes::Writes`], which owns the command queue.

use protocol_core::events::{Event, EventId};
use protocol_core::request::{Request, ResetOption};
use protocol_core::response::Response;

use super::job::{Effect, JobNext};
use super::Reports;
use crate::bms::event_log::ts_newer;
use crate::bms::link::{CompletionRef, Failure, Silence};
use crate::bms::timing::{self, Timing};
use crate::bridge::report::Report;
use crate::Instant;

/// Where a reset is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum ResetStep {
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

impl ResetStep {
    /// The request of this step.
    pub(super) fn request(&self) -> JobNext {
        match self {
            Self::Before => JobNext::Send(Request::ReadAllEvents, Silence::Failure),
            Self::Send { .. } => JobNext::Send(
                Request::ResetClear(ResetOption::ResetBms),
                Silence::Expected,
            ),
            Self::Confirm { .. } => JobNext::Send(Request::ReadAllEvents, Silence::Tolerated),
        }
    }

    /// The answer to this step's request: moves on, and says whether the reset
    /// is over (reported) and what it leaves to the rest of the bridge.
    pub(super) fn on_reply(
        &mut self,
        now: Instant,
        c: &CompletionRef<'_>,
        config: &Timing,
        out: &mut Reports,
    ) -> (bool, Option<Effect>) {
        match self {
            Self::Before => {
                let last_start = match &c.result {
                    Ok(Response::Events(list)) => newest_start(&list.events),
                    _ => {
                        // Without the log there is no way to prove the restart.
                        out.push(Report::ResetDone { confirmed: false });
                        return (true, None);
                    }
                };
                *self = Self::Send { last_start };
                (false, None)
            }
            Self::Send { last_start } => {
                let last_start = *last_start;
                // ACK or silence are both normal (HARDWARE-NOTES); a NACK is not.
                if matches!(c.result, Err(Failure::Nack(_))) {
                    out.push(Report::ResetDone { confirmed: false });
                    (true, None)
                } else {
                    *self = Self::Confirm {
                        attempts: timing::REBOOT_READBACK_ATTEMPTS,
                        last_start,
                    };
                    let hold = now.saturating_add(config.reboot_wait_us);
                    (false, Some(Effect::Hold(hold)))
                }
            }
            Self::Confirm {
                attempts,
                last_start,
            } => {
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
                        out.push(Report::ResetDone { confirmed: true });
                        (true, Some(Effect::Resync))
                    }
                    _ if *attempts > 1 => {
                        *attempts -= 1;
                        let hold = now.saturating_add(config.live_period_us.saturating_mul(2));
                        (false, Some(Effect::Hold(hold)))
                    }
                    _ => {
                        out.push(Report::ResetDone { confirmed: false });
                        (true, Some(Effect::Resync))
                    }
                }
            }
        }
    }
}

/// Timestamp of the newest "System Started" event in a list.
fn newest_start(events: &[Event]) -> Option<u32> {
    events
        .iter()
        .filter(|e| e.id == EventId::SystemStarted)
        .map(|e| e.timestamp_s)
        .reduce(|a, b| if ts_newer(b, a) { b } else { a })
}
