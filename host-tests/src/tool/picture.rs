//! What the monitor's picture says, whichever view shows it (plain text, JSON,
//! CSV, full screen in [`super::live`]): the freshness by the bridge's rule,
//! the cells, the link quality, the battery line, the options and the log
//! writer. Shared by `monitor` and `live`, which import it (not each other).

use std::io::Write;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::{json, Value};
use tinybms_firmware::host_link::lines::{HostLine, Inverter, Read};

use super::{ToolError, ToolResult};

pub use tinybms_rules::view::{
    data_age, freshness, freshness_of, freshness_text, link_quality, rule_of, Freshness,
};

/// How often the picture is redrawn without new data (plain text: how often a
/// NO DATA line repeats).
pub const REDRAW: Duration = Duration::from_millis(500);

/// How the monitor shows what it gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum View {
    /// Full screen (ratatui), on a terminal.
    Live,
    /// Plain text blocks, no escape codes.
    Plain,
    /// The telemetry lines.
    Json,
}

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
    /// How it shows the data.
    pub view: View,
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

fn fmt_opt(v: Option<f64>, decimals: usize, unit: &str) -> String {
    match v {
        Some(x) => format!("{x:.decimals$} {unit}"),
        None => "-".into(),
    }
}

/// The lowest and highest cell's index (0-based).
pub fn min_max(cells: &[f64]) -> Option<(usize, usize)> {
    let mut it = cells.iter().enumerate();
    let (_, first) = it.next()?;
    let (mut lo, mut hi) = ((0, *first), (0, *first));
    for (k, c) in it {
        if *c < lo.1 {
            lo = (k, *c);
        }
        if *c > hi.1 {
            hi = (k, *c);
        }
    }
    Some((lo.0, hi.0))
}

/// A line from the bridge read into the firmware's own types
/// (`host_link::lines`); `None` when it is not one.
fn read_line(v: &Value) -> Option<HostLine> {
    serde_json::from_value(v.clone()).ok()
}

/// The plain-text picture of one telemetry line (no escape codes): what
/// `monitor` prints when its output is not a terminal, or with `--plain`.
pub fn render_text(t: &Value, link: Option<&Value>, header: &str, f: Freshness) -> String {
    let mut s = String::new();
    let mut line = |l: String| {
        s.push_str(l.trim_end());
        s.push('\n');
    };
    line(format!("TinyBMS {header}"));
    let Some(HostLine::Telemetry(t)) = read_line(t) else {
        line(format!("not a telemetry line the bridge writes: {t}"));
        line(freshness_text(f));
        return s;
    };
    let head = &t.head;
    let Some(snap) = &t.snapshot else {
        line(format!(
            "no snapshot yet (online {}, ready {}): waiting for the BMS...",
            head.online, head.ready
        ));
        line(freshness_text(f));
        return s;
    };
    let v = snap.pack_voltage_v;
    let i = snap.pack_current_a;
    let p = match (v, i) {
        (Some(v), Some(i)) => Some(v * i),
        _ => None,
    };
    line(format!(
        "Pack   {}   {}   {}      SOC {}   SOH {}",
        fmt_opt(v, 2, "V"),
        fmt_opt(i, 2, "A"),
        fmt_opt(p, 0, "W"),
        fmt_opt(snap.soc_percent, 1, "%"),
        fmt_opt(snap.soh_percent, 1, "%"),
    ));
    let temp = |x: Option<f64>| match x {
        Some(x) => format!("{x:.1} °C"),
        None => "not connected".into(),
    };
    line(format!(
        "Status {}   Temperatures: internal {}  external {} / {}",
        snap.online_status,
        temp(snap.internal_temperature_c),
        temp(snap.external_temperature_1_c),
        temp(snap.external_temperature_2_c),
    ));
    let left = snap.estimated_time_left_s;
    let life = snap.lifetime_s;
    line(format!(
        "Time left {}h{:02}   BMS lifetime {}d {:02}:{:02}:{:02}",
        left / 3600,
        left / 60 % 60,
        life / 86_400,
        life / 3600 % 24,
        life / 60 % 60,
        life % 60
    ));
    let cells = &snap.cell_voltages_v;
    let balancing = u64::from(snap.real_balancing_bits);
    if let Some((lo, hi)) = min_max(cells) {
        line(format!(
            "Cells ({})  lowest #{} {:.4} V  highest #{} {:.4} V  spread {:.1} mV   (< lowest, > highest, * balancing)",
            cells.len(),
            lo + 1,
            cells[lo],
            hi + 1,
            cells[hi],
            (cells[hi] - cells[lo]) * 1000.0
        ));
        for (r, row) in cells.chunks(4).enumerate() {
            let mut l = String::from(" ");
            for (j, c) in row.iter().enumerate() {
                let k = r * 4 + j;
                let mark = match (k == lo && cells.len() > 1, k == hi && cells.len() > 1) {
                    (true, _) => '<',
                    (_, true) => '>',
                    _ => ' ',
                };
                let bal = if balancing >> k & 1 == 1 { '*' } else { ' ' };
                l.push_str(&format!("  {:>2} {c:.4} V{mark}{bal}", k + 1));
            }
            line(l);
        }
    }
    if let Some(inv) = &t.told.inverter {
        line(told_text(inv));
    }
    let flagged = match &snap.flagged {
        Some(fl) => format!("   flagged: {fl}"),
        None => String::new(),
    };
    line(format!("{}   seq {}{flagged}", freshness_text(f), head.seq));
    if let Some(q) = link.and_then(link_quality) {
        line(format!("Link {q}"));
    }
    s
}

