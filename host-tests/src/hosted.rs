//! The firmware's bridge **and** its host link in real time: what the ESP32
//! runs, on the desktop. Used by `sim --bridge-pty` (the host side on a
//! pseudo-terminal, the BMS simulated) and by `tinybms` in direct mode (the
//! host side an in-process channel, the BMS on a USB-UART adapter).
//!
//! The loop is the chip's: UART bytes go to [`Bridge::handle_rx`] and are
//! mirrored to the host link (its `capture` / `raw` lines), every report goes
//! to [`HostLink::on_report`], host bytes to [`HostLink::handle_rx`] (which
//! submits commands to the bridge), and lines come out of
//! [`HostLink::next_line`] only when the host side can take them — otherwise
//! they wait in the host link's bounded queue, which drops telemetry first.
//!
//! [`Bridge::handle_rx`]: tinybms_firmware::Bridge::handle_rx

use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::time::Duration;

use protocol_core::settings::SettingId;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::host_link::{HostLink, HostLinkConfig};

use crate::pty::Pty;
use crate::realtime::{BytePort, Driver, Happened, SimPort, MAX_SLICE};
use crate::sim::SimBms;

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

/// Bridge + host link on a byte port.
pub struct Hosted<P: BytePort> {
    /// The bridge on its port.
    pub driver: Driver<P>,
    /// The host link.
    pub host: HostLink,
    /// Print every report to stderr, as the device logs it.
    pub log: bool,
    line: Vec<u8>,
    input: Vec<u8>,
}

impl<P: BytePort> Hosted<P> {
    /// Both at time 0 (now). The host link has not seen a connection yet:
    /// call [`Hosted::connected`].
    pub fn new(port: P, bridge: Timing, host: HostLinkConfig) -> Self {
        let driver = Driver::new(port, bridge);
        let now = driver.clock().now();
        Self {
            host: HostLink::new(host, now),
            driver,
            log: false,
            line: vec![0; LINE_BUF],
            input: Vec::new(),
        }
    }

    /// The host opened its port (queues the hello).
    pub fn connected(&mut self) {
        let now = self.driver.clock().now();
        self.host.connected(now);
    }

    /// One round of the loop: the bridge transmits what it wants, host bytes
    /// are handled, lines go out, then UART bytes are awaited until the next
    /// deadline (at most [`MAX_SLICE`]).
    pub fn step(&mut self, side: &mut dyn HostSide) -> io::Result<()> {
        let Self {
            driver,
            host,
            log,
            line,
            input,
        } = self;
        let log = *log;
        driver.service(|h| tell(host, log, h))?;
        input.clear();
        side.read(input)?;
        if !input.is_empty() {
            let now = driver.clock().now();
            host.handle_rx(now, input, &mut driver.bridge);
            // A submitted command may have something to send at once.
            driver.service(|h| tell(host, log, h))?;
        }
        let now = driver.clock().now();
        let host_deadline = host.poll(now, &driver.bridge);
        while side.can_take() {
            match host.next_line(now, &driver.bridge, line) {
                Some(n) => side.write_line(line.get(..n).unwrap_or(&[]))?,
                None => break,
            }
        }
        let wait = MAX_SLICE.min(driver.clock().until(host_deadline));
        driver.receive(wait, |rx| host.on_uart_rx(rx))?;
        Ok(())
    }
}

/// Hands what the driver did to the host link (and the log).
fn tell(host: &mut HostLink, log: bool, h: Happened<'_>) {
    match h {
        Happened::Tx(bytes) => host.on_uart_tx(bytes),
        Happened::Report(at, r) => {
            if log {
                eprintln!("{:>10.3}s {r}", at as f64 / 1e6);
            }
            host.on_report(r);
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
    /// Host writes refused.
    pub read_only: bool,
    /// Telemetry push period, ms (0: off).
    pub stream_period_ms: u32,
    /// Settings written through write/verify at start, as the firmware's
    /// profile.
    pub profile: Vec<(SettingId, i32)>,
    /// The bridge's configuration.
    pub bridge: Timing,
    /// Print the bridge's log lines to stderr.
    pub log: bool,
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
    let pty = Pty::open_announced(out)?;
    let host = HostLinkConfig {
        read_only: o.read_only,
        stream_period_ms: o.stream_period_ms,
        firmware: env!("CARGO_PKG_VERSION"),
        chip: "sim",
    };
    let mut h = Hosted::new(SimPort::new(sim), o.bridge, host);
    h.driver
        .bridge
        .submit_profile(&o.profile)
        .map_err(|_| io::Error::other("the profile does not fit the bridge's command queue"))?;
    h.connected();
    let mut side = PtySide::new(&pty);
    let clock = h.driver.clock();
    let end = duration.map(|d| d.as_micros() as u64);
    h.log = o.log;
    while !stop.load(Ordering::Relaxed) && end.is_none_or(|e| clock.now() < e) {
        h.step(&mut side)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
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
