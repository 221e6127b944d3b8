//! What this installation wants from the inverter output: edit and reflash.
//! (The settings written to the BMS are in [`crate::profile`].)

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
