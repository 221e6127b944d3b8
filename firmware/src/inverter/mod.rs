//! The inverter output: the BMS's telemetry and settings in, CAN frames out,
//! sans-IO like the bridge. The chip shell moves frames between this and the
//! TWAI controller; the host runs it against a simulated pack and inverter.
//!
//! * [`control`] — the charge limits and alarms (the part that protects cells).
//! * [`frames`] — the Victron and SMA Sunny Island frame layouts.
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

pub mod control;
pub mod frames;
pub mod packs;
pub mod port;
pub mod protocol;

use heapless::Deque;
use protocol_core::events::{Event, EventId};
use protocol_core::views::{LiveSnapshot, VersionInfo};

use self::control::{ChargeConfig, ChargeControl, Conditions, Limits, PackSettings, PackState};
use self::frames::CanFrame;
use self::packs::{
    Battery, BatteryLimits, BatteryView, Election, Member, PackPart, PackView, Packs, Received,
    Shares, Summary,
};
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
        hold_us: Instant,
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
            Self::BatteryLost | Self::DuplicateNode(_) | Self::SummaryRefused(..) => {
                crate::Level::Warn
            }
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
/// Failed transmissions in a row before "no ACK" is reported (and sending slows
/// to the fast period only).
const NO_ACK_AFTER: u32 = 8;

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
    stale_since: Option<Instant>,
    hold_ended: bool,
    inverter_seen_at: Option<Instant>,
    inverter_seen: bool,
    tx_failures: u32,
    no_ack_reported: bool,
    bus_off: Option<Instant>,
    bus_offs: u32,
    frames_sent: u32,
    reports: Deque<InverterReport, 8>,
    /// A stale policy given while the data is stale: it applies from the next
    /// stale episode on (see [`Inverter::reconfigure`]).
    next_stale_policy: Option<(StaleMode, Instant)>,
    /// Several packs: what was heard, who speaks, the battery's limits.
    packs: Packs,
    election: Election,
    battery_limits: BatteryLimits,
    shares: Shares,
    battery: Option<(Battery, Limits)>,
    logged_battery: Option<Limits>,
    logged_packs: Option<(u8, u8)>,
    battery_lost: bool,
    /// The battery's limits last sent as the speaker (for the stop frames a
    /// Sunny Island needs when the battery is lost).
    sent_battery: Option<Limits>,
    duplicate_reported: bool,
    /// Nodes whose refused summary was reported (bit `node - 1`).
    refused_reported: u8,
    seq: u8,
    own_summary: Option<Summary>,
    own_closed: Option<(u16, u16)>,
    /// The last 0x351 handed out, and when.
    told: Option<(Limits, Instant)>,
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
            stale_since: None,
            hold_ended: false,
            inverter_seen_at: None,
            inverter_seen: false,
            tx_failures: 0,
            no_ack_reported: false,
            bus_off: None,
            bus_offs: 0,
            frames_sent: 0,
            reports: Deque::new(),
            next_stale_policy: None,
            packs: Packs::new(if config.node <= packs::MAX_NODES {
                config.node
            } else {
                0
            }),
            election: Election::new(now),
            battery_limits: BatteryLimits::new(),
            shares: Shares::new(),
            battery: None,
            logged_battery: None,
            logged_packs: None,
            // No battery yet is no battery lost: a bridge that just started
            // (its own data not read yet) says nothing until it had one.
            battery_lost: true,
            sent_battery: None,
            duplicate_reported: false,
            refused_reported: 0,
            seq: 0,
            own_summary: None,
            own_closed: None,
            told: None,
        }
    }

    /// The node number it runs with (0 = alone).
    pub fn node(&self) -> u8 {
        self.packs.node()
    }

    /// Several packs: the battery last computed and the limits sent for it
    /// (computed by every node, sent by the speaker only).
    pub fn battery(&self) -> Option<&(Battery, Limits)> {
        self.battery.as_ref()
    }

    /// Several packs: this bridge speaks to the inverter.
    pub fn speaking(&self) -> bool {
        self.election.speaking()
    }

    /// Several packs: what was heard of the other nodes.
    pub fn packs(&self) -> &Packs {
        &self.packs
    }

    /// Several packs: the battery and every pack as this bridge sees them at
    /// `now`; `None` for a bridge alone (node 0).
    pub fn battery_view(&self, now: Instant) -> Option<BatteryView> {
        let node = self.packs.node();
        if node == 0 {
            return None;
        }
        let freshness = self.config.freshness;
        let mut packs: heapless::Vec<PackView, { packs::MAX_NODES as usize }> =
            heapless::Vec::new();
        // By node number: the others come in order; this one goes between.
        // The data's age now (sent age plus the time since), as the line shows it.
        let view = |n: u8, m: Member| PackView {
            node: n,
            summary: Summary {
                age_ds: m
                    .data_age_us()
                    .map_or(u8::MAX, |a| (a / (100 * crate::MS)).min(255) as u8),
                ..m.summary
            },
            part: PackPart::of(&m, freshness),
        };
        let mut own = self.own_summary.map(|s| view(node, Member::now(s)));
        for (n, m) in self.packs.known(now) {
            if n > node {
                if let Some(o) = own.take() {
                    let _ = packs.push(o);
                }
            }
            let _ = packs.push(view(n, m));
        }
        if let Some(o) = own {
            let _ = packs.push(o);
        }
        Some(BatteryView {
            node,
            speaking: self.election.speaking(),
            battery: self.battery,
            packs,
        })
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
        if self.stale_since.is_some() && policy(&c) != policy(&self.config) {
            self.next_stale_policy = Some(policy(&c));
            (c.stale_policy, c.stale_hold_us) = policy(&self.config);
        } else {
            self.next_stale_policy = None;
        }
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

    /// Absorption or float.
    pub fn phase(&self) -> control::Phase {
        self.control.phase()
    }

    /// Frames transmitted successfully.
    pub fn frames_sent(&self) -> u32 {
        self.frames_sent
    }

    /// The next report to log.
    pub fn next_report(&mut self) -> Option<InverterReport> {
        self.reports.pop_front()
    }

    fn report(&mut self, r: InverterReport) {
        if self.reports.is_full() {
            let _ = self.reports.pop_front();
        }
        let _ = self.reports.push_back(r);
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

    /// A frame from the bus (the GX keep-alive).
    pub fn on_received(&mut self, now: Instant, id: u16, data: &[u8]) {
        if !self.config.enabled {
            return; // output off: the bus is none of our business
        }
        match self.packs.on_frame(now, id, data) {
            Received::DuplicateNode if !self.duplicate_reported => {
                self.duplicate_reported = true;
                let n = self.packs.node();
                self.report(InverterReport::DuplicateNode(n));
            }
            Received::Refused(node, e) => {
                let bit = 1u8 << (node.saturating_sub(1) & 7);
                if self.refused_reported & bit == 0 {
                    self.refused_reported |= bit;
                    self.report(InverterReport::SummaryRefused(node, e));
                }
            }
            Received::Complete(node) => {
                self.refused_reported &= !(1u8 << (node.saturating_sub(1) & 7));
            }
            _ => {}
        }
        if id == frames::ID_GX_KEEPALIVE || id == frames::ID_GX_KEEPALIVE_2 {
            self.inverter_seen_at = Some(now);
            if !self.inverter_seen {
                self.inverter_seen = true;
                self.report(InverterReport::InverterSeen);
            }
        }
    }

    /// The CAN output's state now.
    pub fn can_state(&self) -> CanState {
        if !self.config.enabled {
            CanState::Off
        } else if self.bus_off.is_some() {
            CanState::BusOff
        } else if self.no_ack_reported {
            CanState::NoAck
        } else if self.frames_sent > 0 {
            CanState::Running
        } else {
            CanState::Waiting
        }
    }

    /// The inverter's keep-alive is heard (within its timeout).
    pub fn inverter_heard(&self) -> bool {
        self.inverter_seen
    }

    /// Result of the last [`InverterAction::Send`].
    pub fn on_tx(&mut self, _now: Instant, result: TxResult) {
        match result {
            TxResult::Sent => {
                self.frames_sent = self.frames_sent.wrapping_add(1);
                if self.no_ack_reported {
                    self.report(InverterReport::BusOk);
                }
                self.tx_failures = 0;
                self.no_ack_reported = false;
            }
            TxResult::Failed => {
                self.tx_failures = self.tx_failures.saturating_add(1);
                if self.tx_failures >= NO_ACK_AFTER && !self.no_ack_reported {
                    self.no_ack_reported = true;
                    let failures = self.tx_failures;
                    self.report(InverterReport::NoAck { failures });
                }
                // Whatever was queued is not retried: the next period sends
                // fresh values (never stale ones late).
                self.queue.clear();
            }
        }
    }

    /// The controller went bus-off.
    pub fn on_bus_off(&mut self, now: Instant) {
        // With a node number: not the speaker while off the bus, and no battery
        // shown as current meanwhile; it listens again after the recovery.
        if self.election.speaking() {
            self.report(InverterReport::Speaker(false));
        }
        self.election.restart(now);
        self.battery = None;
        self.bus_offs = self.bus_offs.saturating_add(1);
        let shift = self.bus_offs.saturating_sub(1).min(4);
        let backoff = self.config.bus_off_backoff_us.saturating_mul(1 << shift);
        self.bus_off = Some(now.saturating_add(backoff));
        self.queue.clear();
        let count = self.bus_offs;
        self.report(InverterReport::BusOff {
            count,
            backoff_ms: (backoff / crate::MS).min(u64::from(u32::MAX)) as u32,
        });
    }

    /// What to do now.
    pub fn poll(&mut self, now: Instant) -> InverterAction {
        if !self.config.enabled {
            return InverterAction::WaitUntil(Instant::MAX);
        }
        self.check_inverter(now);
        if let Some(t) = self.bus_off {
            if now < t {
                return InverterAction::WaitUntil(t);
            }
            self.bus_off = None;
            if self.packs.node() == 0 {
                // The inverter saw no limits meanwhile: they ramp back.
                self.control.cut(now);
            }
            // With a node number: listen again before speaking; the battery's
            // limits come back after the hold.
            self.election.restart(now);
            self.battery_limits.cut(now);
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
        if let Some(t) = self.inverter_seen_at {
            if self.inverter_seen {
                wake = wake.min(t.saturating_add(self.config.inverter_timeout_us));
            }
        }
        InverterAction::WaitUntil(wake.max(now.saturating_add(1)))
    }

    fn send(&mut self, now: Instant, f: CanFrame) -> InverterAction {
        if let Some(l) = frames::limits_of(&f) {
            self.told = Some((l, now));
        }
        InverterAction::Send(f)
    }

    fn check_inverter(&mut self, now: Instant) {
        if let Some(t) = self.inverter_seen_at {
            if self.inverter_seen && now.saturating_sub(t) >= self.config.inverter_timeout_us {
                self.inverter_seen = false;
                self.report(InverterReport::InverterLost);
            }
        }
    }

    /// Computes the limits and queues this period's frames.
    fn fill(&mut self, now: Instant, slow: bool) {
        if self.packs.node() != 0 {
            self.fill_member(now, slow);
            return;
        }
        let (Some(settings), Some((state, taken_at))) = (self.settings, self.state) else {
            return; // nothing the BMS said yet: nothing to send
        };
        let age = now.saturating_sub(taken_at);
        let stale = !self.config.freshness.young(Some(age));
        if stale {
            let since = *self.stale_since.get_or_insert(now);
            if since == now {
                self.report_stale(age);
            }
            match self.config.stale_policy {
                // A Sunny Island keeps obeying the last 0x351 until 0x355 has been
                // missing for 60 s: tell it to stop at once (CCL 0, DCL 0, no
                // measurement frames, so it goes to standby after 60 s as well).
                StaleMode::Stop if self.config.protocol.obeys_last_limits() => {
                    self.queue_stale(true);
                }
                StaleMode::Stop => {}
                StaleMode::Hold => {
                    if now.saturating_sub(since) <= self.config.stale_hold_us {
                        self.queue_stale(false);
                    } else if !self.hold_ended {
                        self.hold_ended = true;
                        self.report(InverterReport::StaleHoldEnded);
                    }
                }
            }
            return;
        }
        if self.stale_since.take().is_some() {
            // The inverter stopped (or ran without charge): the loss was no
            // cause the battery gave — DCL at once, CCL ramps from 0 without
            // the hold (ChargeControl::resume).
            self.control.resume();
            self.hold_ended = false;
            if let Some((p, hold)) = self.next_stale_policy.take() {
                self.config.stale_policy = p;
                self.config.stale_hold_us = hold;
            }
            self.report(InverterReport::Fresh);
        }
        let (limits, conditions) = self.update_own(now, &settings, &state);
        let capacity_ah = settings.capacity_cah / 100;
        let modules = (
            1,
            u16::from(limits.ccl_da == 0),
            u16::from(limits.dcl_da == 0),
            0,
        );
        self.push_inverter_frames(&limits, &state, &conditions, capacity_ah, modules, slow);
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
            self.report(InverterReport::Limits(limits));
        }
        (limits, conditions)
    }

    /// The frames of the inverter protocol for a battery in this state.
    fn push_inverter_frames(
        &mut self,
        limits: &Limits,
        state: &PackState,
        conditions: &Conditions,
        capacity_ah: u16,
        modules: (u16, u16, u16, u16),
        slow: bool,
    ) {
        let (firmware, hardware) = (self.firmware, self.hardware);
        let mut push = |f: CanFrame| {
            let _ = self.queue.push_back(f);
        };
        push(frames::limits(limits));
        self.config.protocol.period_frames(
            &protocol::Period {
                state,
                conditions,
                capacity_ah,
                modules,
                firmware,
                hardware,
                slow,
            },
            &mut push,
        );
    }

    /// What this bridge has learnt of how the battery's current splits.
    pub fn shares(&self) -> &Shares {
        &self.shares
    }

    /// This bridge's own summary as it last sent it (with a node number).
    pub fn own_summary(&self) -> Option<Summary> {
        self.own_summary
    }

    /// With a node number: this pack's limits and summary, the battery of all
    /// packs heard, and — when this bridge is the speaker — the inverter
    /// frames for the battery.
    fn fill_member(&mut self, now: Instant, slow: bool) {
        let own = self.own_pack(now);
        let speaking = self.elect(now, own.is_some());
        let own = own.map(|o| self.send_own_summary(o, speaking));
        let gathered = self.gather(now, own);
        let shares = self.learn_shares(&gathered);
        let Some(battery) = self.aggregate(&gathered, &shares) else {
            self.lose_battery(now, speaking);
            return;
        };
        self.battery_lost = false;
        if !self.election.listened(now) {
            // Not every pack heard yet: no battery limits (nor speaking).
            self.battery = None;
            return;
        }
        let limits = self
            .battery_limits
            .step(now, &battery, gathered.mask, &self.config.charge);
        self.battery = Some((battery, limits));
        if speaking {
            self.speak_for_battery(&battery, limits, slow);
        } else {
            self.logged_battery = None;
        }
    }

    /// This pack as it goes into the battery, once the BMS has said anything:
    /// its limits are computed while its data is fresh (see
    /// [`Inverter::refresh_own`]). The summary carries the pack's limits before
    /// its own hold and ramp: the battery holds and ramps as a whole, so a pack
    /// that comes back after a cut adds its share at once instead of holding
    /// the whole battery at 0.
    fn own_pack(&mut self, now: Instant) -> Option<OwnPack> {
        let (Some(settings), Some((state, taken_at))) = (self.settings, self.state) else {
            return None;
        };
        let age = now.saturating_sub(taken_at);
        self.refresh_own(now, age, &settings, &state);
        let (ccl_da, dcl_da) = self.control.targets();
        self.limits.map(|l| OwnPack {
            state,
            age,
            limits: Limits {
                ccl_da,
                dcl_da,
                ..l
            },
            conditions: self.conditions,
            capacity_cah: settings.capacity_cah,
        })
    }

    /// This pack's data `age` old: stale once (reported when it becomes so),
    /// or fresh — reported when it was stale, and its limits computed. A pack
    /// that was stale left the battery meanwhile; the battery's hold and ramp
    /// rule its return (see `packs`), not this pack's.
    fn refresh_own(
        &mut self,
        now: Instant,
        age: Instant,
        settings: &PackSettings,
        state: &PackState,
    ) {
        if !self.config.freshness.young(Some(age)) {
            if self.stale_since.is_none() {
                self.stale_since = Some(now);
                self.report_stale(age);
            }
        } else {
            if self.stale_since.take().is_some() {
                self.report(InverterReport::Fresh);
            }
            self.update_own(now, settings, state);
        }
    }

    /// Stale telemetry, `age` old: what the configured policy does about it.
    fn report_stale(&mut self, age: Instant) {
        self.report(InverterReport::Stale {
            age_ms: (age / crate::MS).min(u64::from(u32::MAX)) as u32,
            policy: self.config.stale_policy,
            hold_us: self.config.stale_hold_us,
        });
    }

    /// Who speaks (reported when it changes). A bridge that sends no summary
    /// (no BMS data yet; another bridge has its number) must not speak: the
    /// others would not know.
    fn elect(&mut self, now: Instant, has_own: bool) -> bool {
        let able = has_own && !self.duplicate_reported;
        let was = self.election.speaking();
        let speaking = self.election.update(now, &self.packs, able);
        if speaking != was {
            self.report(InverterReport::Speaker(speaking));
        }
        speaking
    }

    /// This pack's summary (saying whether it speaks) onto the bus, and this
    /// pack as a member of the battery. Another bridge with this node number:
    /// this one falls silent (the same identifiers with other data would
    /// collide on the bus) until it restarts; the log says why. The sequence
    /// number advances either way.
    fn send_own_summary(&mut self, own: OwnPack, speaking: bool) -> Member {
        let summary = Summary::own(
            &own.state,
            own.age,
            &own.limits,
            &own.conditions,
            own.capacity_cah,
            speaking,
        );
        if !self.duplicate_reported {
            if let Some(fs) = summary.frames(self.packs.node(), self.seq) {
                for f in fs {
                    let _ = self.queue.push_back(f);
                }
            }
        }
        self.seq = (self.seq + 1) & packs::SEQ_MASK;
        self.own_summary = Some(summary);
        // What the pack may take when its BMS closes its switch again.
        if !summary.fault {
            self.own_closed = Some((summary.limits.ccl_da, summary.limits.dcl_da));
        }
        Member {
            closed_limits: self.own_closed,
            ..Member::now(summary)
        }
    }

    /// Every pack once (this one first, then the others heard), and the packs
    /// in the battery's sums as bits.
    fn gather(&self, now: Instant, own: Option<Member>) -> Gathered {
        let freshness = self.config.freshness;
        let mut g = Gathered::new();
        if let Some(m) = own {
            g.add(self.packs.node(), m, freshness);
        }
        for (n, m) in self.packs.known(now) {
            g.add(n, m, freshness);
        }
        g
    }

    /// What is learnt of how the current splits (see `packs::shares`), from
    /// the packs taking part; returns the learnt share of each member, in the
    /// members' order.
    fn learn_shares(&mut self, g: &Gathered) -> [Option<f32>; packs::MAX_NODES as usize] {
        let freshness = self.config.freshness;
        let mut part: heapless::Vec<(u8, i16), { packs::MAX_NODES as usize }> =
            heapless::Vec::new();
        for (n, m) in g.nodes.iter().zip(&g.members) {
            if m.takes_part(freshness) {
                let _ = part.push((*n, m.summary.current_da));
            }
        }
        let unknown = g.members.iter().any(|m| m.unknown(freshness));
        self.shares.update(&part, unknown);
        let mut shares = [None; packs::MAX_NODES as usize];
        for (s, n) in shares.iter_mut().zip(&g.nodes) {
            *s = self.shares.of(*n);
        }
        shares
    }

    /// The battery the members add up to (`None`: no pack takes part); the
    /// packs online and offline reported when they change.
    fn aggregate(&mut self, g: &Gathered, shares: &[Option<f32>]) -> Option<Battery> {
        let battery = packs::aggregate_with(&g.members, self.config.freshness, shares);
        let counts = battery.map_or((0, g.members.len() as u8), |b| (b.online, b.offline));
        if self.logged_packs != Some(counts) {
            self.logged_packs = Some(counts);
            self.report(InverterReport::Packs {
                online: counts.0,
                offline: counts.1,
            });
        }
        battery
    }

    /// No pack takes part: no battery, its limits cut (they come back after
    /// the hold), reported once. A speaker towards a Sunny Island, which obeys
    /// the last 0x351 for 60 s, tells it to stop (CCL 0, DCL 0).
    fn lose_battery(&mut self, now: Instant, speaking: bool) {
        self.battery = None;
        self.battery_limits.cut(now);
        if !self.battery_lost {
            self.battery_lost = true;
            self.report(InverterReport::BatteryLost);
        }
        if speaking && self.config.protocol.obeys_last_limits() {
            if let Some(last) = self.sent_battery {
                let stop = Limits {
                    ccl_da: 0,
                    dcl_da: 0,
                    ..last
                };
                let _ = self.queue.push_back(frames::limits(&stop));
            }
        }
    }

    /// As the speaker: the battery's limits (logged when they change, kept for
    /// the stop frames of a lost battery) and its inverter frames.
    fn speak_for_battery(&mut self, battery: &Battery, limits: Limits, slow: bool) {
        if self.logged_battery != Some(limits) {
            self.logged_battery = Some(limits);
            self.report(InverterReport::BatteryLimits(limits));
        }
        self.sent_battery = Some(limits);
        let capacity_ah = (battery.capacity_dah / DAH_PER_AH).min(u32::from(u16::MAX)) as u16;
        let modules = (
            u16::from(battery.online),
            u16::from(battery.blocking_charge),
            u16::from(battery.blocking_discharge),
            u16::from(battery.offline),
        );
        self.push_inverter_frames(
            &limits,
            &battery.state,
            &battery.conditions,
            capacity_ah,
            modules,
            slow,
        );
    }

    /// Stale: the limits frame with CCL 0 (and DCL 0 when `stop_discharge`),
    /// the rest as last computed, and the alarm frame with "link lost" flagged.
    /// No measurement frame: those would be stale values sent as fresh. Used by
    /// the hold policy (CCL 0 only) and by "stop sending" towards a Sunny
    /// Island (both 0), which would otherwise obey the last limits for 60 s.
    fn queue_stale(&mut self, stop_discharge: bool) {
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
        let _ = self.queue.push_back(frames::limits(&stale));
        let _ = self.queue.push_back(self.config.protocol.alarms(&c));
    }
}

/// 0.1 Ah per Ah (the battery's capacity is summed in 0.1 Ah, sent in Ah).
const DAH_PER_AH: u32 = 10;

/// This pack as it goes into the battery (with a node number).
#[derive(Debug, Clone, Copy)]
struct OwnPack {
    /// Its state, as last decoded.
    state: PackState,
    /// The age of that state, µs.
    age: Instant,
    /// Its limits, CCL and DCL before its own hold and ramp.
    limits: Limits,
    /// Its alarms and warnings.
    conditions: Conditions,
    /// Its capacity (306), 0.01 Ah.
    capacity_cah: u16,
}

/// Every pack of the battery once: their node numbers and members in the same
/// order, and the packs in the battery's sums as bits (node n: bit n − 1).
struct Gathered {
    nodes: heapless::Vec<u8, { packs::MAX_NODES as usize }>,
    members: heapless::Vec<Member, { packs::MAX_NODES as usize }>,
    mask: u16,
}

impl Gathered {
    fn new() -> Self {
        Self {
            nodes: heapless::Vec::new(),
            members: heapless::Vec::new(),
            mask: 0,
        }
    }

    /// Node `n` as `m`. The packs in the battery's sums: a pack without fresh
    /// data that may still conduct stays (no hold restarts when a lossy bus
    /// makes packs come and go); one known open leaves.
    fn add(&mut self, n: u8, m: Member, freshness: Freshness) {
        let _ = self.nodes.push(n);
        if m.in_sums(freshness) {
            self.mask |= node_bit(n);
        }
        let _ = self.members.push(m);
    }
}

/// Node `n`'s bit in a mask of nodes (bit `n − 1`; the index wrapped to the
/// mask's 16 bits).
const fn node_bit(n: u8) -> u16 {
    1 << (n.saturating_sub(1) & (u16::BITS as u8 - 1))
}
