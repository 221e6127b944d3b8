//! `settings`, `apply`, `set`: the settings table, the profile writer (the
//! text format `host_tests::profile` reads), the difference before an apply,
//! and the `NAME=VALUE` arguments of `set`.

use protocol_core::registers::{option_name, ValueType};
use protocol_core::settings::SettingId;
use serde_json::Value;
use tinybms_firmware::units;

use crate::profile::{find_setting, snake_name};

pub use crate::words::short;

/// The physical value of `raw` for `id`: `3.65 V`, `60 A`, or the enumerated
/// value's name.
pub fn physical(id: SettingId, raw: i64) -> String {
    match id.register() {
        // Flags: the names of the bits set (`none`), then the number.
        Some(r) if r.value_type == ValueType::Bits && !r.options.is_empty() => {
            let names: Vec<&str> = r
                .options
                .iter()
                .filter(|(bit, _)| *bit < 63 && raw >> bit & 1 == 1)
                .map(|(_, n)| *n)
                .collect();
            let known: i64 = r.options.iter().map(|(bit, _)| 1i64 << bit).sum();
            if raw & !known != 0 || raw < 0 {
                return raw.to_string();
            }
            if names.is_empty() {
                format!("none ({raw})")
            } else {
                format!("{} ({raw})", names.join(" + "))
            }
        }
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
pub fn render_groups(lines: &[Value]) -> String {
    let name_of = |l: &Value| l["name"].as_str().and_then(find_setting);
    let mut out = String::new();
    let mut groups: Vec<(&str, Vec<Value>)> = GROUPS
        .iter()
        .map(|(g, ids)| {
            let rows = ids
                .iter()
                .filter_map(|id| lines.iter().find(|l| name_of(l) == Some(*id)).cloned())
                .collect();
            (*g, rows)
        })
        .collect();
    let other: Vec<Value> = lines
        .iter()
        .filter(|l| l["type"] == "setting")
        .filter(|l| {
            !GROUPS
                .iter()
                .any(|(_, ids)| name_of(l).is_some_and(|id| ids.contains(&id)))
        })
        .cloned()
        .collect();
    groups.push(("Other", other));
    // One width for all groups, so the columns line up down the page.
    let all: Vec<Value> = groups.iter().flat_map(|(_, r)| r.iter().cloned()).collect();
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

/// The chemistry the cell voltages are checked against, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Chem {
    /// Which.
    pub chemistry: protocol_core::settings::Chemistry,
    /// Where it comes from, in words.
    pub why: String,
}

/// The chemistry `set`/`apply` check against (the bridge infers the same
/// from the same values), said on stdout when `items` holds a cell voltage:
/// the one given, else the one the BMS's own over-voltage cutoff (else
/// fully-charged voltage) names; none when forced or when they name none.
pub fn chemistry_of(
    current: &[Value],
    items: &[(SettingId, i32)],
    check: protocol_core::settings::ChemistryCheck,
) -> Option<Chem> {
    use protocol_core::settings::{Chemistry, ChemistryCheck};
    let held = |id: SettingId| {
        let n = snake_name(id);
        current
            .iter()
            .find(|l| l["type"] == "setting" && l["name"] == n.as_str())
            .and_then(|l| l["raw"].as_i64())
            .and_then(|v| i32::try_from(v).ok())
    };
    let voltages = items
        .iter()
        .any(|(id, _)| Chemistry::LiFePO4.range(*id).is_some());
    let chem = match check {
        ChemistryCheck::Off => {
            if voltages {
                println!("chemistry: not checked (--force)");
            }
            return None;
        }
        ChemistryCheck::Given(c) => Some(Chem {
            chemistry: c,
            why: "as --chemistry says".into(),
        }),
        ChemistryCheck::Inferred => Chemistry::infer(held).map(|(c, id, v)| Chem {
            chemistry: c,
            why: format!(
                "taken from the {} the BMS holds, {}",
                snake_name(id).replace('_', " "),
                physical(id, i64::from(v))
            ),
        }),
    };
    if voltages {
        match &chem {
            Some(c) => println!("chemistry: {} ({})", c.chemistry.name(), c.why),
            None => println!(
                "chemistry: unknown (the BMS's cutoffs name none): cell voltages checked \
                 against each other only; --chemistry lifepo4|li-ion|lto to check them"
            ),
        }
    }
    chem
}

/// Checks every (setting, raw value) as the bridge will before it writes
/// anything: Rev D's range and enumeration, and the BMS's own min/max as the
/// bridge reported them in `current` (its `setting` lines). `bare`: settings
/// whose value was a plain number taken in the unit `settings` prints — a
/// refusal then says what the number would be as a raw value. All problems
/// at once, or Ok.
pub fn check_all(
    current: &[Value],
    items: &[(SettingId, i32)],
    bare: Option<&[SettingId]>,
    chemistry: Option<&Chem>,
) -> Result<(), String> {
    use protocol_core::settings::Setting;
    let mut problems = Vec::new();
    for &(id, raw) in items {
        let name = snake_name(id);
        let line = current
            .iter()
            .find(|l| l["type"] == "setting" && l["name"] == name.as_str());
        let bms = line.and_then(|l| {
            let lo = l["bms_min"].as_f64()?;
            let hi = l["bms_max"].as_f64()?;
            let lo = tinybms_firmware::units::raw_from_physical(id, lo)?;
            let hi = tinybms_firmware::units::raw_from_physical(id, hi)?;
            Some((lo, hi))
        });
        // The firmware's own relations between settings: against the values
        // written with it first, else the ones the BMS holds.
        let value_of = |other: SettingId| {
            items
                .iter()
                .find(|(i, _)| *i == other)
                .map(|(_, v)| *v)
                .or_else(|| {
                    let n = snake_name(other);
                    current
                        .iter()
                        .find(|l| l["type"] == "setting" && l["name"] == n.as_str())
                        .and_then(|l| l["raw"].as_i64())
                        .and_then(|v| i32::try_from(v).ok())
                })
        };
        let verdict = Setting::new(id, raw).and_then(|s| s.validate_with(bms));
        let relation = verdict.as_ref().ok().map(|()| {
            protocol_core::settings::check_relations(&Setting { id, value: raw }, value_of)
        });
        if let Some(Err(protocol_core::settings::SettingError::Contradicts {
            relation,
            other,
            ..
        })) = relation
        {
            let (low, high) = (snake_name(relation.low), snake_name(relation.high));
            let other_id = if relation.low == id {
                relation.high
            } else {
                relation.low
            };
            problems.push(format!(
                "{name} = {}: {low} {} {high} ({} is {}); change both together if both should move",
                physical(id, i64::from(raw)),
                if relation.gap > 0 {
                    "must stay below"
                } else {
                    "may not exceed"
                },
                snake_name(other_id),
                physical(other_id, i64::from(other))
            ));
            continue;
        }
        // Last, the chemistry's window (what `--force` passes; never the
        // relations above).
        let verdict = verdict.and_then(|()| match chemistry {
            Some(c) => {
                protocol_core::settings::check_chemistry(&Setting { id, value: raw }, c.chemistry)
            }
            None => Ok(()),
        });
        if let (
            Err(protocol_core::settings::SettingError::OutsideChemistry { min, max, .. }),
            Some(c),
        ) = (&verdict, chemistry)
        {
            problems.push(format!(
                "{name} = {}: plainly wrong for a {} pack ({}..{} per cell; {}); \
                 --chemistry CHEM if the pack is another, --force to write it anyway",
                physical(id, i64::from(raw)),
                c.chemistry.name(),
                physical(id, i64::from(*min)),
                physical(id, i64::from(*max)),
                c.why
            ));
            continue;
        }
        if let Err(e) = verdict {
            let range = match (id.register().and_then(|r| r.range), bms) {
                (Some((lo, hi)), Some((bl, bh))) => format!(
                    "Rev D {}..{}, this BMS {}..{}",
                    physical(id, i64::from(lo)),
                    physical(id, i64::from(hi)),
                    physical(id, i64::from(bl)),
                    physical(id, i64::from(bh))
                ),
                (Some((lo, hi)), None) => format!(
                    "Rev D {}..{}",
                    physical(id, i64::from(lo)),
                    physical(id, i64::from(hi))
                ),
                _ => String::new(),
            };
            let why = match e.reason() {
                "out_of_rev_d_range" => "outside Rev D's range",
                "outside_bms_limits" => "outside this BMS's own limits",
                "not_an_option" => "not one of its values",
                other => other,
            };
            let mut msg = format!(
                "{name} = {}: {why}{}",
                physical(id, i64::from(raw)),
                if range.is_empty() {
                    String::new()
                } else {
                    format!(" ({range})")
                }
            );
            // A number meant in raw units? Say so when it would fit.
            if bare.is_some_and(|b| b.contains(&id)) {
                if let Some(shown) = line.and_then(|_| {
                    let v = tinybms_firmware::units::physical(id, raw)?.as_f64();
                    let as_raw = v.round() as i32;
                    (f64::from(as_raw) == v
                        && Setting::new(id, as_raw)
                            .and_then(|s| s.validate_with(bms))
                            .is_ok())
                    .then(|| (as_raw, physical(id, i64::from(as_raw))))
                }) {
                    msg.push_str(&format!(
                        "; did you mean the raw value {} ({})? add --raw, or give the unit",
                        shown.0, shown.1
                    ));
                }
            }
            problems.push(msg);
        }
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "nothing written; refused:\n  {}",
            problems.join("\n  ")
        ))
    }
}

