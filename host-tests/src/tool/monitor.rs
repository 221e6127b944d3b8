//! `tinybms monitor`: the live view (ANSI, redrawn in place), JSON Lines, and
//! the CSV / JSON Lines log.

use std::io::Write;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::{json, Value};

use super::client::Client;
use super::{ToolError, ToolResult};

const BOLD: &str = "\x1b[1m";
const RED: &str = "\x1b[1;31m";
const BLUE: &str = "\x1b[1;36m";
const YELLOW: &str = "\x1b[33m";
const DIM: &str = "\x1b[2m";
const RESET: &str = "\x1b[0m";
/// Cursor home (the screen is redrawn over itself).
pub const HOME: &str = "\x1b[H";
/// Clear the whole screen.
pub const CLEAR: &str = "\x1b[2J";
/// Clear to the end of the line.
const EOL: &str = "\x1b[K";
/// Clear to the end of the screen.
const EOS: &str = "\x1b[J";

/// Log file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogFormat {
    /// One row per record, cells as columns.
    Csv,
    /// The telemetry line with a `time` member.
    JsonLines,
}

impl LogFormat {
    /// From `--format` or the file's extension.
    pub fn from_name(s: &str) -> Option<Self> {
        match s {
            "csv" => Some(Self::Csv),
            "jsonl" | "json" | "ndjson" => Some(Self::JsonLines),
            _ => None,
        }
    }
}

/// What `monitor` does.
#[derive(Debug, Clone)]
pub struct MonitorOptions {
    /// Print the telemetry lines instead of the screen.
    pub json: bool,
    /// Log file and format.
    pub log: Option<(String, LogFormat)>,
    /// Log period.
    pub every: Duration,
    /// Stop after this many updates (screens, JSON lines or log records).
    pub count: Option<u64>,
    /// Stop after this long.
    pub duration: Option<Duration>,
    /// Telemetry push period asked of the bridge.
    pub period_ms: u32,
    /// How long to wait for the BMS to be ready.
    pub ready_timeout: Duration,
}

/// UTC time `2024-05-01T12:00:00.123Z` (no dependency for one format).
pub fn utc_now() -> String {
    let d = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default();
    utc(d.as_secs() as i64, d.subsec_millis())
}

/// UTC time of `secs` since 1970 (civil-from-days, proleptic Gregorian).
pub fn utc(secs: i64, millis: u32) -> String {
    let days = secs.div_euclid(86_400);
    let tod = secs.rem_euclid(86_400);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{millis:03}Z",
        tod / 3600,
        tod / 60 % 60,
        tod % 60
    )
}

fn num(v: &Value, k: &str) -> Option<f64> {
    v[k].as_f64()
}

fn fmt_opt(v: Option<f64>, decimals: usize, unit: &str) -> String {
    match v {
        Some(x) => format!("{x:.decimals$} {unit}"),
        None => "-".into(),
    }
}

/// Link quality from a `link` line: share of requests answered at once, and the
/// counts.
pub fn link_quality(link: &Value) -> Option<String> {
    let requests = link["requests"].as_u64()?;
    let replies = link["replies"].as_u64().unwrap_or(0);
    let failures = link["failures"].as_u64().unwrap_or(0);
    let pct = if requests == 0 {
        100.0
    } else {
        100.0 * (requests.saturating_sub(failures)) as f64 / requests as f64
    };
    Some(format!(
        "{pct:.1} % ok ({requests} requests, {replies} replies, {failures} failed, {} retries, {} CRC errors)",
        link["retries"].as_u64().unwrap_or(0),
        link["crc_errors"].as_u64().unwrap_or(0)
    ))
}

