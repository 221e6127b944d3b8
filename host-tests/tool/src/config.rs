//! `tinybms config`: the bridge's own configuration (the record in its flash,
//! firmware/src/config/) — shown with units, ranges and defaults, changed by
//! name, saved to and loaded from a text file, reset.
//!
//! The field table is the firmware's own ([`tinybms_firmware::config::FIELDS`]),
//! so names, units and ranges are checked here exactly as the bridge checks
//! them before anything is sent; the bridge checks again (and against the BMS's
//! own settings) and has the last word.
//!
//! ## The file format (`--save` / `--load`)
//!
//! ```text
//! # comment (a line starting with `#`, or after a value)
//! charge_current_cap = 50.0 A        # a value in the text form `tinybms config` prints
//! inverter_protocol = sma
//! wifi_ssid = "My network"           # text in double quotes (JSON escapes: \" \\ \u00e9)
//! ```
//!
//! One field per line, each at most once. Secrets (`wifi_key`, `mqtt_password`)
//! are never written to a file; a file may set them.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::time::{Duration, Instant};

use serde_json::{json, Map, Value};
use tinybms_firmware::config::value::{self, Parsed};
use tinybms_firmware::config::{Config, FieldId, Kind};
use tinybms_firmware::host_link::assembler::LINE_MAX;
use tinybms_firmware::host_link::schema::{ConfigEnd, ConfigField, Error, HostLine, Read};
use tinybms_firmware::text::Line;
use tinybms_rules::config::wire_text;

use super::client::{protocol_error, Client};
use super::transport::Mode;
use super::{ToolError, ToolResult};

/// How long the save to flash may take (a sector erase is at most ~0.5 s).
pub const SAVE_TIMEOUT: Duration = Duration::from_secs(10);

/// One field as the bridge reports it (`get config`): its `config` line.
pub type Shown = ConfigField<Read>;

/// Refuses direct mode: a USB-UART adapter has no bridge configuration.
pub fn require_bridge(c: &Client) -> ToolResult<()> {
    match c.mode {
        Mode::Bridge => Ok(()),
        Mode::Direct => Err(ToolError::failed(format!(
            "no bridge answered on `{}` (no hello): an ESP32 board not running this firmware \
             yet (flash it: docs/flashing.md), one still starting, or a USB-UART adapter \
             wired to the BMS (direct mode). The configuration is the ESP32 bridge's own, kept \
             in its flash: give the bridge's port (`tinybms ports`)",
            c.port
        ))),
    }
}

/// Refuses a bridge whose image has no Wi-Fi (its `hello` lists what is
/// built in).
pub fn require_wifi(c: &Client, command: &str) -> ToolResult<()> {
    let features = &c.hello.features;
    if features.iter().any(|f| f == "wifi") {
        return Ok(());
    }
    let built: Vec<&str> = features.iter().map(String::as_str).collect();
    Err(ToolError::failed(format!(
        "this bridge's image has no Wi-Fi (built in: {}): `tinybms {command}` would be \
         stored and never used. Flash an image with Wi-Fi (`tinybms-BOARD-wifi.bin`, or \
         `cargo build --release --features wifi`; docs/flashing.md), then run it again",
        if built.is_empty() {
            "nothing listed".to_string()
        } else {
            built.join(", ")
        }
    )))
}

/// The bridge's configuration: every field, and the `config_end` line.
pub fn fetch(c: &mut Client) -> ToolResult<(Vec<Shown>, ConfigEnd<Read>)> {
    let req = c.send(json!({"cmd": "get", "what": "config"}))?;
    let end = Instant::now() + super::client::GET_TIMEOUT;
    let mut out = Vec::new();
    loop {
        match c.recv_for(req, end, "get config")?.line {
            HostLine::ConfigEnd(e) => return Ok((out, e)),
            HostLine::Config(f) => out.push(f),
            _ => {}
        }
    }
}

