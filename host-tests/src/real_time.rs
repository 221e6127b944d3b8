//! The firmware's logic and the simulated BMS in **real time**, on real byte
//! ports: the counterpart of [`crate::virtual_time`] (virtual time) for the desktop
//! tool and for `sim --pty` / `sim --bridge-pty`.
//!
//! * [`BytePort`] — anything that moves UART bytes: a `serialport` port (a
//!   USB-UART adapter wired to a TinyBMS, or a pty), or [`SimPort`], the
//!   simulated BMS in-process with its clock on the wall clock.
//! * [`Driver`] — the firmware's [`Station`] on a [`BytePort`]: the chip's
//!   station task (do what the station asks for, hand received bytes in,
//!   sleep until the next deadline), so wake-up, resync, write/verify and the
//!   wiring of the consumers are the firmware's own code. It can record the raw exchange as
//!   a `.tbms` capture ([`crate::capture::CaptureWriter`]).
//! * [`serve_sim_pty`] — the simulated BMS on a pseudo-terminal (`sim --pty`).
//!
//! Time: [`Clock`] turns the wall clock into the firmware's [`Instant`]
//! (µs since the start). The logic itself still never reads a clock.

use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use protocol_core::settings::{Setting, SettingId};
use tinybms_firmware::bms::timing::{Timing, BYTE_TIME_US};
use tinybms_firmware::config::store::{Store, StoreError};
use tinybms_firmware::inverter::frames::CanFrame;
use tinybms_firmware::inverter::TxResult;
use tinybms_firmware::station::{Action, Logged, Station};
use tinybms_firmware::text::Line;
use tinybms_firmware::{Instant, Report};

use crate::flash::SimFlash;

use crate::capture::CaptureWriter;
use crate::pty::Pty;
use crate::sim::{PackProfile, SimBms, SimConfig};

/// Longest the loops sleep without looking at their other inputs (a stop flag,
/// the host side), so they stay responsive without spinning.
pub const MAX_SLICE: Duration = Duration::from_millis(10);

/// The simulated BMS hands its output over in chunks of this much wire time
/// (≈ 16 bytes, like a UART driver's FIFO threshold) instead of byte by byte.
pub const SIM_CHUNK_US: u64 = crate::virtual_time::RX_CHUNK_US;

/// Parses a duration: `250ms`, `10s`, `1.5m`, `2h`, `500us`; a bare number is
/// seconds.
pub fn parse_duration(s: &str) -> Result<Duration, String> {
    let (num, unit) = s
        .find(|c: char| !c.is_ascii_digit() && c != '.')
        .map(|i| s.split_at(i))
        .unwrap_or((s, "s"));
    let v: f64 = num.parse().map_err(|_| format!("bad duration `{s}`"))?;
    let scale = match unit {
        "us" => 1e-6,
        "ms" => 1e-3,
        "s" | "" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        _ => return Err(format!("bad duration unit in `{s}` (us, ms, s, m, h)")),
    };
    if !(v * scale).is_finite() || v * scale < 0.0 {
        return Err(format!("bad duration `{s}`"));
    }
    Ok(Duration::from_secs_f64(v * scale))
}

/// The wall clock as the firmware's [`Instant`]: µs since [`Clock::start`].
#[derive(Debug, Clone, Copy)]
pub struct Clock(std::time::Instant);

impl Clock {
    /// Time 0 is now.
    pub fn start() -> Self {
        Self(std::time::Instant::now())
    }
    /// µs since the start.
    pub fn now(&self) -> Instant {
        self.0.elapsed().as_micros() as Instant
    }
    /// Wall-clock time from now until `t` (zero when past).
    pub fn until(&self, t: Instant) -> Duration {
        Duration::from_micros(t.saturating_sub(self.now()))
    }
}

/// A UART-like byte stream.
pub trait BytePort: Send {
    /// Sends every byte (returns once they are handed to the wire).
    fn send(&mut self, bytes: &[u8]) -> io::Result<()>;
    /// Waits up to `timeout` for received bytes; `Ok(0)` when none came.
    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize>;
}

impl BytePort for Box<dyn serialport::SerialPort> {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.write_all(bytes)?;
        // tcdrain: the bridge's response timeout runs from the last byte out.
        self.flush()
    }

    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        // serialport rounds a zero timeout to "no wait"; keep at least 1 ms so a
        // deadline now still reads what is there.
        self.set_timeout(timeout.max(Duration::from_millis(1)))
            .map_err(io::Error::other)?;
        match self.read(buf) {
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::TimedOut => Ok(0),
            Err(e) if e.kind() == io::ErrorKind::Interrupted => Ok(0),
            Err(e) => Err(e),
        }
    }
}

