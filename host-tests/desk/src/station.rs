//! The firmware's station with its host link, its configuration store and
//! its boot lines, as the chip's station task runs it: the station does
//! what it decides (requests, logs, saves), host bytes go in, and lines come
//! out only when the host side can take them — otherwise they wait in the
//! host link's bounded queue, which drops telemetry first.

use std::io;
use std::sync::mpsc;
use std::time::Duration;

use embassy_futures::block_on;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::state::Note;
use tinybms_firmware::config::Config;
use tinybms_firmware::identity::{Features, Identity};
use tinybms_firmware::station::{Logged, Setup, Station};
use tinybms_firmware::update::otadata::Cause;
use tinybms_firmware::Instant;

use crate::driver::{BytePort, Clock, Driver, Happened};
use crate::flash::{DeskFlash, RamFlash};
use crate::MAX_SLICE;

/// Where a desktop station's store lives: a 4 MiB chip with the default
/// partition table's `nvs` partition (what its flash stands for:
/// [`crate::flash::PARTITION_BYTES`]); `hello` and `tinybms version` say it.
pub const STORE_SITE: tinybms_firmware::config::store::StoreSite =
    tinybms_firmware::config::store::StoreSite {
        flash_bytes: 4 * 1024 * 1024,
        partition: Some((0x9000, crate::flash::PARTITION_BYTES)),
        lookup: None,
    };

/// Something that runs beside the station, once a round, before the lines
/// go out (the MQTT output of `sim --mqtt`, as the chip's MQTT task).
pub trait Beside {
    /// One round at `now`.
    fn round(&mut self, station: &mut Station, now: Instant);
}

/// Longest line the host link produces that this loop can carry.
pub const LINE_BUF: usize = 4096;

/// The host's end of the host link.
pub trait HostSide {
    /// Appends the bytes the host sent since the last call (never waits).
    fn read(&mut self, into: &mut Vec<u8>) -> io::Result<()>;
    /// True when a line can be written now without waiting.
    fn can_take(&mut self) -> bool;
    /// Writes one `\n`-terminated line.
    fn write_line(&mut self, line: &[u8]) -> io::Result<()>;
}

/// The station (bridge, host link, inverter output, configuration) on a byte
/// port.
pub struct Hosted<P: BytePort> {
    /// What the station was built with (a restart builds it again).
    pub setup: Setup,
    /// The station on its port.
    pub driver: Driver<P>,
    /// The BOOT button: held from this time (µs) for this long, if ever
    /// (`sim --bridge-pty --boot-button`).
    pub boot_button: Option<(u64, u64)>,
    /// What runs beside the station (`sim --mqtt`'s MQTT output).
    pub beside: Option<Box<dyn Beside>>,
    /// Print every log line to stderr, as the device logs it.
    pub log: bool,
    /// The bridge's name on the network (Improv's device name).
    pub network_name: Option<String>,
    /// The update port on the network (`sim --bridge-pty --update-port`).
    pub update_port: Option<crate::update_port::UpdatePort>,
    line: Vec<u8>,
    input: Vec<u8>,
    next_sample: u64,
}

/// Rounds of lines and flash reads a step gives a history listing.
const LISTING_ROUNDS: usize = 256;

impl<P: BytePort> Hosted<P> {
    /// The station at time 0 (now), with the configuration record in `flash`
    /// (the defaults when it holds none; `chip` names the host link's chip).
    /// The host link has not seen a connection yet: call [`Hosted::connected`].
    pub fn new(port: P, bridge: Timing, flash: DeskFlash, chip: &'static str) -> Self {
        Self::with_wifi(port, bridge, flash, chip, true)
    }

    /// [`Hosted::new`] standing for an image with or without Wi-Fi (what its
    /// `hello` says is built in).
    pub fn with_wifi(
        port: P,
        bridge: Timing,
        flash: DeskFlash,
        chip: &'static str,
        wifi: bool,
    ) -> Self {
        Self::build(port, bridge, flash, chip, wifi, None)
    }

