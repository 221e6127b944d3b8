//! The station's side of the history ([`crate::history`]): what it records
//! (from everything the station logs, the limits it sends, the network's
//! state), and when the flash work may be done — only in a gap of the BMS
//! poll and the CAN output long enough for a sector's erase
//! ([`super::ota::FLASH_WINDOW_US`], the update's rule), so a history write
//! delays neither a request nor a frame (host-tests/tests/history.rs holds
//! every request and frame to its microsecond with and without it).

use super::{Action, Logged, Station};
use crate::bridge::report::Report;
use crate::config::state::Note;
use crate::history::capacity::Capacity;
use crate::history::day::{DayBook, DayRecord, DAY_BYTES};
use crate::history::event::{Code, Who};
use crate::history::log::History;
use crate::history::ring::{Kind, SLOT_MAX};
use crate::history::Aging;
use crate::inverter::InverterReport;
use crate::Instant;

/// The day under way is saved this often, µs.
pub const CHECKPOINT_US: Instant = 3600 * crate::SECOND;

/// The pack's days and capacity, as the station keeps them.
#[derive(Debug, Clone)]
pub(super) struct Days {
    pub book: DayBook,
    pub capacity: Capacity,
    pub next_checkpoint: Instant,
    /// The last closed day's spread at the top of charge, mV.
    pub top_spread: Option<u16>,
    /// The newest capacity estimate in flash (before one qualifies again).
    pub stored_capacity: Option<(u32, u16)>,
    /// Charge control's stage at the last snapshot.
    pub stage: Option<crate::inverter::finish::Stage>,
}

impl Days {
    pub fn new(now: Instant) -> Self {
        Self {
            book: DayBook::new(now),
            capacity: Capacity::new(),
            next_checkpoint: now.saturating_add(CHECKPOINT_US),
            top_spread: None,
            stored_capacity: None,
            stage: None,
        }
    }
}

/// A day record of the history's payload.
fn day_of(p: &crate::history::ring::Payload) -> Option<DayRecord> {
    DayRecord::decode(p.get(..DAY_BYTES)?).ok()
}

/// Network state the history follows.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Watch {
    /// Who changes the configuration now.
    pub who: Option<Who>,
    /// Charging and discharging stopped (CCL, DCL at 0 in what is sent).
    pub stopped: (bool, bool),
    /// Since when the data is stale.
    pub stale_since: Option<Instant>,
    /// The Wi-Fi network.
    pub wifi: LinkWatch,
    /// The MQTT connection.
    pub mqtt: LinkWatch,
}

/// A network link the history follows: up, and since when it is down.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct LinkWatch {
    up: bool,
    down_since: Option<Instant>,
}

impl LinkWatch {
    /// The link is `up` at `now`: `Some(None)` when it was just lost,
    /// `Some(Some(s))` when it came back after `s` seconds down (a first
    /// coming up is no return), `None` when nothing changed.
    fn change(&mut self, now: Instant, up: bool) -> Option<Option<u32>> {
        let was = core::mem::replace(&mut self.up, up);
        match (was, up) {
            (false, true) => self
                .down_since
                .take()
                .map(|t| Some((now.saturating_sub(t) / crate::SECOND) as u32)),
            (true, false) => {
                self.down_since = Some(now);
                Some(None)
            }
            _ => None,
        }
    }
}

impl Station {
    /// The history opened at start ([`History::open`]) and the chip's reset
    /// reason (its raw code; `None` unknown): the start is its first event.
    pub fn set_history(&mut self, now: Instant, history: History, reset_reason: Option<u8>) {
        self.history = history;
        // The day under way goes on from its checkpoint; else the day after
        // the newest closed one.
        let last = self.history.last_day().and_then(day_of);
        let point = self.history.last_checkpoint().and_then(day_of);
        self.days.book = match (point, last) {
            (Some(p), l) if l.is_none_or(|l| p.day > l.day) => DayBook::resume(&p, now),
            (_, Some(l)) => DayBook::starting(l.day.saturating_add(1), now),
            _ => DayBook::new(now),
        };
        self.days.top_spread = last.filter(|l| l.top_cell != 0).map(|l| l.top_spread_mv);
        self.days.stored_capacity = last.filter(|l| l.capacity_cah != 0).map(|l| {
            (
                u32::from(l.capacity_cah),
                u16::from(l.capacity_uncertainty_permille),
            )
        });
        let firmware = self.identity.firmware;
        self.history.event(
            now,
            Code::Started,
            reset_reason.map_or(0xFF, u32::from),
            0,
            firmware,
        );
    }

