//! Settings profiles for the simulator command: `name = value` lines.
//!
//! ```text
//! # comment
//! over_voltage_cutoff = 3650     # snake_case of the setting, or
//! Under-Voltage Cutoff = 2700    # Rev D's name, or
//! 316 = 2700                     # the register address (whole-register settings)
//! ```
//! Values are raw register units (mV, A, s, enumeration values), as in Rev D §3.4.

use protocol_core::registers::Field;
use protocol_core::settings::SettingId;

/// snake_case name of a setting (`OverVoltageCutoff` → `over_voltage_cutoff`).
pub fn snake_name(id: SettingId) -> String {
    let debug = format!("{id:?}");
    let mut out = String::new();
    for (i, c) in debug.chars().enumerate() {
        if c.is_ascii_uppercase() {
            if i > 0 {
                out.push('_');
            }
            out.push(c.to_ascii_lowercase());
        } else {
            out.push(c);
        }
    }
    out
}

/// Finds a setting by snake_case name, Rev D name (case-insensitive) or address.
pub fn find_setting(name: &str) -> Option<SettingId> {
    let n = name.trim();
    if let Ok(addr) = n.parse::<u16>() {
        return SettingId::from_address(addr, Field::Whole)
            .or_else(|| SettingId::from_address(addr, Field::LowByte));
    }
    SettingId::ALL
        .iter()
        .copied()
        .find(|id| snake_name(*id) == n.to_ascii_lowercase() || id.name().eq_ignore_ascii_case(n))
}

/// Parses one `name=value` assignment.
pub fn parse_assignment(s: &str) -> Result<(SettingId, i32), String> {
    let (name, value) = s
        .split_once('=')
        .ok_or_else(|| format!("`{s}`: expected NAME=VALUE"))?;
    let id = find_setting(name).ok_or_else(|| format!("`{}`: no such setting", name.trim()))?;
    let value = value
        .trim()
        .parse::<i32>()
        .map_err(|e| format!("`{}`: {e}", value.trim()))?;
    Ok((id, value))
}

/// Parses a profile file.
pub fn parse_profile(text: &str) -> Result<Vec<(SettingId, i32)>, String> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        out.push(parse_assignment(line).map_err(|e| format!("line {}: {e}", i + 1))?);
    }
    Ok(out)
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
}