    /// The tool's direct mode: a station that runs with `record`, chosen by
    /// the tool itself (streaming off), in RAM. No bridge of its own is
    /// configured, so its log says nothing about a configuration (it said
    /// "config saved to flash" as if the owner had changed one).
    /// It has no CAN output: the computer it runs on drives no inverter, so
    /// neither the live view nor the log tells of one.
    pub fn direct(port: P, bridge: Timing, record: Config, chip: &'static str) -> Self {
        let flash = DeskFlash::Ram(RamFlash::new());
        Self::build(port, bridge, flash, chip, true, Some(record))
    }

    fn build(
        port: P,
        bridge: Timing,
        flash: DeskFlash,
        chip: &'static str,
        wifi: bool,
        record: Option<Config>,
    ) -> Self {
        let clock = Clock::start();
        let mut store = crate::flash::store(flash);
        // The CAN output is built in, as in the ready-made images; a bus
        // with a simulated inverter is attached by `sim` (else nothing
        // acknowledges a frame, as on a chip whose CAN is not wired). The
        // tool's direct mode has none.
        let direct = record.is_some();
        let mut setup = Setup {
            timing: bridge,
            identity: Identity::desktop(
                chip,
                Features {
                    host_link: true,
                    store: true,
                    wifi,
                    can: !direct,
                },
            ),
            inverter: None,
        };
        // A device has a chip flash with two app slots (the tool's own
        // bridge of direct mode is none).
        let chip = (!direct).then(|| crate::ota::ChipFlash(crate::ota::chip_flash()));
        let image = chip
            .as_ref()
            .map(|c| boot_image(&c.0, &mut setup, Cause::PowerCut));
        let mut station = match record {
            Some(config) => Station::with_record(setup, config, clock.now()),
            None => Station::new(setup, block_on(store.load()), clock.now()),
        };
        let panics = image.as_ref().is_some_and(|(_, p)| *p);
        if let Some((ota, _)) = image {
            station.set_ota(ota);
        }
        let mut chip = chip;
        if let Some(c) = chip.as_mut() {
            station.set_history(clock.now(), open_history(c), None);
        }
        let mut driver = Driver::with_station(port, station, clock);
        driver.panics_before_confirm = panics;
        driver.store = Some(store);
        driver.ota = chip;
        let mut h = Self {
            setup,
            driver,
            boot_button: None,
            beside: None,
            log: false,
            network_name: None,
            update_port: None,
            line: vec![0; LINE_BUF],
            input: Vec::new(),
            next_sample: 0,
        };
        // The tool's own bridge of direct mode is no device: it has no boot
        // and no flash.
        if !direct {
            h.boot_lines();
        }
        h
    }

    /// The lines the chip shell writes at boot, as a simulated bridge has
    /// them (a simulated board, CAN bus and BMS): the host link keeps them
    /// for every host, as on the chip.
    fn boot_lines(&mut self) {
        use tinybms_firmware::text::Boot;
        self.driver.station.set_store_site(STORE_SITE);
        let running = self.driver.station.config().running();
        let inverter = running.inverter();
        let mut lines = vec![Boot::Image { log: None }];
        if self.setup.identity.features.can {
            lines.push(if inverter.enabled {
                Boot::Can {
                    protocol: inverter.protocol,
                    pins: None,
                    node: inverter.node,
                }
            } else {
                Boot::CanOff
            });
        }
        lines.push(Boot::HostLink {
            wire: None,
            read_only: running.read_only,
            stream_period_ms: running.stream_period_ms,
        });
        lines.push(Boot::Uart {
            baud: 115_200,
            pins: None,
        });
        for l in &lines {
            self.driver.station.boot_line(l);
        }
    }

    /// A restart of the chip: the station built again from what its store
    /// holds (the port, the CAN bus and the clock stay). Call
    /// [`Hosted::connected`] after it when a host is there.
    pub fn restart(&mut self) {
        self.restart_after(Cause::Reset);
    }

