//! The inverter dialects behind one seam. Each dialect is one file that puts
//! a [`Say`] into its frames and reads them back ([`Told`]); this module
//! lists them once, in [`DIALECTS`] — the configuration's choices
//! (`inverter_protocol`), `sim --inverter` and the docs' table are derived
//! from that list — and says per dialect what its inverters are known to do
//! (heartbeat, answering only, ignoring a limit of 0 A, stopping on silence).
//! The output itself (`super::Inverter`) never branches on the dialect.
//!
//! A new dialect is one file (its frames, `frames` and `read_back`) and one
//! row of [`DIALECTS`] (with its name in [`Protocol`]).
//!
//! [`shared`] is the leaf every dialect imports: the frame, the byte helpers,
//! [`Say`], [`Period`], [`Stops`] and [`Told`].

pub mod growatt;
pub mod pylon;
pub mod shared;
pub mod sma;
pub mod victron;

pub use shared::{CanFrame, Frames, Period, Protected, Say, StopWhy, Stops, Told, MAX_FRAMES};

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

/// What a dialect's inverter does when the battery's frames stop, and so
/// what the bridge sends once a stop is decided blind (the hold is over,
/// its budget spent, or the stale policy is `stop`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum OnSilence {
    /// The inverter stops by itself a few seconds after the last frame: the
    /// bridge says the stop for [`STOP_BEFORE_QUIET`] periods (so the last
    /// thing heard is a stop), then goes quiet.
    Stops,
    /// The inverter may run on: the stop goes out every period until the
    /// data is back.
    RunsOn,
}

/// Periods of a blind stop before a dialect whose inverter stops on silence
/// ([`OnSilence::Stops`]) goes quiet.
pub const STOP_BEFORE_QUIET: u8 = 5;

/// One dialect: its name, what its inverters are known to do, and its two
/// functions.
pub struct Dialect {
    /// Its name in [`Protocol`].
    pub protocol: Protocol,
    /// As the configuration writes it (`inverter_protocol`).
    pub key: &'static str,
    /// As the log names it.
    pub title: &'static str,
    /// Its specification (the docs' table).
    pub spec: &'static str,
    /// The inverter's heartbeat identifiers (the GX's keep-alive, the
    /// Pylontech family's 0x305, Growatt's query 0x301).
    pub heartbeat: &'static [u16],
    /// The battery speaks only in answer to the inverter's query (Growatt's
    /// 0x301): frames computed each period are kept for the answer.
    pub answers_only: bool,
    /// Inverters of this dialect are known to ignore a current limit of 0 A
    /// (Deye and Solis on the Pylontech family: Battery-Emulator #1534,
    /// diyBMS #216, YamBMS #184): a stop is also said by the SOC (with
    /// `stop_by_soc`, on by default), the charge voltage and the enable bits.
    pub ignores_zero: bool,
    /// What its inverter does when the frames stop, and the source.
    pub on_silence: (OnSilence, &'static str),
    /// The frames of one period for this dialect.
    pub frames: fn(&Period<'_>, &mut Frames),
    /// What a frame of this dialect tells, into `told`.
    pub read_back: fn(&CanFrame, &mut Told),
}

/// Every dialect, in the order of the configuration's choices (the record
/// stores the index).
pub const DIALECTS: [Dialect; 6] = [
    victron::DIALECT,
    sma::DIALECT,
    pylon::PYLON,
    pylon::SOLARK,
    pylon::LUXPOWER,
    growatt::DIALECT,
];

/// Every protocol, in the order of [`DIALECTS`].
// The index stays below the length of both arrays, and a constant is worked
// out at build time: an index out of bounds would fail the build, never run.
#[allow(clippy::indexing_slicing)]
pub const PROTOCOLS: [Protocol; DIALECTS.len()] = {
    let mut out = [Protocol::Victron; DIALECTS.len()];
    let mut i = 0;
    while i < DIALECTS.len() {
        out[i] = DIALECTS[i].protocol;
        i += 1;
    }
    out
};

/// Every dialect's key, in the order of [`DIALECTS`] (the configuration's
/// choices of `inverter_protocol`).
// As PROTOCOLS: in bounds, and worked out at build time.
#[allow(clippy::indexing_slicing)]
pub const KEYS: [&str; DIALECTS.len()] = {
    let mut out = [""; DIALECTS.len()];
    let mut i = 0;
    while i < DIALECTS.len() {
        out[i] = DIALECTS[i].key;
        i += 1;
    }
    out
};

impl Protocol {
    /// Its row of [`DIALECTS`].
    pub fn dialect(self) -> &'static Dialect {
        let i = usize::from(self.index());
        DIALECTS.get(i).unwrap_or(&DIALECTS[0])
    }

    /// As the configuration writes it (`inverter_protocol`).
    pub fn key(self) -> &'static str {
        self.dialect().key
    }

    /// As the log names it.
    pub fn title(self) -> &'static str {
        self.dialect().title
    }

    /// Its place in [`DIALECTS`].
    pub fn index(self) -> u8 {
        PROTOCOLS.iter().position(|p| *p == self).unwrap_or(0) as u8
    }

    /// The protocol at `i` in [`DIALECTS`].
    pub fn from_index(i: u8) -> Option<Self> {
        PROTOCOLS.get(usize::from(i)).copied()
    }

    /// The protocol whose key is `key`.
    pub fn from_key(key: &str) -> Option<Self> {
        DIALECTS.iter().find(|d| d.key == key).map(|d| d.protocol)
    }

    /// A 48 V hybrid inverter's protocol (the Pylontech LV family and
    /// Growatt): its inverters may ignore a current limit of 0 A.
    pub fn low_voltage_family(self) -> bool {
        self.dialect().ignores_zero
    }

    /// The battery speaks only in answer to the inverter's query.
    pub fn answers_only(self) -> bool {
        self.dialect().answers_only
    }

    /// `id` from the inverter is its heartbeat.
    pub fn heartbeat(self, id: u16) -> bool {
        self.dialect().heartbeat.contains(&id)
    }

    /// What its inverter does when the frames stop.
    pub fn on_silence(self) -> OnSilence {
        self.dialect().on_silence.0
    }

    /// The frames of one period.
    pub fn frames(self, p: &Period<'_>) -> Frames {
        let mut out = Frames::new();
        (self.dialect().frames)(p, &mut out);
        out
    }

    /// What `f` tells the inverter, into `told`.
    pub fn read_back(self, f: &CanFrame, told: &mut Told) {
        (self.dialect().read_back)(f, told);
    }

    /// The limits a frame of this protocol tells the inverter (its 0x351,
    /// Growatt's 0x311), if it is one.
    pub fn limits_of(self, f: &CanFrame) -> Option<Limits> {
        let mut t = Told::default();
        self.read_back(f, &mut t);
        t.limits
    }
}

use crate::inverter::control::Limits;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_list_is_written_once_and_in_order() {
        for (i, d) in DIALECTS.iter().enumerate() {
            assert_eq!(usize::from(d.protocol.index()), i);
            assert_eq!(Protocol::from_index(i as u8), Some(d.protocol));
            assert_eq!(Protocol::from_key(d.key), Some(d.protocol));
            assert_eq!(d.protocol.key(), KEYS[i]);
        }
        assert_eq!(Protocol::from_index(DIALECTS.len() as u8), None);
    }
}
