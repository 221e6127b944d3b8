//! The station: everything one bridge is, wired together, sans-IO. It owns
//! the [`Bridge`] (the BMS side), the bridge's configuration
//! ([`ConfigState`]), the host link ([`HostLink`](crate::host_link::HostLink)), the inverter output
//! ([`Inverter`](crate::inverter::Inverter)) and what the MQTT output reads ([`Published`]); the chip
//! shell and every desktop runner (the virtual-time harness and its closed
//! loops, the multi-pack loop, `sim --bridge-pty`, the MQTT runner, the
//! desktop tool's direct mode) drive this same type, so the wiring the chip
//! runs is the wiring every test runs.
//!
//! **Inputs**: bytes from the BMS ([`Station::rx_buffer`] +
//! [`Station::received`]), bytes from the host ([`Station::host_rx`]), a host
//! that (re)connected ([`Station::host_connected`]), CAN frames and what the
//! controller did ([`Station::can_received`], [`Station::can_sent`],
//! [`Station::can_bus_off`], [`Station::can_recovered`]), the BOOT button
//! ([`Station::button`]), the end of a save ([`Station::saved`]), log lines of
//! other tasks ([`Station::foreign_log`]), and time: every call takes `now`.
//!
//! **Outputs**: [`Station::poll`] says what to do next ([`Action`]): log a
//! line, send [`Station::transmit_bytes`] to the BMS, hand a frame to the CAN
//! controller (one at a time: the next only after its result), recover the
//! bus, save [`Station::record`] to flash (only when no BMS reply can be on its
//! way; nothing is sent meanwhile), or wait until a time. Lines for the host
//! come out of [`Station::next_host_line`] whenever the port has room for a
//! whole one. What the MQTT output publishes is [`Station::published`]
//! (changed when [`Station::generation`] does), its events
//! [`Station::take_event`].
//!
//! **Rules that live here** (and nowhere in a shell):
//! * log lines go out only when the BMS link is quiet (just before a request,
//!   or while waiting with no reply on its way): a log write that blocks never
//!   delays reading a reply;
//! * a save of the record happens only when the link is quiet, and nothing is
//!   sent to the BMS until it is done;
//! * every bridge report reaches the host link (outcomes, events), the
//!   inverter output (charge-blocking events), the MQTT output (events) and
//!   the log, in that order;
//! * a change of the running configuration reaches the host link and the
//!   inverter output at once;
//! * what the inverter is told ([`Inverter::limits_sent`](crate::inverter::Inverter::limits_sent)) is what MQTT shows.

use heapless::Deque;
use protocol_core::events::Event;
use protocol_core::settings::SettingId;

use crate::bms::timing::Timing;
use crate::bridge::report::{Level, Report};
use crate::bridge::{Bridge, Command, Step};
use crate::config::button::Hold;
use crate::config::state::{ConfigState, Note, Outcomes};
use crate::config::store::{Loaded, Saved, StoreError};
use crate::config::value::Parsed;
use crate::config::{Config, FieldId};
use crate::energy::Energy;
use crate::freshness::Freshness;
use crate::host_link::encode::InverterState;
#[cfg(feature = "host-link")]
use crate::host_link::HostLink;
use crate::improv::{JoinFailure, Network, WifiLink, WifiRequest};
use crate::inverter::control::{Limits, PackSettings};
use crate::inverter::dialect::CanFrame;
use crate::inverter::packs::BatteryView;
#[cfg(feature = "can")]
use crate::inverter::Inverter;
use crate::inverter::{InverterAction, InverterReport, TxResult};
use crate::text::{self, Line};
use crate::Instant;

pub use crate::mqtt::published::{InverterStatus, Published};
use crate::mqtt::MqttState;

/// Shows a host link (the USB port's, or the update port's) the CAN capture
/// of the inverter output `$inverter` (`Option<&parts::Output>`): what is
/// held, the protocol of its frames, and the entry its `get can` listing
/// needs next. A macro: the two ports' types differ with the features.
macro_rules! feed_capture {
    ($h:expr, $inverter:expr) => {{
        let inverter = $inverter;
        let protocol = inverter.map_or("", |i| i.config().protocol.key());
        let capture = inverter.map(|i| i.capture());
        $h.on_can_span(capture.map(|c| c.span()), protocol);
        if let (Some(seq), Some(c)) = ($h.can_wanted(), capture) {
            $h.on_can_entry(seq, c.get(seq));
        }
    }};
}

mod history;
pub mod ota;
mod parts;
pub mod pumps;

