//! When the bridge publishes what (see the module documentation of
//! [`super`]): a sans-IO schedule. The session tells it about the connection
//! ([`Publisher::connected`], [`Publisher::disconnected`]), Home Assistant's
//! status ([`Publisher::on_ha_status`]) and new events ([`Publisher::on_event`]);
//! [`Publisher::next`] hands out the next message, encoded only then, given a
//! [`View`] of the bridge's latest telemetry; [`Publisher::next_due`] says when
//! to ask again.
//!
//! Order of what goes out after a connect: availability, the discovery configs
//! (or their removal), then the state and events. Availability is `online` only
//! while the BMS data is fresh and the link is up; the state is published only
//! then (stale data is never published as current).

use heapless::{Deque, String};
use protocol_core::events::{Event, OnlineStatus};
use protocol_core::views::LiveSnapshot;

use super::battery;
use super::discovery::{self, DeviceInfo, MAX_CELLS};
use super::published::{InverterStatus, Published};
use super::{device_topic, Identity, Settings, TOPIC_MAX};
use crate::freshness::Freshness;
use crate::host_link::encode::{self, StateExtras, TelemetryHead};
use crate::Instant;

/// Events waiting to be published; beyond, the oldest are dropped (counted).
pub const EVENT_QUEUE: usize = 8;

/// How long after a connect the availability waits for the first telemetry,
/// µs. The broker already holds `offline` (the will) when a bridge connects,
/// so an `offline` at once followed by `online` a second later (the bridge's
/// first poll) would only blink Home Assistant's entities; past this, with
/// still no data, `offline` is said anyway (the retained topic may be older
/// than the will: a broker restored from its persistence file).
pub const FIRST_DATA_GRACE_US: Instant = 10_000_000;

/// What the publisher needs of the bridge's latest telemetry.
#[derive(Debug, Clone, Copy)]
pub struct View<'a> {
    /// The latest snapshot.
    pub snapshot: Option<&'a LiveSnapshot>,
    /// Its sequence number.
    pub seq: u32,
    /// Its age now, µs.
    pub age_us: Option<Instant>,
    /// The BMS link is up and the bridge synced.
    pub online: bool,
    /// The name of the check a flagged snapshot failed.
    pub flagged: Option<&'static str>,
    /// The BMS's identity, once its version block is read.
    pub identity: Option<Identity>,
    /// The limits the inverter is sent (CVL 0.1 V, CCL 0.1 A, DCL 0.1 A), if
    /// the CAN output runs.
    pub limits: Option<(u16, u16, u16)>,
    /// Requests sent to the BMS and replies received, since start-up.
    pub link: (u32, u32),
    /// The UART wire's verdict of the last window ([`crate::bms::wire`]).
    pub wire: crate::bms::wire::WireVerdict,
    /// Packs in parallel: the battery as the inverter output sees it (its
    /// device is published while this bridge speaks: [`super::battery`]).
    pub battery: Option<&'a crate::inverter::packs::BatteryView>,
    /// The freshness rule the station runs with.
    pub freshness: Freshness,
    /// Energy into and out of the pack since start-up, mWh.
    pub energy_mwh: (u64, u64),
    /// The pack's capacity (306, 0.01 Ah), once read.
    pub capacity_cah: Option<u16>,
    /// The inverter output, when built in.
    pub inverter: Option<InverterStatus>,
    /// The Wi-Fi signal, dBm (`None`: unknown).
    pub wifi_rssi_dbm: Option<i8>,
    /// An update that was rolled back, in words.
    pub update_rolled_back: Option<&'a str>,
    /// The newest version known beyond the running one.
    pub update_latest: Option<&'a str>,
    /// How the pack ages.
    pub aging: crate::history::Aging,
}

impl<'a> View<'a> {
    /// The view of what the station published, at `now`.
    pub fn of(p: &'a Published, now: Instant) -> Self {
        Self {
            snapshot: p.snapshot.as_ref(),
            seq: p.seq,
            age_us: p.age_us(now),
            online: p.online,
            flagged: p.flagged,
            identity: p.version.as_ref().map(Identity::from_version),
            limits: p.limits,
            link: p.link,
            wire: p.wire,
            battery: p.battery.as_ref(),
            freshness: p.freshness,
            energy_mwh: p.energy_mwh,
            capacity_cah: p.capacity_cah,
            inverter: p.inverter,
            wifi_rssi_dbm: p.wifi_rssi_dbm,
            update_rolled_back: p.update_rolled_back.as_deref(),
            update_latest: p.update_latest.as_deref(),
            aging: p.aging,
        }
    }

