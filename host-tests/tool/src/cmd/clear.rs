//! `tinybms reset`, `clear-events`, `clear-stats`: asked first.

use std::time::Duration;

use serde_json::json;
use tinybms_firmware::host_link::schema::HostLine;

use crate::cli::Conn;
use crate::{confirm, connect_ready, ToolError, ToolResult};

pub fn clear_or_reset(conn: &Conn, yes: bool, what: &str) -> ToolResult<()> {
    let reset = what == "reset";
    let (question, cmd) = match what {
        "reset" => ("Restart the BMS", json!({"cmd": "reset"})),
        "events" => (
            "Clear the BMS's event log",
            json!({"cmd": "clear", "what": "events"}),
        ),
        _ => (
            "Clear the BMS's statistics",
            json!({"cmd": "clear", "what": "statistics"}),
        ),
    };
    if !yes && !confirm(question)? {
        return Err(ToolError::failed("not confirmed: nothing done"));
    }
    let mut c = connect_ready(conn)?;
    // `reset` is answered by `reset_done`, a clear by `cleared`.
    let ok = c.command(cmd, Duration::from_secs(30), |l| match l {
        HostLine::ResetDone(r) if reset => Some(r.confirmed),
        HostLine::Cleared(k) if !reset => Some(k.ok),
        _ => None,
    })?;
    match (reset, ok) {
        (true, true) => println!("the BMS restarted (confirmed by its reset reason)"),
        (true, false) => {
            println!("reset sent, but the BMS's reset reason does not confirm a software reset")
        }
        (false, true) => println!("cleared"),
        (false, false) => return Err(ToolError::failed("the BMS did not acknowledge the clear")),
    }
    Ok(())
}
