//! An inverter seen ignoring a stop: fresh data shows current flowing
//! against a stop told for [`AGAINST_FOR_US`] — more than [`AGAINST_A`] into
//! the pack while charging must stop, or out of it while discharging must.
//! From then on that stop goes out with every signal the dialect has (the
//! SOC, the charge voltage, the protection bits: see `super::say`), and so
//! does every later stop until the bridge restarts: an inverter that ignored
//! one stop is not trusted with the next. Each escalation is reported once
//! ("the inverter ignores the charge stop: 9.8 A for 3 s").

use crate::Instant;

/// A current beyond this against a stop counts as flowing, A (above the
/// TinyBMS's current noise and a charger's trickle).
pub const AGAINST_A: f32 = 2.0;

/// How long it must flow against a stop before the bridge escalates, µs: an
/// inverter that obeys ramps down within a second or two, and a charge into
/// a pack below its charge temperature must end within the few seconds the
/// BMS itself waits before it trips (the escalation goes out at once).
pub const AGAINST_FOR_US: Instant = 3 * crate::SECOND;

/// Which side a stop is of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Side {
    /// Charging must stop.
    Charge,
    /// Discharging must stop.
    Discharge,
}

impl Side {
    /// In words.
    pub const fn text(self) -> &'static str {
        match self {
            Self::Charge => "charge",
            Self::Discharge => "discharge",
        }
    }
}

/// One escalation, as reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Ignored {
    /// The stop ignored.
    pub side: Side,
    /// The current that flowed against it when the bridge escalated, 0.1 A
    /// (its size).
    pub current_da: u16,
    /// For how long, s.
    pub for_s: u16,
}

impl Ignored {
    /// In words, as the monitor and Home Assistant say it: `charge: 9.8 A
    /// for 3 s`.
    pub fn text(&self) -> heapless::String<40> {
        use core::fmt::Write;
        let mut out = heapless::String::new();
        let _ = write!(
            out,
            "{}: {}.{} A for {} s",
            self.side.text(),
            self.current_da / 10,
            self.current_da % 10,
            self.for_s
        );
        out
    }
}

/// One side's watch.
#[derive(Debug, Clone, Copy, Default)]
struct Watch {
    /// Current against the stop since then.
    since: Option<Instant>,
    /// Escalated (until the stop ends).
    escalated: bool,
}

impl Watch {
    /// A fresh snapshot at `now`: the stop `stopped`, current `against` A
    /// against it. Returns the escalation when it begins now.
    fn on_fresh(&mut self, now: Instant, stopped: bool, against: f32) -> Option<(u16, u16)> {
        if !stopped {
            *self = Self::default();
            return None;
        }
        if against <= AGAINST_A {
            self.since = None;
            return None;
        }
        let since = *self.since.get_or_insert(now);
        let lasted = now.saturating_sub(since);
        if !self.escalated && lasted >= AGAINST_FOR_US {
            self.escalated = true;
            let da = (against * 10.0).clamp(0.0, 65_535.0) as u16;
            let s = (lasted / crate::SECOND).min(u64::from(u16::MAX)) as u16;
            return Some((da, s));
        }
        None
    }
}

/// The watch of both sides, and whether an ignored stop was ever seen.
#[derive(Debug, Clone, Copy, Default)]
pub struct IgnoredStops {
    charge: Watch,
    discharge: Watch,
    seen: Option<Ignored>,
}

impl IgnoredStops {
    /// A fresh snapshot at `now` with the pack's `current_a` (positive
    /// charging), while the stops last told were `charge_stopped` and
    /// `discharge_stopped`: an escalation that begins now.
    pub fn on_fresh(
        &mut self,
        now: Instant,
        current_a: f32,
        charge_stopped: bool,
        discharge_stopped: bool,
    ) -> Option<Ignored> {
        let c = self
            .charge
            .on_fresh(now, charge_stopped, current_a)
            .map(|(d, s)| (Side::Charge, d, s));
        let d = self
            .discharge
            .on_fresh(now, discharge_stopped, -current_a)
            .map(|(d, s)| (Side::Discharge, d, s));
        let (side, current_da, for_s) = c.or(d)?;
        let e = Ignored {
            side,
            current_da,
            for_s,
        };
        self.seen = Some(e);
        Some(e)
    }

    /// A stop is to go out with every signal: an ignored stop was seen.
    pub fn escalated(&self) -> bool {
        self.seen.is_some()
    }

    /// The last escalation, if any (the monitor, Home Assistant).
    pub fn last(&self) -> Option<Ignored> {
        self.seen
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Instant = crate::SECOND;

    const Q: Instant = S / 4;

    #[test]
    fn three_seconds_against_a_stop_escalate_once() {
        let mut w = IgnoredStops::default();
        // Charging at 9.8 A with the charge stopped, a snapshot each 250 ms:
        // 3 s, then escalated.
        for k in 0..12 {
            assert_eq!(w.on_fresh(k * Q, 9.8, true, false), None, "{k}");
        }
        let e = w.on_fresh(12 * Q, 9.8, true, false).unwrap();
        assert_eq!((e.side, e.current_da, e.for_s), (Side::Charge, 98, 3));
        assert_eq!(e.text().as_str(), "charge: 9.8 A for 3 s");
        assert!(w.escalated());
        assert_eq!(w.on_fresh(13 * Q, 9.8, true, false), None, "once");
        // The stop ends: every later stop starts escalated (remembered).
        assert_eq!(w.on_fresh(14 * Q, 9.8, false, false), None);
        assert!(w.escalated());
    }

    #[test]
    fn an_inverter_that_ramps_down_is_not_escalated() {
        let mut w = IgnoredStops::default();
        for k in 0..120 {
            // 40 A down to 0 over 2 s, then the sensor's noise.
            let i = if k < 8 { 40.0 - 5.0 * k as f32 } else { 0.3 };
            assert_eq!(w.on_fresh(k * Q, i, true, false), None);
        }
        // Current with no stop in force, or for the side not stopped: nothing.
        for t in 30..60 {
            assert_eq!(w.on_fresh(t * S, 50.0, false, true), None);
        }
        assert!(!w.escalated());
        // Interrupted flow restarts the count.
        let mut w = IgnoredStops::default();
        for k in 0..160 {
            let i = if k % 11 == 10 { 0.0 } else { -20.0 };
            assert_eq!(w.on_fresh(k * Q, i, false, true), None);
        }
    }

    #[test]
    fn a_discharge_against_its_stop_is_seen_too() {
        let mut w = IgnoredStops::default();
        let mut got = None;
        for k in 0..=16 {
            got = got.or(w.on_fresh(k * Q, -100.0, false, true));
        }
        let e = got.unwrap();
        assert_eq!((e.side, e.current_da, e.for_s), (Side::Discharge, 1000, 3));
        assert_eq!(w.last(), Some(e));
    }
}
