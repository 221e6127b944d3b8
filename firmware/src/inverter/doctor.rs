//! The doctor of the inverter's wire: verdicts in words, each with what to
//! do, computed from what the capture holds ([`super::capture`]) — the frames
//! this bridge sent and heard and the bus's errors — and nothing else, so
//! that a capture file gives the same verdicts on a desk as on the bridge.
//!
//! Each rule keeps its evidence for [`KEEP_US`] after it was last seen. The
//! rules and their thresholds:
//!
//! * **no acknowledgement**: [`NO_ACK_MIN`] frames in a row nobody
//!   acknowledged (no other node, CAN-H/CAN-L, termination, bit rate);
//! * **bus-off**: the controller left the bus;
//! * **no inverter heard**: frames acknowledged for [`QUIET_US`] without a
//!   frame of the inverter's (its heartbeat or query);
//! * **heartbeat late**: a gap of more than [`LATE_US`] between two of the
//!   inverter's frames (an inverter that goes quieter than that for longer
//!   than the output's timeout counts as lost: the same verdict, longer gap);
//! * **another dialect**: a frame only an inverter of another dialect sends
//!   (Growatt's query 0x301, a Victron GX's 0x307);
//! * **more than the limit**: the current the bridge reports (its own 0x356)
//!   above the limit it tells (its own 0x351) by more than [`OVER_MARGIN_DA`]
//!   and [`OVER_MARGIN_PCT`] for [`OVER_FOR_US`];
//! * **voltages disagree**: an SMA Sunny Island's 0x305 voltage (bytes 0-1,
//!   0.1 V) off the bridge's 0x356 voltage by more than [`VOLTAGE_OFF_DV`] for
//!   [`VOLTAGE_FOR_US`];
//! * **a name the inverters are not known to take**: a Pylontech-family 0x35E
//!   outside [`KNOWN_NAMES`];
//! * **energy out after a CVL step down**: within [`EXPORT_WINDOW_US`] of a
//!   CVL lowered by at least [`STEP_DV`], a discharge above
//!   [`EXPORT_MIN_DA`] with the pack voltage at or above the new CVL less
//!   0.1 V, for [`EXPORT_FOR_US`] (an inverter pulling the pack down to
//!   the new charge voltage: into the grid or the loads).
//!
//! Growatt's frames (big-endian 0x311/0x313) carry no 0x356: the current
//! rules do not apply to it. A Growatt-speaking bridge says nothing until the
//! inverter asks: with no inverter its capture stays empty, so the bridge
//! tells the doctor the time ([`Doctor::on_quiet`]) and no query for
//! [`QUIET_US`] is "no inverter heard" too (on the bridge only: an empty
//! capture file has no time).

use super::capture::Seen;
use super::dialect::{CanFrame, Protocol};
use crate::log_line::Line;
use crate::Instant;

/// Evidence is kept this long after it was last seen, µs.
pub const KEEP_US: Instant = 60 * crate::SECOND;
/// Frames in a row without an acknowledgement before the verdict.
pub const NO_ACK_MIN: u16 = 3;
/// Acknowledged frames for this long without a frame of the inverter's, µs.
pub const QUIET_US: Instant = 10 * crate::SECOND;
/// A gap between two of the inverter's frames longer than this is late, µs
/// (the heartbeat comes every second).
pub const LATE_US: Instant = 3 * crate::SECOND;
/// The current is over the limit by more than this, 0.1 A…
pub const OVER_MARGIN_DA: i32 = 20;
/// …and more than this share of the limit, %.
pub const OVER_MARGIN_PCT: i32 = 10;
/// …for this long, µs.
pub const OVER_FOR_US: Instant = 20 * crate::SECOND;
/// Voltages disagree by more than this, 0.1 V…
pub const VOLTAGE_OFF_DV: i32 = 10;
/// …for this long, µs.
pub const VOLTAGE_FOR_US: Instant = 10 * crate::SECOND;
/// A CVL step down of at least this, 0.1 V.
pub const STEP_DV: u16 = 2;
/// Energy out is looked for this long after a step down, µs.
pub const EXPORT_WINDOW_US: Instant = 15 * 60 * crate::SECOND;
/// A discharge above this, 0.1 A…
pub const EXPORT_MIN_DA: i32 = 20;
/// …for this long, µs.
pub const EXPORT_FOR_US: Instant = 20 * crate::SECOND;
/// 0x35E names inverters of the Pylontech family are known to take
/// (YamBMS offers these for that reason), space-padded.
pub const KNOWN_NAMES: [&[u8; 8]; 6] = [
    b"PYLON   ",
    b"GOODWE  ",
    b"SHEnergy",
    b"SMA     ",
    b"BYD     ",
    b"DEYE    ",
];

