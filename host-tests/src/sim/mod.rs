//! # A simulated TinyBMS
//!
//! [`SimBms`] is a TinyBMS s516 on the far end of a 115200 8N1 UART, in virtual
//! time and without I/O (sans-IO, in the style of `embassy-net-ppp`): the caller
//! hands it the bytes the host sends and the time, and takes the bytes the BMS
//! puts on the wire. No thread, no sleep, no clock: time is a `u64` of
//! microseconds given by the caller, and the simulator returns "something happens
//! at T" ([`SimBms::next_event_at`], [`SimBms::next_output_at`]) instead of
//! waiting. Virtual time starts at 0 µs.
//!
//! Every frame is parsed and encoded by `protocol-core` ([`Request::parse`],
//! [`Request::frame_len`], [`Response::to_frame`], [`Frame::encode`]); nothing
//! here re-implements the CRC or a layout.
//!
//! ## What it models
//!
//! * **A register file** of 600 `u16` (0-599, Rev D chapter 3), initialised from
//!   a [`PackModel`]: cells, pack voltage/current as f32 and lifetime/SOC as u32
//!   with the low word at the lower address (HARDWARE-NOTES), temperatures
//!   (external sensor 2 disconnected = -32768 on the 14S model), status,
//!   balancing bits, statistics 100-117, the event log 200-297 (§3.3 layout),
//!   settings 300-343, version 500-509 with a seeded serial number.
//! * **Every command** of Rev D chapter 1, answered byte-exactly: 0x02, 0x03,
//!   0x07, 0x09, 0x0B (PL = 2 + 2n, as protocol-core encodes it), 0x0D, 0x10
//!   (8-byte echo), 0x11, 0x12, 0x14-0x1C, 0x1D (min / max / default / current
//!   from the simulator's own table, sensor-dependent for 304, 305, 317, 318),
//!   0x1E, 0x1F, 0x20. Native replies over 63 payload bytes (0x07, 0x09, 0x11,
//!   0x12) are split into packets by [`Frame::encode`].
//! * **Errors**: NACK 0x01 for a bad CRC; NACK 0x00 for an unknown command
//!   byte, a malformed request (bad option byte, too many registers...), a read
//!   past register 599, a write outside 300-399 or to a reserved register
//!   (302, 309, 324-327, 344-399), or a value outside the simulator's min/max.
//!   A refused write changes nothing (all or nothing per request).
//! * **Real-unit behaviour** of HARDWARE-NOTES: a sleeping BMS swallows the first
//!   request (register 114 high byte = 0x03, UART wake-up); 0x02 option 0x05
//!   gets no ACK and reboots (register 114 low byte = 0x04, software reset);
//!   323 and 328 read back 0xFFFF once a write was accepted; a write to 340
//!   reboots; ASCII broadcast lines when 343 = ASCII and 342 ≠ 0.
//! * **Timing**: each byte takes 10 bits / 115200 = 86.8 µs on the wire, both
//!   ways ([`wire_time_us`], exact integer math, rounded up to the µs per
//!   transmission); a reply starts 1-2 ms (seeded) after the last request byte
//!   arrived, and never overlaps another transmission.
//! * **Live values** that move with virtual time (see `live.rs`): a current
//!   model of discharge / idle / charge phases, SOC integrated over the
//!   capacity (register 306), cells from an OCV curve + I·R + per-cell offsets +
//!   noise, registers 40/41 = min/max cell rounded to the mV, pack voltage = sum
//!   of the cells, drifting temperatures, status from the current sign (0x91 /
//!   0x93 / 0x97, 0x92 after a full charge, 0x9B with a latched fault), events
//!   (charger connected, charging started / done, charger disconnected), charge
//!   counters and statistics maxima. [`SimConfig::live`] = false freezes them.
//! * **Seeded fault injection** ([`FaultConfig`]): dropped and bit-flipped output
//!   bytes, truncated / duplicated / delayed replies, lost requests; counted by
//!   kind in [`SimStats::faults`].
//!
//! Determinism: the same model, config, seed and sequence of calls give the
//! same bytes at the same times. The live model, the reply latencies and the
//! faults draw from separate streams derived from the seed, so switching a fault
//! on does not change the pack's values.
//!
//! ## Choices where Rev D and HARDWARE-NOTES are silent
//!
//! * **0x11 (newest events)** returns the BMS timestamp and the events logged
//!   since the previous 0x11 request (since the start of the simulation for the
//!   first one), oldest first, at most the newest
//!   [`SimConfig::newest_events_max`] (16 by default). No new event: a reply
//!   with the timestamp only (PL = 4). 0x12 returns the whole log, oldest first.
//! * **Event log registers 200-297**: slot 0 (200-201) holds the oldest event,
//!   slots fill in order; when all 49 are used the oldest is dropped and the
//!   others move down. Empty slots read 0xFFFF 0xFFFF (erased), also after
//!   0x02 option 0x01. Event timestamps and the 0x11/0x12 BMS timestamp are the
//!   lifetime counter (registers 32-33), in seconds.
//! * **Packet IDs** of multi-packet replies start at 1 (protocol-core's
//!   encoder); [`SimConfig::first_packet_id`] can start them elsewhere (the real
//!   unit was seen sending 0x82 first).
//! * **Reboot** (0x02 option 0x05, write to 340): the BMS goes silent for
//!   [`SimConfig::boot_time_us`] (1 s by default): bytes received meanwhile are
//!   ignored, output queued after the reset instant is lost, no broadcast. At
//!   the end of the boot it logs "System Started" (0x61), register 114 low byte
//!   reads 0x04 (software reset). Values, settings, statistics, the lifetime
//!   counter and a latched fault survive. 0x05 is never acknowledged; the reset
//!   happens one reply latency after the request.
//! * **Write to 340**: the write is answered first (ACK for 0x0B/0x0D, echo for
//!   0x10) and the BMS reboots as soon as that reply has left the wire. Any
//!   accepted write that includes register 340 reboots, even with an unchanged
//!   value (the harsh choice: a client should not rewrite 340 casually).
//! * **323 / 328**: read 0xFFFF from the start (as the real unit did) and after
//!   every accepted write; writing 0xFFFF to them is accepted and changes nothing
//!   (so a read-modify-write of the whole block goes through). A value takes
//!   effect at once: 323 sets SOH (register 45), 328 sets SOC (46-47, and the
//!   live model continues from it), both in 0.002 %.
//! * **Byte-field settings 331-343**: the low byte is checked against min/max,
//!   the reserved high byte is stored as written and not checked; 330 has both
//!   bytes checked (charger type 0-2, timeout 0-30 s). 312-313 are checked as
//!   one u32 (1-100000) after the whole request is applied. 0x1D reports
//!   reserved registers as 0 in the min / max / default tables.
//! * **0x1C** returns register 53's count of cells starting at the model's
//!   first cell register (2 on the 14S model).
//! * **Unknown command byte**: NACK 0x00 right after `AA <cmd>`; the bytes that
//!   follow are skipped as garbage until the next 0xAA. A frame with a bad CRC is
//!   dropped whole (its length is known from the command) and answered NACK
//!   0x01. A partial request is dropped when the next byte comes more than
//!   [`SimConfig::idle_gap_us`] (5 ms) after the previous one.
//! * **Sleep**: UART traffic means bytes from the host; the BMS falls asleep
//!   [`SimConfig::sleep_after_us`] after the last one (not while rebooting).
//!   Asleep, it sends nothing (no broadcast either); any byte wakes it, and the
//!   first complete request after the wake-up (valid or not) gets no reply and
//!   has no effect. Rev D §1.3: "the response to the command will be sent when it
//!   receives the command a second time".
//! * **ASCII broadcasts**: the first line comes one interval after 342/343 were
//!   set (or after boot), then one per interval; a line due while a binary reply
//!   is on the wire waits for it, and a reply due while a line is on the wire
//!   waits for the line, so the two never interleave. See `ascii.rs` for the
//!   line format.
//! * **`no_reply` fault**: the request is lost before the BMS sees it (no
//!   effect), rather than processed with its reply lost; truncation and dropped
//!   bytes cover lost replies.
//! * The BMS only transmits while awake, booted and not silenced with
//!   [`SimBms::set_silent_until`] (bytes due inside a silent window are lost).
//!
//! ## Example
//! ```
//! use host_tests::sim::{PackModel, SimBms, SimConfig};
//! use protocol_core::{Decoder, Request, Response};
//!
//! let mut bms = SimBms::new(PackModel::LiIon_14S, SimConfig::default(), 42);
//! let req = Request::ReadPackVoltage;
//! let sent = bms.host_send(0, &req.to_bytes()?);
//! let mut rx = Vec::new();
//! bms.take_output(sent + 100_000, &mut rx); // 100 ms later
//! let mut dec = Decoder::new();
//! dec.push(&rx);
//! let frame = dec.poll().ok_or("no reply")??;
//! let Response::PackVoltage(v) = Response::decode(&req, &frame)? else { panic!() };
//! assert!((50.0..60.0).contains(&v));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![deny(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::indexing_slicing,
    clippy::panic
)]

