//! `tinybms monitor`: the live view (full screen on a terminal, [`super::live`]),
//! plain text (piped, or `--plain`: no escape codes), JSON Lines, and the CSV /
//! JSON Lines log; `tinybms log`: the bridge's log lines.
//!
//! The picture is redrawn on a timer, not only when a line arrives, so the data
//! age keeps counting: data older than the bridge's own limit (its `telemetry`
//! lines carry `stale_after_ms`; the firmware's one rule, [`rule_of`]) shows as
//! NO DATA (a bridge that froze, a cable pulled), a BMS the bridge lost as
//! OFFLINE.

use std::io::Write;
use std::time::{Duration, Instant};

use serde_json::json;
use tinybms_firmware::host_link::schema::{HostLine, Link, Read, Telemetry};

use super::client::{without_req, Client};
pub use super::picture::*;
use super::{interrupted, interrupted_error, ToolError, ToolResult};

/// Runs the monitor until `--count`, `--duration`, `q` or Ctrl-C; the bridge
/// gets its own stream period back in every case.
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
    let name = pack_name(client);
    let title = title(client, name.as_deref());
    client.stream(o.period_ms)?;
    // A first picture at once, without waiting for the first push; a BMS that
    // does not answer is explained here rather than shown as an empty screen.
    let result = match client.wait_ready(o.ready_timeout) {
        Ok(first) => {
            client.pushed.push_front(first);
            match o.view {
                View::Live => super::live::run(client, o, &title, &mut logger, end),
                _ => watch(client, o, &title, &mut logger, end),
            }
        }
        Err(e) => Err(e),
    };
    // A bridge keeps streaming at whatever period it was last asked for: give
    // it back the one it announced (also after Ctrl-C).
    let _ = client.stream(client.hello.stream_period_ms);
    result
}

/// The bridge's `pack_name`, when it has one set (a bridge whose firmware
/// has no such field, or direct mode: none).
fn pack_name(client: &mut Client) -> Option<String> {
    if client.mode != super::transport::Mode::Bridge {
        return None;
    }
    let (fields, _) = super::config::fetch(client).ok()?;
    let id = tinybms_firmware::config::FieldId::PackName;
    fields
        .iter()
        .find(|f| f.name == id.name())
        .map(|f| f.value.clone())
        .filter(|n| !n.is_empty())
}

/// What the monitor's first line says after its name: the pack's name when
/// it has one, the port, how it is reached.
fn title(client: &Client, name: Option<&str>) -> String {
    match name {
        Some(n) => format!("“{n}” — {} — {}", client.port, client.mode.describe()),
        None => format!("{} — {}", client.port, client.mode.describe()),
    }
}

/// Writes one line and flushes it; false when the reader is gone (a closed
/// pipe: `tinybms monitor PORT | head -3`), so the command ends, gives the
/// bridge its stream period back and lets go of the port.
fn say(out: &mut impl Write, line: std::fmt::Arguments<'_>) -> bool {
    writeln!(out, "{line}").is_ok() && out.flush().is_ok()
}

/// Plain text and JSON Lines: a picture per telemetry line, and between lines
/// a NO DATA / OFFLINE line when the data gets old.
fn watch(
    client: &mut Client,
    o: &MonitorOptions,
    title: &str,
    logger: &mut Option<Logger>,
    end: Option<Instant>,
) -> ToolResult<()> {
    let stdout = std::io::stdout();
    let header = format!("monitor — {title}");
    let mut link: Option<Link<Read>> = None;
    let mut next_link = Instant::now();
    let mut updates = 0u64;
    let mut last: Option<(Telemetry<Read>, Instant)> = None;
    let mut stale_said: Option<Instant> = None;
    loop {
        if interrupted() {
            return Err(interrupted_error());
        }
        if end.is_some_and(|e| Instant::now() >= e) || o.count.is_some_and(|c| updates >= c) {
            break;
        }
        if o.view == View::Plain && Instant::now() >= next_link {
            link = client.link().ok();
            next_link = Instant::now() + Duration::from_secs(5);
        }
        let wait = end.map_or(REDRAW, |e| {
            e.saturating_duration_since(Instant::now()).min(REDRAW)
        });
        let got = client.next_pushed(wait)?;
        if let Some((b, text)) = got
            .as_ref()
            .and_then(|r| Some((r, render_battery_line(&r.line)?)))
        {
            // Packs in parallel: the battery and its packs after each picture.
            let mut out = stdout.lock();
            let said = if o.view == View::Json {
                say(&mut out, format_args!("{}", b.raw))
            } else {
                say(&mut out, format_args!("{text}"))
            };
            if !said {
                return Ok(()); // the reader is gone (`| head`): done
            }
            continue;
        }
        let Some((v, raw)) = got.and_then(|r| match r.line {
            // The first picture answered our `get`: print it like the pushes.
            HostLine::Telemetry(t) => Some((t, without_req(r.raw))),
            _ => None,
        }) else {
            // No new data: say so once it is old (every 10 s while it stays so).
            let f = freshness(
                last.as_ref().map(|(t, _)| t),
                last.as_ref().map_or(Duration::MAX, |(_, at)| at.elapsed()),
            );
            if matches!(f, Freshness::NoData(_))
                && last.is_some()
                && stale_said.is_none_or(|t| t.elapsed() >= Duration::from_secs(10))
            {
                stale_said = Some(Instant::now());
                let text = freshness_text(f);
                let mut out = stdout.lock();
                let said = if o.view == View::Json {
                    say(
                        &mut out,
                        format_args!("{}", json!({"type": "no_data", "detail": text})),
                    )
                } else {
                    say(&mut out, format_args!("{text}"))
                };
                if !said {
                    return Ok(());
                }
            }
            continue;
        };
        stale_said = None;
        let received = Instant::now();
        let mut counted = false;
        if let Some(l) = logger.as_mut() {
            counted |= l.log(&v, &raw)?;
        }
        let mut out = stdout.lock();
        let said = if o.view == View::Json {
            counted = true;
            say(&mut out, format_args!("{raw}"))
        } else {
            let f = freshness(Some(&v), received.elapsed());
            counted |= logger.is_none();
            say(
                &mut out,
                format_args!("{}", render_text(&v, link.as_ref(), &header, f)),
            )
        };
        drop(out);
        if !said {
            return Ok(());
        }
        last = Some((v, received));
        if counted {
            updates += 1;
        }
    }
    Ok(())
}