/// One verdict.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Verdict {
    /// Frames in a row nobody acknowledged.
    NoAck {
        /// How many.
        frames: u16,
    },
    /// The controller left the bus.
    BusOff,
    /// Frames acknowledged, the inverter silent.
    NoInverter {
        /// For how long, s.
        for_s: u32,
    },
    /// Gaps in the inverter's heartbeat.
    HeartbeatLate {
        /// Gaps longer than [`LATE_US`] in the evidence.
        late: u16,
        /// The longest, ms.
        longest_ms: u32,
    },
    /// A frame of another dialect's inverter.
    OtherDialect {
        /// Its identifier.
        id: u16,
        /// The dialect it belongs to.
        heard: Protocol,
    },
    /// The current past the limit told.
    OverLimit {
        /// The charge (true) or the discharge.
        charge: bool,
        /// The current, 0.1 A (magnitude).
        current_da: u16,
        /// The limit told, 0.1 A.
        limit_da: u16,
        /// For how long, s.
        for_s: u32,
    },
    /// The inverter's voltage and the BMS's disagree.
    VoltageDisagrees {
        /// The inverter's, 0.1 V.
        inverter_dv: u16,
        /// The bridge's (the BMS's), 0.1 V.
        bms_dv: u16,
    },
    /// A 0x35E name the inverters are not known to take.
    UnknownName {
        /// The name sent.
        name: [u8; 8],
    },
    /// A discharge after a CVL step down.
    ExportAfterStep {
        /// CVL before, 0.1 V.
        from_dv: u16,
        /// CVL after, 0.1 V.
        to_dv: u16,
        /// The discharge, 0.1 A.
        current_da: u16,
    },
}

/// The kinds of verdict, in the order they are listed.
pub const KINDS: usize = 9;

impl Verdict {
    fn kind(&self) -> usize {
        match self {
            Self::NoAck { .. } => 0,
            Self::BusOff => 1,
            Self::NoInverter { .. } => 2,
            Self::HeartbeatLate { .. } => 3,
            Self::OtherDialect { .. } => 4,
            Self::OverLimit { .. } => 5,
            Self::VoltageDisagrees { .. } => 6,
            Self::UnknownName { .. } => 7,
            Self::ExportAfterStep { .. } => 8,
        }
    }