mod ascii;
pub mod balancer;
mod commands;
mod config;
mod event_loop;
mod events;
mod live;
mod receive;
mod register_file;
pub(crate) mod rng;
mod settings;
mod stats;
mod transmit;

pub use config::{CurrentSensor, FaultConfig, PackModel, SimConfig};
pub use register_file::REGISTER_COUNT;
pub use stats::{FaultCounts, SimStats};

use std::collections::VecDeque;

use live::{Live, Params};
use protocol_core::command::{self as cmd, PREAMBLE};
use protocol_core::crc::crc16;
use protocol_core::events::{Event, EventId, OnlineStatus, Severity};
use protocol_core::frame::{
    Frame, NackCode, FIRST_PACKET_ID, MAX_PACKET_PAYLOAD, PL_MORE_PACKETS, PL_VALUE_MASK,
};
use protocol_core::registers::{EVENTS_FIRST, EVENT_SLOTS};
use protocol_core::request::{Request, RequestError, ResetOption, SettingsOption};
use protocol_core::response::{
    sensor, EventList, ExtendedVersion, RegisterBlock, Response, Temperatures, Version, Words,
    MAX_EVENTS,
};
use rng::Rng;

/// Highest register address that can be read (Rev D §3.5: 510-599 reserved).
pub const LAST_REGISTER: u16 = (REGISTER_COUNT - 1) as u16;