/// What the inverter output does, from a `telemetry` line's `inverter`
/// member: `Inverter victron: CAN running, inverter heard   CVL 56.8 V  CCL
/// 60.0 A  DCL 60.0 A`. `None` for a bridge without CAN output.
pub fn inverter_text(t: &Value) -> Option<String> {
    match read_line(t)? {
        HostLine::Telemetry(t) => t.told.inverter.as_ref().map(told_text),
        _ => None,
    }
}

/// [`inverter_text`] of the member read.
pub fn told_text(inv: &Inverter<Read>) -> String {
    let can = match inv.can.as_str() {
        "running" => "running".to_string(),
        "waiting" => "waiting (nothing sent yet)".to_string(),
        "no_ack" => "NO ACK (nobody acknowledges: wiring, termination, bit rate?)".to_string(),
        "bus_off" => "BUS OFF (recovering)".to_string(),
        "off" => "off (can_output=off)".to_string(),
        other => other.to_string(),
    };
    let heard = if inv.heard {
        "inverter heard"
    } else {
        "inverter not heard"
    };
    let told = match (inv.cvl_v, inv.ccl_a, inv.dcl_a) {
        (Some(v), Some(c), Some(d)) => {
            format!("CVL {v:.1} V  CCL {c:.1} A  DCL {d:.1} A")
        }
        _ => "no limits sent".to_string(),
    };
    format!("Inverter {}: CAN {can}, {heard}   {told}", inv.protocol)
}

/// Packs in parallel: one line of text for a `battery` or `pack` line of a
/// bridge with a node number (what `monitor --plain` prints after each picture).
pub fn render_battery_line(v: &Value) -> String {
    let f = |x: Option<f64>, d: usize, unit: &str| fmt_opt(x, d, unit);
    match read_line(v) {
        Some(HostLine::Battery(b)) => {
            let online = b.packs_online;
            let offline = b.packs_offline;
            let who = if b.speaking {
                format!("node {} speaks to the inverter", b.node)
            } else {
                format!("node {} listens", b.node)
            };
            if online == 0 {
                return format!(
                    "Battery ({who}): no pack takes part ({offline} known): the inverter is stopped"
                );
            }
            format!(
                "Battery ({who}): {online} of {} packs   {}   SOC {}   {}   {}   cells {} to {}   sent: CVL {}  CCL {}  DCL {}",
                u16::from(online) + u16::from(offline),
                f(b.capacity_ah, 0, "Ah"),
                f(b.soc_percent, 1, "%"),
                f(b.voltage_v, 2, "V"),
                f(b.current_a, 1, "A"),
                f(b.min_cell_v, 3, "V"),
                f(b.max_cell_v, 3, "V"),
                f(b.cvl_v, 1, "V"),
                f(b.ccl_a, 1, "A"),
                f(b.dcl_a, 1, "A"),
            )
        }
        Some(HostLine::Pack(p)) => {
            let state = match p.state.as_str() {
                "part" => "in the battery",
                "lost" => "LOST (no summary)",
                "stale" => "STALE (its BMS data is old)",
                "fault" => "FAULT (its switch is open)",
                _ => "?",
            };
            format!(
                "  pack {}{}  {state}   {}   {}   SOC {}   cells {} to {}   own CCL {}  DCL {}   data age {}",
                p.node,
                if p.speaking { "*" } else { " " },
                f(p.voltage_v, 2, "V"),
                f(p.current_a, 1, "A"),
                f(p.soc_percent, 1, "%"),
                f(p.min_cell_v, 3, "V"),
                f(p.max_cell_v, 3, "V"),
                f(p.ccl_a, 1, "A"),
                f(p.dcl_a, 1, "A"),
                f(p.data_age_s, 1, "s"),
            )
        }
        _ => format!("not a battery or pack line the bridge writes: {v}"),
    }
}

/// The CSV header for `cells` cells.
pub fn csv_header(cells: usize) -> String {
    let mut h = String::from(
        "time,seq,age_ms,online,pack_voltage_v,pack_current_a,soc_percent,soh_percent,\
         min_cell_voltage_v,max_cell_voltage_v,internal_temperature_c,external_temperature_1_c,\
         external_temperature_2_c,online_status,real_balancing_bits,flagged,\
         cvl_v,ccl_a,dcl_a,can_state",
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
    // What the inverter is told (empty without CAN output or limits).
    let inv = t.get("inverter").cloned().unwrap_or(Value::Null);
    for k in ["cvl_v", "ccl_a", "dcl_a", "can"] {
        row.push(',');
        row.push_str(&match &inv[k] {
            Value::Null => String::new(),
            Value::String(s) => s.clone(),
            other => other.to_string(),
        });
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

/// The CSV / JSON Lines log (`--log`).
pub(crate) struct Logger {
    pub(crate) path: String,
    pub(crate) out: std::io::BufWriter<std::fs::File>,
    pub(crate) format: LogFormat,
    pub(crate) cells: Option<usize>,
    pub(crate) every: Duration,
    pub(crate) next: Instant,
}

impl Logger {
    pub(crate) fn log(&mut self, t: &Value) -> ToolResult<bool> {
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
