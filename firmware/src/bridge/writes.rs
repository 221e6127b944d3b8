//! The write/verify machine, and the reset and clear commands.
//!
//! Commands ([`super::Command`]) queue here and run one at a time, between live
//! reads (the schedule decides when a job gets the link).
//!
//! For each setting of a group: validate against Rev D and the BMS-reported
//! min/max → read the current value → skip when equal → write with 0x10 (byte
//! fields read-modify-write, keeping the other byte) → echo, or NACK reported with
//! its code → settle → read back → compare (0xFFFF counts as accepted for 323 and
//! 328). A write to 340 restarts the BMS: the read-back waits for the restart.
//! Success is only ever reported with a matching read-back; "failed" only when
//! the write never went out or the read-back shows the old value; when nothing
//! could be read back the outcome is "unconfirmed" and the settings read that
//! follows every write decides ([`Writes::resolve`], [`Report::WriteFollowUp`]).
//!
//! A clear (0x02 options 0x01 and 0x02) is one request, done when the BMS ACKs
//! it; a reset has its own steps ([`super::reset`]).

use heapless::{Deque, Vec};
use protocol_core::request::{Request, ResetOption};
use protocol_core::response::{RegisterBlock, Response};
use protocol_core::settings::{Setting, SettingError, SettingId, ACCEPTED_MARKER};

use super::job::{Effect, JobNext};
use super::reset::ResetStep;
use super::telemetry::Telemetry;
use super::{Command, Reports};
use crate::bms::link::{CompletionRef, Failure, Silence};
use crate::bms::timing::{self, Timing};
use crate::bridge::report::{Report, WriteOutcome};
use crate::Instant;

