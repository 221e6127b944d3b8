//! The inverter protocols, behind one seam: what differs between a Victron
//! GX, an SMA Sunny Island and the 48 V hybrid inverters of the Pylontech LV
//! family is here (the frames of a period, the limits frame, the frames of
//! stale data, whether the inverter keeps obeying the last limits it got,
//! whether the battery speaks only when asked); the output itself
//! (`super::Inverter`) never branches on the protocol.

use super::control::{Conditions, Limits, PackSettings, PackState};
use super::frames::{self, CanFrame};
use super::{growatt, pylon};

/// Which inverter protocol.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Protocol {
    /// Victron-compatible CAN-bus BMS (500 kbit/s).
    Victron,
    /// SMA Sunny Island (500 kbit/s).
    SmaSunnyIsland,
    /// Pylontech LV V1.2 (Deye, Sunsynk, Sofar, Growatt SPF, EG4, MidNite,
    /// GoodWe, Solis "Pylon LV"…).
    Pylon,
    /// Sol-Ark LV V1.3 (8-byte frames, 0x356 in 0.1 V, 0x379).
    SolArk,
    /// Luxpower V04.2 (EG4 "Lithium 6"; cell extremes, capacity in 0x359).
    Luxpower,
    /// Growatt LV V1.04: big-endian, answers the inverter's 0x301 only.
    Growatt,
}

/// Every protocol, in the order of the configuration's choices
/// (`inverter_protocol`; the record stores the index).
pub const PROTOCOLS: [Protocol; 6] = [
    Protocol::Victron,
    Protocol::SmaSunnyIsland,
    Protocol::Pylon,
    Protocol::SolArk,
    Protocol::Luxpower,
    Protocol::Growatt,
];

impl Protocol {
    /// As the configuration writes it (`inverter_protocol`).
    pub const fn key(self) -> &'static str {
        match self {
            Self::Victron => "victron",
            Self::SmaSunnyIsland => "sma",
            Self::Pylon => "pylon",
            Self::SolArk => "solark",
            Self::Luxpower => "luxpower",
            Self::Growatt => "growatt",
        }
    }

    /// As the log names it.
    pub const fn title(self) -> &'static str {
        match self {
            Self::Victron => "Victron",
            Self::SmaSunnyIsland => "SMA Sunny Island",
            Self::Pylon => "Pylontech LV (V1.2)",
            Self::SolArk => "Sol-Ark LV (V1.3)",
            Self::Luxpower => "Luxpower (V04.2)",
            Self::Growatt => "Growatt LV (V1.04)",
        }
    }

    /// Its place in [`PROTOCOLS`].
    pub fn index(self) -> u8 {
        PROTOCOLS.iter().position(|p| *p == self).unwrap_or(0) as u8
    }

    /// The protocol at `i` in [`PROTOCOLS`].
    pub fn from_index(i: u8) -> Option<Self> {
        PROTOCOLS.get(usize::from(i)).copied()
    }

    /// A 48 V hybrid inverter's protocol (the Pylontech LV family): it may
    /// ignore a current limit of 0 A, so charge (discharge) is also stopped by
    /// what such inverters obey (see [`pylon::Stops`]).
    pub const fn low_voltage_family(self) -> bool {
        matches!(
            self,
            Self::Pylon | Self::SolArk | Self::Luxpower | Self::Growatt
        )
    }

    /// The battery speaks only in answer to the inverter's query (Growatt's
    /// 0x301): frames computed each period are kept for the answer, never
    /// sent unasked.
    pub const fn answers_only(self) -> bool {
        matches!(self, Self::Growatt)
    }

    /// `id` from the inverter is its heartbeat (the GX's keep-alive, 0x305 of
    /// the Pylontech family, Growatt's query 0x301).
    pub fn heartbeat(self, id: u16) -> bool {
        match self {
            Self::Victron | Self::SmaSunnyIsland => {
                id == frames::ID_GX_KEEPALIVE || id == frames::ID_GX_KEEPALIVE_2
            }
            Self::Pylon | Self::SolArk | Self::Luxpower => id == pylon::ID_HEARTBEAT,
            Self::Growatt => id == growatt::ID_QUERY,
        }
    }
}

/// What the frames of one period are made of.
pub struct Period<'a> {
    /// The limits computed (before what the Pylontech family adds: see
    /// [`pylon::Stops`]).
    pub limits: &'a Limits,
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
    /// The Pylontech family: what it says beyond the limits (name, enable
    /// bits, requests, SOC reported).
    pub lv: pylon::Extras,
    /// The BMS's settings (Growatt's cell count and battery type).
    pub settings: Option<&'a PackSettings>,
}

impl Protocol {
    /// The frames of one period, in the order they are sent.
    pub fn period_frames(self, p: &Period<'_>, push: &mut impl FnMut(CanFrame)) {
        match self {
            Self::Victron | Self::SmaSunnyIsland => push(frames::limits(p.limits)),
            Self::Pylon | Self::SolArk | Self::Luxpower => {
                return pylon::period_frames(self, p, push);
            }
            Self::Growatt => return growatt::answer_frames(p, push),
        }
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
            _ => {}
        }
    }

    /// Stale data: the limits frame with `limits` (CCL 0, and DCL 0 when
    /// discharge stops too) and the alarm frame with `c` (the link lost
    /// flagged); no measurement frame, which would be stale values sent as
    /// fresh. `modules`: the packs the alarm frame counts (the Pylontech
    /// family's 0x359).
    pub fn stale_frames(
        self,
        limits: &Limits,
        c: &Conditions,
        lv: &pylon::Extras,
        push: &mut impl FnMut(CanFrame),
    ) {
        match self {
            Self::Victron => {
                push(frames::limits(limits));
                push(frames::victron_alarms(c));
            }
            Self::SmaSunnyIsland => {
                push(frames::limits(limits));
                push(frames::sma_alarms(c));
            }
            Self::Pylon | Self::SolArk | Self::Luxpower => {
                pylon::stale_frames(self, limits, c, lv, push)
            }
            Self::Growatt => growatt::stale_frames(limits, c, lv, push),
        }
    }

    /// The limits a frame of this protocol tells the inverter (its 0x351,
    /// Growatt's 0x311), if it is one.
    pub fn limits_of(self, f: &CanFrame) -> Option<Limits> {
        match self {
            Self::Victron | Self::SmaSunnyIsland => frames::limits_of(f),
            Self::Pylon | Self::SolArk | Self::Luxpower => pylon::limits_of(f),
            Self::Growatt => growatt::limits_of(f),
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
