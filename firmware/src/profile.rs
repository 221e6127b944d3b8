//! The settings profile the firmware applies at start-up — the one place to
//! change what this device writes to the BMS — and the profile text format it is
//! written in, shared with `sim --profile` and the desktop tool.
//!
//! **Empty by default: out of the box the firmware never writes to the BMS.**
//!
//! The profile is the text file `firmware/profile.txt`, compiled in
//! ([`PROFILE_TEXT`]) and parsed at start-up. A line that does not parse stops
//! the whole profile (the chip logs the line number and writes nothing).
//!
//! ## Format
//!
//! ```text
//! # comment (from `#` to the end of the line); blank lines are ignored
//! over_voltage_cutoff = 3650     # snake_case of the setting, or
//! Under-Voltage Cutoff = 2700    # Rev D's name (any case), or
//! 316 = 2700                     # the register address (whole-register and low-byte settings)
//! ```
//!
//! Values are integers in raw register units (mV, A, s, 0.01 Ah, enumeration
//! values), as in Rev D §3.4. At start-up every entry goes through the
//! write/verify machine: validated against Rev D's range and the BMS's own
//! min/max, read, skipped when already equal, written, read back and compared;
//! each outcome is logged.
//!
//! The setting names (the snake_case [`setting_key`] and the lookup
//! [`find_setting`]) live here and nowhere else: the host link and the host
//! tools use them too.

use protocol_core::registers::Field;
use protocol_core::settings::SettingId;

/// The start-up profile: the text of `firmware/profile.txt`.
pub const PROFILE_TEXT: &str = include_str!("../profile.txt");

/// Most assignments a profile can hold: what the bridge's command queue takes
/// ([`crate::config::COMMAND_QUEUE`] groups of
/// [`crate::config::MAX_SETTINGS_GROUP`]).
pub const MAX_PROFILE_ENTRIES: usize =
    crate::config::COMMAND_QUEUE * crate::config::MAX_SETTINGS_GROUP;

/// snake_case name of a setting: its `SettingId` variant (`OverVoltageCutoff` →
/// `over_voltage_cutoff`). A host test checks every entry against the variant name.
pub const fn setting_key(id: SettingId) -> &'static str {
    match id {
        SettingId::FullyChargedVoltage => "fully_charged_voltage",
        SettingId::FullyDischargedVoltage => "fully_discharged_voltage",
        SettingId::EarlyBalancingThreshold => "early_balancing_threshold",
        SettingId::ChargeFinishedCurrent => "charge_finished_current",
        SettingId::PeakDischargeCurrentCutoff => "peak_discharge_current_cutoff",
        SettingId::BatteryCapacity => "battery_capacity",
        SettingId::NumberOfSeriesCells => "number_of_series_cells",
        SettingId::AllowedDisbalance => "allowed_disbalance",
        SettingId::ChargerStartupDelay => "charger_startup_delay",
        SettingId::ChargerDisableDelay => "charger_disable_delay",
        SettingId::PulsesPerUnit => "pulses_per_unit",
        SettingId::DistanceUnit => "distance_unit",
        SettingId::OverVoltageCutoff => "over_voltage_cutoff",
        SettingId::UnderVoltageCutoff => "under_voltage_cutoff",
        SettingId::DischargeOverCurrentCutoff => "discharge_over_current_cutoff",
        SettingId::ChargeOverCurrentCutoff => "charge_over_current_cutoff",
        SettingId::OverHeatCutoff => "over_heat_cutoff",
        SettingId::LowTemperatureChargerCutoff => "low_temperature_charger_cutoff",
        SettingId::ChargeRestartLevel => "charge_restart_level",
        SettingId::BatteryMaximumCycles => "battery_maximum_cycles",
        SettingId::StateOfHealth => "state_of_health",
        SettingId::StateOfCharge => "state_of_charge",
        SettingId::ConfigurationFlags => "configuration_flags",
        SettingId::ChargerType => "charger_type",
        SettingId::DischargeOverCurrentTimeout => "discharge_over_current_timeout",
        SettingId::LoadSwitchType => "load_switch_type",
        SettingId::AutomaticRecovery => "automatic_recovery",
        SettingId::ChargerSwitchType => "charger_switch_type",
        SettingId::Ignition => "ignition",
        SettingId::ChargerDetection => "charger_detection",
        SettingId::SpeedSensorInput => "speed_sensor_input",
        SettingId::PrechargePin => "precharge_pin",
        SettingId::PrechargeDuration => "precharge_duration",
        SettingId::TemperatureSensorType => "temperature_sensor_type",
        SettingId::OperationMode => "operation_mode",
        SettingId::SinglePortSwitchType => "single_port_switch_type",
        SettingId::BroadcastTime => "broadcast_time",
        SettingId::Protocol => "protocol",
    }
}