/// Writes awaiting a follow-up outcome.
const UNRESOLVED: usize = timing::MAX_SETTINGS_GROUP;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum WriteStep {
    ReadCurrent,
    Write,
    Settle(Instant),
    ReadBack,
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct WriteJob {
    items: Vec<Setting, { timing::MAX_SETTINGS_GROUP }>,
    index: usize,
    step: WriteStep,
    current: Option<(u16, Option<u16>)>,
    /// The write got no confirmation: the read-back decides.
    unconfirmed: Option<Failure>,
    readback_attempts: u8,
    wrote_any: bool,
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

/// The command queue, the running job and the writes awaiting a follow-up.
#[derive(Debug, Clone)]
pub(super) struct Writes {
    commands: Deque<Command, { timing::COMMAND_QUEUE }>,
    job: Option<Job>,
    unresolved: Vec<Unresolved, UNRESOLVED>,
}

impl Writes {
    pub(super) fn new() -> Self {
        Self {
            commands: Deque::new(),
            job: None,
            unresolved: Vec::new(),
        }
    }

    /// Queues a command; gives it back when the queue is full.
    #[allow(clippy::result_large_err)] // the command itself is handed back
    pub(super) fn submit(&mut self, command: Command) -> Result<(), Command> {
        self.commands.push_back(command)
    }

    /// True while a command is queued or running.
    pub(super) fn busy(&self) -> bool {
        self.job.is_some() || !self.commands.is_empty()
    }

    /// No job is running.
    pub(super) fn idle(&self) -> bool {
        self.job.is_none()
    }

    /// A reset or clear is running: it owns the link until it is done.
    pub(super) fn owns_link(&self) -> bool {
        matches!(self.job, Some(Job::Reset(_) | Job::Clear(_)))
    }

    /// No job, or a settings group between two settings.
    pub(super) fn at_boundary(&self) -> bool {
        match &self.job {
            None => true,
            Some(Job::Write(w)) => w.step == WriteStep::ReadCurrent,
            Some(_) => false,
        }
    }

    /// When a write that settles wants its read-back.
    pub(super) fn settle_until(&self) -> Option<Instant> {
        match &self.job {
            Some(Job::Write(WriteJob {
                step: WriteStep::Settle(s),
                ..
            })) => Some(*s),
            _ => None,
        }
    }

    /// Makes sure a job runs: starts the next queued command when none does.
    /// False when there is neither. (A command may start no job: a group whose
    /// settings were all rejected; [`Self::next_request`] then says `Finished`.)
    pub(super) fn start_next(&mut self, telemetry: &Telemetry, out: &mut Reports) -> bool {
        if self.job.is_none() {
            let Some(cmd) = self.commands.pop_front() else {
                return false;
            };
            self.job = start_job(cmd, telemetry, out);
        }
        true
    }

    /// The running job's next request.
    pub(super) fn next_request(&mut self, now: Instant, out: &mut Reports) -> JobNext {
        let Some(job) = self.job.as_mut() else {
            return JobNext::Finished(None);
        };
        match job {
            Job::Clear(opt) => JobNext::Send(Request::ResetClear(*opt), Silence::Failure),
            Job::Reset(step) => step.request(),
            Job::Write(w) => {
                let Some(item) = w.items.get(w.index).copied() else {
                    let wrote = w.wrote_any;
                    let restarted = w.items.iter().any(|s| s.id.restarts_bms());
                    self.job = None;
                    return JobNext::Finished(if wrote && restarted {
                        // The BMS restarted (340): everything is read again.
                        Some(Effect::Resync)
                    } else if wrote {
                        // The settings (and the unconfirmed outcomes) are read
                        // again; the live data keeps flowing meanwhile.
                        Some(Effect::RereadSettings)
                    } else {
                        None
                    });
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
                                self.finish_item(item, WriteOutcome::Rejected(e), out);
                                return self.next_request(now, out);
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
                                let e = SettingError::NotAnOption {
                                    id: item.id,
                                    value: item.value,
                                };
                                self.finish_item(item, WriteOutcome::Rejected(e), out);
                                self.next_request(now, out)
                            }
                        }
                    }
                }
            }
        }
    }

    /// Reports the outcome of the current setting and moves to the next one.
    fn finish_item(&mut self, setting: Setting, outcome: WriteOutcome, out: &mut Reports) {
        if let Some(Job::Write(w)) = self.job.as_mut() {
            w.index += 1;
            w.step = WriteStep::ReadCurrent;
            w.current = None;
            w.unconfirmed = None;
            w.readback_attempts = 0;
        }
        out.push(Report::Write { setting, outcome });
    }

    /// The link went offline: every setting not done yet is reported, the one
    /// in flight as unconfirmed when it may have been written.
    pub(super) fn abort(&mut self, failure: Failure, out: &mut Reports) {
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
                    out.push(Report::Write {
                        setting: *s,
                        outcome,
                    });
                }
            }
            Some(Job::Reset(_)) => out.push(Report::ResetDone { confirmed: false }),
            Some(Job::Clear(opt)) => out.push(Report::Cleared {
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

    /// The settings read after writes decides the unconfirmed ones.
    pub(super) fn resolve(&mut self, settings: &RegisterBlock, out: &mut Reports) {
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
            out.push(Report::WriteFollowUp {
                setting: u.setting,
                outcome,
            });
        }
    }

    /// The answer to the running job's request.
    pub(super) fn on_reply(
        &mut self,
        now: Instant,
        c: &CompletionRef<'_>,
        config: &Timing,
        out: &mut Reports,
    ) -> Option<Effect> {
        let job = self.job.as_mut()?;
        match job {
            Job::Clear(opt) => {
                let ok = matches!(c.result, Ok(Response::Ack { .. }));
                let option = opt.to_u8();
                let events = *opt == ResetOption::ClearEvents;
                self.job = None;
                out.push(Report::Cleared { option, ok });
                (ok && events).then_some(Effect::EventsCleared)
            }
            Job::Reset(step) => {
                let (done, effect) = step.on_reply(now, c, config, out);
                if done {
                    self.job = None;
                }
                effect
            }
            Job::Write(_) => self.on_write_reply(now, c, config, out),
        }
    }

    /// The answer to a request of the running settings group.
    fn on_write_reply(
        &mut self,
        now: Instant,
        c: &CompletionRef<'_>,
        config: &Timing,
        out: &mut Reports,
    ) -> Option<Effect> {
        let Some(Job::Write(w)) = self.job.as_mut() else {
            return None;
        };
        let item = w.items.get(w.index).copied()?;
        let a = item.id.address();
        match (w.step, &c.result) {
            (WriteStep::ReadCurrent, Ok(Response::Individual(pairs))) => {
                let (Some(first), second) = (pair(pairs, a), pair(pairs, a + 1)) else {
                    let outcome = WriteOutcome::NotWritten(Failure::Timeout);
                    self.finish_item(item, outcome, out);
                    return None;
                };
                // Skip only on true equality (not on 323/328's 0xFFFF marker).
                if item.id.value_from_words(first, second) == Some(item.value) {
                    self.finish_item(item, WriteOutcome::Unchanged, out);
                } else {
                    w.current = Some((first, second));
                    w.step = WriteStep::Write;
                }
                None
            }
            (WriteStep::ReadCurrent, Err(f)) => {
                self.finish_item(item, WriteOutcome::NotWritten(*f), out);
                None
            }
            (WriteStep::ReadCurrent, Ok(_)) => {
                let outcome = WriteOutcome::NotWritten(Failure::Timeout);
                self.finish_item(item, outcome, out);
                None
            }
            (WriteStep::Write, result) => {
                w.wrote_any = true;
                match result {
                    Ok(Response::WriteEcho { .. }) => {}
                    // Refused at the first attempt: nothing was written.
                    Err(Failure::Nack(code)) if c.sends <= 1 => {
                        self.finish_item(item, WriteOutcome::Nacked(*code), out);
                        return None;
                    }
                    // No clear confirmation (lost, damaged, or a NACK after an
                    // unanswered first attempt that may have been applied):
                    // the read-back decides.
                    Err(Failure::Silent) => w.unconfirmed = Some(Failure::Timeout),
                    Err(f) => w.unconfirmed = Some(*f),
                    Ok(_) => w.unconfirmed = Some(Failure::Timeout),
                }
                if item.id.restarts_bms() {
                    w.readback_attempts = timing::REBOOT_READBACK_ATTEMPTS;
                    w.step = WriteStep::ReadBack;
                    Some(Effect::Hold(now.saturating_add(config.reboot_wait_us)))
                } else {
                    w.readback_attempts = 1;
                    w.step = WriteStep::Settle(now.saturating_add(config.write_settle_us));
                    None
                }
            }
            (WriteStep::ReadBack, Ok(Response::Individual(pairs))) => {
                self.on_readback(item, pairs, out)
            }
            (WriteStep::ReadBack, Err(f)) => {
                if w.readback_attempts > 1 {
                    w.readback_attempts -= 1;
                    Some(Effect::Hold(
                        now.saturating_add(config.live_period_us.saturating_mul(2)),
                    ))
                } else {
                    // Written, nothing read back: the settings read that
                    // follows the group decides.
                    let old = w.current.map(|(f, _)| f);
                    self.remember_unresolved(item, old);
                    self.finish_item(item, WriteOutcome::Unconfirmed(*f), out);
                    None
                }
            }
            (WriteStep::ReadBack, Ok(_)) | (WriteStep::Settle(_), _) => {
                let old = w.current.map(|(f, _)| f);
                self.remember_unresolved(item, old);
                let outcome = WriteOutcome::Unconfirmed(Failure::Timeout);
                self.finish_item(item, outcome, out);
                None
            }
        }
    }

    /// The read-back after a write of `item`: verified, or what else it shows.
    fn on_readback(
        &mut self,
        item: Setting,
        pairs: &[(u16, u16)],
        out: &mut Reports,
    ) -> Option<Effect> {
        let Some(Job::Write(w)) = self.job.as_mut() else {
            return None;
        };
        let a = item.id.address();
        let Some(first) = pair(pairs, a) else {
            let old = w.current.map(|(f, _)| f);
            self.remember_unresolved(item, old);
            let outcome = WriteOutcome::Unconfirmed(Failure::Timeout);
            self.finish_item(item, outcome, out);
            return None;
        };
        let second = pair(pairs, a + 1);
        // 323/328 read 0xFFFF once a write is accepted; when they
        // already did before and the write was not confirmed, the
        // marker proves nothing.
        let marker_was_there =
            item.id.reads_back_marker() && w.current.map(|(f, _)| f) == Some(ACCEPTED_MARKER);
        let proof =
            item.matches_readback(first, second) && !(marker_was_there && w.unconfirmed.is_some());
        let old = w.current.map(|(f, _)| f);
        // What the BMS read back once it took the value (not
        // 323/328's marker: their copy waits for the next read).
        let read_back = (proof && !(item.id.reads_back_marker() && first == ACCEPTED_MARKER))
            .then_some(Effect::ReadBack {
                address: a,
                first,
                second,
            });
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
                Some(Failure::Nack(code)) if old == Some(first) => WriteOutcome::Nacked(code),
                Some(f) if old == Some(first) => WriteOutcome::Failed(f),
                _ => WriteOutcome::Mismatch { read_back: first },
            }
        };
        self.finish_item(item, outcome, out);
        read_back
    }
}