    /// The history.
    pub fn history(&self) -> &History {
        &self.history
    }

    /// A host said the date (Unix seconds).
    pub fn set_date(&mut self, now: Instant, unix_s: u64) {
        let who = self.watch.who.unwrap_or(Who::Host);
        self.history.set_date(now, unix_s, who);
    }

    /// A snapshot for the day's record and the capacity estimate.
    pub(super) fn days_snapshot(
        days: &mut Days,
        at: Instant,
        s: &protocol_core::views::LiveSnapshot,
        valid: bool,
        settings: Option<&crate::inverter::control::PackSettings>,
        stage: Option<&crate::inverter::finish::Stage>,
        statistics: Option<&protocol_core::views::Statistics>,
    ) {
        days.book.on_snapshot(at, s, valid, settings, stage);
        if let Some(st) = statistics {
            days.book.on_statistics(st);
        }
        // The bridge's own end of a charge is a full point too.
        let finished = crate::history::capacity::charge_finished(days.stage.as_ref(), stage);
        days.stage = stage.copied();
        let e = if finished && valid {
            let mut full = s.clone();
            full.status = protocol_core::events::OnlineStatus::FullyCharged;
            days.capacity.on_snapshot(at, &full, valid, settings)
        } else {
            days.capacity.on_snapshot(at, s, valid, settings)
        };
        if let Some(e) = e {
            days.book.on_estimate(&e);
        }
    }

    /// A day closed, or the hour's checkpoint due: to the history.
    pub(super) fn tick_days(&mut self, now: Instant) {
        if let Some(rec) = self.days.book.poll(now, self.history.unix(now)) {
            self.days.top_spread = (rec.top_cell != 0).then_some(rec.top_spread_mv);
            self.history.record(Kind::Day, &rec.encode());
            self.days.next_checkpoint = now.saturating_add(CHECKPOINT_US);
        }
        if now >= self.days.next_checkpoint {
            let p = self.days.book.checkpoint(now);
            self.history.record(Kind::Checkpoint, &p.encode());
            self.days.next_checkpoint = now.saturating_add(CHECKPOINT_US);
        }
    }

    /// How the pack ages, for the state Home Assistant reads.
    pub(super) fn aging(&self) -> Aging {
        let t = self.bridge.telemetry();
        Aging {
            capacity: self
                .days
                .capacity
                .estimate()
                .map(|e| (e.cah, e.uncertainty_permille))
                .or(self.days.stored_capacity),
            cycles: t.statistics.as_ref().map(|s| s.charging_count),
            top_spread_mv: self.days.top_spread,
            recording: self.history.problem().is_none(),
        }
    }

    /// The day under way (the desk's tools, the tests).
    pub fn day_book(&self) -> &DayBook {
        &self.days.book
    }

    /// The capacity estimator.
    pub fn capacity(&self) -> &Capacity {
        &self.days.capacity
    }

    /// The flash work of the history, when there is a gap until `free_until`
    /// long enough for it (or a slot to read for a host's listing).
    pub(super) fn history_action(&mut self, now: Instant, free_until: Instant) -> Option<Action> {
        if let Some((at, len)) = self.history.want_read() {
            return Some(Action::HistoryRead(at, len as u16));
        }
        if self.history.pending() && free_until >= now.saturating_add(super::ota::FLASH_WINDOW_US) {
            if let Some(op) = self.history.next_op() {
                return Some(Action::History(op));
            }
        }
        None
    }

    /// When the history's work wants the station polled: the moment the BMS
    /// link turns quiet, while something waits to be written or read (a gap
    /// of the poll is only seen when the station looks at it then; `MAX`:
    /// nothing waits).
    pub(super) fn history_wake(&self, now: Instant) -> Instant {
        if !(self.history.pending() || self.history.want_read().is_some()) {
            return Instant::MAX;
        }
        match self.bridge.quiet_from() {
            Some(q) if q > now => q,
            _ => Instant::MAX,
        }
    }

    /// The operation of [`Action::History`] is done (`ok`: it worked and
    /// read back the same).
    pub fn history_done(&mut self, ok: bool) {
        self.history.done(ok);
    }

    /// The bytes of [`Action::HistoryRead`] (`None`: the read failed).
    pub fn history_read(&mut self, bytes: Option<&[u8]>) {
        self.history
            .read_done(bytes.map(|b| b.get(..SLOT_MAX).unwrap_or(b)));
    }

