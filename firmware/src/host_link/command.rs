//! Commands from the host: one JSON object per line, parsed with `serde` and
//! `serde-json-core` without allocation (strings borrowed from the line).
//!
//! The top-level object is read by a hand-written map visitor instead of a
//! derived `Deserialize` with `deny_unknown_fields`: `serde-json-core` turns
//! every derive-level error (unknown field, missing field, unknown variant) into
//! one `CustomError` without its message, and the protocol promises an error code
//! that names the problem. The visitor also keeps the `req` read before a problem,
//! so the error line can echo it.

use heapless::Vec;
use serde::de::{DeserializeSeed, IgnoredAny, MapAccess, Visitor};
use serde_json_core::str::EscapedStr;

use super::ErrorCode;

/// Most settings in one `set` (PROTOCOL.md).
pub const MAX_SET: usize = 8;

/// Most fields in one `set_config`.
pub const MAX_SET_CONFIG: usize = crate::config::state::MAX_CHANGES;

/// Deepest nesting of objects and arrays accepted in a command line (the
/// command object is 1, `values` is 2): bounds the parser's recursion.
pub const MAX_DEPTH: usize = 4;

/// What `get` asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum What {
    /// `telemetry` line.
    Snapshot,
    /// `setting` lines and `settings_end`.
    Settings,
    /// `statistics` line.
    Statistics,
    /// `event` lines (`history`) and `events_end`.
    Events,
    /// `version` line.
    Version,
    /// `link` line.
    Link,
    /// `config` lines (the bridge's own configuration) and `config_end`.
    Config,
    /// `can` lines (the CAN capture, oldest first) and `can_end`.
    Can,
    /// The history in flash: `history_event`, `history_day` (and
    /// `history_skipped`) lines, oldest first, and `history_end`.
    History,
}

/// What `clear` clears.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClearWhat {
    /// The BMS event log.
    Events,
    /// The BMS statistics.
    Statistics,
}

/// Values of a `set`, by setting name, as sent.
#[derive(Debug, Clone, PartialEq)]
pub enum SetValues<'a> {
    /// `"values"`: physical units.
    Physical(Vec<(&'a str, f64), MAX_SET>),
    /// `"raw"`: register units (integral).
    Raw(Vec<(&'a str, f64), MAX_SET>),
}

/// One parsed command.
#[derive(Debug, Clone, PartialEq)]
pub enum HostCommand<'a> {
    /// `hello`.
    Hello,
    /// `get`.
    Get(What),
    /// `set`, and the chemistry its values are checked against (`force`:
    /// none; `chemistry`: that one; else the one the BMS's voltages name).
    Set(SetValues<'a>, protocol_core::settings::ChemistryCheck),
    /// `reset`.
    Reset,
    /// `clear`.
    Clear(ClearWhat),
    /// `stream`, period in ms (0: off).
    Stream(u32),
    /// `capture`.
    Capture(bool),
    /// `set_config`: the bridge's configuration fields by name, their values
    /// as text (JSON strings, escapes still in).
    SetConfig(Vec<(&'a str, EscapedStr<'a>), MAX_SET_CONFIG>),
    /// `reset_config`: every field back to its default.
    ResetConfig,
    /// `update_begin`: an update file of `size` bytes comes (`check`: its
    /// header only, to hear whether it would be taken).
    UpdateBegin {
        /// The file's length.
        size: u32,
        /// An older version is wanted, features may be dropped (`downgrade`,
        /// `drop_features`: a comma-separated list of feature names).
        permit: crate::update::file::Permit,
        /// Only check the header.
        check: bool,
    },
    /// `update_chunk`: bytes of the file at an offset, base64 as sent.
    UpdateChunk {
        /// The file offset.
        at: u32,
        /// The bytes, base64.
        data: &'a str,
    },
    /// `update_cancel`.
    UpdateCancel,
    /// `update_status`.
    UpdateStatus,
    /// `set_time`: the date, Unix seconds (`at`), for the history's records.
    SetTime(u32),
}

/// A command line that parsed, with its request id.
#[derive(Debug, Clone, PartialEq)]
pub struct Parsed<'a> {
    /// `"req"`, echoed in every answer.
    pub req: Option<u32>,
    /// The command.
    pub command: HostCommand<'a>,
}

/// A command line that did not parse.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CommandError<'a> {
    /// `"req"`, when it was read before the problem.
    pub req: Option<u32>,
    /// The error code.
    pub code: ErrorCode,
    /// Human-readable reason.
    pub detail: &'static str,
    /// The offending member, command or value ("" when none).
    pub subject: &'a str,
}

/// Shortest and longest stream period, ms (0 switches streaming off).
pub const STREAM_PERIOD_MS: (u32, u32) = (100, 60_000);

#[derive(Default)]
struct Fields<'a> {
    cmd: Option<&'a str>,
    req: Option<u32>,
    what: Option<&'a str>,
    values: Option<Vec<(&'a str, f64), MAX_SET>>,
    raw: Option<Vec<(&'a str, f64), MAX_SET>>,
    period_ms: Option<u32>,
    on: Option<bool>,
    fields: Option<Vec<(&'a str, EscapedStr<'a>), MAX_SET_CONFIG>>,
    force: Option<bool>,
    chemistry: Option<&'a str>,
    size: Option<u32>,
    at: Option<u32>,
    data: Option<&'a str>,
    downgrade: Option<bool>,
    check: Option<bool>,
    drop_features: Option<&'a str>,
    /// The first member no command has.
    unknown: Option<&'a str>,
    /// A member given twice.
    duplicate: Option<&'static str>,
    /// `values` / `raw` held more than [`MAX_SET`] settings.
    too_many: bool,
    /// A number member that is not a `u32`.
    invalid: Option<&'static str>,
    /// The member being read (for type errors).
    current: &'static str,
}

struct Top<'f, 'a>(&'f mut Fields<'a>);

impl<'de, 'f> DeserializeSeed<'de> for Top<'f, 'de> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_map(self)
    }
}

