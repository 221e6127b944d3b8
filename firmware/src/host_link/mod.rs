//! The host link: JSON Lines over the chip's USB (USB-Serial-JTAG, CDC-ACM) to a
//! computer. The protocol is `PROTOCOL.md` in this folder
//! (`firmware/src/host_link/PROTOCOL.md`); this module is its sans-IO
//! implementation, like the bridge:
//!
//! * bytes from the host go in through [`HostLink::handle_rx`]: a bounded
//!   [`line::LineAssembler`] (256-byte lines, an over-long line is discarded up to
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

pub mod command;
pub mod encode;
pub mod line;
pub mod lines;
pub mod panic;
pub mod queue;
pub mod wire;
pub mod writer;

use heapless::{Deque, String, Vec};
use protocol_core::events::Event;
use protocol_core::settings::Setting;

use crate::bms::timing::MAX_SETTINGS_GROUP;
use crate::bridge::report::{Report, WriteOutcome};
use crate::bridge::{Bridge, Command};
use crate::config::state::{ConfigState, Outcome};
use crate::config::store::{Saved, StoreError};
use crate::config::value::{self, FieldError, Parsed};
use crate::config::{Config, FieldId, PackSettings, TEXT_MAX};
use crate::improv::Improv;
use crate::Instant;
use command::{ClearWhat, HostCommand, SetValues, What};
use line::{LineAssembler, Piece};

/// Protocol version in the `hello` line.
pub const PROTOCOL_VERSION: u32 = 1;

/// Buffer size [`HostLink::next_line`] needs: the longest line it writes (a
/// `telemetry` line with 16 cells, the inverter member and every value at its
/// widest is about 900 bytes), `\n` included. A line that does not fit a
/// smaller buffer is dropped and counted.
pub const OUT_LINE_MAX: usize = 1280;

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
    /// The line is longer than [`line::LINE_MAX`] bytes.
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

/// Direction of captured UART bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Dir {
    Tx,
    Rx,
}

/// One line (or listing) waiting to be encoded.
#[derive(Debug, Clone, PartialEq)]
enum Out {
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
}

/// What a `config_outcome` line says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ConfigAnswer {
    /// A field the record has.
    Field(FieldId, Outcome),
    /// A name no field has.
    Unknown,
    /// Text that is not a value of the field.
    Invalid(FieldId, FieldError),
}

/// What a `config_done` line says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConfigDone {
    /// Echoed request id.
    pub req: Option<u32>,
    /// Fields changed.
    pub changed: u8,
    /// The save: `None` when nothing needed saving.
    pub saved: Option<Result<Saved, StoreError>>,
    /// Fields waiting for a restart.
    pub restart_needed: u8,
}

