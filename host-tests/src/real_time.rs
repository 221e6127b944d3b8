//! The simulated BMS in **real time**, on real byte ports: the counterpart of
//! [`crate::virtual_time`] (virtual time) for `sim --pty` and for the
//! simulated BMS behind `sim --bridge-pty` / `sim --mqtt`.
//!
//! * [`SimPort`] — the simulated BMS in-process as a [`BytePort`], its clock
//!   on the wall clock, for the desktop station ([`tinybms_desk::Driver`]:
//!   the chip's station task on the desktop, shared with the tool).
//! * [`serve_sim_pty`] — the simulated BMS on a pseudo-terminal (`sim --pty`).

use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use protocol_core::settings::{Setting, SettingId};
use tinybms_desk::{BytePort, Clock};
use tinybms_firmware::bms::timing::BYTE_TIME_US;

use crate::pty::Pty;
use crate::sim::{PackModel, SimBms, SimConfig};

/// The simulated BMS hands its output over in chunks of this much wire time
/// (≈ 16 bytes, like a UART driver's FIFO threshold) instead of byte by byte.
pub const SIM_CHUNK_US: u64 = crate::virtual_time::RX_CHUNK_US;

/// The simulated BMS as a [`BytePort`], in-process, on the wall clock.
pub struct SimPort {
    /// The simulated BMS (its virtual time follows [`SimPort::clock`]).
    pub sim: SimBms,
    clock: Clock,
    pending: Vec<u8>,
}

impl SimPort {
    /// A simulated BMS whose time 0 is now.
    pub fn new(sim: SimBms) -> Self {
        Self {
            sim,
            clock: Clock::start(),
            pending: Vec::new(),
        }
    }

    /// The port's clock.
    pub fn clock(&self) -> Clock {
        self.clock
    }
}

impl BytePort for SimPort {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        let end = self.sim.host_send(self.clock.now(), bytes);
        // Like a UART write + flush: return once the last byte is on the wire.
        std::thread::sleep(self.clock.until(end));
        Ok(())
    }

    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        let deadline = self.clock.now() + timeout.as_micros() as u64;
        loop {
            if self.pending.is_empty() {
                self.sim.take_output(self.clock.now(), &mut self.pending);
            }
            if !self.pending.is_empty() {
                let n = self.pending.len().min(buf.len());
                buf[..n].copy_from_slice(&self.pending[..n]);
                self.pending.drain(..n);
                return Ok(n);
            }
            let now = self.clock.now();
            if now >= deadline {
                return Ok(0);
            }
            let wake = match self.sim.next_output_at() {
                Some(t) => (t.max(now) + SIM_CHUNK_US).min(deadline),
                None => deadline,
            };
            std::thread::sleep(Duration::from_micros(wake.saturating_sub(now).max(50)));
        }
    }
}

/// What `sim --pty` (and the simulated BMS behind `sim --bridge-pty`) is.
#[derive(Debug, Clone)]
pub struct SimOptions {
    /// The pack.
    pub pack: PackModel,
    /// The simulator's configuration (faults, sleep, ...).
    pub config: SimConfig,
    /// Its seed.
    pub seed: u64,
    /// Settings the simulated BMS holds from the start (raw units), on top of
    /// the pack's defaults.
    pub settings: Vec<(SettingId, i32)>,
}

impl Default for SimOptions {
    fn default() -> Self {
        Self {
            pack: PackModel::LiFePO4_16S,
            config: SimConfig {
                // As the soak: a real BMS falls asleep after a while without
                // traffic, and the bridge must wake it.
                sleep_after_us: Some(30_000_000),
                ..SimConfig::default()
            },
            seed: 1,
            settings: Vec::new(),
        }
    }
}

impl SimOptions {
    /// The simulated BMS these options describe. A setting that does not fit
    /// its Rev D range is an error.
    pub fn build(&self) -> Result<SimBms, String> {
        let mut sim = SimBms::new(self.pack, self.config.clone(), self.seed);
        for &(id, value) in &self.settings {
            let s =
                Setting::new(id, value).map_err(|e| format!("{}: {}", id.name(), e.reason()))?;
            let current = Some(sim.register(id.address()));
            let words = s
                .words(current)
                .map_err(|e| format!("{}: {}", id.name(), e.reason()))?;
            for (a, v) in words {
                sim.set_register(a, v);
            }
        }
        Ok(sim)
    }
}

