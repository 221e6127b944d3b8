//! `settings`, `apply`, `set`: the settings table, the profile writer (the
//! text format `host_tests::profile` reads), the difference before an apply,
//! and the `NAME=VALUE` arguments of `set`.

use protocol_core::registers::option_name;
use protocol_core::settings::SettingId;
use serde_json::Value;
use tinybms_firmware::units;

use crate::profile::{find_setting, snake_name};

/// A number as short as it is exact: `3.65`, `60`, `-20`.
pub fn short(x: f64) -> String {
    let s = format!("{x:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".into()
    } else {
        s.to_string()
    }
}

/// The physical value of `raw` for `id`: `3.65 V`, `60 A`, or the enumerated
/// value's name.
pub fn physical(id: SettingId, raw: i64) -> String {
    match id.register() {
        Some(r) => {
            if let Some(name) = u16::try_from(raw).ok().and_then(|v| option_name(r, v)) {
                if !r.options.is_empty() {
                    return format!("{name} ({raw})");
                }
            }
            // The bridge's own conversion (exact fixed point, as the protocol
            // prints it).
            let Some(v) = i32::try_from(raw)
                .ok()
                .and_then(|raw| units::physical(id, raw))
                .map(units::Dec::as_f64)
            else {
                return raw.to_string();
            };
            if r.unit.is_empty() {
                short(v)
            } else {
                format!("{} {}", short(v), r.unit)
            }
        }
        None => raw.to_string(),
    }
}

fn range(min: &Value, max: &Value, unit: &str) -> String {
    match (min.as_f64(), max.as_f64()) {
        (Some(a), Some(b)) => format!("{}..{} {unit}", short(a), short(b)),
        _ => "-".into(),
    }
}

