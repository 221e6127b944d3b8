//! `tinybms log`: The bridge's log lines as they come.

use std::time::Duration;

use crate::cli::Conn;
use crate::{connect, monitor, ToolResult};

/// Runs `tinybms log`.
pub fn run(conn: Conn, duration: Option<Duration>) -> ToolResult<()> {
    let mut c = connect(&conn)?;
    monitor::log(&mut c, duration)
}
