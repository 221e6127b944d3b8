//! The host link: JSON Lines over the chip's USB (USB-Serial-JTAG, CDC-ACM) to a
//! computer. The protocol is `PROTOCOL.md` in this folder
//! (`firmware/src/host_link/PROTOCOL.md`); this module is its sans-IO
//! implementation, like the bridge:
//!
//! * bytes from the host go in through [`HostLink::handle_rx`]: a bounded
//!   [`assembler::LineAssembler`] (256-byte lines, an over-long line is discarded up to
//!   the next newline), [`command::parse`], then dispatch to the [`Bridge`]
//!   through its public interface only (`submit`, `telemetry`, `link_stats`,
//!   `piece_registers`);
//! * every bridge [`Report`] goes in through [`HostLink::on_report`]: write
//!   outcomes come back as `outcome` lines carrying the `req` of the `set` that
//!   asked for them, new BMS events as `event` lines;
//! * UART bytes go in through [`HostLink::on_uart_tx`] / [`HostLink::on_uart_rx`]
//!   (`raw` lines while capture is on);
//! * time goes in through [`HostLink::poll`] (the telemetry stream), which returns
//!   when it wants to be called again;
//! * output comes out one line at a time from [`HostLink::next_line`], encoded
//!   only then (listings such as `get settings` are generated lazily, one line per
//!   call), so the queue holds small items instead of text; [`queue::hand_off`]
//!   puts each line whole into the queue to the port's writer.
//!
//! Nothing here waits: a missing or slow host only fills a bounded queue. Streamed
//! telemetry and `raw` lines are the first to go (counted in `dropped_lines`);
//! answers, outcomes and events have a queue of their own. A command that fails
//! to parse or validate sends nothing to the BMS. With
//! [`HostLinkConfig::read_only`], `set`, `reset` and `clear` are refused.
//!
//! No allocation, no panic on any input (the crate denies `unwrap`, `expect`,
//! `panic` and indexing); property tests and a fuzz target feed it arbitrary bytes.

pub mod assembler;
pub mod command;
mod configure;
mod dispatch;
pub mod encode;
mod output;
mod update;
pub use update::{rolled_back_text, update_view, RolledBack, UpdateView};
pub mod panic;
pub mod queue;
pub mod schema;
pub mod wire;
pub mod writer;

use heapless::{Deque, String, Vec};
use protocol_core::settings::Setting;

use crate::bms::timing::MAX_SETTINGS_GROUP;
use crate::bridge::report::Report;
use crate::bridge::Bridge;
use crate::config::state::ConfigState;
use crate::config::store::{Saved, StoreError};
use crate::config::Config;
use crate::improv::Improv;
use crate::Instant;
use assembler::{LineAssembler, Piece};
use output::{Dir, Out};

pub use configure::{ConfigDone, PENDING_CONFIG};

/// Protocol version in the `hello` line.
pub const PROTOCOL_VERSION: u32 = 1;

/// Buffer size [`HostLink::next_line`] needs: the longest line it writes (a
/// `telemetry` line with 16 cells, the inverter member with what it told,
/// why each limit is what it is, the heartbeat and the doctor's verdicts,
/// every value at its widest, is 1684 bytes), `\n` included. A line that
/// does not fit a smaller buffer is dropped and counted.
pub const OUT_LINE_MAX: usize = 2112;

/// Lines (or listings) waiting for the host: answers, outcomes and events.
pub const QUEUE: usize = 32;

/// Answers to host commands (`accepted`, `error`, `get` results) are queued only
/// while fewer than this many lines wait: the rest of [`QUEUE`] is kept for
/// what the bridge reports (outcomes, events, resets, clears), so a host that
/// sends without reading loses its own answers, never an outcome. A command that
/// arrives while this many lines wait is not carried out at all (its answer could
/// not be queued): nothing is ever done without its `accepted` line.
pub const ANSWERS_MAX: usize = QUEUE / 2;

/// `raw` lines waiting for the host (capture), [`RAW_CHUNK`] bytes each.
pub const RAW_QUEUE: usize = 8;

/// UART bytes per `raw` line.
pub const RAW_CHUNK: usize = 32;

/// Settings whose outcome is awaited (2 full groups; a `set` beyond is `busy`).
pub const PENDING_WRITES: usize = 2 * MAX_SETTINGS_GROUP;

