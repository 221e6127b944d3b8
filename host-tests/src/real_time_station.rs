//! The firmware's station in real time: what the ESP32 runs, on the desktop.
//! Used by `sim --bridge-pty` (the host side on a pseudo-terminal, the BMS
//! simulated), `sim --mqtt` and by `tinybms` in direct mode (the host side an
//! in-process channel, the BMS on a USB-UART adapter).
//!
//! The loop is the chip's station task: the station does what it decides
//! (requests, logs, saves), host bytes go in, and lines come out only when
//! the host side can take them — otherwise they wait in the host link's
//! bounded queue, which drops telemetry first.

use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::time::Duration;

use embassy_futures::block_on;
use protocol_core::settings::SettingId;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::state::Note;
use tinybms_firmware::config::Config;
use tinybms_firmware::identity::{Features, Identity};
use tinybms_firmware::station::{Logged, Setup, Station};

use crate::flash::SimFlash;
use crate::pty::Pty;
use crate::real_time::{BytePort, Driver, Happened, SimPort, MAX_SLICE};
use crate::sim::SimBms;

/// Where a simulated bridge's store lives: a 4 MiB chip with the default
/// partition table's `nvs` partition (what the simulated flash stands for:
/// [`crate::flash::PARTITION_BYTES`]); `hello` and `tinybms version` say it.
pub const SIM_STORE_SITE: tinybms_firmware::config::store::StoreSite =
    tinybms_firmware::config::store::StoreSite {
        flash_bytes: 4 * 1024 * 1024,
        partition: Some((0x9000, crate::flash::PARTITION_BYTES)),
        lookup: None,
    };

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
    /// The MQTT output's feed, when it runs (`sim --mqtt`).
    pub mqtt: Option<crate::mqtt::Shared>,
    /// The MQTT session's notes, when it runs: their latest state goes to
    /// the station (`hello`), as the chip's MQTT task hands it on.
    pub mqtt_notes: Option<crate::mqtt::Notes>,
    mqtt_noted: usize,
    /// Print every log line to stderr, as the device logs it.
    pub log: bool,
    /// The bridge's name on the network (Improv's device name).
    pub network_name: Option<String>,
    line: Vec<u8>,
    input: Vec<u8>,
    next_sample: u64,
}

impl<P: BytePort> Hosted<P> {
    /// The station at time 0 (now), with the configuration record in `flash`
    /// (the defaults when it holds none; `chip` names the host link's chip).
    /// The host link has not seen a connection yet: call [`Hosted::connected`].
    pub fn new(port: P, bridge: Timing, flash: SimFlash, chip: &'static str) -> Self {
        Self::with_wifi(port, bridge, flash, chip, true)
    }

    /// [`Hosted::new`] standing for an image with or without Wi-Fi (what its
    /// `hello` says is built in).
    pub fn with_wifi(
        port: P,
        bridge: Timing,
        flash: SimFlash,
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
        let flash = SimFlash::Ram(crate::flash::RamFlash::new());
        Self::build(port, bridge, flash, chip, true, Some(record))
    }