/// A JSON number that is a `u32` (numbers are read as f64: `serde-json-core`
/// reads `1.5` as an integer `1` followed by garbage).
fn whole(v: f64) -> Option<u32> {
    (v >= 0.0 && v <= f64::from(u32::MAX) && crate::units::round(v) == v).then_some(v as u32)
}

fn put<T>(slot: &mut Option<T>, v: T, name: &'static str, dup: &mut Option<&'static str>) {
    if slot.is_some() {
        dup.get_or_insert(name);
    }
    *slot = Some(v);
}

impl<'de, 'f> Visitor<'de> for Top<'f, 'de> {
    type Value = ();

    fn expecting(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("a command object")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        let f = self.0;
        while let Some(key) = map.next_key::<&'de str>()? {
            match key {
                "cmd" => {
                    f.current = "cmd";
                    let v = map.next_value()?;
                    put(&mut f.cmd, v, "cmd", &mut f.duplicate);
                }
                "req" => {
                    f.current = "req";
                    match whole(map.next_value()?) {
                        Some(v) => put(&mut f.req, v, "req", &mut f.duplicate),
                        None => {
                            f.invalid.get_or_insert("req");
                        }
                    }
                }
                "what" => {
                    f.current = "what";
                    let v = map.next_value()?;
                    put(&mut f.what, v, "what", &mut f.duplicate);
                }
                "period_ms" => {
                    f.current = "period_ms";
                    match whole(map.next_value()?) {
                        Some(v) => put(&mut f.period_ms, v, "period_ms", &mut f.duplicate),
                        None => {
                            f.invalid.get_or_insert("period_ms");
                        }
                    }
                }
                "on" => {
                    f.current = "on";
                    let v = map.next_value()?;
                    put(&mut f.on, v, "on", &mut f.duplicate);
                }
                "size" | "at" => {
                    let name = if key == "at" { "at" } else { "size" };
                    f.current = name;
                    match whole(map.next_value()?) {
                        Some(v) => {
                            let slot = if key == "at" { &mut f.at } else { &mut f.size };
                            put(slot, v, name, &mut f.duplicate);
                        }
                        None => {
                            f.invalid.get_or_insert(name);
                        }
                    }
                }
                "data" => {
                    f.current = "data";
                    let v = map.next_value()?;
                    put(&mut f.data, v, "data", &mut f.duplicate);
                }
                "downgrade" | "check" => {
                    let name = if key == "check" { "check" } else { "downgrade" };
                    f.current = name;
                    let v = map.next_value()?;
                    let slot = if key == "check" {
                        &mut f.check
                    } else {
                        &mut f.downgrade
                    };
                    put(slot, v, name, &mut f.duplicate);
                }
                "drop_features" => {
                    f.current = "drop_features";
                    let v = map.next_value()?;
                    put(&mut f.drop_features, v, "drop_features", &mut f.duplicate);
                }
                "force" => {
                    f.current = "force";
                    let v = map.next_value()?;
                    put(&mut f.force, v, "force", &mut f.duplicate);
                }
                "chemistry" => {
                    f.current = "chemistry";
                    let v = map.next_value()?;
                    put(&mut f.chemistry, v, "chemistry", &mut f.duplicate);
                }
                "fields" => {
                    f.current = "fields";
                    let mut pairs = Vec::new();
                    map.next_value_seed(TextPairs(&mut pairs, &mut f.too_many))?;
                    put(&mut f.fields, pairs, "fields", &mut f.duplicate);
                }
                "values" | "raw" => {
                    let name = if key == "raw" { "raw" } else { "values" };
                    f.current = name;
                    let mut pairs = Vec::new();
                    map.next_value_seed(Pairs(&mut pairs, &mut f.too_many))?;
                    let slot = if key == "raw" {
                        &mut f.raw
                    } else {
                        &mut f.values
                    };
                    put(slot, pairs, name, &mut f.duplicate);
                }
                other => {
                    f.unknown.get_or_insert(other);
                    f.current = "";
                    map.next_value::<IgnoredAny>()?;
                }
            }
        }
        Ok(())
    }
}

