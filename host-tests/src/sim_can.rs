//! The CAN bus of a desktop station in real time (`sim --bridge-pty`, `sim
//! --mqtt`): a virtual bus with a simulated inverter on it, so the firmware's
//! inverter output runs as on the chip — its limits reach the host link and
//! Home Assistant, its CAN state and "inverter heard" are real, and
//! `config inverter_protocol=…` takes effect after a restart — without
//! hardware.
//!
//! The simulated inverter acknowledges every frame (it is the other node on
//! the bus), keeps the last limits it was told (0x351; Growatt's 0x311), and
//! once a second sends 0x305 — the GX keep-alive, the heartbeat of the
//! Pylontech family — and, while the bridge has sent no 0x351 for
//! [`QUERY_AFTER_SILENCE`] (a Growatt-speaking bridge never does) and from
//! [`FIRST_QUERY_AFTER`] on, 0x301, Growatt's query: one inverter for every
//! `inverter_protocol`, which a restart may change, and none that the
//! bridge's doctor would take for another dialect's. A candump log of what the
//! bridge sent can be written (`--can-log`), readable by can-utils and
//! cantools.

use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant as WallInstant};

use tinybms_firmware::inverter::dialect::{victron::ID_GX_KEEPALIVE, CanFrame};
use tinybms_firmware::inverter::TxResult;
use tinybms_firmware::Instant;

use crate::closed_loop::candump_line;
use tinybms_desk::CanSide;

/// How often the simulated inverter sends its keep-alive.
pub const KEEPALIVE_EVERY: Duration = Duration::from_secs(1);
/// No Growatt query before this long after the bus was made.
pub const FIRST_QUERY_AFTER: Duration = Duration::from_secs(3);
/// The query goes out while the bridge has sent no 0x351 for this long.
pub const QUERY_AFTER_SILENCE: Duration = Duration::from_secs(30);

/// What the simulated inverter saw, for a test or the sim's summary.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Seen {
    /// Frames acknowledged.
    pub frames: u64,
    /// The last 0x351 (CVL 0.1 V, CCL 0.1 A, DCL 0.1 A).
    pub limits: Option<(u16, u16, u16)>,
}

/// The bus and its inverter. See the module documentation.
pub struct SimInverterBus {
    seen: Arc<Mutex<Seen>>,
    log: Option<Box<dyn Write + Send>>,
    next_keepalive: WallInstant,
    made_at: WallInstant,
    limits_at: Option<WallInstant>,
    pending: Vec<(u16, Vec<u8>)>,
    /// Keep-alives on (an inverter that is there); off: a bus with only a
    /// listener that acknowledges.
    pub keepalive: bool,
}

/// Growatt's query, as its spec prints it.
const GROWATT_QUERY: (u16, [u8; 8]) = (0x301, [0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77, 0x88]);

impl SimInverterBus {
    /// A bus with an inverter that sends its keep-alive; `log` gets every
    /// frame the bridge sends as a candump line.
    pub fn new(log: Option<Box<dyn Write + Send>>) -> Self {
        Self {
            seen: Arc::default(),
            log,
            next_keepalive: WallInstant::now(),
            made_at: WallInstant::now(),
            limits_at: None,
            pending: Vec::new(),
            keepalive: true,
        }
    }

    /// What the inverter saw (shared: read it while the station runs).
    pub fn seen(&self) -> Arc<Mutex<Seen>> {
        self.seen.clone()
    }
}

impl CanSide for SimInverterBus {
    fn send(&mut self, now: Instant, frame: &CanFrame) -> TxResult {
        let mut seen = self.seen.lock().unwrap_or_else(|e| e.into_inner());
        seen.frames += 1;
        let d = frame.data;
        if frame.id == 0x351 && frame.len >= 6 {
            let word = |i: usize| u16::from_le_bytes([d[i], d[i + 1]]);
            seen.limits = Some((word(0), word(2), word(4)));
            self.limits_at = Some(WallInstant::now());
        }
        if frame.id == 0x311 && frame.len >= 6 {
            let word = |i: usize| u16::from_be_bytes([d[i], d[i + 1]]);
            seen.limits = Some((word(0), word(2), word(4)));
        }
        if let Some(w) = self.log.as_mut() {
            let _ = writeln!(w, "{}", candump_line(now, frame));
            let _ = w.flush();
        }
        TxResult::Sent
    }

    fn recover(&mut self, _now: Instant) -> bool {
        true
    }

    fn receive(&mut self) -> Option<(u16, Vec<u8>)> {
        if self.keepalive && WallInstant::now() >= self.next_keepalive {
            let now = WallInstant::now();
            self.next_keepalive = now + KEEPALIVE_EVERY;
            let speaks = self
                .limits_at
                .is_some_and(|t| now.duration_since(t) < QUERY_AFTER_SILENCE);
            if now.duration_since(self.made_at) >= FIRST_QUERY_AFTER && !speaks {
                self.pending
                    .push((GROWATT_QUERY.0, GROWATT_QUERY.1.to_vec()));
            }
            self.pending.push((ID_GX_KEEPALIVE, vec![0; 8]));
        }
        self.pending.pop()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn acknowledges_keeps_the_limits_and_logs_candump() {
        let log = Arc::new(Mutex::new(Vec::<u8>::new()));
        struct Shared(Arc<Mutex<Vec<u8>>>);
        impl Write for Shared {
            fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
                self.0.lock().unwrap().extend_from_slice(b);
                Ok(b.len())
            }
            fn flush(&mut self) -> std::io::Result<()> {
                Ok(())
            }
        }
        let mut bus = SimInverterBus::new(Some(Box::new(Shared(log.clone()))));
        let f = CanFrame {
            id: 0x351,
            len: 8,
            data: [0x2C, 0x02, 0xF4, 0x01, 0x58, 0x02, 0, 0],
        };
        assert_eq!(bus.send(1_500_000, &f), TxResult::Sent);
        let seen = bus.seen().lock().unwrap().clone();
        assert_eq!(seen.frames, 1);
        assert_eq!(seen.limits, Some((556, 500, 600)));
        let text = String::from_utf8(log.lock().unwrap().clone()).unwrap();
        assert!(text.ends_with(" can0 351#2C02F40158020000\n"), "{text}");
        // The keep-alive at once, without the query: the bridge speaks (a
        // 0x351), and the bus is young; then nothing before a second has
        // passed.
        assert_eq!(bus.receive().map(|(id, _)| id), Some(ID_GX_KEEPALIVE));
        assert_eq!(bus.receive(), None);
        // Older, and no 0x351 for a while: the query too.
        bus.made_at = WallInstant::now() - FIRST_QUERY_AFTER;
        bus.limits_at = Some(WallInstant::now() - QUERY_AFTER_SILENCE);
        bus.next_keepalive = WallInstant::now();
        assert_eq!(bus.receive().map(|(id, _)| id), Some(ID_GX_KEEPALIVE));
        assert_eq!(bus.receive().map(|(id, _)| id), Some(0x301));
        assert_eq!(bus.receive(), None);
        bus.keepalive = false;
        bus.next_keepalive = WallInstant::now();
        assert_eq!(bus.receive(), None);
    }
}