/// `sim --pty`: serves `sim` on a new pseudo-terminal in real time until
/// `duration` has passed (forever when `None`) or `stop` is set. The pty's path
/// is written to `out` as the first line (flushed) before anything else.
///
/// `freeze`: (from, for) — the BMS is silent then (answers nothing).
pub fn serve_sim_pty(
    mut sim: SimBms,
    duration: Option<Duration>,
    freeze: Option<(Duration, Duration)>,
    stop: &AtomicBool,
    out: &mut dyn Write,
) -> io::Result<()> {
    let pty = Pty::open_announced(out)?;
    let clock = Clock::start();
    let end = duration.map(|d| d.as_micros() as u64);
    let mut freeze = freeze.map(|(a, f)| (a.as_micros() as u64, f.as_micros() as u64));
    let mut buf = [0u8; 512];
    let mut outbuf = Vec::new();
    while !stop.load(Ordering::Relaxed) {
        let now = clock.now();
        if end.is_some_and(|e| now >= e) {
            break;
        }
        if let Some((at, long)) = freeze {
            if now >= at {
                sim.set_silent_until(at + long);
                freeze = None;
            }
        }
        outbuf.clear();
        sim.take_output(now, &mut outbuf);
        if !outbuf.is_empty() {
            // What the pty cannot take (nobody reading) is lost, as on a UART.
            pty.write(&outbuf)?;
        }
        let mut wait = Duration::from_millis(50);
        if let Some(t) = sim.next_output_at() {
            wait = wait.min(clock.until(t.max(now) + SIM_CHUNK_US));
        }
        if let Some(e) = end {
            wait = wait.min(clock.until(e));
        }
        let n = pty.read(&mut buf, wait)?;
        if n > 0 {
            sim.host_send(clock.now(), &buf[..n]);
        }
    }
    Ok(())
}

/// The wire time of `n` bytes at 115200 8N1, µs.
pub const fn wire_time_us(n: usize) -> u64 {
    BYTE_TIME_US * n as u64
}

#[cfg(test)]
mod tests {
    use super::*;
    use tinybms_desk::Driver;
    use tinybms_firmware::bms::timing::Timing;

    /// The firmware's bridge on the simulated BMS in real time: asleep at
    /// first, woken by the bridge's own resend, then ready with a snapshot.
    /// Bounded wait, no timing assertion.
    #[test]
    fn the_driver_wakes_the_sim_and_publishes() {
        let sim = SimOptions {
            config: SimConfig {
                start_asleep: true,
                ..SimOptions::default().config
            },
            ..SimOptions::default()
        }
        .build()
        .unwrap();
        let mut d = Driver::new(SimPort::new(sim), Timing::default());
        let stop = AtomicBool::new(false);
        let mut reports = Vec::new();
        let end = std::time::Instant::now() + Duration::from_secs(60);
        while d.station.bridge().telemetry().snapshot.is_none() && std::time::Instant::now() < end {
            d.run_for(Duration::from_millis(200), &stop, |_, r| {
                reports.push(r.to_string())
            })
            .unwrap();
        }
        let t = d.station.bridge().telemetry();
        assert!(t.ready && t.snapshot.is_some(), "{reports:#?}");
        assert!(
            d.station.bridge().link_stats().wakeup_resends >= 1,
            "{reports:#?}"
        );
        assert!(d.tx_bytes > 0 && d.rx_bytes > 0);
    }

    #[test]
    fn settings_of_the_options_are_held_by_the_sim() {
        let o = SimOptions {
            settings: vec![(SettingId::OverVoltageCutoff, 3600)],
            ..SimOptions::default()
        };
        assert_eq!(o.build().unwrap().register(315), 3600);
        let bad = SimOptions {
            settings: vec![(SettingId::OverVoltageCutoff, 9999)],
            ..SimOptions::default()
        };
        assert!(bad.build().is_err());
    }
}