/// Register 114 (Rev D §3.2): low byte = last reset, high byte = last wake-up.
const REG_RESET_WAKE: u16 = 114;
/// Register 114 low byte: software reset.
const RESET_SOFTWARE: u16 = 0x04;
/// Register 114 high byte: UART communication detected.
const WAKE_UART: u16 = 0x03;
/// Register 340: BMS operation mode; writing it restarts the BMS (HARDWARE-NOTES).
const REG_OPERATION_MODE: u16 = 340;
/// Registers 323 / 328 read back this once a write was accepted (Rev D §3.4).
const ACCEPTED_MARKER: u16 = 0xFFFF;
/// An erased event slot register.
const EMPTY_SLOT: u16 = 0xFFFF;

/// Wire time of `bytes` bytes at 115200 baud, 8N1 (10 bits per byte, 86.8 µs),
/// rounded up to the µs: `bytes · 10 / 115200` s = `bytes · 3125 / 36` µs.
pub const fn wire_time_us(bytes: u64) -> u64 {
    (bytes.saturating_mul(3125)).div_ceil(36)
}

/// Internal timed events, in the order they are handled when due at the same
/// microsecond.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Ev {
    BootDone,
    Reboot,
    Input,
    Sleep,
    Live,
    Broadcast,
}

/// A block the simulated BMS answered, before any fault: 0x03/0x07 registers
/// (`option` `None`) or a 0x1D table.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TrueRead {
    /// Virtual time of the answer.
    pub at_us: u64,
    /// The 0x1D option, for a settings table.
    pub option: Option<SettingsOption>,
    /// The values.
    pub block: RegisterBlock,
}

