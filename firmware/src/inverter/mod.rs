//! The inverter output: the BMS's telemetry and settings in, CAN frames out,
//! sans-IO like the bridge. The chip shell moves frames between this and the
//! TWAI controller; the host runs it against a simulated pack and inverter.
//!
//! * [`control`] — the charge limits and alarms (the part that protects cells).
//! * [`say`] — what the inverter is told: the one decision of every period,
//!   for every dialect: the limits, the stops and every signal they go out
//!   with.
//! * [`finish`] — the end of a charge: the balance hold, the periodic full
//!   charge, the step down into float, the SOC ceiling.
//! * [`dialect`] — the dialects behind one seam (Victron, SMA Sunny Island,
//!   the Pylontech LV family, Growatt), listed once; each puts what [`say`]
//!   decided into its frames and reads them back.
//! * [`hold`] — the hold the pack can afford while the BMS's data is stale;
//!   `gap.rs` — a bridge alone's periods while its data is stale: the hold,
//!   then the stop said blind.
//! * [`ignored`] — an inverter seen ignoring a stop.
//! * [`bus`] — the CAN port's health (no ACK, bus-off, the inverter heard).
//! * [`stale`] — a stale episode, its hold and a policy given meanwhile.
//! * [`report`] — what the output tells the log.
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
//! **The rule every other rule serves: no cell past its cutoff and no charge
//! outside its temperature window, whatever the inverter does with the
//! limits and whenever the BMS's data stops.**
//!
//! * **A stop is a stop, fresh or stale.** A side that must stop goes out
//!   with every signal the dialect's inverters are known to obey ([`say`]);
//!   an inverter seen ignoring a stop gets every signal the dialect has,
//!   from then on ([`ignored`]).
//! * **Stale data is never sent as fresh.** When the newest snapshot is
//!   older than [`InverterConfig::freshness`] allows, the charge stops at
//!   once (CCL 0, the charge voltage at most the pack's last), and with the
//!   default [`StaleMode::Hold`] the discharge goes on for at most
//!   `stale_hold` (120 s) within what the last fresh data proves the pack can
//!   afford ([`hold`]): the limit falls to 0 where that budget could be
//!   spent. A short loss of the BMS's data (a loose UART wire, a BMS restart)
//!   then never switches an island inverter off at once, and never runs a
//!   cell past its cutoff. [`StaleMode::Stop`] skips the hold.
//! * **Never silence where an inverter would run on.** Once the hold is over
//!   (or with `stop`), both sides stop, said blind with every signal: a
//!   dialect whose inverter stops on silence (a GX) hears the stop for a few
//!   periods, then nothing; the others hear it every period until the data
//!   is back ([`dialect::OnSilence`]).
//! * When the data is back, nothing waits a hold: DCL is what the data says
//!   at once, CCL ramps from 0 ([`control::ChargeControl::resume`]).

pub mod bus;
pub mod capture;
pub mod control;
pub mod dialect;
pub mod doctor;
pub mod finish;
mod gap;
pub mod hold;
pub mod ignored;
pub mod membership;
pub mod packs;
pub mod port;
pub mod report;
pub mod say;
pub mod stale;
pub mod why;

use heapless::Deque;
use protocol_core::events::{Event, EventId};
use protocol_core::views::{LiveSnapshot, VersionInfo};

use self::bus::BusHealth;
use self::control::{ChargeConfig, ChargeControl, Conditions, Limits, PackSettings, PackState};
use self::dialect::{pylon, CanFrame, Frames, Period, Protected, Stops, Told};
use self::ignored::{Ignored, IgnoredStops};
use self::membership::Membership;
use self::packs::{Battery, BatteryView, Packs, Shares, Summary};
use self::say::Signals;
use self::stale::StaleEpisode;
use crate::Instant;

pub use self::dialect::Protocol;
use self::report::limits_log_due;
pub use self::report::{InverterReport, Reports, LIMITS_LOG_PERIOD_US};
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
    /// In a dialect whose inverters are known to ignore a current limit of
    /// 0 A (the Pylontech family, Growatt): report SOC 100 % (0 %) while
    /// charging (discharging) must stop (`stop_by_soc`, on by default).
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
            stop_by_soc: true,
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