    /// A short key (fixtures, the host link, Home Assistant).
    pub const fn key(&self) -> &'static str {
        match self {
            Self::NoAck { .. } => "no_ack",
            Self::BusOff => "bus_off",
            Self::NoInverter { .. } => "no_inverter",
            Self::HeartbeatLate { .. } => "heartbeat_late",
            Self::OtherDialect { .. } => "other_dialect",
            Self::OverLimit { .. } => "over_limit",
            Self::VoltageDisagrees { .. } => "voltage_disagrees",
            Self::UnknownName { .. } => "unknown_name",
            Self::ExportAfterStep { .. } => "export_after_step",
        }
    }

    /// What is wrong and what to do, in words.
    pub fn write(&self, out: &mut Line) {
        match *self {
            Self::NoAck { frames } => {
                out.uint(u64::from(frames)).push(
                    " frames in a row nobody acknowledged: no other node hears the bridge. \
                     Check CAN-H/CAN-L (not swapped), a 120 ohm terminator at each end, the \
                     inverter on and its bit rate 500 kbit/s",
                );
            }
            Self::BusOff => {
                out.push(
                    "bus-off: the controller saw so many errors it left the bus. Check the \
                     bit rate (500 kbit/s), CAN-H/CAN-L swapped or shorted, the termination, \
                     a ground between the bridge and the inverter",
                );
            }
            Self::NoInverter { for_s } => {
                out.push("the frames are acknowledged but the inverter said nothing for ")
                    .duration_s(u64::from(for_s))
                    .push(
                        ": another node acknowledges. Check the inverter's battery type \
                         (CAN / lithium with BMS), that it is on this bus, and the protocol",
                    );
            }
            Self::HeartbeatLate { late, longest_ms } => {
                out.push("the inverter's heartbeat came late ")
                    .uint(u64::from(late))
                    .push(" time(s), the longest gap ")
                    .fixed(i64::from(longest_ms / 100), 1)
                    .push(
                        " s: a busy or failing inverter, a loose CAN wire, or another node \
                           flooding the bus",
                    );
            }
            Self::OtherDialect { id, heard } => {
                out.push("heard 0x");
                let mut hex = [0u8; 2];
                hex[0] = (id >> 8) as u8;
                hex[1] = id as u8;
                out.hex_bytes(&hex)
                    .push(", which only a ")
                    .push(heard.title())
                    .push(" inverter sends: set inverter_protocol to ")
                    .push(heard.key())
                    .push(" (or the inverter's battery protocol to the one configured)");
            }
            Self::OverLimit {
                charge,
                current_da,
                limit_da,
                for_s,
            } => {
                out.push(if charge {
                    "the inverter charges at "
                } else {
                    "the inverter discharges at "
                })
                .fixed(i64::from(current_da), 1)
                .push(" A against a limit of ")
                .fixed(i64::from(limit_da), 1)
                .push(" A for ")
                .duration_s(u64::from(for_s))
                .push(
                    ": it does not follow the limits. Check that it is in BMS (CAN) mode, \
                     its own current settings, and inverter_model",
                );
            }
            Self::VoltageDisagrees {
                inverter_dv,
                bms_dv,
            } => {
                out.push("the inverter measures ")
                    .fixed(i64::from(inverter_dv), 1)
                    .push(" V, the BMS ")
                    .fixed(i64::from(bms_dv), 1)
                    .push(" V: check the battery cables, the fuse and the shunt's wiring, and the inverter's voltage calibration");
            }
            Self::UnknownName { name } => {
                out.push("0x35E names the battery \"")
                    .push(core::str::from_utf8(&name).unwrap_or("?").trim_end())
                    .push(
                        "\", which inverters are not known to take: most expect PYLON \
                         (GoodWe: GOODWE); set inverter_name",
                    );
            }
            Self::ExportAfterStep {
                from_dv,
                to_dv,
                current_da,
            } => {
                out.push("after CVL fell from ")
                    .fixed(i64::from(from_dv), 1)
                    .push(" V to ")
                    .fixed(i64::from(to_dv), 1)
                    .push(" V the pack gave ")
                    .fixed(i64::from(current_da), 1)
                    .push(
                        " A: the inverter pulls it down to the new charge voltage (into the \
                         grid or the loads). Keep float_step on, or set the inverter not to \
                         discharge the battery to the grid",
                    );
            }
        }
    }
}

/// The inverter's heartbeat as heard.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Heartbeat {
    /// Frames of the inverter's heard.
    pub count: u32,
    /// Mean interval, ms (0 before two).
    pub mean_ms: u32,
    /// Longest gap, ms.
    pub longest_ms: u32,
    /// Gaps longer than [`LATE_US`].
    pub late: u32,
}

/// A condition held since a time (sustained rules).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct Since(Option<Instant>);

impl Since {
    /// `on` at `now`: how long it has held.
    fn hold(&mut self, on: bool, now: Instant) -> Option<Instant> {
        if !on {
            self.0 = None;
            return None;
        }
        Some(now.saturating_sub(*self.0.get_or_insert(now)))
    }
}

