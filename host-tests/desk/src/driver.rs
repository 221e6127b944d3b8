//! The firmware's [`Station`] on a [`BytePort`], on the wall clock: what the
//! station asks for is done (requests to the BMS, frames on the CAN side,
//! the record to the store, Wi-Fi requests), and what the port receives is
//! handed to it.

use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::store::{Loaded, Source};
use tinybms_firmware::config::store::{Store, StoreError};
use tinybms_firmware::config::Config;
use tinybms_firmware::identity::{Features, Identity};
use tinybms_firmware::improv::WifiRequest;
use tinybms_firmware::inverter::dialect::CanFrame;
use tinybms_firmware::inverter::TxResult;
use tinybms_firmware::station::{Action, Logged, Setup, Station};
use tinybms_firmware::text::Line;
use tinybms_firmware::{Instant, Report};

use crate::capture::CaptureWriter;
use crate::flash::DeskFlash;
use crate::MAX_SLICE;

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

/// The Wi-Fi side of a desktop station (the chip's Wi-Fi task).
pub trait WifiSide: Send {
    /// The station starts (boot or restart) with `record`.
    fn boot(&mut self, now: Instant, record: &Config);
    /// The station asks at `now`.
    fn request(&mut self, now: Instant, req: WifiRequest);
    /// Hands the station what is done by `now`.
    fn deliver(&mut self, now: Instant, station: &mut Station);
    /// When something is next due.
    fn next_due(&self) -> Option<Instant>;
}

/// The record of a bridge with nothing but the BMS link: the CAN output off
/// (no inverter output), everything else at its default.
pub fn bridge_only() -> Config {
    Config {
        can_output: false,
        ..Config::default()
    }
}

/// A station with nothing but the BMS link (no consumer: the record's
/// outputs all off) at `now`; `chip` names it in the host link's hello.
pub fn bridge_station(chip: &'static str, config: Timing, now: Instant) -> Station {
    let setup = Setup {
        timing: config,
        identity: Identity::desktop(
            chip,
            Features {
                can: false,
                host_link: false,
                ..Features::default()
            },
        ),
        inverter: None,
    };
    let loaded = Loaded {
        config: bridge_only(),
        source: Source::Empty,
    };
    Station::new(setup, loaded, now)
}

/// The firmware's [`Station`] on a [`BytePort`], in real time.
pub struct Driver<P: BytePort> {
    /// The port to the BMS.
    pub port: P,
    /// The firmware's station.
    pub station: Station,
    /// The configuration store (`None`: a save fails, as on a chip without
    /// a usable partition).
    pub store: Option<Store<DeskFlash>>,
    /// The CAN bus (`None`: nothing acknowledges a frame).
    pub can: Option<Box<dyn CanSide>>,
    /// The Wi-Fi side (`None`: every join fails, as on a chip whose radio
    /// did not start).
    pub wifi: Option<Box<dyn WifiSide>>,
    /// The chip's flash for updates (`None`: every update's flash work
    /// fails, as on a chip whose table has no slots).
    pub ota: Option<crate::ota::ChipFlash>,
    /// The station asked for a restart ([`Action::Restart`]); the owner of
    /// the driver restarts it.
    pub restart_due: bool,
    /// The image running stands for one that panics before it confirms
    /// itself ([`crate::ota::PANICS`]): its confirmation is a panic instead.
    pub panics_before_confirm: bool,
    /// It did: the owner restarts the driver after a panic.
    pub panicked: bool,
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
        let station = bridge_station("host", config, clock.now());
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
            ota: None,
            restart_due: false,
            panics_before_confirm: false,
            panicked: false,
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
                Action::Flash(tinybms_firmware::update::transfer::Op::Otadata(_))
                    if self.panics_before_confirm
                        && self.station.ota().trial()
                            == tinybms_firmware::update::Trial::OnTrial =>
                {
                    self.panicked = true;
                    self.deadline = now;
                    break;
                }
                Action::Flash(op) => {
                    let layout = self.station.ota().layout().copied();
                    let bytes = self.station.program_bytes().to_vec();
                    let ok = self.ota.as_mut().is_some_and(|f| {
                        tinybms_firmware::update::flash::run(f, layout.as_ref(), op, &bytes)
                    });
                    self.station.flashed(now, ok);
                }
                Action::History(op) => {
                    let ok = self
                        .ota
                        .as_mut()
                        .is_some_and(|c| tinybms_firmware::history::log::run(c, op));
                    self.station.history_done(ok);
                }
                Action::HistoryRead(at, len) => {
                    use tinybms_firmware::update::flash::OtaFlash;
                    let mut b = vec![0u8; usize::from(len)];
                    let ok = self.ota.as_mut().is_some_and(|c| c.read(at, &mut b));
                    self.station.history_read(ok.then_some(&b[..]));
                }
                Action::Restart => {
                    self.restart_due = true;
                    self.deadline = now;
                    break;
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