    /// True when the data may be published as current (the one rule).
    pub fn fresh(&self) -> bool {
        self.snapshot.is_some() && self.freshness.fresh(self.online, self.age_us)
    }
}

/// What kind of message [`Publisher::next`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// The availability topic.
    Availability,
    /// A discovery config.
    Discovery,
    /// An empty retained config: the entity removed.
    Removal,
    /// The state.
    State,
    /// An event.
    Event,
    /// A discovery config of the battery's device.
    BatteryDiscovery,
    /// An empty retained config of the battery's device (discovery off).
    BatteryRemoval,
    /// The battery's state.
    BatteryState,
}

/// A message [`Publisher::next`] wrote: its topic is in the caller's topic
/// buffer, its payload the first `len` bytes of the payload buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Message {
    /// What it is.
    pub kind: Kind,
    /// Retained by the broker.
    pub retain: bool,
    /// Payload length.
    pub len: usize,
}

/// Counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PublisherStats {
    /// Messages handed out.
    pub messages: u32,
    /// States handed out.
    pub states: u32,
    /// Events dropped because the queue was full (no broker, a slow one).
    pub events_dropped: u32,
    /// Messages that did not fit the payload buffer (skipped).
    pub too_long: u32,
}

/// The schedule. See the module documentation.
#[derive(Debug, Clone)]
pub struct Publisher {
    settings: Settings,
    /// The bridge that publishes (the device blocks name it).
    bridge: crate::identity::Identity,
    /// `<version> (<build>) on <board>`: the bridge's firmware entity.
    bridge_text: String<96>,
    connected: bool,
    /// The identity announced on this connection.
    announced: Option<Identity>,
    /// Cells announced on this connection.
    announced_cells: u8,
    /// Next discovery entity (or removal index) to send.
    discovery_next: Option<usize>,
    /// Availability last sent on this connection.
    availability: Option<bool>,
    /// When this connection came up.
    connected_at: Instant,
    /// A state is wanted now.
    state_due: bool,
    next_state_at: Instant,
    last_status: Option<OnlineStatus>,
    events: Deque<Event, EVENT_QUEUE>,
    /// Link counters at the previous state, for the quality figure.
    prev_link: Option<(u32, u32)>,
    quality_permille: Option<u32>,
    /// The battery's device: the next config (or removal) to send on this
    /// connection; `None` once all are out.
    battery_next: Option<usize>,
    /// When the battery's next state is due (`None`: not speaking).
    battery_due: Option<Instant>,
    stats: PublisherStats,
}

impl Publisher {
    /// A publisher, not connected, for the bridge `bridge`.
    pub fn new(settings: Settings, bridge: &crate::identity::Identity) -> Self {
        let mut bridge_text = String::new();
        for part in [
            crate::identity::FIRMWARE,
            " (",
            crate::identity::BUILD,
            ") on ",
            bridge.board,
        ] {
            let _ = bridge_text.push_str(part);
        }
        Self {
            settings,
            bridge: *bridge,
            bridge_text,
            connected: false,
            announced: None,
            announced_cells: 0,
            discovery_next: None,
            availability: None,
            connected_at: 0,
            state_due: false,
            next_state_at: 0,
            last_status: None,
            events: Deque::new(),
            prev_link: None,
            quality_permille: None,
            battery_next: Some(0),
            battery_due: None,
            stats: PublisherStats::default(),
        }
    }

    /// The settings.
    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// Counters.
    pub fn stats(&self) -> PublisherStats {
        self.stats
    }

    /// The session connected at `now` (CONNACK received) for `id`: availability,
    /// discovery and a state follow.
    pub fn connected(&mut self, now: Instant, id: Identity) {
        self.connected = true;
        self.announced = Some(id);
        self.announced_cells = 0;
        self.discovery_next = Some(0);
        self.availability = None;
        self.connected_at = now;
        self.state_due = true;
        self.next_state_at = now;
        self.battery_next = Some(0);
        self.battery_due = None;
    }

