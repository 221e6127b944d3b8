//! `tinybms wifi`: The Wi-Fi network: its name and the WPA2 key derived from the passphrase.

use crate::cli::Conn;
use crate::{config, connect, ToolError, ToolResult};

/// Runs `tinybms wifi`.
pub fn run(conn: Conn, ssid: String) -> ToolResult<()> {
    config::check_assignment("wifi_ssid", &ssid)?;
    // The bridge first: an image without Wi-Fi is said so before a
    // passphrase is asked for nothing.
    let mut c = connect(&conn)?;
    config::require_bridge(&c)?;
    config::require_wifi(&c, "wifi")?;
    let pass = config::ask_secret(&format!("Passphrase of `{ssid}` (not shown): "))?;
    let key = config::wpa2_psk(&ssid, &pass).map_err(ToolError::usage)?;
    let changes = vec![
        config::check_assignment("wifi_ssid", &ssid)?,
        config::check_assignment("wifi_key", &key)?,
    ];
    config::apply(&mut c, &changes)?;
    println!("Wi-Fi: the bridge joins `{ssid}` after its next restart (power-cycle or RESET)");
    Ok(())
}
