//! `tinybms monitor` on a terminal: a full-screen live view (ratatui) —
//! every cell as a bar with the lowest and highest marked and balancing
//! shown, the pack, a few minutes of pack voltage and current as sparklines,
//! and how fresh the data is (NO DATA / OFFLINE), redrawn on a timer.
//! `q`, Esc or Ctrl-C quits (the bridge gets its stream period back).
//!
//! [`draw`] only reads a [`LiveState`]: the tests render it into ratatui's
//! `TestBackend` and read the buffer.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use ratatui::crossterm::event::{self, Event, KeyCode, KeyEventKind, KeyModifiers};
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::style::{Color, Modifier, Style};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Block, Borders, Paragraph, Sparkline, Wrap};
use ratatui::Frame;
use tinybms_firmware::host_link::schema::{HostLine, Link, Read, Telemetry};

use super::client::{without_req, Client, Received};
use super::picture::{
    cells_of, freshness, freshness_text, inverter_text, link_quality, min_max, temperature,
    Freshness, Logger, MonitorOptions, REDRAW,
};
use super::{interrupted, interrupted_error, ToolResult};

/// How much history the sparklines show.
pub const HISTORY: Duration = Duration::from_secs(300);

/// What the view shows.
#[derive(Debug, Default)]
pub struct LiveState {
    /// `PORT — mode`.
    pub header: String,
    /// The newest telemetry line and when it arrived.
    pub telemetry: Option<(Telemetry<Read>, Instant)>,
    /// The newest `link` line.
    pub link: Option<Link<Read>>,
    /// (when, pack V, pack A), oldest first, [`HISTORY`] long.
    pub history: VecDeque<(Instant, f64, f64)>,
    /// The bridge's latest log lines (`log` lines), oldest first.
    pub logs: VecDeque<String>,
    /// Packs in parallel: the newest `battery` line and the `pack` lines that
    /// followed it, as text ([`super::picture::render_battery_line`]).
    pub battery: Vec<String>,
}

/// Log lines the view keeps.
pub const LOG_LINES: usize = 3;

impl LiveState {
    /// One of the bridge's log lines.
    pub fn log(&mut self, level: &str, text: &str) {
        if self.logs.len() >= LOG_LINES {
            self.logs.pop_front();
        }
        self.logs.push_back(format!("{level:<4} {text}"));
    }

    /// A `battery` line (it starts a new list) or a `pack` line; any other
    /// line is not for this list.
    pub fn battery_line(&mut self, l: &HostLine) {
        let Some(text) = super::picture::render_battery_line(l) else {
            return;
        };
        if matches!(l, HostLine::Battery(_)) {
            self.battery.clear();
        }
        if self.battery.len() <= usize::from(tinybms_firmware::inverter::packs::MAX_NODES) {
            self.battery.push(text.trim().to_string());
        }
    }

    /// A new telemetry line.
    pub fn update(&mut self, t: Telemetry<Read>, now: Instant) {
        if let Some((v, i)) = t
            .snapshot
            .as_ref()
            .and_then(|s| Some((s.pack_voltage_v?, s.pack_current_a?)))
        {
            self.history.push_back((now, v, i));
        }
        while self
            .history
            .front()
            .is_some_and(|(at, _, _)| now.duration_since(*at) > HISTORY)
        {
            self.history.pop_front();
        }
        self.telemetry = Some((t, now));
    }
}

fn num(x: Option<f64>, decimals: usize, unit: &str) -> String {
    match x {
        Some(x) => format!("{x:.decimals$} {unit}"),
        None => "-".into(),
    }
}

/// Sparkline values: `x` scaled into 0..=100 over the window's min..max.
fn scaled(xs: &[f64], resolution: f64) -> Vec<u64> {
    let lo = xs.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    // A range below what the title can show (52.90..52.90 V) is flat: bars
    // of different heights would show a change nobody can read.
    if hi - lo < resolution {
        return vec![50; xs.len()];
    }
    let span = hi - lo;
    xs.iter()
        .map(|x| (1.0 + 99.0 * (x - lo) / span).round() as u64)
        .collect()
}

/// The smallest window the live view draws in: every cell of a 16-cell pack
/// in two columns with the pack and the footer; what does not fit then goes
/// in this order: the charts, the log's older lines, the packs in parallel.
pub const MIN_SIZE: (u16, u16) = (64, 24);

/// The cell bars span at least this much, V: a healthy pack's few mV of
/// spread must not look like a cell falling out.
pub const CELL_SCALE_MIN_V: f64 = 0.050;

/// How the window's rows go, cells first: the top line, the pack, the
/// freshness lines and every cell (in one column when there is room, else two)
/// always; then, as rows are left, the packs in parallel, the log (its newest
/// lines) and the two charts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Rows {
    cells: u16,
    charts: u16,
    battery: u16,
    log: u16,
}

/// The charts' height.
const CHART_ROWS: u16 = 6;