/// Resets and clears whose result is awaited.
pub const PENDING_OTHERS: usize = 4;

/// Longest offending name echoed in an error's detail (longer ones are cut).
pub const SUBJECT_MAX: usize = 32;

/// The bridge's log lines waiting for the host (`log` lines); when full, the
/// oldest is dropped and counted (a host that connects sees the latest).
pub const LOG_QUEUE: usize = 4;

/// Bytes of the boot lines the host link keeps from boot (the chip shell's
/// first lines: image, CAN, host link, UART, profile — about 400 bytes), for
/// every host after its `hello`. A line that no longer fits is dropped and
/// counted in `dropped_lines`.
pub const BOOT_TEXT: usize = 768;

pub use crate::config::{HostLinkConfig, DEFAULT_STREAM_PERIOD_MS};

/// Error codes of `error` lines (PROTOCOL.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ErrorCode {
    /// The line is not a JSON object.
    MalformedJson,
    /// The line is longer than [`assembler::LINE_MAX`] bytes.
    LineTooLong,
    /// No such command.
    UnknownCommand,
    /// A member no command has, or one this command does not take.
    UnknownField,
    /// A member the command needs is missing.
    MissingField,
    /// A member has the wrong type or an invalid value.
    InvalidValue,
    /// No setting by that name.
    UnknownSetting,
    /// A value outside its range (Rev D, the BMS's own limits, the protocol's).
    OutOfRange,
    /// Host writes are switched off.
    ReadOnly,
    /// A queue is full: try again later.
    Busy,
    /// Settings and limits are not read yet (or the asked block is not).
    NotReady,
}

impl ErrorCode {
    /// The code as printed.
    pub const fn name(self) -> &'static str {
        match self {
            Self::MalformedJson => "malformed_json",
            Self::LineTooLong => "line_too_long",
            Self::UnknownCommand => "unknown_command",
            Self::UnknownField => "unknown_field",
            Self::MissingField => "missing_field",
            Self::InvalidValue => "invalid_value",
            Self::UnknownSetting => "unknown_setting",
            Self::OutOfRange => "out_of_range",
            Self::ReadOnly => "read_only",
            Self::Busy => "busy",
            Self::NotReady => "not_ready",
        }
    }
}

/// The host link's own counters (in the `link` line).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct HostLinkStats {
    /// Lines received (blank lines not counted).
    pub lines_in: u32,
    /// `error` lines queued.
    pub errors: u32,
    /// Output lines dropped: queue full, superseded streamed telemetry, or too
    /// long for the caller's buffer.
    pub dropped_lines: u32,
}

/// What the station shows the host link of the CAN capture.
#[derive(Debug, Clone, Copy, Default)]
struct CanFeed {
    span: Option<(u32, u32)>,
    protocol: &'static str,
    entry: Option<(u32, Option<crate::inverter::capture::Entry>)>,
}

/// The host link. See the module documentation.
#[derive(Debug, Clone)]
pub struct HostLink {
    lines: LineAssembler,
    /// When the last byte from the host came (a half-received Improv packet
    /// older than [`IMPROV_GAP`] is dropped).
    last_rx: Instant,
    /// Improv Wi-Fi on the same port (the browser installer).
    improv: Improv,
    s: State,
}

/// Longest pause inside an Improv packet, µs: a host sends one in a single
/// write, so after this pause its start is dropped (and said) instead of
/// swallowing the lines that follow as its bytes.
pub const IMPROV_GAP: Instant = 500 * crate::MS;

