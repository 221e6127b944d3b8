//! `tinybms stats`, `tinybms version`: one block of the BMS's, as text or JSON.

use serde_json::Value;

use crate::tool::cli::Conn;
use crate::tool::{connect_ready, ToolResult};

pub fn show_one(conn: &Conn, what: &str, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(conn)?;
    let v = c.get_one(what)?;
    if json {
        let mut v = v;
        if let Some(m) = v.as_object_mut() {
            m.shift_remove("req");
        }
        println!("{v}");
    } else if what == "statistics" {
        // The BMS's clock now (its lifetime counter), to say when the
        // statistics were cleared.
        let now_s = c
            .get_one("snapshot")
            .ok()
            .and_then(|t| t["lifetime_s"].as_u64());
        print!("{}", statistics_text(&v, now_s));
    } else {
        print_fields(&v);
    }
    Ok(())
}

/// The words and unit of each member of a `statistics` line.
const STATISTICS: &[(&str, &str, &str)] = &[
    ("total_distance_km", "total distance", "km"),
    ("max_discharge_current_a", "highest discharge current", "A"),
    ("max_charge_current_a", "highest charge current", "A"),
    (
        "max_cell_voltage_difference_v",
        "largest cell voltage difference",
        "V",
    ),
    ("under_voltage_count", "under-voltage protections", ""),
    ("over_voltage_count", "over-voltage protections", ""),
    (
        "discharge_over_current_count",
        "discharge over-current protections",
        "",
    ),
    (
        "charge_over_current_count",
        "charge over-current protections",
        "",
    ),
    ("over_heat_count", "over-heat protections", ""),
    ("charging_count", "charges", ""),
    ("full_charge_count", "full charges", ""),
    ("min_pack_temperature_c", "lowest pack temperature", "°C"),
    ("max_pack_temperature_c", "highest pack temperature", "°C"),
    ("last_reset", "last reset", ""),
    ("last_wakeup", "last wake-up", ""),
];

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
/// counter), with the BMS's timestamp.
pub fn statistics_text(v: &Value, now_s: Option<u64>) -> String {
    let mut rows: Vec<(String, String)> = Vec::new();
    for (key, words, unit) in STATISTICS {
        let x = &v[*key];
        if x.is_null() {
            continue;
        }
        let text = match (x, *key) {
            (Value::String(s), "last_reset") => reason_words(s, true),
            (Value::String(s), "last_wakeup") => reason_words(s, false),
            (Value::String(s), _) => s.clone(),
            (other, _) => other.to_string(),
        };
        let text = if unit.is_empty() {
            text
        } else {
            format!("{text} {unit}")
        };
        rows.push((words.to_string(), text));
    }
    if let Some(at) = v["stats_cleared_at_s"].as_u64() {
        let text = match now_s {
            Some(now) if now >= at => format!(
                "{} ago (BMS time {at} s; now {now} s)",
                duration_words(now - at)
            ),
            Some(now) => format!("at BMS time {at} s (ahead of its clock now, {now} s)"),
            None => format!("at BMS time {at} s"),
        };
        rows.push(("statistics cleared".into(), text));
    }
    // Members this tool does not know yet, as they come.
    if let Some(m) = v.as_object() {
        for (k, x) in m {
            let known = STATISTICS.iter().any(|(key, _, _)| key == k);
            if known || ["type", "req", "stats_cleared_at_s"].contains(&k.as_str()) {
                continue;
            }
            let text = match x {
                Value::String(s) => s.clone(),
                other => other.to_string(),
            };
            rows.push((k.clone(), text));
        }
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
fn store_text(v: &Value) -> String {
    let kib = |b: u64| {
        if b.is_multiple_of(1024) {
            format!("{} KiB", b / 1024)
        } else {
            format!("{b} bytes")
        }
    };
    let mut out = match v["flash_kib"].as_u64() {
        Some(0) => "flash size not reported".to_string(),
        Some(k) => format!("flash {k} KiB"),
        None => "flash ?".to_string(),
    };
    match (
        v["partition_offset"].as_u64(),
        v["partition_bytes"].as_u64(),
    ) {
        (Some(at), Some(len)) => {
            out.push_str(&format!(", nvs partition at {at:#x}, {}", kib(len)));
        }
        _ => out.push_str(", no nvs partition"),
    }
    if let Some(n) = v["needs_bytes"].as_u64() {
        out.push_str(&format!(" (the store needs {})", kib(n)));
    }
    if let Some(p) = v["problem"].as_str() {
        out.push_str(&format!(": {p}; the configuration lives in RAM only"));
    }
    out
}

/// `tinybms version`: the BMS's version and, through a bridge, the bridge's
/// own (from its `hello`: firmware, build, chip, board, what is built in,
/// the configuration record's version, where its store lives, where its MQTT
/// connection stands).
pub fn version(conn: &Conn, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(conn)?;
    let mut v = c.get_one("version")?;
    let bridge = (c.mode == crate::tool::transport::Mode::Bridge).then(|| {
        let h = &c.hello;
        let mut b = serde_json::Map::new();
        for k in [
            "firmware",
            "build",
            "chip",
            "board",
            "features",
            "record_version",
            "store",
            "mqtt",
        ] {
            if !h[k].is_null() {
                b.insert(k.to_string(), h[k].clone());
            }
        }
        b
    });
    if let Some(m) = v.as_object_mut() {
        m.shift_remove("req");
    }
    if json {
        if let (Some(m), Some(b)) = (v.as_object_mut(), bridge) {
            m.insert("bridge".into(), Value::Object(b));
        }
        println!("{v}");
        return Ok(());
    }
    if let Some(b) = bridge {
        println!("the bridge (its own firmware):");
        let w = b.keys().map(String::len).max().unwrap_or(0);
        for (k, x) in &b {
            let text = match x {
                Value::String(s) if k == "mqtt" => mqtt_text(s),
                Value::Object(_) if k == "store" => store_text(x),
                Value::String(s) => s.clone(),
                Value::Array(a) => a
                    .iter()
                    .filter_map(|f| f.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
                other => other.to_string(),
            };
            println!("  {k:<w$}  {text}");
        }
        println!("the BMS:");
    }
    print_fields(&v);
    Ok(())
}

pub fn print_fields(v: &Value) {
    if let Some(m) = v.as_object() {
        let w = m.keys().map(String::len).max().unwrap_or(0);
        for (k, x) in m {
            if k == "type" || k == "req" {
                continue;
            }
            let text = match x {
                Value::String(s) => s.clone(),
                other => other.to_string(),
            };
            println!("{k:<w$}  {text}");
        }
    }
}
