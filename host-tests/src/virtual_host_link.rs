//! The firmware's host link ([`tinybms_firmware::host_link::HostLink`]) in the
//! station the chip runs, in the virtual-time harness (a host reads the lines
//! the station writes), plus the body of the `host_link` fuzz target, which the
//! tests also run on stable over random inputs.

use std::cell::Cell;
use std::rc::Rc;
use std::sync::OnceLock;

use embassy_futures::block_on;
use serde_json::Value;
use tinybms_firmware::config::state::ConfigState;
use tinybms_firmware::config::store::{Loaded, Source};
use tinybms_firmware::config::Config;
use tinybms_firmware::host_link::{HostLink, HostLinkConfig, OUT_LINE_MAX};
use tinybms_firmware::identity::{Features, Identity};
use tinybms_firmware::station::{Setup, Station};
use tinybms_firmware::{Bridge, MS, SECOND};

use crate::sim::{PackModel, SimBms, SimConfig};
use crate::virtual_time::{Harness, Saver};
use tinybms_desk::flash::RamFlash;

/// A station with a host link against the simulated BMS: the chip's wiring,
/// driven by a host in virtual time.
pub struct Rig {
    /// Station, simulated BMS and clock.
    pub h: Harness,
    /// The flash of the configuration store.
    pub flash: RamFlash,
    saves: Rc<Cell<u64>>,
}

/// A configuration record with the host link settings of `config`.
pub fn record_for(config: &HostLinkConfig) -> Config {
    Config {
        read_only: config.read_only,
        stream_period_ms: config.stream_period_ms,
        ..Config::default()
    }
}

/// Host link configuration for tests (`chip` = `sim`).
pub fn config(read_only: bool, stream_period_ms: u32) -> HostLinkConfig {
    HostLinkConfig {
        read_only,
        stream_period_ms,
        firmware: "test",
        chip: "sim",
        ..HostLinkConfig::default()
    }
}

/// [`config`] for an image with Wi-Fi (its network fields are taken).
pub fn config_with_wifi(read_only: bool, stream_period_ms: u32) -> HostLinkConfig {
    let mut c = config(read_only, stream_period_ms);
    c.features.wifi = true;
    c
}

/// A saver that writes the record to a store on `flash` and counts the saves.
pub fn ram_saver(flash: &RamFlash, saves: Rc<Cell<u64>>) -> Saver {
    let mut store = tinybms_desk::flash::store(flash.clone());
    Box::new(move |record: &Config, _: &SimBms| {
        saves.set(saves.get() + 1);
        (block_on(store.save(record)), 0)
    })
}

impl Rig {
    /// A 16S LiFePO4 simulated BMS, a fresh station with a host link at time 0.
    pub fn new(config: HostLinkConfig) -> Self {
        let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 1);
        let setup = Setup {
            timing: tinybms_firmware::bms::timing::Timing::default(),
            identity: Identity::desktop(
                config.chip,
                Features {
                    can: false,
                    host_link: true,
                    ..config.features
                },
            ),
            inverter: None,
        };
        let loaded = Loaded {
            config: record_for(&config),
            source: Source::Empty,
        };
        let mut h = Harness::with_station(sim, Station::new(setup, loaded, 0));
        h.echo = false;
        let flash = RamFlash::new();
        let saves = Rc::new(Cell::new(0));
        h.saver = Some(ram_saver(&flash, saves.clone()));
        Self { h, flash, saves }
    }

    /// A rig whose bridge is synced (ready), read by a host meanwhile.
    pub fn ready(config: HostLinkConfig) -> Self {
        let mut r = Self::new(config);
        r.run_reading(6 * SECOND);
        assert!(r.h.bridge().telemetry().ready, "bridge not ready after 6 s");
        r
    }

    /// The host link.
    pub fn link(&self) -> &HostLink {
        self.h.station.host_link().expect("the rig has a host link")
    }

    /// The host link, to drive it past the station.
    pub fn link_mut(&mut self) -> &mut HostLink {
        self.h
            .station
            .host_link_mut()
            .expect("the rig has a host link")
    }

    /// The configuration.
    pub fn config(&self) -> &ConfigState {
        self.h.station.config()
    }

    /// Saves of the configuration made.
    pub fn saves(&self) -> u64 {
        self.saves.get()
    }

    /// Runs for `us` of virtual time without reading the host link's output.
    pub fn run(&mut self, us: u64) {
        let end = self.h.now + us;
        self.h.run_until(end);
    }

    /// Holds the BOOT button for `us`, sampled as the chip's button task does,
    /// then lets it go.
    pub fn hold_button(&mut self, us: u64) {
        let period = tinybms_firmware::config::button::SAMPLE_PERIOD_US;
        let end = self.h.now + us;
        while self.h.now < end {
            let now = self.h.now;
            self.h.station.button(now, true);
            self.run(period);
        }
        let now = self.h.now;
        self.h.station.button(now, false);
    }

    /// Runs like [`Rig::run`], with a host that reads every line as it comes
    /// (every 50 ms); returns them.
    pub fn run_reading(&mut self, us: u64) -> Vec<Value> {
        let end = self.h.now + us;
        let mut out = Vec::new();
        while self.h.now < end {
            let step = (self.h.now + 50 * MS).min(end);
            self.run(step - self.h.now);
            out.extend(self.drain_all());
        }
        out
    }

    /// Sends bytes from the host.
    pub fn send(&mut self, bytes: &[u8]) {
        let now = self.h.now;
        self.h.station.host_rx(now, bytes);
    }

    /// Sends one line (a `\n` is appended).
    pub fn line(&mut self, line: &str) {
        let mut b = line.as_bytes().to_vec();
        b.push(b'\n');
        self.send(&b);
    }

    /// Every line waiting, as text (each checked to be one `\n`-terminated line).
    pub fn drain_text(&mut self) -> Vec<String> {
        let mut out = Vec::new();
        let mut buf = [0u8; OUT_LINE_MAX];
        let now = self.h.now;
        while let Some(n) = self.h.station.next_host_line(now, &mut buf) {
            out.push(check_line(buf.get(..n).unwrap_or(&[])));
        }
        out
    }

    /// Every line waiting, parsed, but the bridge's own `log` lines (see
    /// [`Rig::drain_all`]).
    pub fn drain(&mut self) -> Vec<Value> {
        let mut out = self.drain_all();
        out.retain(|l| l["type"] != "log");
        out
    }

    /// Every line waiting, parsed, `log` lines included.
    pub fn drain_all(&mut self) -> Vec<Value> {
        self.drain_text()
            .iter()
            .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
            .collect()
    }
}

