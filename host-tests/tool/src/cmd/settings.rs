//! `tinybms settings`: The BMS's settings, by group, and their profile file.

use std::path::PathBuf;

use crate::cli::Conn;
use crate::client::setting_lines;
use crate::transport::Mode;
use crate::{connect_ready, monitor, serial_suffix, settings, ToolError, ToolResult};

/// Runs `tinybms settings`.
pub fn run(conn: Conn, save: Option<PathBuf>, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(&conn)?;
    let got = c.get("settings")?;
    if json {
        // As the bridge wrote them.
        for r in &got {
            println!("{}", r.raw);
        }
        return Ok(());
    }
    let lines = setting_lines(&got);
    print!("{}", settings::render_groups(&lines));
    if let Some(path) = &save {
        let serial = serial_suffix(&mut c);
        let header = format!(
            "TinyBMS settings saved by tinybms {} from {} ({}) at {}{}",
            env!("CARGO_PKG_VERSION"),
            c.port,
            match c.mode {
                Mode::Bridge => "through the bridge",
                Mode::Direct => "direct",
            },
            monitor::utc_now(),
            serial
        );
        let (text, saved) = settings::profile_text(&lines, &header);
        std::fs::write(path, text)
            .map_err(|e| ToolError::failed(format!("cannot write `{}`: {e}", path.display())))?;
        let skipped = lines.len().saturating_sub(saved);
        println!(
            "saved {saved} settings to {}{}",
            path.display(),
            if skipped > 0 {
                format!(" ({skipped} left out: not read, or write-only)")
            } else {
                String::new()
            }
        );
    }
    Ok(())
}
