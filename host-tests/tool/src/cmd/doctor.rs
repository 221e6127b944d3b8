//! `tinybms doctor`: both wires in words. On a bridge: the BMS's UART wire
//! (its `link` line: damaged, lost and resent replies and a verdict), why each
//! limit is what it is (its `telemetry` line), then its CAN capture (`get
//! can`: the last minute of frames both ways) read by the firmware's own
//! doctor — the heartbeat and each verdict with its numbers and what to do
//! — and saved as a candump log with `--out`. On a capture file (such a log,
//! or one of the fixtures): the same doctor over it.

use std::path::Path;

use tinybms_firmware::host_link::schema::HostLine;
use tinybms_firmware::inverter::capture::parse_line;
use tinybms_firmware::inverter::doctor::Doctor;
use tinybms_firmware::inverter::Protocol;
use tinybms_firmware::log_line::Line;

use crate::cli::{Conn, ModeArg};
use crate::{connect_ready, ToolError, ToolResult};

/// What to do about a verdict the bridge reports by its key.
pub fn advice(key: &str) -> &'static str {
    match key {
        "no_ack" => "nobody acknowledges the frames: CAN-H/CAN-L, a 120 ohm terminator at each end, the inverter on at 500 kbit/s",
        "bus_off" => "the controller left the bus: bit rate, CAN-H/CAN-L swapped or shorted, termination, a common ground",
        "no_inverter" => "frames acknowledged, the inverter silent: its battery type (CAN/lithium with BMS), the protocol, the bus it is on",
        "heartbeat_late" => "the inverter's heartbeat came late: a busy inverter, a loose CAN wire, a node flooding the bus",
        "other_dialect" => "a frame only another dialect's inverter sends: check inverter_protocol against the inverter's battery protocol",
        "over_limit" => "the inverter draws more than the limit for a while: its BMS (CAN) mode, its own current settings, inverter_model",
        "voltage_disagrees" => "the inverter's voltage and the BMS's disagree: cables, fuse, shunt wiring, the inverter's calibration",
        "unknown_name" => "0x35E names the battery with a name inverters are not known to take: most expect PYLON (GoodWe: GOODWE)",
        "export_after_step" => "the pack gave energy after CVL fell: the inverter pulls it down to the charge voltage; keep float_step on",
        _ => "(a verdict this tool does not know: update tinybms)",
    }
}

/// Runs `tinybms doctor`.
pub fn run(
    port: Option<String>,
    capture: Option<&Path>,
    protocol: &str,
    out: Option<&Path>,
) -> ToolResult<()> {
    match (port, capture) {
        (Some(_), Some(_)) => Err(ToolError::usage(
            "either a PORT or --capture FILE, not both",
        )),
        (None, Some(file)) => on_capture(file, protocol),
        (Some(target), None) => on_bridge(&target, out),
        (None, None) => Err(ToolError::usage(
            "tinybms doctor PORT, or tinybms doctor --capture FILE [--protocol P]",
        )),
    }
}

/// The bridge's capture (`get can`), saved to `out` when given, and the
/// doctor over it.
fn capture_of(c: &mut crate::client::Client, out: Option<&Path>) -> ToolResult<()> {
    let lines = c.get("can")?;
    let mut text = String::new();
    let mut protocol = None;
    for r in &lines {
        match &r.line {
            HostLine::Can(l) => {
                text.push_str(&l.line);
                text.push('\n');
            }
            HostLine::CanEnd(e) => protocol = Some(e.protocol.clone()),
            _ => {}
        }
    }
    let key = protocol.unwrap_or_default();
    let p = Protocol::from_key(&key)
        .ok_or_else(|| ToolError::failed(format!("the bridge speaks `{key}`: unknown here")))?;
    if let Some(file) = out {
        std::fs::write(file, &text)
            .map_err(|e| ToolError::failed(format!("cannot write {}: {e}", file.display())))?;
        println!(
            "the CAN capture saved to {} ({} frames)",
            file.display(),
            text.lines().count()
        );
    }
    diagnose(&text, p, "the bridge's capture")
}

