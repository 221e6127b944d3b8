//! `tinybms history PORT`: the bridge's own history in flash — its events
//! (`history_event` lines) or, with `--days`, its daily records of the pack
//! (`history_day` lines, read by the firmware's own
//! `tinybms_firmware::history::day`) — as text, CSV or JSON Lines. The tool
//! tells the bridge the date first (`set_time`), so what it records from
//! then on carries it.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde_json::{json, Map, Value};
use tinybms_firmware::history::day::DayRecord;
use tinybms_firmware::history::event::Who;
use tinybms_firmware::host_link::schema::HostLine;

use crate::cli::Conn;
use crate::picture::utc;
use crate::{connect_ready, ToolError, ToolResult};

/// How long the whole listing may take (thousands of lines over a UART).
const LISTING_TIME: Duration = Duration::from_secs(300);

/// Output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Text,
    Csv,
    Json,
}

/// Runs `tinybms history`.
pub fn run(conn: Conn, days: bool, format: &str) -> ToolResult<()> {
    let format = match format {
        "text" => Format::Text,
        "csv" => Format::Csv,
        "json" => Format::Json,
        f => return Err(ToolError::usage(format!("--format {f}: text, csv or json"))),
    };
    let mut c = connect_ready(&conn)?;
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    // The date, for what the bridge records from now on (refused by an older
    // bridge: it records without it).
    let _ = c.command(
        json!({"cmd": "set_time", "at": now}),
        Duration::from_secs(5),
        |l| Some(matches!(l, HostLine::Accepted(_))),
    );
    let lines = c.get_within("history", LISTING_TIME)?;
    let mut rows: Vec<Map<String, Value>> = Vec::new();
    let mut skipped = Vec::new();
    for r in &lines {
        match &r.line {
            HostLine::HistoryEvent(e) if !days => rows.push(event_row(e)),
            HostLine::HistoryDay(d) if days => rows.push(day_row(d.id, &d.record)),
            HostLine::HistorySkipped(s) => skipped.push(format!(
                "skipped: a record of the {} at {:#x}: {}",
                s.ring, s.at, s.reason
            )),
            _ => {}
        }
    }
    print_rows(&rows, format, if days { "days" } else { "events" });
    for s in &skipped {
        eprintln!("{s}");
    }
    Ok(())
}

/// An event as named columns.
fn event_row(
    e: &tinybms_firmware::host_link::schema::HistoryEvent<
        tinybms_firmware::host_link::schema::Read,
    >,
) -> Map<String, Value> {
    let mut m = Map::new();
    m.insert("id".into(), json!(e.id));
    m.insert("boot".into(), json!(e.boot));
    m.insert("uptime_s".into(), json!(e.uptime_ms as f64 / 1000.0));
    m.insert(
        "date".into(),
        e.date.map_or(Value::Null, |d| json!(utc(d as i64, 0))),
    );
    m.insert("event".into(), json!(e.code));
    m.insert("what".into(), json!(words(&e.code, e.a, e.b, &e.text)));
    m
}

/// An event in words.
fn words(code: &str, a: u32, b: u32, text: &str) -> String {
    let who = || Who::from_u32(b).map_or("?", Who::key);
    let sides = |a: u32| match a & 3 {
        1 => "charging",
        2 => "discharging",
        _ => "charging and discharging",
    };
    match code {
        "started" => format!("started {text}, reset reason {}", reset_reason(a)),
        "bms_event" => format!("BMS: {text} (0x{a:02X}, BMS time {b} s)"),
        "bms_offline" => format!("the BMS stopped answering ({a} failures)"),
        "bms_online" => "the BMS answers again".into(),
        "stale" => format!("data stale (newest {:.1} s old)", f64::from(a) / 1000.0),
        "fresh" => format!("fresh data again after {a} s"),
        "stop" => format!("{} stopped: {text}", sides(a)),
        "resume" => format!("{} allowed again", sides(a)),
        "inverter_lost" => "the inverter is no longer heard".into(),
        "inverter_seen" => "the inverter is heard".into(),
        "bus_off" => format!("CAN bus-off (#{a})"),
        "config" => format!("configuration: {text} changed ({})", who()),
        "config_reset" => format!("configuration back to defaults ({})", who()),
        "update_installed" => format!("update {text} installed"),
        "rolled_back" => format!("update {text} rolled back"),
        "update_confirmed" => format!("update {text} confirmed"),
        "wifi_lost" => "Wi-Fi lost".into(),
        "wifi_back" => format!("Wi-Fi back after {a} s"),
        "mqtt_lost" => "MQTT lost".into(),
        "mqtt_back" => format!("MQTT back after {a} s"),
        "dropped" => format!("{a} events not kept (too many too fast)"),
        "time_set" => format!("date set ({})", who()),
        other => format!("{other} {a} {b} {text}"),
    }
}

