//! The host link's output: what waits to be said ([`Out`], encoded only when
//! its turn comes), in the order [`HostLink::next_line`] gives it — Improv
//! packets, the boot lines after a `hello`, answers, outcomes and events,
//! `log` lines, streamed telemetry with the battery's lines, then `raw`
//! lines. A listing (`get settings`, `get events`, `get config`) stays at the
//! front, one line per call, until its end line.

use heapless::String;
use protocol_core::events::Event;
use protocol_core::settings::Setting;

use super::configure::{ConfigAnswer, ConfigDone};
use super::{encode, ErrorCode, HostLink, State, SUBJECT_MAX};
use crate::bridge::report::WriteOutcome;
use crate::bridge::Bridge;
use crate::config::state::{ConfigState, Outcome};
use crate::Instant;

/// Direction of captured UART bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Dir {
    Tx,
    Rx,
}

/// One line (or listing) waiting to be encoded.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Out {
    Hello(Option<u32>),
    Telemetry(Option<u32>),
    Error {
        req: Option<u32>,
        code: ErrorCode,
        detail: &'static str,
        subject: String<SUBJECT_MAX>,
    },
    Accepted(Option<u32>, &'static str),
    Outcome {
        req: Option<u32>,
        setting: Setting,
        outcome: WriteOutcome,
        follow_up: bool,
    },
    Event(Event),
    /// `get events`: events `next..end` (sequence numbers), `sent` so far.
    Events {
        req: Option<u32>,
        next: u32,
        end: u32,
        sent: u32,
    },
    /// `get can`: capture entries `next..end` (sequence numbers), `sent` so
    /// far.
    Can {
        req: Option<u32>,
        next: u32,
        end: u32,
        sent: u32,
    },
    /// `get history`: the listing asked of the history (`started`), lines
    /// so far (events, days, skipped).
    History {
        req: Option<u32>,
        started: bool,
        counts: [u32; 3],
    },
    /// `get settings`: the next index into `SettingId::ALL`.
    Settings {
        req: Option<u32>,
        next: u8,
    },
    Statistics(Option<u32>),
    Version(Option<u32>),
    Link(Option<u32>),
    ResetDone(Option<u32>, bool),
    Cleared(Option<u32>, u8, bool),
    /// `get config`: the next index into `config::FIELDS`.
    Config {
        req: Option<u32>,
        next: u8,
    },
    /// One field of a `set_config`.
    ConfigOutcome {
        req: Option<u32>,
        name: String<SUBJECT_MAX>,
        outcome: ConfigAnswer,
    },
    /// The end of a `set_config` or `reset_config`.
    ConfigDone(ConfigDone),
    /// The answer to an `update_…` command.
    Update(Option<u32>, super::update::UpdateLine),
}

impl HostLink {
    /// Encodes the next output line into `out` (at least [`OUT_LINE_MAX`](super::OUT_LINE_MAX) bytes),
    /// `\n`-terminated; returns its length, or `None` when nothing is waiting.
    /// Order: answers, outcomes and events first, then `log` lines, then
    /// streamed telemetry, then `raw` lines.
    pub fn next_line(
        &mut self,
        now: Instant,
        bridge: &Bridge,
        config: &ConfigState,
        out: &mut [u8],
    ) -> Option<usize> {
        if let Some(p) = self.improv.next_packet(self.s.config.firmware) {
            let dst = out.get_mut(..p.len())?;
            dst.copy_from_slice(&p);
            return Some(p.len());
        }
        loop {
            let written = if let Some(at) = self.s.boot_replay {
                // The boot lines, right after the `hello`.
                let rest = self.s.boot.get(at..).unwrap_or("");
                let Some((line, _)) = rest.split_once('\n') else {
                    self.s.boot_replay = None;
                    continue;
                };
                self.s.boot_replay = Some(at + line.len() + 1);
                let level = if line.starts_with('W') {
                    crate::Level::Warn
                } else {
                    crate::Level::Info
                };
                encode::boot_log(out, level, line.get(1..).unwrap_or(""))
            } else if matches!(self.s.queue.front(), Some(Out::History { .. }))
                && self.s.history_item.is_none()
            {
                // The station reads the history's next record first.
                return None;
            } else if !self.s.queue.is_empty() {
                self.s.encode_front(now, bridge, config, out)
            } else if let Some((level, text)) = self.s.logs.pop_front() {
                encode::log(out, level, &text)
            } else if self.s.stream_due {
                self.s.stream_due = false;
                self.s.battery_lines = self.s.battery.as_ref().map_or(0, |v| 1 + v.packs.len());
                telemetry(now, bridge, None, &self.s, out)
            } else if self.s.battery_lines > 0 {
                let v = self.s.battery.as_ref();
                let total = v.map_or(0, |v| 1 + v.packs.len());
                let i = total.saturating_sub(self.s.battery_lines);
                self.s.battery_lines -= 1;
                match (v, i) {
                    (Some(v), 0) => encode::battery(out, v),
                    (Some(v), i) => match v.packs.get(i - 1) {
                        Some(p) => encode::pack(out, p),
                        None => continue,
                    },
                    (None, _) => continue,
                }
            } else if let Some((dir, bytes)) = self.s.raw.pop_front() {
                let dir = match dir {
                    Dir::Tx => "tx",
                    Dir::Rx => "rx",
                };
                encode::raw(out, dir, &bytes)
            } else {
                return None;
            };
            match written {
                Some(n) => return Some(n),
                None => {
                    self.s.stats.dropped_lines = self.s.stats.dropped_lines.wrapping_add(1);
                }
            }
        }
    }
}

