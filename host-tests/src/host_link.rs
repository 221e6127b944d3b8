//! The firmware's host link ([`tinybms_firmware::host_link::HostLink`]) wired to
//! the virtual-time harness: the same loop as the chip shell (bridge reports
//! forwarded to the host link, its stream timer polled, output drained line by
//! line), plus the body of the `host_link` fuzz target, which the tests also run
//! on stable over random inputs.

use std::sync::OnceLock;

use embassy_futures::block_on;
use serde_json::Value;
use tinybms_firmware::config::state::ConfigState;
use tinybms_firmware::config::store::{save_when_quiet, Source, Store};
use tinybms_firmware::config::Config;
use tinybms_firmware::host_link::{HostLink, HostLinkConfig, OUT_LINE_MAX};
use tinybms_firmware::{Bridge, MS, SECOND};

use crate::flash::RamFlash;
use crate::harness::Harness;
use crate::sim::{PackProfile, SimBms, SimConfig};

/// A bridge against the simulated BMS with a host link on top.
pub struct Rig {
    /// Bridge, simulated BMS and clock.
    pub h: Harness,
    /// The host link under test.
    pub link: HostLink,
    /// The bridge's configuration.
    pub config: ConfigState,
    /// Its store, on a flash in RAM.
    pub store: Store<RamFlash>,
    /// That flash (shared with the store).
    pub flash: RamFlash,
    /// Saves of the configuration made.
    pub saves: u64,
    /// Log lines already handed to the host link.
    forwarded: usize,
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
    }
}

impl Rig {
    /// A 16S LiFePO4 simulated BMS, a fresh bridge and a host link at time 0.
    pub fn new(config: HostLinkConfig) -> Self {
        let sim = SimBms::new(PackProfile::LiFePO4_16S, SimConfig::default(), 1);
        let mut h = Harness::new(sim);
        h.echo = false;
        let flash = RamFlash::new();
        Self {
            link: HostLink::new(config, h.now),
            config: ConfigState::new(record_for(&config), Source::Empty),
            store: crate::flash::store(flash.clone()),
            flash,
            saves: 0,
            h,
            forwarded: 0,
        }
    }

    /// A rig whose bridge is synced (ready).
    pub fn ready(config: HostLinkConfig) -> Self {
        let mut r = Self::new(config);
        r.run(6 * SECOND);
        assert!(r.h.bridge.telemetry().ready, "bridge not ready after 6 s");
        r
    }

    /// Runs bridge and host link for `us` of virtual time, in 50 ms steps,
    /// without reading the host link's output.
    pub fn run(&mut self, us: u64) {
        let end = self.h.now + us;
        while self.h.now < end {
            let step = (self.h.now + 50 * MS).min(end);
            self.h.run_until(step);
            self.forward();
            self.service_config();
            self.link.poll(self.h.now, &self.h.bridge);
        }
    }

    /// What the chip's bridge task does for the configuration after a pass:
    /// at-once changes to the host link, the save when the link is quiet.
    pub fn service_config(&mut self) {
        let now = self.h.now;
        if let Some(c) = self.config.take_running_change() {
            self.link.apply_config(now, c);
        }
        let due = self.config.save_due() && self.h.bridge.quiet(now);
        if let Some(r) = block_on(save_when_quiet(
            &mut self.config,
            &mut self.store,
            &self.h.bridge,
            now,
        )) {
            self.link.on_config_saved(r);
        }
        if due {
            self.saves += 1;
        }
    }

    /// Runs like [`Rig::run`], with a host that reads every line as it comes
    /// (every 50 ms); returns them.
    pub fn run_reading(&mut self, us: u64) -> Vec<Value> {
        let end = self.h.now + us;
        let mut out = Vec::new();
        while self.h.now < end {
            let step = (self.h.now + 50 * MS).min(end);
            self.run(step - self.h.now);
            out.extend(self.drain());
        }
        out
    }

    fn forward(&mut self) {
        while let Some(l) = self.h.log.get(self.forwarded) {
            self.link.on_report(&l.report);
            self.forwarded += 1;
        }
    }

    /// Sends bytes from the host.
    pub fn send(&mut self, bytes: &[u8]) {
        self.link
            .handle_rx(self.h.now, bytes, &mut self.h.bridge, &mut self.config);
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
        while let Some(n) = self
            .link
            .next_line(self.h.now, &self.h.bridge, &self.config, &mut buf)
        {
            out.push(check_line(buf.get(..n).unwrap_or(&[])));
        }
        out
    }

    /// Every line waiting, parsed.
    pub fn drain(&mut self) -> Vec<Value> {
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
    READY.get_or_init(|| Rig::ready(config(false, 0)).h.bridge)
}

/// The `host_link` fuzz target's body (protocol-core/fuzz/fuzz_targets/host_link.rs).
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
        link.handle_rx(now, piece, &mut bridge, &mut cfg);
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
