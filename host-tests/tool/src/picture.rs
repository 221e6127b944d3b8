//! What the monitor's picture says, whichever view shows it (plain text, JSON,
//! CSV, full screen in [`super::live`]): the freshness by the bridge's rule,
//! the cells, the link quality, the battery line, the options and the log
//! writer. Shared by `monitor` and `live`, which import it (not each other).

use std::io::Write;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::{json, Value};
use tinybms_firmware::host_link::schema::{
    Battery, HostLine, Inverter, Link, Pack, Read, Snapshot, Telemetry,
};

use super::{ToolError, ToolResult};

pub use tinybms_rules::view::{
    data_age, freshness, freshness_text, link_quality, rule_of, Freshness,
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

/// A number as the bridge's line had it (and `--json` prints it): the
/// shortest decimal that reads back as the same `f64`.
pub fn json_number(x: f64) -> String {
    serde_json::Number::from_f64(x).map_or_else(String::new, |n| n.to_string())
}

/// A member of the snapshot, when the line has one.
fn snap<T>(t: &Telemetry<Read>, f: impl Fn(&Snapshot<Read>) -> Option<T>) -> Option<T> {
    t.snapshot.as_ref().and_then(f)
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

/// The cell voltages of a telemetry line (none before its first snapshot).
pub fn cells_of(t: &Telemetry<Read>) -> &[f64] {
    t.snapshot
        .as_ref()
        .map_or(&[][..], |s| s.cell_voltages_v.as_slice())
}

/// The plain-text picture of one telemetry line (no escape codes): what
/// `monitor` prints when its output is not a terminal, or with `--plain`.
pub fn render_text(
    t: &Telemetry<Read>,
    link: Option<&Link<Read>>,
    header: &str,
    f: Freshness,
) -> String {
    let mut s = String::new();
    let mut line = |l: String| {
        s.push_str(l.trim_end());
        s.push('\n');
    };
    line(format!("TinyBMS {header}"));
    let Some(sn) = t.snapshot.as_ref() else {
        line(format!(
            "no snapshot yet (online {}, ready {}): waiting for the BMS...",
            t.head.online, t.head.ready
        ));
        line(freshness_text(f));
        return s;
    };
    // How fresh it is comes first: stale values are never read before the
    // word that says they are old.
    let flagged = match &sn.flagged {
        Some(fl) => format!("   flagged: {fl}"),
        None => String::new(),
    };
    line(format!(
        "{}   seq {}{flagged}",
        freshness_text(f),
        t.head.seq
    ));
    let v = sn.pack_voltage_v;
    let i = sn.pack_current_a;
    let p = match (v, i) {
        (Some(v), Some(i)) => Some(v * i),
        _ => None,
    };
    line(format!(
        "Pack   {}   {}   {}      SOC {}   SOH {}",
        fmt_opt(v, 2, "V"),
        fmt_opt(i, 2, "A"),
        fmt_opt(p, 0, "W"),
        fmt_opt(sn.soc_percent, 1, "%"),
        fmt_opt(sn.soh_percent, 1, "%"),
    ));
    line(format!(
        "Status {}   Temperatures: internal {}  external {} / {}",
        sn.online_status,
        temperature(sn.internal_temperature_c),
        temperature(sn.external_temperature_1_c),
        temperature(sn.external_temperature_2_c),
    ));
    let (left, life) = (sn.estimated_time_left_s, sn.lifetime_s);
    line(format!(
        "Time left {}h{:02}   BMS lifetime {}d {:02}:{:02}:{:02}",
        left / 3600,
        left / 60 % 60,
        life / 86_400,
        life / 3600 % 24,
        life / 60 % 60,
        life % 60
    ));
    let cells = cells_of(t);
    let balancing = u64::from(sn.real_balancing_bits);
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
    if let Some(inv) = inverter_text(t) {
        for l in inv.lines() {
            line(l.to_string());
        }
    }
    if let Some(q) = link.map(link_quality) {
        line(format!("Link {q}"));
    }
    // The wire's verdict of the last minute, when it is not healthy.
    if let Some(l) = link.filter(|l| !l.wire.is_empty() && l.wire != "healthy") {
        line(format!("  wire: {}", l.wire_verdict));
    }
    s
}

/// A temperature, or that its sensor is not connected.
pub fn temperature(c: Option<f64>) -> String {
    match c {
        Some(x) => format!("{x:.1} °C"),
        None => "not connected".into(),
    }
}

/// What the inverter output does, from a `telemetry` line's `inverter`
/// member: `Inverter victron: CAN running, inverter heard   CVL 56.8 V  CCL
/// 60.0 A  DCL 60.0 A`, and below it, each on a line of its own when there
/// is one, the stop in force with what the frames told of it, the stop the
/// inverter was seen ignoring, and the configuration changes that wait for a
/// restart. `None` for a bridge without CAN output.
pub fn inverter_text(t: &Telemetry<Read>) -> Option<String> {
    let inv: &Inverter<Read> = t.told.inverter.as_ref()?;
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
    let name = match inv.name.as_deref() {
        Some(n) if !n.is_empty() => format!(" (0x35E {n})"),
        _ => String::new(),
    };
    let mut out = format!(
        "Inverter {}{name}: CAN {can}, {heard}   {told}",
        inv.protocol
    );
    if let Some(p) = protection_text(inv) {
        out.push_str("\n  ");
        out.push_str(&p);
    }
    if let Some(r) = inv.stage_reason.as_deref() {
        out.push_str("\n  charge: ");
        out.push_str(r);
    }
    for (name, why) in [
        ("CVL", &inv.cvl_why),
        ("CCL", &inv.ccl_why),
        ("DCL", &inv.dcl_why),
    ] {
        if let Some(w) = why.as_deref() {
            out.push_str(&format!("\n  {name}: {w}"));
        }
    }
    if let Some(d) = inv.doctor.as_deref() {
        out.push_str(&format!(
            "\n  doctor: {} (tinybms doctor PORT: what to do)",
            d.replace(',', ", ")
        ));
    }
    if let Some(e) = inv.ignored.as_deref() {
        out.push_str(&format!(
            "\n  the inverter ignored a stop ({e}): every stop is told every way"
        ));
    }
    match t.head.restart_pending {
        Some(1) => out.push_str("\n  1 configuration change waits for a restart"),
        Some(n) if n > 1 => {
            out.push_str(&format!("\n  {n} configuration changes wait for a restart"))
        }
        _ => {}
    }
    Some(out)
}

/// The stops in force and what the frames told of them (`protection
/// active: charge stopped (temperature); told: charge enable off, SOC 100
/// %`); `None` when nothing must stop.
fn protection_text(inv: &Inverter<Read>) -> Option<String> {
    let stopped = |side: &str, why: &Option<String>| match why.as_deref() {
        Some(w) if w != "none" => Some(format!("{side} stopped ({w})")),
        _ => None,
    };
    let parts: Vec<String> = [
        stopped("charge", &inv.charge_stop),
        stopped("discharge", &inv.discharge_stop),
    ]
    .into_iter()
    .flatten()
    .collect();
    if parts.is_empty() {
        return None;
    }
    let on_off = |b: bool| if b { "on" } else { "off" };
    let mut told = Vec::new();
    if let Some(c) = inv.charge_enabled {
        told.push(format!("charge enable {}", on_off(c)));
    }
    if let Some(d) = inv.discharge_enabled {
        told.push(format!("discharge enable {}", on_off(d)));
    }
    if let Some(soc) = inv.soc_told {
        told.push(format!("SOC {soc} %"));
    }
    let told = if told.is_empty() {
        String::new()
    } else {
        format!("; told: {}", told.join(", "))
    };
    Some(format!("protection active: {}{told}", parts.join(", ")))
}

/// Packs in parallel: one line of text for a `battery` or `pack` line of a
/// bridge with a node number (what `monitor --plain` prints after each
/// picture); `None` for any other line.
pub fn render_battery_line(l: &HostLine) -> Option<String> {
    match l {
        HostLine::Battery(b) => Some(render_battery(b)),
        HostLine::Pack(p) => Some(render_pack(p)),
        _ => None,
    }
}

/// A `battery` line as text (see [`render_battery_line`]).
pub fn render_battery(b: &Battery<Read>) -> String {
    let (online, offline) = (u32::from(b.packs_online), u32::from(b.packs_offline));
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
        online + offline,
        fmt_opt(b.capacity_ah, 0, "Ah"),
        fmt_opt(b.soc_percent, 1, "%"),
        fmt_opt(b.voltage_v, 2, "V"),
        fmt_opt(b.current_a, 1, "A"),
        fmt_opt(b.min_cell_v, 3, "V"),
        fmt_opt(b.max_cell_v, 3, "V"),
        fmt_opt(b.cvl_v, 1, "V"),
        fmt_opt(b.ccl_a, 1, "A"),
        fmt_opt(b.dcl_a, 1, "A"),
    )
}

/// A `pack` line as text (see [`render_battery_line`]).
pub fn render_pack(p: &Pack<Read>) -> String {
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
        fmt_opt(p.voltage_v, 2, "V"),
        fmt_opt(p.current_a, 1, "A"),
        fmt_opt(p.soc_percent, 1, "%"),
        fmt_opt(p.min_cell_v, 3, "V"),
        fmt_opt(p.max_cell_v, 3, "V"),
        fmt_opt(p.ccl_a, 1, "A"),
        fmt_opt(p.dcl_a, 1, "A"),
        fmt_opt(p.data_age_s, 1, "s"),
    )
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

/// One CSV row of a telemetry line: each value as the line had it, empty
/// where it had none (the columns of [`csv_header`]).
pub fn csv_row(time: &str, t: &Telemetry<Read>, cells: usize) -> String {
    let num = |x: Option<f64>| x.map(json_number).unwrap_or_default();
    let text = |x: Option<&str>| x.unwrap_or_default().to_string();
    let of = |f: fn(&Snapshot<Read>) -> Option<f64>| num(snap(t, f));
    let columns = [
        t.head.seq.to_string(),
        t.head.age_ms.map(|a| a.to_string()).unwrap_or_default(),
        t.head.online.to_string(),
        of(|s| s.pack_voltage_v),
        of(|s| s.pack_current_a),
        of(|s| s.soc_percent),
        of(|s| s.soh_percent),
        of(|s| s.min_cell_voltage_v),
        of(|s| s.max_cell_voltage_v),
        of(|s| s.internal_temperature_c),
        of(|s| s.external_temperature_1_c),
        of(|s| s.external_temperature_2_c),
        text(t.snapshot.as_ref().map(|s| s.online_status.as_str())),
        snap(t, |s| Some(s.real_balancing_bits.to_string())).unwrap_or_default(),
        text(t.snapshot.as_ref().and_then(|s| s.flagged.as_deref())),
        // What the inverter is told (empty without CAN output or limits).
        num(t.told.inverter.as_ref().and_then(|i| i.cvl_v)),
        num(t.told.inverter.as_ref().and_then(|i| i.ccl_a)),
        num(t.told.inverter.as_ref().and_then(|i| i.dcl_a)),
        text(t.told.inverter.as_ref().map(|i| i.can.as_str())),
    ];
    let mut row = time.to_string();
    for c in columns {
        row.push(',');
        row.push_str(&c);
    }
    let list = cells_of(t);
    for k in 0..cells {
        row.push(',');
        if let Some(c) = list.get(k) {
            row.push_str(&json_number(*c));
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
    /// Logs `t` (`raw`: the JSON it came as, without its `req`) when it is
    /// time to and the line has a snapshot; true when it did.
    pub(crate) fn log(&mut self, t: &Telemetry<Read>, raw: &Value) -> ToolResult<bool> {
        if Instant::now() < self.next || t.snapshot.is_none() {
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
                let n = snap(t, |s| Some(usize::from(s.cell_count))).unwrap_or(0);
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
                let mut v = raw.clone();
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