#[derive(Debug, Clone)]
struct State {
    config: HostLinkConfig,
    stream_period_ms: u32,
    next_stream: Option<Instant>,
    stream_due: bool,
    /// Packs in parallel: the battery as the inverter output sees it, and the
    /// lines of it still to send after this period's telemetry (the battery
    /// line, then one per pack).
    battery: Option<crate::inverter::packs::BatteryView>,
    battery_lines: usize,
    /// The inverter output now (each telemetry line says it), when built in.
    inverter: Option<encode::InverterState>,
    /// The CAN capture as the station shows it (`get can`).
    can: CanFeed,
    /// A host said the date (`set_time`), for the station to take.
    time: Option<u32>,
    /// Why `get history` cannot be answered (`None`: it can).
    history: Option<&'static str>,
    /// The history listing's next item, as the station read it
    /// (`Some(None)`: the listing is over).
    history_item: Option<Option<crate::history::log::Listed>>,
    /// Configuration fields that wait for a restart.
    restart_pending: u32,
    /// Where the MQTT connection stands (`hello`), once the session said.
    mqtt: Option<&'static str>,
    /// The radio's start (`hello`, images with Wi-Fi), once the shell said.
    radio: Option<crate::wifi::Radio>,
    /// The Wi-Fi link (`hello`, images with Wi-Fi).
    wifi: crate::improv::WifiLink,
    capture: bool,
    /// The updates' side: the slot, its trial, the keys trusted, a rollback
    /// (`hello`; the rollback in `update` lines too).
    update: update::UpdateView,
    /// The update port on the network: `hello` and the `update_…` commands
    /// only ([`HostLink::update_port`]).
    update_only: bool,
    queue: Deque<Out, QUEUE>,
    raw: Deque<(Dir, Vec<u8, RAW_CHUNK>), RAW_QUEUE>,
    logs: Deque<(crate::Level, String<{ crate::text::LINE_MAX }>), LOG_QUEUE>,
    /// The boot lines, each as its level (`I`, `W`) and text, ended by `\n`.
    boot: String<BOOT_TEXT>,
    /// Where the boot lines' replay after a `hello` stands (a byte offset
    /// into `boot`), while it runs.
    boot_replay: Option<usize>,
    writes: Vec<(Option<u32>, Setting), PENDING_WRITES>,
    follow_ups: Vec<(Option<u32>, Setting), PENDING_WRITES>,
    resets: Deque<Option<u32>, PENDING_OTHERS>,
    clears: Vec<(Option<u32>, u8), PENDING_OTHERS>,
    /// Changes of the configuration waiting for the save (their `config_done`).
    config_saves: Vec<ConfigDone, PENDING_CONFIG>,
    stats: HostLinkStats,
}

fn ms(t: u32) -> Instant {
    Instant::from(t) * crate::MS
}

fn subject(s: &str) -> String<SUBJECT_MAX> {
    let mut out = String::new();
    for c in s.chars() {
        if out.push(c).is_err() {
            break;
        }
    }
    out
}

/// The configured stream period, within the range a `stream` command may ask
/// for (0: off).
fn configured_period(config: &HostLinkConfig) -> u32 {
    match config.stream_period_ms {
        0 => 0,
        p => p.clamp(command::STREAM_PERIOD_MS.0, command::STREAM_PERIOD_MS.1),
    }
}

impl HostLink {
    /// A host link at time `now`. Nothing is queued until [`HostLink::connected`]
    /// or a command.
    pub fn new(config: HostLinkConfig, now: Instant) -> Self {
        let period = configured_period(&config);
        let mut link = Self {
            lines: LineAssembler::new(),
            last_rx: now,
            improv: Improv::new(&crate::identity::Identity {
                firmware: config.firmware,
                chip: config.chip,
                board: config.board,
                features: config.features,
            }),
            s: State {
                config,
                stream_period_ms: 0,
                next_stream: None,
                stream_due: false,
                battery: None,
                battery_lines: 0,
                inverter: None,
                can: CanFeed::default(),
                time: None,
                history: Some("this bridge keeps no history"),
                history_item: None,
                restart_pending: 0,
                mqtt: None,
                radio: None,
                wifi: crate::improv::WifiLink::Off,
                capture: false,
                update: update::UpdateView::default(),
                update_only: false,
                queue: Deque::new(),
                raw: Deque::new(),
                logs: Deque::new(),
                boot: String::new(),
                boot_replay: None,
                writes: Vec::new(),
                follow_ups: Vec::new(),
                resets: Deque::new(),
                clears: Vec::new(),
                config_saves: Vec::new(),
                stats: HostLinkStats::default(),
            },
        };
        link.s.set_stream(now, period);
        link
    }

    /// The host opened the port (or may have): a `hello` line goes first.
    pub fn connected(&mut self, now: Instant) {
        self.s.new_session(now);
        if self.s.queue.push_front(Out::Hello(None)).is_err() {
            self.s.stats.dropped_lines = self.s.stats.dropped_lines.wrapping_add(1);
        }
    }