/// The simulated TinyBMS. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct SimBms {
    model: PackModel,
    config: SimConfig,
    regs: [u16; REGISTER_COUNT],
    now: u64,

    // Host -> BMS.
    input: VecDeque<(u64, u8)>,
    host_wire_free: u64,
    rx: Vec<u8>,
    rx_last: u64,
    swallow_next: bool,
    busy_until: u64,

    // BMS -> host: (time the byte has fully arrived, byte), in time order.
    out: VecDeque<(u64, u8)>,
    out_free: u64,

    // Power state.
    asleep: bool,
    last_traffic: u64,
    pending_reboot: Option<u64>,
    boot_until: Option<u64>,
    silent: Option<(u64, u64)>,

    next_broadcast: Option<u64>,

    live: Live,
    next_step: u64,
    fault: Option<EventId>,

    /// (sequence number, event), oldest first, at most [`EVENT_SLOTS`].
    events: VecDeque<(u64, Event)>,
    event_seq: u64,
    newest_read_seq: u64,

    rng_faults: Rng,
    rng_latency: Rng,
    /// The previous reply as encoded (for the repeated-fragment fault).
    last_reply: Vec<u8>,
    stats: SimStats,

    // Test hooks.
    record: bool,
    sent_log: Vec<Frame>,
    record_reads: Option<u64>,
    recent_reads: VecDeque<TrueRead>,
    logged: Vec<(u64, Event)>,
    ignored_writes: Vec<u16>,
    ignored_commands: Vec<u8>,
    drop_next: std::collections::BTreeMap<u8, u32>,
    drop_replies: std::collections::BTreeMap<u8, u32>,
    forged: Option<Vec<u8>>,
    forged_live: Option<Vec<u8>>,
    forged_pair: Option<(u16, u16)>,
    pinned: Vec<(u16, u16)>,
    limit_overrides: Vec<(u16, u16, u16)>,
}

impl SimBms {
    /// A BMS managing `model`, configured by `config`; every random choice
    /// (serial number, live values, latencies, faults) derives from `seed`.
    pub fn new(model: PackModel, config: SimConfig, seed: u64) -> Self {
        let mut master = Rng::new(seed);
        let mut rng_serial = master.fork();
        let rng_live = master.fork();
        let rng_faults = master.fork();
        let rng_latency = master.fork();
        let lifetime = register_file::initial_lifetime_s(model);
        let mut regs = register_file::initial_registers(
            model,
            config.current_sensor,
            lifetime,
            &mut rng_serial,
        );
        let params = Params::from_registers(&regs, false);
        let live = Live::new(model, rng_live, params.capacity_ah, lifetime);
        live.publish(&mut regs, &params);
        let asleep = config.start_asleep;
        let mut sim = Self {
            model,
            config,
            regs,
            now: 0,
            input: VecDeque::new(),
            host_wire_free: 0,
            rx: Vec::new(),
            rx_last: 0,
            swallow_next: false,
            busy_until: 0,
            out: VecDeque::new(),
            out_free: 0,
            asleep,
            last_traffic: 0,
            pending_reboot: None,
            boot_until: None,
            silent: None,
            next_broadcast: None,
            live,
            next_step: live::STEP_US,
            fault: None,
            events: VecDeque::new(),
            event_seq: 0,
            newest_read_seq: 0,
            rng_faults,
            rng_latency,
            last_reply: Vec::new(),
            stats: SimStats::default(),
            record: false,
            sent_log: Vec::new(),
            record_reads: None,
            recent_reads: VecDeque::new(),
            logged: Vec::new(),
            ignored_writes: Vec::new(),
            ignored_commands: Vec::new(),
            drop_next: std::collections::BTreeMap::new(),
            drop_replies: std::collections::BTreeMap::new(),
            forged: None,
            forged_live: None,
            forged_pair: None,
            pinned: Vec::new(),
            limit_overrides: Vec::new(),
        };
        for &(ago, id) in register_file::HISTORY {
            sim.push_event(Event {
                timestamp_s: lifetime.saturating_sub(ago) & Event::MAX_TIMESTAMP,
                id,
            });
        }
        sim.write_event_registers();
        sim.reconfigure_broadcast(0);
        sim
    }

    // ------------------------------------------------------------------
    // Public API
    // ------------------------------------------------------------------

    /// The host starts sending `bytes` at `now_us` (or when its previous bytes
    /// have left the wire, if later). Each byte reaches the BMS 86.8 µs after the
    /// previous one. Returns the time the last byte has arrived: advancing to it
    /// lets the BMS see the whole request.
    pub fn host_send(&mut self, now_us: u64, bytes: &[u8]) -> u64 {
        self.advance(now_us);
        let start = self.now.max(self.host_wire_free);
        for (k, &b) in bytes.iter().enumerate() {
            self.input
                .push_back((start + wire_time_us(k as u64 + 1), b));
        }
        let end = start + wire_time_us(bytes.len() as u64);
        self.host_wire_free = end;
        end
    }

