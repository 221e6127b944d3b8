//! Runs the firmware's own station ([`tinybms_firmware::station::Station`]: the
//! bridge with its configuration, host link and inverter output) against the
//! simulated TinyBMS in virtual time, doing what the station says as the chip
//! shell's `station_task` does, with the UART replaced by [`crate::sim::SimBms`],
//! the CAN bus by an outbox and the clock by a number. No threads, no sleeps:
//! hours of polling run in seconds.

use std::collections::HashMap;

use protocol_core::events::Event;
use protocol_core::request::SettingsOption;
use protocol_core::response::RegisterBlock;
use protocol_core::settings::Setting;
use protocol_core::views::{LiveSnapshot, VersionInfo};
use tinybms_firmware::bms::event_log::ts_newer;
use tinybms_firmware::bms::timing::{Timing, BYTE_TIME_US};
use tinybms_firmware::bridge::report::WriteOutcome;
use tinybms_firmware::config::store::{Saved, StoreError};
use tinybms_firmware::config::Config;
use tinybms_firmware::inverter::dialect::CanFrame;
use tinybms_firmware::inverter::TxResult;
use tinybms_firmware::station::{Action, Logged, Station};
use tinybms_firmware::{Bridge, Level, Report};

use crate::sim::{PackModel, SimBms, SimConfig};
use crate::truth;
use tinybms_desk::driver::bridge_station;

/// How long the simulator keeps the blocks it answered, for the ground-truth
/// checks (a confirmed read on a bad line may take minutes).
pub const TRUTH_WINDOW_US: u64 = 600 * 1_000_000;

/// Events logged this close to the end of a run and not reported yet are
/// "pending", not "missing" (on a bad line a gap fill takes seconds).
pub const EVENT_REPORT_GRACE_US: u64 = 60 * 1_000_000;

/// What [`Harness::checked`] found: every published value compared with what the
/// simulated BMS really sent, every write outcome with its register file.
#[derive(Debug, Clone, Default)]
pub struct Soak {
    /// Snapshots published.
    pub published: u64,
    /// Of which flagged (confirmed, but failing a check).
    pub flagged: u64,
    /// Published blocks (snapshots, settings, limits, statistics, version) with
    /// a value the BMS never sent.
    pub wrong: u64,
    /// The first few of them, described.
    pub wrong_examples: Vec<String>,
    /// Blocks checked (snapshots and the others).
    pub blocks_checked: u64,
    /// "verified"/"unchanged" outcomes while the BMS did not hold the value.
    pub false_successes: u64,
    /// "failed"/"nacked" outcomes while the BMS did hold the new value.
    pub false_failures: u64,
    /// Write outcomes by name (first outcome and follow-ups together).
    pub outcomes: HashMap<&'static str, u64>,
    /// Follow-up outcomes.
    pub follow_ups: u64,
    /// Transitions to offline.
    pub offline_transitions: u64,
    /// Longest time without a new snapshot once the bridge was ready, µs.
    pub longest_gap_us: u64,
    /// Time of the first "ready".
    pub ready_at: Option<u64>,
    /// Event reports: key (timestamp, id) -> how many times reported.
    pub events_reported: HashMap<(u32, u8), u32>,
    /// The start-up history line: (time, count, newest).
    pub history: Option<(u64, u8, Option<Event>)>,
    /// Lines logged by level.
    pub warn_lines: u64,
    /// Lines logged in all.
    pub lines: u64,
    last_publish: Option<u64>,
    last_settings: Option<RegisterBlock>,
    last_limits: (Option<RegisterBlock>, Option<RegisterBlock>),
    last_stats: Option<RegisterBlock>,
    last_version: Option<VersionInfo>,
}

/// Events compared with what the simulated BMS logged.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct EventCheck {
    /// Events the BMS logged after the start-up history.
    pub logged: u64,
    /// Of which reported exactly once.
    pub reported_once: u64,
    /// Logged but never reported.
    pub missing: u64,
    /// Logged in the last minute of the run and not reported yet.
    pub pending: u64,
    /// Reported more than once.
    pub duplicated: u64,
    /// Reported but never logged.
    pub invented: u64,
    /// Events in the start-up history line.
    pub history: u64,
}