/// The doctor. Feed it every entry of the capture in order
/// ([`Doctor::on_entry`]); [`Doctor::verdicts`] says what it found.
#[derive(Debug, Clone)]
pub struct Doctor {
    protocol: Protocol,
    found: [Option<(Verdict, Instant)>; KINDS],
    no_ack_run: u16,
    first_acked: Option<Instant>,
    heard_at: Option<Instant>,
    heartbeat: Heartbeat,
    gap_sum_ms: u64,
    late_window: u16,
    /// The limits told (CVL 0.1 V, CCL, DCL 0.1 A) and the CVL before a step.
    limits: Option<(u16, u16, u16)>,
    step: Option<(u16, u16, Instant)>,
    /// The bridge's pack voltage (0.1 V) and current (0.1 A) told.
    pack: Option<(u16, i32)>,
    over: Since,
    voltage_off: Since,
    export: Since,
    /// A verdict that was not held before (for the log), not yet taken.
    news: Option<Verdict>,
    /// The first time [`Doctor::on_quiet`] was called.
    quiet_from: Option<Instant>,
}

impl Doctor {
    /// A doctor for a bridge speaking `protocol`.
    pub const fn new(protocol: Protocol) -> Self {
        Self {
            protocol,
            found: [None; KINDS],
            no_ack_run: 0,
            first_acked: None,
            heard_at: None,
            heartbeat: Heartbeat {
                count: 0,
                mean_ms: 0,
                longest_ms: 0,
                late: 0,
            },
            gap_sum_ms: 0,
            late_window: 0,
            limits: None,
            step: None,
            pack: None,
            over: Since(None),
            voltage_off: Since(None),
            export: Since(None),
            news: None,
            quiet_from: None,
        }
    }

    /// The time, for a bridge that speaks only when asked (Growatt): nothing
    /// heard of the inverter for [`QUIET_US`] is "no inverter heard".
    pub fn on_quiet(&mut self, now: Instant) {
        let from = *self.quiet_from.get_or_insert(now);
        let since = self.heard_at.map_or(from, |h| h.max(from));
        let quiet = now.saturating_sub(since);
        if quiet >= QUIET_US {
            self.found(
                Verdict::NoInverter {
                    for_s: (quiet / crate::SECOND) as u32,
                },
                now,
            );
        }
    }

    /// A verdict that is new (its kind held no evidence of the last
    /// [`KEEP_US`]), once: the log says it when it begins.
    pub fn take_news(&mut self) -> Option<Verdict> {
        self.news.take()
    }

    /// The heartbeat as heard so far.
    pub fn heartbeat(&self) -> Heartbeat {
        self.heartbeat
    }

    fn found(&mut self, v: Verdict, now: Instant) {
        if let Some(slot) = self.found.get_mut(v.kind()) {
            let held = slot.is_some_and(|(_, at)| now.saturating_sub(at) <= KEEP_US);
            if !held {
                self.news = Some(v);
            }
            *slot = Some((v, now));
        }
    }

    /// One entry of the capture, in order.
    pub fn on_entry(&mut self, at: Instant, seen: Seen) {
        match seen {
            Seen::NoAck => {
                self.no_ack_run = self.no_ack_run.saturating_add(1);
                if self.no_ack_run >= NO_ACK_MIN {
                    self.found(
                        Verdict::NoAck {
                            frames: self.no_ack_run,
                        },
                        at,
                    );
                }
            }
            Seen::BusOff => self.found(Verdict::BusOff, at),
            Seen::Sent(f) => {
                self.no_ack_run = 0;
                self.first_acked.get_or_insert(at);
                self.on_sent(at, &f);
            }
            Seen::Heard(f) => self.on_heard(at, &f),
        }
        self.check_quiet(at);
    }

    /// Nothing heard of the inverter while frames are acknowledged.
    fn check_quiet(&mut self, at: Instant) {
        let since = match (self.heard_at, self.first_acked) {
            (Some(h), Some(a)) => h.max(a),
            (None, Some(a)) => a,
            _ => return,
        };
        let quiet = at.saturating_sub(since);
        if quiet >= QUIET_US && self.first_acked.is_some_and(|a| a <= at) {
            // Only while this bridge's frames get acknowledged.
            if self.no_ack_run == 0 {
                self.found(
                    Verdict::NoInverter {
                        for_s: (quiet / crate::SECOND) as u32,
                    },
                    at,
                );
            }
        }
    }

