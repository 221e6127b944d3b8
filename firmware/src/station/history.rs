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
use crate::history::event::{Code, Who};
use crate::history::log::History;
use crate::history::ring::SLOT_MAX;
use crate::inverter::InverterReport;
use crate::Instant;

/// Network state the history follows.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Watch {
    /// Who changes the configuration now.
    pub who: Option<Who>,
    /// Charging and discharging stopped (CCL, DCL at 0 in what is sent).
    pub stopped: (bool, bool),
    /// Since when the data is stale.
    pub stale_since: Option<Instant>,
    /// Since when the Wi-Fi network is lost (`Some(None)`: it was never up).
    pub wifi_down: Option<Instant>,
    pub wifi_up: bool,
    /// Since when the MQTT connection is lost.
    pub mqtt_down: Option<Instant>,
    pub mqtt_up: bool,
}

impl Station {
    /// The history opened at start ([`History::open`]) and the chip's reset
    /// reason (its raw code; `None` unknown): the start is its first event.
    pub fn set_history(&mut self, now: Instant, history: History, reset_reason: Option<u8>) {
        self.history = history;
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
            Logged::Inverter(InverterReport::Stale { age_ms, .. }) => {
                if self.watch.stale_since.is_none() {
                    self.watch.stale_since = Some(now.saturating_sub(u64::from(*age_ms) * 1000));
                    h.event(now, Code::StaleBegan, *age_ms, 0, "");
                }
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
        let w = &mut self.watch;
        if up && !w.wifi_up {
            if let Some(t) = w.wifi_down.take() {
                let s = now.saturating_sub(t) / crate::SECOND;
                self.history.event(now, Code::WifiBack, s as u32, 0, "");
            }
        } else if !up && w.wifi_up {
            w.wifi_down = Some(now);
            self.history.event(now, Code::WifiLost, 0, 0, "");
        }
        self.watch.wifi_up = up;
    }

    /// The MQTT connection holds or not.
    pub(super) fn record_mqtt(&mut self, now: Instant, up: bool) {
        let w = &mut self.watch;
        if up && !w.mqtt_up {
            if let Some(t) = w.mqtt_down.take() {
                let s = now.saturating_sub(t) / crate::SECOND;
                self.history.event(now, Code::MqttBack, s as u32, 0, "");
            }
        } else if !up && w.mqtt_up {
            w.mqtt_down = Some(now);
            self.history.event(now, Code::MqttLost, 0, 0, "");
        }
        self.watch.mqtt_up = up;
    }
}
