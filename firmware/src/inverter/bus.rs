//! The CAN port's health, as the inverter output keeps it: frames sent and
//! acknowledged, failures in a row ("no ACK"), bus-offs with their growing
//! pause, and the inverter's keep-alive heard or lost. Sans-IO: every input
//! is a result the controller gave or a frame the bus carried, at a time;
//! what to log goes to the [`Reports`] given.

use super::{CanState, InverterReport, Reports, TxResult};
use crate::Instant;

/// Failed transmissions in a row before "no ACK" is reported (and sending slows
/// to the fast period only).
pub const NO_ACK_AFTER: u32 = 8;

/// The port's health. See the module documentation.
#[derive(Debug, Clone, Default)]
pub struct BusHealth {
    frames_sent: u32,
    tx_failures: u32,
    no_ack_reported: bool,
    /// Off the bus until this time.
    bus_off: Option<Instant>,
    bus_offs: u32,
    keepalive_at: Option<Instant>,
    inverter_seen: bool,
}

impl BusHealth {
    /// Frames transmitted successfully.
    pub fn frames_sent(&self) -> u32 {
        self.frames_sent
    }

    /// The port's state for an output that is on.
    pub fn state(&self) -> CanState {
        if self.bus_off.is_some() {
            CanState::BusOff
        } else if self.no_ack_reported {
            CanState::NoAck
        } else if self.frames_sent > 0 {
            CanState::Running
        } else {
            CanState::Waiting
        }
    }

    /// The inverter's keep-alive is heard (within its timeout).
    pub fn inverter_heard(&self) -> bool {
        self.inverter_seen
    }

    /// The result of one transmission. `false`: what was queued must be
    /// dropped (the next period sends fresh values, never stale ones late).
    pub fn on_tx(&mut self, result: TxResult, reports: &mut Reports) -> bool {
        match result {
            TxResult::Sent => {
                self.frames_sent = self.frames_sent.wrapping_add(1);
                if self.no_ack_reported {
                    reports.push(InverterReport::BusOk);
                }
                self.tx_failures = 0;
                self.no_ack_reported = false;
                true
            }
            TxResult::Failed => {
                self.tx_failures = self.tx_failures.saturating_add(1);
                if self.tx_failures >= NO_ACK_AFTER && !self.no_ack_reported {
                    self.no_ack_reported = true;
                    let failures = self.tx_failures;
                    reports.push(InverterReport::NoAck { failures });
                }
                false
            }
        }
    }

    /// The controller went bus-off at `now`: off the bus for `backoff_us`,
    /// doubled for each bus-off before it up to 16 ×.
    pub fn on_bus_off(&mut self, now: Instant, backoff_us: Instant, reports: &mut Reports) {
        self.bus_offs = self.bus_offs.saturating_add(1);
        let shift = self.bus_offs.saturating_sub(1).min(4);
        let backoff = backoff_us.saturating_mul(1 << shift);
        self.bus_off = Some(now.saturating_add(backoff));
        let count = self.bus_offs;
        reports.push(InverterReport::BusOff {
            count,
            backoff_ms: (backoff / crate::MS).min(u64::from(u32::MAX)) as u32,
        });
    }

    /// Off the bus at `now`: `Some(until)` while the pause lasts; `None` when
    /// on the bus. Once the pause is over the recovery is due:
    /// [`BusHealth::recovery_due`].
    pub fn off_until(&self, now: Instant) -> Option<Instant> {
        self.bus_off.filter(|t| now < *t)
    }

    /// The pause after a bus-off is over at `now`: the recovery starts (once).
    pub fn recovery_due(&mut self, now: Instant) -> bool {
        match self.bus_off {
            Some(t) if now >= t => {
                self.bus_off = None;
                true
            }
            _ => false,
        }
    }

    /// The inverter's keep-alive was heard at `now`.
    pub fn keepalive(&mut self, now: Instant, reports: &mut Reports) {
        self.keepalive_at = Some(now);
        if !self.inverter_seen {
            self.inverter_seen = true;
            reports.push(InverterReport::InverterSeen);
        }
    }