    /// Appends to `out`, in order, every byte the BMS has fully put on the wire
    /// at or before `now_us` (advancing the simulation to `now_us` first).
    pub fn take_output(&mut self, now_us: u64, out: &mut Vec<u8>) {
        self.advance(now_us);
        while let Some(&(t, b)) = self.out.front() {
            if t > self.now {
                break;
            }
            out.push(b);
            self.out.pop_front();
        }
    }

    /// Time at which the next output byte completes, so a caller can jump
    /// virtual time. Exact for bytes already scheduled. While a request is still
    /// arriving (or not yet processed), or a broadcast line is due, it is a
    /// lower bound: the earliest the reply's / line's first byte can complete
    /// (end of the request's last byte + the minimum latency + one byte). The
    /// reply is scheduled once the simulation reaches that point, so
    /// [`SimBms::take_output`] at that time may return nothing yet (or nothing at
    /// all: a sleeping BMS, a lost request); ask again. `None`: nothing can come
    /// out before the host sends more.
    pub fn next_output_at(&self) -> Option<u64> {
        let scheduled = self.out.front().map(|&(t, _)| t);
        let reply = self.pending_frame_end().map(|t| {
            t.saturating_add(self.config.reply_latency_us.0)
                .saturating_add(wire_time_us(1))
        });
        let line = self
            .next_broadcast
            .filter(|_| !self.asleep)
            .map(|t| t.saturating_add(wire_time_us(1)));
        [scheduled, reply, line].into_iter().flatten().min()
    }

    /// Arrival time of the byte that completes the first request (or unknown
    /// command) among the bytes not processed yet: framing only, no effect.
    fn pending_frame_end(&self) -> Option<u64> {
        let mut rx = self.rx.clone();
        let mut last = self.rx_last;
        for &(t, b) in &self.input {
            if !rx.is_empty() && t.saturating_sub(last) > self.config.idle_gap_us {
                rx.clear();
            }
            last = t;
            rx.push(b);
            loop {
                match rx.first() {
                    Some(&x) if x != PREAMBLE => {
                        rx.remove(0);
                    }
                    _ => break,
                }
            }
            match Request::frame_len(&rx) {
                Ok(Some(n)) if rx.len() >= n => return Some(t),
                Err(RequestError::UnknownCommand(_)) => return Some(t),
                _ => {}
            }
        }
        None
    }

    /// Earliest time at which anything happens: an output byte completes, an
    /// input byte arrives, a live-value step (every second when live values are
    /// on), a broadcast, a sleep, a reboot or the end of one. Advancing to it
    /// and checking again walks the simulation event by event.
    pub fn next_event_at(&self) -> Option<u64> {
        let internal = self.next_internal().map(|(t, _)| t);
        let output = self.out.front().map(|&(t, _)| t);
        [internal, output].into_iter().flatten().min()
    }

    /// Moves the simulation to `now_us`: bytes arrive and are answered, live
    /// values step, broadcasts go out, the BMS sleeps, reboots... in time order.
    /// Time never goes back: an earlier `now_us` is ignored.
    pub fn advance(&mut self, now_us: u64) {
        let target = now_us.max(self.now);
        while let Some((t, ev)) = self.next_internal() {
            if t > target {
                break;
            }
            let t = t.max(self.now);
            self.now = t;
            self.handle(ev, t);
        }
        self.now = target;
    }

    /// The simulation's present time, µs.
    pub fn now_us(&self) -> u64 {
        self.now
    }

    /// Register `addr` as the BMS holds it (0 beyond 599).
    pub fn register(&self, addr: u16) -> u16 {
        self.regs.get(usize::from(addr)).copied().unwrap_or(0)
    }

    /// The whole register file.
    pub fn registers(&self) -> &[u16; REGISTER_COUNT] {
        &self.regs
    }

    /// Sets register `addr` (ignored beyond 599), bypassing every check. With
    /// live values on, the live registers (0-55 except 45, statistics maxima,
    /// event slots) are rewritten by the model at its next step; freeze them with
    /// [`SimConfig::live`] = false. Setting 342/343 restarts the broadcast timer.
    pub fn set_register(&mut self, addr: u16, v: u16) {
        if let Some(r) = self.regs.get_mut(usize::from(addr)) {
            *r = v;
        }
        if addr == 342 || addr == 343 {
            self.reconfigure_broadcast(self.now);
        }
    }