fn telemetry(
    now: Instant,
    bridge: &Bridge,
    req: Option<u32>,
    s: &State,
    out: &mut [u8],
) -> Option<usize> {
    let t = bridge.telemetry();
    let head = encode::TelemetryHead {
        req,
        seq: t.snapshot_seq,
        age_ms: t.snapshot_age_us(now).map(|a| a / crate::MS),
        stale_after_ms: Some(s.config.freshness.limit_us / crate::MS),
        online: t.online,
        ready: t.ready,
        inverter: s.inverter,
        restart_pending: s.restart_pending,
    };
    encode::telemetry(
        out,
        head,
        t.snapshot.as_ref(),
        t.live.flagged.map(|c| c.name()),
        None,
    )
}

/// The front item's next line when it is a listing: another item (the
/// listing stays at the front), or its end line (it is done).
enum Listed {
    More(Option<usize>),
    Last(Option<usize>),
    /// The front item is no listing.
    Not,
}

impl State {
    /// Encodes the front item; pops it unless it is a listing with more to say.
    pub(super) fn encode_front(
        &mut self,
        now: Instant,
        bridge: &Bridge,
        config: &ConfigState,
        out: &mut [u8],
    ) -> Option<usize> {
        let n = match self.listing_line(bridge, config, out)? {
            Listed::More(n) => return n,
            Listed::Last(n) => n,
            Listed::Not => self.single_line(now, bridge, config, out),
        };
        self.queue.pop_front();
        n
    }

    /// The front item's line when it is a listing (`None`: nothing waits).
    fn listing_line(
        &mut self,
        bridge: &Bridge,
        config: &ConfigState,
        out: &mut [u8],
    ) -> Option<Listed> {
        let t = bridge.telemetry();
        let known = bridge.events();
        let first_seq = known.total().wrapping_sub(known.len() as u32);
        let front = self.queue.front_mut()?;
        let listed = match front {
            Out::Settings { req, next } => {
                let ids = protocol_core::settings::SettingId::ALL;
                match ids.get(usize::from(*next)) {
                    Some(&id) => {
                        *next = next.saturating_add(1);
                        let raw = t.settings.as_ref().and_then(|b| id.read(b));
                        let limits = match (&t.limits_min, &t.limits_max) {
                            (Some(lo), Some(hi)) => id.limits(lo, hi),
                            _ => None,
                        };
                        return Some(Listed::More(encode::setting(out, *req, id, raw, limits)));
                    }
                    None => encode::end(out, "settings_end", *req, ids.len() as u32),
                }
            }
            Out::Events {
                req,
                next,
                end,
                sent,
            } => {
                // Events evicted since the listing began are skipped.
                if next.wrapping_sub(first_seq) > u32::MAX / 2 {
                    *next = first_seq;
                }
                let remaining = end.wrapping_sub(*next);
                let e = if remaining > 0 && remaining <= u32::MAX / 2 {
                    known.get(next.wrapping_sub(first_seq) as usize).copied()
                } else {
                    None
                };
                if let Some(e) = e {
                    *next = next.wrapping_add(1);
                    *sent = sent.wrapping_add(1);
                    return Some(Listed::More(encode::event(out, *req, &e, true)));
                }
                encode::end(out, "events_end", *req, *sent)
            }
            Out::Can {
                req,
                next,
                end,
                sent,
            } => {
                let (first, _) = self.can.span.unwrap_or((*end, *end));
                // Entries overwritten since the listing began are skipped.
                if next.wrapping_sub(first) > u32::MAX / 2 {
                    *next = first;
                }
                let remaining = end.wrapping_sub(*next);
                let e = match self.can.entry {
                    Some((seq, e))
                        if seq == *next && remaining > 0 && remaining <= u32::MAX / 2 =>
                    {
                        e
                    }
                    _ => None,
                };
                if let Some(e) = e {
                    *next = next.wrapping_add(1);
                    *sent = sent.wrapping_add(1);
                    let mut l = crate::log_line::Line::new();
                    e.write_candump(&mut l);
                    return Some(Listed::More(encode::can(out, *req, l.as_str())));
                }
                encode::can_end(out, *req, *sent, self.can.protocol)
            }
            Out::History { req, counts, .. } => match self.history_item.take() {
                Some(Some(item)) => {
                    let i = match item {
                        crate::history::log::Listed::Event(..) => 0,
                        crate::history::log::Listed::Day(..) => 1,
                        crate::history::log::Listed::Skipped(..) => 2,
                    };
                    if let Some(c) = counts.get_mut(i) {
                        *c = c.saturating_add(1);
                    }
                    return Some(Listed::More(encode::history(out, *req, &item)));
                }
                // Over (or never started: no history).
                _ => encode::history_end(out, *req, *counts),
            },
            Out::Config { req, next } => {
                let fields = crate::config::FIELDS;
                match fields.get(usize::from(*next)) {
                    Some(f) => {
                        *next = next.saturating_add(1);
                        let bms = t
                            .settings
                            .as_ref()
                            .and_then(crate::config::PackSettings::from_registers);
                        return Some(Listed::More(encode::config_field(
                            out,
                            *req,
                            f,
                            config,
                            bms.as_ref(),
                        )));
                    }
                    None => encode::config_end(out, *req, config),
                }
            }
            _ => return Some(Listed::Not),
        };
        Some(Listed::Last(listed))
    }

