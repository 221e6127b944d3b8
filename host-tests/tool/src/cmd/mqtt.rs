//! `tinybms mqtt`: The MQTT broker the bridge publishes to.

use crate::cli::Conn;
use crate::{config, connect, ToolResult};

/// Runs `tinybms mqtt`.
pub fn run(conn: Conn, host: String, tcp_port: u16, user: Option<String>) -> ToolResult<()> {
    // The bridge first: an image without Wi-Fi is said so before a password
    // is asked for nothing.
    let mut c = connect(&conn)?;
    config::require_bridge(&c)?;
    config::require_wifi(&c, "mqtt")?;
    let mut changes = vec![
        config::check_assignment("mqtt_host", &host)?,
        config::check_assignment("mqtt_port", &tcp_port.to_string())?,
    ];
    match &user {
        Some(user) => {
            let pass =
                config::ask_secret(&format!("Password of `{user}` at {host} (not shown): "))?;
            changes.push(config::check_assignment("mqtt_user", user)?);
            changes.push(config::check_assignment("mqtt_password", &pass)?);
        }
        None => {
            changes.push(config::check_assignment("mqtt_user", "")?);
            changes.push(config::check_assignment("mqtt_password", "")?);
        }
    }
    let (fields, _) = config::fetch(&mut c).map_err(config::fetch_error)?;
    config::check_locally(&config::record_of(&fields), &changes)?;
    config::apply(&mut c, &changes)?;
    println!("MQTT: the bridge publishes to {host} after its next restart");
    Ok(())
}