/// A command becomes a job; the settings of a group that fail validation are
/// reported as rejected and left out (a group left empty starts no job).
fn start_job(cmd: Command, telemetry: &Telemetry, out: &mut Reports) -> Option<Job> {
    match cmd {
        Command::ResetBms => Some(Job::Reset(ResetStep::Before)),
        Command::ClearEvents => Some(Job::Clear(ResetOption::ClearEvents)),
        Command::ClearStatistics => Some(Job::Clear(ResetOption::ClearStatistics)),
        Command::ApplySettings(settings, chemistry) => {
            let mut items = Vec::new();
            // Each setting against the others: those of this group first,
            // else what the BMS holds.
            let held = |id: SettingId| telemetry.settings.as_ref().and_then(|b| id.read(b));
            let value_of = |id: SettingId| {
                settings
                    .iter()
                    .find(|x| x.id == id)
                    .map(|x| x.value)
                    .or_else(|| held(id))
            };
            // The pack's chemistry: as the host said, else what the BMS's own
            // voltages name (never the values being written).
            let chemistry = chemistry.chemistry(held);
            for s in settings.iter().copied() {
                let checked = check_setting(&s, telemetry)
                    .and_then(|()| protocol_core::settings::check_relations(&s, value_of))
                    .and_then(|()| match chemistry {
                        Some(c) => protocol_core::settings::check_chemistry(&s, c),
                        None => Ok(()),
                    });
                match checked {
                    Ok(()) => {
                        let _fits = items.push(s); // same capacity
                    }
                    Err(e) => out.push(Report::Write {
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
/// For the sensor-dependent settings (304, 305, 317, 318) the BMS's limits
/// replace Rev D's range when known.
fn check_setting(s: &Setting, telemetry: &Telemetry) -> Result<(), SettingError> {
    let bms = match (&telemetry.limits_min, &telemetry.limits_max) {
        (Some(min), Some(max)) => s.id.limits(min, max),
        _ => None,
    };
    s.validate_with(bms)
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