impl Soak {
    fn wrong(&mut self, what: String) {
        self.wrong += 1;
        self.example(what);
    }

    fn example(&mut self, what: String) {
        if self.wrong_examples.len() < 10 {
            self.wrong_examples.push(what);
        }
    }
}

/// A UART read returns after at most this much wire time (≈ 16 bytes: the ESP32
/// RX FIFO threshold / idle timeout behaviour), so replies arrive in chunks.
pub const RX_CHUNK_US: u64 = 16 * BYTE_TIME_US;

/// The ESP32-C3/C6 UART's RX FIFO, bytes: what survives while the CPU does
/// not run (a flash erase or write stops it, [`Harness::stall`]).
pub const UART_FIFO_BYTES: usize = 128;

/// One log line, as the device would print it.
#[derive(Debug, Clone, PartialEq)]
pub struct LogLine {
    /// Virtual time, µs.
    pub at_us: u64,
    /// Level.
    pub level: Level,
    /// The report.
    pub report: Report,
}

impl core::fmt::Display for LogLine {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let level = match self.level {
            Level::Info => "INFO ",
            Level::Warn => "WARN ",
        };
        write!(
            f,
            "{:>10.3}s {level} {}",
            self.at_us as f64 / 1e6,
            self.report
        )
    }
}

/// The CAN controller of a harness's station: what it sent, and a bus-off
/// in progress.
#[derive(Debug, Clone, Default)]
pub struct CanPort {
    /// Frames go on a bus (false: no other node acknowledges them).
    pub attached: bool,
    /// Frames sent and not yet taken by the loop that delivers them: (time,
    /// frame).
    pub outbox: Vec<(u64, CanFrame)>,
    /// The controller is bus-off until this time (a scenario's fault): a
    /// recovery before it fails.
    pub bus_off_until: Option<u64>,
}

/// Saves the station's record: the result and for how long the save stops
/// the CPU, µs.
pub type Saver = Box<dyn FnMut(&Config, &SimBms) -> (Result<Saved, StoreError>, u64)>;

