//! The firmware's station on the desktop, in real time: what the ESP32 runs,
//! with a serial port (or any [`BytePort`]) for its UART, a RAM or file flash
//! for its configuration store, and a host side for its host link.
//!
//! Shared by the desktop tool `tinybms` (its direct mode: a TinyBMS on a
//! USB-UART adapter) and the simulator `sim` (`--bridge-pty`, `--mqtt`), which
//! gives it a simulated BMS, CAN bus and Wi-Fi through the same traits. Nothing
//! here simulates anything.

use std::time::Duration;

pub mod capture;
pub mod driver;
pub mod flash;
pub mod ota;
pub mod station;
pub mod update_port;

pub use driver::{BytePort, CanSide, Clock, Driver, Happened, WifiSide};
pub use station::{ChannelSide, HostSide, Hosted, NoHost};

/// Longest the loops sleep without looking at their other inputs (a stop flag,
/// the host side), so they stay responsive without spinning.
pub const MAX_SLICE: Duration = Duration::from_millis(10);

/// Parses a duration: `250ms`, `10s`, `1.5m`, `2h`, `500us`; a bare number is
/// seconds.
pub fn parse_duration(s: &str) -> Result<Duration, String> {
    let (num, unit) = s
        .find(|c: char| !c.is_ascii_digit() && c != '.')
        .map(|i| s.split_at(i))
        .unwrap_or((s, "s"));
    let v: f64 = num.parse().map_err(|_| format!("bad duration `{s}`"))?;
    let scale = match unit {
        "us" => 1e-6,
        "ms" => 1e-3,
        "s" | "" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        _ => return Err(format!("bad duration unit in `{s}` (us, ms, s, m, h)")),
    };
    if !(v * scale).is_finite() || v * scale < 0.0 {
        return Err(format!("bad duration `{s}`"));
    }
    Ok(Duration::from_secs_f64(v * scale))
}

/// A program whose output goes into a pipe that closes first (`tinybms
/// settings PORT | head`) ends quietly, as `cat` does, instead of panicking
/// on its next `println!`: the default action of SIGPIPE, which Rust's
/// runtime sets to ignored. Called first by the desktop programs' `main`.
pub fn end_quietly_on_a_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: sets a signal's disposition to the system default, at the start
    // of `main`, before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations() {
        assert_eq!(parse_duration("250ms").unwrap(), Duration::from_millis(250));
        assert_eq!(parse_duration("10").unwrap(), Duration::from_secs(10));
        assert_eq!(parse_duration("1.5m").unwrap(), Duration::from_secs(90));
        assert!(parse_duration("5 parsecs").is_err());
        assert!(parse_duration("-1s").is_err());
    }
}