    /// At `now`: the keep-alive lost after `timeout_us` without one.
    pub fn check_keepalive(&mut self, now: Instant, timeout_us: Instant, reports: &mut Reports) {
        if let Some(t) = self.keepalive_at {
            if self.inverter_seen && now.saturating_sub(t) >= timeout_us {
                self.inverter_seen = false;
                reports.push(InverterReport::InverterLost);
            }
        }
    }

    /// When the keep-alive times out, while it is heard.
    pub fn keepalive_deadline(&self, timeout_us: Instant) -> Option<Instant> {
        match self.keepalive_at {
            Some(t) if self.inverter_seen => Some(t.saturating_add(timeout_us)),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::SECOND;

    fn drain(r: &mut Reports) -> heapless::Vec<InverterReport, 8> {
        core::iter::from_fn(|| r.pop()).collect()
    }

    #[test]
    fn no_ack_is_reported_once_after_eight_failures_and_ends_with_a_frame_sent() {
        let (mut b, mut r) = (BusHealth::default(), Reports::default());
        for _ in 0..NO_ACK_AFTER - 1 {
            assert!(!b.on_tx(TxResult::Failed, &mut r));
        }
        assert!(drain(&mut r).is_empty());
        assert_eq!(b.state(), CanState::Waiting);
        b.on_tx(TxResult::Failed, &mut r);
        b.on_tx(TxResult::Failed, &mut r);
        assert_eq!(
            drain(&mut r).as_slice(),
            [InverterReport::NoAck { failures: 8 }]
        );
        assert_eq!(b.state(), CanState::NoAck);
        assert!(b.on_tx(TxResult::Sent, &mut r));
        assert_eq!(drain(&mut r).as_slice(), [InverterReport::BusOk]);
        assert_eq!((b.state(), b.frames_sent()), (CanState::Running, 1));
    }

    #[test]
    fn the_pause_after_a_bus_off_doubles_up_to_sixteen_times() {
        let (mut b, mut r) = (BusHealth::default(), Reports::default());
        let mut now = 0;
        for (count, expect_s) in [(1, 1), (2, 2), (3, 4), (4, 8), (5, 16), (6, 16)] {
            b.on_bus_off(now, SECOND, &mut r);
            assert_eq!(
                drain(&mut r).as_slice(),
                [InverterReport::BusOff {
                    count,
                    backoff_ms: expect_s * 1000
                }]
            );
            assert_eq!(b.state(), CanState::BusOff);
            let until = now + u64::from(expect_s) * SECOND;
            assert_eq!(b.off_until(now), Some(until));
            assert!(!b.recovery_due(until - 1));
            assert!(b.recovery_due(until));
            assert!(!b.recovery_due(until), "the recovery starts once");
            assert_eq!(b.off_until(until), None);
            now = until;
        }
    }

    #[test]
    fn the_keepalive_is_heard_then_lost_after_its_timeout() {
        let (mut b, mut r) = (BusHealth::default(), Reports::default());
        assert_eq!(b.keepalive_deadline(5 * SECOND), None);
        b.keepalive(SECOND, &mut r);
        b.keepalive(2 * SECOND, &mut r);
        assert_eq!(drain(&mut r).as_slice(), [InverterReport::InverterSeen]);
        assert_eq!(b.keepalive_deadline(5 * SECOND), Some(7 * SECOND));
        b.check_keepalive(7 * SECOND - 1, 5 * SECOND, &mut r);
        assert!(b.inverter_heard());
        b.check_keepalive(7 * SECOND, 5 * SECOND, &mut r);
        assert!(!b.inverter_heard());
        assert_eq!(drain(&mut r).as_slice(), [InverterReport::InverterLost]);
        assert_eq!(b.keepalive_deadline(5 * SECOND), None);
    }
}