    /// [`Hosted::restart`] after `cause` (what the next boot's trial reads).
    pub fn restart_after(&mut self, cause: Cause) {
        let loaded = match self.driver.store.as_mut() {
            Some(store) => block_on(store.load()),
            None => return,
        };
        let now = self.driver.clock().now();
        // The image booted names the station (its version).
        let image = self
            .driver
            .ota
            .as_ref()
            .map(|c| boot_image(&c.0, &mut self.setup, cause));
        self.driver.station = Station::new(self.setup, loaded, now);
        if let Some(c) = self.driver.ota.as_mut() {
            let h = open_history(c);
            self.driver.station.set_history(now, h, None);
        }
        self.driver.panics_before_confirm = image.as_ref().is_some_and(|(_, p)| *p);
        self.driver.panicked = false;
        if let Some((ota, _)) = image {
            self.driver.station.set_ota(ota);
        }
        self.driver.restart_due = false;
        if let Some(u) = self.update_port.as_mut() {
            u.drop_connection();
        }
        self.boot_lines();
        self.boot_wifi();
    }

    /// The Wi-Fi side at a start: the stored network joined in the
    /// background (as the chip's Wi-Fi task does), the name the installer
    /// shows.
    pub fn boot_wifi(&mut self) {
        let now = self.driver.clock().now();
        if let Some(name) = self.network_name.clone() {
            self.driver.station.set_network_name(&name);
        }
        let record = self.driver.station.config().running().clone();
        if let Some(w) = self.driver.wifi.as_mut() {
            w.boot(now, &record);
        }
    }

    /// The station.
    pub fn station(&mut self) -> &mut Station {
        &mut self.driver.station
    }

    /// The host opened its port (queues the hello).
    pub fn connected(&mut self) {
        let now = self.driver.clock().now();
        self.driver.station.host_connected(now);
    }

    /// One round of the chip's station task: what the station wants done,
    /// host bytes in, lines out while the host side takes them, then UART
    /// bytes awaited until the next deadline (at most [`MAX_SLICE`]).
    pub fn step(&mut self, side: &mut dyn HostSide) -> io::Result<()> {
        let log = self.log;
        let print = |h: Happened<'_>| {
            if let (true, Happened::Log(at, _, text)) = (log, h) {
                eprintln!("{:>10.3}s {text}", at as f64 / 1e6);
            }
        };
        self.driver.service(print)?;
        // An installed update restarts the chip; an image that "panics"
        // resets it before it confirms itself.
        let now = self.driver.clock().now();
        if self.driver.restart_due {
            self.restart_after(Cause::Reset);
            if self.log {
                eprintln!(
                    "{:>10.3}s restarted ({})",
                    now as f64 / 1e6,
                    self.setup.identity.firmware
                );
            }
        } else if self.driver.panicked {
            if self.log {
                eprintln!("{:>10.3}s the image panicked (simulated)", now as f64 / 1e6);
            }
            self.restart_after(Cause::Panic);
        }
        self.input.clear();
        side.read(&mut self.input)?;
        if !self.input.is_empty() {
            let now = self.driver.clock().now();
            self.driver.station.host_rx(now, &self.input);
            // A submitted command may have something to send at once.
            self.driver.service(print)?;
        }
        let now = self.driver.clock().now();
        if let Some((from, long)) = self.boot_button {
            if now >= self.next_sample {
                self.next_sample = now + tinybms_firmware::config::button::SAMPLE_PERIOD_US;
                let pressed = now >= from && now < from + long;
                self.driver.station.button(now, pressed);
            }
        }
        if let Some(b) = self.beside.as_mut() {
            b.round(&mut self.driver.station, now);
        }
        if let Some(u) = self.update_port.as_mut() {
            u.round(&mut self.driver.station, now);
        }
        // A listing of the history reads a record between two lines (the
        // station's flash reads): as the chip's task loop does, without
        // waiting for the next deadline in between.
        for _ in 0..LISTING_ROUNDS {
            let mut wrote = false;
            while side.can_take() {
                match self.driver.station.next_host_line(now, &mut self.line) {
                    Some(n) => {
                        side.write_line(self.line.get(..n).unwrap_or(&[]))?;
                        wrote = true;
                    }
                    None => break,
                }
            }
            if !(wrote && self.driver.station.history().listing()) {
                break;
            }
            self.driver.service(print)?;
        }
        let mut wait = MAX_SLICE;
        if self.boot_button.is_some() {
            wait = wait.min(Duration::from_micros(
                tinybms_firmware::config::button::SAMPLE_PERIOD_US,
            ));
        }
        self.driver.receive(wait, |_| {})?;
        Ok(())
    }
}

