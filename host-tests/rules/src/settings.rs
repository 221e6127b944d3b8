//! The BMS's settings as an owner types them (`tinybms set`, the console):
//! `NAME=VALUE` in the unit `settings` prints, with a unit, or raw; checked as
//! the bridge will check them before it writes anything (Rev D's range and
//! enumeration, the BMS's own limits, the relations between settings), every
//! problem in one sentence.

use protocol_core::registers::{option_name, ValueType};
use protocol_core::settings::SettingId;
use tinybms_firmware::host_link::schema::{Read, SettingLine};
use tinybms_firmware::units;

pub use crate::profile::{find_setting, snake_name};
use crate::words::short;

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

/// The raw value the BMS holds for `id`, from the bridge's `setting` lines
/// (`None`: not listed, or not read).
pub fn held(current: &[SettingLine<Read>], id: SettingId) -> Option<i32> {
    let n = snake_name(id);
    current.iter().find(|l| l.name == n).and_then(|l| l.raw)
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
/// from the same values): the one given, else the one the BMS's own
/// over-voltage cutoff (else fully-charged voltage) names; none when forced
/// or when they name none. With it, the sentence the owner is told when
/// `items` holds a cell voltage (`chemistry: LiFePO4 (taken from …)`).
pub fn chemistry_of(
    current: &[SettingLine<Read>],
    items: &[(SettingId, i32)],
    check: protocol_core::settings::ChemistryCheck,
) -> (Option<Chem>, Option<String>) {
    use protocol_core::settings::{Chemistry, ChemistryCheck};
    let held = |id: SettingId| held(current, id);
    let voltages = items
        .iter()
        .any(|(id, _)| Chemistry::LiFePO4.range(*id).is_some());
    let chem = match check {
        ChemistryCheck::Off => {
            return (
                None,
                voltages.then(|| "chemistry: not checked (--force)".to_string()),
            );
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
    let said = voltages.then(|| match &chem {
        Some(c) => format!("chemistry: {} ({})", c.chemistry.name(), c.why),
        None => "chemistry: unknown (the BMS's cutoffs name none): cell voltages checked \
                 against each other only; --chemistry lifepo4|li-ion|lto to check them"
            .to_string(),
    });
    (chem, said)
}

/// Checks every (setting, raw value) as the bridge will before it writes
/// anything: Rev D's range and enumeration, and the BMS's own min/max as the
/// bridge reported them in `current` (its `setting` lines). `bare`: settings
/// whose value was a plain number taken in the unit `settings` prints — a
/// refusal then says what the number would be as a raw value. All problems
/// at once, or Ok.
pub fn check_all(
    current: &[SettingLine<Read>],
    items: &[(SettingId, i32)],
    bare: Option<&[SettingId]>,
    chemistry: Option<&Chem>,
) -> Result<(), String> {
    use protocol_core::settings::Setting;
    let mut problems = Vec::new();
    for &(id, raw) in items {
        let name = snake_name(id);
        let line = current.iter().find(|l| l.name == name);
        let bms = line.and_then(|l| {
            let lo = l.bms_min?;
            let hi = l.bms_max?;
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
                .or_else(|| held(current, other))
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
            problems.push(refusal(
                id,
                raw,
                &e,
                bms,
                line.is_some() && bare.is_some_and(|b| b.contains(&id)),
            ));
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

/// What a refused value of `id` says: why, the ranges it must keep, and —
/// when it was a `bare` number the BMS has a line for — the raw value it
/// may have meant.
fn refusal(
    id: SettingId,
    raw: i32,
    e: &protocol_core::settings::SettingError,
    bms: Option<(i32, i32)>,
    bare: bool,
) -> String {
    let name = snake_name(id);
    let range = match (id.register().and_then(|r| r.range), bms) {
        (Some((lo, hi)), Some((bl, bh))) => format!(
            "allowed {}..{}, this BMS {}..{}",
            physical(id, i64::from(lo)),
            physical(id, i64::from(hi)),
            physical(id, i64::from(bl)),
            physical(id, i64::from(bh))
        ),
        (Some((lo, hi)), None) => format!(
            "allowed {}..{}",
            physical(id, i64::from(lo)),
            physical(id, i64::from(hi))
        ),
        _ => String::new(),
    };
    let why = match e.reason() {
        "out_of_rev_d_range" => "outside the range the TinyBMS allows",
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
    if let Some((as_raw, shown)) = bare.then(|| raw_meant(id, raw, bms)).flatten() {
        msg.push_str(&format!(
            "; did you mean the raw value {as_raw} ({shown})? add --raw, or give the unit"
        ));
    }
    msg
}

/// The raw value a number `raw` (taken in the unit `settings` prints) would
/// be, when that is a whole number `id` takes.
fn raw_meant(id: SettingId, raw: i32, bms: Option<(i32, i32)>) -> Option<(i32, String)> {
    use protocol_core::settings::Setting;
    let v = tinybms_firmware::units::physical(id, raw)?.as_f64();
    let as_raw = v.round() as i32;
    (f64::from(as_raw) == v
        && Setting::new(id, as_raw)
            .and_then(|s| s.validate_with(bms))
            .is_ok())
    .then(|| (as_raw, physical(id, i64::from(as_raw))))
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
        return Err(match crate::words::suggest(name.trim(), &names) {
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