/// `{NAME: number, ...}`, at most [`MAX_SET`] kept.
struct Pairs<'v, 'a>(&'v mut Vec<(&'a str, f64), MAX_SET>, &'v mut bool);

impl<'de, 'v> DeserializeSeed<'de> for Pairs<'v, 'de> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_map(self)
    }
}

impl<'de, 'v> Visitor<'de> for Pairs<'v, 'de> {
    type Value = ();

    fn expecting(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("an object of setting names and numbers")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while let Some(name) = map.next_key::<&'de str>()? {
            let v: f64 = map.next_value()?;
            if self.0.push((name, v)).is_err() {
                *self.1 = true;
            }
        }
        Ok(())
    }
}

/// `{NAME: "text", ...}`, at most [`MAX_SET_CONFIG`] kept.
struct TextPairs<'v, 'a>(
    &'v mut Vec<(&'a str, EscapedStr<'a>), MAX_SET_CONFIG>,
    &'v mut bool,
);

impl<'de, 'v> DeserializeSeed<'de> for TextPairs<'v, 'de> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_map(self)
    }
}

impl<'de, 'v> Visitor<'de> for TextPairs<'v, 'de> {
    type Value = ();

    fn expecting(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("an object of field names and strings")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while let Some(name) = map.next_key::<&'de str>()? {
            let v: EscapedStr<'de> = map.next_value()?;
            if self.0.push((name, v)).is_err() {
                *self.1 = true;
            }
        }
        Ok(())
    }
}

/// Deepest nesting of `{`/`[` outside strings.
fn depth(line: &[u8]) -> usize {
    let (mut d, mut max, mut in_str, mut esc) = (0usize, 0usize, false, false);
    for &b in line {
        if in_str {
            match (esc, b) {
                (true, _) => esc = false,
                (false, b'\\') => esc = true,
                (false, b'"') => in_str = false,
                _ => {}
            }
            continue;
        }
        match b {
            b'"' => in_str = true,
            b'{' | b'[' => {
                d += 1;
                max = max.max(d);
            }
            b'}' | b']' => d = d.saturating_sub(1),
            _ => {}
        }
    }
    max
}

fn syntax(e: serde_json_core::de::Error) -> &'static str {
    use serde_json_core::de::Error as E;
    match e {
        E::EofWhileParsingList
        | E::EofWhileParsingObject
        | E::EofWhileParsingString
        | E::EofWhileParsingNumber
        | E::EofWhileParsingValue => "unexpected end of line",
        E::TrailingCharacters => "trailing characters",
        E::TrailingComma => "trailing comma",
        E::KeyMustBeAString => "key must be a string",
        E::InvalidUnicodeCodePoint | E::InvalidEscapeSequence => "invalid string",
        _ => "not valid JSON",
    }
}

fn what(s: &str) -> Option<What> {
    Some(match s {
        "snapshot" => What::Snapshot,
        "settings" => What::Settings,
        "statistics" => What::Statistics,
        "events" => What::Events,
        "version" => What::Version,
        "link" => What::Link,
        "config" => What::Config,
        "can" => What::Can,
        "history" => What::History,
        _ => return None,
    })
}

