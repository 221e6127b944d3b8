//! `tinybms stats`, `tinybms version`: one block of the BMS's, as text or JSON.

use serde_json::Value;

use crate::tool::cli::Conn;
use crate::tool::{connect_ready, ToolResult};

pub fn show_one(conn: &Conn, what: &str, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(conn)?;
    let v = c.get_one(what)?;
    if json {
        let mut v = v;
        if let Some(m) = v.as_object_mut() {
            m.shift_remove("req");
        }
        println!("{v}");
    } else {
        print_fields(&v);
    }
    Ok(())
}

/// The MQTT state of `hello` in words.
fn mqtt_text(key: &str) -> String {
    use tinybms_firmware::mqtt::MqttState as S;
    match S::from_key(key) {
        Some(S::Connected | S::Held) => "connected to the broker".into(),
        Some(S::WaitingForBms) => "waiting for the BMS's serial number".into(),
        Some(S::Reconnecting) => "connection lost, reconnecting (`tinybms log` says why)".into(),
        Some(S::CannotConnect) => "cannot connect (`tinybms log` says why)".into(),
        Some(S::ClientIdTaken) => "another client uses this bridge's client id: the broker \
             drops one for the other; give each bridge its own hostname \
             (`tinybms config PORT hostname=…`)"
            .into(),
        None => key.to_string(),
    }
}

/// `tinybms version`: the BMS's version and, through a bridge, the bridge's
/// own (from its `hello`: firmware, build, chip, board, what is built in,
/// the configuration record's version, where its MQTT connection stands).
pub fn version(conn: &Conn, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(conn)?;
    let mut v = c.get_one("version")?;
    let bridge = (c.mode == crate::tool::transport::Mode::Bridge).then(|| {
        let h = &c.hello;
        let mut b = serde_json::Map::new();
        for k in [
            "firmware",
            "build",
            "chip",
            "board",
            "features",
            "record_version",
            "mqtt",
        ] {
            if !h[k].is_null() {
                b.insert(k.to_string(), h[k].clone());
            }
        }
        b
    });
    if let Some(m) = v.as_object_mut() {
        m.shift_remove("req");
    }
    if json {
        if let (Some(m), Some(b)) = (v.as_object_mut(), bridge) {
            m.insert("bridge".into(), Value::Object(b));
        }
        println!("{v}");
        return Ok(());
    }
    if let Some(b) = bridge {
        println!("the bridge (its own firmware):");
        let w = b.keys().map(String::len).max().unwrap_or(0);
        for (k, x) in &b {
            let text = match x {
                Value::String(s) if k == "mqtt" => mqtt_text(s),
                Value::String(s) => s.clone(),
                Value::Array(a) => a
                    .iter()
                    .filter_map(|f| f.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
                other => other.to_string(),
            };
            println!("  {k:<w$}  {text}");
        }
        println!("the BMS:");
    }
    print_fields(&v);
    Ok(())
}

pub fn print_fields(v: &Value) {
    if let Some(m) = v.as_object() {
        let w = m.keys().map(String::len).max().unwrap_or(0);
        for (k, x) in m {
            if k == "type" || k == "req" {
                continue;
            }
            let text = match x {
                Value::String(s) => s.clone(),
                other => other.to_string(),
            };
            println!("{k:<w$}  {text}");
        }
    }
}