/// The ESP32-C3/C6 reset reason's name (`SocResetReason`).
fn reset_reason(code: u32) -> &'static str {
    match code {
        0x01 => "power-on",
        0x03 | 0x0C => "software reset (a panic or a restart)",
        0x07 | 0x08 | 0x09 | 0x0B | 0x0D | 0x10 | 0x11 | 0x12 => "watchdog",
        0x0F => "brown-out",
        0x15 => "USB",
        0x17 => "power glitch",
        0xFF => "unknown",
        _ => "other",
    }
}

/// A day record as named columns (its bytes read by the firmware's own
/// decoder; a record it refuses says why).
fn day_row(id: u32, hex: &str) -> Map<String, Value> {
    let bytes: Vec<u8> = (0..hex.len() / 2)
        .filter_map(|i| u8::from_str_radix(hex.get(2 * i..2 * i + 2)?, 16).ok())
        .collect();
    let mut m = Map::new();
    m.insert("id".into(), json!(id));
    match DayRecord::decode(&bytes) {
        Ok(d) => {
            m.extend(day_json(&d));
        }
        Err(e) => {
            m.insert("error".into(), json!(e.reason()));
        }
    }
    m
}

fn cell(v: &Value) -> String {
    match v {
        Value::Null => String::new(),
        Value::String(s) => s.clone(),
        v => v.to_string(),
    }
}

fn print_rows(rows: &[Map<String, Value>], format: Format, what: &str) {
    let mut columns: Vec<&String> = Vec::new();
    for r in rows {
        for k in r.keys() {
            if !columns.contains(&k) {
                columns.push(k);
            }
        }
    }
    match format {
        Format::Json => {
            for r in rows {
                println!("{}", Value::Object(r.clone()));
            }
        }
        Format::Csv => {
            println!(
                "{}",
                columns
                    .iter()
                    .map(|c| c.as_str())
                    .collect::<Vec<_>>()
                    .join(",")
            );
            for r in rows {
                let line: Vec<String> = columns
                    .iter()
                    .map(|c| {
                        let v = cell(r.get(*c).unwrap_or(&Value::Null));
                        if v.contains([',', '"', '\n']) {
                            format!("\"{}\"", v.replace('"', "\"\""))
                        } else {
                            v
                        }
                    })
                    .collect();
                println!("{}", line.join(","));
            }
        }
        Format::Text => {
            if rows.is_empty() {
                println!("no {what} in the history yet");
            }
            for r in rows {
                let line: Vec<String> = columns
                    .iter()
                    .filter_map(|c| {
                        let v = cell(r.get(*c)?);
                        (!v.is_empty()).then(|| format!("{c}={v}"))
                    })
                    .collect();
                println!("{}", line.join("  "));
            }
        }
    }
}

/// A day record's members, named as `tinybms history --days` prints them.
fn day_json(d: &DayRecord) -> Map<String, Value> {
    let mut m = Map::new();
    let mut put = |k: &str, v: Value| {
        m.insert(k.into(), v);
    };
    put("day", json!(d.day));
    put(
        "date",
        if d.date_unix_s == 0 {
            Value::Null
        } else {
            json!(utc(i64::from(d.date_unix_s), 0))
        },
    );
    put("hours", json!(f64::from(d.covered_s) / 3600.0));
    put("cut_by_restart", json!(d.cut_by_restart));
    put("energy_in_kwh", json!(f64::from(d.energy_in_wh) / 1000.0));
    put("energy_out_kwh", json!(f64::from(d.energy_out_wh) / 1000.0));
    put("charge_in_ah", json!(f64::from(d.charge_in_cah) / 100.0));
    put("charge_out_ah", json!(f64::from(d.charge_out_cah) / 100.0));
    put("lowest_cell_v", json!(f64::from(d.lowest_cell_mv) / 1000.0));
    put("lowest_at_h", json!(f64::from(d.lowest_at_s) / 3600.0));
    put(
        "highest_cell_v",
        json!(f64::from(d.highest_cell_mv) / 1000.0),
    );
    put("highest_at_h", json!(f64::from(d.highest_at_s) / 3600.0));
    put("top_spread_mv", json!(d.top_spread_mv));
    put("runner_cell", json!(d.top_cell));
    put("bulk_min", json!(d.stages.bulk));
    put("absorption_min", json!(d.stages.absorption));
    put("balance_held_min", json!(d.stages.balance_held));
    put("float_min", json!(d.stages.float));
    put("other_min", json!(d.stages.other));
    put("cycles", json!(d.cycles));
    put("full_charges", json!(d.full_charges));
    put(
        "max_cell_difference_mv",
        json!(f64::from(d.max_cell_difference_raw) / 10.0),
    );
    put(
        "capacity_ah",
        if d.capacity_cah == 0 {
            Value::Null
        } else {
            json!(f64::from(d.capacity_cah) / 100.0)
        },
    );
    put(
        "capacity_uncertainty_pct",
        if d.capacity_cah == 0 {
            Value::Null
        } else {
            json!(f64::from(d.capacity_uncertainty_permille) / 10.0)
        },
    );
    m
}