/// The screen for one telemetry line (without the cursor-home prefix); every
/// line ends with clear-to-end-of-line so a redraw leaves no leftovers.
pub fn render_screen(
    t: &Value,
    link: Option<&Value>,
    header: &str,
    received_ago: Duration,
) -> String {
    let mut s = String::new();
    let mut line = |l: String| {
        s.push_str(&l);
        s.push_str(EOL);
        s.push('\n');
    };
    line(format!("{BOLD}TinyBMS{RESET} {header}"));
    let online = t["online"] == true;
    let ready = t["ready"] == true;
    if t.get("pack_voltage_v").is_none() {
        line(String::new());
        line(format!(
            "{YELLOW}no snapshot yet{RESET} (online {online}, ready {ready}): waiting for the BMS..."
        ));
        s.push_str(EOS);
        return s;
    }
    let v = num(t, "pack_voltage_v");
    let i = num(t, "pack_current_a");
    let p = match (v, i) {
        (Some(v), Some(i)) => Some(v * i),
        _ => None,
    };
    line(String::new());
    line(format!(
        "Pack   {BOLD}{}{RESET}   {BOLD}{}{RESET}   {}      SOC {BOLD}{}{RESET}   SOH {}",
        fmt_opt(v, 2, "V"),
        fmt_opt(i, 2, "A"),
        fmt_opt(p, 0, "W"),
        fmt_opt(num(t, "soc_percent"), 1, "%"),
        fmt_opt(num(t, "soh_percent"), 1, "%"),
    ));
    let status = t["online_status"].as_str().unwrap_or("-");
    let status = match status {
        "fault" => format!("{RED}{status}{RESET}"),
        _ => format!("{BOLD}{status}{RESET}"),
    };
    let temp = |k: &str| match t[k].as_f64() {
        Some(x) => format!("{x:.1} °C"),
        None => "n/c".into(),
    };
    line(format!(
        "Status {status}   Temperatures: internal {}  external {} / {}",
        temp("internal_temperature_c"),
        temp("external_temperature_1_c"),
        temp("external_temperature_2_c"),
    ));
    if let Some(left) = t["estimated_time_left_s"].as_u64() {
        let life = t["lifetime_s"].as_u64().unwrap_or(0);
        line(format!(
            "Time left {}h{:02}   BMS lifetime {}d {:02}:{:02}:{:02}",
            left / 3600,
            left / 60 % 60,
            life / 86_400,
            life / 3600 % 24,
            life / 60 % 60,
            life % 60
        ));
    }
    line(String::new());
    let cells: Vec<f64> = t["cell_voltages_v"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_f64).collect())
        .unwrap_or_default();
    let balancing = t["real_balancing_bits"].as_u64().unwrap_or(0);
    let (mut min_i, mut max_i) = (0, 0);
    for (k, c) in cells.iter().enumerate() {
        if *c < cells[min_i] {
            min_i = k;
        }
        if *c > cells[max_i] {
            max_i = k;
        }
    }
    if let (Some(lo), Some(hi)) = (cells.get(min_i), cells.get(max_i)) {
        line(format!(
            "Cells ({})  min {BLUE}#{} {:.4} V{RESET}  max {RED}#{} {:.4} V{RESET}  spread {:.1} mV   (* balancing)",
            cells.len(),
            min_i + 1,
            lo,
            max_i + 1,
            hi,
            (hi - lo) * 1000.0
        ));
    }
    for row in cells.chunks(4).enumerate() {
        let mut l = String::from(" ");
        for (j, c) in row.1.iter().enumerate() {
            let k = row.0 * 4 + j;
            let mark = if balancing >> k & 1 == 1 { '*' } else { ' ' };
            let color = if cells.len() > 1 && k == max_i {
                RED
            } else if cells.len() > 1 && k == min_i {
                BLUE
            } else {
                ""
            };
            let end = if color.is_empty() { "" } else { RESET };
            l.push_str(&format!("  {:>2} {color}{c:.4} V{end}{mark}", k + 1));
        }
        line(l);
    }
    line(String::new());
    let age = t["age_ms"]
        .as_f64()
        .map(|ms| ms / 1000.0 + received_ago.as_secs_f64());
    let flagged = match t["flagged"].as_str() {
        Some(f) => format!("   {RED}flagged: {f}{RESET}"),
        None => String::new(),
    };
    let online = if online {
        String::from("online")
    } else {
        format!("{RED}OFFLINE{RESET}")
    };
    line(format!(
        "Data age {}   seq {}   {online}{flagged}",
        fmt_opt(age, 1, "s"),
        t["seq"]
    ));
    if let Some(q) = link.and_then(link_quality) {
        line(format!("{DIM}Link {q}{RESET}"));
    }
    s.push_str(EOS);
    s
}

/// The CSV header for `cells` cells.
pub fn csv_header(cells: usize) -> String {
    let mut h = String::from(
        "time,seq,age_ms,online,pack_voltage_v,pack_current_a,soc_percent,soh_percent,\
         min_cell_voltage_v,max_cell_voltage_v,internal_temperature_c,external_temperature_1_c,\
         external_temperature_2_c,online_status,real_balancing_bits,flagged",
    );
    for k in 1..=cells {
        h.push_str(&format!(",cell_{k}_v"));
    }
    h
}

/// One CSV row of a telemetry line.
pub fn csv_row(time: &str, t: &Value, cells: usize) -> String {
    let field = |k: &str| match &t[k] {
        Value::Null => String::new(),
        Value::String(s) => s.clone(),
        other => other.to_string(),
    };
    let mut row = time.to_string();
    for k in [
        "seq",
        "age_ms",
        "online",
        "pack_voltage_v",
        "pack_current_a",
        "soc_percent",
        "soh_percent",
        "min_cell_voltage_v",
        "max_cell_voltage_v",
        "internal_temperature_c",
        "external_temperature_1_c",
        "external_temperature_2_c",
        "online_status",
        "real_balancing_bits",
        "flagged",
    ] {
        row.push(',');
        row.push_str(&field(k));
    }
    let list = t["cell_voltages_v"].as_array().cloned().unwrap_or_default();
    for k in 0..cells {
        row.push(',');
        if let Some(c) = list.get(k) {
            row.push_str(&c.to_string());
        }
    }
    row
}