    /// The connection is gone (the broker has the will: `offline`).
    pub fn disconnected(&mut self) {
        self.connected = false;
        self.availability = None;
        self.discovery_next = None;
    }

    /// The identity the current connection was made for (its will topic): a
    /// session reconnects when the BMS turns out to be another one.
    pub fn announced(&self) -> Option<Identity> {
        self.announced
    }

    /// A message on Home Assistant's status topic: `online` (Home Assistant
    /// restarted) re-sends the discovery configs and a state.
    pub fn on_ha_status(&mut self, payload: &[u8]) {
        if payload.trim_ascii() == b"online" && self.connected {
            self.discovery_next = Some(0);
            self.state_due = true;
            self.battery_next = Some(0);
            self.battery_due = self.battery_due.map(|_| 0);
        }
    }

    /// A new BMS event: published as soon as the connection allows. While
    /// nothing is connected, or the queue is full, the oldest is dropped.
    pub fn on_event(&mut self, e: Event) {
        if self.events.is_full() {
            self.events.pop_front();
            self.stats.events_dropped = self.stats.events_dropped.wrapping_add(1);
        }
        let _ = self.events.push_back(e);
    }

    /// When [`Publisher::next`] may have something new (the next state), µs.
    pub fn next_due(&self) -> Instant {
        let first_word = match (self.connected, self.availability) {
            (true, None) => self.connected_at.saturating_add(FIRST_DATA_GRACE_US),
            _ => Instant::MAX,
        };
        self.next_state_at
            .min(self.battery_due.unwrap_or(Instant::MAX))
            .min(first_word)
    }

    /// The next message at `now`, written into `topic` and `payload` (at least
    /// [`super::PAYLOAD_MAX`] bytes); `None` when nothing is waiting.
    pub fn next(
        &mut self,
        now: Instant,
        view: &View<'_>,
        topic: &mut String<TOPIC_MAX>,
        payload: &mut [u8],
    ) -> Option<Message> {
        if !self.connected {
            return None;
        }
        let id = self.announced?;
        let fresh = view.fresh();
        // A status change is worth a state at once.
        let status = view.snapshot.map(|s| s.status);
        if status.is_some() && status != self.last_status {
            self.last_status = status;
            self.state_due = true;
        }
        for _ in 0..4 {
            // No telemetry yet on a new connection: silent for the grace
            // (the will already says `offline`).
            let first_wait = self.availability.is_none()
                && view.snapshot.is_none()
                && now < self.connected_at.saturating_add(FIRST_DATA_GRACE_US);
            if self.availability != Some(fresh) && !first_wait {
                self.availability = Some(fresh);
                if !device_topic(topic, &self.settings, &id, "availability") {
                    return None;
                }
                let text: &[u8] = if fresh { b"online" } else { b"offline" };
                return Some(self.emit(Kind::Availability, true, text, payload));
            }
            // Discovery waits for a snapshot: the pack's cell count decides
            // which cells are announced (and which removed).
            if let (Some(n), Some(snap)) = (self.discovery_next, view.snapshot) {
                let cells = snap.cell_count.min(16) as u8;
                match self.discovery_message(n, cells, &id, topic, payload) {
                    Some(m) => {
                        self.discovery_next = Some(n + 1);
                        return Some(m);
                    }
                    None => {
                        self.discovery_next = None;
                        self.announced_cells = cells;
                    }
                }
            }
            // The pack's cell count changed: announce (or remove) again.
            if let Some(s) = view.snapshot {
                let cells = s.cell_count.min(16) as u8;
                if cells != self.announced_cells && self.discovery_next.is_none() {
                    self.discovery_next = Some(0);
                    continue;
                }
            }
            break;
        }
        let due = self.state_due || now >= self.next_state_at;
        if fresh && due {
            if let Some(m) = self.state(now, view, &id, topic, payload) {
                return Some(m);
            }
        }
        if let Some(m) = self.battery(now, view, topic, payload) {
            return Some(m);
        }
        if let Some(e) = self.events.pop_front() {
            if !device_topic(topic, &self.settings, &id, "event") {
                return None;
            }
            let n = encode::event(payload, None, &e, false)?;
            // The line's `\n` is not part of the payload.
            return Some(self.count(Message {
                kind: Kind::Event,
                retain: false,
                len: n.saturating_sub(1),
            }));
        }
        None
    }