impl Rows {
    fn fit(height: u16, pack: u16, cells: usize, battery: usize, logs: usize) -> Self {
        let fixed = 1 + pack + 2;
        let left = height.saturating_sub(fixed);
        let cells = cells as u16;
        let two_columns = 1 + cells.div_ceil(2);
        let one_column = 1 + cells;
        let mut rest = left.saturating_sub(two_columns.max(4));
        let battery = if battery == 0 {
            0
        } else {
            (1 + battery as u16).min(rest)
        };
        rest -= battery;
        let log = if logs == 0 || rest < 2 {
            0
        } else {
            (1 + logs as u16).min(rest)
        };
        rest -= log;
        let charts = if rest >= CHART_ROWS { CHART_ROWS } else { 0 };
        rest -= charts;
        // What is left widens the cells to one column when it is enough.
        let cells = if rest + two_columns >= one_column {
            one_column
        } else {
            two_columns.max(4)
        };
        Self {
            cells,
            charts,
            battery,
            log,
        }
    }
}

/// The pack's lines (pack, status and temperatures, the inverter), values
/// bold when `live`, dimmed when not.
fn pack_lines(t: &Telemetry<Read>, live: bool, alarm: Style) -> Vec<Line<'static>> {
    // Pack, status, temperatures (nothing known before the first snapshot).
    let sn = t.snapshot.as_ref();
    let of =
        |f: fn(&tinybms_firmware::host_link::schema::Snapshot<Read>) -> Option<f64>| sn.and_then(f);
    let p = match (of(|s| s.pack_voltage_v), of(|s| s.pack_current_a)) {
        (Some(v), Some(i)) => format!("{:.0} W", v * i),
        _ => "-".into(),
    };
    let temp = |f| temperature(of(f));
    // Data that is not fresh is shown as what it is: the last known values,
    // dimmed, grey bars, and no status the BMS is not saying now.
    let last = sn.map_or("-", |s| s.online_status.as_str());
    let status = if live {
        last.to_string()
    } else {
        format!("unknown (last known: {last})")
    };
    let bold = if live {
        Style::new().add_modifier(Modifier::BOLD)
    } else {
        Style::new().add_modifier(Modifier::DIM)
    };
    let status_style = if live && last == "fault" { alarm } else { bold };
    let lines = vec![
        Line::from(vec![
            Span::raw("Pack "),
            Span::styled(num(of(|s| s.pack_voltage_v), 2, "V"), bold),
            Span::raw("  "),
            Span::styled(num(of(|s| s.pack_current_a), 2, "A"), bold),
            Span::raw(format!("  {p}   SOC ")),
            Span::styled(num(of(|s| s.soc_percent), 1, "%"), bold),
            Span::raw(format!("   SOH {}", num(of(|s| s.soh_percent), 1, "%"))),
        ]),
        Line::from(vec![
            Span::raw("Status "),
            Span::styled(status, status_style),
            Span::raw(format!(
                "   internal {}   external {} / {}",
                temp(|s| s.internal_temperature_c),
                temp(|s| s.external_temperature_1_c),
                temp(|s| s.external_temperature_2_c)
            )),
        ]),
    ];
    let mut lines = lines;
    if let Some(inv) = inverter_text(t) {
        for l in inv.lines() {
            let trouble = l.contains("NO ACK") || l.contains("BUS OFF") || l.contains("ignored");
            lines.push(Line::styled(
                l.to_string(),
                if trouble { alarm } else { Style::new() },
            ));
        }
    }
    lines.into_iter().map(glue).collect()
}

/// A no-break space: the paragraph never wraps at it.
const NBSP: char = '\u{a0}';

