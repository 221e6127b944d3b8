//! Dispatch: a host's command line to what it asks of the bridge, and the
//! bridge's reports back to the requests that caused them (a write's
//! `outcome` to its `set`, a reset's and a clear's end to theirs).

use heapless::Vec;
use protocol_core::settings::Setting;

use super::command::{self, ClearWhat, HostCommand, SetValues, What};
use super::{ErrorCode, Out, State, ANSWERS_MAX, PENDING_WRITES, QUEUE};
use crate::bms::timing::MAX_SETTINGS_GROUP;
use crate::bridge::report::{Report, WriteOutcome};
use crate::bridge::{Bridge, Command};
use crate::config::state::ConfigState;
use crate::Instant;

impl State {
    pub(super) fn dispatch(
        &mut self,
        now: Instant,
        line: &[u8],
        bridge: &mut Bridge,
        config: &mut ConfigState,
        ota: &mut crate::update::Ota,
    ) {
        if self.queue.len() >= ANSWERS_MAX {
            // The host sends without reading: its answer could not be queued, so
            // the command is not carried out at all (counted as a dropped line).
            self.stats.dropped_lines = self.stats.dropped_lines.wrapping_add(1);
            return;
        }
        let parsed = match command::parse(line) {
            Ok(p) => p,
            Err(e) => return self.error(e.req, e.code, e.detail, e.subject),
        };
        let req = parsed.req;
        if self.update_only
            && !matches!(
                parsed.command,
                HostCommand::Hello
                    | HostCommand::Get(What::Can)
                    | HostCommand::UpdateBegin { .. }
                    | HostCommand::UpdateChunk { .. }
                    | HostCommand::UpdateCancel
                    | HostCommand::UpdateStatus
            )
        {
            return self.error(
                req,
                ErrorCode::UnknownCommand,
                "only hello, get can and the update_… commands on the update port",
                "",
            );
        }
        // The running record decides read-only (the BOOT button may have lifted it).
        self.apply_config(now, config.running());
        let writes = matches!(
            parsed.command,
            HostCommand::Set(..)
                | HostCommand::Reset
                | HostCommand::Clear(_)
                | HostCommand::SetConfig(_)
                | HostCommand::ResetConfig
                | HostCommand::UpdateBegin { .. }
                | HostCommand::UpdateChunk { .. }
        );
        if writes && self.config.read_only {
            return self.error(req, ErrorCode::ReadOnly, "host writes are switched off", "");
        }
        match parsed.command {
            HostCommand::Hello => {
                self.new_session(now);
                self.push(Out::Hello(req));
            }
            HostCommand::Get(what) => self.get(req, what, bridge),
            HostCommand::Set(values, check) => self.set(req, &values, check, bridge),
            HostCommand::Reset => {
                if self.resets.is_full() {
                    return self.error(req, ErrorCode::Busy, "resets pending", "");
                }
                if bridge.submit(Command::ResetBms).is_err() {
                    return self.error(req, ErrorCode::Busy, "command queue full", "");
                }
                let _ = self.resets.push_back(req);
                self.push(Out::Accepted(req, "reset"));
            }
            HostCommand::Clear(what) => {
                let (command, option) = match what {
                    ClearWhat::Events => (Command::ClearEvents, 1),
                    ClearWhat::Statistics => (Command::ClearStatistics, 2),
                };
                if self.clears.is_full() {
                    return self.error(req, ErrorCode::Busy, "clears pending", "");
                }
                if bridge.submit(command).is_err() {
                    return self.error(req, ErrorCode::Busy, "command queue full", "");
                }
                let _ = self.clears.push((req, option));
                self.push(Out::Accepted(req, "clear"));
            }
            HostCommand::Stream(period) => {
                self.set_stream(now, period);
                self.push(Out::Accepted(req, "stream"));
            }
            HostCommand::Capture(on) => {
                self.capture = on;
                if !on {
                    self.raw.clear();
                }
                self.push(Out::Accepted(req, "capture"));
            }
            HostCommand::SetConfig(fields) => self.set_config(now, req, &fields, bridge, config),
            HostCommand::ResetConfig => {
                if self.config_saves.is_full() || self.queue.len() + 2 > QUEUE {
                    return self.error(req, ErrorCode::Busy, "configuration changes pending", "");
                }
                let changed = config.reset().len() as u8;
                self.push(Out::Accepted(req, "reset_config"));
                self.config_changed(now, req, changed, config);
            }
            HostCommand::UpdateBegin { .. }
            | HostCommand::UpdateChunk { .. }
            | HostCommand::UpdateCancel
            | HostCommand::UpdateStatus => {
                let l = self.update(now, &parsed.command, ota);
                self.push(Out::Update(req, l));
            }
            HostCommand::SetTime(at) => {
                self.time = Some(at);
                self.push(Out::Accepted(req, "set_time"));
            }
        }
    }