/// Checks the framing of one output line and returns it without its `\n`.
pub fn check_line(bytes: &[u8]) -> String {
    let text = std::str::from_utf8(bytes).expect("output is UTF-8");
    let body = text.strip_suffix('\n').expect("output line ends with \\n");
    assert!(!body.contains('\n'), "one line: {text:?}");
    let v: Value = serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {body}"));
    assert!(v.get("type").and_then(Value::as_str).is_some(), "{body}");
    body.to_string()
}

/// A synced bridge, made once (cloned for every fuzz input).
fn ready_bridge() -> &'static Bridge {
    static READY: OnceLock<Bridge> = OnceLock::new();
    READY.get_or_init(|| Rig::ready(config(false, 0)).h.bridge().clone())
}

/// The `host_link` fuzz target's body (host-tests/fuzz/fuzz_targets/host_link.rs).
///
/// Input: byte 0 = chunk size (0: byte at a time); byte 1 bit 0 = read-only, bit 1
/// = bridge not synced yet; the rest = bytes from the host. They are fed in chunks
/// to a host link over a synced bridge (no UART traffic: commands only queue), and
/// its output drained after each chunk. Beyond "never panics": every output line
/// is one `\n`-terminated JSON object with a `type`, and unless a `set`, `reset`
/// or `clear` was `accepted`, nothing reached the bridge.
pub fn fuzz_one(data: &[u8]) {
    let (chunk, flags, input) = match data {
        [c, f, rest @ ..] => (usize::from(*c), *f, rest),
        _ => return,
    };
    let mut bridge = if flags & 2 != 0 {
        Bridge::new(tinybms_firmware::bms::timing::Timing::default(), 0)
    } else {
        ready_bridge().clone()
    };
    let host = config(flags & 1 != 0, 100);
    let mut link = HostLink::new(host, 0);
    let mut cfg = ConfigState::new(record_for(&host), Source::Empty);
    let before = cfg.stored().clone();
    let mut writes_accepted = 0usize;
    let mut config_accepted = 0usize;
    let mut buf = [0u8; OUT_LINE_MAX];
    let mut now = 0;
    for piece in input.chunks(chunk.max(1)) {
        now += 10 * MS;
        link.handle_rx(
            now,
            piece,
            &mut bridge,
            &mut cfg,
            &mut tinybms_firmware::update::Ota::default(),
        );
        link.poll(now, &bridge);
        while let Some(n) = link.next_line(now, &bridge, &cfg, &mut buf) {
            let line = check_line(buf.get(..n).unwrap_or(&[]));
            let v: Value = serde_json::from_str(&line).unwrap_or(Value::Null);
            let cmd = v["cmd"].as_str().unwrap_or("");
            if v["type"] == "accepted" && ["set", "reset", "clear"].contains(&cmd) {
                writes_accepted += 1;
            }
            if v["type"] == "accepted" && ["set_config", "reset_config"].contains(&cmd) {
                config_accepted += 1;
            }
        }
    }
    // The record is always valid, whatever came in.
    assert!(cfg.stored().validate().is_ok());
    if config_accepted == 0 {
        assert_eq!(
            cfg.stored(),
            &before,
            "the configuration changed without `accepted`"
        );
    }
    if writes_accepted == 0 {
        assert!(
            !bridge.busy(),
            "a command reached the bridge without `accepted`"
        );
    }
    if flags & 1 != 0 {
        assert_eq!(writes_accepted, 0, "read-only link accepted a write");
        assert_eq!(
            config_accepted, 0,
            "read-only link accepted a configuration change"
        );
    }
}