/// How often a bridge of several packs hands the battery to the host link
/// and the MQTT output, µs.
pub const BATTERY_VIEW_PERIOD_US: Instant = crate::SECOND;

/// BMS events kept for the MQTT output until it takes them; beyond, the
/// oldest go (counted in [`Station::events_dropped`]).
pub const MQTT_EVENTS: usize = 8;

/// What the station is built with besides its record.
#[derive(Debug, Clone, Copy)]
pub struct Setup {
    /// The bridge's timing.
    pub timing: Timing,
    /// Who the bridge is (chip, board, what is built in: a host link — a
    /// port to a computer —, a CAN controller — without one the inverter
    /// output is off, whatever the record says —, Wi-Fi, the store), for the
    /// host link's `hello`.
    pub identity: crate::identity::Identity,
    /// The inverter output's settings instead of the record's (for desktop
    /// runs of settings the record cannot hold: its periods and timeouts);
    /// `None` on the chip. A later change of the running configuration
    /// replaces them as usual.
    pub inverter: Option<crate::inverter::InverterConfig>,
}

/// What happened that the log shows.
#[derive(Debug, Clone, PartialEq)]
pub enum Logged {
    /// A bridge report.
    Bridge(Report),
    /// A configuration note.
    Config(Note),
    /// An inverter output report.
    Inverter(InverterReport),
    /// A host came back after this many of its lines were dropped (nobody
    /// read the port).
    HostMissed(u32),
    /// Improv Wi-Fi (the browser installer's network set-up).
    Improv(crate::improv::Note),
    /// The radio's start (images with Wi-Fi).
    Radio(crate::wifi::Radio),
    /// Updates: a transfer, the trial, a rollback.
    Update(ota::UpdateNote),
}

impl Logged {
    /// The level it is logged at.
    pub fn level(&self) -> Level {
        match self {
            Self::Bridge(r) => r.level(),
            Self::Config(n) => text::config_level(n),
            Self::Inverter(r) => r.level(),
            Self::HostMissed(_) => Level::Warn,
            Self::Improv(n) => text::improv_level(n),
            Self::Radio(r) if r.warns() => Level::Warn,
            Self::Radio(_) => Level::Info,
            Self::Update(n) => n.level(),
        }
    }
}

/// What the shell must do next.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Log this (the words: [`Station::log_text`]), then poll again.
    Log(Logged),
    /// Write [`Station::transmit_bytes`] to the BMS, then poll again.
    Transmit,
    /// Hand this frame to the CAN controller; report the result with
    /// [`Station::can_sent`] or [`Station::can_bus_off`].
    Can(CanFrame),
    /// Start the CAN controller's bus-off recovery; report it with
    /// [`Station::can_recovered`].
    CanRecover,
    /// Save [`Station::record`] now and report with [`Station::saved`];
    /// send nothing to the BMS before.
    Save,
    /// Ask the Wi-Fi side this (Improv Wi-Fi); report with
    /// [`Station::wifi_joined`] or [`Station::wifi_scanned`].
    Wifi(WifiRequest),
    /// Do this flash operation of an update ([`Station::program_bytes`] for
    /// a program), read it back, and report with [`Station::flashed`]; send
    /// nothing to the BMS before.
    Flash(crate::update::transfer::Op),
    /// Restart the chip (an update is installed).
    Restart,
    /// Do this flash operation of the history, read it back, and report
    /// with [`Station::history_done`]; send nothing to the BMS before.
    History(crate::history::ring::Op),
    /// Read this many bytes at this flash address for a host's listing of
    /// the history, and hand them to [`Station::history_read`].
    HistoryRead(u32, u16),
    /// Nothing before this time, unless an input arrives.
    WaitUntil(Instant),
}

/// The CAN controller as the station sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Can {
    /// Ready for a frame; the inverter output wants to be polled at this time.
    Idle(Instant),
    /// A frame or a recovery is with the controller.
    Busy,
}

