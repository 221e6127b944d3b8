//! What the desktop tool (`tinybms`) and the browser console (compiled to
//! WebAssembly, `host-tests/web/wasm`) both say about a value an owner types:
//! checked by the firmware's own rules (its configuration field table, value
//! parser and rules between fields; the register map and the relations
//! between BMS settings), refused with one message, whichever of the two
//! asked. Plain `std` with no I/O, so it builds for `wasm32-unknown-unknown`.
//!
//! * [`words`] — numbers as short as they are exact, and "did you mean".
//! * [`config`] — the bridge's own configuration: `NAME=VALUE`, a change
//!   against the record the bridge holds, the text sent for a value.
//! * [`settings`] — the BMS's settings: `NAME=VALUE` with units, checked
//!   against Rev D, the BMS's own limits and the relations between settings.
//! * [`profile`] — settings profiles (`name = value` lines) and their messages.
//! * [`view`] — the live picture's words: freshness (by the firmware's rule)
//!   and link quality.

pub mod config;
pub mod profile;
pub mod settings;
pub mod view;
pub mod words;
