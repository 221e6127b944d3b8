//! `tinybms reset`, `clear-events`, `clear-stats`: asked first.

use std::time::Duration;

use serde_json::json;

use crate::tool::cli::Conn;
use crate::tool::{confirm, connect_ready, ToolError, ToolResult};

pub fn clear_or_reset(conn: &Conn, yes: bool, what: &str) -> ToolResult<()> {
    let (question, cmd, done) = match what {
        "reset" => ("Restart the BMS", json!({"cmd": "reset"}), "reset_done"),
        "events" => (
            "Clear the BMS's event log",
            json!({"cmd": "clear", "what": "events"}),
            "cleared",
        ),
        _ => (
            "Clear the BMS's statistics",
            json!({"cmd": "clear", "what": "statistics"}),
            "cleared",
        ),
    };
    if !yes && !confirm(question)? {
        return Err(ToolError::failed("not confirmed: nothing done"));
    }
    let mut c = connect_ready(conn)?;
    let v = c.command(cmd, done, Duration::from_secs(30))?;
    let ok = v["ok"] == true || v["confirmed"] == true;
    match (done, ok) {
        ("reset_done", true) => println!("the BMS restarted (confirmed by its reset reason)"),
        ("reset_done", false) => {
            println!("reset sent, but the BMS's reset reason does not confirm a software reset")
        }
        (_, true) => println!("cleared"),
        (_, false) => return Err(ToolError::failed("the BMS did not acknowledge the clear")),
    }
    Ok(())
}
