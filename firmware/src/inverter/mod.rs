//! The inverter output: the BMS's telemetry and settings in, CAN frames out,
//! sans-IO like the bridge. The chip shell moves frames between this and the
//! TWAI controller; the host runs it against a simulated pack and inverter.
//!
//! * [`control`] — the charge limits and alarms (the part that protects cells).
//! * [`frames`] — the Victron and SMA Sunny Island frame layouts; [`pylon`]
//!   — the Pylontech LV family's (Pylon, Sol-Ark, Luxpower) and what such
//!   inverters obey when charging or discharging must stop; [`growatt`] —
//!   Growatt's, sent only when asked; [`protocol`] — which frames each
//!   protocol sends.
//! * [`bus`] — the CAN port's health (no ACK, bus-off, the inverter heard).
//! * [`stale`] — a stale episode, its hold and a policy given meanwhile.
//! * [`membership`] and [`packs`] — several packs on one bus: this bridge's
//!   part, and the wire and rules they share.
//! * [`port`] — the controller's side, as the chip's CAN task pumps it.
//!
//! Inputs: [`Inverter::on_snapshot`] (each published snapshot, with the
//! settings), [`Inverter::on_event`] (BMS events), [`Inverter::on_received`]
//! (frames from the bus), [`Inverter::on_tx`] / [`Inverter::on_bus_off`] (what the
//! controller reports). Output: [`Inverter::poll`] says "send this frame now",
//! "recover the bus now" or "wake me at T", and [`Inverter::next_report`] says
//! what to log.
//!
//! **Stale data is never sent as fresh.** When the newest snapshot is older than
//! [`InverterConfig::freshness`] allows, the configured [`StaleMode`] applies.
//! The default, [`StaleMode::Hold`], keeps the inverter running on the
//! battery for a bounded time (`stale_hold`, 120 s): CCL 0, DCL and CVL as
//! last computed, the alarm frame saying "BMS link lost", no measurement
//! frames; then it stops too. A short loss of the BMS's data (a loose UART
//! wire, a BMS restart) then never switches an island inverter off, while the
//! BMS's own cutoffs still protect the pack and nothing charges it.
//! [`StaleMode::Stop`] sends nothing more to a Victron GX: it stops charging
//! and discharging 3 s after the last 0x351 (what Victron's own devices do on
//! a lost battery). A Sunny Island would keep obeying the last 0x351 until
//! 0x355 has been missing for 60 s, so with `stop` it gets 0x351 with CCL 0
//! and DCL 0 (and no measurement frames: standby after 60 s). When the data
//! is back, nothing waits a hold: DCL is what the data says at once, CCL
//! ramps from 0 ([`control::ChargeControl::resume`]).

pub mod bus;
pub mod control;
pub mod frames;
pub mod growatt;
pub mod membership;
pub mod packs;
pub mod port;
pub mod protocol;
pub mod pylon;
pub mod stale;

use heapless::Deque;
use protocol_core::events::{Event, EventId};
use protocol_core::views::{LiveSnapshot, VersionInfo};

use self::bus::BusHealth;
use self::control::{ChargeConfig, ChargeControl, Conditions, Limits, PackSettings, PackState};
use self::frames::CanFrame;
use self::membership::Membership;
use self::packs::{Battery, BatteryView, Packs, Shares, Summary};
use self::pylon::{Extras, Stops};
use self::stale::StaleEpisode;
use crate::Instant;

pub use self::protocol::Protocol;
pub use crate::freshness::{Freshness, StaleMode};