    /// Records what a logged item means for the history.
    pub(super) fn record_logged(&mut self, now: Instant, item: &Logged) {
        let h = &mut self.history;
        match item {
            Logged::Bridge(Report::NewEvent(e)) => h.event(
                now,
                Code::Bms,
                u32::from(e.id.raw()),
                e.timestamp_s,
                e.id.name(),
            ),
            Logged::Bridge(Report::Offline { failures }) => {
                h.event(now, Code::BmsOffline, u32::from(*failures), 0, "")
            }
            Logged::Bridge(Report::Online) => h.event(now, Code::BmsOnline, 0, 0, ""),
            Logged::Inverter(InverterReport::Stale { age_ms, .. })
                if self.watch.stale_since.is_none() =>
            {
                self.watch.stale_since = Some(now.saturating_sub(u64::from(*age_ms) * 1000));
                h.event(now, Code::StaleBegan, *age_ms, 0, "");
            }
            Logged::Inverter(InverterReport::Fresh) => {
                if let Some(t) = self.watch.stale_since.take() {
                    let s = now.saturating_sub(t) / crate::SECOND;
                    h.event(now, Code::StaleEnded, s as u32, 0, "");
                }
            }
            Logged::Inverter(InverterReport::InverterLost) => {
                h.event(now, Code::InverterLost, 0, 0, "")
            }
            Logged::Inverter(InverterReport::InverterSeen) => {
                h.event(now, Code::InverterSeen, 0, 0, "")
            }
            Logged::Inverter(InverterReport::BusOff { count, .. }) => {
                h.event(now, Code::BusOff, *count, 0, "")
            }
            Logged::Config(Note::Changed(field, _)) => {
                let who = self.watch.who.unwrap_or(Who::Host);
                h.event(now, Code::Config, 0, who as u32, field.name());
            }
            Logged::Config(Note::Reset) => {
                let who = self.watch.who.unwrap_or(Who::Host);
                h.event(now, Code::ConfigReset, 0, who as u32, "");
            }
            Logged::Update(n) => {
                use super::ota::UpdateNote;
                match n {
                    UpdateNote::Installed(v) => {
                        h.event(now, Code::UpdateInstalled, 0, 0, v.as_str())
                    }
                    UpdateNote::RolledBack(v, cause) => {
                        h.event(now, Code::RolledBack, *cause as u32, 0, v.as_str())
                    }
                    UpdateNote::Confirmed => {
                        h.event(now, Code::UpdateConfirmed, 0, 0, self.identity.firmware)
                    }
                    _ => {}
                }
            }
            _ => {}
        }
    }

    /// The limits sent changed: a side that stopped (its limit at 0) or
    /// resumed is an event, with the rule that set it.
    pub(super) fn record_limits(&mut self, now: Instant) {
        let Some(inv) = self.inverter.as_ref() else {
            return;
        };
        let Some(l) = inv.limits_sent(now) else {
            return;
        };
        let stopped = (l.ccl_da == 0, l.dcl_da == 0);
        let was = self.watch.stopped;
        self.watch.stopped = stopped;
        let bits = |c: bool, d: bool| u32::from(c) | (u32::from(d) << 1);
        let began = bits(stopped.0 && !was.0, stopped.1 && !was.1);
        let ended = bits(!stopped.0 && was.0, !stopped.1 && was.1);
        if began != 0 {
            let why = inv.reasons().map_or("", |r| {
                if began & 1 != 0 {
                    r.ccl.key()
                } else {
                    r.dcl.key()
                }
            });
            self.history.event(now, Code::Stop, began, 0, why);
        }
        if ended != 0 {
            self.history.event(now, Code::Resume, ended, 0, "");
        }
    }

    /// The Wi-Fi network is up or not (images with Wi-Fi).
    pub(super) fn record_wifi(&mut self, now: Instant, up: bool) {
        let change = self.watch.wifi.change(now, up);
        self.record_link(now, change, (Code::WifiLost, Code::WifiBack));
    }

    /// The MQTT connection holds or not.
    pub(super) fn record_mqtt(&mut self, now: Instant, up: bool) {
        let change = self.watch.mqtt.change(now, up);
        self.record_link(now, change, (Code::MqttLost, Code::MqttBack));
    }

    /// A link's loss, or its return after `Some(seconds)` down, as an event.
    fn record_link(
        &mut self,
        now: Instant,
        change: Option<Option<u32>>,
        (lost, back): (Code, Code),
    ) {
        match change {
            Some(None) => self.history.event(now, lost, 0, 0, ""),
            Some(Some(s)) => self.history.event(now, back, s, 0, ""),
            None => {}
        }
    }
}