/// Figures kept whole where a line wraps in a narrow window: the space
/// between a label and its number (`CVL 56.8`) and between a number and its
/// unit (`56.8 V`) becomes a no-break space, so the paragraph wraps only
/// between figures.
fn glue(line: Line<'static>) -> Line<'static> {
    let text: Vec<char> = line.spans.iter().flat_map(|s| s.content.chars()).collect();
    let at = |i: Option<usize>| i.and_then(|i| text.get(i)).copied();
    let unit = |c: char| matches!(c, 'V' | 'A' | 'W' | '%' | '°' | 's' | 'm' | 'k' | 'h');
    let keep = |i: usize| {
        let (prev, next, next2) = (at(i.checked_sub(1)), at(Some(i + 1)), at(Some(i + 2)));
        let number_next = next.is_some_and(|c| c.is_ascii_digit())
            || (next == Some('-') && next2.is_some_and(|c| c.is_ascii_digit()));
        let label_before = prev.is_some_and(|c| c.is_alphabetic() || c == '/');
        let number_before = prev.is_some_and(|c| c.is_ascii_digit());
        (number_next && label_before) || (number_before && next.is_some_and(unit))
    };
    let mut i = 0;
    let spans = line
        .spans
        .into_iter()
        .map(|span| {
            let content: String = span
                .content
                .chars()
                .map(|c| {
                    let glued = if c == ' ' && keep(i) { NBSP } else { c };
                    i += 1;
                    glued
                })
                .collect();
            Span::styled(content, span.style)
        })
        .collect::<Vec<_>>();
    Line::from(spans).style(line.style)
}

/// `text` in `width` columns, never cut inside a figure: whole as it is when
/// it fits, else up to the last gap between its parts (three spaces) or,
/// without one, the last space that fits, then ` …`.
fn fit(text: &str, width: u16) -> String {
    let width = usize::from(width);
    if text.chars().count() <= width {
        return text.to_string();
    }
    // The last cut at a gap (else at a space) whose head and ` …` fit.
    let fits = |p: &usize| text.get(..*p).map_or(0, |h| h.chars().count()) + 2 <= width;
    let last_fit = |sep: &str| {
        text.match_indices(sep)
            .map(|(p, _)| p)
            .filter(|p| *p > 0)
            .take_while(fits)
            .last()
    };
    let cut = last_fit("   ")
        .or_else(|| last_fit(" "))
        .unwrap_or_else(|| {
            text.char_indices()
                .nth(width.saturating_sub(2))
                .map_or(text.len(), |(i, _)| i)
        });
    format!("{} …", text.get(..cut).unwrap_or("").trim_end())
}

/// Rows `text` takes in `width` columns wrapped at its spaces, as the
/// paragraph wraps it (at least one).
fn rows_for(text: &str, width: u16) -> u16 {
    let width = usize::from(width.max(1));
    let (mut rows, mut col) = (1u16, 0usize);
    for word in text.split(' ') {
        let w = word.chars().count();
        if col > 0 && col + 1 + w > width {
            rows = rows.saturating_add(1);
            col = w;
        } else {
            col += usize::from(col > 0) + w;
        }
        while col > width {
            rows = rows.saturating_add(1);
            col -= width;
        }
    }
    rows
}

/// Draws the view of `s` at `now`.
pub fn draw(f: &mut Frame, s: &LiveState, now: Instant) {
    let area = f.area();
    if area.width < MIN_SIZE.0 || area.height < MIN_SIZE.1 {
        return draw_too_small(f, area);
    }
    let fresh = freshness(
        s.telemetry.as_ref().map(|(t, _)| t),
        s.telemetry
            .as_ref()
            .map_or(Duration::MAX, |(_, at)| now.saturating_duration_since(*at)),
    );
    let alarm = Style::new()
        .fg(Color::White)
        .bg(Color::Red)
        .add_modifier(Modifier::BOLD);
    // The pack's lines wrap rather than lose their end (the limits, what to
    // check when nobody acknowledges) in a narrow window: as many rows as
    // they take.
    let lines = s
        .telemetry
        .as_ref()
        .map(|(t, _)| pack_lines(t, matches!(fresh, Freshness::Fresh(_)), alarm));
    let pack_rows = 1 + lines.as_ref().map_or(2, |lines| {
        lines
            .iter()
            .map(|l| {
                let text: String = l.spans.iter().map(|s| s.content.as_ref()).collect();
                rows_for(&text, area.width)
            })
            .sum()
    });
    let rows = Rows::fit(
        area.height,
        pack_rows,
        s.telemetry.as_ref().map_or(0, |(t, _)| cells_of(t).len()),
        s.battery.len(),
        s.logs.len(),
    );
    let [top, pack, cells_area, spark_area, foot, battery_area, log_area] = Layout::vertical([
        Constraint::Length(1),
        Constraint::Length(pack_rows),
        Constraint::Min(rows.cells),
        Constraint::Length(rows.charts),
        Constraint::Length(2),
        Constraint::Length(rows.battery),
        Constraint::Length(rows.log),
    ])
    .areas(area);
    draw_panes(f, s, &rows, battery_area, log_area);
    let state = match fresh {
        Freshness::Fresh(_) => {
            Span::styled(" online ", Style::new().fg(Color::Black).bg(Color::Green))
        }
        Freshness::Offline(_) => Span::styled(" OFFLINE ", alarm),
        Freshness::NoData(_) => Span::styled(" NO DATA ", alarm),
    };
    f.render_widget(
        Paragraph::new(Line::from(vec![
            Span::styled("TinyBMS ", Style::new().add_modifier(Modifier::BOLD)),
            Span::raw(format!("{}  ", s.header)),
            state,
            Span::raw("   q quits"),
        ])),
        top,
    );
    let (Some((t, _)), Some(lines)) = (s.telemetry.as_ref(), lines) else {
        f.render_widget(Paragraph::new("waiting for the first data..."), pack);
        return;
    };
    let live = matches!(fresh, Freshness::Fresh(_));
    f.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: false })
            .block(Block::new().borders(Borders::TOP)),
        pack,
    );
    draw_cells(f, t, cells_area, live);
    draw_charts(f, s, &rows, spark_area, live);
    draw_foot(f, s, t, fresh, alarm, foot);
}

/// What a window too small for the view shows.
fn draw_too_small(f: &mut Frame, area: Rect) {
    f.render_widget(
        Paragraph::new(vec![
            Line::raw(format!(
                "window too small: {}x{}, the live view needs {}x{}",
                area.width, area.height, MIN_SIZE.0, MIN_SIZE.1
            )),
            Line::raw("make it larger, or use `tinybms monitor PORT --plain`"),
            Line::raw("q quits"),
        ]),
        area,
    );
}