/// The simulated BMS as a [`BytePort`], in-process, on the wall clock.
pub struct SimPort {
    /// The simulated BMS (its virtual time follows [`SimPort::clock`]).
    pub sim: SimBms,
    clock: Clock,
    pending: Vec<u8>,
}

impl SimPort {
    /// A simulated BMS whose time 0 is now.
    pub fn new(sim: SimBms) -> Self {
        Self {
            sim,
            clock: Clock::start(),
            pending: Vec::new(),
        }
    }

    /// The port's clock.
    pub fn clock(&self) -> Clock {
        self.clock
    }
}

impl BytePort for SimPort {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        let end = self.sim.host_send(self.clock.now(), bytes);
        // Like a UART write + flush: return once the last byte is on the wire.
        std::thread::sleep(self.clock.until(end));
        Ok(())
    }

    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        let deadline = self.clock.now() + timeout.as_micros() as u64;
        loop {
            if self.pending.is_empty() {
                self.sim.take_output(self.clock.now(), &mut self.pending);
            }
            if !self.pending.is_empty() {
                let n = self.pending.len().min(buf.len());
                buf[..n].copy_from_slice(&self.pending[..n]);
                self.pending.drain(..n);
                return Ok(n);
            }
            let now = self.clock.now();
            if now >= deadline {
                return Ok(0);
            }
            let wake = match self.sim.next_output_at() {
                Some(t) => (t.max(now) + SIM_CHUNK_US).min(deadline),
                None => deadline,
            };
            std::thread::sleep(Duration::from_micros(wake.saturating_sub(now).max(50)));
        }
    }
}

/// What [`Driver::service`] tells its caller about.
#[derive(Debug)]
pub enum Happened<'a> {
    /// These bytes were sent to the BMS.
    Tx(&'a [u8]),
    /// The station logged this, at this time, in these words.
    Log(Instant, &'a Logged, &'a str),
}

/// The CAN controller of a desktop station: a virtual bus.
pub trait CanSide: Send {
    /// Sends a frame at `now`.
    fn send(&mut self, now: Instant, frame: &CanFrame) -> TxResult;
    /// A bus-off recovery at `now`: back on the bus?
    fn recover(&mut self, now: Instant) -> bool;
    /// A frame received from the bus, if one waits.
    fn receive(&mut self) -> Option<(u16, Vec<u8>)>;
}

/// The firmware's [`Station`] on a [`BytePort`], in real time.
pub struct Driver<P: BytePort> {
    /// The port to the BMS.
    pub port: P,
    /// The firmware's station.
    pub station: Station,
    /// The configuration store (`None`: a save fails, as on a chip without
    /// a usable partition).
    pub store: Option<Store<SimFlash>>,
    /// The CAN bus (`None`: nothing acknowledges a frame).
    pub can: Option<Box<dyn CanSide>>,
    /// The Wi-Fi side (`None`: every join fails, as on a chip whose radio
    /// did not start).
    pub wifi: Option<crate::sim_wifi::SimWifi>,
    clock: Clock,
    capture: Option<CaptureWriter>,
    rx: Vec<u8>,
    deadline: Instant,
    /// Bytes sent to the BMS.
    pub tx_bytes: u64,
    /// Bytes received from the BMS.
    pub rx_bytes: u64,
}

impl<P: BytePort> Driver<P> {
    /// A bridge alone (no consumer) whose time 0 is now.
    pub fn new(port: P, config: Timing) -> Self {
        let clock = Clock::start();
        let station = crate::virtual_time::bridge_station("host", config, clock.now());
        Self::with_station(port, station, clock)
    }

    /// `station` on `port`, on `clock`.
    pub fn with_station(port: P, station: Station, clock: Clock) -> Self {
        Self {
            port,
            station,
            store: None,
            can: None,
            wifi: None,
            clock,
            capture: None,
            rx: vec![0; 512],
            deadline: 0,
            tx_bytes: 0,
            rx_bytes: 0,
        }
    }

    /// The driver's clock.
    pub fn clock(&self) -> Clock {
        self.clock
    }

    /// Records every byte from now on as a `.tbms` capture.
    pub fn record(&mut self, capture: CaptureWriter) {
        self.capture = Some(capture);
    }

    /// Stops recording and returns the writer (flushed).
    pub fn stop_recording(&mut self) -> Option<CaptureWriter> {
        let mut c = self.capture.take()?;
        let _ = c.flush();
        Some(c)
    }