    /// The link of the update port on the network (`update::TCP_PORT`): the
    /// same lines, but only `hello` and the `update_…` commands are taken,
    /// and nothing is streamed.
    pub fn update_port(config: HostLinkConfig, now: Instant) -> Self {
        let mut link = Self::new(
            HostLinkConfig {
                stream_period_ms: 0,
                ..config
            },
            now,
        );
        link.s.update_only = true;
        link
    }

    /// What `hello` says of updates, and the rollback of the `update` lines
    /// (the station says it at boot and when the owner's key changes).
    pub fn set_update(&mut self, view: UpdateView) {
        self.s.update = view;
    }

    /// Improv Wi-Fi on this port.
    pub fn improv(&self) -> &Improv {
        &self.improv
    }

    /// Improv Wi-Fi on this port, to hand it what the Wi-Fi side did.
    pub fn improv_mut(&mut self) -> &mut Improv {
        &mut self.improv
    }

    /// The Wi-Fi link changed (Improv answers by it, `hello` says it).
    pub fn wifi_link(&mut self, link: crate::improv::WifiLink) {
        self.improv.wifi_link(link);
        self.s.wifi = link;
    }

    /// Counters.
    pub fn stats(&self) -> HostLinkStats {
        self.s.stats
    }

    /// Current stream period, ms (0: off).
    pub fn stream_period_ms(&self) -> u32 {
        self.s.stream_period_ms
    }

    /// The port dropped `n` whole lines (a host that does not read).
    pub fn lines_dropped(&mut self, n: u32) {
        self.s.stats.dropped_lines = self.s.stats.dropped_lines.wrapping_add(n);
    }

    /// True while capture (`raw` lines) is on.
    pub fn capturing(&self) -> bool {
        self.s.capture
    }

    /// True when lines are waiting for [`HostLink::next_line`].
    pub fn has_output(&self) -> bool {
        self.improv.has_output()
            || !self.s.queue.is_empty()
            || self.s.boot_replay.is_some()
            || self.s.stream_due
            || !self.s.raw.is_empty()
            || !self.s.logs.is_empty()
    }

    /// One of the bridge's own log lines (the words of [`crate::text`]), for
    /// the host as a `log` line: the log on the same cable as the host link.
    /// Longer than [`crate::text::LINE_MAX`] bytes: cut.
    pub fn log(&mut self, level: crate::Level, text: &str) {
        let mut t = String::new();
        for c in text.chars() {
            if t.push(c).is_err() {
                break;
            }
        }
        if self.s.logs.is_full() {
            self.s.logs.pop_front();
            self.s.stats.dropped_lines = self.s.stats.dropped_lines.wrapping_add(1);
        }
        let _ = self.s.logs.push_back((level, t));
    }

    /// A line the bridge wrote at boot (the words of
    /// [`crate::text::Boot`]): kept from boot and sent to every host right
    /// after its `hello` as a `log` line with `"boot":true` (the latest
    /// [`LOG_QUEUE`] log lines alone would have lost it by then). A newline
    /// in it ends it.
    pub fn boot_line(&mut self, level: crate::Level, text: &str) {
        let text = text.split('\n').next().unwrap_or("");
        let mark = match level {
            crate::Level::Info => 'I',
            crate::Level::Warn => 'W',
        };
        let b = &mut self.s.boot;
        if b.len() + text.len() + 2 > BOOT_TEXT {
            self.s.stats.dropped_lines = self.s.stats.dropped_lines.wrapping_add(1);
            return;
        }
        let _ = b.push(mark);
        let _ = b.push_str(text);
        let _ = b.push('\n');
    }

