//! What this installation wants from the inverter output and the host link:
//! edit and reflash. (The settings written to the BMS are in `firmware/profile.txt`,
//! see [`crate::bms::profile`].)

use crate::host_link::HostLinkConfig;
use crate::inverter::control::ChargeConfig;
use crate::inverter::{InverterConfig, Protocol, StalePolicy};

/// CAN output on (`false`: the bridge only reads the BMS; no frame is sent).
pub const CAN_OUTPUT: bool = true;

/// The inverter protocol: [`Protocol::Victron`] (a GX on VE.Can, "CAN-bus BMS
/// 500 kbit/s") or [`Protocol::SmaSunnyIsland`].
pub const PROTOCOL: Protocol = Protocol::Victron;

/// What happens when the telemetry goes stale: stop sending (the inverter stops
/// charging and discharging), or [`StalePolicy::HoldChargeZero`] for a bounded
/// time (CCL 0, discharge allowed).
pub const STALE_POLICY: StalePolicy = StalePolicy::StopSending;

/// The inverter output's configuration: the constants above, charge control's
/// documented defaults (see [`ChargeConfig`]).
pub fn inverter_config() -> InverterConfig {
    InverterConfig {
        enabled: CAN_OUTPUT,
        protocol: PROTOCOL,
        stale_policy: STALE_POLICY,
        charge: ChargeConfig::default(),
        ..InverterConfig::default()
    }
}

/// Host link (JSON Lines over the USB cable, `firmware/src/host_link/PROTOCOL.md`):
/// `true` refuses `set`, `reset` and `clear` from the computer (a read-only
/// bridge); reading, streaming and capture still work.
pub const HOST_READ_ONLY: bool = false;

/// Host link: telemetry stream period at start, ms (0: off; else 100-60000). The
/// host can change it (`stream`) until the next restart.
pub const HOST_STREAM_PERIOD_MS: u32 = crate::host_link::DEFAULT_STREAM_PERIOD_MS;

/// The host link's configuration: the constants above, this firmware's version
/// and the chip's name.
pub fn host_link_config(chip: &'static str) -> HostLinkConfig {
    HostLinkConfig {
        read_only: HOST_READ_ONLY,
        stream_period_ms: HOST_STREAM_PERIOD_MS,
        firmware: env!("CARGO_PKG_VERSION"),
        chip,
    }
}
