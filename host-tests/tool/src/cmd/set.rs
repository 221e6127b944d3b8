//! `tinybms set`: Settings given on the command line, each verified.

use protocol_core::settings::{ChemistryCheck, SettingId};

use crate::cli::Conn;
use crate::{confirm_restart, connect_ready, settings, write_settings, ToolError, ToolResult};
use tinybms_rules::profile::snake_name;

/// Runs `tinybms set`.
pub fn run(
    conn: Conn,
    assignments: Vec<String>,
    raw: bool,
    dry_run: bool,
    yes: bool,
    chemistry: ChemistryCheck,
) -> ToolResult<()> {
    let mut items: Vec<(SettingId, i32)> = Vec::new();
    let mut bare: Vec<SettingId> = Vec::new();
    for a in &assignments {
        let (id, value, was_bare) = settings::parse_set_arg(a, raw).map_err(ToolError::usage)?;
        // One value per setting: which one is meant is not clear.
        if items.iter().any(|(i, _)| *i == id) {
            return Err(ToolError::usage(format!(
                "`{}` is given twice: give each setting once",
                snake_name(id)
            )));
        }
        if was_bare {
            bare.push(id);
        }
        items.push((id, value));
    }
    let mut c = connect_ready(&conn)?;
    let current = c.settings()?;
    let chem = settings::chemistry_of(&current, &items, chemistry);
    settings::check_all(&current, &items, Some(&bare), chem.as_ref()).map_err(ToolError::failed)?;
    if dry_run {
        let changes = settings::diff(&current, &items);
        print!(
            "{}",
            settings::render_diff(&changes, items.len().saturating_sub(changes.len()))
        );
        println!("dry run: every value checked, nothing written");
        return Ok(());
    }
    confirm_restart(yes, &items)?;
    write_settings(&mut c, &items, chemistry)
}
