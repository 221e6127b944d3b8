//! `tinybms stats`, `tinybms version`: one block of the BMS's, as text or JSON.

use serde_json::{json, Map, Value};
use tinybms_firmware::host_link::schema::{Hello, HostLine, Read, StatisticsLine, Store};

use crate::cli::Conn;
use crate::client::Received;
use crate::picture::json_number;
use crate::{connect_ready, ToolResult};

pub fn show_one(conn: &Conn, what: &str, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(conn)?;
    // Read by the bridge after it is ready: may take a moment more.
    let got = c.get_one_read(what, conn.timeout)?;
    if json {
        println!("{}", got.raw_without_req());
    } else if let HostLine::Statistics(s) = &got.line {
        // The BMS's clock now (its lifetime counter), to say when the
        // statistics were cleared.
        let now_s = c
            .snapshot()
            .ok()
            .and_then(|t| t.snapshot.map(|s| u64::from(s.lifetime_s)));
        print!("{}", statistics_text(s, &got.raw, now_s));
    } else {
        print_fields(&got);
    }
    Ok(())
}

/// The members of `raw` (a line as it came) that its type does not have (a
/// newer bridge's), as they came; `typed`: the line as read, written back.
fn unknown_members(typed: &Value, raw: &Value) -> Vec<(String, Value)> {
    let known =
        |k: &str| k == "type" || k == "req" || typed.as_object().is_some_and(|m| m.contains_key(k));
    raw.as_object()
        .into_iter()
        .flatten()
        .filter(|(k, _)| !known(k))
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect()
}

/// The members of a line beside its type and `req`, in the order the bridge
/// writes them: the ones its type has, as read (`typed`: written back), then
/// the ones it does not have, as they came in `raw`.
fn members(typed: Value, raw: &Value) -> Vec<(String, Value)> {
    let mut out: Vec<(String, Value)> = typed
        .as_object()
        .into_iter()
        .flatten()
        .filter(|(k, _)| *k != "type" && *k != "req")
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    out.extend(unknown_members(&typed, raw));
    out
}