impl<P: BytePort> Hosted<P> {
    /// Changes the configuration record by name (text values, as `tinybms
    /// config NAME=VALUE`) and stores it: the start-up options of `sim
    /// --bridge-pty`. A refusal is an error naming the field.
    pub fn change_config(&mut self, changes: &[(String, String)]) -> Result<(), String> {
        use tinybms_firmware::config::state::Outcome;
        use tinybms_firmware::config::{value, FieldId};
        if changes.is_empty() {
            return Ok(());
        }
        let mut parsed = Vec::new();
        for (name, text) in changes {
            let id = FieldId::from_name(name)
                .ok_or_else(|| format!("no configuration field `{name}`"))?;
            let v = value::parse(id.field(), text)
                .map_err(|e| format!("{name} = {text}: {}", e.detail))?;
            parsed.push((id, v));
        }
        let now = self.driver.clock().now();
        for (id, o) in self.driver.station.change_config(now, &parsed) {
            if let Outcome::Refused(e) = o {
                return Err(format!("{}: {}", id.name(), e.detail));
            }
            if let Outcome::RuleBroken(d, _) = o {
                return Err(format!("{}: {d}", id.name()));
            }
        }
        // Before any request: the link is quiet, the save goes now.
        let mut failed = None;
        self.driver
            .service(|h| {
                if let Happened::Log(_, Logged::Config(Note::SaveFailed(e)), _) = h {
                    failed = Some(e.reason());
                }
            })
            .map_err(|e| e.to_string())?;
        match failed {
            Some(reason) => Err(format!("saving the configuration: {reason}")),
            None => Ok(()),
        }
    }
}

/// A boot of the chip flash: the update side for the station, and whether
/// the image booted "panics" (see [`crate::ota`]). `setup` takes the
/// image's version.
fn boot_image(
    flash: &crate::flash::RamFlash,
    setup: &mut Setup,
    cause: Cause,
) -> (tinybms_firmware::update::Ota, bool) {
    let image = crate::ota::boot(flash, cause);
    let version = image
        .version
        .as_deref()
        .unwrap_or(tinybms_firmware::identity::FIRMWARE);
    if setup.identity.firmware != version {
        // One string per image booted, kept for the program's life.
        setup.identity.firmware = Box::leak(version.to_string().into_boxed_str());
    }
    (image.ota, image.panics)
}

/// The host side as channels (the tool's direct mode): bytes in, lines out.
pub struct ChannelSide {
    /// Host bytes.
    pub from_host: mpsc::Receiver<Vec<u8>>,
    /// Lines to the host (without their newline).
    pub to_host: mpsc::Sender<String>,
}

impl HostSide for ChannelSide {
    fn read(&mut self, into: &mut Vec<u8>) -> io::Result<()> {
        while let Ok(b) = self.from_host.try_recv() {
            into.extend_from_slice(&b);
        }
        Ok(())
    }

    fn can_take(&mut self) -> bool {
        true
    }

    fn write_line(&mut self, line: &[u8]) -> io::Result<()> {
        let text = String::from_utf8_lossy(line);
        let text = text.trim_end_matches(['\n', '\r']);
        self.to_host
            .send(text.to_string())
            .map_err(|_| io::Error::new(io::ErrorKind::BrokenPipe, "the tool stopped listening"))
    }
}

/// No host on the host link (`sim --mqtt` without `--bridge-pty`).
pub struct NoHost;

impl HostSide for NoHost {
    fn read(&mut self, _: &mut Vec<u8>) -> io::Result<()> {
        Ok(())
    }
    fn can_take(&mut self) -> bool {
        true
    }
    fn write_line(&mut self, _: &[u8]) -> io::Result<()> {
        Ok(())
    }
}

/// The history in the desktop chip's flash (its `history` partition), as the
/// chip opens it at boot.
pub fn open_history(chip: &mut crate::ota::ChipFlash) -> tinybms_firmware::history::log::History {
    use tinybms_firmware::history::log::{find, History};
    let range = find(chip, crate::ota::CHIP_BYTES as u32);
    History::open(chip, range)
}
