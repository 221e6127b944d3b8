//! Direct mode: waits for the firmware's host link (branch `link`); until it
//! is merged, direct mode reports that it is not available.
use super::client::Client;
use super::{ToolError, ToolResult};
use crate::capture::CaptureWriter;

/// Not available yet.
pub fn start(
    _serial: Box<dyn serialport::SerialPort>,
    port: String,
    _capture: Option<CaptureWriter>,
) -> ToolResult<Client> {
    Err(ToolError::connect(format!(
        "no bridge answered on `{port}`, and direct mode is not built yet (it needs the firmware's host link)"
    )))
}

/// Not available yet.
pub fn stop(_client: &mut Client) -> ToolResult<(u64, u64)> {
    Ok((0, 0))
}