struct Logger {
    path: String,
    out: std::io::BufWriter<std::fs::File>,
    format: LogFormat,
    cells: Option<usize>,
    every: Duration,
    next: Instant,
}

impl Logger {
    fn log(&mut self, t: &Value) -> ToolResult<bool> {
        if Instant::now() < self.next || t.get("pack_voltage_v").is_none() {
            return Ok(false);
        }
        self.next += self.every;
        if self.next < Instant::now() {
            self.next = Instant::now() + self.every;
        }
        let time = utc_now();
        let err = |e: std::io::Error| ToolError::failed(format!("writing the log: {e}"));
        match self.format {
            LogFormat::Csv => {
                let n = t["cell_count"].as_u64().unwrap_or(0) as usize;
                let first = self.cells.is_none();
                let cells = *self.cells.get_or_insert(n);
                let header = csv_header(cells);
                if self.out.get_ref().metadata().map(|m| m.len()).unwrap_or(0) == 0 {
                    writeln!(self.out, "{header}").map_err(err)?;
                } else if first {
                    // Appending: only under the same columns.
                    let text = std::fs::read_to_string(&self.path).map_err(err)?;
                    if text.lines().next() != Some(header.as_str()) {
                        return Err(ToolError::failed(format!(
                            "`{}` holds a log with other columns (another cell count, or not \
                             a tinybms CSV log): log to a new file",
                            self.path
                        )));
                    }
                }
                writeln!(self.out, "{}", csv_row(&time, t, cells)).map_err(err)?;
            }
            LogFormat::JsonLines => {
                let mut v = t.clone();
                if let Some(m) = v.as_object_mut() {
                    m.insert("time".into(), json!(time));
                }
                writeln!(self.out, "{v}").map_err(err)?;
            }
        }
        self.out.flush().map_err(err)?;
        Ok(true)
    }
}

/// Runs the monitor until `--count`, `--duration` or Ctrl-C.
pub fn run(client: &mut Client, o: &MonitorOptions) -> ToolResult<()> {
    let mut logger = match &o.log {
        None => None,
        Some((path, format)) => {
            let f = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .map_err(|e| ToolError::failed(format!("cannot open the log `{path}`: {e}")))?;
            Some(Logger {
                path: path.clone(),
                out: std::io::BufWriter::new(f),
                format: *format,
                cells: None,
                every: o.every,
                next: Instant::now(),
            })
        }
    };
    let start = Instant::now();
    let end = o.duration.map(|d| start + d);
    client.stream(o.period_ms)?;
    // A first picture at once, without waiting for the first push; a BMS that
    // does not answer is explained here rather than shown as an empty screen.
    let first = client.wait_ready(o.ready_timeout)?;
    client.pushed.push_front(first);
    if !o.json {
        let stdout = std::io::stdout();
        let mut out = stdout.lock();
        let _ = write!(out, "{CLEAR}{HOME}");
        let _ = out.flush();
    }
    let result = watch(client, o, &mut logger, end);
    // A bridge keeps streaming at whatever period it was last asked for: give
    // it back the one it announced.
    if let Some(p) = client.hello["stream_period_ms"].as_u64() {
        let _ = client.stream(p as u32);
    }
    result
}

fn watch(
    client: &mut Client,
    o: &MonitorOptions,
    logger: &mut Option<Logger>,
    end: Option<Instant>,
) -> ToolResult<()> {
    let screen = !o.json;
    let stdout = std::io::stdout();
    let header = format!("monitor — {} — {}", client.port, client.mode.describe());
    let mut link: Option<Value> = None;
    let mut next_link = Instant::now();
    let mut updates = 0u64;
    loop {
        if end.is_some_and(|e| Instant::now() >= e) || o.count.is_some_and(|c| updates >= c) {
            break;
        }
        if screen && Instant::now() >= next_link {
            link = client.get_one("link").ok();
            next_link = Instant::now() + Duration::from_secs(5);
        }
        let wait = end.map_or(Duration::from_secs(1), |e| {
            e.saturating_duration_since(Instant::now())
                .min(Duration::from_secs(1))
        });
        let Some(v) = client.next_pushed(wait)? else {
            continue;
        };
        if v["type"] != "telemetry" {
            continue;
        }
        // The first picture answered our `get`: print it like the pushes.
        let mut v = v;
        if let Some(m) = v.as_object_mut() {
            m.shift_remove("req");
        }
        let received = Instant::now();
        let mut counted = false;
        if let Some(l) = logger.as_mut() {
            counted |= l.log(&v)?;
        }
        if o.json {
            let mut out = stdout.lock();
            let _ = writeln!(out, "{v}");
            let _ = out.flush();
            counted = true;
        } else if screen {
            let text = render_screen(&v, link.as_ref(), &header, received.elapsed());
            let mut out = stdout.lock();
            let _ = write!(out, "{HOME}{text}");
            let _ = out.flush();
            counted |= logger.is_none();
        }
        if counted {
            updates += 1;
        }
    }
    Ok(())
}
