//! Settings profiles for the simulator command: `name = value` lines.
//!
//! ```text
//! # comment
//! over_voltage_cutoff = 3650     # snake_case of the setting, or
//! Under-Voltage Cutoff = 2700    # Rev D's name, or
//! 316 = 2700                     # the register address (whole-register settings)
//! ```
//! Values are raw register units (mV, A, s, enumeration values), as in Rev D §3.4.
//!
//! The parser is the firmware's own (`tinybms_firmware::profile`, no_std): the
//! firmware's start-up profile `firmware/profile.txt`, `sim --profile` and the
//! desktop tool read the same format with the same code. These wrappers turn its
//! errors into messages.

use protocol_core::settings::SettingId;
use tinybms_firmware::profile::{self as fw, ProfileError};

/// snake_case name of a setting (`OverVoltageCutoff` → `over_voltage_cutoff`).
pub fn snake_name(id: SettingId) -> String {
    fw::setting_key(id).to_string()
}

/// Finds a setting by snake_case name, Rev D name (case-insensitive) or address.
pub fn find_setting(name: &str) -> Option<SettingId> {
    fw::find_setting(name)
}

fn message(e: &ProfileError<'_>) -> String {
    match e.kind {
        fw::ProfileErrorKind::ExpectedAssignment => format!("`{}`: expected NAME=VALUE", e.text),
        fw::ProfileErrorKind::UnknownSetting => format!("`{}`: no such setting", e.text),
        fw::ProfileErrorKind::BadValue => format!("`{}`: not an integer (i32)", e.text),
    }
}

/// Parses one `name=value` assignment.
pub fn parse_assignment(s: &str) -> Result<(SettingId, i32), String> {
    fw::parse_assignment(s).map_err(|e| message(&e))
}

/// Parses a profile file.
pub fn parse_profile(text: &str) -> Result<Vec<(SettingId, i32)>, String> {
    fw::entries(text)
        .map(|e| e.map_err(|e| format!("line {}: {}", e.line, message(&e))))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_files() {
        assert_eq!(
            snake_name(SettingId::OverVoltageCutoff),
            "over_voltage_cutoff"
        );
        assert_eq!(
            find_setting("over_voltage_cutoff"),
            Some(SettingId::OverVoltageCutoff)
        );
        assert_eq!(
            find_setting("Under-Voltage Cutoff"),
            Some(SettingId::UnderVoltageCutoff)
        );
        assert_eq!(find_setting("342"), Some(SettingId::BroadcastTime));
        assert_eq!(find_setting("nope"), None);
        let p = parse_profile("# x\nover_voltage_cutoff = 3650 # mV\n\n316=2700\n").unwrap();
        assert_eq!(
            p,
            vec![
                (SettingId::OverVoltageCutoff, 3650),
                (SettingId::UnderVoltageCutoff, 2700)
            ]
        );
        assert!(parse_profile("a = b").unwrap_err().starts_with("line 1"));
        assert!(parse_assignment("over_voltage_cutoff=x").is_err());
    }

    #[test]
    fn keys_are_the_variant_names_in_snake_case() {
        for &id in SettingId::ALL {
            let debug = format!("{id:?}");
            let mut want = String::new();
            for (i, c) in debug.chars().enumerate() {
                if c.is_ascii_uppercase() {
                    if i > 0 {
                        want.push('_');
                    }
                    want.push(c.to_ascii_lowercase());
                } else {
                    want.push(c);
                }
            }
            assert_eq!(snake_name(id), want);
            assert_eq!(find_setting(&want), Some(id));
            assert_eq!(find_setting(id.name()), Some(id));
        }
    }

    #[test]
    fn the_firmware_profile_parses() {
        let text = tinybms_firmware::profile::PROFILE_TEXT;
        let entries = parse_profile(text).unwrap();
        // Shipped empty: out of the box the firmware never writes to the BMS.
        assert!(entries.is_empty(), "{entries:?}");
        assert!(tinybms_firmware::profile::parse::<
            { tinybms_firmware::profile::MAX_PROFILE_ENTRIES },
        >(text)
        .unwrap()
        .is_empty());
        // The commented example in it parses once uncommented.
        let example: String = text
            .lines()
            .filter_map(|l| l.strip_prefix("# "))
            .filter(|l| l.contains(" = ") && !l.contains('`'))
            .map(|l| format!("{l}\n"))
            .collect();
        assert_eq!(parse_profile(&example).unwrap().len(), 4, "{example}");
    }
}