/// The table `tinybms config PORT` prints.
pub fn render(fields: &[Shown], end: &ConfigEnd<Read>) -> String {
    let mut out = String::new();
    let differing = fields.iter().filter(|f| f.value != f.default).count();
    let pending = end.restart_pending;
    let _ =
        writeln!(
        out,
        "bridge configuration (started from {}; {differing} field{} differ{} from the defaults{})",
        end.source,
        if differing == 1 { "" } else { "s" },
        if differing == 1 { "s" } else { "" },
        if pending > 0 {
            format!("; {pending} wait{} for a restart", if pending == 1 { "s" } else { "" })
        } else {
            String::new()
        }
    );
    let w = fields.iter().map(|f| f.name.len()).max().unwrap_or(10);
    let vw = fields
        .iter()
        .map(|f| shown(f).chars().count())
        .max()
        .unwrap_or(8)
        .min(28);
    let mut group = "";
    for f in fields {
        if f.group != group {
            group = &f.group;
            let _ = writeln!(out, "\n{group}");
        }
        let mark = if f.value != f.default { '*' } else { ' ' };
        let restart = if f.restart_pending {
            "  (restart pending)"
        } else {
            ""
        };
        let _ = writeln!(
            out,
            "{mark} {:<w$}  {:<vw$}  default {:<14} {}; {}{restart}",
            f.name,
            shown(f),
            with_unit(&f.default, &f.unit),
            f.range,
            match f.applies.as_str() {
                "now" => "applies at once",
                _ => "applies at the next restart",
            },
        );
    }
    let _ = writeln!(
        out,
        "\n* differs from the default. `tinybms config PORT NAME` explains a field; \
         `tinybms config PORT NAME=VALUE…` changes it."
    );
    out
}

/// One field in detail (`tinybms config PORT NAME`).
pub fn render_one(f: &Shown) -> String {
    format!(
        "{}: {}\n  value    {}{}\n  default  {}\n  range    {}\n  applies  {}\n",
        f.name,
        f.help,
        shown(f),
        if f.restart_pending {
            " (stored; the bridge runs with the old value until it restarts)"
        } else {
            ""
        },
        with_unit(&f.default, &f.unit),
        f.range,
        if f.applies == "now" {
            "at once"
        } else {
            "at the next restart"
        }
    )
}

/// A field's value as shown: with its unit, and what a value that leaves it
/// to the BMS comes to now (`bms (3450 mV)`, `none (60.0 A)`).
fn shown(f: &Shown) -> String {
    let v = with_unit(&f.value, &f.unit);
    match &f.effective {
        Some(e) => format!("{v} ({e})"),
        None => v,
    }
}

/// A value with its unit, unless it is a word (`none`, `on`, `set`).
fn with_unit(v: &str, unit: &str) -> String {
    let numeric = v.starts_with(|c: char| c.is_ascii_digit() || c == '-');
    if numeric && !unit.is_empty() {
        format!("{v} {unit}")
    } else if v.is_empty() {
        "(empty)".into()
    } else {
        v.to_string()
    }
}

/// The field named `name`, or an error with a suggestion
/// ([`tinybms_rules::config::field_named`], shared with the browser console).
pub fn field_named(name: &str) -> ToolResult<FieldId> {
    tinybms_rules::config::field_named(name).map_err(ToolError::usage)
}

/// Checks one `NAME=VALUE` as the bridge would: the field exists and the text
/// is a value of it. Returns the name and the text to send.
pub fn check_assignment(name: &str, text: &str) -> ToolResult<(FieldId, Parsed)> {
    // A name no field has is a usage error; a value the field refuses is a
    // refusal, as the bridge's own (exit 1).
    tinybms_rules::config::field_named(name).map_err(ToolError::usage)?;
    tinybms_rules::config::check_assignment(name, text)
        .map_err(|e| ToolError::failed(format!("refused, nothing changed: {e}")))
}

/// `NAME=VALUE` split.
pub fn split_assignment(arg: &str) -> ToolResult<(String, String)> {
    tinybms_rules::config::split_assignment(arg).map_err(ToolError::usage)
}

/// The record the bridge holds, rebuilt from its `config` lines (secrets that
/// are set get a placeholder, so the rules between fields can be checked).
pub fn record_of(fields: &[Shown]) -> Config {
    tinybms_rules::config::record_of(fields)
}

/// Checks `changes` against the bridge's record locally (every rule between
/// fields), so that a change that cannot be accepted is refused before
/// anything is sent.
pub fn check_locally(current: &Config, changes: &[(FieldId, Parsed)]) -> ToolResult<()> {
    // A value the rules refuse is a refusal, not a usage error: the command
    // was right, the bridge would refuse what it asks.
    tinybms_rules::config::check_locally(current, changes)
        .map_err(|e| ToolError::failed(format!("refused, nothing changed: {e}")))
}

