//! `tinybms events`: The BMS's event log, with wall-clock times from its lifetime counter.

use serde_json::json;
use tinybms_firmware::host_link::schema::HostLine;

use crate::cli::Conn;
use crate::{connect_ready, monitor, ToolResult};

/// Runs `tinybms events`.
pub fn run(conn: Conn, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(&conn)?;
    let events = c.get("events")?;
    // The BMS's clock: its lifetime counter now, against ours.
    let lifetime = c
        .snapshot()
        .ok()
        .and_then(|t| t.snapshot.map(|s| u64::from(s.lifetime_s)));
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0);
    let wall = |ts: u64| lifetime.map(|l| monitor::utc(now - (l as i64 - ts as i64), 0));
    // Each `event` line, and the JSON it came as.
    let list: Vec<_> = events
        .iter()
        .filter_map(|r| match &r.line {
            HostLine::Event(e) => Some((e, &r.raw)),
            _ => None,
        })
        .collect();
    if json {
        for (e, raw) in list {
            let mut raw = raw.clone();
            let w = wall(u64::from(e.timestamp_s));
            if let (Some(m), Some(w)) = (raw.as_object_mut(), w) {
                m.insert("time".into(), json!(w));
            }
            println!("{raw}");
        }
        return Ok(());
    }
    if list.is_empty() {
        println!("no events");
    }
    for (e, _) in list {
        let t = u64::from(e.timestamp_s);
        let when = wall(t)
            .map(|w| format!("{}  ", &w[..19].replace('T', " ")))
            .unwrap_or_default();
        println!(
            "{when}BMS {:>3}d {:02}:{:02}:{:02}  0x{:02X}  {:<8} {}",
            t / 86_400,
            t / 3600 % 24,
            t / 60 % 60,
            t % 60,
            e.id,
            e.severity,
            e.name
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