/// A member's value as text: text as it is, anything else as JSON.
fn value_text(x: &Value) -> String {
    match x {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// A duration in whole units, the two largest: `23 d 3 h`, `3 h 12 min`,
/// `12 min 5 s`, `45 s`.
pub fn duration_words(s: u64) -> String {
    let (d, h, m, sec) = (s / 86_400, s / 3600 % 24, s / 60 % 60, s % 60);
    if d > 0 {
        format!("{d} d {h} h")
    } else if h > 0 {
        format!("{h} h {m} min")
    } else if m > 0 {
        format!("{m} min {sec} s")
    } else {
        format!("{sec} s")
    }
}

/// The BMS's own name of a reset or wake-up reason from its key in the
/// `statistics` line (`por_pdr_reset` → `POR/PDR reset`).
fn reason_words(key: &str, reset: bool) -> String {
    use protocol_core::events::{ResetReason, WakeupReason};
    let snake = |n: &str| {
        let mut out = String::new();
        for c in n.chars() {
            if c.is_ascii_alphanumeric() {
                out.push(c.to_ascii_lowercase());
            } else if !out.is_empty() && !out.ends_with('_') {
                out.push('_');
            }
        }
        out.trim_end_matches('_').to_string()
    };
    (0..=u8::MAX)
        .map(|raw| {
            if reset {
                ResetReason::from_raw(raw).name()
            } else {
                WakeupReason::from_raw(raw).name()
            }
        })
        .find(|n| !n.is_empty() && snake(n) == key)
        .map_or_else(|| key.replace('_', " "), str::to_string)
}

/// `tinybms stats` as text: each statistic in words with its unit; when they
/// were cleared as a time ago by the BMS's clock `now_s` (its lifetime
/// counter), with the BMS's timestamp. `raw`: the line as it came, for the
/// members this tool does not know yet.
pub fn statistics_text(v: &StatisticsLine<Read>, raw: &Value, now_s: Option<u64>) -> String {
    let num = |x: Option<f64>| x.map(json_number);
    let count = |n: u16| Some(n.to_string());
    // Each statistic: its words, its value (none: not known), its unit.
    let known: [(&str, Option<String>, &str); 15] = [
        ("total distance", num(v.total_distance_km), "km"),
        (
            "highest discharge current",
            num(v.max_discharge_current_a),
            "A",
        ),
        ("highest charge current", num(v.max_charge_current_a), "A"),
        (
            "largest cell voltage difference",
            num(v.max_cell_voltage_difference_v),
            "V",
        ),
        (
            "under-voltage protections",
            count(v.under_voltage_count),
            "",
        ),
        ("over-voltage protections", count(v.over_voltage_count), ""),
        (
            "discharge over-current protections",
            count(v.discharge_over_current_count),
            "",
        ),
        (
            "charge over-current protections",
            count(v.charge_over_current_count),
            "",
        ),
        ("over-heat protections", count(v.over_heat_count), ""),
        ("charges", count(v.charging_count), ""),
        ("full charges", count(v.full_charge_count), ""),
        (
            "lowest pack temperature",
            Some(v.min_pack_temperature_c.to_string()),
            "°C",
        ),
        (
            "highest pack temperature",
            Some(v.max_pack_temperature_c.to_string()),
            "°C",
        ),
        ("last reset", Some(reason_words(&v.last_reset, true)), ""),
        (
            "last wake-up",
            Some(reason_words(&v.last_wakeup, false)),
            "",
        ),
    ];
    let mut rows: Vec<(String, String)> = Vec::new();
    for (words, text, unit) in known {
        let Some(text) = text else {
            continue;
        };
        let text = if unit.is_empty() {
            text
        } else {
            format!("{text} {unit}")
        };
        rows.push((words.to_string(), text));
    }
    let at = u64::from(v.stats_cleared_at_s);
    let text = match now_s {
        Some(now) if now >= at => format!(
            "{} ago (BMS time {at} s; now {now} s)",
            duration_words(now - at)
        ),
        Some(now) => format!("at BMS time {at} s (ahead of its clock now, {now} s)"),
        None => format!("at BMS time {at} s"),
    };
    rows.push(("statistics cleared".into(), text));
    // Members this tool does not know yet, as they come.
    let typed = serde_json::to_value(v).unwrap_or(Value::Null);
    for (k, x) in unknown_members(&typed, raw) {
        rows.push((k, value_text(&x)));
    }
    let w = rows
        .iter()
        .map(|(k, _)| k.chars().count())
        .max()
        .unwrap_or(0);
    let mut out = String::new();
    for (k, text) in rows {
        out.push_str(&format!("{k:<w$}  {text}\n"));
    }
    out
}

/// The MQTT state of `hello` in words.
fn mqtt_text(key: &str) -> String {
    use tinybms_firmware::mqtt::MqttState as S;
    match S::from_key(key) {
        Some(S::Connected | S::Held) => "connected to the broker".into(),
        Some(S::WaitingForBms) => "waiting for the BMS's serial number".into(),
        Some(S::Reconnecting) => "connection lost, reconnecting (`tinybms log` says why)".into(),
        Some(S::CannotConnect) => "cannot connect (`tinybms log` says why)".into(),
        Some(S::ClientIdTaken) => "another client uses this bridge's client id: the broker \
             drops one for the other; give each bridge its own hostname \
             (`tinybms config PORT hostname=…`)"
            .into(),
        None => key.to_string(),
    }
}

/// Where the bridge's configuration store lives (`hello`'s `store`), in
/// words: `flash 4096 KiB, nvs partition at 0x9000, 24 KiB (the store needs
/// 8 KiB)`, and why it cannot hold the store when it cannot.
fn store_text(v: &Store<Read>) -> String {
    let kib = |b: u64| {
        if b.is_multiple_of(1024) {
            format!("{} KiB", b / 1024)
        } else {
            format!("{b} bytes")
        }
    };
    let mut out = match v.flash_kib {
        0 => "flash size not reported".to_string(),
        k => format!("flash {k} KiB"),
    };
    match (v.partition_offset, v.partition_bytes) {
        (Some(at), Some(len)) => {
            out.push_str(&format!(
                ", nvs partition at {at:#x}, {}",
                kib(u64::from(len))
            ));
        }
        _ => out.push_str(", no nvs partition"),
    }
    out.push_str(&format!(
        " (the store needs {})",
        kib(u64::from(v.needs_bytes))
    ));
    if let Some(p) = &v.problem {
        out.push_str(&format!(": {p}; the configuration lives in RAM only"));
    }
    out
}

/// `tinybms version`: the BMS's version and, through a bridge, the bridge's
/// own (from its `hello`: firmware, build, chip, board, what is built in,
/// the configuration record's version, where its store lives, where its
/// radio's start and its MQTT connection stand).
pub fn version(conn: &Conn, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(conn)?;
    let got = c.get_one_read("version", conn.timeout)?;
    let bridge = (c.mode == crate::transport::Mode::Bridge).then(|| bridge_of(&c.hello));
    if json {
        let mut v = got.raw_without_req();
        if let (Some(m), Some(b)) = (v.as_object_mut(), bridge) {
            let b: Map<String, Value> = b.into_iter().map(|(k, x, _)| (k.to_string(), x)).collect();
            m.insert("bridge".into(), Value::Object(b));
        }
        println!("{v}");
        return Ok(());
    }
    if let Some(b) = bridge {
        println!("the bridge (its own firmware):");
        let w = b.iter().map(|(k, _, _)| k.len()).max().unwrap_or(0);
        for (k, _, text) in &b {
            println!("  {k:<w$}  {text}");
        }
        println!("the BMS:");
    }
    print_fields(&got);
    Ok(())
}

/// A board's name and, when it differs, its key (`ESP32-C3 SuperMini
/// (c3-supermini)`): update files and `IMAGE_BOARDS` name boards by key.
fn board_words(name: &str) -> String {
    let key = tinybms_firmware::boards::key_of(name);
    if key == name {
        name.to_string()
    } else {
        format!("{name} ({key})")
    }
}

/// What `version` says of the bridge, from its `hello`: each member's name,
/// its value (`--json`) and its words.
fn bridge_of(h: &Hello<Read>) -> Vec<(&'static str, Value, String)> {
    let mut b = vec![
        ("firmware", json!(h.firmware), h.firmware.clone()),
        ("build", json!(h.build), h.build.clone()),
        ("chip", json!(h.chip), h.chip.clone()),
        // Its name, and the key update files and IMAGE_BOARDS use.
        ("board", json!(h.board), board_words(&h.board)),
        ("features", json!(h.features), h.features.join(", ")),
        (
            "record_version",
            json!(h.record_version),
            h.record_version.to_string(),
        ),
    ];
    if let Some(s) = &h.store {
        let v = serde_json::to_value(s).unwrap_or(Value::Null);
        b.push(("store", v, store_text(s)));
    }
    if let Some(hist) = &h.history {
        let text = if hist == "recording" {
            "kept in flash (tinybms history PORT)".to_string()
        } else {
            format!("off: {hist}")
        };
        b.push(("history", json!(hist), text));
    }
    if let Some(r) = &h.radio {
        let text = tinybms_firmware::wifi::Radio::from_key(r).map_or_else(
            || r.clone(),
            |r| r.text().trim_start_matches("radio: ").to_string(),
        );
        b.push(("radio", json!(r), text));
    }
    if let Some(m) = &h.mqtt {
        b.push(("mqtt", json!(m), mqtt_text(m)));
    }
    if let Some(ip) = h.wifi.as_ref().and_then(|w| w.ip.as_ref()) {
        // Where `tinybms update HOST FILE` finds it on the network.
        b.push((
            "address",
            json!(ip),
            format!("{ip} (tinybms update {ip} FILE)"),
        ));
    }
    if let Some(u) = &h.update {
        let v = serde_json::to_value(u).unwrap_or(Value::Null);
        let key = |k: &Option<String>| k.as_ref().map(|k| k.to_lowercase());
        let keys: Vec<String> = [
            key(&u.built_in_key).map(|k| format!("built in {k}")),
            key(&u.owner_key).map(|k| format!("update_key {k}")),
        ]
        .into_iter()
        .flatten()
        .collect();
        let text = format!(
            "{}, {}; {}",
            u.slot
                .as_deref()
                .unwrap_or("one app slot (reinstall once by cable)"),
            u.trial.replace('_', " "),
            if keys.is_empty() {
                "trusts no key (set update_key over USB)".to_string()
            } else {
                format!("takes files signed by {}", keys.join(", "))
            }
        );
        b.push(("updates", v, text));
    }
    if let Some(r) = &h.rolled_back {
        b.push(("rolled_back", json!(r), r.clone()));
    }
    b
}

/// A `version` line's members, one a line (see `members`).
pub fn print_fields(got: &Received) {
    let typed = match &got.line {
        HostLine::Version(v) => serde_json::to_value(v).unwrap_or(Value::Null),
        _ => Value::Null,
    };
    let rows = members(typed, &got.raw);
    // As wide as the widest member name (the type's own included).
    let w = rows
        .iter()
        .map(|(k, _)| k.len())
        .chain(["type".len()])
        .max()
        .unwrap_or(0);
    for (k, x) in rows {
        println!("{k:<w$}  {}", value_text(&x));
    }
}
