//! `settings`, `apply`, `set`: the settings table, the profile writer (the
//! text format `tinybms_rules::profile` reads), the difference before an apply,
//! and the `NAME=VALUE` arguments of `set`.

use protocol_core::settings::SettingId;
use tinybms_firmware::host_link::schema::{Read, SettingLine};

use tinybms_rules::profile::{find_setting, snake_name};

pub use tinybms_rules::settings::{check_all, parse_set_arg, physical, Chem};
pub use tinybms_rules::words::short;

/// The chemistry `set`/`apply` check against
/// ([`tinybms_rules::settings::chemistry_of`]), said on stdout when a cell
/// voltage is written.
pub fn chemistry_of(
    current: &[SettingLine<Read>],
    items: &[(SettingId, i32)],
    check: protocol_core::settings::ChemistryCheck,
) -> Option<Chem> {
    let (chem, said) = tinybms_rules::settings::chemistry_of(current, items, check);
    if let Some(line) = said {
        println!("{line}");
    }
    chem
}

fn range(min: Option<f64>, max: Option<f64>, unit: &str) -> String {
    match (min, max) {
        (Some(a), Some(b)) => format!("{}..{} {unit}", short(a), short(b)),
        _ => "-".into(),
    }
}

/// The `settings` table, one row per `setting` line.
pub fn render_table(lines: &[SettingLine<Read>]) -> String {
    let mut rows = vec![[
        "name".to_string(),
        "value".to_string(),
        "raw".to_string(),
        "allowed range".to_string(),
        "BMS min..max".to_string(),
    ]];
    for l in lines {
        let unit = l.unit.as_str();
        let value = match l.value {
            Some(v) if unit.is_empty() => short(v),
            Some(v) => format!("{} {unit}", short(v)),
            None => "-".into(),
        };
        // Not read (`raw` null): no value, whatever the setting.
        let raw = l.raw.map(i64::from);
        let value = match (find_setting(&l.name), raw) {
            (Some(id), Some(0xFFFF)) if id.reads_back_marker() => {
                "- (write-only: reads 0xFFFF)".to_string()
            }
            (Some(id), Some(raw)) if id.register().is_some_and(|r| !r.options.is_empty()) => {
                physical(id, raw)
            }
            _ => value,
        };
        rows.push([
            l.name.clone(),
            value,
            // As the line has it: `null` when not read.
            raw.map_or_else(|| "null".to_string(), |r| r.to_string()),
            range(l.min, l.max, unit),
            range(l.bms_min, l.bms_max, unit),
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

/// The groups of settings, as in the BMS's own tool (Battery Insider).
pub const GROUPS: &[(&str, &[SettingId])] = {
    use SettingId::*;
    &[
        (
            "Battery",
            &[
                FullyChargedVoltage,
                FullyDischargedVoltage,
                BatteryCapacity,
                NumberOfSeriesCells,
                BatteryMaximumCycles,
                StateOfHealth,
                StateOfCharge,
            ],
        ),
        (
            "Safety",
            &[
                OverVoltageCutoff,
                UnderVoltageCutoff,
                DischargeOverCurrentCutoff,
                DischargeOverCurrentTimeout,
                PeakDischargeCurrentCutoff,
                ChargeOverCurrentCutoff,
                OverHeatCutoff,
                LowTemperatureChargerCutoff,
                AutomaticRecovery,
            ],
        ),
        ("Balancing", &[EarlyBalancingThreshold, AllowedDisbalance]),
        (
            "Charger",
            &[
                ChargerType,
                ChargerSwitchType,
                ChargerDetection,
                ChargerStartupDelay,
                ChargerDisableDelay,
                ChargeFinishedCurrent,
                ChargeRestartLevel,
                PrechargePin,
                PrechargeDuration,
            ],
        ),
        ("Current sensor and flags", &[ConfigurationFlags]),
        (
            "Peripherals",
            &[
                LoadSwitchType,
                SinglePortSwitchType,
                Ignition,
                SpeedSensorInput,
                PulsesPerUnit,
                DistanceUnit,
                TemperatureSensorType,
            ],
        ),
        (
            "Communication and mode",
            &[BroadcastTime, Protocol, OperationMode],
        ),
    ]
};

/// The `settings` table in [`GROUPS`], one heading per group; a setting in no
/// group (none today: a test checks) comes last under "Other".
pub fn render_groups(lines: &[SettingLine<Read>]) -> String {
    let name_of = |l: &SettingLine<Read>| find_setting(&l.name);
    let mut out = String::new();
    let mut groups: Vec<(&str, Vec<SettingLine<Read>>)> = GROUPS
        .iter()
        .map(|(g, ids)| {
            let rows = ids
                .iter()
                .filter_map(|id| lines.iter().find(|l| name_of(l) == Some(*id)).cloned())
                .collect();
            (*g, rows)
        })
        .collect();
    let other: Vec<SettingLine<Read>> = lines
        .iter()
        .filter(|l| {
            !GROUPS
                .iter()
                .any(|(_, ids)| name_of(l).is_some_and(|id| ids.contains(&id)))
        })
        .cloned()
        .collect();
    groups.push(("Other", other));
    // One width for all groups, so the columns line up down the page.
    let all: Vec<SettingLine<Read>> = groups.iter().flat_map(|(_, r)| r.iter().cloned()).collect();
    let table = render_table(&all);
    let mut rows = table.lines();
    // Indented like the rows under their group headings.
    let header = rows.next().unwrap_or("");
    out.push_str("  ");
    out.push_str(header);
    out.push('\n');
    for (g, r) in &groups {
        if r.is_empty() {
            continue;
        }
        out.push_str(&format!("\n{g}\n"));
        for _ in r {
            if let Some(row) = rows.next() {
                out.push_str("  ");
                out.push_str(row);
                out.push('\n');
            }
        }
    }
    out
}

/// A profile of the settings read (`name = raw  # physical`), readable by
/// `tinybms_rules::profile::parse_profile` (and so by `apply` and `sim --profile`).
/// Settings that read back a marker instead of their value are left as
/// comments.
pub fn profile_text(lines: &[SettingLine<Read>], header: &str) -> (String, usize) {
    let mut saved = 0;
    let mut out = String::new();
    for l in header.lines() {
        out.push_str(&format!("# {l}\n"));
    }
    out.push_str(
        "# One setting per line: `name = value` in raw register units (Rev D §3.4);\n\
         # the comment gives the physical value. `tinybms apply PORT FILE` writes it back.\n\n",
    );
    for l in lines {
        let name = l.name.as_str();
        let Some(raw) = l.raw.map(i64::from) else {
            continue;
        };
        match find_setting(name) {
            Some(id) if id.reads_back_marker() => out.push_str(&format!(
                "# {name} = {raw}  # not saved: this register reads back a marker, not its value\n"
            )),
            Some(id) => {
                saved += 1;
                out.push_str(&format!("{name} = {raw}  # {}\n", physical(id, raw)))
            }
            None => out.push_str(&format!("# {name} = {raw}  # unknown to this tool\n")),
        }
    }
    (out, saved)
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
pub fn diff(current: &[SettingLine<Read>], wanted: &[(SettingId, i32)]) -> Vec<Change> {
    let mut out: Vec<Change> = Vec::new();
    for &(id, to) in wanted {
        let from = tinybms_rules::settings::held(current, id).map(i64::from);
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

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::{json, Value};
    use tinybms_firmware::host_link::schema::HostLine;

    /// A `setting` line as the tool reads it.
    fn setting(v: Value) -> SettingLine<Read> {
        match serde_json::from_value(v).unwrap() {
            HostLine::Setting(s) => s,
            other => panic!("not a setting: {other:?}"),
        }
    }

    /// A `setting` line as the bridge writes it.
    fn line(name: &str, raw: i64, value: f64, unit: &str) -> SettingLine<Read> {
        let address = find_setting(name).unwrap().address();
        setting(
            json!({"type":"setting","name":name,"address":address,"raw":raw,"value":value,
               "unit":unit,"min":1.2,"max":4.5,"bms_min":null,"bms_max":null}),
        )
    }

    #[test]
    fn profile_round_trips_through_the_parser() {
        let lines = vec![
            line("over_voltage_cutoff", 3650, 3.65, "V"),
            line("under_voltage_cutoff", 2700, 2.7, "V"),
        ];
        let (text, saved) = profile_text(&lines, "saved by a test");
        assert_eq!(saved, 2);
        assert!(
            text.contains("over_voltage_cutoff = 3650  # 3.65 V"),
            "{text}"
        );
        let p = tinybms_rules::profile::parse_profile(&text).unwrap();
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
            let address = find_setting(name).unwrap().address();
            let lines = vec![setting(
                json!({"type":"setting","name":name,"address":address,"raw":null,"value":null,
                "unit":"","min":0.0,"max":2.0,"bms_min":null,"bms_max":null}),
            )];
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
        use SettingId::*;
        let ok = |a: &str, raw: bool| parse_set_arg(a, raw).map(|(id, v, _)| (id, v));
        assert_eq!(
            ok("over_voltage_cutoff=3.6V", false),
            Ok((OverVoltageCutoff, 3600))
        );
        assert_eq!(
            ok("over_voltage_cutoff=3.6", false),
            Ok((OverVoltageCutoff, 3600))
        );
        assert_eq!(
            ok("over_voltage_cutoff=3600mV", false),
            Ok((OverVoltageCutoff, 3600))
        );
        assert_eq!(
            ok("Over-Voltage Cutoff=3.6", false),
            Ok((OverVoltageCutoff, 3600))
        );
        assert_eq!(ok("charger_type=CC/CV", false), Ok((ChargerType, 1)));
        assert_eq!(
            ok("distance_unit=Kilometer (2)", false),
            Ok((DistanceUnit, 2))
        );
        assert_eq!(
            ok("over_voltage_cutoff=3600", true),
            Ok((OverVoltageCutoff, 3600))
        );
        // A plain number is physical: 3600 is 3600 V (range check refuses it later).
        assert_eq!(
            ok("over_voltage_cutoff=3600", false),
            Ok((OverVoltageCutoff, 3_600_000))
        );
        assert!(parse_set_arg("over_voltage_cutoff=3.6005", false)
            .unwrap_err()
            .contains("steps of 0.001 V"));
        assert!(parse_set_arg("over_voltage_cutoff=3.6A", false)
            .unwrap_err()
            .contains("in V or mV"));
        assert!(parse_set_arg("over_volatge_cutoff=3.6", false)
            .unwrap_err()
            .contains("did you mean `over_voltage_cutoff`"));
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
