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
//! * [`link`] — one outstanding request at a time, response timeout, wake-up
//!   resend, bounded retries, offline detection, link statistics.
//! * [`bridge`] — on top of the link: the poll schedule, the sync phase, the
//!   telemetry model, the write/verify machine for settings (and the reset and
//!   clear commands), each in its own file under `bridge/`, and a thin
//!   coordinator whose narrow interface every consumer uses: read
//!   [`Bridge::telemetry`], act with [`Bridge::submit`], hear outcomes from
//!   [`Bridge::next_report`].
//! * [`reader`] — register blocks read whole on a clean line and in pieces on a
//!   bad one, confirmed by a second read where the values do not change by
//!   themselves.
//! * [`checks`] — the consistency checks a live block must pass before it is
//!   published.
//! * [`event_log`] — every BMS event reported exactly once.
//! * [`inverter`] — charge control and the inverter CAN protocols (Victron,
//!   SMA Sunny Island).
//! * [`config`] — every default as a named, documented constant.
//! * [`profile`] — the settings profile applied at start-up (empty by default).
//! * [`site`] — the inverter output of this installation (protocol, stale policy,
//!   CAN on/off).
//! * [`boards`] — the supported boards' pins and log paths, checked at compile time.
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

pub mod boards;
pub mod bridge;
pub mod checks;
pub mod config;
pub mod event_log;
pub mod host_link;
pub mod inverter;
pub mod link;
pub mod profile;
pub mod reader;
pub mod report;
pub mod site;

pub use bridge::{Action, Bridge, Command, LiveMeta, Step, Telemetry};
pub use link::{LinkStats, Transmit};
pub use report::{Level, Report};

/// Time in microseconds since an arbitrary origin (boot on the chip, 0 in the
/// simulator). Always passed in, never read.
pub type Instant = u64;

/// Microseconds per millisecond.
pub const MS: Instant = 1_000;
/// Microseconds per second.
pub const SECOND: Instant = 1_000_000;