/// The station, the simulated BMS and the virtual clock.
pub struct Harness {
    /// The firmware's station (the bridge and its consumers) under test.
    pub station: Station,
    /// The simulated BMS.
    pub sim: SimBms,
    /// Virtual time, µs.
    pub now: u64,
    /// Every report, in order.
    pub log: Vec<LogLine>,
    /// Every snapshot the bridge published (time, snapshot).
    pub published: Vec<(u64, LiveSnapshot)>,
    /// Bytes the bridge transmitted.
    pub tx_bytes: u64,
    /// Bytes the bridge received.
    pub rx_bytes: u64,
    /// Wire time the bridge's transmissions occupied, µs.
    pub tx_busy_us: u64,
    /// Print each log line to stdout as it happens.
    pub echo: bool,
    seen_seq: u32,
    /// Live snapshot latencies, µs: the first request byte of the live read that
    /// produced the snapshot (whole block, pieces or a confirming read alike) to
    /// the snapshot being published. The bridge's reader stamps the time its first
    /// piece is handed to the UART (`LiveMeta::span_us` runs from it to the last
    /// piece received, which is when the snapshot is published).
    pub live_latencies: Vec<u64>,
    /// Statistics reads started (requests whose first register is 100).
    pub stats_reads: u64,
    /// Event-log reads started (0x11 / 0x12, or a 0x03 / 0x09 read from register 200).
    pub event_reads: u64,
    /// Keep every log line and published snapshot (off for long soaks: the
    /// counters of [`Harness::soak`] remain).
    pub retain: bool,
    /// Ground-truth checks, when made by [`Harness::checked`].
    pub soak: Option<Soak>,
    /// Bytes the BMS sent while the CPU was stopped ([`Harness::stall`]) that
    /// did not fit the UART's FIFO: lost.
    pub fifo_lost_bytes: u64,
    /// Stalls so far and their total length, µs.
    pub stalls: (u64, u64),
    /// When set, every call made to the bridge is appended here in the format of
    /// [`crate::trace`] (the recorded trace the RISC-V cost benchmark replays).
    pub trace: Option<Vec<u8>>,
    /// What else the station logged (configuration notes, inverter reports).
    pub other_log: Vec<(u64, Logged)>,
    /// The CAN controller.
    pub can: CanPort,
    /// The configuration store (`None`: none; a save then fails as on a chip
    /// without a usable partition).
    pub saver: Option<Saver>,
    /// Lines the host link wrote, collected after every pass when set.
    pub host_lines: Option<Vec<String>>,
    /// Or the host link's port as the chip's writer drives it, with a host
    /// that drains it as it likes ([`crate::virtual_host_port`]).
    pub host_port: Option<crate::virtual_host_port::HostPort>,
    /// For how long the port's writer kept the CPU (a spinning writer).
    port_busy_us: u64,
    /// [`Harness::run_until`] also does what the station wants done at the
    /// end time itself (up to its next wait) before it returns: for loops
    /// that step other parts at that time (the closed loops' CAN bus and
    /// inverter model). Off: it returns at the end time, as a plain
    /// `while now < end` loop.
    pub finish_at_end: bool,
    /// The chip's flash for updates (`None`: an update's flash work fails).
    pub ota: Option<tinybms_desk::ota::ChipFlash>,
    /// How long an update's erase, program and `otadata` write stop the
    /// CPU, µs (the boards' flash: about 45, 15 and 45 ms).
    pub flash_stall_us: (u64, u64, u64),
    /// Every update flash operation: its time and its name.
    pub flash_ops: Vec<(u64, &'static str)>,
    /// The station asked for a restart (an update installed): the station
    /// does nothing more (each run after it only moves the clock to its
    /// end).
    pub restart_requested: bool,
    /// When it asked for it.
    pub restarted_at: Option<u64>,
    /// When set, every request to the BMS: its time and bytes.
    pub tx_log: Option<Vec<(u64, Vec<u8>)>>,
}

impl Harness {
    /// A copy of this harness as it is now — the station, the simulated BMS,
    /// the clock and the CAN controller — to run on from here on its own (a
    /// sweep's branch): no log kept, no host, no store, no trace, no update
    /// flash.
    pub fn fork(&self) -> Harness {
        let mut h = Harness::with_station(self.sim.clone(), self.station.clone());
        h.now = self.now;
        h.seen_seq = self.seen_seq;
        h.can = self.can.clone();
        h.retain = false;
        h.finish_at_end = self.finish_at_end;
        h.flash_stall_us = self.flash_stall_us;
        h
    }

    /// A harness at time 0 with the default bridge configuration.
    pub fn new(sim: SimBms) -> Self {
        Self::with_config(sim, Timing::default())
    }

    /// A harness at time 0 with a bridge alone (no consumer: [`bridge_only`](tinybms_desk::driver::bridge_only)).
    pub fn with_config(sim: SimBms, config: Timing) -> Self {
        Self::with_station(sim, bridge_station("sim", config, 0))
    }

    /// A harness at time 0 around `station`.
    pub fn with_station(sim: SimBms, station: Station) -> Self {
        Self {
            station,
            sim,
            now: 0,
            log: Vec::new(),
            published: Vec::new(),
            tx_bytes: 0,
            rx_bytes: 0,
            tx_busy_us: 0,
            echo: false,
            seen_seq: 0,
            live_latencies: Vec::new(),
            stats_reads: 0,
            event_reads: 0,
            retain: true,
            soak: None,
            trace: None,
            fifo_lost_bytes: 0,
            stalls: (0, 0),
            other_log: Vec::new(),
            can: CanPort::default(),
            saver: None,
            host_lines: None,
            host_port: None,
            port_busy_us: 0,
            finish_at_end: false,
            ota: None,
            flash_stall_us: (45_000, 15_000, 45_000),
            flash_ops: Vec::new(),
            restart_requested: false,
            restarted_at: None,
            tx_log: None,
        }
    }

