//! The settings profile the firmware applies at start-up — the one place to
//! change what this device writes to the BMS.
//!
//! **Empty by default: out of the box the firmware never writes to the BMS.**
//!
//! Each entry is a setting and its value in raw register units (mV, A, s, or the
//! enumerated value of Rev D §3.4). At start-up every entry goes through the
//! write/verify machine: validated against Rev D's range and the BMS's own
//! min/max, read, skipped when already equal, written, read back and compared;
//! each outcome is logged. Example for a 16S LiFePO4 pack (uncomment to use):
//!
//! ```
//! use protocol_core::settings::SettingId;
//! pub const PROFILE: &[(SettingId, i32)] = &[
//!     (SettingId::FullyChargedVoltage, 3550),   // mV
//!     (SettingId::OverVoltageCutoff, 3650),     // mV
//!     (SettingId::UnderVoltageCutoff, 2700),    // mV
//!     (SettingId::ChargeOverCurrentCutoff, 60), // A
//! ];
//! ```

use protocol_core::settings::SettingId;

/// The start-up profile. Empty: nothing is written.
pub const PROFILE: &[(SettingId, i32)] = &[];
