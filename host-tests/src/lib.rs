//! The TinyBMS firmware's test bench on the desktop: the simulated TinyBMS
//! (with its faults and its ground truth), the virtual-time harness that runs
//! the firmware's station against it, the same in real time on pseudo-terminals
//! (`sim --pty`, `sim --bridge-pty`, `sim --mqtt`), `replay` of captures, and
//! the fixtures the tests share. The desktop tool is its own crate
//! (`host-tests/tool`), and the station on the desktop that the tool and `sim`
//! share is `tinybms-desk` (`host-tests/desk`).

pub mod closed_loop;
pub mod doctor_fixtures;
pub mod fixtures;
pub mod flash;
pub mod harsh;
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
pub mod trace;
pub mod truth;
pub mod virtual_host_link;
pub mod virtual_host_port;
pub mod virtual_time;
pub mod year;

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
