//! TinyBMS firmware library (placeholder — owned by the bridge-logic author).
#![no_std]

/// Crate version string (placeholder public item).
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