/// The `settings` table, one row per `setting` line.
pub fn render_table(lines: &[Value]) -> String {
    let mut rows = vec![[
        "name".to_string(),
        "value".to_string(),
        "raw".to_string(),
        "Rev D range".to_string(),
        "BMS min..max".to_string(),
    ]];
    for l in lines.iter().filter(|l| l["type"] == "setting") {
        let unit = l["unit"].as_str().unwrap_or("");
        let value = match l["value"].as_f64() {
            Some(v) if unit.is_empty() => short(v),
            Some(v) => format!("{} {unit}", short(v)),
            None => "-".into(),
        };
        // Not read (`raw` null): no value, whatever the setting.
        let raw = l["raw"].as_i64();
        let value = match (find_setting(l["name"].as_str().unwrap_or("")), raw) {
            (Some(id), Some(0xFFFF)) if id.reads_back_marker() => {
                "- (write-only: reads 0xFFFF)".to_string()
            }
            (Some(id), Some(raw)) if id.register().is_some_and(|r| !r.options.is_empty()) => {
                physical(id, raw)
            }
            _ => value,
        };
        rows.push([
            l["name"].as_str().unwrap_or("?").to_string(),
            value,
            l["raw"].to_string(),
            range(&l["min"], &l["max"], unit),
            range(&l["bms_min"], &l["bms_max"], unit),
        ]);
    }
    let mut widths = [0usize; 5];
    for r in &rows {
        for (w, c) in widths.iter_mut().zip(r.iter()) {
            *w = (*w).max(c.chars().count());
        }
    }
    let mut out = String::new();
    for r in &rows {
        let mut line = String::new();
        for (k, (w, c)) in widths.iter().zip(r.iter()).enumerate() {
            let pad = w.saturating_sub(c.chars().count());
            if k == 2 {
                line.push_str(&" ".repeat(pad));
                line.push_str(c);
            } else {
                line.push_str(c);
                line.push_str(&" ".repeat(pad));
            }
            line.push_str("  ");
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    out
}

/// A profile of the settings read (`name = raw  # physical`), readable by
/// `host_tests::profile::parse_profile` (and so by `apply` and `sim --profile`).
/// Settings that read back a marker instead of their value are left as
/// comments.
pub fn profile_text(lines: &[Value], header: &str) -> String {
    let mut out = String::new();
    for l in header.lines() {
        out.push_str(&format!("# {l}\n"));
    }
    out.push_str(
        "# One setting per line: `name = value` in raw register units (Rev D §3.4);\n\
         # the comment gives the physical value. `tinybms apply PORT FILE` writes it back.\n\n",
    );
    for l in lines.iter().filter(|l| l["type"] == "setting") {
        let name = l["name"].as_str().unwrap_or("?");
        let Some(raw) = l["raw"].as_i64() else {
            continue;
        };
        match find_setting(name) {
            Some(id) if id.reads_back_marker() => out.push_str(&format!(
                "# {name} = {raw}  # not saved: this register reads back a marker, not its value\n"
            )),
            Some(id) => out.push_str(&format!("{name} = {raw}  # {}\n", physical(id, raw))),
            None => out.push_str(&format!("# {name} = {raw}  # unknown to this tool\n")),
        }
    }
    out
}

/// One setting an apply would change.
#[derive(Debug, Clone, PartialEq)]
pub struct Change {
    /// The setting.
    pub id: SettingId,
    /// Raw value now (None: not in the bridge's list).
    pub from: Option<i64>,
    /// Raw value wanted.
    pub to: i64,
}

/// The settings of `wanted` whose value differs from the bridge's `current`
/// lines (later duplicates in the profile win).
pub fn diff(current: &[Value], wanted: &[(SettingId, i32)]) -> Vec<Change> {
    let mut out: Vec<Change> = Vec::new();
    for &(id, to) in wanted {
        let name = snake_name(id);
        let from = current
            .iter()
            .find(|l| l["type"] == "setting" && l["name"] == name.as_str())
            .and_then(|l| l["raw"].as_i64());
        out.retain(|c| c.id != id);
        if from != Some(i64::from(to)) {
            out.push(Change {
                id,
                from,
                to: i64::from(to),
            });
        }
    }
    out
}

/// The difference as text.
pub fn render_diff(changes: &[Change], unchanged: usize) -> String {
    let mut out = String::new();
    for c in changes {
        let from = c
            .from
            .map_or("?".to_string(), |r| format!("{r} ({})", physical(c.id, r)));
        out.push_str(&format!(
            "  {:<36} {from} -> {} ({})\n",
            snake_name(c.id),
            c.to,
            physical(c.id, c.to)
        ));
    }
    out.push_str(&format!(
        "{} to change, {unchanged} already equal\n",
        changes.len()
    ));
    out
}

/// Parses one `set` argument. With `raw`, `NAME=INTEGER` in register units;
/// otherwise `NAME=NUMBER[UNIT]` in the unit `settings` prints for it (the unit
/// suffix is optional and must be that unit, e.g. `over_voltage_cutoff=3.65V`).
/// Returns the snake_case name and the number.
pub fn parse_set_arg(arg: &str, raw: bool) -> Result<(String, f64), String> {
    let (name, value) = arg
        .split_once('=')
        .ok_or_else(|| format!("`{arg}`: expected NAME=VALUE"))?;
    let id = find_setting(name).ok_or_else(|| {
        format!(
            "`{}`: no such setting (`tinybms settings PORT` lists them)",
            name.trim()
        )
    })?;
    let value = value.trim();
    if raw {
        let v: i64 = value
            .parse()
            .map_err(|_| format!("`{value}`: --raw values are integers in register units"))?;
        return Ok((snake_name(id), v as f64));
    }
    let unit = id.register().map_or("", |r| r.unit);
    let end = value
        .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-' || c == '+' || c == 'e'))
        .unwrap_or(value.len());
    let (number, suffix) = value.split_at(end);
    let suffix = suffix.trim();
    if !suffix.is_empty() && suffix != unit && !(unit == "°C" && suffix == "C") {
        return Err(format!(
            "`{value}`: {} is set in {} (e.g. `{}=12{}`), or give --raw register units",
            snake_name(id),
            if unit.is_empty() {
                "plain numbers".to_string()
            } else {
                format!("`{unit}`")
            },
            snake_name(id),
            unit
        ));
    }
    let v: f64 = number
        .parse()
        .map_err(|_| format!("`{value}` is not a number"))?;
    Ok((snake_name(id), v))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn line(name: &str, raw: i64, value: f64, unit: &str) -> Value {
        json!({"type":"setting","name":name,"raw":raw,"value":value,"unit":unit,
               "min":1.2,"max":4.5,"bms_min":null,"bms_max":null})
    }

    #[test]
    fn profile_round_trips_through_the_parser() {
        let lines = vec![
            line("over_voltage_cutoff", 3650, 3.65, "V"),
            line("under_voltage_cutoff", 2700, 2.7, "V"),
        ];
        let text = profile_text(&lines, "saved by a test");
        assert!(
            text.contains("over_voltage_cutoff = 3650  # 3.65 V"),
            "{text}"
        );
        let p = crate::profile::parse_profile(&text).unwrap();
        assert_eq!(
            p,
            vec![
                (SettingId::OverVoltageCutoff, 3650),
                (SettingId::UnderVoltageCutoff, 2700)
            ]
        );
        let d = diff(
            &lines,
            &[
                (SettingId::OverVoltageCutoff, 3600),
                (SettingId::UnderVoltageCutoff, 2700),
            ],
        );
        assert_eq!(
            d,
            vec![Change {
                id: SettingId::OverVoltageCutoff,
                from: Some(3650),
                to: 3600
            }]
        );
        let table = render_table(&lines);
        assert!(table.contains("3.65 V"), "{table}");
    }

    /// A setting the bridge could not read (`raw` null) shows no value, also
    /// when it is an enumeration (it showed option 0's name, as if read).
    #[test]
    fn unread_setting_shows_no_value() {
        for name in ["charger_type", "over_voltage_cutoff", "configuration_flags"] {
            let lines = vec![json!({"type":"setting","name":name,"raw":null,"value":null,
                "unit":"","min":0.0,"max":2.0,"bms_min":null,"bms_max":null})];
            let table = render_table(&lines);
            let row = table.lines().nth(1).unwrap();
            let cols: Vec<&str> = row
                .split("  ")
                .map(str::trim)
                .filter(|c| !c.is_empty())
                .collect();
            assert_eq!(cols[..3], [name, "-", "null"], "{table}");
        }
    }

    #[test]
    fn set_arguments() {
        assert_eq!(
            parse_set_arg("over_voltage_cutoff=3.6V", false).unwrap(),
            ("over_voltage_cutoff".into(), 3.6)
        );
        assert_eq!(
            parse_set_arg("Over-Voltage Cutoff=3.6", false).unwrap(),
            ("over_voltage_cutoff".into(), 3.6)
        );
        assert!(parse_set_arg("over_voltage_cutoff=3600mV", false)
            .unwrap_err()
            .contains("`V`"));
        assert_eq!(
            parse_set_arg("over_voltage_cutoff=3600", true).unwrap().1,
            3600.0
        );
        assert!(parse_set_arg("nope=1", false)
            .unwrap_err()
            .contains("no such"));
        assert!(parse_set_arg("x", false).is_err());
    }

    #[test]
    fn utc_formatting() {
        assert_eq!(super::super::monitor::utc(0, 0), "1970-01-01T00:00:00.000Z");
        assert_eq!(
            super::super::monitor::utc(1_709_251_199, 5),
            "2024-02-29T23:59:59.005Z"
        );
    }
}