    /// The bridge.
    pub fn bridge(&self) -> &Bridge {
        self.station.bridge()
    }

    /// The bridge, for commands.
    pub fn bridge_mut(&mut self) -> &mut Bridge {
        self.station.bridge_mut()
    }

    /// A harness that checks every published value and write outcome against
    /// the simulated BMS as it goes ([`Harness::soak`]).
    pub fn checked(mut sim: SimBms, config: Timing) -> Self {
        sim.record_reads(TRUTH_WINDOW_US);
        let mut h = Self::with_config(sim, config);
        h.soak = Some(Soak::default());
        h
    }

    /// Events reported compared with the events the simulated BMS logged.
    pub fn event_check(&self) -> EventCheck {
        let mut c = EventCheck::default();
        let Some(soak) = &self.soak else {
            return c;
        };
        let newest = soak.history.and_then(|(_, _, n)| n);
        c.history = soak.history.map(|(_, n, _)| u64::from(n)).unwrap_or(0);
        let mut logged: HashMap<(u32, u8), u32> = HashMap::new();
        // Logged in the last minute of the run: maybe not read yet.
        let recent: Vec<(u32, u8)> = self
            .sim
            .logged_events()
            .iter()
            .filter(|(t, _)| t.saturating_add(EVENT_REPORT_GRACE_US) > self.now)
            .map(|(_, e)| (e.timestamp_s, e.id.raw()))
            .collect();
        for (_, e) in self.sim.logged_events() {
            let in_history = match newest {
                Some(n) => !ts_newer(e.timestamp_s, n.timestamp_s),
                None => soak.history.is_some_and(|(t, _, _)| t >= self.sim.now_us()),
            };
            if soak.history.is_some() && in_history {
                continue;
            }
            *logged.entry((e.timestamp_s, e.id.raw())).or_default() += 1;
        }
        for (key, n) in &logged {
            c.logged += u64::from(*n);
            match soak.events_reported.get(key).copied().unwrap_or(0) {
                0 if recent.contains(key) => c.pending += u64::from(*n),
                0 => c.missing += u64::from(*n),
                r if r == *n => c.reported_once += u64::from(*n),
                r if r > *n => c.duplicated += u64::from(r - n),
                r => {
                    c.reported_once += u64::from(r);
                    c.missing += u64::from(n - r);
                }
            }
        }
        for (key, r) in &soak.events_reported {
            if !logged.contains_key(key) {
                c.invented += u64::from(*r);
            }
        }
        c
    }

    /// Runs until virtual time `end_us`.
    pub fn run_until(&mut self, end_us: u64) {
        self.run_until_hooked(end_us, &mut |_, _, _| 0);
    }

    /// The CPU stops for `us` (a flash erase or write: the cache is off), as it
    /// does on the chip: the BMS's bytes meanwhile fill the UART's FIFO, what
    /// does not fit is lost ([`Harness::fifo_lost_bytes`]), and the bridge gets
    /// the FIFO's contents when the CPU runs again.
    pub fn stall(&mut self, us: u64) {
        let end = self.now + us;
        let mut rx = Vec::new();
        self.sim.take_output(end, &mut rx);
        let kept = rx.len().min(UART_FIFO_BYTES);
        self.fifo_lost_bytes += (rx.len() - kept) as u64;
        self.stalls.0 += 1;
        self.stalls.1 += us;
        self.now = end;
        self.deliver(&rx[..kept]);
    }

    fn deliver(&mut self, rx: &[u8]) {
        if rx.is_empty() {
            return;
        }
        self.rx_bytes += rx.len() as u64;
        if let Some(t) = self.trace.as_mut() {
            crate::trace::record_rx(t, self.now, rx);
        }
        // The chip's way: the UART driver writes into the bridge's receive
        // space (`rx_buffer` + `received`).
        let mut rest: &[u8] = rx;
        while !rest.is_empty() {
            let space = self.station.rx_buffer();
            let n = space.len().min(rest.len());
            space[..n].copy_from_slice(&rest[..n]);
            self.station.received(self.now, n);
            rest = &rest[n..];
        }
    }