/// The packs in parallel and the bridge's log, as many lines as `rows` gives them.
fn draw_panes(f: &mut Frame, s: &LiveState, rows: &Rows, battery_area: Rect, log_area: Rect) {
    if rows.battery > 0 {
        let shown = usize::from(rows.battery - 1);
        let lines: Vec<Line> = s
            .battery
            .iter()
            .take(shown)
            .map(|l| Line::raw(fit(l, battery_area.width)))
            .collect();
        f.render_widget(
            Paragraph::new(lines).block(
                Block::new()
                    .borders(Borders::TOP)
                    .title("Packs in parallel (* speaks to the inverter)"),
            ),
            battery_area,
        );
    }
    if rows.log > 0 {
        let shown = usize::from(rows.log - 1);
        let lines: Vec<Line> = s
            .logs
            .iter()
            .skip(s.logs.len().saturating_sub(shown))
            .map(|l| Line::raw(fit(l, log_area.width)))
            .collect();
        f.render_widget(
            Paragraph::new(lines)
                .block(Block::new().borders(Borders::TOP).title("The bridge's log")),
            log_area,
        );
    }
}

/// The pack's voltage and current over the last minutes (greyed when not `live`).
fn draw_charts(f: &mut Frame, s: &LiveState, rows: &Rows, spark_area: Rect, live: bool) {
    // Sparklines, when the window has room for them after the cells.
    let [vs, is] = Layout::horizontal([Constraint::Percentage(50), Constraint::Percentage(50)])
        .areas(spark_area);
    let volts: Vec<f64> = s.history.iter().map(|(_, v, _)| *v).collect();
    let amps: Vec<f64> = s.history.iter().map(|(_, _, i)| *i).collect();
    let range = |xs: &[f64], unit: &str| {
        let lo = xs.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if xs.is_empty() {
            String::new()
        } else {
            format!(" {lo:.2}..{hi:.2} {unit}")
        }
    };
    for (area, xs, title, unit) in [
        (vs, &volts, "Pack voltage", "V"),
        (is, &amps, "Current", "A"),
    ] {
        if rows.charts == 0 {
            break;
        }
        let w = area.width.saturating_sub(2) as usize;
        // The title shows two decimals.
        let data = scaled(xs, 0.005);
        let data = &data[data.len().saturating_sub(w)..];
        f.render_widget(
            Sparkline::default()
                .block(Block::bordered().title(format!(
                    "{title}, last {} min{}",
                    HISTORY.as_secs() / 60,
                    range(xs, unit)
                )))
                .data(data)
                .max(100)
                // History stays on screen when the BMS goes silent, greyed
                // like the cells: nothing drawn in colour is stale.
                .style(Style::new().fg(if live { Color::Cyan } else { Color::DarkGray })),
            area,
        );
    }
}

/// How fresh the data is, its sequence number and flag, and the link's quality.
fn draw_foot(
    f: &mut Frame,
    s: &LiveState,
    t: &Telemetry<Read>,
    fresh: Freshness,
    alarm: Style,
    foot: Rect,
) {
    // Freshness and link.
    let mut foot_lines = vec![Line::from(vec![
        Span::styled(
            freshness_text(fresh),
            if matches!(fresh, Freshness::Fresh(_)) {
                Style::new()
            } else {
                alarm
            },
        ),
        Span::raw(format!("   seq {}", t.head.seq)),
        Span::styled(
            t.snapshot
                .as_ref()
                .and_then(|s| s.flagged.as_deref())
                .map(|fl| format!("   flagged: {fl}"))
                .unwrap_or_default(),
            alarm,
        ),
    ])];
    if let Some(q) = s.link.as_ref().map(link_quality) {
        foot_lines.push(Line::styled(
            format!("Link {q}"),
            Style::new().add_modifier(Modifier::DIM),
        ));
    }
    f.render_widget(Paragraph::new(foot_lines), foot);
}

/// Every cell as a bar (scaled over the pack's own spread), the lowest blue,
/// the highest red, a `*` where the BMS balances.
fn draw_cells(f: &mut Frame, t: &Telemetry<Read>, area: Rect, live: bool) {
    let cells = cells_of(t);
    let balancing = t
        .snapshot
        .as_ref()
        .map_or(0, |s| u64::from(s.real_balancing_bits));
    let Some((lo_i, hi_i)) = min_max(cells) else {
        return;
    };
    let (lo, hi) = (cells[lo_i], cells[hi_i]);
    // The bars start below the lowest cell (so it still shows) and span at
    // least CELL_SCALE_MIN_V: a few mV of spread look like a few mV.
    let floor = hi - ((hi - lo) * 1.25).max(CELL_SCALE_MIN_V);
    // The title's parts, most important first: as many as the width holds,
    // none cut (a cut figure reads as another figure).
    let parts = [
        format!(
            "{}Cells ({})",
            if live { "" } else { "Last known: " },
            cells.len()
        ),
        format!("  lowest #{} {lo:.4} V", lo_i + 1),
        format!("  highest #{} {hi:.4} V", hi_i + 1),
        format!("  spread {:.1} mV", (hi - lo) * 1000.0),
        format!("  bars from {floor:.3} V"),
        "  * balancing".to_string(),
    ];
    let mut title = String::new();
    for part in parts {
        if title.chars().count() + part.chars().count() > usize::from(area.width) {
            break;
        }
        title.push_str(&part);
    }
    let block = Block::new().borders(Borders::TOP).title(title);
    let inner = block.inner(area);
    f.render_widget(block, area);
    let columns: usize = if inner.height as usize >= cells.len() {
        1
    } else {
        2
    };
    let per_col = cells.len().div_ceil(columns);
    if per_col > inner.height as usize {
        // Never a cell left out in silence.
        f.render_widget(
            Paragraph::new(format!(
                "window too low for {} cells: {} more rows, or `--plain`",
                cells.len(),
                per_col - inner.height as usize
            )),
            inner,
        );
        return;
    }
    let col_w = (inner.width as usize / columns).max(20);
    let bar_w = col_w.saturating_sub(18).max(1);
    let mut lines: Vec<Line> = Vec::new();
    for row in 0..per_col {
        let mut spans = Vec::new();
        for col in 0..columns {
            let k = col * per_col + row;
            let Some(c) = cells.get(k) else { continue };
            let frac = ((c - floor) / (hi - floor).max(1e-9)).clamp(0.0, 1.0);
            let n = (frac * bar_w as f64).round() as usize;
            let color = if !live {
                Color::DarkGray
            } else if cells.len() > 1 && k == hi_i {
                Color::Red
            } else if cells.len() > 1 && k == lo_i {
                Color::Blue
            } else {
                Color::Green
            };
            let mark = if balancing >> k & 1 == 1 { '*' } else { ' ' };
            spans.push(Span::raw(format!("{:>2} {c:.4} V{mark} ", k + 1)));
            spans.push(Span::styled("█".repeat(n), Style::new().fg(color)));
            spans.push(Span::raw(" ".repeat(bar_w - n + 1)));
        }
        lines.push(Line::from(spans));
    }
    f.render_widget(Paragraph::new(lines), inner);
}