/// Finds a setting by snake_case name or Rev D name (both case-insensitive, spaces
/// around ignored) or register address (whole-register and low-byte settings).
pub fn find_setting(name: &str) -> Option<SettingId> {
    let n = name.trim();
    if let Ok(addr) = n.parse::<u16>() {
        return SettingId::from_address(addr, Field::Whole)
            .or_else(|| SettingId::from_address(addr, Field::LowByte));
    }
    SettingId::ALL
        .iter()
        .copied()
        .find(|id| setting_key(*id).eq_ignore_ascii_case(n) || id.name().eq_ignore_ascii_case(n))
}

/// Why a profile line was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ProfileErrorKind {
    /// No `=` in the line.
    ExpectedAssignment,
    /// No setting by that name or address.
    UnknownSetting,
    /// The value is not an integer that fits in 32 bits.
    BadValue,
}

impl ProfileErrorKind {
    /// Short snake_case reason.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::ExpectedAssignment => "expected NAME = VALUE",
            Self::UnknownSetting => "no such setting",
            Self::BadValue => "not an integer",
        }
    }
}

/// A profile line that does not parse, with the evidence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProfileError<'a> {
    /// 1-based line number (1 for [`parse_assignment`]).
    pub line: u32,
    /// What is wrong.
    pub kind: ProfileErrorKind,
    /// The offending text: the whole assignment, the name or the value.
    pub text: &'a str,
}

/// Parses one `NAME = VALUE` assignment (no comment).
pub fn parse_assignment(s: &str) -> Result<(SettingId, i32), ProfileError<'_>> {
    let err = |kind, text| ProfileError {
        line: 1,
        kind,
        text,
    };
    let (name, value) = s
        .split_once('=')
        .ok_or(err(ProfileErrorKind::ExpectedAssignment, s.trim()))?;
    let id = find_setting(name).ok_or(err(ProfileErrorKind::UnknownSetting, name.trim()))?;
    let value = value
        .trim()
        .parse::<i32>()
        .map_err(|_| err(ProfileErrorKind::BadValue, value.trim()))?;
    Ok((id, value))
}

/// The assignments of a profile text, in order, each with its line number in
/// the error. Comments and blank lines are skipped.
#[derive(Debug, Clone)]
pub struct Entries<'a> {
    lines: core::str::Lines<'a>,
    line: u32,
}

/// Iterates over the assignments of a profile text.
pub fn entries(text: &str) -> Entries<'_> {
    Entries {
        lines: text.lines(),
        line: 0,
    }
}

impl<'a> Iterator for Entries<'a> {
    type Item = Result<(SettingId, i32), ProfileError<'a>>;

    fn next(&mut self) -> Option<Self::Item> {
        for raw in self.lines.by_ref() {
            self.line = self.line.saturating_add(1);
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            return Some(parse_assignment(line).map_err(|e| ProfileError {
                line: self.line,
                ..e
            }));
        }
        None
    }
}

/// Why a whole profile was refused by [`parse`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParseError<'a> {
    /// A line does not parse.
    Line(ProfileError<'a>),
    /// More than `N` assignments (the line of the first one too many).
    TooMany {
        /// Line number.
        line: u32,
    },
}

/// Parses a whole profile: every assignment, or the first error (then nothing
/// is to be written).
pub fn parse<const N: usize>(
    text: &str,
) -> Result<heapless::Vec<(SettingId, i32), N>, ParseError<'_>> {
    let mut out = heapless::Vec::new();
    let mut it = entries(text);
    while let Some(entry) = it.next() {
        let entry = entry.map_err(ParseError::Line)?;
        if out.push(entry).is_err() {
            return Err(ParseError::TooMany { line: it.line });
        }
    }
    Ok(out)
}