    /// As [`Harness::run_until`], calling `after_pass(station, sim, now)` at
    /// the end of every pass of the loop, where the chip's station task does
    /// its other work; it returns for how long that work stops the CPU (0: not
    /// at all), which is then [`Harness::stall`]ed. (`sim` is there for checks:
    /// what the BMS has on its way.)
    ///
    /// With [`Harness::finish_at_end`], what the station wants done at
    /// `end_us` itself is done before it returns (up to its next wait), so a
    /// loop that steps other parts at `end_us` sees what the station did then.
    pub fn run_until_hooked(
        &mut self,
        end_us: u64,
        after_pass: &mut dyn FnMut(&mut Station, &SimBms, u64) -> u64,
    ) {
        let mut rx = Vec::new();
        // Past the end (a request's wire time, a stall): done; at it: up to
        // the station's next wait when `finish_at_end`.
        while self.now < end_us || (self.finish_at_end && self.now == end_us) {
            let at_end = self.now >= end_us;
            let action = self.station.poll(self.now);
            match action {
                Action::Log(item) => {
                    self.logged(item);
                    continue;
                }
                Action::Can(f) => {
                    if self.can.attached {
                        self.can.outbox.push((self.now, f));
                        self.station.can_sent(self.now, TxResult::Sent);
                    } else {
                        self.station.can_sent(self.now, TxResult::Failed);
                    }
                    continue;
                }
                Action::Wifi(req) => {
                    // No radio in virtual time.
                    self.station.wifi_unavailable(self.now, &req);
                    continue;
                }
                Action::CanRecover => {
                    let ok = self.can.bus_off_until.is_none_or(|u| self.now >= u);
                    if ok {
                        self.can.bus_off_until = None;
                    }
                    self.station.can_recovered(self.now, ok);
                    continue;
                }
                Action::Flash(op) => {
                    use tinybms_firmware::update::transfer::Op;
                    let layout = self.station.ota().layout().copied();
                    let bytes = self.station.program_bytes().to_vec();
                    let ok = self.ota.as_mut().is_some_and(|f| {
                        tinybms_firmware::update::flash::run(f, layout.as_ref(), op, &bytes)
                    });
                    let (erase, program, otadata) = self.flash_stall_us;
                    let stall = match op {
                        Op::Erase(_) => erase,
                        Op::Program(_) => program,
                        Op::Otadata(_) => otadata,
                    };
                    self.flash_ops
                        .push((self.now, tinybms_firmware::station::ota::op_name(&op)));
                    self.station.flashed(self.now, ok);
                    self.stall(stall);
                    self.drain();
                    continue;
                }
                Action::History(op) => {
                    use tinybms_firmware::history::ring::Op;
                    let ok = self
                        .ota
                        .as_mut()
                        .is_some_and(|f| tinybms_firmware::history::log::run(f, op));
                    let (erase, program, _) = self.flash_stall_us;
                    let (stall, name) = match op {
                        Op::Erase(_) => (erase, "history erase"),
                        Op::Program(..) => (program, "history program"),
                    };
                    self.flash_ops.push((self.now, name));
                    self.station.history_done(ok);
                    self.stall(stall);
                    self.drain();
                    continue;
                }
                Action::HistoryRead(at, len) => {
                    use tinybms_firmware::update::flash::OtaFlash;
                    let mut b = vec![0u8; usize::from(len)];
                    let ok = self.ota.as_mut().is_some_and(|f| f.read(at, &mut b));
                    self.station.history_read(ok.then_some(&b[..]));
                    continue;
                }
                Action::Restart => {
                    // The chip restarts into the update: this station's run
                    // ends (the clock goes on to the end).
                    if !self.restart_requested {
                        self.restarted_at = Some(self.now);
                    }
                    self.restart_requested = true;
                    self.now = self.now.max(end_us);
                    break;
                }
                Action::Save => {
                    let (result, stall) = match self.saver.as_mut() {
                        Some(save) => save(self.station.record(), &self.sim),
                        None => (Err(StoreError::Partition), 0),
                    };
                    self.station.saved(result);
                    if stall > 0 {
                        self.stall(stall);
                    }
                    self.drain();
                    continue;
                }
                Action::Transmit => {
                    let bytes = self.station.transmit_bytes().to_vec();
                    if let Some(t) = self.trace.as_mut() {
                        let mut tx = tinybms_firmware::Transmit::new();
                        let _ = tx.extend_from_slice(&bytes);
                        crate::trace::record_poll(
                            t,
                            self.now,
                            &tinybms_firmware::bridge::Action::Transmit(tx),
                        );
                    }
                    self.count_request(&bytes);
                    if let Some(log) = self.tx_log.as_mut() {
                        log.push((self.now, bytes.clone()));
                    }
                    self.sim.host_send(self.now, &bytes);
                    self.tx_bytes += bytes.len() as u64;
                    // write + flush: the task resumes when the last byte left.
                    let wire = BYTE_TIME_US * bytes.len() as u64;
                    self.tx_busy_us += wire;
                    self.now += wire;
                }
                Action::WaitUntil(t) => {
                    if at_end {
                        break;
                    }
                    if let Some(tr) = self.trace.as_mut() {
                        crate::trace::record_poll(
                            tr,
                            self.now,
                            &tinybms_firmware::bridge::Action::WaitUntil(t),
                        );
                    }
                    let t = t.clamp(self.now, end_us);
                    let wake = match self.sim.next_output_at() {
                        Some(first) if first <= t => (first.max(self.now) + RX_CHUNK_US).min(t),
                        _ => t,
                    };
                    // Always make progress, even on a deadline equal to now.
                    self.now = wake.max(self.now + 1).min(end_us.max(self.now + 1));
                    rx.clear();
                    self.sim.take_output(self.now, &mut rx);
                    self.deliver(&rx);
                }
            }
            self.drain();
            let stall = after_pass(&mut self.station, &self.sim, self.now)
                + std::mem::take(&mut self.port_busy_us);
            if stall > 0 {
                self.stall(stall);
                self.drain();
            }
        }
        self.sim.advance(self.now);
    }