    /// The front item's line when it is not a listing.
    fn single_line(
        &mut self,
        now: Instant,
        bridge: &Bridge,
        config: &ConfigState,
        out: &mut [u8],
    ) -> Option<usize> {
        let t = bridge.telemetry();
        let front = self.queue.front()?;
        match front {
            Out::Hello(req) => {
                // The boot lines follow it.
                self.boot_replay = (!self.boot.is_empty()).then_some(0);
                encode::hello(
                    out,
                    *req,
                    &encode::HelloFields {
                        firmware: self.config.firmware,
                        chip: self.config.chip,
                        board: self.config.board,
                        features: self.config.features,
                        read_only: self.config.read_only,
                        stream_period_ms: self.stream_period_ms,
                        dropped_lines: self.stats.dropped_lines,
                        store: config.site(),
                        mqtt: self.mqtt,
                        radio: self.radio.map(crate::wifi::Radio::key),
                        wifi: self.config.features.wifi.then_some(self.wifi),
                        update: &self.update,
                        history: self.history,
                    },
                )
            }
            Out::Telemetry(req) => telemetry(now, bridge, *req, self, out),
            Out::Error {
                req,
                code,
                detail,
                subject,
            } => encode::error(out, *req, code.name(), detail, subject.as_str()),
            Out::Accepted(req, cmd) => encode::accepted(out, *req, cmd),
            Out::Update(req, l) => l.encode(*req, self.update.rolled_back.as_deref(), out),
            Out::Outcome {
                req,
                setting,
                outcome,
                follow_up,
            } => encode::outcome(out, *req, setting, outcome, *follow_up),
            Out::Event(e) => encode::event(out, None, e, false),
            Out::Statistics(req) => match &t.statistics {
                Some(s) => encode::statistics(out, *req, s),
                None => None,
            },
            Out::Version(req) => match &t.version {
                Some(v) => encode::version(out, *req, v),
                None => None,
            },
            Out::Link(req) => encode::link(
                out,
                *req,
                &bridge.link_stats(),
                t.online,
                bridge.piece_registers(),
                &self.stats,
                bridge.wire(),
            ),
            Out::ConfigOutcome { req, name, outcome } => match outcome {
                ConfigAnswer::Field(id, o) => {
                    encode::config_outcome(out, *req, name, Some(*id), *o, config)
                }
                ConfigAnswer::Unknown => encode::config_unknown(out, *req, name),
                ConfigAnswer::Invalid(id, e) => {
                    encode::config_outcome(out, *req, name, Some(*id), Outcome::Refused(*e), config)
                }
            },
            Out::ConfigDone(done) => encode::config_done(out, done),
            Out::ResetDone(req, confirmed) => encode::reset_done(out, *req, *confirmed),
            Out::Cleared(req, option, ok) => encode::cleared(
                out,
                *req,
                if *option == 1 { "events" } else { "statistics" },
                *ok,
            ),
            Out::Settings { .. }
            | Out::Events { .. }
            | Out::Config { .. }
            | Out::Can { .. }
            | Out::History { .. } => None,
        }
    }
}
