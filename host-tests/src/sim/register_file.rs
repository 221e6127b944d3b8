//! Initial register file of each [`PackModel`]: settings, statistics,
//! version block with a serial number, event history.

use super::config::{CurrentSensor, PackModel};
use super::rng::Rng;
use super::settings;
use protocol_core::events::EventId;

/// Registers 0..=599 (Rev D chapter 3; 510-599 reserved).
pub const REGISTER_COUNT: usize = 600;

/// BMS lifetime counter at start, s (registers 32-33; also the event clock).
pub(crate) const fn initial_lifetime_s(model: PackModel) -> u32 {
    match model {
        PackModel::LiFePO4_16S => 3_877_000,
        PackModel::LiIon_14S => 9_876_543,
    }
}

/// Registers the live model does not own, for `model`. The live model then
/// writes 0-55 on top.
pub(crate) fn initial_registers(
    model: PackModel,
    sensor: CurrentSensor,
    lifetime_s: u32,
    rng: &mut Rng,
) -> [u16; REGISTER_COUNT] {
    let mut r = [0u16; REGISTER_COUNT];
    let lfp = model == PackModel::LiFePO4_16S;
    let mut set = |a: u16, v: u16| {
        if let Some(x) = r.get_mut(usize::from(a)) {
            *x = v;
        }
    };
    // Settings (Rev D §3.4), clamped into the fitted sensor's limits.
    for (a, v) in settings::model_values(model) {
        set(a, settings::clamp_to_sensor(a, v, sensor));
    }
    // SOH, 0.002 % (Rev D §3.1 register 45).
    set(45, if lfp { 48_500 } else { 46_000 });
    // Statistics (Rev D §3.2).
    set(100, if lfp { 0 } else { 0x2F1C });
    set(101, 0);
    set(102, if lfp { 480 } else { 455 });
    set(103, if lfp { 240 } else { 180 });
    set(104, if lfp { 214 } else { 388 });
    set(105, 1);
    set(106, if lfp { 0 } else { 2 });
    set(107, 0);
    set(108, 0);
    set(109, 0);
    set(111, if lfp { 143 } else { 412 });
    set(112, if lfp { 97 } else { 388 });
    set(113, u16::from_le_bytes([8, 38]));
    // Last reset: POR/PDR (0x05); last wake-up: charger connected (0x00).
    set(114, 0x0005);
    let cleared = lifetime_s.saturating_sub(2_000_000);
    set(116, cleared as u16);
    set(117, (cleared >> 16) as u16);
    // Version (Rev D §3.5): HW 1.0, FW 20 / internal 58, bootloader 2, model 5;
    // 501 high byte: BPT (bit 0) = low power, BCS (bits 1-2) = the sensor.
    set(500, 0x0001);
    set(501, 0x14 | ((sensor.bcs() << 1) << 8));
    set(502, 58);
    set(503, 0x0502);
    for a in 504..=509 {
        set(a, rng.next_u64() as u16);
    }
    r
}

/// Event history at start, oldest first, as (seconds before now, event).
pub(crate) const HISTORY: &[(u32, EventId)] = &[
    (1_500_000, EventId::SystemStarted),
    (180_000, EventId::ChargerConnected),
    (179_990, EventId::ChargingStarted),
    (150_000, EventId::ChargingDone),
    (149_990, EventId::ChargerDisconnected),
    (86_400, EventId::SystemStarted),
    (7_200, EventId::ChargerConnected),
    (7_190, EventId::ChargingStarted),
    (3_600, EventId::ChargingDone),
    (3_590, EventId::ChargerDisconnected),
];