    /// Bytes from the host at `now`, in any chunks. Complete lines are parsed and
    /// dispatched at once: to `bridge`, or for the bridge's own configuration to
    /// `config`.
    pub fn handle_rx(
        &mut self,
        now: Instant,
        bytes: &[u8],
        bridge: &mut Bridge,
        config: &mut ConfigState,
        ota: &mut crate::update::Ota,
    ) {
        if self.lines.is_improv()
            && now.saturating_sub(self.last_rx) > IMPROV_GAP
            && self.lines.drop_partial()
        {
            self.improv.on_packet(now, b"IMPROV");
        }
        self.last_rx = now;
        let mut rest = bytes;
        while !rest.is_empty() {
            let (used, piece) = self.lines.push(rest);
            match piece {
                Some(Piece::Improv(p)) => self.improv.on_packet(now, p),
                Some(Piece::Line(l)) => {
                    if l.iter().all(u8::is_ascii_whitespace) {
                        // Blank lines (keep-alives) are ignored.
                    } else {
                        self.s.stats.lines_in = self.s.stats.lines_in.wrapping_add(1);
                        self.s.dispatch(now, l, bridge, config, ota);
                    }
                }
                Some(Piece::TooLong) => {
                    self.s.stats.lines_in = self.s.stats.lines_in.wrapping_add(1);
                    self.s.error(
                        None,
                        ErrorCode::LineTooLong,
                        "longer than 256 bytes: discarded up to the next newline",
                        "",
                    );
                }
                None => {}
            }
            rest = rest.get(used.max(1)..).unwrap_or(&[]);
        }
    }

    /// The running configuration changed (a `set_config`, a `reset_config`, the
    /// BOOT button): read-only and the stream period follow it at once.
    pub fn apply_config(&mut self, now: Instant, running: &Config) {
        self.s.apply_config(now, running);
    }

    /// The save of the configuration is done (`Err` once the last attempt
    /// failed): every change waiting for it gets its `config_done` line.
    pub fn on_config_saved(&mut self, result: Result<Saved, StoreError>) {
        for mut done in core::mem::take(&mut self.s.config_saves) {
            done.saved = Some(result);
            self.s.report(Out::ConfigDone(done));
        }
    }

    /// Every report of the bridge, in order (the shell hands each one here as
    /// well as to its log).
    pub fn on_report(&mut self, report: &Report) {
        self.s.on_report(report);
    }

    /// Packs in parallel: the battery as the inverter output sees it now
    /// (`Inverter::battery_view`); streamed after each telemetry line as a
    /// `battery` line and a `pack` line per pack. `None` for a bridge alone.
    pub fn on_battery(&mut self, view: Option<crate::inverter::packs::BatteryView>) {
        self.s.battery = view;
    }

    /// The inverter output now: what it tells the inverter, the CAN state,
    /// whether the inverter is heard (`None`: no CAN output built in). Every
    /// `telemetry` line carries it.
    pub fn on_inverter(&mut self, state: Option<encode::InverterState>) {
        self.s.inverter = state;
    }

    /// The CAN capture's sequence numbers held (`first..end`; `None`: no CAN
    /// output built in) and the protocol of its frames, before each
    /// [`HostLink::next_line`].
    pub fn on_can_span(&mut self, span: Option<(u32, u32)>, protocol: &'static str) {
        self.s.can.span = span;
        self.s.can.protocol = protocol;
    }

    /// Whether the bridge keeps a history (`Err`: why not), before each
    /// [`HostLink::next_line`].
    pub fn on_history(&mut self, problem: Option<&'static str>) {
        self.s.history = problem;
    }

    /// The date a host said (`set_time`, Unix seconds), once.
    pub fn take_time(&mut self) -> Option<u32> {
        self.s.time.take()
    }

    /// A `get history` listing waits to be started: true once (the station
    /// then starts reading the history).
    pub fn history_start(&mut self) -> bool {
        match self.s.queue.front_mut() {
            Some(output::Out::History { started, .. }) if !*started => {
                *started = true;
                true
            }
            _ => false,
        }
    }

    /// A `get history` listing waits for its next item.
    pub fn history_wanted(&self) -> bool {
        matches!(self.s.queue.front(), Some(output::Out::History { .. }))
            && self.s.history_item.is_none()
    }

    /// The listing's next item (`None`: the listing is over).
    pub fn on_history_item(&mut self, item: Option<crate::history::log::Listed>) {
        self.s.history_item = Some(item);
    }

    /// The capture entry a `get can` listing needs next, if one is under way.
    pub fn can_wanted(&self) -> Option<u32> {
        match self.s.queue.front() {
            Some(output::Out::Can { next, .. }) => Some(*next),
            _ => None,
        }
    }