    /// The battery's device (packs in parallel): its configs once per
    /// connection and its state every period while this bridge speaks; with
    /// discovery off, its configs removed once per connection (the state
    /// still published while speaking).
    fn battery(
        &mut self,
        now: Instant,
        view: &View<'_>,
        topic: &mut String<TOPIC_MAX>,
        payload: &mut [u8],
    ) -> Option<Message> {
        let s = &self.settings;
        if let (false, Some(n)) = (s.discovery, self.battery_next) {
            if let Some(e) = battery::ENTITIES.get(n) {
                self.battery_next = Some(n + 1);
                if !battery::config_topic(topic, s, e) {
                    return None;
                }
                return Some(self.emit(Kind::BatteryRemoval, true, b"", payload));
            }
            self.battery_next = None;
        }
        let Some(b) = view.battery.filter(|b| b.speaking) else {
            self.battery_due = None;
            return None;
        };
        if let (true, Some(n)) = (s.discovery, self.battery_next) {
            let Some(e) = battery::ENTITIES.get(n) else {
                self.battery_next = None;
                self.battery_due = Some(now);
                return self.battery(now, view, topic, payload);
            };
            self.battery_next = Some(n + 1);
            if !battery::config_topic(topic, s, e) {
                return None;
            }
            return match battery::config(payload, s, &self.bridge, e) {
                Some(len) => Some(self.count(Message {
                    kind: Kind::BatteryDiscovery,
                    retain: true,
                    len,
                })),
                None => {
                    self.stats.too_long = self.stats.too_long.wrapping_add(1);
                    None
                }
            };
        }
        if now < self.battery_due.unwrap_or(0) {
            return None;
        }
        self.battery_due = Some(now.saturating_add(s.publish_period_us));
        if !battery::state_topic(topic, s) {
            return None;
        }
        let n = encode::battery(payload, b)?;
        // The line's `\n` is not part of the payload.
        Some(self.count(Message {
            kind: Kind::BatteryState,
            retain: false,
            len: n.saturating_sub(1),
        }))
    }

    fn emit(&mut self, kind: Kind, retain: bool, text: &[u8], payload: &mut [u8]) -> Message {
        let n = text.len().min(payload.len());
        if let (Some(dst), Some(src)) = (payload.get_mut(..n), text.get(..n)) {
            dst.copy_from_slice(src);
        }
        self.count(Message {
            kind,
            retain,
            len: n,
        })
    }

    fn count(&mut self, m: Message) -> Message {
        self.stats.messages = self.stats.messages.wrapping_add(1);
        if m.kind == Kind::State {
            self.stats.states = self.stats.states.wrapping_add(1);
        }
        m
    }

    /// The `n`-th message of a discovery round: configs of the entities (or,
    /// with discovery off, empty retained payloads for every entity of a full
    /// pack), then removals of cells beyond the pack's count. `None` at the end.
    fn discovery_message(
        &mut self,
        n: usize,
        cells: u8,
        id: &Identity,
        topic: &mut String<TOPIC_MAX>,
        payload: &mut [u8],
    ) -> Option<Message> {
        let s = &self.settings;
        if !s.discovery {
            let e = discovery::nth(n, MAX_CELLS)?;
            if !discovery::config_topic(topic, s, id, &e) {
                return None;
            }
            return Some(self.emit(Kind::Removal, true, b"", payload));
        }
        let announce = discovery::count(cells);
        if n < announce {
            let e = discovery::nth(n, cells)?;
            if !discovery::config_topic(topic, s, id, &e) {
                return None;
            }
            let info = DeviceInfo {
                id,
                bridge: &self.bridge,
            };
            return match discovery::config(payload, s, &info, &e) {
                Some(len) => Some(self.count(Message {
                    kind: Kind::Discovery,
                    retain: true,
                    len,
                })),
                None => {
                    self.stats.too_long = self.stats.too_long.wrapping_add(1);
                    // Skip it: the next one.
                    self.discovery_message(n + 1, cells, id, topic, payload)
                }
            };
        }
        // Cells a pack of `cells` does not have: removed.
        let c = n - announce + usize::from(cells) + 1;
        if c > usize::from(MAX_CELLS) {
            return None;
        }
        let e = discovery::cell(c as u8);
        if !discovery::config_topic(topic, s, id, &e) {
            return None;
        }
        Some(self.emit(Kind::Removal, true, b"", payload))
    }