/// A profile of the settings read (`name = raw  # physical`), readable by
/// `host_tests::profile::parse_profile` (and so by `apply` and `sim --profile`).
/// Settings that read back a marker instead of their value are left as
/// comments.
pub fn profile_text(lines: &[Value], header: &str) -> (String, usize) {
    let mut saved = 0;
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

/// Parses one `set` argument: `NAME=VALUE`. With `raw`, VALUE is an integer in
/// register units. Otherwise VALUE is in the unit `settings` prints for the
/// setting (a plain number: `3.65`), with a unit (`3.65V`, `3650mV`), or an
/// enumeration value's name (`CC/CV`); converted exactly, as a profile's
/// values are (`tinybms_firmware::bms::profile::parse_value`). Returns the
/// setting, its raw value, and whether the value was a plain number.
pub fn parse_set_arg(arg: &str, raw: bool) -> Result<(SettingId, i32, bool), String> {
    use tinybms_firmware::bms::profile::parse_value;
    let (name, value) = arg
        .split_once('=')
        .ok_or_else(|| format!("`{arg}`: expected NAME=VALUE"))?;
    let Some(id) = find_setting(name) else {
        let names: Vec<&str> = SettingId::ALL
            .iter()
            .map(|&i| tinybms_firmware::bms::profile::setting_key(i))
            .collect();
        return Err(match super::suggest(name.trim(), &names) {
            Some(s) => format!("`{}`: no such setting; did you mean `{s}`?", name.trim()),
            None => format!(
                "`{}`: no such setting (`tinybms settings PORT` lists them)",
                name.trim()
            ),
        });
    };
    let value = value.trim();
    let forms = crate::profile::value_forms(id);
    if raw {
        let v: i32 = value.parse().map_err(|_| {
            format!(
                "`{value}`: --raw values are integers in register units ({})",
                snake_name(id)
            )
        })?;
        return Ok((id, v, false));
    }
    let unit = id.register().map_or("", |r| r.unit);
    let plain = !value.is_empty()
        && value
            .chars()
            .all(|c| c.is_ascii_digit() || matches!(c, '.' | '-' | '+'));
    let text = if plain && !unit.is_empty() {
        format!("{value} {unit}")
    } else {
        value.to_string()
    };
    parse_value(id, &text)
        .map(|v| (id, v, plain))
        .map_err(|k| format!("`{value}`: {} ({}: {forms})", k.reason(), snake_name(id)))
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
        let (text, saved) = profile_text(&lines, "saved by a test");
        assert_eq!(saved, 2);
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