/// `set_config`s whose `config_done` waits for the flash.
pub const PENDING_CONFIG: usize = 4;

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
    /// Where the MQTT connection stands (`hello`), once the session said.
    mqtt: Option<&'static str>,
    /// The radio's start (`hello`, images with Wi-Fi), once the shell said.
    radio: Option<crate::wifi::Radio>,
    /// The Wi-Fi link (`hello`, images with Wi-Fi).
    wifi: crate::improv::WifiLink,
    capture: bool,
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
                mqtt: None,
                radio: None,
                wifi: crate::improv::WifiLink::Off,
                capture: false,
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
                        self.s.dispatch(now, l, bridge, config);
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

    /// Encodes the next output line into `out` (at least [`OUT_LINE_MAX`] bytes),
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
    };
    encode::telemetry(
        out,
        head,
        t.snapshot.as_ref(),
        t.live.flagged.map(|c| c.name()),
        None,
    )
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
        if self.config.stream_period_ms != running.stream_period_ms {
            self.config.stream_period_ms = running.stream_period_ms;
            self.set_stream(now, configured_period(&self.config));
        }
    }

    fn dispatch(
        &mut self,
        now: Instant,
        line: &[u8],
        bridge: &mut Bridge,
        config: &mut ConfigState,
    ) {
        if self.queue.len() >= ANSWERS_MAX {
            // The host sends without reading: its answer could not be queued, so
            // the command is not carried out at all (counted as a dropped line).
            self.stats.dropped_lines = self.stats.dropped_lines.wrapping_add(1);
            return;
        }
        let parsed = match command::parse(line) {
            Ok(p) => p,
            Err(e) => return self.error(e.req, e.code, e.detail, e.subject),
        };
        let req = parsed.req;
        // The running record decides read-only (the BOOT button may have lifted it).
        self.apply_config(now, config.running());
        let writes = matches!(
            parsed.command,
            HostCommand::Set(..)
                | HostCommand::Reset
                | HostCommand::Clear(_)
                | HostCommand::SetConfig(_)
                | HostCommand::ResetConfig
        );
        if writes && self.config.read_only {
            return self.error(req, ErrorCode::ReadOnly, "host writes are switched off", "");
        }
        match parsed.command {
            HostCommand::Hello => {
                self.new_session(now);
                self.push(Out::Hello(req));
            }
            HostCommand::Get(what) => self.get(req, what, bridge),
            HostCommand::Set(values, check) => self.set(req, &values, check, bridge),
            HostCommand::Reset => {
                if self.resets.is_full() {
                    return self.error(req, ErrorCode::Busy, "resets pending", "");
                }
                if bridge.submit(Command::ResetBms).is_err() {
                    return self.error(req, ErrorCode::Busy, "command queue full", "");
                }
                let _ = self.resets.push_back(req);
                self.push(Out::Accepted(req, "reset"));
            }
            HostCommand::Clear(what) => {
                let (command, option) = match what {
                    ClearWhat::Events => (Command::ClearEvents, 1),
                    ClearWhat::Statistics => (Command::ClearStatistics, 2),
                };
                if self.clears.is_full() {
                    return self.error(req, ErrorCode::Busy, "clears pending", "");
                }
                if bridge.submit(command).is_err() {
                    return self.error(req, ErrorCode::Busy, "command queue full", "");
                }
                let _ = self.clears.push((req, option));
                self.push(Out::Accepted(req, "clear"));
            }
            HostCommand::Stream(period) => {
                self.set_stream(now, period);
                self.push(Out::Accepted(req, "stream"));
            }
            HostCommand::Capture(on) => {
                self.capture = on;
                if !on {
                    self.raw.clear();
                }
                self.push(Out::Accepted(req, "capture"));
            }
            HostCommand::SetConfig(fields) => self.set_config(now, req, &fields, bridge, config),
            HostCommand::ResetConfig => {
                if self.config_saves.is_full() || self.queue.len() + 2 > QUEUE {
                    return self.error(req, ErrorCode::Busy, "configuration changes pending", "");
                }
                let changed = config.reset().len() as u8;
                self.push(Out::Accepted(req, "reset_config"));
                self.config_changed(now, req, changed, config);
            }
        }
    }

    /// After a change of `changed` fields: the running record applied here,
    /// and the `config_done` line now (nothing to save) or after the save.
    fn config_changed(
        &mut self,
        now: Instant,
        req: Option<u32>,
        changed: u8,
        config: &ConfigState,
    ) {
        self.apply_config(now, config.running());
        let done = ConfigDone {
            req,
            changed,
            saved: None,
            restart_needed: config.restarts_pending() as u8,
        };
        if config.save_due() {
            if self.config_saves.push(done).is_err() {
                // Checked before the change: never full here.
                self.report(Out::ConfigDone(done));
            }
        } else {
            self.report(Out::ConfigDone(done));
        }
    }

    fn set_config(
        &mut self,
        now: Instant,
        req: Option<u32>,
        fields: &[(&str, serde_json_core::str::EscapedStr<'_>)],
        bridge: &Bridge,
        config: &mut ConfigState,
    ) {
        // Every line this command will write must fit: accepted, one outcome
        // per field (and one for a broken rule), done.
        if self.config_saves.is_full() || self.queue.len() + fields.len() + 3 > QUEUE {
            return self.error(req, ErrorCode::Busy, "configuration changes pending", "");
        }
        let mut parsed: Vec<(FieldId, Parsed), { command::MAX_SET_CONFIG }> = Vec::new();
        let mut answers: Vec<
            (String<SUBJECT_MAX>, Option<ConfigAnswer>),
            { command::MAX_SET_CONFIG },
        > = Vec::new();
        for (name, text) in fields {
            let answer = match FieldId::from_name(name) {
                None => Some(ConfigAnswer::Unknown),
                Some(id) => match unescape(text)
                    .map_err(|e| (id, e))
                    .and_then(|t| value::parse(id.field(), &t).map_err(|e| (id, e)))
                {
                    Ok(p) => {
                        let _ = parsed.push((id, p));
                        None
                    }
                    Err((id, e)) => Some(ConfigAnswer::Invalid(id, e)),
                },
            };
            let _ = answers.push((subject(name), answer));
        }
        self.push(Out::Accepted(req, "set_config"));
        let refused = answers.iter().any(|(_, a)| a.is_some());
        if refused {
            for (name, a) in answers {
                let outcome = match a {
                    Some(a) => a,
                    None => match FieldId::from_name(&name) {
                        Some(id) => ConfigAnswer::Field(id, Outcome::NotApplied),
                        None => ConfigAnswer::Unknown,
                    },
                };
                self.report(Out::ConfigOutcome { req, name, outcome });
            }
            return self.config_changed(now, req, 0, config);
        }
        let bms = bridge
            .telemetry()
            .settings
            .as_ref()
            .and_then(PackSettings::from_registers);
        let outcomes = config.change(&parsed, false, bms.as_ref());
        let mut changed = 0u8;
        for (id, o) in outcomes {
            if matches!(o, Outcome::Applied | Outcome::AtRestart) {
                changed = changed.saturating_add(1);
            }
            self.report(Out::ConfigOutcome {
                req,
                name: subject(id.name()),
                outcome: ConfigAnswer::Field(id, o),
            });
        }
        self.config_changed(now, req, changed, config);
    }

    fn get(&mut self, req: Option<u32>, what: What, bridge: &Bridge) {
        let t = bridge.telemetry();
        match what {
            What::Snapshot => self.push(Out::Telemetry(req)),
            What::Settings if t.settings.is_none() => {
                self.error(req, ErrorCode::NotReady, "settings not read yet", "")
            }
            What::Settings => self.push(Out::Settings { req, next: 0 }),
            What::Statistics if t.statistics.is_none() => {
                self.error(req, ErrorCode::NotReady, "statistics not read yet", "")
            }
            What::Statistics => self.push(Out::Statistics(req)),
            What::Version if t.version.is_none() => {
                self.error(req, ErrorCode::NotReady, "version not read yet", "")
            }
            What::Version => self.push(Out::Version(req)),
            What::Link => self.push(Out::Link(req)),
            What::Config => self.push(Out::Config { req, next: 0 }),
            What::Events => {
                let known = bridge.events();
                let end = known.total();
                let next = end.wrapping_sub(known.len() as u32);
                self.push(Out::Events {
                    req,
                    next,
                    end,
                    sent: 0,
                });
            }
        }
    }

    fn set(
        &mut self,
        req: Option<u32>,
        values: &SetValues<'_>,
        chemistry: protocol_core::settings::ChemistryCheck,
        bridge: &mut Bridge,
    ) {
        let t = bridge.telemetry();
        if !t.ready || t.settings.is_none() {
            return self.error(
                req,
                ErrorCode::NotReady,
                "settings and limits not read yet",
                "",
            );
        }
        let (pairs, physical) = match values {
            SetValues::Physical(p) => (p, true),
            SetValues::Raw(p) => (p, false),
        };
        let mut items: Vec<Setting, MAX_SETTINGS_GROUP> = Vec::new();
        for &(name, value) in pairs {
            let Some(id) = crate::bms::profile::find_setting(name) else {
                return self.error(req, ErrorCode::UnknownSetting, "no such setting", name);
            };
            if items.iter().any(|s| s.id == id) {
                // Both values in turn would write one the host may not mean.
                return self.error(req, ErrorCode::InvalidValue, "setting given twice", name);
            }
            let raw = if physical {
                crate::units::raw_from_physical(id, value)
            } else if crate::units::round(value) == value
                && value >= f64::from(i32::MIN)
                && value <= f64::from(i32::MAX)
            {
                Some(value as i32)
            } else {
                None
            };
            let Some(raw) = raw else {
                return self.error(req, ErrorCode::OutOfRange, "not a raw value", name);
            };
            let setting = Setting { id, value: raw };
            let limits = match (&t.limits_min, &t.limits_max) {
                (Some(lo), Some(hi)) => id.limits(lo, hi),
                _ => None,
            };
            if let Err(e) = setting.validate_with(limits) {
                return self.error(req, ErrorCode::OutOfRange, e.reason(), name);
            }
            if items.push(setting).is_err() {
                return self.error(req, ErrorCode::InvalidValue, "too many settings", "");
            }
        }
        if self.writes.len() + items.len() > PENDING_WRITES {
            return self.error(req, ErrorCode::Busy, "writes pending", "");
        }
        if bridge
            .submit(Command::ApplySettings(items.clone(), chemistry))
            .is_err()
        {
            return self.error(req, ErrorCode::Busy, "command queue full", "");
        }
        for s in items {
            let _ = self.writes.push((req, s));
        }
        self.push(Out::Accepted(req, "set"));
    }

    fn on_report(&mut self, report: &Report) {
        match report {
            Report::Write { setting, outcome } => {
                let req = take(&mut self.writes, setting);
                if matches!(outcome, WriteOutcome::Unconfirmed(_)) {
                    if self.follow_ups.is_full() {
                        self.follow_ups.remove(0);
                    }
                    let _ = self.follow_ups.push((req, *setting));
                }
                self.report(Out::Outcome {
                    req,
                    setting: *setting,
                    outcome: *outcome,
                    follow_up: false,
                });
            }
            Report::WriteFollowUp { setting, outcome } => {
                let req = take(&mut self.follow_ups, setting);
                self.report(Out::Outcome {
                    req,
                    setting: *setting,
                    outcome: *outcome,
                    follow_up: true,
                });
            }
            Report::NewEvent(e) => self.report(Out::Event(*e)),
            // The bridge's periodic link statistics go to a host that asked for
            // a stream too.
            Report::LinkStats(_) if self.stream_period_ms > 0 => self.report(Out::Link(None)),
            Report::ResetDone { confirmed } => {
                let req = self.resets.pop_front().flatten();
                self.report(Out::ResetDone(req, *confirmed));
            }
            Report::Cleared { option, ok } => {
                let req = match self.clears.iter().position(|(_, o)| o == option) {
                    Some(i) => self.clears.remove(i).0,
                    None => None,
                };
                self.report(Out::Cleared(req, *option, *ok));
            }
            _ => {}
        }
    }

    /// Encodes the front item; pops it unless it is a listing with more to say.
    fn encode_front(
        &mut self,
        now: Instant,
        bridge: &Bridge,
        config: &ConfigState,
        out: &mut [u8],
    ) -> Option<usize> {
        let t = bridge.telemetry();
        let known = bridge.events();
        let first_seq = known.total().wrapping_sub(known.len() as u32);
        let front = self.queue.front_mut()?;
        let n = match front {
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
                        return encode::setting(out, *req, id, raw, limits);
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
                    return encode::event(out, *req, &e, true);
                }
                encode::end(out, "events_end", *req, *sent)
            }
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
            ),
            Out::Config { req, next } => {
                let fields = crate::config::FIELDS;
                match fields.get(usize::from(*next)) {
                    Some(f) => {
                        *next = next.saturating_add(1);
                        let bms = t
                            .settings
                            .as_ref()
                            .and_then(crate::config::PackSettings::from_registers);
                        return encode::config_field(out, *req, f, config, bms.as_ref());
                    }
                    None => encode::config_end(out, *req, config),
                }
            }
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
        };
        self.queue.pop_front();
        n
    }
}

/// The text of a JSON string with its escapes resolved.
fn unescape(s: &serde_json_core::str::EscapedStr<'_>) -> Result<String<TEXT_MAX>, FieldError> {
    use serde_json_core::str::EscapedStringFragment as F;
    let mut out = String::new();
    for fragment in s.fragments() {
        let ok = match fragment {
            Ok(F::NotEscaped(t)) => out.push_str(t).is_ok(),
            Ok(F::Escaped(c)) => out.push(c).is_ok(),
            Err(_) => {
                return Err(FieldError {
                    out_of_range: false,
                    detail: "invalid escape in the string",
                })
            }
        };
        if !ok {
            return Err(FieldError::TOO_LONG);
        }
    }
    Ok(out)
}

/// Removes the oldest pending entry for `setting` and returns its request id.
fn take(
    pending: &mut Vec<(Option<u32>, Setting), PENDING_WRITES>,
    setting: &Setting,
) -> Option<u32> {
    let i = pending.iter().position(|(_, s)| s == setting)?;
    Some(pending.remove(i).0).flatten()
}