    fn state(
        &mut self,
        now: Instant,
        view: &View<'_>,
        id: &Identity,
        topic: &mut String<TOPIC_MAX>,
        payload: &mut [u8],
    ) -> Option<Message> {
        if !device_topic(topic, &self.settings, id, "state") {
            return None;
        }
        // Link quality: replies per request since the previous state (since
        // start-up for the first).
        let (req0, rep0) = self.prev_link.unwrap_or((0, 0));
        let dreq = view.link.0.wrapping_sub(req0);
        let drep = view.link.1.wrapping_sub(rep0);
        if dreq > 0 {
            self.quality_permille =
                Some((u64::from(drep.min(dreq)) * 1000 / u64::from(dreq)) as u32);
        }
        self.prev_link = Some(view.link);
        let snapshot = view.snapshot?;
        let status_name = match snapshot.status {
            protocol_core::events::OnlineStatus::Unknown(_) => "Other",
            s => s.name(),
        };
        // What is left: the SOC (1e-6 %) of the capacity (0.01 Ah).
        let remaining_cah = view.capacity_cah.map(|c| {
            (u64::from(c) * u64::from(snapshot.soc_raw.min(100_000_000)) / 100_000_000) as u32
        });
        let ignored = view.inverter.and_then(|i| i.ignored).map(|e| e.text());
        let stage = view.inverter.and_then(|i| i.stage).map(|s| s.text());
        let why = view
            .inverter
            .and_then(|i| i.reasons)
            .map(|r| [r.cvl.text(), r.ccl.text(), r.dcl.text()]);
        let why_text = |k: usize| why.as_ref().and_then(|w| w.get(k)).map(|l| l.as_str());
        let mut wire = crate::log_line::Line::new();
        view.wire.text(&mut wire);
        let doctor = view.inverter.map(|i| {
            let mut keys = heapless::String::<160>::new();
            for v in i.verdicts.iter().flatten() {
                if !keys.is_empty() {
                    let _ = keys.push_str(", ");
                }
                let _ = keys.push_str(v.key()); // nine keys fit
            }
            if keys.is_empty() {
                let _ = keys.push_str("ok");
            }
            keys
        });
        let extras = StateExtras {
            status: snapshot.status.key().unwrap_or("other"),
            status_name,
            age_ms: view.age_us.unwrap_or(0) / crate::MS,
            link_quality_permille: self.quality_permille,
            limits: view.limits,
            remaining_cah,
            energy_mwh: view.energy_mwh,
            uptime_s: now / crate::SECOND,
            bridge_firmware: &self.bridge_text,
            can_state: view.inverter.map(|i| i.can.key()),
            inverter_heard: view.inverter.map(|i| i.heard),
            stops: view.inverter.and_then(|i| i.stops).map(|s| s.keys()),
            soc_told: view.inverter.and_then(|i| i.told.soc_pct),
            ignored_stop: ignored.as_deref(),
            charge_stage: stage.as_ref().map(|s| s.as_str()),
            why: [why_text(0), why_text(1), why_text(2)],
            can_doctor: doctor.as_ref().map(|d| d.as_str()),
            bms_wire: Some(wire.as_str()),
            wifi_rssi_dbm: view.wifi_rssi_dbm,
            update_rolled_back: view.update_rolled_back,
            update_latest: view.update_latest,
            aging: view.aging,
        };
        let head = TelemetryHead {
            req: None,
            seq: view.seq,
            age_ms: view.age_us.map(|a| a / crate::MS),
            stale_after_ms: None,
            online: view.online,
            ready: true,
            inverter: None,
            restart_pending: 0,
        };
        let n = encode::state(payload, head, Some(snapshot), view.flagged, Some(&extras));
        let Some(n) = n else {
            self.stats.too_long = self.stats.too_long.wrapping_add(1);
            self.state_due = false;
            self.next_state_at = now.saturating_add(self.settings.publish_period_us);
            return None;
        };
        self.state_due = false;
        self.next_state_at = now.saturating_add(self.settings.publish_period_us);
        Some(self.count(Message {
            kind: Kind::State,
            retain: false,
            len: n,
        }))
    }
}