    /// Does what the station asks until it waits (requests go out, frames on
    /// the bus, the record to the store); tells `on` what was sent and
    /// logged. Returns the station's next deadline.
    pub fn service(&mut self, mut on: impl FnMut(Happened<'_>)) -> io::Result<Instant> {
        if let Some(can) = self.can.as_mut() {
            while let Some((id, data)) = can.receive() {
                self.station.can_received(self.clock.now(), id, &data);
            }
        }
        if let Some(w) = self.wifi.as_mut() {
            w.deliver(self.clock.now(), &mut self.station);
        }
        loop {
            let now = self.clock.now();
            match self.station.poll(now) {
                Action::Wifi(req) => match self.wifi.as_mut() {
                    Some(w) => w.request(now, req),
                    None => self.station.wifi_unavailable(now, &req),
                },
                Action::Log(item) => {
                    let mut line = Line::new();
                    self.station.log_text(&item, &mut line);
                    on(Happened::Log(now, &item, line.as_str()));
                }
                Action::Transmit => {
                    let bytes = self.station.transmit_bytes().to_vec();
                    self.port.send(&bytes)?;
                    self.tx_bytes += bytes.len() as u64;
                    if let Some(c) = self.capture.as_mut() {
                        c.tx(&bytes)?;
                    }
                    on(Happened::Tx(&bytes));
                }
                Action::Can(f) => match self.can.as_mut() {
                    Some(can) => {
                        let r = can.send(now, &f);
                        self.station.can_sent(now, r);
                    }
                    None => self.station.can_sent(now, TxResult::Failed),
                },
                Action::CanRecover => {
                    let ok = self.can.as_mut().is_some_and(|c| c.recover(now));
                    self.station.can_recovered(now, ok);
                }
                Action::Save => {
                    let r = match self.store.as_mut() {
                        Some(store) => embassy_futures::block_on(store.save(self.station.record())),
                        None => Err(StoreError::Partition),
                    };
                    self.station.saved(r);
                }
                Action::WaitUntil(t) => {
                    self.deadline = t;
                    if let Some(due) = self.wifi.as_ref().and_then(|w| w.next_due()) {
                        self.deadline = self.deadline.min(due);
                    }
                    break;
                }
            }
        }
        Ok(self.deadline)
    }

    /// Waits for UART bytes until the station's deadline (at most `max_wait`)
    /// and hands what came to it (and to `on_rx`). Returns how many.
    pub fn receive(
        &mut self,
        max_wait: Duration,
        mut on_rx: impl FnMut(&[u8]),
    ) -> io::Result<usize> {
        let wait = self.clock.until(self.deadline).min(max_wait);
        let n = self.port.recv(&mut self.rx, wait)?;
        if n > 0 {
            let bytes = &self.rx[..n];
            self.station.handle_rx(self.clock.now(), bytes);
            self.rx_bytes += n as u64;
            if let Some(c) = self.capture.as_mut() {
                c.rx(bytes)?;
            }
            on_rx(bytes);
        }
        Ok(n)
    }

    /// Runs the station alone for `duration` (or until `stop`); its bridge's
    /// reports to `on_report`.
    pub fn run_for(
        &mut self,
        duration: Duration,
        stop: &AtomicBool,
        mut on_report: impl FnMut(Instant, &Report),
    ) -> io::Result<()> {
        let end = self.clock.now() + duration.as_micros() as u64;
        while self.clock.now() < end && !stop.load(Ordering::Relaxed) {
            self.service(|h| {
                if let Happened::Log(t, Logged::Bridge(r), _) = h {
                    on_report(t, r)
                }
            })?;
            self.receive(MAX_SLICE, |_| {})?;
        }
        Ok(())
    }
}

/// What `sim --pty` (and the simulated BMS behind `sim --bridge-pty`) is.
#[derive(Debug, Clone)]
pub struct SimOptions {
    /// The pack.
    pub pack: PackProfile,
    /// The simulator's configuration (faults, sleep, ...).
    pub config: SimConfig,
    /// Its seed.
    pub seed: u64,
    /// Settings the simulated BMS holds from the start (raw units), on top of
    /// the pack's defaults.
    pub settings: Vec<(SettingId, i32)>,
}

impl Default for SimOptions {
    fn default() -> Self {
        Self {
            pack: PackProfile::LiFePO4_16S,
            config: SimConfig {
                // As the soak: a real BMS falls asleep after a while without
                // traffic, and the bridge must wake it.
                sleep_after_us: Some(30_000_000),
                ..SimConfig::default()
            },
            seed: 1,
            settings: Vec::new(),
        }
    }
}

impl SimOptions {
    /// The simulated BMS these options describe. A setting that does not fit
    /// its Rev D range is an error.
    pub fn build(&self) -> Result<SimBms, String> {
        let mut sim = SimBms::new(self.pack, self.config.clone(), self.seed);
        for &(id, value) in &self.settings {
            let s =
                Setting::new(id, value).map_err(|e| format!("{}: {}", id.name(), e.reason()))?;
            let current = Some(sim.register(id.address()));
            let words = s
                .words(current)
                .map_err(|e| format!("{}: {}", id.name(), e.reason()))?;
            for (a, v) in words {
                sim.set_register(a, v);
            }
        }
        Ok(sim)
    }
}

/// `sim --pty`: serves `sim` on a new pseudo-terminal in real time until
/// `duration` has passed (forever when `None`) or `stop` is set. The pty's path
/// is written to `out` as the first line (flushed) before anything else.
///
/// `freeze`: (from, for) — the BMS is silent then (answers nothing).
pub fn serve_sim_pty(
    mut sim: SimBms,
    duration: Option<Duration>,
    freeze: Option<(Duration, Duration)>,
    stop: &AtomicBool,
    out: &mut dyn Write,
) -> io::Result<()> {
    let pty = Pty::open_announced(out)?;
    let clock = Clock::start();
    let end = duration.map(|d| d.as_micros() as u64);
    let mut freeze = freeze.map(|(a, f)| (a.as_micros() as u64, f.as_micros() as u64));
    let mut buf = [0u8; 512];
    let mut outbuf = Vec::new();
    while !stop.load(Ordering::Relaxed) {
        let now = clock.now();
        if end.is_some_and(|e| now >= e) {
            break;
        }
        if let Some((at, long)) = freeze {
            if now >= at {
                sim.set_silent_until(at + long);
                freeze = None;
            }
        }
        outbuf.clear();
        sim.take_output(now, &mut outbuf);
        if !outbuf.is_empty() {
            // What the pty cannot take (nobody reading) is lost, as on a UART.
            pty.write(&outbuf)?;
        }
        let mut wait = Duration::from_millis(50);
        if let Some(t) = sim.next_output_at() {
            wait = wait.min(clock.until(t.max(now) + SIM_CHUNK_US));
        }
        if let Some(e) = end {
            wait = wait.min(clock.until(e));
        }
        let n = pty.read(&mut buf, wait)?;
        if n > 0 {
            sim.host_send(clock.now(), &buf[..n]);
        }
    }
    Ok(())
}

/// The wire time of `n` bytes at 115200 8N1, µs.
pub const fn wire_time_us(n: usize) -> u64 {
    BYTE_TIME_US * n as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations() {
        assert_eq!(parse_duration("250ms").unwrap(), Duration::from_millis(250));
        assert_eq!(parse_duration("10").unwrap(), Duration::from_secs(10));
        assert_eq!(parse_duration("1.5m").unwrap(), Duration::from_secs(90));
        assert!(parse_duration("5 parsecs").is_err());
        assert!(parse_duration("-1s").is_err());
    }

    /// The firmware's bridge on the simulated BMS in real time: asleep at
    /// first, woken by the bridge's own resend, then ready with a snapshot.
    /// Bounded wait, no timing assertion.
    #[test]
    fn the_driver_wakes_the_sim_and_publishes() {
        let sim = SimOptions {
            config: SimConfig {
                start_asleep: true,
                ..SimOptions::default().config
            },
            ..SimOptions::default()
        }
        .build()
        .unwrap();
        let mut d = Driver::new(SimPort::new(sim), Timing::default());
        let stop = AtomicBool::new(false);
        let mut reports = Vec::new();
        let end = std::time::Instant::now() + Duration::from_secs(60);
        while d.station.bridge().telemetry().snapshot.is_none() && std::time::Instant::now() < end {
            d.run_for(Duration::from_millis(200), &stop, |_, r| {
                reports.push(r.to_string())
            })
            .unwrap();
        }
        let t = d.station.bridge().telemetry();
        assert!(t.ready && t.snapshot.is_some(), "{reports:#?}");
        assert!(
            d.station.bridge().link_stats().wakeup_resends >= 1,
            "{reports:#?}"
        );
        assert!(d.tx_bytes > 0 && d.rx_bytes > 0);
    }

    #[test]
    fn settings_of_the_options_are_held_by_the_sim() {
        let o = SimOptions {
            settings: vec![(SettingId::OverVoltageCutoff, 3600)],
            ..SimOptions::default()
        };
        assert_eq!(o.build().unwrap().register(315), 3600);
        let bad = SimOptions {
            settings: vec![(SettingId::OverVoltageCutoff, 9999)],
            ..SimOptions::default()
        };
        assert!(bad.build().is_err());
    }
}