/// Sends `changes` (split into `set_config` lines that fit the protocol's
/// line length), printing one line per field; fails when any was refused or
/// the save did not go through.
pub fn apply(c: &mut Client, changes: &[(FieldId, Parsed)]) -> ToolResult<()> {
    let mut refused = 0;
    let mut restart = 0;
    let mut saved_all = true;
    let mut changed = 0;
    for group in line_groups(changes) {
        let mut map = Map::new();
        for (id, p) in &group {
            map.insert(id.name().to_string(), json!(wire_text(*id, p)));
        }
        let req = c.send(json!({"cmd": "set_config", "fields": Value::Object(map)}))?;
        let end = Instant::now() + SAVE_TIMEOUT;
        loop {
            let v = match c.recv_for(req, end, "set_config") {
                Ok(r) => r.line,
                Err(e) => return Err(read_only_hint(e)),
            };
            match v {
                HostLine::ConfigOutcome(v) => {
                    let o = v.outcome.as_str();
                    let name = v.name.as_str();
                    let shown = v.value.as_deref().unwrap_or("");
                    let line = match o {
                        "applied" => format!("{name} = {shown}: applied"),
                        "at_restart" => {
                            restart += 1;
                            format!("{name} = {shown}: stored, applies at the next restart")
                        }
                        "unchanged" => format!("{name} = {shown}: unchanged"),
                        "not_applied" => format!("{name}: not applied (another field was refused)"),
                        _ => {
                            refused += 1;
                            format!(
                                "{name}: refused, {} ({}){}",
                                v.error.as_deref().unwrap_or("?"),
                                v.detail.as_deref().unwrap_or(""),
                                v.range
                                    .as_deref()
                                    .map(|r| format!("; it takes {r}"))
                                    .unwrap_or_default()
                            )
                        }
                    };
                    if o == "applied" || o == "at_restart" {
                        changed += 1;
                    }
                    println!("{line}");
                }
                HostLine::ConfigDone(v) => {
                    if v.saved == Some(false) {
                        saved_all = false;
                        println!(
                            "NOT saved to flash: {} (the change holds until the bridge restarts)",
                            v.detail.as_deref().unwrap_or("?")
                        );
                    }
                    break;
                }
                _ => {}
            }
        }
        if refused > 0 {
            break;
        }
    }
    if refused > 0 {
        return Err(ToolError::failed(format!(
            "{refused} field{} refused: nothing of that change was applied",
            if refused == 1 { "" } else { "s" }
        )));
    }
    if !saved_all {
        return Err(ToolError::failed(
            "the configuration was not saved to flash",
        ));
    }
    if changed > 0 {
        println!(
            "saved to the bridge's flash{}",
            if restart > 0 {
                format!("; {restart} field(s) apply after a restart (power-cycle or press RESET)")
            } else {
                String::new()
            }
        );
    } else {
        println!("nothing changed");
    }
    Ok(())
}

/// Splits `changes` into groups whose `set_config` line fits the bridge's
/// line length (and its 12 fields a line).
fn line_groups(changes: &[(FieldId, Parsed)]) -> Vec<Vec<(FieldId, Parsed)>> {
    let mut groups: Vec<Vec<(FieldId, Parsed)>> = Vec::new();
    let mut cur: Vec<(FieldId, Parsed)> = Vec::new();
    let fits = |g: &[(FieldId, Parsed)]| {
        let mut map = Map::new();
        for (id, p) in g {
            map.insert(id.name().to_string(), json!(wire_text(*id, p)));
        }
        let line = json!({"cmd": "set_config", "req": u32::MAX, "fields": Value::Object(map)});
        line.to_string().len() <= LINE_MAX
            && g.len() <= tinybms_firmware::host_link::command::MAX_SET_CONFIG
    };
    for ch in changes {
        cur.push(ch.clone());
        if !fits(&cur) && cur.len() > 1 {
            let last = cur.pop();
            groups.push(std::mem::take(&mut cur));
            cur.extend(last);
        }
    }
    if !cur.is_empty() {
        groups.push(cur);
    }
    groups
}

fn read_only_hint(e: ToolError) -> ToolError {
    if e.message.contains("read_only") || e.message.contains("read-only") {
        super::client::read_only_refusal()
    } else {
        e
    }
}