/// Inverter output settings; [`Default`] gives the documented defaults.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct InverterConfig {
    /// CAN output on at all.
    pub enabled: bool,
    /// Protocol.
    pub protocol: Protocol,
    /// Charge control.
    pub charge: ChargeConfig,
    /// When telemetry is stale (the one rule; default 5 s: 20 live periods).
    pub freshness: Freshness,
    /// What to do then.
    pub stale_policy: StaleMode,
    /// With [`StaleMode::Hold`]: how long, µs (default 120 s).
    pub stale_hold_us: Instant,
    /// Period of 0x351, 0x355, 0x356, 0x35A, µs (1 s).
    pub fast_period_us: Instant,
    /// Period of the other frames, µs (5 s).
    pub slow_period_us: Instant,
    /// The GX counts as lost after this long without its keep-alive, µs.
    pub inverter_timeout_us: Instant,
    /// Pause after a bus-off before the controller is recovered, µs (doubles
    /// up to 16 × on repeated bus-offs).
    pub bus_off_backoff_us: Instant,
    /// Node number among bridges of packs in parallel on one bus (1..=8, see
    /// [`packs`]); 0 = this bridge's pack is the whole battery.
    pub node: u8,
    /// The Pylontech family's 0x35E (`inverter_name`), padded with spaces.
    pub name: [u8; 8],
    /// The Pylontech family: report SOC 100 % (0 %) while charging
    /// (discharging) must stop (`stop_by_soc`), for an inverter that ignores
    /// a current limit of 0 A.
    pub stop_by_soc: bool,
}

impl Default for InverterConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            protocol: Protocol::Victron,
            charge: ChargeConfig::default(),
            freshness: Freshness::default(),
            stale_policy: StaleMode::Hold,
            stale_hold_us: 120 * crate::SECOND,
            fast_period_us: crate::SECOND,
            slow_period_us: 5 * crate::SECOND,
            inverter_timeout_us: 5 * crate::SECOND,
            bus_off_backoff_us: crate::SECOND,
            node: 0,
            name: pylon::DEFAULT_NAME,
            stop_by_soc: false,
        }
    }
}

/// What the shell must do next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InverterAction {
    /// Transmit this frame now; report the result with [`Inverter::on_tx`].
    Send(CanFrame),
    /// Start the controller's bus-off recovery now.
    Recover,
    /// Nothing until this time (or until something is reported).
    WaitUntil(Instant),
}

/// Result of one transmission.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TxResult {
    /// Sent (acknowledged by another node).
    Sent,
    /// Not acknowledged / error: the controller counts it (error-passive when no
    /// other node is on the bus).
    Failed,
}

/// The CAN output as an owner sees it (Home Assistant's diagnostics).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CanState {
    /// The output is off in the configuration.
    Off,
    /// Nothing sent yet (no data, or not every pack heard).
    Waiting,
    /// Frames go out and are acknowledged.
    Running,
    /// Frames go out and nobody acknowledges them (no other node, wiring).
    NoAck,
    /// The controller is off the bus until its recovery.
    BusOff,
}

impl CanState {
    /// As the MQTT state writes it.
    pub const fn key(self) -> &'static str {
        match self {
            Self::Off => "off",
            Self::Waiting => "waiting",
            Self::Running => "running",
            Self::NoAck => "no_ack",
            Self::BusOff => "bus_off",
        }
    }
}

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
        /// With [`StaleMode::Hold`], for how long, µs.
        stale_hold_us: Instant,
    },
    /// Hold-charge-zero time is up: sending stopped.
    StaleHoldEnded,
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
    /// No pack takes part: the speaker sends nothing (Victron) or stops the
    /// inverter (SMA: CCL 0, DCL 0).
    BatteryLost,
    /// The Pylontech family: what must stop now and why — said every way
    /// such inverters obey (logged when it changes).
    Protection(Stops),
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
            Self::InverterSeen
            | Self::Fresh
            | Self::BusOk
            | Self::Limits(_)
            | Self::BatteryLimits(_)
            | Self::Speaker(_)
            | Self::Packs { .. } => crate::Level::Info,
            Self::BatteryLost
            | Self::DuplicateNode(_)
            | Self::SummaryRefused(..)
            | Self::Protection(_)
            | Self::ShutdownAsked(_) => crate::Level::Warn,
            Self::InverterLost
            | Self::Stale { .. }
            | Self::StaleHoldEnded
            | Self::NoAck { .. }
            | Self::BusOff { .. } => crate::Level::Warn,
        }
    }
}

/// A charge block whose recovery event never arrived ends after the BMS has
/// been out of "fault" this long, µs.
pub const CHARGE_BLOCK_TIMEOUT_US: Instant = 5 * 60 * crate::SECOND;

