//! The BMS side: everything that talks to the TinyBMS over its UART, below the
//! bridge.
//!
//! * [`link`] — one outstanding request at a time: response timeout, wake-up
//!   resend, bounded retries, offline detection, link statistics.
//! * [`reader`] — register blocks read whole on a clean line and in pieces on a
//!   bad one, confirmed by a second read where the values do not change by
//!   themselves.
//! * [`checks`] — the consistency checks a live block must pass before it is
//!   published.
//! * [`event_log`] — every BMS event reported exactly once.
//! * [`profile`] — the settings profile written to the BMS at start-up (empty by
//!   default) and the setting names.
//! * [`timing`] — periods and timeouts, every default a named constant.
//! * [`wire`] — the link counters of a window in figures (damaged, lost,
//!   resent per thousand sends) and a verdict in words (healthy, noisy, a bad
//!   wire, a silent or a sleeping BMS).

pub mod checks;
pub mod event_log;
pub mod link;
pub mod profile;
pub mod reader;
pub mod timing;
pub mod uart;
pub mod wire;