/// Parses one command line (without its `\n`). Never panics.
pub fn parse(line: &[u8]) -> Result<Parsed<'_>, CommandError<'_>> {
    let f = read_members(line)?;
    let req = f.req;
    let Some(cmd) = f.cmd else {
        return Err(missing(req, "cmd"));
    };
    let Some(&(_, takes, build)) = COMMANDS.iter().find(|(name, ..)| *name == cmd) else {
        return Err(err(req, ErrorCode::UnknownCommand, "unknown command", cmd));
    };
    if let Some(u) = f.unknown {
        return Err(err(req, ErrorCode::UnknownField, "unknown member", u));
    }
    let given = [
        ("what", f.what.is_some()),
        ("values", f.values.is_some()),
        ("raw", f.raw.is_some()),
        ("period_ms", f.period_ms.is_some()),
        ("on", f.on.is_some()),
        ("fields", f.fields.is_some()),
        ("force", f.force.is_some()),
        ("chemistry", f.chemistry.is_some()),
        ("size", f.size.is_some()),
        ("at", f.at.is_some()),
        ("data", f.data.is_some()),
        ("downgrade", f.downgrade.is_some()),
        ("check", f.check.is_some()),
        ("drop_features", f.drop_features.is_some()),
    ];
    for (name, present) in given {
        if present && !takes.contains(&name) {
            return Err(err(
                req,
                ErrorCode::UnknownField,
                "member not taken by this command",
                name,
            ));
        }
    }
    let command = build(f)?;
    Ok(Parsed { req, command })
}

/// An error line's content.
fn err<'a>(
    req: Option<u32>,
    code: ErrorCode,
    detail: &'static str,
    subject: &'a str,
) -> CommandError<'a> {
    CommandError {
        req,
        code,
        detail,
        subject,
    }
}

/// A member the command needs is not there.
fn missing(req: Option<u32>, member: &'static str) -> CommandError<'static> {
    err(req, ErrorCode::MissingField, "missing member", member)
}

/// A command from its members.
type Build = for<'a> fn(Fields<'a>) -> Result<HostCommand<'a>, CommandError<'a>>;

/// Every command: its name, the members it takes besides `cmd` and `req`,
/// and how it is built from them. One row per command: a command not here is
/// unknown.
const COMMANDS: &[(&str, &[&str], Build)] = &[
    ("hello", &[], |_| Ok(HostCommand::Hello)),
    ("reset", &[], |_| Ok(HostCommand::Reset)),
    ("reset_config", &[], |_| Ok(HostCommand::ResetConfig)),
    ("set_config", &["fields"], set_config),
    ("get", &["what"], get),
    ("clear", &["what"], clear),
    ("set", &["values", "raw", "force", "chemistry"], set),
    ("stream", &["period_ms"], stream),
    ("capture", &["on"], capture),
    (
        "update_begin",
        &["size", "downgrade", "check", "drop_features"],
        update_begin,
    ),
    ("update_chunk", &["at", "data"], update_chunk),
    ("update_cancel", &[], |_| Ok(HostCommand::UpdateCancel)),
    ("update_status", &[], |_| Ok(HostCommand::UpdateStatus)),
    ("set_time", &["at"], |f| {
        Ok(HostCommand::SetTime(f.at.ok_or(missing(f.req, "at"))?))
    }),
];

fn update_begin(f: Fields<'_>) -> Result<HostCommand<'_>, CommandError<'_>> {
    let drop = match f.drop_features {
        None => 0,
        Some(list) => crate::update::file::feature_bits(list).ok_or(err(
            f.req,
            ErrorCode::InvalidValue,
            "not a list of feature names (can, host-link, wifi, store)",
            "drop_features",
        ))?,
    };
    Ok(HostCommand::UpdateBegin {
        size: f.size.ok_or(missing(f.req, "size"))?,
        permit: crate::update::file::Permit {
            downgrade: f.downgrade.unwrap_or(false),
            drop,
        },
        check: f.check.unwrap_or(false),
    })
}

fn update_chunk(f: Fields<'_>) -> Result<HostCommand<'_>, CommandError<'_>> {
    Ok(HostCommand::UpdateChunk {
        at: f.at.ok_or(missing(f.req, "at"))?,
        data: f.data.ok_or(missing(f.req, "data"))?,
    })
}

