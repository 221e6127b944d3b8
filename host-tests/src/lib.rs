//! Host-side test infrastructure for the TinyBMS firmware: the capture format and
//! its replay, the simulated TinyBMS, and the virtual-time harness that runs the
//! firmware's bridge logic against it.

pub mod capture;
pub mod closed_loop;
pub mod harness;
pub mod host_link;
pub mod hosted;
pub mod profile;
#[cfg(unix)]
pub mod pty;
#[cfg(not(unix))]
#[path = "pty_unsupported.rs"]
pub mod pty;
pub mod realtime;
pub mod replay;
pub mod sim;
pub mod tool;
pub mod trace;
pub mod truth;