    fn on_heard(&mut self, at: Instant, f: &CanFrame) {
        let p = self.protocol;
        let other = match f.id {
            0x301 if p != Protocol::Growatt => Some(Protocol::Growatt),
            0x307 if p != Protocol::Victron => Some(Protocol::Victron),
            _ => None,
        };
        if let Some(heard) = other {
            self.found(Verdict::OtherDialect { id: f.id, heard }, at);
        }
        if p == Protocol::SmaSunnyIsland && f.id == 0x305 && f.bytes().iter().any(|b| *b != 0) {
            let inverter_dv = u16::from_le_bytes([f.byte(0), f.byte(1)]);
            if let Some((bms_dv, _)) = self.pack {
                let off = (i32::from(inverter_dv) - i32::from(bms_dv)).abs() > VOLTAGE_OFF_DV;
                if self
                    .voltage_off
                    .hold(off, at)
                    .is_some_and(|d| d >= VOLTAGE_FOR_US)
                {
                    self.found(
                        Verdict::VoltageDisagrees {
                            inverter_dv,
                            bms_dv,
                        },
                        at,
                    );
                }
            }
        }
        if p.heartbeat(f.id) {
            self.on_heartbeat(at);
        }
    }

    fn on_heartbeat(&mut self, at: Instant) {
        let h = &mut self.heartbeat;
        h.count = h.count.saturating_add(1);
        if let Some(last) = self.heard_at {
            let gap_ms = (at.saturating_sub(last) / crate::MS) as u32;
            self.gap_sum_ms = self.gap_sum_ms.saturating_add(u64::from(gap_ms));
            h.mean_ms = (self.gap_sum_ms / u64::from(h.count - 1).max(1)) as u32;
            h.longest_ms = h.longest_ms.max(gap_ms);
            if Instant::from(gap_ms) * crate::MS > LATE_US {
                h.late = h.late.saturating_add(1);
                let fresh = self.found[3].is_some_and(|(_, t)| at.saturating_sub(t) <= KEEP_US);
                self.late_window = if fresh {
                    self.late_window.saturating_add(1)
                } else {
                    1
                };
                let longest = match self.found[3] {
                    Some((Verdict::HeartbeatLate { longest_ms, .. }, _)) if fresh => {
                        longest_ms.max(gap_ms)
                    }
                    _ => gap_ms,
                };
                self.found(
                    Verdict::HeartbeatLate {
                        late: self.late_window,
                        longest_ms: longest,
                    },
                    at,
                );
            }
        }
        self.heard_at = Some(at);
    }

    fn on_sent(&mut self, at: Instant, f: &CanFrame) {
        let p = self.protocol;
        if let Some(l) = p.limits_of(f) {
            if let Some((cvl, _, _)) = self.limits {
                if l.cvl_dv.saturating_add(STEP_DV) <= cvl {
                    self.step = Some((cvl, l.cvl_dv, at));
                }
            }
            self.limits = Some((l.cvl_dv, l.ccl_da, l.dcl_da));
        }
        if f.id == 0x35E && p.low_voltage_family() && p != Protocol::Growatt {
            let name = f.data;
            if !KNOWN_NAMES.iter().any(|k| **k == name) {
                self.found(Verdict::UnknownName { name }, at);
            }
        }
        if f.id == 0x356 && p != Protocol::Growatt && f.len >= 4 {
            let raw = i16::from_le_bytes([f.byte(0), f.byte(1)]);
            // Sol-Ark's 0x356 voltage is in 0.1 V, the others' in 0.01 V.
            let dv = if p == Protocol::SolArk {
                i32::from(raw)
            } else {
                i32::from(raw) / 10
            };
            let current_da = i32::from(i16::from_le_bytes([f.byte(2), f.byte(3)]));
            self.pack = Some((dv.clamp(0, i32::from(u16::MAX)) as u16, current_da));
            self.check_currents(at, dv, current_da);
        }
    }