/// Frames in one burst at most (a summary and a slow period of the battery's).
const QUEUE: usize = 16;

/// A Luxpower inverter's shutdown request holds this long after its last
/// 0x300, µs.
pub const SHUTDOWN_HOLD_US: Instant = 10 * crate::SECOND;

/// The inverter output. See the module documentation.
#[derive(Debug, Clone)]
pub struct Inverter {
    config: InverterConfig,
    control: ChargeControl,
    settings: Option<PackSettings>,
    state: Option<(PackState, Instant)>,
    firmware: u16,
    hardware: u16,
    /// The limits last computed from fresh data.
    limits: Option<Limits>,
    logged_limits: Option<Limits>,
    /// When they were logged.
    limits_logged_at: Instant,
    conditions: Conditions,
    charge_blocked: Option<EventId>,
    fault_clear_since: Option<Instant>,
    /// The last cutoff event of the BMS (what its fault status is about).
    tripped: Option<EventId>,
    queue: Deque<CanFrame, QUEUE>,
    next_fast: Instant,
    next_slow: Instant,
    /// A stop to pass on now, before the period is due (the period keeps
    /// its rhythm).
    urgent: bool,
    stale: StaleEpisode,
    bus: BusHealth,
    reports: Reports,
    membership: Membership,
    /// The last limits frame handed out, and when.
    told: Option<(Limits, Instant)>,
    /// What the last period's frames tell, read back, and the stops they say.
    said: (Stops, Told),
    /// The stops of the last fresh period (a stale one keeps their causes).
    fresh_stops: Stops,
    /// Stops the inverter was seen ignoring.
    ignored: IgnoredStops,
    /// The end-of-charge stage last logged.
    logged_stage: Option<finish::Stage>,
    /// Why the limits last told are what they are, and whether it was logged.
    reasons: Option<why::Reasons>,
    logged_reasons: Option<why::Reasons>,
    /// The snapshot the watch of ignored stops saw last.
    watched_at: Option<Instant>,
    /// When SOC was last at least 97 % (or the data first came): the
    /// full-charge request's 30 days run from it.
    full_at: Option<Instant>,
    /// The last shutdown request of a Luxpower inverter.
    shutdown_at: Option<Instant>,
    /// Growatt: the frames of the last period, for the next query, and when
    /// they were made.
    answer: heapless::Vec<CanFrame, 8>,
    answer_at: Option<Instant>,
    /// The last frames both ways ([`capture`]), the frame handed out and
    /// not yet reported sent, and the doctor reading them ([`doctor`]).
    capture: capture::Capture,
    in_flight: Option<CanFrame>,
    doctor: doctor::Doctor,
}

