//! The desktop station ([`tinybms_desk::Hosted`]: the firmware's station in
//! real time, shared with the tool) against the simulated BMS, CAN bus and
//! Wi-Fi: what `sim --bridge-pty` and `sim --mqtt` run, with the host side on
//! a pseudo-terminal ([`PtySide`]).

use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use protocol_core::settings::SettingId;
use tinybms_desk::flash::{DeskFlash, FileFlash, RamFlash};
use tinybms_desk::station::Beside;
use tinybms_desk::{HostSide, Hosted, NoHost};
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::station::Station;
use tinybms_firmware::Instant;

use crate::pty::Pty;
use crate::real_time::SimPort;
use crate::sim::SimBms;

/// The MQTT output beside a desktop station, as the chip's MQTT task: the
/// feed it publishes from, and the session's notes, whose latest state goes
/// to the station (`hello`).
pub struct MqttBeside {
    /// The MQTT output's feed.
    pub feed: crate::mqtt::Shared,
    /// The MQTT session's notes, when a session runs.
    pub notes: Option<crate::mqtt::Notes>,
    noted: usize,
}

impl MqttBeside {
    /// Beside a station whose feed is `feed` (and session's notes `notes`).
    pub fn new(feed: crate::mqtt::Shared, notes: Option<crate::mqtt::Notes>) -> Self {
        Self {
            feed,
            notes,
            noted: 0,
        }
    }
}

impl Beside for MqttBeside {
    fn round(&mut self, station: &mut Station, now: Instant) {
        // The Wi-Fi task's reading, as on a chip (this bridge's MQTT runs
        // over the desktop's network: a simulated signal).
        station.wifi_rssi(Some(crate::mqtt::simulated_rssi(now, 0)));
        self.feed.update(station, now);
        if let Some(notes) = &self.notes {
            let notes = notes.lock().unwrap_or_else(|e| e.into_inner());
            if notes.len() > self.noted {
                self.noted = notes.len();
                if let Some(n) = notes.last() {
                    station.mqtt_state(n.state());
                }
            }
        }
    }
}

/// The host side on a pseudo-terminal (`sim --bridge-pty`).
pub struct PtySide<'a> {
    pty: &'a Pty,
    buf: Vec<u8>,
    /// The rest of a line the pty could not take whole yet, and since when
    /// it waits.
    rest: Vec<u8>,
    stuck_since: Option<std::time::Instant>,
    patience: Duration,
}

/// A line the pty cannot take waits this long for the reader to drain it;
/// past it, nobody is taken to be reading: the backlog is discarded.
pub const PTY_STUCK: Duration = Duration::from_secs(2);

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
            rest: Vec::new(),
            stuck_since: None,
            patience: PTY_STUCK,
        }
    }

    /// On `pty`, waiting `patience` (not [`PTY_STUCK`]) for a reader.
    pub fn with_patience(pty: &'a Pty, patience: Duration) -> Self {
        Self {
            patience,
            ..Self::new(pty)
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
        // The rest of a line the pty could not take whole: a reader drains
        // it (a listing longer than the pty holds, ~18 KB, comes out as fast
        // as it is read); one that does not for PTY_STUCK is not there, and
        // what the pty holds is stale for whoever opens it next: discarded.
        if !self.rest.is_empty() {
            let n = self.pty.write(&self.rest).unwrap_or(0);
            self.rest.drain(..n.min(self.rest.len()));
            if !self.rest.is_empty() {
                let since = *self.stuck_since.get_or_insert_with(std::time::Instant::now);
                if since.elapsed() < self.patience {
                    return false;
                }
                self.pty.discard_unread();
                self.rest.clear();
            }
        }
        self.stuck_since = None;
        true
    }

    fn write_line(&mut self, line: &[u8]) -> io::Result<()> {
        let n = self.pty.write(line)?;
        if n < line.len() {
            self.rest.extend_from_slice(line.get(n..).unwrap_or(&[]));
        }
        Ok(())
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
    /// Stand for this board's image (`--board`): its chip and name in
    /// `hello`, what an update file must name.
    pub board: Option<String>,
    /// The update port on the network at this address (`--update-port`).
    pub update_port: Option<std::net::SocketAddr>,
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
        Some(path) => DeskFlash::File(FileFlash::open(path)?),
        None => DeskFlash::Ram(RamFlash::new()),
    };
    let client_id = sim_client_id(&sim);
    let mut h = Hosted::with_wifi(SimPort::new(sim), o.bridge, flash, "sim", !o.no_wifi);
    let board = o.board.as_deref().and_then(|n| {
        tinybms_firmware::boards::BOARDS
            .iter()
            .find(|b| b.name == n)
    });
    if let Some(b) = board {
        h.setup.identity.board = b.name;
        h.setup.identity.chip = b.chip.name();
    }
    h.change_config(&o.config).map_err(io::Error::other)?;
    // Start-up options are what the bridge boots with: the changes stored,
    // then a restart, so those that apply at the next restart (the MQTT
    // topics, discovery, the inverter protocol) apply now.
    if !o.config.is_empty() || board.is_some() {
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
        h.driver.wifi = Some(Box::new(crate::sim_wifi::SimWifi::new(
            o.wifi_networks.clone(),
        )));
    }
    if let Some(addr) = o.update_port {
        let port = tinybms_desk::update_port::UpdatePort::bind(addr)?;
        if o.log {
            eprintln!("update port: {}", port.local_addr()?);
        }
        h.update_port = Some(port);
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
        let notes = crate::mqtt::spawn(
            target,
            (
                tinybms_firmware::mqtt::Settings::from_config(&record),
                h.setup.identity,
            ),
            shared.clone(),
            clock,
            crate::mqtt::TcpNet::default(),
            o.log,
        );
        h.beside = Some(Box::new(MqttBeside::new(shared, Some(notes))));
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;
    use std::sync::mpsc;

    /// Nobody reads the pty for a while (no client, or one that stopped): the
    /// lines written meanwhile must never be cut. The pty takes ~18 KB, FIONREAD
    /// counts only what the line discipline moved to its read buffer (≤ 4 KB),
    /// so the backlog check alone never fired and the write that met the full
    /// buffer left half a line in it. A client that then reads gets whole lines.
    #[test]
    fn unread_pty_never_gets_cut_lines() {
        let pty = Pty::open().unwrap();
        // Nobody reads: no wait (the sim waits PTY_STUCK) before the backlog
        // goes.
        let mut side = PtySide::with_patience(&pty, Duration::ZERO);
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
        // The rounds go on while the client reads: the rest of a line the
        // pty took only in part follows it.
        while let Ok(b) = rx.recv_timeout(Duration::from_millis(500)) {
            got.extend_from_slice(&b);
            side.can_take();
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
