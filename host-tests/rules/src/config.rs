//! The bridge's own configuration as an owner types it: `NAME=VALUE`, checked
//! by the firmware's field table and value parser, then the whole record by
//! its rules between fields — what the bridge will check again, so a change
//! it would refuse is refused before anything is sent. Every error is the
//! sentence the owner reads.

use serde_json::Value;
use tinybms_firmware::config::value::{self, Parsed};
use tinybms_firmware::config::{Config, FieldId, Kind, FIELDS};
use tinybms_firmware::host_link::schema::{ConfigField, Read};
use tinybms_firmware::text::Line;

use crate::words::suggest;

/// The field named `name`, or the sentence that says there is none (with
/// the name meant, when it looks like a typo).
pub fn field_named(name: &str) -> Result<FieldId, String> {
    FieldId::from_name(name).ok_or_else(|| {
        let names: Vec<&str> = FIELDS.iter().map(|f| f.name).collect();
        format!(
            "no configuration field `{name}`{} (`tinybms config PORT` lists them)",
            suggest(name, &names)
                .map(|s| format!("; did you mean `{s}`?"))
                .unwrap_or_default()
        )
    })
}

/// The range of a field as written (`0 A..500 A, or none`).
pub fn range_text(id: FieldId) -> String {
    let mut range = Line::new();
    value::write_range(id.field(), &mut range);
    range.as_str().to_string()
}

/// Checks one `NAME=VALUE` as the bridge would: the field exists and the
/// text is a value of it.
pub fn check_assignment(name: &str, text: &str) -> Result<(FieldId, Parsed), String> {
    let id = field_named(name)?;
    let f = id.field();
    // A key or a secret is never repeated (a private key pasted by mistake
    // must not land in a terminal's history twice).
    let hidden = f.is_secret()
        || matches!(
            f.kind,
            Kind::Text {
                rule: tinybms_firmware::config::TextRule::Key,
                ..
            }
        );
    let shown = if hidden { "(the value given)" } else { text };
    value::parse(f, text).map(|p| (id, p)).map_err(|e| {
        format!(
            "{name} = {shown}: {} (it takes {}{})",
            e.detail,
            range_text(id),
            if f.unit.is_empty() {
                String::new()
            } else {
                format!("; the unit may be given: `{name}=… {}`", f.unit)
            }
        )
    })
}

/// `NAME=VALUE` split.
pub fn split_assignment(arg: &str) -> Result<(String, String), String> {
    arg.split_once('=')
        .map(|(n, v)| (n.trim().to_string(), v.trim().to_string()))
        .ok_or_else(|| format!("`{arg}`: want NAME=VALUE"))
}

/// The record the bridge holds, rebuilt from its `config` lines (secrets
/// that are set get a placeholder, so the rules between fields can be
/// checked).
pub fn record_of(lines: &[ConfigField<Read>]) -> Config {
    let mut c = Config::default();
    for l in lines {
        let Some(id) = FieldId::from_name(&l.name) else {
            continue;
        };
        let f = id.field();
        let text = match f.kind {
            Kind::Secret { hex64: true, .. } if l.value == "set" => "0".repeat(64),
            Kind::Secret { .. } if l.value == "set" => "set".into(),
            Kind::Secret { .. } => String::new(),
            _ => l.value.clone(),
        };
        if let Ok(p) = value::parse(f, &text) {
            let _ = c.set(id, p.as_value());
        }
    }
    c
}

/// Checks `changes` against the bridge's record (every rule between
/// fields), so that a change that cannot be accepted is refused before
/// anything is sent.
pub fn check_locally(current: &Config, changes: &[(FieldId, Parsed)]) -> Result<(), String> {
    let mut next = current.clone();
    for (id, p) in changes {
        next.set(*id, p.as_value())
            .map_err(|e| format!("{}: {}", id.name(), e.detail))?;
    }
    next.validate()
        .map_err(|e| format!("{}: {}", e.field.name(), e.detail))
}

/// The text a change sends for a field (its text form; a secret as given).
pub fn wire_text(id: FieldId, p: &Parsed) -> String {
    let mut l = Line::new();
    match p {
        Parsed::Text(t) => t.to_string(),
        _ => {
            value::write(id.field(), &p.as_value(), true, &mut l);
            l.as_str().to_string()
        }
    }
}

/// A field as the firmware's table has it, for a page that shows them.
pub fn fields_json() -> Value {
    let fields: Vec<Value> = FIELDS
        .iter()
        .map(|f| {
            let mut default = Line::new();
            value::write(f, &Config::default().get(f.id), true, &mut default);
            serde_json::json!({
                "name": f.name,
                "unit": f.unit,
                "group": f.group.name(),
                "applies": f.applies.name(),
                "help": f.help,
                "range": range_text(f.id),
                "default": if f.is_secret() { "unset".to_string() } else { default.as_str().to_string() },
                "secret": f.is_secret(),
                "kind": match f.kind {
                    Kind::Bool => "bool",
                    Kind::Choice(_) => "choice",
                    Kind::Number { .. } => "number",
                    Kind::Text { .. } => "text",
                    Kind::Secret { .. } => "secret",
                },
                "choices": match f.kind {
                    Kind::Choice(c) => c.to_vec(),
                    Kind::Bool => vec!["on", "off"],
                    _ => vec![],
                },
            })
        })
        .collect();
    Value::Array(fields)
}
