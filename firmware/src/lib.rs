//! # tinybms-firmware — the bridge logic
//!
//! Everything the ESP32 does with the TinyBMS, written as plain sans-IO `no_std`
//! code so that it also compiles and runs on the host (host-tests drives it against
//! a simulated BMS in virtual time). No HAL type, no `await`, no clock read: time is
//! an argument ([`Instant`], microseconds), bytes go in through
//! [`Bridge::handle_rx`], and [`Bridge::poll`] says what to do next — transmit these
//! bytes, or wait until a deadline. What happened comes out as [`Report`]s, which
//! the chip shell logs with `defmt` and the host simulator prints.
//!
//! The library is grouped by side:
//!
//! | side | module | what |
//! | --- | --- | --- |
//! | the BMS | [`bms`] | the UART link, block reads, the checks a snapshot passes, the event log, the start-up profile, timing |
//! | the bridge | [`bridge`] | the coordinator on top of the link: poll schedule, sync, telemetry, the write/verify machine, [`Report`]s |
//! | consumers | [`inverter`] | charge control and the inverter CAN protocols (Victron, SMA Sunny Island), the CAN port's health, several packs on one bus |
//! | | [`host_link`] | JSON Lines to a computer over USB |
//! | | [`improv`] | Improv Wi-Fi on the same port: the browser installer's network set-up |
//! | | [`mqtt`] | the battery in Home Assistant: discovery, state, availability (publish only) |
//! | | [`wifi`] | the Wi-Fi side's rules: joins, scans, the radio's start, the bridge's name on the network |
//! | this installation | [`config`] | the bridge's own configuration: the record, its checks, its store in flash |
//! | | [`boards`] | the supported boards' pins and log paths, checked at compile time |
//! | | [`partitions`] | the ESP-IDF partition table, read from its bytes; the history partition |
//! | | [`update`] | updates without a cable: signed update files, the transfer into the other app slot, the trial boot that rolls itself back |
//! | | [`identity`], [`energy`] | who the bridge is (firmware, build, chip, board, features); energy into and out of the pack |
//! | | [`history`] | the pack's days (a record of each) and its capacity, estimated between full and the knee |
//! | all of it | [`station`] | **the entry point**: one bridge with everything it feeds, wired together — what the chip runs and every desktop runner runs |
//! | shared | [`freshness`] | the one freshness rule and the one stale choice |
//! | | [`backoff`] | how a lost connection is retried (Wi-Fi and MQTT alike) |
//! | | [`text`], [`log_line`] | the words of every log line, and the bounded line they are written into |
//! | | [`units`] | raw and physical values, exact decimals |
//!
//! A runner builds a [`station::Station`] and drives it: bytes, frames and time
//! in, [`station::Action`]s out. Consumers read [`Bridge::telemetry`] and act
//! through [`Bridge::submit`]; none reaches into another's state.
#![no_std]
#![deny(missing_docs)]
#![deny(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]
#![cfg_attr(
    test,
    allow(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing
    )
)]
#![allow(clippy::large_enum_variant)]

pub mod backoff;
pub mod bms;
pub mod boards;
pub mod bridge;
pub mod config;
pub mod energy;
pub mod freshness;
pub mod history;
pub mod host_link;
pub mod identity;
pub mod improv;
pub mod inverter;
pub mod log_line;
pub mod mqtt;
pub mod partitions;
pub mod station;
pub mod text;
pub mod units;
pub mod update;
pub mod wifi;

pub use bms::link::{LinkStats, Transmit};
pub use bridge::report::{Level, Report};
pub use bridge::{Bridge, Command, LiveMeta, Step, Telemetry};

/// Time in microseconds since an arbitrary origin (boot on the chip, 0 in the
/// simulator). Always passed in, never read.
pub type Instant = u64;

/// Microseconds per millisecond.
pub const MS: Instant = 1_000;
/// Microseconds per second.
pub const SECOND: Instant = 1_000_000;
