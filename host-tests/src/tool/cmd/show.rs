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