    /// The current against the limits, and after a step down.
    fn check_currents(&mut self, at: Instant, dv: i32, current_da: i32) {
        let Some((cvl, ccl, dcl)) = self.limits else {
            return;
        };
        let charge = current_da > 0;
        let limit = i32::from(if charge { ccl } else { dcl });
        let magnitude = current_da.abs();
        let over = magnitude > limit + OVER_MARGIN_DA.max(limit * OVER_MARGIN_PCT / 100);
        if let Some(d) = self.over.hold(over, at).filter(|d| *d >= OVER_FOR_US) {
            self.found(
                Verdict::OverLimit {
                    charge,
                    current_da: magnitude.min(i32::from(u16::MAX)) as u16,
                    limit_da: limit as u16,
                    for_s: (d / crate::SECOND) as u32,
                },
                at,
            );
        }
        let after_step = self
            .step
            .filter(|(_, _, t)| at.saturating_sub(*t) <= EXPORT_WINDOW_US);
        let out = after_step.is_some() && current_da < -EXPORT_MIN_DA && dv + 1 >= i32::from(cvl);
        if let (Some((from_dv, to_dv, _)), Some(_)) = (
            after_step,
            self.export.hold(out, at).filter(|d| *d >= EXPORT_FOR_US),
        ) {
            self.found(
                Verdict::ExportAfterStep {
                    from_dv,
                    to_dv,
                    current_da: (-current_da).min(i32::from(u16::MAX)) as u16,
                },
                at,
            );
        }
    }

    /// The verdicts whose evidence is at most [`KEEP_US`] old at `now`, in
    /// their order; `None` for all of a capture read whole.
    pub fn verdicts(&self, now: Option<Instant>) -> heapless::Vec<Verdict, KINDS> {
        let mut out = heapless::Vec::new();
        for (v, at) in self.found.iter().flatten() {
            if now.is_none_or(|n| n.saturating_sub(*at) <= KEEP_US) {
                let _fits = out.push(*v); // one per kind
            }
        }
        out
    }

    /// [`Doctor::verdicts`] at `now` as a fixed array (the host link's
    /// state is `Copy`).
    pub fn verdict_array(&self, now: Instant) -> [Option<Verdict>; KINDS] {
        let mut a = [None; KINDS];
        for (slot, v) in a.iter_mut().zip(self.verdicts(Some(now))) {
            *slot = Some(v);
        }
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inverter::capture::Seen;

    fn f(id: u16, data: [u8; 8]) -> CanFrame {
        CanFrame::new(id, 8, data)
    }

    fn limits(cvl_dv: u16, ccl_da: u16, dcl_da: u16) -> CanFrame {
        let c = cvl_dv.to_le_bytes();
        let a = ccl_da.to_le_bytes();
        let d = dcl_da.to_le_bytes();
        f(0x351, [c[0], c[1], a[0], a[1], d[0], d[1], 0xE0, 0x01])
    }

    fn measured(v_cv: i16, i_da: i16) -> CanFrame {
        let v = v_cv.to_le_bytes();
        let i = i_da.to_le_bytes();
        f(0x356, [v[0], v[1], i[0], i[1], 0xFA, 0, 0, 0])
    }

    /// `secs` of a healthy Victron bus with the current `i_da` under CCL 100 A.
    fn healthy(d: &mut Doctor, from_s: u64, secs: u64, i_da: i16) {
        for s in from_s..from_s + secs {
            let t = s * crate::SECOND;
            d.on_entry(t, Seen::Sent(limits(552, 1000, 1000)));
            d.on_entry(t + 1000, Seen::Sent(measured(5300, i_da)));
            d.on_entry(t + 400_000, Seen::Heard(f(0x305, [0; 8])));
        }
    }

    fn keys(d: &Doctor) -> heapless::Vec<&'static str, KINDS> {
        d.verdicts(None).iter().map(|v| v.key()).collect()
    }