/// Longest one frame's transmission may take before it counts as failed
/// ([`TxResult::Failed`]): a frame takes about 0.25 ms at 500 kbit/s, so
/// this is only met when nobody acknowledges (the controller retries) or the
/// bus is jammed. The CAN task goes by it, and by the two below.
pub const CAN_TX_TIMEOUT_US: Instant = 100 * crate::MS;
/// After [`InverterAction::Recover`], how long the controller is given to
/// come back on the bus before the recovery counts as failed.
pub const BUS_RECOVERY_WAIT_US: Instant = 500 * crate::MS;
/// How often, meanwhile, it is asked whether it is back.
pub const BUS_RECOVERY_POLL_US: Instant = 10 * crate::MS;

/// While the current limits only rise on their way to their targets (a ramp),
/// they are logged at most this often; a limit that falls, and the end of a
/// ramp, are logged at once.
pub const LIMITS_LOG_PERIOD_US: Instant = 10 * crate::SECOND;

/// Whether limits that differ from the ones last logged (at `at`) are logged
/// now: always when one fell or the ramp reached its `targets` (CCL, DCL);
/// on the way up, once a [`LIMITS_LOG_PERIOD_US`].
fn limits_log_due(
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

/// Frames in one burst at most (a summary and a slow period of the battery's).
const QUEUE: usize = 16;

/// A Luxpower inverter's shutdown request holds this long after its last
/// 0x300, µs.
pub const SHUTDOWN_HOLD_US: Instant = 10 * crate::SECOND;

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

/// The inverter output. See the module documentation.
#[derive(Debug, Clone)]
pub struct Inverter {
    config: InverterConfig,
    control: ChargeControl,
    settings: Option<PackSettings>,
    state: Option<(PackState, Instant)>,
    firmware: u16,
    hardware: u16,
    limits: Option<Limits>,
    logged_limits: Option<Limits>,
    /// When they were logged.
    limits_logged_at: Instant,
    conditions: Conditions,
    charge_blocked: Option<EventId>,
    fault_clear_since: Option<Instant>,
    queue: Deque<CanFrame, QUEUE>,
    next_fast: Instant,
    next_slow: Instant,
    stale: StaleEpisode,
    bus: BusHealth,
    reports: Reports,
    membership: Membership,
    /// The last 0x351 handed out, and when.
    told: Option<(Limits, Instant)>,
    /// The Pylontech family: what must stop, as last reported.
    stops: Stops,
    /// When SOC was last at least 97 % (or the data first came): the
    /// full-charge request's 30 days run from it.
    full_at: Option<Instant>,
    /// The last shutdown request of a Luxpower inverter.
    shutdown_at: Option<Instant>,
    /// Growatt: the frames of the last period, for the next query, and when
    /// they were made.
    answer: heapless::Vec<CanFrame, 8>,
    answer_at: Option<Instant>,
}

impl Inverter {
    /// An inverter output at `now`, with nothing to send until the first
    /// snapshot with settings.
    pub fn new(config: InverterConfig, now: Instant) -> Self {
        Self {
            config,
            control: ChargeControl::new(config.charge),
            settings: None,
            state: None,
            firmware: 0,
            hardware: 0,
            limits: None,
            logged_limits: None,
            limits_logged_at: 0,
            conditions: Conditions::default(),
            charge_blocked: None,
            fault_clear_since: None,
            queue: Deque::new(),
            next_fast: now,
            next_slow: now,
            stale: StaleEpisode::default(),
            bus: BusHealth::default(),
            reports: Reports::default(),
            membership: Membership::new(config.node, now),
            told: None,
            stops: Stops::default(),
            full_at: None,
            shutdown_at: None,
            answer: heapless::Vec::new(),
            answer_at: None,
        }
    }

    /// The node number it runs with (0 = alone).
    pub fn node(&self) -> u8 {
        self.membership.node()
    }

    /// Several packs: the battery last computed and the limits sent for it
    /// (computed by every node, sent by the speaker only).
    pub fn battery(&self) -> Option<&(Battery, Limits)> {
        self.membership.battery()
    }

    /// Several packs: this bridge speaks to the inverter.
    pub fn speaking(&self) -> bool {
        self.membership.speaking()
    }

    /// Several packs: what was heard of the other nodes.
    pub fn packs(&self) -> &Packs {
        self.membership.packs()
    }

    /// Several packs: the battery and every pack as this bridge sees them at
    /// `now`; `None` for a bridge alone (node 0).
    pub fn battery_view(&self, now: Instant) -> Option<BatteryView> {
        self.membership.view(now, self.config.freshness)
    }

    /// The configuration changed while running (a `set_config` of fields that
    /// apply at once): charge control's settings and the stale age apply from
    /// the next snapshot on — a limit that falls falls at once, one that rises
    /// ramps as after any cut. A new stale policy given while the data is
    /// stale applies from the next stale episode (switching policy in the middle
    /// of one could re-allow a discharge the inverter has already stopped). The
    /// output on/off and the protocol are what the task was started with: they
    /// change at the next restart only.
    pub fn reconfigure(&mut self, new: InverterConfig) {
        let mut c = new;
        c.enabled = self.config.enabled;
        c.protocol = self.config.protocol;
        c.node = self.config.node;
        let policy = |c: &InverterConfig| (c.stale_policy, c.stale_hold_us);
        (c.stale_policy, c.stale_hold_us) =
            self.stale.reconfigure(policy(&self.config), policy(&c));
        self.control.set_config(c.charge);
        self.config = c;
    }

    /// The configuration it runs with.
    pub fn config(&self) -> &InverterConfig {
        &self.config
    }

    /// The limits last computed.
    pub fn limits(&self) -> Option<Limits> {
        self.limits
    }

    /// What the inverter is told at `now`: the limits of the last 0x351 this
    /// output sent, while it sends them (one came within two fast periods) —
    /// this pack's limits for a bridge alone, the battery's while this bridge
    /// speaks for several packs; `None` when nothing is sent (output off, stale
    /// data with "stop", a bridge of several packs that does not speak).
    pub fn limits_sent(&self, now: Instant) -> Option<Limits> {
        let (l, at) = self.told?;
        (now.saturating_sub(at) <= 2 * self.config.fast_period_us).then_some(l)
    }

    /// Alarms and warnings last computed.
    pub fn conditions(&self) -> Conditions {
        self.conditions
    }

    /// The Pylontech family: what must stop now and why, as the inverter is
    /// told (`None` for another protocol or with the output off).
    pub fn protection(&self) -> Option<Stops> {
        (self.config.enabled && self.config.protocol.low_voltage_family()).then_some(self.stops)
    }

    /// Absorption or float.
    pub fn phase(&self) -> control::Phase {
        self.control.phase()
    }

    /// Frames transmitted successfully.
    pub fn frames_sent(&self) -> u32 {
        self.bus.frames_sent()
    }

    /// The next report to log.
    pub fn next_report(&mut self) -> Option<InverterReport> {
        self.reports.pop()
    }

    /// A published snapshot, decoded at `taken_at`, with the BMS settings
    /// (see [`PackSettings::from_registers`]) and the version when known.
    pub fn on_snapshot(
        &mut self,
        taken_at: Instant,
        snapshot: &LiveSnapshot,
        settings: Option<PackSettings>,
        version: Option<&VersionInfo>,
    ) {
        if let Some(s) = settings {
            self.settings = Some(s);
        }
        let mut p = PackState::from_snapshot(snapshot);
        // A charge block ends with its own recovery event (see `on_event`); if
        // that event never reaches us, after the BMS has been out of "fault" for
        // CHARGE_BLOCK_TIMEOUT_US.
        if p.fault {
            self.fault_clear_since = None;
        } else if self.charge_blocked.is_some() {
            let since = *self.fault_clear_since.get_or_insert(taken_at);
            if taken_at.saturating_sub(since) >= CHARGE_BLOCK_TIMEOUT_US {
                self.charge_blocked = None;
            }
        }
        p.charge_blocked = self.charge_blocked.is_some();
        self.state = Some((p, taken_at));
        if let Some(v) = version {
            self.firmware = u16::from(v.firmware_public);
            self.hardware = u16::from_le_bytes([v.hardware, v.hardware_changes]);
        }
    }

    /// A BMS event: charge-side fault events block charging until the BMS
    /// reports the matching recovery (or, failing that, see
    /// [`CHARGE_BLOCK_TIMEOUT_US`]).
    pub fn on_event(&mut self, e: &Event) {
        let recovers = |blocked: EventId| match blocked {
            EventId::OverVoltageCutoff => EventId::RecoveredOverVoltage,
            EventId::ChargingOverCurrentCutoff => EventId::RecoveredChargingOverCurrent,
            EventId::LowTemperatureCutoff => EventId::RecoveredLowTemperatureFault,
            _ => EventId::RecoveredRegenerationOverCurrent,
        };
        match e.id {
            EventId::OverVoltageCutoff
            | EventId::ChargingOverCurrentCutoff
            | EventId::LowTemperatureCutoff
            | EventId::RegenerationOverCurrentCutoff => {
                self.charge_blocked = Some(e.id);
                self.fault_clear_since = None;
            }
            id if self.charge_blocked.map(recovers) == Some(id) => self.charge_blocked = None,
            _ => {}
        }
    }

    /// A frame from the bus (the inverter's heartbeat or query, a Luxpower
    /// inverter's shutdown request, other packs' summaries).
    pub fn on_received(&mut self, now: Instant, id: u16, data: &[u8]) {
        if !self.config.enabled {
            return; // output off: the bus is none of our business
        }
        self.membership.on_frame(now, id, data, &mut self.reports);
        let protocol = self.config.protocol;
        if protocol.heartbeat(id) {
            self.bus.keepalive(now, &mut self.reports);
        }
        if protocol.answers_only() && growatt::is_query(id) {
            self.answer_query(now);
        }
        if protocol == Protocol::Luxpower && pylon::shutdown_asked(id, data) {
            if self.shutdown_at.is_none() {
                self.reports.push(InverterReport::ShutdownAsked(true));
            }
            self.shutdown_at = Some(now);
        }
    }

    /// Growatt's query: the frames of the last period, when they are recent
    /// (two periods); nothing otherwise (no data yet, or stale with "stop").
    fn answer_query(&mut self, now: Instant) {
        let fresh = self
            .answer_at
            .is_some_and(|t| now.saturating_sub(t) <= 2 * self.config.fast_period_us);
        if fresh {
            for f in self.answer.iter() {
                let _ = self.queue.push_back(*f);
            }
        }
    }

    /// The Pylontech family's extras at `now` for these limits: what must
    /// stop (reported when it changes), the name, the full-charge request.
    fn extras(
        &mut self,
        now: Instant,
        limits: &Limits,
        state: Option<&PackState>,
        c: &Conditions,
    ) -> Extras {
        if self
            .shutdown_at
            .is_some_and(|t| now.saturating_sub(t) > SHUTDOWN_HOLD_US)
        {
            self.shutdown_at = None;
            self.reports.push(InverterReport::ShutdownAsked(false));
        }
        let stops = if self.shutdown_at.is_some() {
            Stops::shutdown()
        } else {
            match state {
                Some(s) => Stops::of(limits, s, c),
                None => Stops {
                    charge: Some(pylon::StopWhy::LinkLost),
                    discharge: (limits.dcl_da == 0).then_some(pylon::StopWhy::LinkLost),
                },
            }
        };
        if self.config.protocol.low_voltage_family() && stops != self.stops {
            self.stops = stops;
            self.reports.push(InverterReport::Protection(stops));
        }
        if let Some(s) = state {
            if s.soc_pct >= pylon::FULL_SOC_PCT || self.full_at.is_none() {
                self.full_at = Some(now);
            }
        }
        let full_charge = self
            .full_at
            .is_some_and(|t| now.saturating_sub(t) >= pylon::FULL_CHARGE_AFTER_US);
        Extras {
            name: self.config.name,
            stops,
            by_soc: self.config.stop_by_soc,
            full_charge,
        }
    }

    /// No answer to the next query (this bridge no longer speaks for the
    /// battery, or has no battery).
    fn forget_answer(&mut self) {
        self.answer.clear();
        self.answer_at = None;
    }

    /// Queues `frames` to be sent now, or — for a protocol that answers
    /// only — keeps them for the next query.
    fn queue_frames(&mut self, now: Instant, frames: &[CanFrame]) {
        if self.config.protocol.answers_only() {
            self.answer.clear();
            for f in frames {
                let _ = self.answer.push(*f);
            }
            self.answer_at = Some(now);
        } else {
            for f in frames {
                let _ = self.queue.push_back(*f);
            }
        }
    }

    /// The CAN output's state now.
    pub fn can_state(&self) -> CanState {
        if !self.config.enabled {
            CanState::Off
        } else {
            self.bus.state()
        }
    }

    /// The inverter's keep-alive is heard (within its timeout).
    pub fn inverter_heard(&self) -> bool {
        self.bus.inverter_heard()
    }

    /// Result of the last [`InverterAction::Send`].
    pub fn on_tx(&mut self, _now: Instant, result: TxResult) {
        if !self.bus.on_tx(result, &mut self.reports) {
            // Whatever was queued is not retried: the next period sends
            // fresh values (never stale ones late).
            self.queue.clear();
        }
    }

    /// The controller went bus-off.
    pub fn on_bus_off(&mut self, now: Instant) {
        // With a node number: not the speaker while off the bus, and no battery
        // shown as current meanwhile; it listens again after the recovery.
        self.membership.on_bus_off(now, &mut self.reports);
        self.queue.clear();
        self.bus
            .on_bus_off(now, self.config.bus_off_backoff_us, &mut self.reports);
    }

    /// What to do now.
    pub fn poll(&mut self, now: Instant) -> InverterAction {
        if !self.config.enabled {
            return InverterAction::WaitUntil(Instant::MAX);
        }
        let timeout = self.config.inverter_timeout_us;
        self.bus.check_keepalive(now, timeout, &mut self.reports);
        if let Some(t) = self.bus.off_until(now) {
            return InverterAction::WaitUntil(t);
        }
        if self.bus.recovery_due(now) {
            if self.membership.node() == 0 {
                // The inverter saw no limits meanwhile: they ramp back.
                self.control.cut(now);
            }
            // With a node number: listen again before speaking; the battery's
            // limits come back after the hold.
            self.membership.on_recovery(now);
            return InverterAction::Recover;
        }
        if let Some(f) = self.queue.pop_front() {
            return self.send(now, f);
        }
        if now >= self.next_fast {
            self.next_fast = now.saturating_add(self.config.fast_period_us);
            let slow = now >= self.next_slow;
            if slow {
                self.next_slow = now.saturating_add(self.config.slow_period_us);
            }
            self.fill(now, slow);
            if let Some(f) = self.queue.pop_front() {
                return self.send(now, f);
            }
        }
        let mut wake = self.next_fast;
        if let Some(t) = self.bus.keepalive_deadline(timeout) {
            wake = wake.min(t);
        }
        InverterAction::WaitUntil(wake.max(now.saturating_add(1)))
    }

    fn send(&mut self, now: Instant, f: CanFrame) -> InverterAction {
        if let Some(l) = self.config.protocol.limits_of(&f) {
            self.told = Some((l, now));
        }
        InverterAction::Send(f)
    }

    /// Computes the limits and queues this period's frames.
    fn fill(&mut self, now: Instant, slow: bool) {
        if self.membership.node() != 0 {
            self.fill_member(now, slow);
            return;
        }
        let (Some(settings), Some((state, taken_at))) = (self.settings, self.state) else {
            return; // nothing the BMS said yet: nothing to send
        };
        let age = now.saturating_sub(taken_at);
        if !self.config.freshness.young(Some(age)) {
            self.fill_stale(now, age);
            return;
        }
        if self.stale.ends() {
            // The inverter stopped (or ran without charge): the loss was no
            // cause the battery gave — DCL at once, CCL ramps from 0 without
            // the hold (ChargeControl::resume).
            self.control.resume();
            if let Some((p, hold)) = self.stale.resume() {
                self.config.stale_policy = p;
                self.config.stale_hold_us = hold;
            }
            self.reports.push(InverterReport::Fresh);
        }
        let (limits, conditions) = self.update_own(now, &settings, &state);
        let capacity_ah = settings.capacity_cah / 100;
        let modules = (
            1,
            u16::from(limits.ccl_da == 0),
            u16::from(limits.dcl_da == 0),
            0,
        );
        self.push_inverter_frames(
            now,
            &limits,
            &state,
            &conditions,
            capacity_ah,
            modules,
            slow,
        );
    }

    /// A bridge alone whose newest data is `age` old, stale: what its
    /// policy sends.
    fn fill_stale(&mut self, now: Instant, age: Instant) {
        let since = self.stale.stale_at(now);
        if since == now {
            self.report_stale(age);
        }
        match self.config.stale_policy {
            // A Sunny Island keeps obeying the last 0x351 until 0x355 has been
            // missing for 60 s: tell it to stop at once (CCL 0, DCL 0, no
            // measurement frames, so it goes to standby after 60 s as well).
            StaleMode::Stop if self.config.protocol.obeys_last_limits() => {
                self.queue_stale(now, true);
            }
            StaleMode::Stop => {}
            StaleMode::Hold => {
                if now.saturating_sub(since) <= self.config.stale_hold_us {
                    self.queue_stale(now, false);
                } else if self.stale.hold_ends() {
                    self.reports.push(InverterReport::StaleHoldEnded);
                }
            }
        }
    }

    /// This pack's limits and conditions from fresh data: kept, and logged
    /// when the limits change.
    fn update_own(
        &mut self,
        now: Instant,
        settings: &PackSettings,
        state: &PackState,
    ) -> (Limits, Conditions) {
        let (limits, mut conditions) = self.control.update(now, settings, state);
        conditions.link_lost = 0;
        self.limits = Some(limits);
        self.conditions = conditions;
        if self.logged_limits != Some(limits)
            && limits_log_due(
                self.logged_limits,
                self.limits_logged_at,
                &limits,
                self.control.targets(),
                now,
            )
        {
            self.logged_limits = Some(limits);
            self.limits_logged_at = now;
            self.reports.push(InverterReport::Limits(limits));
        }
        (limits, conditions)
    }

    /// The frames of the inverter protocol for a battery in this state.
    #[allow(clippy::too_many_arguments)]
    fn push_inverter_frames(
        &mut self,
        now: Instant,
        limits: &Limits,
        state: &PackState,
        conditions: &Conditions,
        capacity_ah: u16,
        modules: (u16, u16, u16, u16),
        slow: bool,
    ) {
        let lv = self.extras(now, limits, Some(state), conditions);
        let settings = self.settings;
        let mut out: heapless::Vec<CanFrame, QUEUE> = heapless::Vec::new();
        self.config.protocol.period_frames(
            &protocol::Period {
                limits,
                state,
                conditions,
                capacity_ah,
                modules,
                firmware: self.firmware,
                hardware: self.hardware,
                slow,
                lv,
                settings: settings.as_ref(),
            },
            &mut |f| {
                let _ = out.push(f);
            },
        );
        self.queue_frames(now, &out);
    }

    /// What this bridge has learnt of how the battery's current splits.
    pub fn shares(&self) -> &Shares {
        self.membership.shares()
    }

    /// This bridge's own summary as it last sent it (with a node number).
    pub fn own_summary(&self) -> Option<Summary> {
        self.membership.own_summary()
    }

    /// Stale telemetry, `age` old: what the configured policy does about it.
    fn report_stale(&mut self, age: Instant) {
        self.reports.push(InverterReport::Stale {
            age_ms: (age / crate::MS).min(u64::from(u32::MAX)) as u32,
            policy: self.config.stale_policy,
            stale_hold_us: self.config.stale_hold_us,
        });
    }

    /// Stale: the limits frame with CCL 0 (and DCL 0 when `stop_discharge`),
    /// the rest as last computed, and the alarm frame with "link lost" flagged.
    /// No measurement frame: those would be stale values sent as fresh. Used by
    /// the hold policy (CCL 0 only) and by "stop sending" towards a Sunny
    /// Island (both 0), which would otherwise obey the last limits for 60 s.
    fn queue_stale(&mut self, now: Instant, stop_discharge: bool) {
        let Some(last) = self.limits else {
            return;
        };
        let stale = Limits {
            ccl_da: 0,
            dcl_da: if stop_discharge { 0 } else { last.dcl_da },
            ..last
        };
        if !stop_discharge {
            // The hold keeps these limits (only CCL ramps back afterwards).
            self.limits = Some(stale);
        }
        let mut c = self.conditions;
        c.link_lost = 1;
        let lv = self.extras(now, &stale, None, &c);
        let mut out: heapless::Vec<CanFrame, QUEUE> = heapless::Vec::new();
        self.config
            .protocol
            .stale_frames(&stale, &c, &lv, &mut |f| {
                let _ = out.push(f);
            });
        self.queue_frames(now, &out);
    }
}
