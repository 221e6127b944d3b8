//! `tinybms events`: The BMS's event log, with wall-clock times from its lifetime counter.

use serde_json::{json, Value};

use crate::tool::cli::Conn;
use crate::tool::{connect_ready, monitor, ToolResult};

/// Runs `tinybms events`.
pub fn run(conn: Conn, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(&conn)?;
    let events = c.get("events")?;
    // The BMS's clock: its lifetime counter now, against ours.
    let lifetime = c
        .get_one("snapshot")
        .ok()
        .and_then(|t| t["lifetime_s"].as_u64());
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0);
    let wall = |ts: u64| lifetime.map(|l| monitor::utc(now - (l as i64 - ts as i64), 0));
    let list: Vec<&Value> = events.iter().filter(|e| e["type"] == "event").collect();
    if json {
        for e in list {
            let mut e = e.clone();
            let w = wall(e["timestamp_s"].as_u64().unwrap_or(0));
            if let (Some(m), Some(w)) = (e.as_object_mut(), w) {
                m.insert("time".into(), json!(w));
            }
            println!("{e}");
        }
        return Ok(());
    }
    if list.is_empty() {
        println!("no events");
    }
    for e in list {
        let t = e["timestamp_s"].as_u64().unwrap_or(0);
        let when = wall(t)
            .map(|w| format!("{}  ", &w[..19].replace('T', " ")))
            .unwrap_or_default();
        println!(
            "{when}BMS {:>3}d {:02}:{:02}:{:02}  0x{:02X}  {:<8} {}",
            t / 86_400,
            t / 3600 % 24,
            t / 60 % 60,
            t % 60,
            e["id"].as_u64().unwrap_or(0),
            e["severity"].as_str().unwrap_or("?"),
            e["name"].as_str().unwrap_or("?")
        );
    }
    if lifetime.is_some() {
        println!(
            "(times from the BMS's lifetime counter, which stops while the BMS is off: \
             events before a power-down are earlier than shown)"
        );
    }
    Ok(())
}
