//! The pack's history, kept by the bridge: what a day of the pack was
//! ([`day`]: the record of each day and the book that fills it) and how much
//! charge the pack really holds ([`capacity`]: estimated from the charges and
//! discharges between two points whose state of charge is known).
//!
//! Sans-IO like the rest of the library: snapshots and time go in, records
//! and estimates come out; where they are kept (flash) is the station's.

pub mod capacity;
pub mod day;