/// One bridge. See the module documentation.
#[derive(Debug, Clone)]
pub struct Station {
    bridge: Bridge,
    config: ConfigState,
    host: Option<parts::Host>,
    inverter: Option<parts::Output>,
    identity: crate::identity::Identity,
    can: Can,
    hold: Hold,
    /// [`Bridge::step`] said "transmit": the logs go first.
    transmit_pending: bool,
    /// The snapshot the inverter output has (its sequence number).
    fed_seq: u32,
    /// Several packs: the battery view, and when it is handed on next.
    battery: Option<BatteryView>,
    next_view: Instant,
    /// What the MQTT output reads changed: bumped on a new snapshot, a change
    /// of online, the limits sent, the battery view.
    generation: u32,
    last_online: bool,
    last_limits: Option<Limits>,
    events: Deque<Event, MQTT_EVENTS>,
    events_dropped: u32,
    /// Lines the port dropped since a host last came; and how many of them
    /// the log still has to say (once the host is back).
    host_missed: u32,
    missed_to_log: u32,
    /// The radio's state to log, when it changed.
    radio_to_log: Option<crate::wifi::Radio>,
    /// Energy in and out, counted over the snapshots.
    energy: Energy,
    /// The Wi-Fi signal, dBm, as the Wi-Fi task last read it.
    wifi_rssi: Option<i8>,
    /// The MQTT session's state as `hello` says it (see [`Station::mqtt_state`]).
    mqtt: Option<MqttState>,
    /// Updates: the slots, `otadata`, the trial, the transfer.
    ota: crate::update::Ota,
    /// What the log still has to say of updates.
    ota_notes: Deque<ota::UpdateNote, 4>,
    /// An installed update restarts the bridge at this time.
    restart_at: Option<Instant>,
    /// The link of a connection to the update port on the network.
    update_port: Option<parts::UpdatePort>,
    /// The history in flash (events, days).
    history: crate::history::log::History,
    /// What the history follows.
    watch: history::Watch,
    /// The latest `now` the station was polled with.
    last_now: Instant,
    /// The pack's days and capacity.
    days: history::Days,
}

impl Station {
    /// A station at `now` with the record it loaded.
    pub fn new(setup: Setup, loaded: Loaded, now: Instant) -> Self {
        Self::with_config(setup, ConfigState::new(loaded.config, loaded.source), now)
    }

    /// A station at `now` that runs with a record its runner chose itself
    /// (the desktop tool's direct mode, which has no bridge of its own to
    /// configure): its log says nothing about a configuration
    /// ([`ConfigState::fixed`]).
    pub fn with_record(setup: Setup, config: Config, now: Instant) -> Self {
        Self::with_config(setup, ConfigState::fixed(config), now)
    }

    fn with_config(setup: Setup, config: ConfigState, now: Instant) -> Self {
        #[cfg(feature = "can")]
        let inverter = setup.identity.features.can.then(|| {
            let c = setup
                .inverter
                .unwrap_or_else(|| config.running().inverter());
            Inverter::new(c, now)
        });
        #[cfg(not(feature = "can"))]
        let inverter = None;
        #[cfg(feature = "host-link")]
        let host = setup
            .identity
            .features
            .host_link
            .then(|| HostLink::new(config.running().host_link(&setup.identity), now));
        #[cfg(not(feature = "host-link"))]
        let host = None;
        Self {
            bridge: Bridge::new(setup.timing, now),
            config,
            host,
            inverter,
            identity: setup.identity,
            can: Can::Idle(now),
            hold: Hold::new(),
            transmit_pending: false,
            fed_seq: 0,
            battery: None,
            next_view: now,
            generation: 0,
            last_online: false,
            last_limits: None,
            events: Deque::new(),
            events_dropped: 0,
            host_missed: 0,
            missed_to_log: 0,
            radio_to_log: None,
            energy: Energy::new(),
            wifi_rssi: None,
            mqtt: None,
            ota: crate::update::Ota::default(),
            ota_notes: Deque::new(),
            restart_at: None,
            update_port: None,
            history: crate::history::log::History::without("this runner keeps no history"),
            watch: history::Watch::default(),
            last_now: now,
            days: history::Days::new(now),
        }
    }

    /// The bridge.
    pub fn bridge(&self) -> &Bridge {
        &self.bridge
    }

    /// The bridge, for commands (`submit`) and counters.
    pub fn bridge_mut(&mut self) -> &mut Bridge {
        &mut self.bridge
    }

    /// The configuration.
    pub fn config(&self) -> &ConfigState {
        &self.config
    }

    /// The host link, when built in.
    #[cfg(feature = "host-link")]
    pub fn host_link(&self) -> Option<&HostLink> {
        self.host.as_ref()
    }

    /// The host link, to drive it past the station (tests of the host link's
    /// own lines).
    #[cfg(feature = "host-link")]
    pub fn host_link_mut(&mut self) -> Option<&mut HostLink> {
        self.host.as_mut()
    }

    /// The inverter output, when built in.
    #[cfg(feature = "can")]
    pub fn inverter(&self) -> Option<&Inverter> {
        self.inverter.as_ref()
    }