/// What one period is made of, besides what is told.
struct Made<'a> {
    state: &'a PackState,
    conditions: &'a Conditions,
    capacity_ah: u16,
    modules: (u16, u16, u16, u16),
    slow: bool,
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
            tripped: None,
            queue: Deque::new(),
            next_fast: now,
            next_slow: now,
            urgent: false,
            stale: StaleEpisode::default(),
            bus: BusHealth::default(),
            reports: Reports::default(),
            membership: Membership::new(config.node, now),
            told: None,
            said: (Stops::default(), Told::default()),
            fresh_stops: Stops::default(),
            ignored: IgnoredStops::default(),
            logged_stage: None,
            reasons: None,
            logged_reasons: None,
            watched_at: None,
            full_at: None,
            shutdown_at: None,
            answer: heapless::Vec::new(),
            answer_at: None,
            capture: capture::Capture::new(),
            in_flight: None,
            doctor: doctor::Doctor::new(config.protocol),
        }
    }

    /// The last frames both ways on the bus ([`capture`]).
    pub fn capture(&self) -> &capture::Capture {
        &self.capture
    }

    /// What the doctor found in them ([`doctor`]).
    pub fn doctor(&self) -> &doctor::Doctor {
        &self.doctor
    }

    /// Records `seen` in the capture and shows it to the doctor (with the
    /// time as it is: the capture keeps milliseconds that wrap after 49
    /// days, the doctor's evidence is judged against the running clock).
    fn capture_now(&mut self, now: Instant, seen: capture::Seen) {
        self.capture.record(now, seen);
        self.doctor.on_entry(now, seen);
        if let Some(v) = self.doctor.take_news() {
            self.reports.push(InverterReport::Doctor(v));
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

    /// The limits last computed from fresh data.
    pub fn limits(&self) -> Option<Limits> {
        self.limits
    }

    /// What the inverter is told at `now`: the limits of the last limits
    /// frame this output sent, while it sends them (one came within two fast
    /// periods) — this pack's limits for a bridge alone, the battery's while
    /// this bridge speaks for several packs; `None` when nothing is sent
    /// (output off, quiet after a stop, a bridge of several packs that does
    /// not speak).
    pub fn limits_sent(&self, now: Instant) -> Option<Limits> {
        let (l, at) = self.told?;
        (now.saturating_sub(at) <= 2 * self.config.fast_period_us).then_some(l)
    }

    /// Alarms and warnings last computed.
    pub fn conditions(&self) -> Conditions {
        self.conditions
    }

    /// What must stop now and why, as the inverter is told (`None` with the
    /// output off).
    pub fn protection(&self) -> Option<Stops> {
        self.config.enabled.then_some(self.said.0)
    }

    /// What the last period's frames tell the inverter, read back from them
    /// (`None` with the output off).
    pub fn told(&self) -> Option<Told> {
        self.config.enabled.then_some(self.said.1)
    }

    /// The last stop the inverter was seen ignoring, if any.
    pub fn ignored(&self) -> Option<Ignored> {
        self.ignored.last()
    }

    /// Absorption or float.
    pub fn phase(&self) -> control::Phase {
        self.control.phase()
    }

    /// Where the charge is and why ([`finish`]); `None` before the first
    /// fresh data or with the output off.
    pub fn stage(&self) -> Option<finish::Stage> {
        (self.config.enabled && self.limits.is_some()).then(|| self.control.stage())
    }

    /// Why each limit last told is what it is ([`why`]); `None` before the
    /// first period or with the output off.
    pub fn reasons(&self) -> Option<why::Reasons> {
        self.config.enabled.then_some(self.reasons).flatten()
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
        let over_current = self
            .settings
            .is_some_and(|s| self.control.watch_current(taken_at, &s, &p));
        // A current past its cutoff: the stop goes out at once.
        self.urgent |= over_current;
        if self.membership.node() == 0 && self.watch_ignored(taken_at, p.current_a) {
            // Escalated: every signal goes out at once, not a period later.
            self.next_fast = self.next_fast.min(taken_at);
        }
        if let Some(v) = version {
            self.firmware = u16::from(v.firmware_public);
            self.hardware = u16::from_le_bytes([v.hardware, v.hardware_changes]);
        }
    }

    /// A BMS event: charge-side fault events block charging until the BMS
    /// reports the matching recovery (or, failing that, see
    /// [`CHARGE_BLOCK_TIMEOUT_US`]); a cutoff event says what the BMS's fault
    /// status is about (its protection bits).
    pub fn on_event(&mut self, e: &Event) {
        let recovers = |blocked: EventId| match blocked {
            EventId::OverVoltageCutoff => EventId::RecoveredOverVoltage,
            EventId::ChargingOverCurrentCutoff => EventId::RecoveredChargingOverCurrent,
            EventId::LowTemperatureCutoff => EventId::RecoveredLowTemperatureFault,
            _ => EventId::RecoveredRegenerationOverCurrent,
        };
        if Protected::of_event(e.id).is_some() {
            self.tripped = Some(e.id);
        }
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

    /// What the BMS itself protects against now: while its status says
    /// "fault", the cutoff its last cutoff event named (a fault without one:
    /// a system error).
    fn bms_protected(&self, state: &PackState) -> Protected {
        if !state.fault {
            return Protected::default();
        }
        self.tripped
            .and_then(Protected::of_event)
            .unwrap_or(Protected {
                system: true,
                ..Protected::default()
            })
    }

    /// A frame from the bus (the inverter's heartbeat or query, a Luxpower
    /// inverter's shutdown request, other packs' summaries).
    pub fn on_received(&mut self, now: Instant, id: u16, data: &[u8]) {
        if !self.config.enabled {
            return; // output off: the bus is none of our business
        }
        let mut data8 = [0u8; 8];
        for (d, b) in data8.iter_mut().zip(data) {
            *d = *b;
        }
        let len = data.len().min(8) as u8;
        self.capture_now(now, capture::Seen::Heard(CanFrame::new(id, len, data8)));
        // Another pack stops a side: the inverter hears it now.
        self.urgent |= self.membership.on_frame(now, id, data, &mut self.reports);
        let protocol = self.config.protocol;
        if protocol.heartbeat(id) {
            self.bus.keepalive(now, &mut self.reports);
        }
        if protocol.answers_only() && dialect::growatt::is_query(id) {
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
    /// (two periods); nothing otherwise (no data yet, or quiet).
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

    /// The full-charge request at `now` (SOC not at 97 % for 30 days), from
    /// the SOC of fresh data (`None`: stale).
    fn full_charge(&mut self, now: Instant, soc_pct: Option<f32>) -> bool {
        if let Some(soc) = soc_pct {
            if soc >= pylon::FULL_SOC_PCT || self.full_at.is_none() {
                self.full_at = Some(now);
            }
        }
        self.full_at
            .is_some_and(|t| now.saturating_sub(t) >= pylon::FULL_CHARGE_AFTER_US)
    }

    /// A Luxpower inverter's shutdown request is in force at `now` (its end
    /// reported once).
    fn shutdown_asked(&mut self, now: Instant) -> bool {
        if self
            .shutdown_at
            .is_some_and(|t| now.saturating_sub(t) > SHUTDOWN_HOLD_US)
        {
            self.shutdown_at = None;
            self.reports.push(InverterReport::ShutdownAsked(false));
        }
        self.shutdown_at.is_some()
    }

    /// The signals a stop goes out with now: every one once the inverter was
    /// seen ignoring a stop, else what the dialect's inverters obey.
    fn signals(&self) -> Signals {
        if self.ignored.escalated() {
            Signals::ALL
        } else {
            Signals::ordinary(self.config.protocol.dialect(), self.config.stop_by_soc)
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
    pub fn on_tx(&mut self, now: Instant, result: TxResult) {
        if let Some(f) = self.in_flight.take() {
            let seen = match result {
                TxResult::Sent => capture::Seen::Sent(f),
                TxResult::Failed => capture::Seen::NoAck,
            };
            self.capture_now(now, seen);
        }
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
        self.in_flight = None;
        self.capture_now(now, capture::Seen::BusOff);
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
        if self.config.protocol.answers_only() {
            self.doctor.on_quiet(now);
            if let Some(v) = self.doctor.take_news() {
                self.reports.push(InverterReport::Doctor(v));
            }
        }
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
        let due = now >= self.next_fast;
        if due || self.urgent {
            self.urgent = false;
            let mut slow = false;
            if due {
                self.next_fast = now.saturating_add(self.config.fast_period_us);
                slow = now >= self.next_slow;
                if slow {
                    self.next_slow = now.saturating_add(self.config.slow_period_us);
                }
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
        self.in_flight = Some(f);
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
            self.fill_stale(now, age, &settings, &state);
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
        let made = Made {
            state: &state,
            conditions: &conditions,
            capacity_ah,
            modules,
            slow,
        };
        self.tell_fresh(now, &limits, &made);
    }

    /// A fresh current taken at `taken_at` (once each): flowing against the
    /// stops last told, it escalates them (reported once). Returns whether an
    /// escalation began.
    fn watch_ignored(&mut self, taken_at: Instant, current_a: f32) -> bool {
        if self.watched_at == Some(taken_at) {
            return false;
        }
        self.watched_at = Some(taken_at);
        let stops = self.said.0;
        let e = self.ignored.on_fresh(
            taken_at,
            current_a,
            stops.charge.is_some(),
            stops.discharge.is_some(),
        );
        if let Some(e) = e {
            self.reports.push(InverterReport::IgnoresStop(e));
        }
        e.is_some()
    }

    /// Fresh data: what must stop (the limits computed, a Luxpower's
    /// shutdown request) and the frames that tell it.
    fn tell_fresh(&mut self, now: Instant, limits: &Limits, m: &Made<'_>) {
        let stops = if self.shutdown_asked(now) {
            Stops::shutdown()
        } else {
            Stops::of(limits, m.state, m.conditions)
        };
        self.fresh_stops = stops;
        let full_charge = self.full_charge(now, Some(m.state.soc_pct));
        let signals = self.signals();
        self.tell(now, *limits, stops, signals, true, full_charge, m);
    }

    /// The one decision of a period ([`say::decide`]), put into the
    /// dialect's frames, read back for the log, and queued.
    #[allow(clippy::too_many_arguments)]
    fn tell(
        &mut self,
        now: Instant,
        limits: Limits,
        stops: Stops,
        signals: Signals,
        fresh: bool,
        full_charge: bool,
        m: &Made<'_>,
    ) {
        let floor_dv = self.settings.map_or(0, |s| {
            (u32::from(s.cells) * u32::from(s.uv_cutoff_mv)).div_ceil(100) as u16
        });
        let say = say::decide(&say::Inputs {
            limits,
            state: m.state,
            conditions: m.conditions,
            stops,
            fresh,
            signals,
            bms_protected: self.bms_protected(m.state),
            floor_dv,
            name: self.config.name,
            full_charge,
        });
        let settings = self.settings;
        let protocol = self.config.protocol;
        let frames: Frames = protocol.frames(&Period {
            say: &say,
            state: m.state,
            conditions: m.conditions,
            capacity_ah: m.capacity_ah,
            modules: m.modules,
            firmware: self.firmware,
            hardware: self.hardware,
            slow: m.slow,
            settings: settings.as_ref(),
        });
        let mut told = Told::default();
        for f in &frames {
            protocol.read_back(f, &mut told);
        }
        let base = if self.membership.node() == 0 {
            self.control.reasons()
        } else {
            let packs = why::Why::Battery {
                packs: m.modules.0.min(u16::from(u8::MAX)) as u8,
            };
            why::Reasons {
                cvl: packs,
                ccl: packs,
                dcl: packs,
            }
        };
        self.reasons_now(base.after_say(&limits, &say.limits, say.stops, fresh));
        self.said_now(say.stops, told);
        self.queue_frames(now, &frames);
    }

    /// Why the limits of this period are what they are, reported when a
    /// rule changes (not each number).
    fn reasons_now(&mut self, r: why::Reasons) {
        self.reasons = Some(r);
        if !self.logged_reasons.is_some_and(|l| l.same_rules(&r)) {
            self.logged_reasons = Some(r);
            self.reports.push(InverterReport::Reasons(r));
        }
    }

    /// What this period says, reported when the stops or the signals that
    /// say them change.
    fn said_now(&mut self, stops: Stops, told: Told) {
        let key = |(s, t): &(Stops, Told)| {
            let forced = t.soc_pct.filter(|v| !s.none() && (*v == 0 || *v == 100));
            (
                *s,
                t.charge_enabled,
                t.discharge_enabled,
                t.protection,
                t.link_lost,
                forced,
            )
        };
        let changed = key(&self.said) != key(&(stops, told));
        self.said = (stops, told);
        if changed {
            self.reports
                .push(InverterReport::Protection { stops, told });
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
        let (limits, conditions) = self.control.update(now, settings, state);
        self.limits = Some(limits);
        self.conditions = conditions;
        let stage = self.control.stage();
        if !self.logged_stage.is_some_and(|s| s.same_kind(stage)) {
            self.logged_stage = Some(stage);
            self.reports.push(InverterReport::Stage(stage));
        }
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

    /// What this bridge has learnt of how the battery's current splits.
    pub fn shares(&self) -> &Shares {
        self.membership.shares()
    }

    /// This bridge's own summary as it last sent it (with a node number).
    pub fn own_summary(&self) -> Option<Summary> {
        self.membership.own_summary()
    }
}
