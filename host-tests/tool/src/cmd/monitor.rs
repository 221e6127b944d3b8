//! `tinybms monitor`: The live view, plain text or JSON Lines, and the CSV/JSON Lines log.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Duration;

use crate::cli::{Conn, FormatArg};
use crate::monitor::{self, LogFormat, MonitorOptions, View};
use crate::{connect, ToolError, ToolResult};

/// Runs `tinybms monitor`.
#[allow(clippy::too_many_arguments)]
pub fn run(
    conn: Conn,
    json: bool,
    plain: bool,
    log: Option<PathBuf>,
    every: Duration,
    format: Option<FormatArg>,
    period: Duration,
    count: Option<u64>,
    duration: Option<Duration>,
) -> ToolResult<()> {
    let log = match log {
        None => None,
        Some(path) => {
            let f = match format {
                Some(FormatArg::Csv) => LogFormat::Csv,
                Some(FormatArg::Jsonl) => LogFormat::JsonLines,
                None => {
                    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("csv");
                    LogFormat::from_name(ext).ok_or_else(|| {
                        ToolError::usage(format!(
                            "log format of `{}`: csv or jsonl (--format, or the file's extension)",
                            path.display()
                        ))
                    })?
                }
            };
            Some((path.to_string_lossy().into_owned(), f))
        }
    };
    let view = if json {
        View::Json
    } else if plain || !std::io::stdout().is_terminal() {
        View::Plain
    } else {
        View::Live
    };
    let o = MonitorOptions {
        view,
        log,
        every,
        count,
        duration,
        period_ms: stream_period_ms(period),
        ready_timeout: conn.timeout,
    };
    let mut c = connect(&conn)?;
    monitor::run(&mut c, &o)
}

/// `--period` as the bridge can stream it (100 ms to 60 s), said when it is
/// not what was asked.
fn stream_period_ms(period: Duration) -> u32 {
    let asked = period.as_millis();
    let ms = asked.clamp(100, 60_000) as u32;
    if u128::from(ms) != asked {
        eprintln!(
            "tinybms: --period {asked}ms: the bridge streams every 100 ms to 60 s; using {ms} ms"
        );
    }
    ms
}