    /// Test hook: change the configuration while running (e.g. the current sensor,
    /// which changes the settings limits the BMS enforces and reports).
    pub fn config_mut(&mut self) -> &mut SimConfig {
        &mut self.config
    }

    /// Test hook: requests with this command byte are never answered and have no
    /// effect (a BMS firmware without that command, answering nothing).
    pub fn ignore_command(&mut self, command: u8) {
        self.ignored_commands.push(command);
    }

    /// Test hook: the next `n` requests with this command byte are lost (no
    /// answer, no effect), as if the line had swallowed them.
    pub fn drop_next_requests(&mut self, command: u8, n: u32) {
        self.drop_next.insert(command, n);
    }

    /// Test hook: keep a copy of every frame the BMS sends, as built, before any
    /// fault is applied — the ground truth a test compares decoded values with.
    pub fn record_frames(&mut self, on: bool) {
        self.record = on;
    }

    /// Test hook: the next `n` requests of `command` are executed (a write is
    /// applied) but their replies are lost on the wire.
    pub fn drop_next_replies(&mut self, command: u8, n: u32) {
        self.drop_replies.insert(command, n);
    }

    /// Test hook: the next reply (of any command) is replaced by these bytes on
    /// the wire — e.g. a CRC-valid frame the BMS never built, as a CRC collision
    /// on a noisy line produces. The ground truth keeps the real answer.
    pub fn forge_next_reply(&mut self, bytes: Vec<u8>) {
        self.forged = Some(bytes);
    }

    /// Test hook: the next 0x09 reply that holds register `addr` carries `value`
    /// for it instead, in a CRC-valid frame (what a CRC collision in a piece on a
    /// bad line looks like). The ground truth keeps the real answer.
    pub fn forge_next_pair(&mut self, addr: u16, value: u16) {
        self.forged_pair = Some((addr, value));
    }

    /// True while a [`SimBms::forge_next_pair`] forgery has not gone out yet.
    pub fn pair_forgery_pending(&self) -> bool {
        self.forged_pair.is_some()
    }

    /// Test hook: the next 0x03 reply carrying 56 registers (a whole live block)
    /// is replaced by these bytes on the wire.
    pub fn forge_next_live_reply(&mut self, bytes: Vec<u8>) {
        self.forged_live = Some(bytes);
    }

    /// Test hook: register `addr` reads `value` whatever the live model computes
    /// (a broken sense wire reads 0 V on its cell).
    pub fn pin_register(&mut self, addr: u16, value: u16) {
        self.pinned.retain(|&(a, _)| a != addr);
        self.pinned.push((addr, value));
        self.set_reg(addr, value);
    }

    /// Test hook: the BMS reports (0x1D) and enforces these limits for setting
    /// `addr` instead of its table's (another current sensor, say).
    pub fn override_limits(&mut self, addr: u16, min: u16, max: u16) {
        self.limit_overrides.retain(|&(a, _, _)| a != addr);
        self.limit_overrides.push((addr, min, max));
    }

    /// Closed loop: the pack current is imposed by an inverter model from now on
    /// (`None` gives it back to the built-in load/charge model), A, positive =
    /// charging. The BMS's switches still cut it while a fault is latched.
    pub fn set_external_current(&mut self, amps: Option<f64>) {
        self.live.forced_current = amps;
    }

    /// Closed loop: the pack temperature is imposed (external sensors; the
    /// BMS's own sensor reads 2 °C more), °C.
    pub fn force_temperature(&mut self, celsius: Option<f64>) {
        self.live.forced_temp = celsius;
    }

    /// Closed loop: cell `index` (0-based) runs `mv` millivolts above the others.
    pub fn set_cell_offset_mv(&mut self, index: usize, mv: f64) {
        self.live.set_offset(index, mv / 1000.0);
    }

    /// Packs in parallel: the pack's open-circuit voltage now, V.
    pub fn open_circuit_v(&self) -> f64 {
        self.live.open_circuit_v()
    }

    /// Packs in parallel: the pack's internal resistance, Ω.
    pub fn internal_resistance_ohm(&self) -> f64 {
        self.live.resistance_ohm()
    }