    /// Something the station logged.
    fn logged(&mut self, item: Logged) {
        match item {
            Logged::Bridge(report) => {
                let line = LogLine {
                    at_us: self.now,
                    level: report.level(),
                    report,
                };
                if self.echo {
                    println!("{line}");
                }
                self.check_report(&line);
                if self.retain {
                    self.log.push(line);
                }
            }
            other => {
                if self.echo {
                    let mut l = tinybms_firmware::text::Line::new();
                    self.station.log_text(&other, &mut l);
                    println!("{:>10.3}s {}", self.now as f64 / 1e6, l.as_str());
                }
                if self.retain {
                    self.other_log.push((self.now, other));
                }
            }
        }
    }

    fn count_request(&mut self, bytes: &[u8]) {
        use protocol_core::request::Request;
        let first = match Request::parse(bytes) {
            Ok(Request::ReadNewestEvents | Request::ReadAllEvents) => Some(200),
            Ok(Request::ReadRegisters { start, .. }) => Some(start),
            Ok(Request::ReadIndividual(a)) => a.first().copied(),
            _ => None,
        };
        match first {
            Some(100) => self.stats_reads += 1,
            Some(200) => self.event_reads += 1,
            _ => {}
        }
    }

    fn drain(&mut self) {
        let t = self.station.bridge().telemetry();
        if t.snapshot_seq != self.seen_seq {
            self.seen_seq = t.snapshot_seq;
            if let (Some(s), Some(at)) = (&t.snapshot, t.snapshot_at) {
                if self.retain {
                    self.published.push((at, s.clone()));
                }
                self.live_latencies.push(u64::from(t.live.span_us));
            }
            self.check_snapshot();
        }
        self.check_blocks();
        if let Some(port) = self.host_port.as_mut() {
            self.port_busy_us += port.pump(self.now, &mut self.station);
        }
        if let Some(lines) = self.host_lines.as_mut() {
            let mut buf = [0u8; tinybms_firmware::host_link::OUT_LINE_MAX];
            while let Some(n) = self.station.next_host_line(self.now, &mut buf) {
                let text = String::from_utf8_lossy(&buf[..n]);
                lines.push(text.trim_end_matches('\n').to_string());
            }
        }
    }