    fn get(&mut self, req: Option<u32>, what: What, bridge: &Bridge) {
        let t = bridge.telemetry();
        match what {
            What::Snapshot => self.push(Out::Telemetry(req)),
            What::Settings if t.settings.is_none() => {
                self.error(req, ErrorCode::NotReady, "settings not read yet", "")
            }
            What::Settings => self.push(Out::Settings { req, next: 0 }),
            What::Statistics if t.statistics.is_none() => {
                self.error(req, ErrorCode::NotReady, "statistics not read yet", "")
            }
            What::Statistics => self.push(Out::Statistics(req)),
            What::Version if t.version.is_none() => {
                self.error(req, ErrorCode::NotReady, "version not read yet", "")
            }
            What::Version => self.push(Out::Version(req)),
            What::Link => self.push(Out::Link(req)),
            What::Config => self.push(Out::Config { req, next: 0 }),
            What::Can => match self.can.span {
                None => self.error(req, ErrorCode::NotReady, "no CAN output built in", ""),
                Some((first, end)) => self.push(Out::Can {
                    req,
                    next: first,
                    end,
                    sent: 0,
                }),
            },
            What::History => match self.history {
                Some(problem) => self.error(req, ErrorCode::NotReady, problem, ""),
                None => self.push(Out::History {
                    req,
                    started: false,
                    counts: [0; 3],
                }),
            },
            What::Events => {
                let known = bridge.events();
                let end = known.total();
                let next = end.wrapping_sub(known.len() as u32);
                self.push(Out::Events {
                    req,
                    next,
                    end,
                    sent: 0,
                });
            }
        }
    }

    fn set(
        &mut self,
        req: Option<u32>,
        values: &SetValues<'_>,
        chemistry: protocol_core::settings::ChemistryCheck,
        bridge: &mut Bridge,
    ) {
        let t = bridge.telemetry();
        if !t.ready || t.settings.is_none() {
            return self.error(
                req,
                ErrorCode::NotReady,
                "settings and limits not read yet",
                "",
            );
        }
        let (pairs, physical) = match values {
            SetValues::Physical(p) => (p, true),
            SetValues::Raw(p) => (p, false),
        };
        let mut items: Vec<Setting, MAX_SETTINGS_GROUP> = Vec::new();
        for &(name, value) in pairs {
            let Some(id) = crate::bms::profile::find_setting(name) else {
                return self.error(req, ErrorCode::UnknownSetting, "no such setting", name);
            };
            if items.iter().any(|s| s.id == id) {
                // Both values in turn would write one the host may not mean.
                return self.error(req, ErrorCode::InvalidValue, "setting given twice", name);
            }
            let raw = if physical {
                crate::units::raw_from_physical(id, value)
            } else if crate::units::round(value) == value
                && value >= f64::from(i32::MIN)
                && value <= f64::from(i32::MAX)
            {
                Some(value as i32)
            } else {
                None
            };
            let Some(raw) = raw else {
                return self.error(req, ErrorCode::OutOfRange, "not a raw value", name);
            };
            let setting = Setting { id, value: raw };
            let limits = match (&t.limits_min, &t.limits_max) {
                (Some(lo), Some(hi)) => id.limits(lo, hi),
                _ => None,
            };
            if let Err(e) = setting.validate_with(limits) {
                return self.error(req, ErrorCode::OutOfRange, e.reason(), name);
            }
            if items.push(setting).is_err() {
                return self.error(req, ErrorCode::InvalidValue, "too many settings", "");
            }
        }
        if self.writes.len() + items.len() > PENDING_WRITES {
            return self.error(req, ErrorCode::Busy, "writes pending", "");
        }
        if bridge
            .submit(Command::ApplySettings(items.clone(), chemistry))
            .is_err()
        {
            return self.error(req, ErrorCode::Busy, "command queue full", "");
        }
        for s in items {
            let _ = self.writes.push((req, s));
        }
        self.push(Out::Accepted(req, "set"));
    }

    pub(super) fn on_report(&mut self, report: &Report) {
        match report {
            Report::Write { setting, outcome } => {
                let req = take(&mut self.writes, setting);
                if matches!(outcome, WriteOutcome::Unconfirmed(_)) {
                    if self.follow_ups.is_full() {
                        self.follow_ups.remove(0);
                    }
                    let _ = self.follow_ups.push((req, *setting));
                }
                self.report(Out::Outcome {
                    req,
                    setting: *setting,
                    outcome: *outcome,
                    follow_up: false,
                });
            }
            Report::WriteFollowUp { setting, outcome } => {
                let req = take(&mut self.follow_ups, setting);
                self.report(Out::Outcome {
                    req,
                    setting: *setting,
                    outcome: *outcome,
                    follow_up: true,
                });
            }
            Report::NewEvent(e) => self.report(Out::Event(*e)),
            // The bridge's periodic link statistics go to a host that asked for
            // a stream too.
            Report::LinkStats(_) if self.stream_period_ms > 0 => self.report(Out::Link(None)),
            Report::ResetDone { confirmed } => {
                let req = self.resets.pop_front().flatten();
                self.report(Out::ResetDone(req, *confirmed));
            }
            Report::Cleared { option, ok } => {
                let req = match self.clears.iter().position(|(_, o)| o == option) {
                    Some(i) => self.clears.remove(i).0,
                    None => None,
                };
                self.report(Out::Cleared(req, *option, *ok));
            }
            _ => {}
        }
    }
}

/// Removes the oldest pending entry for `setting` and returns its request id.
fn take(
    pending: &mut Vec<(Option<u32>, Setting), PENDING_WRITES>,
    setting: &Setting,
) -> Option<u32> {
    let i = pending.iter().position(|(_, s)| s == setting)?;
    Some(pending.remove(i).0).flatten()
}