    /// The capture entry of sequence number `seq` (`None`: no longer held),
    /// as [`HostLink::can_wanted`] asked.
    pub fn on_can_entry(&mut self, seq: u32, entry: Option<crate::inverter::capture::Entry>) {
        self.s.can.entry = Some((seq, entry));
    }

    /// How many configuration fields changed that apply at the next restart
    /// (each `telemetry` line says it).
    pub fn on_restart_pending(&mut self, n: u32) {
        self.s.restart_pending = n;
    }

    /// Where the MQTT connection stands now, as `hello` says it (the key of
    /// the station's `mqtt::MqttState`).
    pub fn on_mqtt(&mut self, key: &'static str) {
        self.s.mqtt = Some(key);
    }

    /// Where the radio's start stands now, as `hello` says it.
    pub fn on_radio(&mut self, radio: crate::wifi::Radio) {
        self.s.radio = Some(radio);
    }

    /// Bytes sent to the BMS (for capture).
    pub fn on_uart_tx(&mut self, bytes: &[u8]) {
        self.s.capture_bytes(Dir::Tx, bytes);
    }

    /// Bytes received from the BMS (for capture).
    pub fn on_uart_rx(&mut self, bytes: &[u8]) {
        self.s.capture_bytes(Dir::Rx, bytes);
    }

    /// Timers: queues streamed telemetry when due. Returns when to call again
    /// (`Instant::MAX` while streaming is off).
    pub fn poll(&mut self, now: Instant, _bridge: &Bridge) -> Instant {
        let s = &mut self.s;
        match s.next_stream {
            Some(t) if now >= t => {
                if s.stream_due {
                    // The previous one never left: superseded.
                    s.stats.dropped_lines = s.stats.dropped_lines.wrapping_add(1);
                }
                s.stream_due = true;
                let period = ms(s.stream_period_ms);
                let next = t.saturating_add(period);
                let next = if next <= now {
                    now.saturating_add(period)
                } else {
                    next
                };
                s.next_stream = Some(next);
                next
            }
            Some(t) => t,
            None => Instant::MAX,
        }
    }
}

impl State {
    /// Queues an answer to a host command.
    fn push(&mut self, item: Out) {
        if self.queue.len() >= ANSWERS_MAX {
            self.stats.dropped_lines = self.stats.dropped_lines.wrapping_add(1);
            return;
        }
        self.report(item);
    }

    /// Queues a line about something the bridge reported.
    fn report(&mut self, item: Out) {
        if self.queue.push_back(item).is_err() {
            self.stats.dropped_lines = self.stats.dropped_lines.wrapping_add(1);
        }
    }

    fn error(&mut self, req: Option<u32>, code: ErrorCode, detail: &'static str, subj: &str) {
        self.stats.errors = self.stats.errors.wrapping_add(1);
        self.push(Out::Error {
            req,
            code,
            detail,
            subject: subject(subj),
        });
    }

    /// A host (re)connected or said `hello`: whatever an earlier host left
    /// behind — a capture left on, a stream period it asked for — ends, so a
    /// tool that was killed or unplugged leaves no trace in the next session.
    fn new_session(&mut self, now: Instant) {
        self.capture = false;
        self.raw.clear();
        self.set_stream(now, configured_period(&self.config));
    }

    /// Streams telemetry every `period` ms from `now` (0: off).
    fn set_stream(&mut self, now: Instant, period: u32) {
        self.stream_period_ms = period;
        self.next_stream = (period > 0).then(|| now.saturating_add(ms(period)));
    }

    fn capture_bytes(&mut self, dir: Dir, bytes: &[u8]) {
        if !self.capture {
            return;
        }
        for chunk in bytes.chunks(RAW_CHUNK) {
            let mut v = Vec::new();
            let _ = v.extend_from_slice(chunk);
            if self.raw.push_back((dir, v)).is_err() {
                self.stats.dropped_lines = self.stats.dropped_lines.wrapping_add(1);
            }
        }
    }

    /// Read-only and the stream period from the running configuration.
    fn apply_config(&mut self, now: Instant, running: &Config) {
        self.config.read_only = running.read_only;
        self.config.freshness = running.freshness();
        // The update port streams nothing.
        if !self.update_only && self.config.stream_period_ms != running.stream_period_ms {
            self.config.stream_period_ms = running.stream_period_ms;
            self.set_stream(now, configured_period(&self.config));
        }
    }
}
