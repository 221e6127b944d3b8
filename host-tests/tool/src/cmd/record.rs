//! `tinybms record`: a capture file of the UART traffic, for bug reports.

use std::path::Path;
use std::time::{Duration, Instant};

use serde_json::json;
use tinybms_firmware::host_link::schema::{HostLine, Raw, Read};

use crate::cli::Conn;
use crate::client::{self, Client};
use crate::transport::Mode;
use crate::transport::SerialLines;
use crate::{choice, direct, interrupted, monitor, open_and_probe, ToolError, ToolResult};
use tinybms_desk::capture::{parse_hex, CaptureWriter};

/// A `raw` line's bytes went to the BMS (else they came from it).
fn is_tx(r: &Raw<Read>) -> bool {
    r.dir == "tx"
}

pub fn record(conn: &Conn, file: &Path, duration: Duration) -> ToolResult<()> {
    let path = file.display().to_string();
    let f = std::fs::File::create(file)
        .map_err(|e| ToolError::failed(format!("cannot create `{path}`: {e}")))?;
    let header = format!(
        "recorded by tinybms {} from {} at {}",
        env!("CARGO_PKG_VERSION"),
        conn.port,
        monitor::utc_now()
    );
    let writer = CaptureWriter::new(Box::new(std::io::BufWriter::new(f)), &header)
        .map_err(|e| ToolError::failed(format!("writing `{path}`: {e}")))?;
    let port = conn.port.clone();
    let (serial, mode, probe) = open_and_probe(&port, choice(conn))?;
    let (mut tx, mut rx) = (0usize, 0usize);
    let started = Instant::now();
    // What was recorded, not what was asked: Ctrl-C ends it early.
    let recorded = || started.elapsed().min(duration);
    let took: Duration;
    match (mode, probe) {
        (Mode::Direct, _) => {
            let _ = serial.clear(serialport::ClearBuffer::Input);
            let mut c = direct::start(serial, port.clone(), Some(writer))?;
            let _ = c.stream(0);
            let end = Instant::now() + duration;
            while Instant::now() < end && !interrupted() {
                let left = end.saturating_duration_since(Instant::now());
                let _ = c.next_pushed(left.min(Duration::from_millis(200)))?;
            }
            took = recorded();
            let (t, r) = direct::stop(&mut c)?;
            tx = t as usize;
            rx = r as usize;
        }
        (Mode::Bridge, Some((hello, split))) => {
            let lines = SerialLines::new(serial, split);
            let mut c = Client::new(Box::new(lines), Mode::Bridge, hello, port.clone());
            let mut writer = writer;
            c.stream(0)?;
            let req = c.send(json!({"cmd": "capture", "on": true}))?;
            c.recv_for(req, Instant::now() + client::GET_TIMEOUT, "capture")?;
            let end = Instant::now() + duration;
            let werr = |e: std::io::Error| ToolError::failed(format!("writing `{path}`: {e}"));
            // Ctrl-C ends the recording early; capture goes off all the same.
            while Instant::now() < end && !interrupted() {
                let left = end.saturating_duration_since(Instant::now());
                let Some(r) = c.next_pushed(left.min(Duration::from_millis(200)))? else {
                    continue;
                };
                let HostLine::Raw(v) = r.line else {
                    continue;
                };
                let bytes = parse_hex(&v.hex)
                    .map_err(|e| ToolError::failed(format!("a raw line the bridge sent: {e}")))?;
                if is_tx(&v) {
                    writer.tx(&bytes).map_err(werr)?;
                    tx += bytes.len();
                } else {
                    writer.rx(&bytes).map_err(werr)?;
                    rx += bytes.len();
                }
            }
            took = recorded();
            finish_capture(&mut c, &mut writer, (took, duration), &path)?;
        }
        (Mode::Bridge, None) => return Err(ToolError::failed("internal: bridge without hello")),
    }
    let early = if interrupted() {
        format!(
            ", stopped by Ctrl-C ({:.1} s asked)",
            duration.as_secs_f64()
        )
    } else {
        String::new()
    };
    println!(
        "recorded {:.1} s to {path}: {tx} bytes sent, {rx} received ({}){early}",
        took.as_secs_f64(),
        match mode {
            Mode::Bridge => "through the bridge's capture",
            Mode::Direct => "direct",
        }
    );
    // The capture is kept and said; Ctrl-C ends the command as it ends
    // every other (status 130).
    if interrupted() {
        return Err(crate::interrupted_error());
    }
    Ok(())
}

/// Capture off, the raw lines still queued before its answer written, and
/// the recording's end said in the file (`took` of `asked`).
fn finish_capture(
    c: &mut Client,
    writer: &mut CaptureWriter,
    (took, duration): (Duration, Duration),
    path: &str,
) -> ToolResult<()> {
    let werr = |e: std::io::Error| ToolError::failed(format!("writing `{path}`: {e}"));
    let req = c.send(json!({"cmd": "capture", "on": false}))?;
    // Raw lines still queued before the answer are part of the capture.
    loop {
        let Some(r) = c.recv(Duration::from_secs(5))? else {
            break;
        };
        if r.line.req() == Some(req) {
            break;
        }
        if let HostLine::Raw(v) = r.line {
            if let Ok(bytes) = parse_hex(&v.hex) {
                if is_tx(&v) {
                    writer.tx(&bytes).map_err(werr)?;
                } else {
                    writer.rx(&bytes).map_err(werr)?;
                }
            }
        }
    }
    if let Some(dropped) = c.link().ok().map(|l| l.dropped_lines) {
        if dropped > 0 {
            let _ = writer.comment(&format!(
                "the bridge dropped {dropped} output lines since it started (raw lines may be missing)"
            ));
        }
    }
    let _ = writer.comment(&format!(
        "recorded {:.1} s of the {:.1} s asked{}",
        took.as_secs_f64(),
        duration.as_secs_f64(),
        if interrupted() {
            " (stopped by Ctrl-C)"
        } else {
            ""
        }
    ));
    writer.flush().map_err(werr)?;
    Ok(())
}
