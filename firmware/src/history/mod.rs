//! The bridge's history in flash: what happened while nobody watched (the
//! event log) and how the pack ages (daily records, the capacity estimate),
//! kept across restarts in the `history` partition.
//!
//! | file | what |
//! | --- | --- |
//! | [`ring`] | a ring of fixed-size records in flash sectors: whole or absent after a power cut |
//! | [`event`] | the bridge's events as records |
//! | [`day`] | the record of each day of the pack and the book that fills it |
//! | [`capacity`] | how much charge the pack really holds: estimated from the runs between two points whose state of charge is known |
//! | [`log`] | the history as the station keeps it: what is written when, the listing |
//!
//! Sans-IO like the rest of the library: snapshots, events and time go in,
//! records, estimates and flash operations come out.

/// How the pack ages, as Home Assistant and the state show it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Aging {
    /// The measured capacity ([`capacity::Capacity::estimate`]), 0.01 Ah,
    /// and its uncertainty, 0.1 % (`None`: no run qualified yet).
    pub capacity: Option<(u32, u16)>,
    /// The TinyBMS's charging count (register 111), as last read.
    pub cycles: Option<u16>,
    /// The spread at the top of charge of the last closed day, mV.
    pub top_spread_mv: Option<u16>,
    /// The history is kept in flash (false: no partition, see `hello`).
    pub recording: bool,
}

pub mod capacity;
pub mod day;
pub mod event;
pub mod log;
pub mod ring;
