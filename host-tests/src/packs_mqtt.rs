//! `sim --packs N --mqtt HOST:PORT` and `sim --packs N --bridge-pty`: packs
//! in parallel in real time. With a broker, each bridge has its own MQTT
//! output, as a battery of Wi-Fi bridges publishes it — every pack its own
//! device (its own serial and client id), and the bridge that speaks to the
//! inverter the battery's device as well. With a pseudo-terminal, it is the
//! host link of pack 1's bridge (the primary), as its USB port: `tinybms
//! monitor` shows the packs-in-parallel panel on the desk.
//!
//! The packs are the multi-pack loop's ([`crate::multi_pack`]: physics,
//! CAN bus, each BMS at its own cutoffs), paced to the wall clock; each
//! station's published picture goes to its own session (the library's
//! publisher and session, as on the chip).

use std::io;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use tinybms_firmware::config::{value, Config, FieldId};
use tinybms_firmware::identity::{Features, Identity};
use tinybms_firmware::inverter::InverterConfig;
use tinybms_firmware::mqtt::session::Target;
use tinybms_firmware::mqtt::Settings;

use crate::mqtt::{Notes, Shared, TcpNet};
use crate::multi_pack::{MultiLoop, PackSpec};
use crate::real_time_station::sim_client_id;
use tinybms_desk::station::LINE_BUF;
use tinybms_desk::HostSide;

/// How often the loop catches up with the wall clock.
const PACE: Duration = Duration::from_millis(50);

/// The record every simulated bridge runs with: the defaults and `changes`
/// (`--config NAME=VALUE`, checked by the firmware's rules).
pub fn record(changes: &[(String, String)]) -> Result<Config, String> {
    let mut c = Config::default();
    for (name, text) in changes {
        let id =
            FieldId::from_name(name).ok_or_else(|| format!("no configuration field `{name}`"))?;
        let v =
            value::parse(id.field(), text).map_err(|e| format!("{name} = {text}: {}", e.detail))?;
        c.set(id, v.as_value())
            .map_err(|e| format!("{name} = {text}: {}", e.detail))?;
    }
    Ok(c)
}

/// What is running: the loop and each pack's session notes.
pub struct PacksOnMqtt {
    /// The packs.
    pub packs: MultiLoop,
    /// Each pack's MQTT feed (none without a broker).
    pub shared: Vec<Shared>,
    /// Each pack's session notes (none without a broker).
    pub notes: Vec<Notes>,
    clock: tinybms_desk::Clock,
    input: Vec<u8>,
    line: Vec<u8>,
}

impl PacksOnMqtt {
    /// `n` packs (2-8) charging from 60 % on, each bridge publishing to
    /// `broker` (`host:port`) with `record`'s network fields, or to none;
    /// pack 1's bridge with its host link when `primary_host`.
    pub fn start(
        n: usize,
        inverter: InverterConfig,
        (broker, primary_host): (Option<(&str, u16)>, bool),
        record: &Config,
        seed: u64,
        log: bool,
    ) -> Result<Self, String> {
        let specs = PackSpec::alike(n.clamp(2, 8), |k| 60.0 + 2.0 * k as f64);
        let mut packs = MultiLoop::with_packs_and_host(inverter, &specs, 100.0, seed, primary_host);
        let clock = tinybms_desk::Clock::start();
        let mut shared = Vec::new();
        let mut notes = Vec::new();
        for p in &mut packs.nodes {
            // Nothing kept for figures: this runs as long as the owner likes.
            p.h.retain = false;
            let Some((host, port)) = broker else {
                continue;
            };
            let mut target = Target::from_config(record, &sim_client_id(&p.h.sim));
            target.host.clear();
            target
                .host
                .push_str(host)
                .map_err(|_| "--mqtt: the host name is longer than 64 bytes".to_string())?;
            target.port = port;
            let bridge = Identity::desktop(
                "sim",
                Features {
                    can: true,
                    wifi: true,
                    ..Features::default()
                },
            );
            let s = Shared::default();
            notes.push(crate::mqtt::spawn(
                target,
                (Settings::from_config(record), bridge),
                s.clone(),
                clock,
                TcpNet::default(),
                log,
            ));
            shared.push(s);
        }
        Ok(Self {
            packs,
            shared,
            notes,
            clock,
            input: Vec::new(),
            line: vec![0; LINE_BUF],
        })
    }

    /// Runs until `duration` has passed (for ever without one) or `stop`;
    /// `host`, when given, is on pack 1's host link.
    pub fn run(
        &mut self,
        duration: Option<Duration>,
        stop: &AtomicBool,
        mut host: Option<&mut dyn HostSide>,
    ) -> io::Result<()> {
        let end = duration.map(|d| d.as_micros() as u64);
        if let (Some(_), Some(primary)) = (host.as_ref(), self.packs.nodes.first_mut()) {
            // A host on the USB port from the start, as `sim --bridge-pty`.
            primary.h.station.host_connected(self.clock.now());
        }
        while !stop.load(Ordering::Relaxed) && end.is_none_or(|e| self.clock.now() < e) {
            let now = self.clock.now();
            self.packs.run_until(now);
            for (k, (p, s)) in self.packs.nodes.iter_mut().zip(&self.shared).enumerate() {
                p.h.station
                    .wifi_rssi(Some(crate::mqtt::simulated_rssi(now, k)));
                s.update(&mut p.h.station, now);
            }
            if let (Some(side), Some(primary)) = (host.as_deref_mut(), self.packs.nodes.first_mut())
            {
                self.input.clear();
                side.read(&mut self.input)?;
                if !self.input.is_empty() {
                    primary.h.station.host_rx(now, &self.input);
                }
                while side.can_take() {
                    match primary.h.station.next_host_line(now, &mut self.line) {
                        Some(n) => side.write_line(self.line.get(..n).unwrap_or(&[]))?,
                        None => break,
                    }
                }
            }
            std::thread::sleep(PACE);
        }
        Ok(())
    }
}