/// Runs the live view until `q`/Esc/Ctrl-C, `--count` or `--duration`.
pub(super) fn run(
    client: &mut Client,
    o: &MonitorOptions,
    title: &str,
    logger: &mut Option<Logger>,
    end: Option<Instant>,
) -> ToolResult<()> {
    let mut s = LiveState {
        header: title.to_string(),
        ..LiveState::default()
    };
    let mut terminal = ratatui::init();
    let result = (|| -> ToolResult<()> {
        let mut updates = 0u64;
        let mut next_link = Instant::now();
        let mut next_draw = Instant::now();
        loop {
            if interrupted() {
                return Err(interrupted_error());
            }
            if end.is_some_and(|e| Instant::now() >= e) || o.count.is_some_and(|c| updates >= c) {
                return Ok(());
            }
            if Instant::now() >= next_link {
                s.link = client.link().ok();
                next_link = Instant::now() + Duration::from_secs(5);
            }
            // Keys (raw mode: Ctrl-C is a key here, not a signal).
            while event::poll(Duration::ZERO).unwrap_or(false) {
                if let Ok(Event::Key(k)) = event::read() {
                    let ctrl_c =
                        k.code == KeyCode::Char('c') && k.modifiers.contains(KeyModifiers::CONTROL);
                    if k.kind == KeyEventKind::Press && ctrl_c {
                        // Ctrl-C ends every command alike: status 130.
                        return Err(interrupted_error());
                    }
                    if k.kind == KeyEventKind::Press
                        && matches!(k.code, KeyCode::Char('q') | KeyCode::Esc)
                    {
                        return Ok(());
                    }
                }
            }
            if let Some(Received { line, raw }) = client.next_pushed(Duration::from_millis(50))? {
                match line {
                    HostLine::Log(l) => {
                        s.log(&l.level, &l.text);
                        next_draw = Instant::now();
                    }
                    l @ (HostLine::Battery(_) | HostLine::Pack(_)) => {
                        s.battery_line(&l);
                        next_draw = Instant::now();
                    }
                    HostLine::Telemetry(t) => {
                        if let Some(l) = logger.as_mut() {
                            l.log(&t, &without_req(raw))?;
                        }
                        s.update(t, Instant::now());
                        updates += 1;
                        next_draw = Instant::now();
                    }
                    _ => {}
                }
            }
            if Instant::now() >= next_draw {
                let now = Instant::now();
                let _ = terminal.draw(|f| draw(f, &s, now));
                next_draw = now + REDRAW;
            }
        }
    })();
    ratatui::restore();
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use ratatui::backend::TestBackend;
    use ratatui::Terminal;
    use serde_json::{json, Value};

    use crate::client::fixtures::{line, telemetry_line as decoded};

    fn screen(s: &LiveState, now: Instant) -> String {
        let mut term = Terminal::new(TestBackend::new(100, 40)).unwrap();
        term.draw(|f| draw(f, s, now)).unwrap();
        let buf = term.backend().buffer().clone();
        let mut out = String::new();
        for y in 0..buf.area.height {
            for x in 0..buf.area.width {
                out.push_str(buf[(x, y)].symbol());
            }
            out.push('\n');
        }
        // A no-break space shows as a space.
        out.replace(NBSP, " ")
    }

    /// A telemetry line as the bridge writes it (`host_link::schema::Telemetry`).
    fn telemetry_json(online: bool) -> Value {
        json!({"type":"telemetry","seq":7,"age_ms":200,"online":online,
            "ready":true,"pack_voltage_v":52.9,"pack_current_a":-10.0,"min_cell_voltage_v":3.29,
            "max_cell_voltage_v":3.31,"cell_voltages_v":[3.30,3.31,3.29,3.305],
            "cell_first_register":0,"cell_count":4,"soc_percent":65.0,"soh_percent":97.0,
            "lifetime_s":86_400,"estimated_time_left_s":36_000,
            "internal_temperature_c":27.0,"external_temperature_1_c":null,
            "external_temperature_2_c":24.8,"online_status":"discharging",
            "balancing_decision_bits":2,"real_balancing_bits":2,"speed_kmh":0.0,
            "distance_left_km":0,"flagged":null})
    }

    fn telemetry(online: bool) -> Telemetry<Read> {
        decoded(telemetry_json(online))
    }

    /// Fresh telemetry of 16 cells (3.305..3.312 V) with `inverter`'s line.
    fn sixteen_cells_and(inverter: Value) -> Telemetry<Read> {
        let mut t = telemetry_json(true);
        let cells: Vec<f64> = (0..16).map(|k| 3.305 + f64::from(k % 8) * 0.001).collect();
        t["cell_voltages_v"] = json!(cells);
        t["cell_count"] = json!(16);
        t["inverter"] = inverter;
        decoded(t)
    }

    #[test]
    fn cells_pack_and_freshness_are_on_the_screen() {
        let t0 = Instant::now();
        let mut s = LiveState {
            header: "/dev/x — through the bridge".into(),
            ..LiveState::default()
        };
        s.update(telemetry(true), t0);
        let text = screen(&s, t0 + Duration::from_millis(300));
        assert!(
            text.contains("52.90 V") && text.contains("-10.00 A"),
            "{text}"
        );
        assert!(text.contains("lowest #3 3.2900 V"), "{text}");
        assert!(text.contains("highest #2 3.3100 V"), "{text}");
        assert!(text.contains(" 2 3.3100 V*"), "balancing mark: {text}");
        assert!(text.contains("not connected"), "{text}");
        assert!(text.contains("Data age 0.5 s"), "{text}");
        assert!(text.contains(" online "), "{text}");
        assert!(!text.contains("NO DATA"), "{text}");
    }

    /// The age keeps counting without new lines; past 5 s the view says NO
    /// DATA (a frozen bridge sends nothing that could say so).
    #[test]
    fn old_data_is_no_data_and_a_lost_bms_is_offline() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        s.update(telemetry(true), t0);
        let text = screen(&s, t0 + Duration::from_secs(3));
        assert!(text.contains("Data age 3.2 s"), "{text}");
        let text = screen(&s, t0 + Duration::from_secs(9));
        assert!(text.contains("NO DATA"), "{text}");
        assert!(text.contains("newest data 9.2 s old"), "{text}");
        let mut s = LiveState::default();
        s.update(telemetry(false), t0);
        s.log("warn", "BMS offline after 3 failed requests");
        let text = screen(&s, t0 + Duration::from_millis(100));
        assert!(text.contains("OFFLINE"), "{text}");
        assert!(
            text.contains("warn BMS offline after 3 failed requests"),
            "{text}"
        );
    }

    #[test]
    fn the_battery_and_its_packs_are_under_the_pack() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        s.update(telemetry(true), t0);
        s.battery_line(&line(
            json!({"type":"battery","node":2,"speaking":false,"packs_online":2,
            "packs_offline":0,"capacity_ah":560.0,"soc_percent":65.0,"soh_percent":100.0,
            "voltage_v":53.2,"current_a":-8.2,"min_cell_v":3.301,"max_cell_v":3.345,
            "min_temperature_c":21.5,"max_temperature_c":24.8,"cvl_v":55.2,"ccl_a":100.0,
            "dcl_a":200.0}),
        ));
        for (node, speaking) in [(1, true), (2, false)] {
            s.battery_line(&line(
                json!({"type":"pack","node":node,"state":"part","speaking":speaking,
                "voltage_v":53.2,"current_a":-4.1,"soc_percent":65.0,"soh_percent":100,
                "min_cell_v":3.301,"max_cell_v":3.345,"min_temperature_c":21.5,
                "max_temperature_c":24.8,"capacity_ah":280.0,"data_age_s":0.3,"cvl_v":55.2,
                "ccl_a":58.8,"dcl_a":117.6}),
            ));
        }
        let text = screen(&s, t0);
        assert!(text.contains("Packs in parallel"), "{text}");
        assert!(
            text.contains("Battery (node 2 listens): 2 of 2 packs"),
            "{text}"
        );
        assert!(text.contains("pack 1*  in the battery"), "{text}");
        assert!(text.contains("pack 2   in the battery"), "{text}");
        // A new battery line starts the list again.
        s.battery_line(&line(
            json!({"type":"battery","node":2,"speaking":false,"packs_online":0,
            "packs_offline":2,"capacity_ah":null,"soc_percent":null,"soh_percent":null,
            "voltage_v":null,"current_a":null,"min_cell_v":null,"max_cell_v":null,
            "min_temperature_c":null,"max_temperature_c":null,"cvl_v":null,"ccl_a":null,
            "dcl_a":null}),
        ));
        assert_eq!(s.battery.len(), 1);
    }

    fn screen_of(s: &LiveState, now: Instant, w: u16, h: u16) -> String {
        let mut term = Terminal::new(TestBackend::new(w, h)).unwrap();
        term.draw(|f| draw(f, s, now)).unwrap();
        let buf = term.backend().buffer().clone();
        let mut out = String::new();
        for y in 0..buf.area.height {
            for x in 0..buf.area.width {
                out.push_str(buf[(x, y)].symbol());
            }
            out.push('\n');
        }
        // A no-break space shows as a space.
        out.replace(NBSP, " ")
    }

    fn sixteen_cells() -> Telemetry<Read> {
        let mut t = telemetry_json(true);
        let cells: Vec<f64> = (0..16).map(|k| 3.305 + f64::from(k % 8) * 0.001).collect();
        t["cell_voltages_v"] = json!(cells);
        t["cell_count"] = json!(16);
        decoded(t)
    }

    /// Issue 26, item 11: a 60x20 terminal dropped cells 8 and 16 and cut
    /// text in silence; a window too small now says so, and at the smallest
    /// size every cell is there.
    #[test]
    fn a_small_window_says_so_and_the_smallest_shows_every_cell() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        s.update(sixteen_cells(), t0);
        let text = screen_of(&s, t0, 60, 20);
        assert!(text.contains("window too small: 60x20"), "{text}");
        let text = screen_of(&s, t0, MIN_SIZE.0, MIN_SIZE.1);
        for k in 1..=16 {
            assert!(text.contains(&format!("{k:>2} 3.3")), "cell {k}: {text}");
        }
    }

    /// Issue 42, item 3: in an 80x24 terminal (most terminals' default) with
    /// the log and the inverter's line, the monitor showed no cell at all
    /// ("window too low for 16 cells"); the cells come before the charts.
    #[test]
    fn every_cell_shows_in_an_80x24_window_with_the_log_and_the_inverter() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        s.update(
            sixteen_cells_and(json!({"protocol":"victron","can":"sending","heard":true,
                "cvl_v":56.8,"ccl_a":60.0,"dcl_a":60.0})),
            t0,
        );
        for k in 0..5 {
            s.log("info", &format!("log line {k}"));
        }
        for (w, h) in [(80, 24), (MIN_SIZE.0, MIN_SIZE.1), (120, 30)] {
            let text = screen_of(&s, t0, w, h);
            assert!(!text.contains("too low"), "{w}x{h}: {text}");
            for k in 1..=16 {
                assert!(
                    text.contains(&format!("{k:>2} 3.3")),
                    "{w}x{h}: cell {k}: {text}"
                );
            }
            assert!(text.contains("Inverter"), "{w}x{h}: {text}");
            assert!(
                text.contains("log line 4"),
                "{w}x{h}: the newest log line: {text}"
            );
        }
        // Room left over gives the charts back.
        assert!(screen_of(&s, t0, 120, 40).contains("Pack voltage, last"));
    }

    /// Seen on an 80x24 capture of the real monitor: the inverter's line lost
    /// its end ("DCL 60.0" without its unit; with nobody acknowledging, what
    /// to check) and the cells' title was cut mid-figure. Now the inverter's
    /// line wraps and the title keeps only whole parts.
    #[test]
    fn no_line_is_cut_in_a_narrow_window() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        s.update(
            sixteen_cells_and(json!({"protocol":"victron","can":"no_ack","heard":false,
                "cvl_v":56.8,"ccl_a":120.0,"dcl_a":150.0})),
            t0,
        );
        s.battery = vec![
            "Battery (node 1 speaks to the inverter): 3 of 3 packs   840 Ah   SOC 62.1 %   53.06 V   28.3 A".into(),
            "  pack 1*  in the battery   53.06 V   28.3 A   SOC 60.1 %   cells 3.313 V to 3.320 V".into(),
        ];
        for (w, h) in [(80, 24), (MIN_SIZE.0, MIN_SIZE.1)] {
            let text = screen_of(&s, t0, w, h);
            // A panel line too long for the window ends at a gap, marked.
            let battery = text
                .lines()
                .find(|l| l.starts_with("Battery"))
                .unwrap_or_else(|| panic!("{w}x{h}: {text}"));
            assert!(battery.trim_end().ends_with(" …"), "{w}x{h}: {battery}");
            assert!(!battery.contains(" 53 "), "{w}x{h}: {battery}");
            // The screen's rows joined: a wrapped line reads whole.
            let joined = text
                .lines()
                .map(str::trim_end)
                .collect::<Vec<_>>()
                .join(" ");
            assert!(joined.contains("DCL 150.0 A"), "{w}x{h}: {text}");
            assert!(joined.contains("bit rate?"), "{w}x{h}: {text}");
            let title = text
                .lines()
                .find(|l| l.contains("Cells (16)"))
                .unwrap_or_else(|| panic!("{w}x{h}: {text}"));
            let title = title.trim_end_matches(['─', ' ']);
            assert!(
                title.ends_with(" V") || title.ends_with(" mV") || title.ends_with("balancing"),
                "{w}x{h}: the title cut: {title}"
            );
            for k in 1..=16 {
                assert!(text.contains(&format!("{k:>2} 3.3")), "{w}x{h}: cell {k}");
            }
        }
        assert_eq!(fit("pack 1   53.06 V   28.3 A", 20), "pack 1   53.06 V …");
        assert_eq!(fit("BMS 27.0 °C now", 12), "BMS 27.0 …");
        assert_eq!(fit("short", 20), "short");
        assert_eq!(fit("abcdefghij", 6), "abcd …");
        assert_eq!(rows_for("a bb ccc", 4), 2);
        assert_eq!(rows_for("a bb ccc dd", 4), 3);
        assert_eq!(rows_for("abcdefgh", 4), 2);
        assert_eq!(rows_for("", 4), 1);
    }

    /// Issue 42, item 4: with the BMS silent the monitor kept the last values
    /// bold, the bars green and "Status discharging": only the badge said
    /// OFFLINE. Now the values are the last known ones, dimmed, in grey bars,
    /// and no status is claimed.
    #[test]
    fn offline_data_does_not_look_live() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        s.update(telemetry(false), t0);
        let mut term = Terminal::new(TestBackend::new(100, 40)).unwrap();
        term.draw(|f| draw(f, &s, t0)).unwrap();
        let buf = term.backend().buffer().clone();
        let text = screen(&s, t0);
        assert!(text.contains("OFFLINE"), "{text}");
        assert!(
            text.contains("Status unknown (last known: discharging)"),
            "{text}"
        );
        assert!(!text.contains("Status discharging"), "{text}");
        assert!(text.contains("Last known: Cells (4)"), "{text}");
        let bars: Vec<_> = buf
            .content()
            .iter()
            .filter(|c| c.symbol() == "█")
            .map(|c| c.fg)
            .collect();
        assert!(!bars.is_empty());
        assert!(bars.iter().all(|c| *c == Color::DarkGray), "{bars:?}");
        // Fresh again: colours and the status come back.
        s.update(telemetry(true), t0);
        let text = screen(&s, t0);
        assert!(text.contains("Status discharging"), "{text}");
    }

    /// Issue 26, item 11: bars over a 7 mV spread looked alarming, and a
    /// chart titled 52.90..52.90 V drew bars of different heights.
    #[test]
    fn cell_bars_span_at_least_50_mv_and_a_flat_chart_is_flat() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        s.update(sixteen_cells(), t0);
        let text = screen(&s, t0);
        // 3.305..3.312 V: the scale is 50 mV down from the highest cell.
        assert!(text.contains("bars from 3.262 V"), "{text}");
        // The lowest cell's bar is most of the highest's, not a sliver.
        let bar = |cell: &str| {
            text.lines()
                .find(|l| l.contains(cell))
                .map_or(0, |l| l.matches('█').count())
        };
        let (lo, hi) = (bar(" 1 3.3050 V"), bar(" 8 3.3120 V"));
        assert!(
            hi > 0 && lo * 100 >= hi * 80,
            "lowest {lo}, highest {hi}: {text}"
        );
        assert_eq!(scaled(&[52.901, 52.904, 52.902], 0.005), vec![50, 50, 50]);
        assert_eq!(scaled(&[52.90, 53.00], 0.005), vec![1, 100]);
    }

    #[test]
    fn history_is_kept_for_five_minutes() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        for k in 0..400u64 {
            s.update(telemetry(true), t0 + Duration::from_secs(k));
        }
        assert!(s.history.len() <= 301, "{}", s.history.len());
        let text = screen(&s, t0 + Duration::from_secs(400));
        assert!(text.contains("Pack voltage, last 5 min"), "{text}");
    }

    /// Issue 51: `--plain` printed the last pack values first and OFFLINE
    /// last; the word that says how old they are now comes first.
    #[test]
    fn a_plain_picture_says_offline_before_the_old_values() {
        let t = telemetry(false);
        let f = freshness(Some(&t), Duration::ZERO);
        let text = crate::picture::render_text(&t, None, "monitor — x", f);
        let offline = text.find("OFFLINE").unwrap_or_else(|| panic!("{text}"));
        let pack = text.find("Pack").unwrap_or_else(|| panic!("{text}"));
        assert!(offline < pack, "{text}");
        assert_eq!(
            text.lines().nth(1).map(|l| l.contains("OFFLINE")),
            Some(true),
            "{text}"
        );
    }

    /// Issue 51: at the smallest size (64 columns) a wrapped line broke
    /// inside a figure (`CVL` at the end of a row, `56.8 V` on the next);
    /// now every figure stays whole on its row.
    #[test]
    fn a_narrow_window_wraps_between_figures_never_inside_one() {
        let t0 = Instant::now();
        let mut s = LiveState::default();
        s.update(
            sixteen_cells_and(json!({"protocol":"pylon","can":"running","heard":true,
                "cvl_v":56.8,"ccl_a":0.0,"dcl_a":48.0,"name":"PYLON",
                "charge_stop":"temperature","soc_told":100,"charge_enabled":false,
                "discharge_enabled":true,"ignored":"charge 9.8 A for 3 s"})),
            t0,
        );
        let screen = screen_of(&s, t0, MIN_SIZE.0, MIN_SIZE.1);
        let rows: Vec<&str> = screen.lines().collect();
        for figure in [
            "CVL 56.8 V",
            "CCL 0.0 A",
            "DCL 48.0 A",
            "52.90 V",
            "SOC 65.0 %",
            "internal 27.0 °C",
            "/ 24.8 °C",
            "charge 9.8 A",
        ] {
            assert!(
                rows.iter().any(|r| r.contains(figure)),
                "`{figure}` cut: {screen}"
            );
        }
        // Wide enough for one row each: nothing changes but the glue.
        let wide = screen_of(&s, t0, 160, 40);
        assert!(wide.contains("CVL 56.8 V  CCL 0.0 A  DCL 48.0 A"), "{wide}");
    }
}