/// `--reset`: every field back to its default; says which changed (`fields`:
/// the bridge's record before).
pub fn reset(c: &mut Client, fields: &[Shown]) -> ToolResult<()> {
    let v = c
        .command(json!({"cmd": "reset_config"}), SAVE_TIMEOUT, |l| match l {
            HostLine::ConfigDone(d) => Some(d),
            _ => None,
        })
        .map_err(read_only_hint)?;
    if v.saved == Some(false) {
        return Err(ToolError::failed(format!(
            "the defaults were not saved to flash: {}",
            v.detail.as_deref().unwrap_or("?")
        )));
    }
    let was: Vec<String> = fields
        .iter()
        .filter(|f| f.value != f.default)
        .map(|f| {
            let shown = if f.secret {
                "set".to_string()
            } else {
                with_unit(&f.value, &f.unit)
            };
            format!(
                "  {} = {} (was {shown})",
                f.name,
                with_unit(&f.default, &f.unit)
            )
        })
        .collect();
    match v.changed {
        0 => println!("every field was at its default already: nothing changed"),
        1 => println!("1 field back to its default:"),
        n => println!("{n} fields back to their defaults:"),
    }
    for l in &was {
        println!("{l}");
    }
    if v.restart_needed > 0 {
        println!(
            "{} of them apply{} at the next restart",
            v.restart_needed,
            if v.restart_needed == 1 { "s" } else { "" }
        );
    }
    Ok(())
}

/// The file `--save` writes: every field but the secrets.
pub fn file_text(fields: &[Shown], header: &str) -> String {
    let mut out = format!(
        "# {header}\n# The ESP32 bridge's configuration: `name = value` per line, in the units \
         `tinybms config` prints.\n# `tinybms config PORT --load FILE` writes it back. Secrets \
         are never saved here.\n"
    );
    // (name, value, comment) per field; secrets by name only.
    let mut rows: Vec<(&str, Option<(String, String)>)> = Vec::new();
    for f in fields {
        let name = f.name.as_str();
        let Some(id) = FieldId::from_name(name) else {
            continue;
        };
        let field = id.field();
        if field.is_secret() {
            rows.push((name, None));
            continue;
        }
        let value = match field.kind {
            Kind::Text { .. } => json!(f.value).to_string(),
            _ => with_unit(&f.value, &f.unit),
        };
        let comment = format!("{}; default {}", f.range, with_unit(&f.default, &f.unit));
        rows.push((name, Some((value, comment))));
    }
    // One width for the names and one for the values: the comments line up.
    let name_w = rows
        .iter()
        .map(|(n, _)| n.chars().count())
        .max()
        .unwrap_or(0);
    let value_w = rows
        .iter()
        .filter_map(|(_, v)| v.as_ref().map(|(v, _)| v.chars().count()))
        .max()
        .unwrap_or(0);
    for (name, row) in rows {
        match row {
            None => {
                let value = fields
                    .iter()
                    .find(|f| f.name == name)
                    .map_or("", |f| f.value.as_str());
                let _ = writeln!(out, "# {name}: {value} (secrets are not saved)");
            }
            Some((value, comment)) => {
                let _ = writeln!(out, "{name:<name_w$} = {value:<value_w$} # {comment}");
            }
        }
    }
    out
}

/// Reads a configuration file (see the module documentation): the fields it
/// sets, in order; an error names the line.
pub fn parse_file(text: &str) -> Result<Vec<(FieldId, Parsed)>, String> {
    let mut out: Vec<(FieldId, Parsed)> = Vec::new();
    let mut seen: BTreeMap<&str, usize> = BTreeMap::new();
    for (n, raw) in text.lines().enumerate() {
        let n = n + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let (name, rest) = line
            .split_once('=')
            .ok_or_else(|| format!("line {n}: want `name = value`: {raw}"))?;
        let name = name.trim();
        let rest = rest.trim();
        let text = if rest.starts_with('"') {
            // A JSON string, then maybe a comment.
            let mut de = serde_json::Deserializer::from_str(rest).into_iter::<String>();
            match de.next() {
                Some(Ok(s)) => {
                    let after = rest[de.byte_offset()..].trim();
                    if !after.is_empty() && !after.starts_with('#') {
                        return Err(format!("line {n}: text after the quoted value: {raw}"));
                    }
                    s
                }
                _ => {
                    return Err(format!(
                        "line {n}: an unterminated or invalid quoted value: {raw}"
                    ))
                }
            }
        } else {
            rest.split('#').next().unwrap_or("").trim().to_string()
        };
        let id = field_named(name).map_err(|e| format!("line {n}: {}", e.message))?;
        if let Some(first) = seen.insert(id.name(), n) {
            return Err(format!(
                "line {n}: `{}` is already set on line {first}: give each field once",
                id.name()
            ));
        }
        let p = value::parse(id.field(), &text).map_err(|e| {
            let mut range = Line::new();
            value::write_range(id.field(), &mut range);
            format!(
                "line {n}: {} = {text}: {} (it takes {})",
                id.name(),
                e.detail,
                range.as_str()
            )
        })?;
        out.push((id, p));
    }
    Ok(out)
}