    /// The inverter output's node number (0: this bridge alone).
    fn node(&self) -> u8 {
        self.inverter.as_ref().map_or(0, |i| i.node())
    }

    /// The chip's name the host link gives.
    pub fn chip(&self) -> &'static str {
        self.identity.chip
    }

    /// A line the shell writes once at boot (the board, its pins, the log
    /// path, the CAN output, the host link's wire, the UART, the profile):
    /// its words and level, for the shell's own log; the host link keeps it
    /// and gives it to every host after its `hello`.
    pub fn boot_line(&mut self, line: &text::Boot) -> (Level, Line) {
        let mut out = Line::new();
        text::boot(line, &self.identity, &mut out);
        if let Some(h) = self.host.as_mut() {
            h.boot_line(line.level(), out.as_str());
        }
        (line.level(), out)
    }

    /// Changes the configuration as a host's `set_config` would (not
    /// read-only-checked: the start-up options of a desktop runner). The
    /// changes apply like any other; the save follows through [`Action::Save`].
    pub fn change_config(&mut self, now: Instant, changes: &[(FieldId, Parsed)]) -> Outcomes {
        let settings = self.bridge.telemetry().settings.clone();
        let pack = settings
            .as_ref()
            .and_then(crate::config::PackSettings::from_registers);
        self.watch.who = Some(crate::history::event::Who::Host);
        let out = self.config.change(changes, false, pack.as_ref());
        self.apply_running(now);
        out
    }

    // ---- the BMS ----

    /// Where the UART driver writes received bytes (see [`Bridge::rx_buffer`]).
    pub fn rx_buffer(&mut self) -> &mut [u8] {
        self.bridge.rx_buffer()
    }

    /// The first `n` bytes of [`Station::rx_buffer`] were received at `now`.
    pub fn received(&mut self, now: Instant, n: usize) {
        if let Some(h) = self.host.as_mut() {
            if h.capturing() {
                let bytes = self.bridge.rx_buffer().get(..n).unwrap_or(&[]);
                h.on_uart_rx(bytes);
            }
        }
        self.bridge.handle_received(now, n);
        self.feed_inverter();
    }

    /// Bytes received at `now`, from a buffer of the caller's.
    pub fn handle_rx(&mut self, now: Instant, bytes: &[u8]) {
        let mut rest = bytes;
        while !rest.is_empty() {
            let space = self.bridge.rx_buffer();
            let n = space.len().min(rest.len());
            if let (Some(dst), Some(src)) = (space.get_mut(..n), rest.get(..n)) {
                dst.copy_from_slice(src);
            }
            self.received(now, n);
            rest = rest.get(n..).unwrap_or(&[]);
        }
    }

    /// The bytes to write after [`Action::Transmit`].
    pub fn transmit_bytes(&self) -> &[u8] {
        self.bridge.transmit_bytes()
    }

    // ---- the host ----

    /// A host (re)opened the port: `hello` first.
    pub fn host_connected(&mut self, now: Instant) {
        if let Some(h) = self.host.as_mut() {
            h.connected(now);
        }
        if self.host_missed > 0 {
            self.missed_to_log = self.missed_to_log.saturating_add(self.host_missed);
            self.host_missed = 0;
        }
    }

    /// Bytes from the host at `now`.
    pub fn host_rx(&mut self, now: Instant, bytes: &[u8]) {
        self.watch.who = Some(crate::history::event::Who::Usb);
        if let Some(h) = self.host.as_mut() {
            h.handle_rx(
                now,
                bytes,
                &mut self.bridge,
                &mut self.config,
                &mut self.ota,
            );
            if let Some(t) = h.take_time() {
                self.history
                    .set_date(now, u64::from(t), crate::history::event::Who::Usb);
            }
        }
        self.apply_running(now);
    }

    /// The next line for the host (`\n`-terminated) into `out` (at least
    /// [`crate::host_link::OUT_LINE_MAX`] bytes); call only when the port can
    /// take a whole line.
    pub fn next_host_line(&mut self, now: Instant, out: &mut [u8]) -> Option<usize> {
        let inverter = self.inverter.as_ref().map(|i| InverterState {
            protocol: i.config().protocol.key(),
            can: i.can_state().key(),
            heard: i.inverter_heard(),
            limits: i.limits_sent(now).map(|l| (l.cvl_dv, l.ccl_da, l.dcl_da)),
            stops: i.protection().map(|s| s.keys()),
            told: i.told().unwrap_or_default(),
            ignored: i.ignored(),
            stage: i.stage(),
            reasons: i.reasons(),
            heartbeat: i.doctor().heartbeat(),
            verdicts: i.doctor().verdict_array(now),
        });
        let pending = self.config.restarts_pending() as u32;
        let h = self.host.as_mut()?;
        feed_capture!(h, self.inverter.as_ref());
        h.on_history(self.history.problem());
        if h.history_start() {
            self.history.list();
        }
        if h.history_wanted() {
            if let Some(item) = self.history.take_listed() {
                h.on_history_item(item);
            }
        }
        h.on_inverter(inverter);
        h.on_restart_pending(pending);
        h.next_line(now, &self.bridge, &self.config, out)
    }

    /// The MQTT session's latest state (images with Wi-Fi): `hello` says it.
    pub fn mqtt_state(&mut self, state: MqttState) {
        // While two clients fight over one id, each new connection is
        // dropped again at once: only one that held ends the finding.
        if self.mqtt == Some(MqttState::ClientIdTaken) && state == MqttState::Connected {
            return;
        }
        self.mqtt = Some(state);
        let up = matches!(state, MqttState::Connected | MqttState::Held);
        self.record_mqtt(self.last_now, up);
        if let Some(h) = self.host.as_mut() {
            h.on_mqtt(state.key());
        }
    }

    /// Where the radio's start stands (images with Wi-Fi): `hello` says it,
    /// and the log (a later state before the line went out replaces it).
    pub fn radio(&mut self, radio: crate::wifi::Radio) {
        self.radio_to_log = Some(radio);
        if let Some(h) = self.host.as_mut() {
            h.on_radio(radio);
        }
    }

    /// The Wi-Fi signal of the access point, dBm, as the Wi-Fi task read it
    /// (`None`: not joined, or not read): MQTT publishes it as a diagnostic.
    pub fn wifi_rssi(&mut self, dbm: Option<i8>) {
        if dbm != self.wifi_rssi {
            self.wifi_rssi = dbm;
            self.generation = self.generation.wrapping_add(1);
        }
    }

    /// Lines are waiting for the host.
    pub fn host_has_output(&self) -> bool {
        self.host.as_ref().is_some_and(parts::Host::has_output)
    }

    /// The port dropped `n` whole lines (a host that does not read): counted
    /// in the host link's `dropped_lines`.
    pub fn host_lines_dropped(&mut self, n: u32) {
        if let Some(h) = self.host.as_mut() {
            h.lines_dropped(n);
            self.host_missed = self.host_missed.saturating_add(n);
        }
    }

    /// A log line of another task (Wi-Fi, MQTT) for the host link's `log`
    /// lines (the task logs it itself).
    pub fn foreign_log(&mut self, level: Level, text: &str) {
        if let Some(h) = self.host.as_mut() {
            h.log(level, text);
        }
    }

    // ---- Wi-Fi (images with Wi-Fi; Improv on the host port) ----

    /// The bridge's name on the network (its host name), for the installer.
    pub fn set_network_name(&mut self, name: &str) {
        if let Some(h) = self.host.as_mut() {
            h.improv_mut().set_name(name);
        }
    }

    /// The Wi-Fi link changed: joined (its address), lost, or off.
    pub fn wifi_link(&mut self, link: WifiLink) {
        self.record_wifi(self.last_now, matches!(link, WifiLink::Up(_)));
        if let Some(h) = self.host.as_mut() {
            h.wifi_link(link);
        }
    }

    /// The join of the last [`Action::Wifi`] ended.
    pub fn wifi_joined(&mut self, now: Instant, result: Result<[u8; 4], JoinFailure>) {
        if let Some(h) = self.host.as_mut() {
            h.improv_mut().joined(now, result);
            if let Ok(ip) = result {
                h.wifi_link(WifiLink::Up(ip));
            }
        }
    }

    /// The Wi-Fi side cannot carry out `req` (no radio, or it is not
    /// there): a join fails, a scan finds nothing — the answer every shell
    /// without a Wi-Fi task gives.
    pub fn wifi_unavailable(&mut self, now: Instant, req: &WifiRequest) {
        match req {
            WifiRequest::Join { .. } => self.wifi_joined(now, Err(JoinFailure::Other)),
            WifiRequest::Scan => self.wifi_scanned(now, &[]),
        }
    }

    /// The scan of the last [`Action::Wifi`] ended.
    pub fn wifi_scanned(&mut self, now: Instant, networks: &[Network]) {
        if let Some(h) = self.host.as_mut() {
            h.improv_mut().scanned(now, networks);
        }
    }

    // ---- the CAN bus ----

    /// A frame from the bus.
    pub fn can_received(&mut self, now: Instant, id: u16, data: &[u8]) {
        if let Some(i) = self.inverter.as_mut() {
            i.on_received(now, id, data);
        }
    }

    /// The frame of the last [`Action::Can`] was sent or failed.
    pub fn can_sent(&mut self, now: Instant, result: TxResult) {
        self.can = Can::Idle(now);
        if let Some(i) = self.inverter.as_mut() {
            i.on_tx(now, result);
        }
    }

    /// The controller went bus-off (with the last frame, or by itself).
    pub fn can_bus_off(&mut self, now: Instant) {
        self.can = Can::Idle(now);
        if let Some(i) = self.inverter.as_mut() {
            i.on_bus_off(now);
        }
    }

    /// The recovery asked for by [`Action::CanRecover`] ended: the controller
    /// is back on the bus (`ok`) or still off.
    pub fn can_recovered(&mut self, now: Instant, ok: bool) {
        self.can = Can::Idle(now);
        if !ok {
            if let Some(i) = self.inverter.as_mut() {
                i.on_bus_off(now);
            }
        }
    }

    // ---- the button, the store ----

    /// A sample of the BOOT button (see [`crate::config::button`]): held long
    /// enough, it lifts read-only.
    pub fn button(&mut self, now: Instant, pressed: bool) {
        if self.hold.sample(now, pressed) {
            self.watch.who = Some(crate::history::event::Who::Button);
            self.config.unlock();
            self.apply_running(now);
        }
    }

    /// The record to write after [`Action::Save`].
    pub fn record(&self) -> &Config {
        self.config.stored()
    }

    /// Where the store lives (the chip's flash and its partition), for the
    /// log and `hello`.
    pub fn set_store_site(&mut self, site: crate::config::store::StoreSite) {
        self.config.set_site(site);
    }

    /// The save of [`Action::Save`] is done.
    pub fn saved(&mut self, result: Result<Saved, StoreError>) {
        if let Some(r) = self.config.saved(result) {
            if let Some(h) = self.host.as_mut() {
                h.on_config_saved(r);
            }
        }
    }

    // ---- what the MQTT output reads ----

    /// Bumped whenever [`Station::published`] changes.
    pub fn generation(&self) -> u32 {
        self.generation
    }

    /// The picture to publish at `now` (see [`Published`]).
    pub fn published(&self, now: Instant) -> Published {
        let t = self.bridge.telemetry();
        let s = self.bridge.link_stats();
        Published {
            snapshot: t.snapshot.clone(),
            seq: t.snapshot_seq,
            taken_at: t.snapshot_at,
            online: t.online && t.ready,
            flagged: t.live.flagged.map(|c| c.name()),
            version: t.version,
            link: (s.requests, s.replies),
            wire: self.bridge.wire().1,
            limits: self
                .inverter
                .as_ref()
                .and_then(|i| i.limits_sent(now))
                .map(|l| (l.cvl_dv, l.ccl_da, l.dcl_da)),
            freshness: self.freshness(),
            battery: self.battery.clone(),
            energy_mwh: (self.energy.charged_mwh(), self.energy.discharged_mwh()),
            capacity_cah: t
                .settings
                .as_ref()
                .and_then(|b| b.get(SettingId::BatteryCapacity.address())),
            inverter: self.inverter.as_ref().map(|i| InverterStatus {
                protocol: i.config().protocol.key(),
                can: i.can_state(),
                heard: i.inverter_heard(),
                stops: i.protection(),
                told: i.told().unwrap_or_default(),
                ignored: i.ignored(),
                stage: i.stage(),
                reasons: i.reasons(),
                verdicts: i.doctor().verdict_array(now),
            }),
            wifi_rssi_dbm: self.wifi_rssi,
            update_rolled_back: crate::host_link::rolled_back_text(&self.ota),
            update_latest: self.ota.latest(self.identity.firmware).map(|v| {
                let mut s = crate::update::transfer::Version::new();
                let _ = s.push_str(v);
                s
            }),
            aging: self.aging(),
        }
    }

    /// The one freshness rule, with the limit the configuration sets.
    pub fn freshness(&self) -> Freshness {
        match self.inverter.as_ref() {
            Some(i) => i.config().freshness,
            None => self.config.running().freshness(),
        }
    }

    /// The next BMS event for the MQTT output.
    pub fn take_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// Events the MQTT output did not take in time.
    pub fn events_dropped(&self) -> u32 {
        self.events_dropped
    }

    /// Several packs: the battery as this bridge sees it (refreshed every
    /// [`BATTERY_VIEW_PERIOD_US`]).
    pub fn battery_view(&self) -> Option<&BatteryView> {
        self.battery.as_ref()
    }

    // ---- the log ----

    /// The words of a logged item (as the chip prints them).
    pub fn log_text(&self, item: &Logged, out: &mut Line) {
        match item {
            Logged::Bridge(r) => text::report(r, out),
            Logged::Config(n) => text::config_note(n, &self.config, out),
            // An image without the output has no reports of it (and links
            // none of their words).
            Logged::Inverter(r) if cfg!(feature = "can") => text::inverter(r, out),
            Logged::Inverter(_) => {}
            Logged::HostMissed(n) if cfg!(feature = "host-link") => {
                out.push("host link: ")
                    .uint(u64::from(*n))
                    .push(" lines dropped while no host read the port");
            }
            Logged::HostMissed(_) => {}
            Logged::Improv(n) if cfg!(feature = "host-link") => text::improv_note(n, out),
            Logged::Improv(_) => {}
            Logged::Radio(r) => {
                out.push(r.text());
            }
            Logged::Update(n) => n.text(out),
        }
    }

    // ---- what to do next ----

    /// What to do at `now`.
    pub fn poll(&mut self, now: Instant) -> Action {
        self.last_now = now;
        self.feed_inverter();
        self.tick_days(now);
        self.apply_running(now);
        self.tick_battery(now);
        if self.transmit_pending {
            if let Some(item) = self.next_logged(now) {
                return Action::Log(item);
            }
            self.transmit_pending = false;
            return self.transmit();
        }
        // The flash write stops the CPU: only when no reply can be on its way,
        // and before the next request (the poll is held until `saved`).
        if self.config.save_due() && self.bridge.quiet(now) {
            return Action::Save;
        }
        if let Some(req) = self.improv(now) {
            return Action::Wifi(req);
        }
        let mut wake = Instant::MAX;
        if let (Can::Idle(_), Some(inverter)) = (self.can, self.inverter.as_mut()) {
            match inverter.poll(now) {
                InverterAction::Send(f) => {
                    self.can = Can::Busy;
                    self.note_limits(now);
                    return Action::Can(f);
                }
                InverterAction::Recover => {
                    self.can = Can::Busy;
                    return Action::CanRecover;
                }
                InverterAction::WaitUntil(t) => {
                    self.can = Can::Idle(t);
                    self.note_limits(now);
                    wake = t;
                }
            }
        }
        match self.bridge.step(now) {
            Step::Transmit => {
                if let Some(item) = self.next_logged(now) {
                    self.transmit_pending = true;
                    return Action::Log(item);
                }
                self.transmit()
            }
            Step::WaitUntil(t) => {
                if self.bridge.quiet(now) {
                    if let Some(item) = self.next_logged(now) {
                        return Action::Log(item);
                    }
                    // An update's flash work only in a gap the BMS poll and
                    // the CAN output leave long enough for it; a restart
                    // into an installed update.
                    if let Some(a) = self.ota_action(now, t.min(wake)) {
                        return a;
                    }
                    // The history's writes in the same kind of gap.
                    if let Some(a) = self.history_action(now, t.min(wake)) {
                        return a;
                    }
                }
                if let Some(h) = self.host.as_mut() {
                    wake = wake.min(h.poll(now, &self.bridge));
                    wake = wake.min(h.improv().wake(now));
                }
                if self.node() != 0 {
                    wake = wake.min(self.next_view);
                }
                wake = wake.min(self.ota_wake(now));
                wake = wake.min(self.history_wake(now));
                Action::WaitUntil(t.min(wake))
            }
        }
    }

    /// Improv Wi-Fi's work: a step of a key derivation, a request for the
    /// Wi-Fi side, a network joined into the record.
    fn improv(&mut self, now: Instant) -> Option<WifiRequest> {
        let h = self.host.as_mut()?;
        let req = h.improv_mut().poll(now);
        if let Some((ssid, key)) = h.improv_mut().take_joined() {
            self.watch.who = Some(crate::history::event::Who::WifiSetup);
            if self.config.joined_network(&ssid, &key) {
                self.apply_running(now);
            }
        }
        req
    }

    fn transmit(&mut self) -> Action {
        if let Some(h) = self.host.as_mut() {
            if h.capturing() {
                h.on_uart_tx(self.bridge.transmit_bytes());
            }
        }
        Action::Transmit
    }

    /// The next thing to log, with what it means for the others.
    fn next_logged(&mut self, now: Instant) -> Option<Logged> {
        let item = if let Some(r) = self.bridge.next_report() {
            if let Some(h) = self.host.as_mut() {
                h.on_report(&r);
            }
            if let Report::NewEvent(e) = &r {
                if let Some(i) = self.inverter.as_mut() {
                    i.on_event(e);
                }
                if self.events.is_full() {
                    self.events.pop_front();
                    self.events_dropped = self.events_dropped.wrapping_add(1);
                }
                let _ = self.events.push_back(*e);
                self.generation = self.generation.wrapping_add(1);
            }
            Logged::Bridge(r)
        } else if let Some(n) = self.config.next_note() {
            Logged::Config(n)
        } else if let Some(r) = self.inverter.as_mut().and_then(|i| i.next_report()) {
            Logged::Inverter(r)
        } else if self.missed_to_log > 0 {
            Logged::HostMissed(core::mem::take(&mut self.missed_to_log))
        } else if let Some(n) = self.host.as_mut().and_then(|h| h.improv_mut().next_note()) {
            Logged::Improv(n)
        } else if let Some(r) = self.radio_to_log.take() {
            Logged::Radio(r)
        } else {
            self.next_update_note()?
        };
        self.record_logged(now, &item);
        if self.host.is_some() {
            let mut line = Line::new();
            self.log_text(&item, &mut line);
            if let Some(h) = self.host.as_mut() {
                h.log(item.level(), line.as_str());
            }
        }
        Some(item)
    }

    /// A new snapshot goes to the inverter output (with the settings charge
    /// control uses and the version), and changes what MQTT reads.
    fn feed_inverter(&mut self) {
        let t = self.bridge.telemetry();
        let online = t.online && t.ready;
        if online != self.last_online {
            self.last_online = online;
            self.generation = self.generation.wrapping_add(1);
        }
        if t.snapshot_seq == self.fed_seq {
            return;
        }
        self.fed_seq = t.snapshot_seq;
        self.generation = self.generation.wrapping_add(1);
        if let (Some(s), Some(at)) = (&t.snapshot, t.snapshot_at) {
            let valid = t.live.flagged.is_none();
            self.energy
                .on_snapshot(at, s.pack_voltage_v, s.pack_current_a, valid);
            let settings = t.settings.as_ref().and_then(PackSettings::from_registers);
            if let Some(i) = self.inverter.as_mut() {
                i.on_snapshot(at, s, settings, t.version.as_ref());
            }
            let stage = self.inverter.as_ref().and_then(|i| i.stage());
            Self::days_snapshot(
                &mut self.days,
                at,
                s,
                valid,
                settings.as_ref(),
                stage.as_ref(),
                t.statistics.as_ref(),
            );
        }
    }

    /// The limits the inverter is told changed: MQTT shows them.
    fn note_limits(&mut self, now: Instant) {
        let l = self.inverter.as_ref().and_then(|i| i.limits_sent(now));
        if l != self.last_limits {
            self.last_limits = l;
            self.generation = self.generation.wrapping_add(1);
            self.record_limits(now);
        }
    }

    /// The running configuration changed: the host link and the inverter
    /// output follow it at once.
    fn apply_running(&mut self, now: Instant) {
        if let Some(c) = self.config.take_running_change() {
            if let Some(h) = self.host.as_mut() {
                h.apply_config(now, c);
            }
            if let Some(i) = self.inverter.as_mut() {
                i.reconfigure(c.inverter());
            }
            self.ota.set_owner_key(c.update_key());
            self.refresh_update_view();
        }
    }

    /// Several packs: the battery to the host link and MQTT once a period.
    fn tick_battery(&mut self, now: Instant) {
        if self.node() == 0 || now < self.next_view {
            return;
        }
        self.next_view = now.saturating_add(BATTERY_VIEW_PERIOD_US);
        let v = self.inverter.as_ref().and_then(|i| i.battery_view(now));
        if let Some(h) = self.host.as_mut() {
            h.on_battery(v.clone());
        }
        if v != self.battery {
            self.battery = v;
            self.generation = self.generation.wrapping_add(1);
        }
    }

    /// Queues the start-up profile.
    #[allow(clippy::result_large_err)] // the command itself is handed back
    pub fn submit_profile(
        &mut self,
        profile: &[(protocol_core::settings::SettingId, i32)],
    ) -> Result<(), Command> {
        self.bridge.submit_profile(profile)
    }
}
