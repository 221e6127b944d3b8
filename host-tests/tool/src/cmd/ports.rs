//! `tinybms ports`: The serial ports there are.

use crate::{transport, ToolResult};

/// Runs `tinybms ports`.
pub fn run() -> ToolResult<()> {
    let list = transport::port_list();
    if list.is_empty() {
        println!(
            "no serial port found (plug the adapter or the ESP32 in; `dmesg` shows it arriving)"
        );
    }
    for p in list {
        println!("{p}");
    }
    Ok(())
}
