//! The protocol's commands as calls: each sends one command with a fresh `req`
//! and collects the lines that answer it (firmware/src/host_link/PROTOCOL.md).
//! Lines that answer nothing of ours (pushed telemetry, new events) are kept
//! in [`Client::pushed`] for whoever wants them (the monitor).
//!
//! Every line from the bridge is read once, through the host link's own types
//! ([`HostLine`], `tinybms_firmware::host_link::schema`): what a line holds,
//! the tool reads from its type, never by a member's name in a string. The
//! JSON it came as is kept beside it ([`Received::raw`]) only to be printed or
//! logged as it came (`--json`, the log; `req` left out) and to list members a
//! newer bridge adds that the types do not know (`tinybms stats`). A line that
//! is not one the bridge writes is counted in [`Client::garbage_lines`].

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use serde_json::{json, Map, Value};
use tinybms_firmware::host_link::schema::{
    Error, Hello, HostLine, Link, Outcome, Read, SettingLine, Telemetry,
};

use super::transport::{Lines, Mode};
use super::{ToolError, ToolResult};

/// How long a plain `get` may take (the bridge answers from memory).
pub const GET_TIMEOUT: Duration = Duration::from_secs(10);

/// Stops an in-process bridge; returns its bytes sent and received.
pub type Finish = Box<dyn FnMut() -> ToolResult<(u64, u64)> + Send>;

/// A line from the bridge: read through the host link's types, and the JSON
/// it came as (for printing or logging it as it came).
#[derive(Debug, Clone)]
pub struct Received {
    /// The line.
    pub line: HostLine,
    /// The JSON object it came as.
    pub raw: Value,
}

impl Received {
    /// Reads one line of text; `None` when it is not a line the bridge writes
    /// (not JSON, not an object, or members that are not the line's).
    pub fn parse(text: &str) -> Option<Self> {
        let raw: Value = serde_json::from_str(text).ok()?;
        Self::of(raw)
    }

    /// Reads a JSON object already parsed (`None` as for [`Received::parse`]).
    pub fn of(raw: Value) -> Option<Self> {
        if !raw.is_object() {
            return None;
        }
        let line = serde_json::from_value(raw.clone()).ok()?;
        Some(Self { line, raw })
    }

    /// The JSON as it came without its `req`: an answer to one of ours,
    /// printed like a pushed line.
    pub fn raw_without_req(&self) -> Value {
        without_req(self.raw.clone())
    }
}

/// A line's JSON without its `req` (see [`Received::raw_without_req`]).
pub fn without_req(mut raw: Value) -> Value {
    if let Some(m) = raw.as_object_mut() {
        m.shift_remove("req");
    }
    raw
}

/// The `setting` lines among `got` (a `get settings` answer).
pub fn setting_lines(got: &[Received]) -> Vec<SettingLine<Read>> {
    got.iter()
        .filter_map(|r| match &r.line {
            HostLine::Setting(s) => Some(s.clone()),
            _ => None,
        })
        .collect()
}

/// A connected bridge (real, simulated or in-process).
pub struct Client {
    lines: Box<dyn Lines>,
    next_req: u32,
    /// How it is reached.
    pub mode: Mode,
    /// The `hello` line.
    pub hello: Hello<Read>,
    /// The port's path, for messages.
    pub port: String,
    /// Lines not answering any of our commands, oldest first.
    pub pushed: VecDeque<Received>,
    /// Lines from the bridge that were not lines it writes (not JSON
    /// objects, or not read as any line type's members).
    pub garbage_lines: u64,
    /// Direct mode: stops the in-process bridge, returns its bytes sent and
    /// received.
    pub finish: Option<Finish>,
}

/// What every command that writes says when the bridge is read-only.
pub fn read_only_refusal() -> ToolError {
    ToolError::failed(
        "the bridge is read-only: it refuses every write, to the BMS and to its own \
         configuration. To allow writes, hold the board's BOOT button for 5 seconds while \
         the bridge runs (or erase its configuration: docs/configuration.md, \
         \"Read-only, and the way out\")",
    )
}

