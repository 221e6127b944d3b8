//! The firmware's host link ([`tinybms_firmware::host_link::HostLink`]) wired to
//! the virtual-time harness: the same loop as the chip shell (bridge reports
//! forwarded to the host link, its stream timer polled, output drained line by
//! line), plus the body of the `host_link` fuzz target, which the tests also run
//! on stable over random inputs.

use std::sync::OnceLock;

use serde_json::Value;
use tinybms_firmware::host_link::{HostLink, HostLinkConfig, OUT_LINE_MAX};
use tinybms_firmware::{Bridge, MS, SECOND};

use crate::harness::Harness;
use crate::sim::{PackProfile, SimBms, SimConfig};

/// A bridge against the simulated BMS with a host link on top.
pub struct Rig {
    /// Bridge, simulated BMS and clock.
    pub h: Harness,
    /// The host link under test.
    pub link: HostLink,
    /// Log lines already handed to the host link.
    forwarded: usize,
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
        Self {
            link: HostLink::new(config, h.now),
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
            self.link.poll(self.h.now, &self.h.bridge);
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
        self.link.handle_rx(self.h.now, bytes, &mut self.h.bridge);
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
        while let Some(n) = self.link.next_line(self.h.now, &self.h.bridge, &mut buf) {
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
    let mut link = HostLink::new(config(flags & 1 != 0, 100), 0);
    let mut writes_accepted = 0usize;
    let mut buf = [0u8; OUT_LINE_MAX];
    let mut now = 0;
    for piece in input.chunks(chunk.max(1)) {
        now += 10 * MS;
        link.handle_rx(now, piece, &mut bridge);
        link.poll(now, &bridge);
        while let Some(n) = link.next_line(now, &bridge, &mut buf) {
            let line = check_line(buf.get(..n).unwrap_or(&[]));
            let v: Value = serde_json::from_str(&line).unwrap_or(Value::Null);
            if v["type"] == "accepted"
                && ["set", "reset", "clear"].contains(&v["cmd"].as_str().unwrap_or(""))
            {
                writes_accepted += 1;
            }
        }
    }
    if writes_accepted == 0 {
        assert!(
            !bridge.busy(),
            "a command reached the bridge without `accepted`"
        );
    }
    if flags & 1 != 0 {
        assert_eq!(writes_accepted, 0, "read-only link accepted a write");
    }
}