    fn check_report(&mut self, line: &LogLine) {
        let Some(soak) = self.soak.as_mut() else {
            return;
        };
        soak.lines += 1;
        if line.level == Level::Warn {
            soak.warn_lines += 1;
        }
        match &line.report {
            Report::Offline { .. } => soak.offline_transitions += 1,
            Report::Ready { .. } => {
                soak.ready_at.get_or_insert(line.at_us);
                soak.last_publish.get_or_insert(line.at_us);
            }
            Report::NewEvent(e) => {
                *soak
                    .events_reported
                    .entry((e.timestamp_s, e.id.raw()))
                    .or_default() += 1;
            }
            Report::EventHistory { count, newest } if soak.history.is_none() => {
                soak.history = Some((line.at_us, *count, *newest));
            }
            Report::Write { setting, outcome } | Report::WriteFollowUp { setting, outcome } => {
                if matches!(line.report, Report::WriteFollowUp { .. }) {
                    soak.follow_ups += 1;
                }
                *soak.outcomes.entry(outcome.name()).or_default() += 1;
                let holds = holds(&self.sim, setting);
                // 323/328 read 0xFFFF whether or not a write was applied: a
                // failure cannot be judged from the register file.
                let judged = !setting.id.reads_back_marker();
                match outcome {
                    WriteOutcome::Verified | WriteOutcome::Unchanged if !holds => {
                        soak.false_successes += 1;
                        soak.example(format!(
                            "{} at {} µs but the BMS holds {:04X}",
                            line.report,
                            line.at_us,
                            self.sim.register(setting.id.address())
                        ));
                    }
                    WriteOutcome::Failed(_) | WriteOutcome::Nacked(_) if holds && judged => {
                        soak.false_failures += 1;
                    }
                    _ => {}
                }
            }
            _ => {}
        }
    }

    fn check_snapshot(&mut self) {
        let Some(soak) = self.soak.as_mut() else {
            return;
        };
        let t = self.station.bridge().telemetry();
        let (Some(block), Some(at)) = (&t.live_registers, t.snapshot_at) else {
            return;
        };
        soak.published += 1;
        soak.blocks_checked += 1;
        if t.live.flagged.is_some() {
            soak.flagged += 1;
        }
        if let Some(last) = soak.last_publish {
            soak.longest_gap_us = soak.longest_gap_us.max(at.saturating_sub(last));
        }
        soak.last_publish = Some(at);
        if let Err(e) = truth::check_registers(block, self.sim.recent_reads()) {
            if std::env::var_os("TINYBMS_DEBUG").is_some() {
                for r in self.sim.recent_reads().iter().rev().take(60) {
                    eprintln!("DBG {} {:?} {:?}", r.at_us, r.option, r.block);
                }
                eprintln!("DBG published {block:?}");
            }
            let what = format!("snapshot at {at} µs ({} pieces): {e}", t.live.pieces);
            soak.wrong(what);
        }
    }