    fn build(
        port: P,
        bridge: Timing,
        flash: SimFlash,
        chip: &'static str,
        wifi: bool,
        record: Option<Config>,
    ) -> Self {
        let clock = crate::real_time::Clock::start();
        let mut store = crate::flash::store(flash);
        // The CAN output is built in, as in the ready-made images; a bus
        // with a simulated inverter is attached by `sim` (else nothing
        // acknowledges a frame, as on a chip whose CAN is not wired). The
        // tool's direct mode has none.
        let direct = record.is_some();
        let setup = Setup {
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
        let station = match record {
            Some(config) => Station::with_record(setup, config, clock.now()),
            None => Station::new(setup, block_on(store.load()), clock.now()),
        };
        let mut driver = Driver::with_station(port, station, clock);
        driver.store = Some(store);
        let mut h = Self {
            setup,
            driver,
            boot_button: None,
            mqtt: None,
            mqtt_notes: None,
            mqtt_noted: 0,
            log: false,
            network_name: None,
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
        self.driver.station.set_store_site(SIM_STORE_SITE);
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
        let loaded = match self.driver.store.as_mut() {
            Some(store) => block_on(store.load()),
            None => return,
        };
        let now = self.driver.clock().now();
        self.driver.station = Station::new(self.setup, loaded, now);
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
        if let Some(m) = &self.mqtt {
            // The Wi-Fi task's reading, as on a chip (this bridge's MQTT runs
            // over the desktop's network: a simulated signal).
            self.driver
                .station
                .wifi_rssi(Some(crate::mqtt::simulated_rssi(now, 0)));
            m.update(&mut self.driver.station, now);
        }
        if let Some(notes) = &self.mqtt_notes {
            let notes = notes.lock().unwrap_or_else(|e| e.into_inner());
            if notes.len() > self.mqtt_noted {
                self.mqtt_noted = notes.len();
                if let Some(n) = notes.last() {
                    self.driver.station.mqtt_state(n.state());
                }
            }
        }
        while side.can_take() {
            match self.driver.station.next_host_line(now, &mut self.line) {
                Some(n) => side.write_line(self.line.get(..n).unwrap_or(&[]))?,
                None => break,
            }
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

/// The host side on a pseudo-terminal (`sim --bridge-pty`).
pub struct PtySide<'a> {
    pty: &'a Pty,
    buf: Vec<u8>,
}

/// Unread bytes on the pty beyond which nobody is taken to be reading: the
/// backlog is discarded (stale for whoever opens the path next) and lines wait
/// in the host link's queue.
pub const PTY_BACKLOG: usize = 8192;

impl<'a> PtySide<'a> {
    /// On `pty`.
    pub fn new(pty: &'a Pty) -> Self {
        Self {
            pty,
            buf: vec![0; 1024],
        }
    }
}

impl HostSide for PtySide<'_> {
    fn read(&mut self, into: &mut Vec<u8>) -> io::Result<()> {
        loop {
            let n = self.pty.read(&mut self.buf, Duration::ZERO)?;
            if n == 0 {
                return Ok(());
            }
            into.extend_from_slice(self.buf.get(..n).unwrap_or(&[]));
        }
    }

    fn can_take(&mut self) -> bool {
        if self.pty.unread() >= PTY_BACKLOG {
            self.pty.discard_unread();
            return false;
        }
        true
    }

    fn write_line(&mut self, line: &[u8]) -> io::Result<()> {
        if self.pty.write(line)? < line.len() {
            // The pty is full (~18 KB; FIONREAD in `can_take` sees only the
            // line discipline's ≤ 4 KB, so the backlog check does not catch
            // it): nobody reads. What it holds is stale and the part of this
            // line in it would reach the next reader cut: discard it all, then
            // write the line whole (or, should even that not fit, nothing).
            self.pty.discard_unread();
            if self.pty.write(line)? < line.len() {
                self.pty.discard_unread();
            }
        }
        Ok(())
    }
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

/// What `sim --bridge-pty` runs.
#[derive(Debug, Clone)]
pub struct BridgePtyOptions {
    /// Changes to the configuration record at start, as `tinybms config NAME=VALUE`
    /// would make them (stored: `--read-only`, `--stream-period`, `--config`).
    pub config: Vec<(String, String)>,
    /// The file that holds the configuration record (`--flash`); `None`: RAM.
    pub flash: Option<std::path::PathBuf>,
    /// Hold the BOOT button from this time for this long (`--boot-button`).
    pub boot_button: Option<(Duration, Duration)>,
    /// Open the host link's pty (`--bridge-pty`); without it the host link
    /// has no host.
    pub pty: bool,
    /// Publish to this MQTT broker (`--mqtt HOST:PORT`), with the record's
    /// network fields.
    pub mqtt: Option<(String, u16)>,
    /// Settings written through write/verify at start, as the firmware's
    /// profile.
    pub profile: Vec<(SettingId, i32)>,
    /// The bridge's configuration.
    pub bridge: Timing,
    /// Print the bridge's log lines to stderr.
    pub log: bool,
    /// (from, for): the whole bridge stops then, as a hung chip (`--freeze`).
    pub freeze: Option<(Duration, Duration)>,
    /// Stand for an image without Wi-Fi (`--no-wifi`: its `hello` says so).
    pub no_wifi: bool,
    /// Write what the bridge sends on CAN here, as a candump log (`--can-log`).
    pub can_log: Option<std::path::PathBuf>,
    /// (at, for): the simulated BMS answers nothing then, while the bridge
    /// runs (`--bms-silent`: a cut UART wire).
    pub bms_silent: Option<(Duration, Duration)>,
    /// The Wi-Fi networks in range of the simulated radio (`--wifi-network`;
    /// none: every join is "not found").
    pub wifi_networks: Vec<crate::sim_wifi::SimNetwork>,
    /// (at, for): the simulated BMS cuts off for over-temperature then, and
    /// recovers after (`--bms-fault`).
    pub bms_fault: Option<(Duration, Duration)>,
}

/// `sim --bridge-pty`: the bridge and host link against `sim` in real time,
/// the host side on a new pty whose path is the first line written to `out`.
pub fn serve_bridge_pty(
    sim: SimBms,
    o: &BridgePtyOptions,
    duration: Option<Duration>,
    stop: &AtomicBool,
    out: &mut dyn Write,
) -> io::Result<()> {
    let flash = match &o.flash {
        Some(path) => SimFlash::File(crate::flash::FileFlash::open(path)?),
        None => SimFlash::Ram(crate::flash::RamFlash::new()),
    };
    let client_id = sim_client_id(&sim);
    let mut h = Hosted::with_wifi(SimPort::new(sim), o.bridge, flash, "sim", !o.no_wifi);
    h.change_config(&o.config).map_err(io::Error::other)?;
    // Start-up options are what the bridge boots with: the changes stored,
    // then a restart, so those that apply at the next restart (the MQTT
    // topics, discovery, the inverter protocol) apply now.
    if !o.config.is_empty() {
        h.restart();
    }
    let can_log = match &o.can_log {
        Some(path) => {
            Some(Box::new(io::BufWriter::new(std::fs::File::create(path)?)) as Box<dyn Write + Send>)
        }
        None => None,
    };
    h.driver.can = Some(Box::new(crate::sim_can::SimInverterBus::new(can_log)));
    if !o.no_wifi {
        h.driver.wifi = Some(crate::sim_wifi::SimWifi::new(o.wifi_networks.clone()));
    }
    h.network_name = Some(client_id.clone());
    h.boot_wifi();
    h.boot_button = o
        .boot_button
        .map(|(from, long)| (from.as_micros() as u64, long.as_micros() as u64));
    h.station()
        .submit_profile(&o.profile)
        .map_err(|_| io::Error::other("the profile does not fit the bridge's command queue"))?;
    h.station()
        .boot_line(&tinybms_firmware::text::Boot::Profile {
            settings: o.profile.len(),
            queued: true,
        });
    let clock = h.driver.clock();
    if let Some((host, port)) = &o.mqtt {
        let record = h.station().config().running().clone();
        let mut target = tinybms_firmware::mqtt::session::Target::from_config(&record, &client_id);
        target.host.clear();
        target
            .host
            .push_str(host)
            .map_err(|_| io::Error::other("--mqtt: the host name is longer than 64 bytes"))?;
        target.port = *port;
        let shared = crate::mqtt::Shared::default();
        h.mqtt_notes = Some(crate::mqtt::spawn(
            target,
            (
                tinybms_firmware::mqtt::Settings::from_config(&record),
                h.setup.identity,
            ),
            shared.clone(),
            clock,
            crate::mqtt::TcpNet::default(),
            o.log,
        ));
        h.mqtt = Some(shared);
    }
    let pty = if o.pty {
        Some(Pty::open_announced(out)?)
    } else {
        None
    };
    h.connected();
    let mut pty_side = pty.as_ref().map(PtySide::new);
    let mut none = NoHost;
    let end = duration.map(|d| d.as_micros() as u64);
    h.log = o.log;
    let mut freeze = o.freeze;
    let mut silent = o.bms_silent;
    let mut fault = o
        .bms_fault
        .map(|(at, long)| (at.as_micros() as u64, (at + long).as_micros() as u64, false));
    while !stop.load(Ordering::Relaxed) && end.is_none_or(|e| clock.now() < e) {
        if let Some((at, until, on)) = fault.as_mut() {
            let sim = &mut h.driver.port.sim;
            if !*on && clock.now() >= *at {
                *on = true;
                sim.inject_fault_event(protocol_core::events::EventId::OverTemperatureCutoff);
            } else if *on && clock.now() >= *until {
                sim.clear_fault();
                fault = None;
            }
        }
        if let Some((at, long)) = silent {
            if clock.now() >= at.as_micros() as u64 {
                let sim = &mut h.driver.port.sim;
                let until = clock.now() + long.as_micros() as u64;
                sim.set_silent_until(until);
                silent = None;
            }
        }
        if let Some((at, long)) = freeze {
            if clock.now() >= at.as_micros() as u64 {
                std::thread::sleep(long);
                freeze = None;
            }
        }
        match pty_side.as_mut() {
            Some(side) => h.step(side)?,
            None => h.step(&mut none)?,
        }
    }
    Ok(())
}

/// The MQTT client id of a simulated bridge: `tinybms-sim-` and the last six
/// hex digits of its BMS's serial (the Home Assistant device's name), so two
/// simulated bridges of different seeds never take each other's session.
pub fn sim_client_id(sim: &SimBms) -> String {
    let r = sim.registers();
    // The serial's bytes as the version block reads them (504-509, low byte
    // first): the last three are the high byte of 508 and both of 509.
    let tail = [
        r[508].to_le_bytes()[1],
        r[509].to_le_bytes()[0],
        r[509].to_le_bytes()[1],
    ];
    format!("tinybms-sim-{:02X}{:02X}{:02X}", tail[0], tail[1], tail[2])
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    /// Nobody reads the pty for a while (no client, or one that stopped): the
    /// lines written meanwhile must never be cut. The pty takes ~18 KB, FIONREAD
    /// counts only what the line discipline moved to its read buffer (≤ 4 KB),
    /// so the backlog check alone never fired and the write that met the full
    /// buffer left half a line in it. A client that then reads gets whole lines.
    #[test]
    fn unread_pty_never_gets_cut_lines() {
        let pty = Pty::open().unwrap();
        let mut side = PtySide::new(&pty);
        let mut written = 0usize;
        for i in 0..1000u32 {
            if side.can_take() {
                let line = format!("{{\"n\":{i},\"pad\":\"{}\"}}\n", "x".repeat(90));
                side.write_line(line.as_bytes()).unwrap();
                written += line.len();
            }
        }
        assert!(written > 64 * 1024, "{written}");
        let mut client = std::fs::OpenOptions::new()
            .read(true)
            .open(pty.path())
            .unwrap();
        let mut got = Vec::new();
        let mut buf = [0u8; 4096];
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || loop {
            match client.read(&mut buf) {
                Ok(n) if n > 0 => {
                    if tx.send(buf[..n].to_vec()).is_err() {
                        break;
                    }
                }
                _ => break,
            }
        });
        while let Ok(b) = rx.recv_timeout(Duration::from_millis(500)) {
            got.extend_from_slice(&b);
        }
        let text = String::from_utf8_lossy(&got);
        let lines: Vec<&str> = text.split_terminator('\n').collect();
        assert!(!lines.is_empty());
        for l in &lines {
            assert!(
                serde_json::from_str::<serde_json::Value>(l).is_ok(),
                "a cut line: {l:?}"
            );
        }
        assert!(text.ends_with('\n'), "ends mid-line");
    }
}