    #[test]
    fn a_healthy_bus_has_no_verdict() {
        let mut d = Doctor::new(Protocol::Victron);
        healthy(&mut d, 0, 120, 500);
        assert!(keys(&d).is_empty(), "{:?}", keys(&d));
        let h = d.heartbeat();
        assert_eq!(
            (h.count, h.mean_ms, h.longest_ms, h.late),
            (120, 1000, 1000, 0)
        );
    }

    #[test]
    fn each_rule_fires_on_its_evidence() {
        let mut d = Doctor::new(Protocol::Victron);
        for k in 0..3 {
            d.on_entry(k * 100_000, Seen::NoAck);
        }
        assert_eq!(keys(&d), ["no_ack"]);

        let mut d = Doctor::new(Protocol::Victron);
        for s in 0..11 {
            d.on_entry(s * crate::SECOND, Seen::Sent(limits(552, 1000, 1000)));
        }
        assert_eq!(keys(&d), ["no_inverter"]);

        let mut d = Doctor::new(Protocol::Victron);
        healthy(&mut d, 0, 10, 0);
        healthy(&mut d, 14, 10, 0); // a 4 s gap in the heartbeat
        assert_eq!(keys(&d), ["heartbeat_late"]);

        let mut d = Doctor::new(Protocol::Pylon);
        d.on_entry(0, Seen::Heard(f(0x301, [0; 8])));
        assert_eq!(
            d.verdicts(None).first(),
            Some(&Verdict::OtherDialect {
                id: 0x301,
                heard: Protocol::Growatt
            })
        );

        let mut d = Doctor::new(Protocol::Victron);
        healthy(&mut d, 0, 40, 1300); // 130 A against 100 A
        assert_eq!(keys(&d), ["over_limit"]);

        let mut d = Doctor::new(Protocol::Pylon);
        d.on_entry(0, Seen::Sent(f(0x35E, *b"TINYBMS ")));
        assert_eq!(keys(&d), ["unknown_name"]);
        let mut d = Doctor::new(Protocol::Pylon);
        d.on_entry(0, Seen::Sent(f(0x35E, *b"PYLON   ")));
        assert!(keys(&d).is_empty());
    }

    #[test]
    fn the_limits_are_what_over_limit_goes_by() {
        // 109 A against 100 A: within 10 %: no verdict; 111 A: one.
        for (i, fires) in [(1090, false), (1110, true)] {
            let mut d = Doctor::new(Protocol::Victron);
            healthy(&mut d, 0, 40, i);
            assert_eq!(!keys(&d).is_empty(), fires, "{i}");
        }
    }

    #[test]
    fn a_verdict_is_news_once_until_its_evidence_expires() {
        let mut d = Doctor::new(Protocol::Victron);
        d.on_entry(0, Seen::BusOff);
        assert_eq!(d.take_news(), Some(Verdict::BusOff));
        d.on_entry(crate::SECOND, Seen::BusOff);
        assert_eq!(d.take_news(), None);
        d.on_entry(KEEP_US + 2 * crate::SECOND, Seen::BusOff);
        assert_eq!(d.take_news(), Some(Verdict::BusOff));
    }

    #[test]
    fn a_bridge_that_answers_only_hears_no_query() {
        let mut d = Doctor::new(Protocol::Growatt);
        d.on_quiet(0);
        d.on_quiet(9 * crate::SECOND);
        assert!(d.verdicts(None).is_empty());
        d.on_quiet(QUIET_US);
        assert_eq!(
            d.verdicts(None).first().map(|v| v.key()),
            Some("no_inverter")
        );
        // Queries every second: nothing.
        let mut d = Doctor::new(Protocol::Growatt);
        for s in 0..30 {
            let t = s * crate::SECOND;
            d.on_entry(t, Seen::Heard(f(0x301, [0; 8])));
            d.on_quiet(t + 1);
        }
        assert!(d.verdicts(None).is_empty(), "{:?}", d.verdicts(None));
    }

    #[test]
    fn evidence_expires() {
        let mut d = Doctor::new(Protocol::Victron);
        d.on_entry(0, Seen::BusOff);
        assert_eq!(d.verdicts(Some(KEEP_US)).len(), 1);
        assert!(d.verdicts(Some(KEEP_US + 1)).is_empty());
    }
}