/// The line's members, read as JSON (syntax, nesting, types, duplicates).
fn read_members(line: &[u8]) -> Result<Fields<'_>, CommandError<'_>> {
    let first = line.iter().copied().find(|b| !b.is_ascii_whitespace());
    if first != Some(b'{') {
        return Err(err(
            None,
            ErrorCode::MalformedJson,
            "expected a JSON object",
            "",
        ));
    }
    if depth(line) > MAX_DEPTH {
        return Err(err(None, ErrorCode::MalformedJson, "nested too deeply", ""));
    }
    let mut f = Fields::default();
    let mut de = serde_json_core::de::Deserializer::new(line, None);
    let result = Top(&mut f).deserialize(&mut de).and_then(|()| de.end());
    if let Err(e) = result {
        use serde_json_core::de::Error as E;
        return Err(match e {
            E::InvalidType | E::InvalidNumber if !f.current.is_empty() => err(
                f.req,
                ErrorCode::InvalidValue,
                "wrong type or number",
                f.current,
            ),
            e => err(f.req, ErrorCode::MalformedJson, syntax(e), ""),
        });
    }
    if let Some(m) = f.invalid {
        return Err(err(
            f.req,
            ErrorCode::InvalidValue,
            "not an unsigned 32-bit integer",
            m,
        ));
    }
    if let Some(d) = f.duplicate {
        return Err(err(
            f.req,
            ErrorCode::MalformedJson,
            "member given twice",
            d,
        ));
    }
    Ok(f)
}

fn set_config(f: Fields<'_>) -> Result<HostCommand<'_>, CommandError<'_>> {
    let req = f.req;
    let fields = f.fields.ok_or(missing(req, "fields"))?;
    if f.too_many || fields.is_empty() {
        return Err(err(
            req,
            ErrorCode::InvalidValue,
            "1 to 12 fields per set_config",
            "",
        ));
    }
    Ok(HostCommand::SetConfig(fields))
}

fn get(f: Fields<'_>) -> Result<HostCommand<'_>, CommandError<'_>> {
    let req = f.req;
    let w = f.what.ok_or(missing(req, "what"))?;
    Ok(HostCommand::Get(what(w).ok_or(err(
        req,
        ErrorCode::InvalidValue,
        "what: snapshot, settings, statistics, events, version, link or config",
        w,
    ))?))
}

fn clear(f: Fields<'_>) -> Result<HostCommand<'_>, CommandError<'_>> {
    let req = f.req;
    let w = f.what.ok_or(missing(req, "what"))?;
    Ok(HostCommand::Clear(match w {
        "events" => ClearWhat::Events,
        "statistics" => ClearWhat::Statistics,
        _ => {
            return Err(err(
                req,
                ErrorCode::InvalidValue,
                "what: events or statistics",
                w,
            ))
        }
    }))
}

fn set(f: Fields<'_>) -> Result<HostCommand<'_>, CommandError<'_>> {
    let req = f.req;
    let values = match (f.values, f.raw) {
        (Some(v), None) => SetValues::Physical(v),
        (None, Some(r)) => SetValues::Raw(r),
        (None, None) => return Err(missing(req, "values")),
        (Some(_), Some(_)) => {
            return Err(err(
                req,
                ErrorCode::InvalidValue,
                "values and raw are exclusive",
                "raw",
            ))
        }
    };
    let n = match &values {
        SetValues::Physical(v) | SetValues::Raw(v) => v.len(),
    };
    if f.too_many || n == 0 {
        return Err(err(
            req,
            ErrorCode::InvalidValue,
            "1 to 8 settings per set",
            "",
        ));
    }
    // serde-json-core reads `null` as NaN: a value of the wrong type.
    let (SetValues::Physical(v) | SetValues::Raw(v)) = &values;
    if let Some(&(name, _)) = v.iter().find(|(_, x)| x.is_nan()) {
        return Err(err(req, ErrorCode::InvalidValue, "not a number", name));
    }
    use protocol_core::settings::{Chemistry, ChemistryCheck};
    let check = match (f.force, f.chemistry) {
        (Some(true), _) => ChemistryCheck::Off,
        (_, Some(c)) => ChemistryCheck::Given(Chemistry::from_key(c).ok_or(err(
            req,
            ErrorCode::InvalidValue,
            "chemistry: lifepo4, li-ion or lto",
            c,
        ))?),
        _ => ChemistryCheck::Inferred,
    };
    Ok(HostCommand::Set(values, check))
}

fn stream(f: Fields<'_>) -> Result<HostCommand<'_>, CommandError<'_>> {
    let req = f.req;
    let p = f.period_ms.ok_or(missing(req, "period_ms"))?;
    if p != 0 && !(STREAM_PERIOD_MS.0..=STREAM_PERIOD_MS.1).contains(&p) {
        return Err(err(
            req,
            ErrorCode::OutOfRange,
            "period_ms: 0 (off) or 100-60000",
            "period_ms",
        ));
    }
    Ok(HostCommand::Stream(p))
}

fn capture(f: Fields<'_>) -> Result<HostCommand<'_>, CommandError<'_>> {
    let on = f.on.ok_or(missing(f.req, "on"))?;
    Ok(HostCommand::Capture(on))
}
