//! `tinybms apply`: A settings profile: the difference first, then only what differs, each verified.

use std::path::PathBuf;

use protocol_core::settings::{ChemistryCheck, SettingId};

use crate::cli::Conn;
use crate::{
    confirm_restart, connect_ready, read_profile, settings, write_settings, ToolError, ToolResult,
};
use tinybms_rules::profile::parse_profile;

/// Runs `tinybms apply`.
pub fn run(
    conn: Conn,
    file: PathBuf,
    dry_run: bool,
    yes: bool,
    chemistry: ChemistryCheck,
) -> ToolResult<()> {
    let text = read_profile(&file, &conn.port)?;
    let wanted =
        parse_profile(&text).map_err(|e| ToolError::failed(format!("{}: {e}", file.display())))?;
    let mut c = connect_ready(&conn)?;
    let current = c.settings()?;
    let chem = settings::chemistry_of(&current, &wanted, chemistry);
    settings::check_all(&current, &wanted, None, chem.as_ref()).map_err(ToolError::failed)?;
    let changes = settings::diff(&current, &wanted);
    let unchanged = wanted.len().saturating_sub(changes.len());
    println!("{}: {} settings", file.display(), wanted.len());
    print!("{}", settings::render_diff(&changes, unchanged));
    if dry_run {
        println!("dry run: every value checked, nothing written");
        return Ok(());
    }
    if changes.is_empty() {
        return Ok(());
    }
    let items: Vec<(SettingId, i32)> = changes.iter().map(|ch| (ch.id, ch.to as i32)).collect();
    confirm_restart(yes, &items)?;
    write_settings(&mut c, &items, chemistry)
}