    fn check_blocks(&mut self) {
        let Some(soak) = self.soak.as_mut() else {
            return;
        };
        let t = self.station.bridge().telemetry();
        let reads = self.sim.recent_reads();
        if t.settings != soak.last_settings {
            let previous = std::mem::replace(&mut soak.last_settings, t.settings.clone());
            if let Some(b) = &t.settings {
                soak.blocks_checked += 1;
                // Values kept since the last check were judged then (see
                // `truth::check_changed`: a write's read-back patches one).
                if let Err(e) = truth::check_changed(b, previous.as_ref(), reads) {
                    soak.wrong(format!("settings at {} µs: {e}", self.now));
                }
            }
        }
        if t.statistics_registers != soak.last_stats {
            soak.last_stats = t.statistics_registers.clone();
            if let Some(b) = &t.statistics_registers {
                soak.blocks_checked += 1;
                if let Err(e) = truth::check_registers(b, reads) {
                    soak.wrong(format!("statistics at {} µs: {e}", self.now));
                }
            }
        }
        for (option, now) in [
            (SettingsOption::Min, &t.limits_min),
            (SettingsOption::Max, &t.limits_max),
        ] {
            let last = if option == SettingsOption::Min {
                &mut soak.last_limits.0
            } else {
                &mut soak.last_limits.1
            };
            if now != last {
                *last = now.clone();
                if let Some(b) = now {
                    soak.blocks_checked += 1;
                    if let Err(e) = truth::check_table(b, option, reads) {
                        soak.wrong(format!("limits at {} µs: {e}", self.now));
                    }
                }
            }
        }
        if t.version != soak.last_version {
            soak.last_version = t.version;
            if let Some(v) = t.version {
                soak.blocks_checked += 1;
                let regs: heapless::Vec<u16, 127> =
                    (500..=509).map(|a| self.sim.register(a)).collect();
                let truth = VersionInfo::from_registers(&RegisterBlock {
                    start: 500,
                    values: regs,
                });
                if truth != Ok(v) {
                    soak.wrong(format!("version at {} µs: {v:?}", self.now));
                }
            }
        }
    }

    /// The longest time without a snapshot so far, counting the time since the
    /// last one (µs), once the bridge was ready.
    pub fn longest_gap_us(&self) -> u64 {
        match &self.soak {
            Some(s) => {
                let open = s
                    .last_publish
                    .map(|t| self.now.saturating_sub(t))
                    .unwrap_or(0);
                s.longest_gap_us.max(open)
            }
            None => 0,
        }
    }

    /// Log lines whose report matches `f`.
    pub fn reports<'a>(
        &'a self,
        f: impl Fn(&Report) -> bool + 'a,
    ) -> impl Iterator<Item = &'a LogLine> + 'a {
        self.log.iter().filter(move |l| f(&l.report))
    }

    /// (min, mean, max, count) of [`Harness::live_latencies`], µs.
    pub fn live_latency(&self) -> Option<(u64, u64, u64, usize)> {
        let l = &self.live_latencies;
        let n = l.len();
        (n > 0).then(|| {
            let sum: u64 = l.iter().sum();
            (
                l.iter().copied().min().unwrap_or(0),
                sum / n as u64,
                l.iter().copied().max().unwrap_or(0),
                n,
            )
        })
    }

    /// The whole log as text, one line per report.
    pub fn log_text(&self) -> String {
        self.log.iter().map(|l| format!("{l}\n")).collect()
    }
}

/// True when the simulated BMS holds the value of `s` now (0xFFFF counts for
/// 323/328, as for the bridge).
fn holds(sim: &SimBms, s: &Setting) -> bool {
    let a = s.id.address();
    let second = (s.id.register_count() == 2).then(|| sim.register(a + 1));
    s.matches_readback(sim.register(a), second)
}

/// The benchmark's trace ([`crate::trace`]): runs the default bridge against a clean simulated BMS for `duration_us` and
/// returns the trace (None if no live reply was ever sent).
pub fn record_clean(seed: u64, duration_us: u64) -> Option<Vec<u8>> {
    let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), seed);
    let mut h = Harness::new(sim);
    h.retain = false;
    h.trace = Some(Vec::new());
    h.run_until(duration_us);
    let body = h.trace.take().unwrap_or_default();
    let rx = crate::trace::received(&body);
    let reply = crate::trace::find_live_reply(&rx)?.to_vec();
    let mut out = Vec::with_capacity(body.len() + 128);
    out.extend_from_slice(crate::trace::MAGIC);
    out.push(reply.len() as u8);
    out.extend_from_slice(&reply);
    out.extend_from_slice(&body);
    out.push(b'E');
    Some(out)
}