    /// Packs in parallel: sets every cell's internal resistance, Ω.
    pub fn set_cell_resistance_ohm(&mut self, ohm: f64) {
        self.live.set_cell_resistance(ohm);
    }

    /// The BMS's SOC reads `bias` % above the truth from now on (its
    /// estimate drifted: it has not been fully charged for long).
    pub fn set_soc_bias(&mut self, bias: f64) {
        self.live.soc_bias = bias;
    }

    /// Sets the state of charge, %.
    pub fn set_soc_percent(&mut self, soc: f64) {
        self.live.set_soc(soc);
    }

    /// Test hook: empties the event log (no "Events Cleared" entry).
    pub fn clear_event_log(&mut self) {
        self.clear_events();
    }

    /// Test hook: keep every register block and 0x1D table the BMS answers, as
    /// built before any fault, for `window_us` of virtual time (bounded memory
    /// for long soaks). The ground truth of [`crate::truth`].
    pub fn record_reads(&mut self, window_us: u64) {
        self.record_reads = Some(window_us);
    }

    /// Blocks recorded by [`SimBms::record_reads`], oldest first.
    pub fn recent_reads(&self) -> &VecDeque<TrueRead> {
        &self.recent_reads
    }

    /// Every event logged since the BMS was created (the start-up history
    /// included), with the virtual time it was logged.
    pub fn logged_events(&self) -> &[(u64, Event)] {
        &self.logged
    }

    /// The frames recorded since [`SimBms::record_frames`] was turned on.
    pub fn sent_frames(&self) -> &[Frame] {
        &self.sent_log
    }

    /// Test hook: writes to `addr` are checked and acknowledged as usual but not
    /// stored (a BMS that silently keeps its old value), so a read-back differs.
    pub fn ignore_writes_to(&mut self, addr: u16) {
        self.ignored_writes.push(addr);
    }

    /// Counters.
    pub fn stats(&self) -> &SimStats {
        &self.stats
    }

    /// True while the BMS sleeps (the next request only wakes it).
    pub fn is_asleep(&self) -> bool {
        self.asleep
    }

    /// True while the BMS reboots (silent, ignoring input).
    pub fn is_rebooting(&self) -> bool {
        self.boot_until.is_some()
    }

    /// The BMS behaves as disconnected from now until `t_us`: it ignores input
    /// and its output due in that window is lost. The pack keeps living.
    pub fn set_silent_until(&mut self, t_us: u64) {
        let from = self.now;
        self.silent = Some((from, t_us));
        self.out.retain(|&(ts, _)| ts <= from || ts >= t_us);
        self.rx.clear();
    }

    /// Logs `id` in the event log now. A fault-class event (IDs 0x01-0x30)
    /// also latches a fault: status 0x9B, switches open (no current), the
    /// matching statistics counter (105-109) incremented, until
    /// [`SimBms::clear_fault`].
    pub fn inject_fault_event(&mut self, id: EventId) {
        self.log_event(id);
        if id.severity() == Severity::Fault {
            self.fault = Some(id);
            let counter = match id {
                EventId::UnderVoltageCutoff => Some(105),
                EventId::OverVoltageCutoff => Some(106),
                EventId::DischargingOverCurrentCutoff => Some(107),
                EventId::ChargingOverCurrentCutoff => Some(108),
                EventId::OverTemperatureCutoff => Some(109),
                _ => None,
            };
            if let Some(a) = counter {
                self.set_reg(a, self.register(a).saturating_add(1));
            }
            self.set_reg(50, live::STATUS_FAULT);
        }
    }

    /// Clears a latched fault, logging the matching "Recovered From ..." event
    /// when Rev D chapter 4 has one.
    pub fn clear_fault(&mut self) {
        if let Some(id) = self.fault.take() {
            let recovered = match id {
                EventId::UnderVoltageCutoff => Some(EventId::RecoveredUnderVoltage),
                EventId::OverVoltageCutoff => Some(EventId::RecoveredOverVoltage),
                EventId::OverTemperatureCutoff => Some(EventId::RecoveredOverTemperature),
                EventId::DischargingOverCurrentCutoff => {
                    Some(EventId::RecoveredDischargingOverCurrent)
                }
                EventId::ChargingOverCurrentCutoff => Some(EventId::RecoveredChargingOverCurrent),
                EventId::RegenerationOverCurrentCutoff => {
                    Some(EventId::RecoveredRegenerationOverCurrent)
                }
                EventId::LowTemperatureCutoff => Some(EventId::RecoveredLowTemperatureFault),
                _ => None,
            };
            if let Some(r) = recovered {
                self.log_event(r);
            }
            self.set_reg(50, self.live.status(false));
        }
    }