/// The changes a file makes to the bridge's record: only the fields that differ.
pub fn diff(current: &Config, wanted: &[(FieldId, Parsed)]) -> Vec<(FieldId, Parsed)> {
    wanted
        .iter()
        .filter(|(id, p)| current.get(*id) != p.as_value() || id.field().is_secret())
        .cloned()
        .collect()
}

/// A refused `get config` as an error (an older bridge firmware has none).
pub fn fetch_error(e: ToolError) -> ToolError {
    if e.message.contains("invalid_value") {
        ToolError::failed(
            "the bridge does not know `get config`: its firmware is older than this tool \
             (flash the current image, docs/flashing.md)",
        )
    } else {
        e
    }
}

/// `error` lines of set_config turned into tool errors (kept for callers that
/// parse answers themselves).
pub fn error_of(e: &Error<Read>) -> ToolError {
    read_only_hint(protocol_error(e))
}

/// The WPA2 pre-shared key of `passphrase` on the network `ssid`
/// (IEEE 802.11i: PBKDF2-HMAC-SHA1, 4096 rounds, the SSID as salt, 32 bytes)
/// as the 64 hex digits the bridge stores and hands to the Wi-Fi driver, so
/// the chip never derives it.
pub fn wpa2_psk(ssid: &str, passphrase: &str) -> Result<String, String> {
    if ssid.is_empty() || ssid.len() > 32 {
        return Err(format!(
            "an SSID has 1 to 32 bytes (`{ssid}` has {})",
            ssid.len()
        ));
    }
    let n = passphrase.chars().count();
    if !(8..=63).contains(&n) || !passphrase.chars().all(|c| (' '..='~').contains(&c)) {
        return Err(format!(
            "a WPA2 passphrase has 8 to 63 printable ASCII characters (this one has {n}{})",
            if passphrase.is_ascii() {
                ""
            } else {
                ", not all ASCII"
            }
        ));
    }
    let mut key = [0u8; 32];
    pbkdf2::pbkdf2_hmac::<sha1::Sha1>(passphrase.as_bytes(), ssid.as_bytes(), 4096, &mut key);
    Ok(key.iter().map(|b| format!("{b:02x}")).collect())
}

/// A secret typed by the user: without echo at a terminal, else one line of
/// standard input (scripts, tests). `None` when nothing was given.
pub fn ask_secret(prompt: &str) -> ToolResult<String> {
    use std::io::{BufRead, IsTerminal};
    let text = if std::io::stdin().is_terminal() {
        rpassword::prompt_password(prompt)
            .map_err(|e| ToolError::failed(format!("reading the answer: {e}")))?
    } else {
        let mut line = String::new();
        let n = std::io::stdin()
            .lock()
            .read_line(&mut line)
            .map_err(|e| ToolError::failed(format!("reading the answer: {e}")))?;
        if n == 0 {
            // No terminal and nothing on standard input: never an empty
            // secret set without a word.
            return Err(ToolError::failed(format!(
                "{}nothing to read: standard input is not a terminal and gave no line \
                 (give it one: `echo 'SECRET' | tinybms …`); nothing changed",
                prompt.trim_end_matches(": ").trim_end().to_string() + ": "
            )));
        }
        line.trim_end_matches(['\n', '\r']).to_string()
    };
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::wpa2_psk;

    #[test]
    fn wpa2_keys_are_the_ieee_802_11i_test_vectors() {
        assert_eq!(
            wpa2_psk("IEEE", "password").unwrap(),
            "f42c6fc52df0ebef9ebb4b90b38a5f902e83fe1b135a70e23aed762e9710a12e"
        );
        assert_eq!(
            wpa2_psk("ThisIsASSID", "ThisIsAPassword").unwrap(),
            "0dc0d6eb90555ed6419756b9a15ec3e3209b63df707dd508d14581f8982721af"
        );
        assert!(wpa2_psk("IEEE", "short").is_err());
        assert!(wpa2_psk("IEEE", &"x".repeat(64)).is_err());
        assert!(wpa2_psk("", "password").is_err());
    }
}
