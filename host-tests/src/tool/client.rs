//! The protocol's commands as calls: each sends one command with a fresh `req`
//! and collects the lines that answer it (firmware/src/host_link/PROTOCOL.md).
//! Lines that answer nothing of ours (pushed telemetry, new events) are kept
//! in [`Client::pushed`] for whoever wants them (the monitor).

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use serde_json::{json, Map, Value};

use super::transport::{Lines, Mode};
use super::{ToolError, ToolResult};

/// How long a plain `get` may take (the bridge answers from memory).
pub const GET_TIMEOUT: Duration = Duration::from_secs(10);

/// Stops an in-process bridge; returns its bytes sent and received.
pub type Finish = Box<dyn FnMut() -> ToolResult<(u64, u64)> + Send>;

/// A connected bridge (real, simulated or in-process).
pub struct Client {
    lines: Box<dyn Lines>,
    next_req: u32,
    /// How it is reached.
    pub mode: Mode,
    /// The `hello` line.
    pub hello: Value,
    /// The port's path, for messages.
    pub port: String,
    /// Lines not answering any of our commands, oldest first.
    pub pushed: VecDeque<Value>,
    /// Lines from the bridge that were not JSON objects.
    pub garbage_lines: u64,
    /// Direct mode: stops the in-process bridge, returns its bytes sent and
    /// received.
    pub finish: Option<Finish>,
}

/// An `error` line as a tool error, with a hint where one helps.
pub fn protocol_error(v: &Value) -> ToolError {
    let code = v["error"].as_str().unwrap_or("error");
    let detail = v["detail"].as_str().unwrap_or("");
    let hint = match code {
        "read_only" => {
            " (the bridge is built or started read-only: host writes are switched off)"
        }
        "not_ready" => " (the bridge has not read the settings and their limits yet: try again in a few seconds)",
        "busy" => " (the bridge's command queue is full: try again when the running writes are done)",
        "unknown_setting" => " (`tinybms settings PORT` lists the names)",
        "out_of_range" => {
            " (`tinybms settings PORT` shows each setting's Rev D range and the BMS's own min..max)"
        }
        _ => "",
    };
    let detail = if detail.is_empty() {
        String::new()
    } else {
        format!(" ({detail})")
    };
    ToolError::failed(format!("the bridge refused: {code}{detail}{hint}"))
}

impl Client {
    /// A client on `lines`, after the hello.
    pub fn new(lines: Box<dyn Lines>, mode: Mode, hello: Value, port: String) -> Self {
        Self {
            lines,
            next_req: 1,
            mode,
            hello,
            port,
            pushed: VecDeque::new(),
            garbage_lines: 0,
            finish: None,
        }
    }

    /// Sends `cmd` (an object) with a new `req`; returns the req.
    pub fn send(&mut self, mut cmd: Value) -> ToolResult<u32> {
        let req = self.next_req;
        self.next_req = self.next_req.wrapping_add(1);
        if let Some(m) = cmd.as_object_mut() {
            m.insert("req".into(), json!(req));
        }
        self.lines.send_line(&cmd.to_string())?;
        Ok(req)
    }

    /// The next JSON object from the bridge, waiting up to `timeout`.
    pub fn recv(&mut self, timeout: Duration) -> ToolResult<Option<Value>> {
        let end = Instant::now() + timeout;
        loop {
            let left = end.saturating_duration_since(Instant::now());
            match self.lines.recv_line(left)? {
                None => return Ok(None),
                Some(l) => match serde_json::from_str::<Value>(&l) {
                    Ok(v) if v.is_object() => return Ok(Some(v)),
                    _ => self.garbage_lines += 1,
                },
            }
            if left.is_zero() {
                return Ok(None);
            }
        }
    }

