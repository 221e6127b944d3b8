//! Runs the firmware's own bridge logic ([`tinybms_firmware::Bridge`]) against the
//! simulated TinyBMS in virtual time: the same loop as the chip shell's
//! `bridge_task`, with the UART replaced by [`crate::sim::SimBms`] and the clock by
//! a number. No threads, no sleeps: hours of polling run in seconds.

use protocol_core::views::LiveSnapshot;
use tinybms_firmware::config::{Config, BYTE_TIME_US};
use tinybms_firmware::{Action, Bridge, Level, Report};

use crate::sim::SimBms;

/// A UART read returns after at most this much wire time (≈ 16 bytes: the ESP32
/// RX FIFO threshold / idle timeout behaviour), so replies arrive in chunks.
pub const RX_CHUNK_US: u64 = 16 * BYTE_TIME_US;

/// One log line, as the device would print it.
#[derive(Debug, Clone, PartialEq)]
pub struct LogLine {
    /// Virtual time, µs.
    pub at_us: u64,
    /// Level.
    pub level: Level,
    /// The report.
    pub report: Report,
}

impl core::fmt::Display for LogLine {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let level = match self.level {
            Level::Info => "INFO ",
            Level::Warn => "WARN ",
        };
        write!(
            f,
            "{:>10.3}s {level} {}",
            self.at_us as f64 / 1e6,
            self.report
        )
    }
}

/// The bridge, the simulated BMS and the virtual clock.
pub struct Harness {
    /// The firmware logic under test.
    pub bridge: Bridge,
    /// The simulated BMS.
    pub sim: SimBms,
    /// Virtual time, µs.
    pub now: u64,
    /// Every report, in order.
    pub log: Vec<LogLine>,
    /// Every snapshot the bridge published (time, snapshot).
    pub published: Vec<(u64, LiveSnapshot)>,
    /// Bytes the bridge transmitted.
    pub tx_bytes: u64,
    /// Bytes the bridge received.
    pub rx_bytes: u64,
    /// Wire time the bridge's transmissions occupied, µs.
    pub tx_busy_us: u64,
    /// Print each log line to stdout as it happens.
    pub echo: bool,
    seen_seq: u32,
    live_request: Vec<u8>,
    live_sent_at: Option<u64>,
    /// Live snapshot latencies, µs: first transmission of the 0x03 0-55 request to
    /// the snapshot being published.
    pub live_latencies: Vec<u64>,
}

impl Harness {
    /// A harness at time 0 with the default bridge configuration.
    pub fn new(sim: SimBms) -> Self {
        Self::with_config(sim, Config::default())
    }

    /// A harness at time 0.
    pub fn with_config(sim: SimBms, config: Config) -> Self {
        Self {
            bridge: Bridge::new(config, 0),
            sim,
            now: 0,
            log: Vec::new(),
            published: Vec::new(),
            tx_bytes: 0,
            rx_bytes: 0,
            tx_busy_us: 0,
            echo: false,
            seen_seq: 0,
            live_request: protocol_core::request::Request::read_registers(0, 56)
                .and_then(|r| r.to_bytes())
                .map(|b| b.to_vec())
                .unwrap_or_default(),
            live_sent_at: None,
            live_latencies: Vec::new(),
        }
    }

    /// Runs until virtual time `end_us`.
    pub fn run_until(&mut self, end_us: u64) {
        let mut rx = Vec::new();
        while self.now < end_us {
            match self.bridge.poll(self.now) {
                Action::Transmit(bytes) => {
                    if bytes.as_slice() == self.live_request.as_slice() {
                        match self.live_sent_at {
                            Some(t) if self.now - t < 1_000_000 => {}
                            _ => self.live_sent_at = Some(self.now),
                        }
                    }
                    self.sim.host_send(self.now, &bytes);
                    self.tx_bytes += bytes.len() as u64;
                    // write + flush: the task resumes when the last byte left.
                    let wire = BYTE_TIME_US * bytes.len() as u64;
                    self.tx_busy_us += wire;
                    self.now += wire;
                }
                Action::WaitUntil(t) => {
                    let t = t.clamp(self.now, end_us);
                    let wake = match self.sim.next_output_at() {
                        Some(first) if first <= t => (first.max(self.now) + RX_CHUNK_US).min(t),
                        _ => t,
                    };
                    // Always make progress, even on a deadline equal to now.
                    self.now = wake.max(self.now + 1).min(end_us.max(self.now + 1));
                    rx.clear();
                    self.sim.take_output(self.now, &mut rx);
                    if !rx.is_empty() {
                        self.rx_bytes += rx.len() as u64;
                        self.bridge.handle_rx(self.now, &rx);
                    }
                }
            }
            self.drain();
        }
        self.sim.advance(self.now);
    }

    fn drain(&mut self) {
        while let Some(report) = self.bridge.next_report() {
            let line = LogLine {
                at_us: self.now,
                level: report.level(),
                report,
            };
            if self.echo {
                println!("{line}");
            }
            self.log.push(line);
        }
        let t = self.bridge.telemetry();
        if t.snapshot_seq != self.seen_seq {
            self.seen_seq = t.snapshot_seq;
            if let (Some(s), Some(at)) = (&t.snapshot, t.snapshot_at) {
                self.published.push((at, s.clone()));
                if let Some(sent) = self.live_sent_at.take() {
                    self.live_latencies.push(at - sent);
                }
            }
        }
    }

    /// Log lines whose report matches `f`.
    pub fn reports<'a>(
        &'a self,
        f: impl Fn(&Report) -> bool + 'a,
    ) -> impl Iterator<Item = &'a LogLine> + 'a {
        self.log.iter().filter(move |l| f(&l.report))
    }

    /// (min, mean, max, count) of [`Harness::live_latencies`], µs.
    pub fn live_latency(&self) -> Option<(u64, u64, u64, usize)> {
        let l = &self.live_latencies;
        let n = l.len();
        (n > 0).then(|| {
            let sum: u64 = l.iter().sum();
            (
                l.iter().copied().min().unwrap_or(0),
                sum / n as u64,
                l.iter().copied().max().unwrap_or(0),
                n,
            )
        })
    }

    /// The whole log as text, one line per report.
    pub fn log_text(&self) -> String {
        self.log.iter().map(|l| format!("{l}\n")).collect()
    }
}