/// `tinybms log`: the bridge's `log` lines as they come, until `duration` or
/// Ctrl-C. Telemetry is switched off meanwhile (and given back after).
pub fn log(client: &mut Client, duration: Option<Duration>) -> ToolResult<()> {
    client.stream(0)?;
    let end = duration.map(|d| Instant::now() + d);
    let stdout = std::io::stdout();
    let result = loop {
        if interrupted() {
            break Err(interrupted_error());
        }
        if end.is_some_and(|e| Instant::now() >= e) {
            break Ok(());
        }
        match client.next_pushed(Duration::from_millis(200)) {
            Err(e) => break Err(e),
            Ok(Some(r)) => {
                let HostLine::Log(v) = r.line else {
                    continue;
                };
                let mut out = stdout.lock();
                // A line the bridge wrote at boot, kept for every host: no
                // time of ours.
                let when = if v.boot == Some(true) {
                    "at boot".to_string()
                } else {
                    utc_now()[11..23].to_string()
                };
                let said = say(
                    &mut out,
                    format_args!("{:<12}  {:<4}  {}", when, v.level, v.text),
                );
                if !said {
                    break Ok(()); // the reader is gone (`| head`): done
                }
            }
            Ok(None) => {}
        }
    };
    let _ = client.stream(client.hello.stream_period_ms);
    result
}

#[cfg(test)]
mod tests {
    use super::{freshness, render_battery_line, Freshness};
    use serde_json::json;
    use std::time::Duration;

    use crate::client::fixtures::{line, telemetry_line as telemetry};

    #[test]
    fn the_monitor_goes_stale_by_the_bridge_s_limit() {
        let with = |limit: Option<u64>, age_ms: u64| {
            let mut t =
                json!({"type":"telemetry","seq":3,"age_ms":age_ms,"online":true,"ready":true});
            if let Some(l) = limit {
                t["stale_after_ms"] = json!(l);
            }
            freshness(Some(&telemetry(t)), Duration::from_millis(500))
        };
        // 6.5 s old: fresh by a bridge set to 10 s, stale by the default 5 s.
        assert!(matches!(with(Some(10_000), 6_000), Freshness::Fresh(_)));
        assert!(matches!(with(None, 6_000), Freshness::NoData(Some(_))));
        assert!(matches!(with(Some(5_000), 4_000), Freshness::Fresh(_)));
        assert!(matches!(with(Some(5_000), 4_600), Freshness::NoData(_)));
        let offline = json!({"type":"telemetry","seq":3,"age_ms":0,"online":false,"ready":true});
        assert!(matches!(
            freshness(Some(&telemetry(offline)), Duration::ZERO),
            Freshness::Offline(_)
        ));
    }

    #[test]
    fn the_battery_and_its_packs_read_as_text() {
        let b = json!({"type":"battery","node":1,"speaking":true,"packs_online":3,"packs_offline":1,
            "capacity_ah":840.0,"soc_percent":65.43,"soh_percent":100.0,"voltage_v":53.2,"current_a":-12.3,
            "min_cell_v":3.301,"max_cell_v":3.345,"min_temperature_c":21.5,"max_temperature_c":24.8,
            "cvl_v":55.2,"ccl_a":176.4,"dcl_a":352.8});
        assert_eq!(
            render_battery_line(&line(b)).unwrap(),
            "Battery (node 1 speaks to the inverter): 3 of 4 packs   840 Ah   SOC 65.4 %   53.20 V   -12.3 A   \
             cells 3.301 V to 3.345 V   sent: CVL 55.2 V  CCL 176.4 A  DCL 352.8 A"
        );
        let none = json!({"type":"battery","node":2,"speaking":false,"packs_online":0,"packs_offline":3,
            "capacity_ah":null,"soc_percent":null,"cvl_v":null,"ccl_a":null,"dcl_a":null});
        assert_eq!(
            render_battery_line(&line(none)).unwrap(),
            "Battery (node 2 listens): no pack takes part (3 known): the inverter is stopped"
        );
        let p = json!({"type":"pack","node":3,"state":"stale","speaking":false,"voltage_v":53.21,
            "current_a":-4.1,"soc_percent":65.43,"soh_percent":97,"min_cell_v":3.301,"max_cell_v":3.345,
            "capacity_ah":280.0,"data_age_s":12.5,"cvl_v":55.2,"ccl_a":58.8,"dcl_a":117.6});
        assert_eq!(
            render_battery_line(&line(p)).unwrap(),
            "  pack 3   STALE (its BMS data is old)   53.21 V   -4.1 A   SOC 65.4 %   cells 3.301 V to 3.345 V   \
             own CCL 58.8 A  DCL 117.6 A   data age 12.5 s"
        );
    }
}