fn on_capture(file: &Path, protocol: &str) -> ToolResult<()> {
    let p = Protocol::from_key(protocol)
        .ok_or_else(|| ToolError::usage(format!("--protocol {protocol}: not a protocol")))?;
    let text = std::fs::read_to_string(file)
        .map_err(|e| ToolError::failed(format!("cannot read {}: {e}", file.display())))?;
    diagnose(&text, p, &file.display().to_string())
}

/// The doctor over a capture's text, printed.
fn diagnose(text: &str, p: Protocol, what: &str) -> ToolResult<()> {
    let mut d = Doctor::new(p);
    let mut frames = 0;
    for (k, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let (at, seen) = parse_line(line)
            .map_err(|e| ToolError::failed(format!("{what} line {}: {}", k + 1, e.text())))?;
        d.on_entry(at, seen);
        frames += 1;
    }
    let h = d.heartbeat();
    println!("{frames} frames read, the bridge speaking {}", p.title());
    match h.count {
        0 => println!("heartbeat in the capture: none heard"),
        1 => println!("heartbeat in the capture: one heard"),
        n => println!(
            "heartbeat in the capture: {n} heard, every {} ms on average, longest gap {} ms, {} late",
            h.mean_ms, h.longest_ms, h.late
        ),
    }
    let verdicts = d.verdicts(None);
    if verdicts.is_empty() {
        println!("no verdict: the capture shows nothing wrong");
    }
    for v in &verdicts {
        let mut l = Line::new();
        v.write(&mut l);
        println!("- {}: {}", v.key(), l.as_str());
    }
    Ok(())
}

fn on_bridge(target: &str, out: Option<&Path>) -> ToolResult<()> {
    if !crate::is_serial(target) {
        // The update port: the capture only (no telemetry there).
        let mut c = crate::connect_bridge_or_host(target)?;
        return capture_of(&mut c, out).map(|_| ());
    }
    let mut c = connect_ready(&Conn {
        port: target.to_string(),
        mode: ModeArg::Bridge,
        timeout: std::time::Duration::from_secs(15),
    })?;
    let t = c.snapshot()?;
    // The BMS's wire first: without data nothing else is right.
    let l = c.link()?;
    if l.wire.is_empty() {
        println!("BMS wire: (this bridge's firmware does not judge it)");
    } else {
        println!(
            "BMS wire: {} (last minute, per thousand sends: {} corrupted, {} lost, {} resent)",
            l.wire_verdict, l.corrupted_permille, l.lost_permille, l.resent_permille
        );
    }
    let Some(inv) = t.told.inverter else {
        println!("this bridge has no CAN output");
        return Ok(());
    };
    println!(
        "inverter: {} on CAN ({}), {}",
        inv.protocol,
        inv.can,
        if inv.heard { "heard" } else { "not heard" }
    );
    let num = |x: &Option<f64>| x.map_or("-".to_string(), |v| format!("{v}"));
    for (name, value, unit, why) in [
        ("CVL", &inv.cvl_v, "V", &inv.cvl_why),
        ("CCL", &inv.ccl_a, "A", &inv.ccl_why),
        ("DCL", &inv.dcl_a, "A", &inv.dcl_why),
    ] {
        println!(
            "{name} {} {unit}: {}",
            num(value),
            why.as_deref().unwrap_or("(not computed yet)")
        );
    }
    match (
        inv.heartbeat_ms,
        inv.heartbeat_longest_ms,
        inv.heartbeat_late,
    ) {
        (Some(m), Some(l), Some(n)) => {
            println!("heartbeat since the bridge started: every {m} ms on average, longest gap {l} ms, {n} late")
        }
        _ => println!("heartbeat since the bridge started: none heard"),
    }
    capture_of(&mut c, out)?;
    // What the bridge itself found in the last minute (its capture may have
    // moved on since).
    if let Some(keys) = inv.doctor.as_deref() {
        println!("the bridge's own verdicts of the last minute:");
        for k in keys.split(',') {
            println!("- {k}: {}", advice(k));
        }
    }
    Ok(())
}