    /// The next line answering `req` (others go to [`Client::pushed`]); an
    /// `error` line for it is returned as an error.
    pub fn recv_for(&mut self, req: u32, end: Instant, what: &str) -> ToolResult<Value> {
        loop {
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(ToolError::failed(format!(
                    "no answer to `{what}` from the bridge in time (is it still connected?)"
                )));
            }
            match self.recv(left)? {
                None => continue,
                Some(v) if v["req"] == json!(req) => {
                    if v["type"] == "error" {
                        return Err(protocol_error(&v));
                    }
                    return Ok(v);
                }
                Some(v) => {
                    if self.pushed.len() >= 10_000 {
                        self.pushed.pop_front();
                    }
                    self.pushed.push_back(v)
                }
            }
        }
    }

    /// `get WHAT`: the lines answering it (for settings and events, up to and
    /// without the `_end` line).
    pub fn get(&mut self, what: &str) -> ToolResult<Vec<Value>> {
        let req = self.send(json!({"cmd": "get", "what": what}))?;
        let end = Instant::now() + GET_TIMEOUT;
        let last = match what {
            "settings" => "settings_end",
            "events" => "events_end",
            "snapshot" => "telemetry",
            "statistics" => "statistics",
            other => other,
        };
        let mut out = Vec::new();
        loop {
            let v = self.recv_for(req, end, &format!("get {what}"))?;
            if v["type"] == last {
                if !last.ends_with("_end") {
                    out.push(v);
                }
                return Ok(out);
            }
            out.push(v);
        }
    }

    /// `get WHAT` for a single line.
    pub fn get_one(&mut self, what: &str) -> ToolResult<Value> {
        self.get(what)?
            .pop()
            .ok_or_else(|| ToolError::failed(format!("`get {what}` answered nothing")))
    }

    /// Waits until the bridge is online and ready (settings and limits read);
    /// explains what is wrong when it does not get there within `timeout`.
    /// Says every few seconds on stderr what it is waiting for; Ctrl-C stops it.
    pub fn wait_ready(&mut self, timeout: Duration) -> ToolResult<Value> {
        let start = Instant::now();
        let mut next_note = start + Duration::from_secs(3);
        loop {
            let t = self.get_one("snapshot")?;
            if t["ready"] == true && t["online"] == true {
                return Ok(t);
            }
            if start.elapsed() >= timeout {
                return Err(self.not_ready_error(&t));
            }
            if super::interrupted() {
                return Err(super::interrupted_error());
            }
            if Instant::now() >= next_note {
                next_note += Duration::from_secs(3);
                let link = self.get_one("link").unwrap_or(Value::Null);
                let n = |k: &str| link[k].as_u64().unwrap_or(0);
                eprintln!(
                    "waiting for the BMS ({:.0} s of {:.0} s): {} requests sent, {} replies{}",
                    start.elapsed().as_secs_f64(),
                    timeout.as_secs_f64(),
                    n("requests"),
                    n("replies"),
                    if t["online"] == true {
                        ", reading its settings"
                    } else {
                        ""
                    }
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    fn not_ready_error(&mut self, t: &Value) -> ToolError {
        let link = self.get_one("link").unwrap_or(Value::Null);
        let n = |k: &str| link[k].as_u64().unwrap_or(0);
        let replies = n("replies");
        let garbage = n("skipped_bytes") + n("crc_errors") + n("framing_errors");
        let who = match self.mode {
            Mode::Direct => format!("`{}`", self.port),
            Mode::Bridge => "the bridge's UART".to_string(),
        };
        if replies == 0 && garbage > 0 {
            ToolError::connect(format!(
                "something answers on {who}, but not with TinyBMS frames ({} bytes skipped, \
                 {} CRC errors): a different device on this port, or the wrong baud rate \
                 (the TinyBMS talks 115200 8N1)",
                n("skipped_bytes"),
                n("crc_errors")
            ))
        } else if replies == 0 {
            let unflashed = match self.mode {
                Mode::Direct => {
                    "No bridge answered a hello either: if this port is an ESP32 board, it is \
                     not running this firmware yet (flash it: docs/flashing.md) or is still \
                     starting. If it is a USB-UART adapter wired to the BMS, check: "
                }
                Mode::Bridge => "Check the bridge's wiring to the BMS: ",
            };
            ToolError::connect(format!(
                "nothing answers on {who} ({} requests sent, no byte back). {unflashed}TX and \
                 RX crossed (TX -> BMS RX, RX <- BMS TX), a common ground (GND <-> BMS UART \
                 ground), 3.3 V logic levels, the BMS powered. A sleeping BMS is woken \
                 automatically (the first request is sent twice).",
                n("requests")
            ))
        } else {
            ToolError::connect(format!(
                "the BMS answers ({replies} replies) but its settings could not be read \
                 completely yet (online {}, ready {}): a bad line? `tinybms monitor` shows the \
                 link quality",
                t["online"], t["ready"]
            ))
        }
    }

    /// `set`: writes `settings` (name -> number) as physical values (`raw`
    /// false) or register units; calls `on_outcome` for every outcome line and
    /// returns them. Waits for follow-ups of unconfirmed writes up to
    /// `follow_up_wait`.
    pub fn set(
        &mut self,
        settings: &[(String, f64)],
        raw: bool,
        chemistry: protocol_core::settings::ChemistryCheck,
        follow_up_wait: Duration,
        mut on_outcome: impl FnMut(&Value),
    ) -> ToolResult<Vec<Value>> {
        let mut map = Map::new();
        for (name, v) in settings {
            let num = if raw { json!(*v as i64) } else { json!(v) };
            map.insert(name.clone(), num);
        }
        let key = if raw { "raw" } else { "values" };
        let mut cmd = json!({"cmd": "set", key: Value::Object(map)});
        match chemistry {
            protocol_core::settings::ChemistryCheck::Inferred => {}
            protocol_core::settings::ChemistryCheck::Given(c) => {
                cmd["chemistry"] = json!(c.key());
            }
            protocol_core::settings::ChemistryCheck::Off => cmd["force"] = json!(true),
        }
        let req = self.send(cmd)?;
        // A write reads, writes, waits 200 ms, reads back; a reboot-causing
        // setting waits for the BMS to come back. Generous.
        let per = Duration::from_secs(20);
        let mut end = Instant::now() + per;
        let mut out = Vec::new();
        let mut firsts = 0;
        let mut unconfirmed = 0;
        while firsts < settings.len() || unconfirmed > 0 {
            if firsts == settings.len() {
                end = end.min(Instant::now() + follow_up_wait);
            }
            let v = match self.recv_for(req, end, "set") {
                Ok(v) => v,
                Err(_) if firsts == settings.len() => break,
                Err(e) => return Err(e),
            };
            if v["type"] != "outcome" {
                continue;
            }
            if v["follow_up"] == true {
                unconfirmed -= 1;
            } else {
                firsts += 1;
                end = Instant::now() + per;
                if v["outcome"] == "unconfirmed" {
                    unconfirmed += 1;
                }
            }
            on_outcome(&v);
            out.push(v);
        }
        Ok(out)
    }

    /// A command answered by `accepted` then one line of type `done`.
    pub fn command(&mut self, cmd: Value, done: &str, timeout: Duration) -> ToolResult<Value> {
        let name = cmd["cmd"].as_str().unwrap_or("command").to_string();
        let req = self.send(cmd)?;
        let end = Instant::now() + timeout;
        loop {
            let v = self.recv_for(req, end, &name)?;
            if v["type"] == done {
                return Ok(v);
            }
        }
    }

    /// `stream`: the telemetry push period (0 = off).
    pub fn stream(&mut self, period_ms: u32) -> ToolResult<()> {
        let req = self.send(json!({"cmd": "stream", "period_ms": period_ms}))?;
        self.recv_for(req, Instant::now() + GET_TIMEOUT, "stream")?;
        Ok(())
    }

    /// The next pushed line (kept or new), waiting up to `timeout`.
    pub fn next_pushed(&mut self, timeout: Duration) -> ToolResult<Option<Value>> {
        if let Some(v) = self.pushed.pop_front() {
            return Ok(Some(v));
        }
        self.recv(timeout)
    }
}