    /// The latched fault, if any.
    pub fn fault(&self) -> Option<EventId> {
        self.fault
    }

    /// The event log, oldest first (what 0x12 returns).
    pub fn events(&self) -> Vec<Event> {
        self.events.iter().map(|&(_, e)| e).collect()
    }

    /// What 0x1D returns for `option`: registers 300-399.
    pub fn settings_values(&self, option: SettingsOption) -> [u16; 100] {
        let mut v = [0u16; 100];
        for (i, x) in v.iter_mut().enumerate() {
            let addr = 300 + i as u16;
            let spec = settings::spec(addr, self.config.current_sensor);
            *x = match (option, spec) {
                (SettingsOption::Current, _) => self.register(addr),
                (_, None) => 0,
                (_, Some(s)) if s.kind == settings::Kind::Reserved => 0,
                (SettingsOption::Min, _) if self.limit(addr).is_some() => {
                    self.limit(addr).map_or(0, |l| l.0)
                }
                (SettingsOption::Max, _) if self.limit(addr).is_some() => {
                    self.limit(addr).map_or(0, |l| l.1)
                }
                (SettingsOption::Min, Some(s)) => s.min,
                (SettingsOption::Max, Some(s)) => s.max,
                (SettingsOption::Default, Some(s)) => s.default,
            };
        }
        v
    }

    fn limit(&self, addr: u16) -> Option<(u16, u16)> {
        self.limit_overrides
            .iter()
            .find(|&&(a, _, _)| a == addr)
            .map(|&(_, lo, hi)| (lo, hi))
    }

    /// The model of the simulated pack.
    pub fn pack_model(&self) -> PackModel {
        self.model
    }

    /// The configuration.
    pub fn config(&self) -> &SimConfig {
        &self.config
    }
}

/// (address, value) pairs of a block write.
fn consecutive(start: u16, values: &[u16]) -> Vec<(u16, u16)> {
    values
        .iter()
        .enumerate()
        .map(|(i, &v)| (start.wrapping_add(i as u16), v))
        .collect()
}

/// Renumbers the non-last packets of an encoded multi-packet reply from
/// `first_id` (and recomputes their CRCs).
fn renumber_packets(buf: &mut [u8], first_id: u8) {
    const PACKET: usize = 3 + MAX_PACKET_PAYLOAD + 2;
    let mut pos = 0usize;
    let mut id = first_id;
    while let Some(&pl) = buf.get(pos + 2) {
        if pl & PL_MORE_PACKETS == 0 {
            break;
        }
        let Some(packet) = buf.get_mut(pos..pos + PACKET) else {
            break;
        };
        if let Some(p) = packet.get_mut(2) {
            *p = PL_MORE_PACKETS | (id & PL_VALUE_MASK);
        }
        let crc = crc16(packet.get(..PACKET - 2).unwrap_or(&[])).to_le_bytes();
        if let Some(c) = packet.get_mut(PACKET - 2..) {
            c.copy_from_slice(&crc);
        }
        pos += PACKET;
        id = id.wrapping_add(1);
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn wire_time_is_86_8_us_per_byte() {
        assert_eq!(wire_time_us(0), 0);
        assert_eq!(wire_time_us(1), 87); // 86.806
        assert_eq!(wire_time_us(36), 3125); // exact
        assert_eq!(wire_time_us(11_520), 1_000_000); // 1 s = 11520 bytes
    }

    #[test]
    fn renumbering_keeps_frames_valid() {
        let payload: Vec<u8> = (0..90u8).collect();
        let f = Frame::data(cmd::READ_BLOCK, &payload).unwrap();
        let mut b = vec![0u8; f.encoded_len().unwrap()];
        f.encode(&mut b).unwrap();
        renumber_packets(&mut b, 2);
        assert_eq!(b[2], 0x82);
        assert_eq!(crc16(&b[..66]).to_le_bytes(), [b[66], b[67]]);
        assert_eq!(b[70], 27);
    }
}
