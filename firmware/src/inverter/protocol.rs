//! The inverter protocols, behind one seam: what differs between a Victron
//! GX and an SMA Sunny Island is here (the frames of a period, the alarm
//! frame, whether the inverter keeps obeying the last limits it got); the
//! output itself (`super::Inverter`) never branches on the protocol.

use super::control::{Conditions, PackState};
use super::frames::{self, CanFrame};

/// Which inverter protocol.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Protocol {
    /// Victron-compatible CAN-bus BMS (500 kbit/s).
    Victron,
    /// SMA Sunny Island (500 kbit/s).
    SmaSunnyIsland,
}

impl Protocol {
    /// As the configuration writes it (`inverter_protocol`).
    pub const fn key(self) -> &'static str {
        match self {
            Self::Victron => "victron",
            Self::SmaSunnyIsland => "sma",
        }
    }
}

/// What the frames of one period are made of.
pub struct Period<'a> {
    /// The battery's state.
    pub state: &'a PackState,
    /// Its alarms and warnings.
    pub conditions: &'a Conditions,
    /// Its capacity, Ah.
    pub capacity_ah: u16,
    /// Modules (packs): online, blocking charge, blocking discharge, offline.
    pub modules: (u16, u16, u16, u16),
    /// The BMS's public firmware version (register 501).
    pub firmware: u16,
    /// The BMS's hardware version and changes (register 500).
    pub hardware: u16,
    /// This period also carries the slow frames (every fifth).
    pub slow: bool,
}

impl Protocol {
    /// The frames after 0x351 of one period, in the order they are sent.
    pub fn period_frames(self, p: &Period<'_>, push: &mut impl FnMut(CanFrame)) {
        match self {
            Self::Victron => {
                push(frames::victron_alarms(p.conditions));
                push(frames::soc(p.state));
                push(frames::measurements(p.state));
                if p.slow {
                    push(frames::name());
                    push(frames::victron_info(p.firmware, p.capacity_ah));
                    push(frames::module_counts(p.modules));
                    push(frames::cell_extremes(p.state));
                    push(frames::capacity(p.capacity_ah));
                }
            }
            Self::SmaSunnyIsland => {
                push(frames::sma_alarms(p.conditions));
                push(frames::soc(p.state));
                push(frames::sma_measurements(p.state));
                if p.slow {
                    push(frames::name());
                    push(frames::sma_info(p.hardware, p.capacity_ah, p.firmware));
                }
            }
        }
    }

    /// The alarm frame (0x35A) for `c`.
    pub fn alarms(self, c: &Conditions) -> CanFrame {
        match self {
            Self::Victron => frames::victron_alarms(c),
            Self::SmaSunnyIsland => frames::sma_alarms(c),
        }
    }

    /// The inverter keeps obeying the last 0x351 when frames stop (a Sunny
    /// Island does for 60 s, until 0x355 has been missing that long): to stop
    /// it, it must be sent CCL 0 and DCL 0. A GX stops by itself after 3 s
    /// without frames.
    pub fn obeys_last_limits(self) -> bool {
        matches!(self, Self::SmaSunnyIsland)
    }
}
