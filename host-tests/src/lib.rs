//! Host-side test infrastructure for the TinyBMS firmware: the capture format and
//! its replay, the simulated TinyBMS, and the virtual-time harness that runs the
//! firmware's bridge logic against it.

pub mod capture;
pub mod closed_loop;
pub mod flash;
pub mod mqtt;
pub mod mqtt_e2e;
pub mod multi_pack;
pub mod packs_mqtt;
pub mod profile;
#[cfg(unix)]
pub mod pty;
#[cfg(not(unix))]
#[path = "pty_unsupported.rs"]
pub mod pty;
pub mod real_time;
pub mod real_time_station;
pub mod replay;
pub mod sim;
pub mod sim_can;
pub mod sim_wifi;
pub mod tool;
pub mod trace;
pub mod truth;
pub mod virtual_host_link;
pub mod virtual_host_port;
pub mod virtual_time;
pub mod words;

impl pty::Pty {
    /// Opens a new pair and writes its path to `out` as a first line (flushed):
    /// how `sim --pty` and `sim --bridge-pty` tell a client where to connect.
    /// (Here, not in `pty.rs`: the same on every system.)
    pub fn open_announced(out: &mut dyn std::io::Write) -> std::io::Result<Self> {
        let pty = Self::open()?;
        writeln!(out, "{}", pty.path().display())?;
        out.flush()?;
        Ok(pty)
    }
}