/// In direct mode, a port silent to every request this long is nothing the
/// tool can talk to (the bridge inside the tool has sent its requests, their
/// wake-up resends and retries by then).
pub const DIRECT_SILENT_FOR: Duration = Duration::from_secs(4);

/// An `error` line as a tool error, with a hint where one helps.
pub fn protocol_error(e: &Error<Read>) -> ToolError {
    let code = e.error.as_str();
    let detail = e.detail.as_str();
    let hint = match code {
        "read_only" => return read_only_refusal(),
        "not_ready" => " (the bridge has not read the settings and their limits yet: try again in a few seconds)",
        "busy" => " (the bridge's command queue is full: try again when the running writes are done)",
        "unknown_setting" => " (`tinybms settings PORT` lists the names)",
        "out_of_range" => {
            " (`tinybms settings PORT` shows each setting's allowed range and the BMS's own min..max)"
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
    pub fn new(lines: Box<dyn Lines>, mode: Mode, hello: Hello<Read>, port: String) -> Self {
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

    /// The next line from the bridge, waiting up to `timeout`.
    pub fn recv(&mut self, timeout: Duration) -> ToolResult<Option<Received>> {
        let end = Instant::now() + timeout;
        loop {
            let left = end.saturating_duration_since(Instant::now());
            match self.lines.recv_line(left)? {
                None => return Ok(None),
                Some(l) => match Received::parse(&l) {
                    Some(r) => return Ok(Some(r)),
                    None => self.garbage_lines += 1,
                },
            }
            if left.is_zero() {
                return Ok(None);
            }
        }
    }

    /// The next line answering `req` (others go to [`Client::pushed`]); an
    /// `error` line for it is returned as an error.
    pub fn recv_for(&mut self, req: u32, end: Instant, what: &str) -> ToolResult<Received> {
        let r = self.answer_to(req, end, what)?;
        if let HostLine::Error(e) = &r.line {
            return Err(protocol_error(e));
        }
        Ok(r)
    }

    /// The line answering `req`, an `error` line too; lines of other
    /// requests and pushed lines meanwhile are kept for later.
    fn answer_to(&mut self, req: u32, end: Instant, what: &str) -> ToolResult<Received> {
        loop {
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(ToolError::failed(format!(
                    "no answer to `{what}` from the bridge in time (is it still connected?)"
                )));
            }
            match self.recv(left)? {
                None => continue,
                Some(r) if r.line.req() == Some(req) => return Ok(r),
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
    pub fn get(&mut self, what: &str) -> ToolResult<Vec<Received>> {
        self.get_within(what, GET_TIMEOUT)
    }

    /// [`Client::get`] with a time for the whole answer (a long listing).
    pub fn get_within(&mut self, what: &str, within: Duration) -> ToolResult<Vec<Received>> {
        let req = self.send(json!({"cmd": "get", "what": what}))?;
        let end = Instant::now() + within;
        let mut out = Vec::new();
        loop {
            let r = self.recv_for(req, end, &format!("get {what}"))?;
            // The line that ends the answer: an `_end` line (left out), or the
            // answer's one line.
            let (last, kept) = match (&r.line, what) {
                (HostLine::SettingsEnd(_), _) | (HostLine::EventsEnd(_), _) => (true, false),
                // Kept: it names the protocol of the capture's frames.
                (HostLine::CanEnd(_), _) => (true, true),
                // Kept: its counts.
                (HostLine::HistoryEnd(_), _) => (true, true),
                (HostLine::Telemetry(_), "snapshot")
                | (HostLine::Statistics(_), "statistics")
                | (HostLine::Version(_), "version")
                | (HostLine::Link(_), "link") => (true, true),
                _ => (false, true),
            };
            if kept {
                out.push(r);
            }
            if last {
                return Ok(out);
            }
        }
    }

    /// `get WHAT` for a single line the bridge reads only after it is ready
    /// (statistics, the version): asked again every 200 ms while it answers
    /// `not_ready`, until `timeout`.
    pub fn get_one_read(&mut self, what: &str, timeout: Duration) -> ToolResult<Received> {
        let end = Instant::now() + timeout;
        loop {
            let req = self.send(json!({"cmd": "get", "what": what}))?;
            let r = self.answer_to(req, Instant::now() + GET_TIMEOUT, &format!("get {what}"))?;
            match &r.line {
                HostLine::Error(e) if e.error == "not_ready" && Instant::now() < end => {
                    std::thread::sleep(Duration::from_millis(200));
                }
                HostLine::Error(e) => return Err(protocol_error(e)),
                _ => return Ok(r),
            }
        }
    }

    /// `get WHAT` for a single line.
    pub fn get_one(&mut self, what: &str) -> ToolResult<Received> {
        self.get(what)?
            .pop()
            .ok_or_else(|| ToolError::failed(format!("`get {what}` answered nothing")))
    }

    /// `get WHAT` for a single line of the type `pick` takes.
    fn get_typed<T>(&mut self, what: &str, pick: impl Fn(HostLine) -> Option<T>) -> ToolResult<T> {
        pick(self.get_one(what)?.line)
            .ok_or_else(|| ToolError::failed(format!("`get {what}` answered another line")))
    }

    /// `get snapshot`: the `telemetry` line.
    pub fn snapshot(&mut self) -> ToolResult<Telemetry<Read>> {
        self.get_typed("snapshot", |l| match l {
            HostLine::Telemetry(t) => Some(t),
            _ => None,
        })
    }

    /// `get link`: the `link` line.
    pub fn link(&mut self) -> ToolResult<Link<Read>> {
        self.get_typed("link", |l| match l {
            HostLine::Link(k) => Some(k),
            _ => None,
        })
    }

    /// `get settings`: the `setting` lines.
    pub fn settings(&mut self) -> ToolResult<Vec<SettingLine<Read>>> {
        Ok(setting_lines(&self.get("settings")?))
    }

    /// Waits until the bridge is online and ready (settings and limits read);
    /// explains what is wrong when it does not get there within `timeout`.
    /// Says every few seconds on stderr what it is waiting for; Ctrl-C stops it.
    /// Returns the `telemetry` line that said so.
    pub fn wait_ready(&mut self, timeout: Duration) -> ToolResult<Received> {
        let start = Instant::now();
        let mut next_note = start + Duration::from_secs(3);
        loop {
            let got = self.get_one("snapshot")?;
            let HostLine::Telemetry(t) = &got.line else {
                return Err(ToolError::failed("`get snapshot` answered another line"));
            };
            if t.head.ready && t.head.online {
                return Ok(got);
            }
            let t = t.clone();
            if start.elapsed() >= timeout {
                return Err(self.not_ready_error(&t));
            }
            // Direct mode on a port where not one byte came back: no TinyBMS
            // (a sleeping one answers the wake-up resend at once), and no
            // bridge answered the hello either. Said now, not after the
            // whole timeout.
            if self.mode == Mode::Direct && start.elapsed() >= DIRECT_SILENT_FOR {
                let link = self.link().ok();
                let silent = link
                    .as_ref()
                    .is_some_and(|l| l.requests > 0 && l.replies == 0 && l.skipped_bytes == 0);
                if silent {
                    return Err(self.not_ready_error(&t));
                }
            }
            if super::interrupted() {
                return Err(super::interrupted_error());
            }
            if Instant::now() >= next_note {
                next_note += Duration::from_secs(3);
                let link = self.link().ok();
                let n = |k: fn(&Link<Read>) -> u32| link.as_ref().map_or(0, k);
                eprintln!(
                    "waiting for the BMS ({:.0} s of {:.0} s): {} requests sent, {} replies{}",
                    start.elapsed().as_secs_f64(),
                    timeout.as_secs_f64(),
                    n(|l| l.requests),
                    n(|l| l.replies),
                    if t.head.online {
                        ", reading its settings"
                    } else {
                        ""
                    }
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    fn not_ready_error(&mut self, t: &Telemetry<Read>) -> ToolError {
        let link = self.link().ok();
        let n = |k: fn(&Link<Read>) -> u32| link.as_ref().map_or(0, |l| u64::from(k(l)));
        let replies = n(|l| l.replies);
        let garbage = n(|l| l.skipped_bytes) + n(|l| l.crc_errors) + n(|l| l.framing_errors);
        let who = match self.mode {
            Mode::Direct => format!("`{}`", self.port),
            Mode::Bridge => "the bridge's UART".to_string(),
        };
        if replies == 0 && garbage > 0 {
            ToolError::connect(format!(
                "something answers on {who}, but not with TinyBMS frames ({} bytes skipped, \
                 {} CRC errors): a different device on this port, or the wrong baud rate \
                 (the TinyBMS talks 115200 8N1)",
                n(|l| l.skipped_bytes),
                n(|l| l.crc_errors)
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
                n(|l| l.requests)
            ))
        } else {
            ToolError::connect(format!(
                "the BMS answers ({replies} replies) but its settings could not be read \
                 completely yet (online {}, ready {}): a bad line? `tinybms monitor` shows the \
                 link quality",
                t.head.online, t.head.ready
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
        mut on_outcome: impl FnMut(&Outcome<Read>),
    ) -> ToolResult<Vec<Outcome<Read>>> {
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
                Ok(r) => match r.line {
                    HostLine::Outcome(o) => o,
                    _ => continue,
                },
                Err(_) if firsts == settings.len() => break,
                Err(e) => return Err(e),
            };
            if v.follow_up {
                unconfirmed -= 1;
            } else {
                firsts += 1;
                end = Instant::now() + per;
                if v.outcome == "unconfirmed" {
                    unconfirmed += 1;
                }
            }
            on_outcome(&v);
            out.push(v);
        }
        Ok(out)
    }

    /// A command answered by `accepted` then the line `done` takes (what
    /// it returns for it).
    pub fn command<T>(
        &mut self,
        cmd: Value,
        timeout: Duration,
        done: impl Fn(HostLine) -> Option<T>,
    ) -> ToolResult<T> {
        let name = cmd["cmd"].as_str().unwrap_or("command").to_string();
        let req = self.send(cmd)?;
        let end = Instant::now() + timeout;
        loop {
            if let Some(v) = done(self.recv_for(req, end, &name)?.line) {
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
    pub fn next_pushed(&mut self, timeout: Duration) -> ToolResult<Option<Received>> {
        if let Some(v) = self.pushed.pop_front() {
            return Ok(Some(v));
        }
        self.recv(timeout)
    }
}

/// Lines as the tool reads them, for the tool's unit tests.
#[cfg(test)]
pub(crate) mod fixtures {
    use serde_json::Value;
    use tinybms_firmware::host_link::schema::{HostLine, Read, Telemetry};

    /// A line as the tool reads it.
    pub fn line(v: Value) -> HostLine {
        serde_json::from_value(v).unwrap()
    }

    /// A telemetry line as the tool reads it.
    pub fn telemetry_line(v: Value) -> Telemetry<Read> {
        match line(v) {
            HostLine::Telemetry(t) => t,
            other => panic!("not telemetry: {other:?}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A line the bridge writes is read through its type; anything else is
    /// no line (counted as garbage by [`Client::recv`]), never a panic.
    #[test]
    fn only_lines_the_bridge_writes_are_read() {
        let log = Received::parse(r#"{"type":"log","level":"info","text":"hello there"}"#)
            .expect("a log line");
        match &log.line {
            HostLine::Log(l) => {
                assert_eq!((l.level.as_str(), l.text.as_str()), ("info", "hello there"))
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(log.raw["text"], "hello there");
        // A newer bridge's line type: read, as a line this tool does not know.
        let newer = Received::parse(r#"{"type":"brand_new","x":1}"#).expect("a line");
        assert_eq!(newer.line, HostLine::Other);
        for garbage in [
            "",
            "this is not json",
            "[1,2]",
            "7",
            r#"{"no_type":1}"#,
            // A known type without its members: not a line the bridge writes.
            r#"{"type":"telemetry"}"#,
            r#"{"type":"error","req":3,"error":7}"#,
        ] {
            assert!(Received::parse(garbage).is_none(), "{garbage}");
        }
        let answer = Received::parse(
            r#"{"type":"error","req":3,"error":"busy","detail":"the queue is full"}"#,
        )
        .expect("an error line");
        assert_eq!(answer.line.req(), Some(3));
        assert_eq!(answer.raw_without_req().get("req"), None);
    }
}
