//! `tinybms`, the desktop tool: talks to a TinyBMS through the ESP32 bridge's
//! USB port, or directly over a USB-UART adapter (then the firmware's own bridge
//! and host link run inside the tool, so both ways speak the same protocol,
//! firmware/src/host_link/PROTOCOL.md). `src/bin/tinybms.rs` only calls [`main`].
//!
//! * [`transport`] — opening the port, the hello probe, lines over a serial port.
//! * [`direct`] — the in-process bridge for direct mode.
//! * [`client`] — the protocol's commands as calls.
//! * [`monitor`], [`settings`] — what the commands print.

pub mod client;
pub mod config;
pub mod direct;
pub mod monitor;
pub mod settings;
pub mod transport;

use std::io::{BufRead, Write};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use crate::capture::{parse_hex, CaptureWriter};
use crate::profile::{find_setting, parse_profile};
use crate::realtime::parse_duration;
use client::Client;
use monitor::{LogFormat, MonitorOptions};
use transport::{Mode, ModeChoice, SerialLines};

/// What went wrong, in a sentence for the user, and the exit status.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ToolError {
    /// The sentence.
    pub message: String,
    /// 1: the operation failed; 2: usage; 3: could not connect.
    pub status: u8,
}

impl ToolError {
    /// The operation failed (exit 1).
    pub fn failed(message: impl Into<String>) -> Self {
        Self {
            message: message.into(),
            status: 1,
        }
    }
    /// A usage error (exit 2).
    pub fn usage(message: impl Into<String>) -> Self {
        Self {
            message: message.into(),
            status: 2,
        }
    }
    /// Could not reach the device (exit 3).
    pub fn connect(message: impl Into<String>) -> Self {
        Self {
            message: message.into(),
            status: 3,
        }
    }
}

/// Result of the tool's operations.
pub type ToolResult<T> = Result<T, ToolError>;

/// The help text.
pub const USAGE: &str =
    "tinybms — read and configure a TinyBMS, through the ESP32 bridge or directly

usage: tinybms COMMAND [PORT] [ARGS] [OPTIONS]

commands:
  ports                       list the serial ports
  monitor PORT                live view: cells (min/max, * balancing), pack, SOC/SOH,
                              temperatures, status, age of the data, link quality
      --json                  print the telemetry lines (JSON Lines) instead
      --log FILE              also log to FILE (CSV, or JSON Lines for .jsonl/.json)
      --every D               log period (default 10s)
      --format csv|jsonl      log format (default: from the extension)
      --period D              telemetry refresh period asked of the bridge (default 1s)
      --count N, --duration D stop after N updates / after D
  settings PORT [--save FILE] every setting: value, raw, Rev D range, the BMS's min/max;
                              --save writes them as a profile (name = raw  # physical)
  apply PORT FILE [--dry-run] show what the profile changes, then write and verify each
  set PORT NAME=VALUE...      write and verify settings; VALUE in the unit `settings`
                              prints (a suffix of that unit is allowed: 3.65V);
      --raw                   VALUE in raw register units instead (3650)
  events PORT                 the BMS's event log, oldest first
  stats PORT                  the statistics (registers 100-117)
  version PORT                hardware/firmware version, serial number
  reset PORT                  restart the BMS        (these three ask for confirmation
  clear-events PORT           clear the event log     on stdin unless --yes)
  clear-stats PORT            clear the statistics
  record PORT FILE.tbms       record the raw UART exchange as a capture `replay` reads
      --duration D            how long (default 10s)
  config PORT                 the bridge's own configuration (kept in its flash): every
                              field with its value, unit, default, range, when it applies
  config PORT NAME            one field, explained
  config PORT NAME=VALUE...   change fields (VALUE as shown, a unit may be given: 50A);
                              one line per field, then saved to the bridge's flash
      --save FILE             write the configuration to FILE (secrets left out)
      --load FILE [--dry-run] show what FILE changes, then change it
      --reset                 every field back to its default (asks unless --yes)
  wifi PORT --ssid NAME       the Wi-Fi network: asks for its passphrase and stores the
                              WPA2 key derived from it (never the passphrase itself)
  mqtt PORT --host HOST       the MQTT broker (and --port P, default 1883; --user U: asks
                              for the password); Wi-Fi and MQTT apply at the next restart

options for every command with a PORT:
  --mode auto|bridge|direct   auto (default): a bridge answers `{\"cmd\":\"hello\"}`;
                              when nothing does, the port is taken to be a USB-UART
                              adapter wired to the TinyBMS (115200 8N1) and the
                              firmware's bridge runs inside this tool
  --yes                       do not ask for confirmation
  --timeout D                 how long to wait for the BMS to be ready (default 15s)

durations: 500ms, 10s, 5m, 1h. Exit status: 0 ok, 1 failed (a write not verified...),
2 usage error, 3 cannot reach the device.";

/// Parsed command line.
#[derive(Debug, Default)]
struct Args {
    command: String,
    positional: Vec<String>,
    mode: Option<ModeChoice>,
    yes: bool,
    json: bool,
    raw: bool,
    dry_run: bool,
    save: Option<String>,
    load: Option<String>,
    reset: bool,
    ssid: Option<String>,
    host: Option<String>,
    port: Option<u16>,
    user: Option<String>,
    log: Option<String>,
    every: Option<Duration>,
    format: Option<String>,
    period: Option<Duration>,
    count: Option<u64>,
    duration: Option<Duration>,
    timeout: Option<Duration>,
}

fn parse_args(argv: &[String]) -> ToolResult<Args> {
    let mut a = Args::default();
    let mut it = argv.iter();
    while let Some(arg) = it.next() {
        let mut value = |name: &str| {
            it.next()
                .cloned()
                .ok_or_else(|| ToolError::usage(format!("{name} needs a value")))
        };
        let dur = |s: String| parse_duration(&s).map_err(ToolError::usage);
        match arg.as_str() {
            "-h" | "--help" => a.command = "help".into(),
            "--mode" => {
                a.mode = Some(match value("--mode")?.as_str() {
                    "auto" => ModeChoice::Auto,
                    "bridge" => ModeChoice::Bridge,
                    "direct" => ModeChoice::Direct,
                    other => {
                        return Err(ToolError::usage(format!(
                            "--mode {other}: auto, bridge or direct"
                        )))
                    }
                })
            }
            "--yes" | "-y" => a.yes = true,
            "--json" => a.json = true,
            "--raw" => a.raw = true,
            "--dry-run" => a.dry_run = true,
            "--save" => a.save = Some(value("--save")?),
            "--load" => a.load = Some(value("--load")?),
            "--reset" => a.reset = true,
            "--ssid" => a.ssid = Some(value("--ssid")?),
            "--host" => a.host = Some(value("--host")?),
            "--user" => a.user = Some(value("--user")?),
            "--port" => {
                a.port = Some(
                    value("--port")?
                        .parse()
                        .map_err(|_| ToolError::usage("--port needs a TCP port, 1 to 65535"))?,
                )
            }
            "--log" => a.log = Some(value("--log")?),
            "--every" => a.every = Some(dur(value("--every")?)?),
            "--format" => a.format = Some(value("--format")?),
            "--period" => a.period = Some(dur(value("--period")?)?),
            "--count" => {
                a.count = Some(
                    value("--count")?
                        .parse()
                        .map_err(|_| ToolError::usage("--count needs a whole number"))?,
                )
            }
            "--duration" => a.duration = Some(dur(value("--duration")?)?),
            "--timeout" => a.timeout = Some(dur(value("--timeout")?)?),
            s if s.starts_with('-')
                && s.len() > 1
                && !s[1..].starts_with(|c: char| c.is_ascii_digit()) =>
            {
                return Err(ToolError::usage(format!("unknown option `{s}`")))
            }
            _ if a.command.is_empty() => a.command = arg.clone(),
            _ => a.positional.push(arg.clone()),
        }
    }
    Ok(a)
}

/// Runs the tool with `argv` (without the program name).
pub fn main(argv: &[String]) -> ExitCode {
    match run(argv) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("tinybms: {}", e.message);
            if e.status == 2 {
                eprintln!("(tinybms --help for the commands)");
            }
            ExitCode::from(e.status)
        }
    }
}

fn port_arg(a: &Args) -> ToolResult<String> {
    a.positional.first().cloned().ok_or_else(|| {
        ToolError::usage(format!(
            "`{}` needs a PORT (see `tinybms ports`)",
            a.command
        ))
    })
}

fn run(argv: &[String]) -> ToolResult<()> {
    let a = parse_args(argv)?;
    let expect = |n: usize, what: &str| -> ToolResult<()> {
        if a.positional.len() == n {
            Ok(())
        } else {
            Err(ToolError::usage(format!(
                "usage: tinybms {} {what}",
                a.command
            )))
        }
    };
    match a.command.as_str() {
        "" | "help" => {
            println!("{USAGE}");
            Ok(())
        }
        "ports" => {
            let list = transport::port_list();
            if list.is_empty() {
                println!("no serial port found (plug the adapter or the ESP32 in; `dmesg` shows it arriving)");
            }
            for p in list {
                println!("{p}");
            }
            Ok(())
        }
        "monitor" => {
            expect(1, "PORT")?;
            let log = match &a.log {
                None => None,
                Some(path) => {
                    let ext = std::path::Path::new(path)
                        .extension()
                        .and_then(|e| e.to_str())
                        .unwrap_or("");
                    let name = a.format.clone().unwrap_or_else(|| {
                        if ext.is_empty() {
                            "csv".into()
                        } else {
                            ext.to_string()
                        }
                    });
                    let f = LogFormat::from_name(&name).ok_or_else(|| {
                        ToolError::usage(format!(
                            "log format `{name}`: csv or jsonl (--format, or the file's extension)"
                        ))
                    })?;
                    Some((path.clone(), f))
                }
            };
            let o = MonitorOptions {
                json: a.json,
                log,
                every: a.every.unwrap_or(Duration::from_secs(10)),
                count: a.count,
                duration: a.duration,
                period_ms: a
                    .period
                    .map_or(1000, |d| d.as_millis().clamp(100, 60_000) as u32),
                ready_timeout: ready_timeout(&a),
            };
            let mut c = connect(&a)?;
            monitor::run(&mut c, &o)
        }
        "settings" => {
            expect(1, "PORT [--save FILE]")?;
            let mut c = connect(&a)?;
            c.wait_ready(ready_timeout(&a))?;
            let lines = c.get("settings")?;
            print!("{}", settings::render_table(&lines));
            if let Some(path) = &a.save {
                let serial = serial_suffix(&mut c);
                let header = format!(
                    "TinyBMS settings saved by tinybms {} from {} ({}) at {}{}",
                    env!("CARGO_PKG_VERSION"),
                    c.port,
                    match c.mode {
                        Mode::Bridge => "through the bridge",
                        Mode::Direct => "direct",
                    },
                    monitor::utc_now(),
                    serial
                );
                std::fs::write(path, settings::profile_text(&lines, &header))
                    .map_err(|e| ToolError::failed(format!("cannot write `{path}`: {e}")))?;
                println!("saved {} settings to {path}", lines.len());
            }
            Ok(())
        }
        "apply" => {
            expect(2, "PORT FILE [--dry-run]")?;
            let path = &a.positional[1];
            let text = std::fs::read_to_string(path)
                .map_err(|e| ToolError::failed(format!("cannot read `{path}`: {e}")))?;
            let wanted =
                parse_profile(&text).map_err(|e| ToolError::usage(format!("{path}: {e}")))?;
            let mut c = connect(&a)?;
            c.wait_ready(ready_timeout(&a))?;
            let current = c.get("settings")?;
            let changes = settings::diff(&current, &wanted);
            let unchanged = wanted.len().saturating_sub(changes.len());
            println!("{path}: {} settings", wanted.len());
            print!("{}", settings::render_diff(&changes, unchanged));
            if a.dry_run || changes.is_empty() {
                if a.dry_run {
                    println!("dry run: nothing written");
                }
                return Ok(());
            }
            let items: Vec<(String, f64)> = changes
                .iter()
                .map(|ch| (crate::profile::snake_name(ch.id), ch.to as f64))
                .collect();
            confirm_restart(&a, &items)?;
            write_settings(&mut c, &items, true)
        }
        "set" => {
            if a.positional.len() < 2 {
                return Err(ToolError::usage(
                    "usage: tinybms set PORT NAME=VALUE... [--raw]",
                ));
            }
            let items = a.positional[1..]
                .iter()
                .map(|s| settings::parse_set_arg(s, a.raw))
                .collect::<Result<Vec<_>, _>>()
                .map_err(ToolError::usage)?;
            // One value per setting: the command object keeps only one, and
            // which one is meant is not clear.
            for (i, (name, _)) in items.iter().enumerate() {
                if items[..i].iter().any(|(n, _)| n == name) {
                    return Err(ToolError::usage(format!(
                        "`{name}` is given twice: give each setting once"
                    )));
                }
            }
            confirm_restart(&a, &items)?;
            let mut c = connect(&a)?;
            c.wait_ready(ready_timeout(&a))?;
            write_settings(&mut c, &items, a.raw)
        }
        "events" => {
            expect(1, "PORT")?;
            let mut c = connect(&a)?;
            c.wait_ready(ready_timeout(&a))?;
            let events = c.get("events")?;
            if events.is_empty() {
                println!("no events");
            }
            for e in events.iter().filter(|e| e["type"] == "event") {
                let t = e["timestamp_s"].as_u64().unwrap_or(0);
                println!(
                    "{:>10} s  ({:>3}d {:02}:{:02}:{:02})  0x{:02X}  {:<8} {}",
                    t,
                    t / 86_400,
                    t / 3600 % 24,
                    t / 60 % 60,
                    t % 60,
                    e["id"].as_u64().unwrap_or(0),
                    e["severity"].as_str().unwrap_or("?"),
                    e["name"].as_str().unwrap_or("?")
                );
            }
            Ok(())
        }
        "stats" | "version" => {
            expect(1, "PORT")?;
            let mut c = connect(&a)?;
            c.wait_ready(ready_timeout(&a))?;
            let what = if a.command == "stats" {
                "statistics"
            } else {
                "version"
            };
            let v = c.get_one(what)?;
            print_fields(&v);
            Ok(())
        }
        "reset" | "clear-events" | "clear-stats" => {
            expect(1, "PORT [--yes]")?;
            let (question, cmd, done) = match a.command.as_str() {
                "reset" => ("Restart the BMS", json!({"cmd": "reset"}), "reset_done"),
                "clear-events" => (
                    "Clear the BMS's event log",
                    json!({"cmd": "clear", "what": "events"}),
                    "cleared",
                ),
                _ => (
                    "Clear the BMS's statistics",
                    json!({"cmd": "clear", "what": "statistics"}),
                    "cleared",
                ),
            };
            if !a.yes && !confirm(question)? {
                return Err(ToolError::failed("not confirmed: nothing done"));
            }
            let mut c = connect(&a)?;
            c.wait_ready(ready_timeout(&a))?;
            let v = c.command(cmd, done, Duration::from_secs(30))?;
            let ok = v["ok"] == true || v["confirmed"] == true;
            match (done, ok) {
                ("reset_done", true) => {
                    println!("the BMS restarted (confirmed by its reset reason)")
                }
                ("reset_done", false) => {
                    println!(
                        "reset sent, but the BMS's reset reason does not confirm a software reset"
                    )
                }
                (_, true) => println!("cleared"),
                (_, false) => {
                    return Err(ToolError::failed("the BMS did not acknowledge the clear"))
                }
            }
            Ok(())
        }
        "record" => {
            expect(2, "PORT FILE.tbms [--duration D]")?;
            record(&a)
        }
        "config" => run_config(&a),
        "wifi" => {
            expect(1, "PORT --ssid NAME")?;
            let ssid = a
                .ssid
                .clone()
                .ok_or_else(|| ToolError::usage("usage: tinybms wifi PORT --ssid NAME"))?;
            let pass = config::ask_secret(&format!("Passphrase of `{ssid}` (not shown): "))?;
            let key = config::wpa2_psk(&ssid, &pass).map_err(ToolError::usage)?;
            let changes = vec![
                config::check_assignment("wifi_ssid", &ssid)?,
                config::check_assignment("wifi_key", &key)?,
            ];
            let mut c = connect(&a)?;
            config::require_bridge(&c)?;
            config::apply(&mut c, &changes)?;
            println!(
                "Wi-Fi: the bridge joins `{ssid}` after its next restart (power-cycle or RESET)"
            );
            Ok(())
        }
        "mqtt" => {
            expect(1, "PORT --host HOST [--port P] [--user U]")?;
            let host = a.host.clone().ok_or_else(|| {
                ToolError::usage("usage: tinybms mqtt PORT --host HOST [--port P] [--user U]")
            })?;
            let mut changes = vec![
                config::check_assignment("mqtt_host", &host)?,
                config::check_assignment("mqtt_port", &a.port.unwrap_or(1883).to_string())?,
            ];
            match &a.user {
                Some(user) => {
                    let pass = config::ask_secret(&format!(
                        "Password of `{user}` at {host} (not shown): "
                    ))?;
                    changes.push(config::check_assignment("mqtt_user", user)?);
                    changes.push(config::check_assignment("mqtt_password", &pass)?);
                }
                None => {
                    changes.push(config::check_assignment("mqtt_user", "")?);
                    changes.push(config::check_assignment("mqtt_password", "")?);
                }
            }
            let mut c = connect(&a)?;
            config::require_bridge(&c)?;
            let (fields, _) = config::fetch(&mut c).map_err(config::fetch_error)?;
            config::check_locally(&config::record_of(&fields), &changes)?;
            config::apply(&mut c, &changes)?;
            println!("MQTT: the bridge publishes to {host} after its next restart");
            Ok(())
        }
        other => Err(ToolError::usage(format!("unknown command `{other}`"))),
    }
}

/// `tinybms config …` (see [`config`]).
fn run_config(a: &Args) -> ToolResult<()> {
    if a.positional.is_empty() {
        return Err(ToolError::usage(
            "usage: tinybms config PORT [NAME | NAME=VALUE...] [--save FILE | --load FILE | --reset]",
        ));
    }
    let args = &a.positional[1..];
    let modes = [
        !args.is_empty(),
        a.save.is_some(),
        a.load.is_some(),
        a.reset,
    ]
    .iter()
    .filter(|m| **m)
    .count();
    if modes > 1 {
        return Err(ToolError::usage(
            "give one of NAME=VALUE..., --save, --load or --reset",
        ));
    }
    // Everything that can be checked without the bridge is checked first.
    let assignments = if args.iter().any(|x| x.contains('=')) {
        let mut out = Vec::new();
        for arg in args {
            let (name, text) = config::split_assignment(arg)?;
            let (id, p) = config::check_assignment(&name, &text)?;
            if out.iter().any(|(o, _)| *o == id) {
                return Err(ToolError::usage(format!(
                    "`{}` is given twice: give each field once",
                    id.name()
                )));
            }
            out.push((id, p));
        }
        Some(out)
    } else {
        None
    };
    if assignments.is_none() && args.len() > 1 {
        return Err(ToolError::usage(
            "usage: tinybms config PORT NAME (one field), or NAME=VALUE... to change fields",
        ));
    }
    let explain = match (&assignments, args.first()) {
        (None, Some(name)) => Some(config::field_named(name)?),
        _ => None,
    };
    let loaded = match &a.load {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| ToolError::failed(format!("cannot read `{path}`: {e}")))?;
            Some(config::parse_file(&text).map_err(|e| ToolError::usage(format!("{path}: {e}")))?)
        }
        None => None,
    };
    if a.reset
        && !a.yes
        && !confirm("Set every field of the bridge's configuration back to its default")?
    {
        return Err(ToolError::failed("not confirmed: nothing changed"));
    }
    let mut c = connect(a)?;
    config::require_bridge(&c)?;
    let (fields, end) = config::fetch(&mut c).map_err(config::fetch_error)?;
    let current = config::record_of(&fields);
    if let Some(changes) = assignments {
        config::check_locally(&current, &changes)?;
        return config::apply(&mut c, &changes);
    }
    if let Some(wanted) = loaded {
        let changes = config::diff(&current, &wanted);
        config::check_locally(&current, &changes)?;
        println!(
            "{}: {} fields, {} differ from the bridge's",
            a.load.as_deref().unwrap_or(""),
            wanted.len(),
            changes.len()
        );
        for (id, p) in &changes {
            let mut l = tinybms_firmware::text::Line::new();
            tinybms_firmware::config::value::write(id.field(), &p.as_value(), true, &mut l);
            let now = fields
                .iter()
                .find(|f| f.line["name"] == id.name())
                .and_then(|f| f.line["value"].as_str())
                .unwrap_or("?");
            println!("  {:<24} {now} -> {}", id.name(), l.as_str());
        }
        if a.dry_run || changes.is_empty() {
            if a.dry_run {
                println!("dry run: nothing changed");
            }
            return Ok(());
        }
        return config::apply(&mut c, &changes);
    }
    if a.reset {
        return config::reset(&mut c);
    }
    if let Some(id) = explain {
        let f = fields
            .iter()
            .find(|f| f.line["name"] == id.name())
            .ok_or_else(|| ToolError::failed(format!("the bridge has no field `{}`", id.name())))?;
        print!("{}", config::render_one(f));
        return Ok(());
    }
    print!("{}", config::render(&fields, &end));
    if let Some(path) = &a.save {
        let header = format!(
            "saved by tinybms {} from {} at {}",
            env!("CARGO_PKG_VERSION"),
            c.port,
            monitor::utc_now()
        );
        std::fs::write(path, config::file_text(&fields, &header))
            .map_err(|e| ToolError::failed(format!("cannot write `{path}`: {e}")))?;
        let secrets = fields.iter().filter(|f| f.line["secret"] == true).count();
        println!(
            "saved {} fields to {path} ({secrets} secrets left out)",
            fields.len() - secrets
        );
    }
    Ok(())
}

/// The candidate closest to `name` when it is close enough to be a typo.
pub fn suggest<'a>(name: &str, candidates: &[&'a str]) -> Option<&'a str> {
    let dist = |a: &str, b: &str| -> usize {
        let (a, b): (Vec<char>, Vec<char>) = (a.chars().collect(), b.chars().collect());
        let mut prev: Vec<usize> = (0..=b.len()).collect();
        for (i, ca) in a.iter().enumerate() {
            let mut cur = vec![i + 1; b.len() + 1];
            for (j, cb) in b.iter().enumerate() {
                let sub = prev[j] + usize::from(ca != cb);
                cur[j + 1] = sub.min(prev[j + 1] + 1).min(cur[j] + 1);
            }
            prev = cur;
        }
        prev[b.len()]
    };
    let lower = name.to_ascii_lowercase();
    candidates
        .iter()
        .map(|c| (dist(&lower, c), *c))
        .filter(|(d, c)| *d <= (c.len() / 3).max(2))
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

fn ready_timeout(a: &Args) -> Duration {
    a.timeout.unwrap_or(Duration::from_secs(15))
}

fn serial_suffix(c: &mut Client) -> String {
    c.get_one("version")
        .ok()
        .and_then(|v| {
            v["serial_number"]
                .as_str()
                .map(|s| format!(", BMS serial {s}"))
        })
        .unwrap_or_default()
}

fn print_fields(v: &Value) {
    if let Some(m) = v.as_object() {
        let w = m.keys().map(String::len).max().unwrap_or(0);
        for (k, x) in m {
            if k == "type" || k == "req" {
                continue;
            }
            let text = match x {
                Value::String(s) => s.clone(),
                other => other.to_string(),
            };
            println!("{k:<w$}  {text}");
        }
    }
}

/// A setting whose write restarts the BMS (340, operation mode) is written only
/// when confirmed (or `--yes`), like `reset`: the BMS switches its outputs off
/// while it restarts.
fn confirm_restart(a: &Args, items: &[(String, f64)]) -> ToolResult<()> {
    let restarting: Vec<&str> = items
        .iter()
        .filter(|(name, _)| find_setting(name).is_some_and(|id| id.restarts_bms()))
        .map(|(name, _)| name.as_str())
        .collect();
    if restarting.is_empty() || a.yes {
        return Ok(());
    }
    let question = format!(
        "Writing {} restarts the BMS (its outputs switch off while it restarts). Go on",
        restarting.join(", ")
    );
    if confirm(&question)? {
        Ok(())
    } else {
        Err(ToolError::failed("not confirmed: nothing written"))
    }
}

fn confirm(question: &str) -> ToolResult<bool> {
    print!("{question}? Type `yes` to go on: ");
    let _ = std::io::stdout().flush();
    let mut line = String::new();
    std::io::stdin()
        .lock()
        .read_line(&mut line)
        .map_err(|e| ToolError::failed(format!("reading the answer: {e}")))?;
    Ok(line.trim().eq_ignore_ascii_case("yes") || line.trim().eq_ignore_ascii_case("y"))
}

/// Writes settings in groups of 8 (the protocol's limit), printing each
/// outcome; fails when any did not end verified or unchanged.
fn write_settings(c: &mut Client, items: &[(String, f64)], raw: bool) -> ToolResult<()> {
    let mut bad = 0;
    let mut count = 0;
    for group in items.chunks(8) {
        let outcomes = c.set(group, raw, Duration::from_secs(15), |v| {
            let follow = if v["follow_up"] == true {
                " (follow-up)"
            } else {
                ""
            };
            let detail = v["detail"]
                .as_str()
                .filter(|d| !d.is_empty())
                .map(|d| format!(": {d}"))
                .unwrap_or_default();
            println!(
                "{:<36} {:>8}  {}{follow}{detail}",
                v["name"].as_str().unwrap_or("?"),
                v["raw"],
                v["outcome"].as_str().unwrap_or("?")
            );
        })?;
        // The last word on each setting: a follow-up settles an unconfirmed one.
        for (name, _) in group {
            count += 1;
            let last = outcomes.iter().rev().find(|v| v["name"] == name.as_str());
            let ok =
                last.is_some_and(|v| v["outcome"] == "verified" || v["outcome"] == "unchanged");
            if !ok {
                bad += 1;
            }
        }
    }
    if bad > 0 {
        return Err(ToolError::failed(format!(
            "{bad} of {count} settings not verified on the BMS"
        )));
    }
    println!(
        "{count} setting{} verified",
        if count == 1 { "" } else { "s" }
    );
    Ok(())
}

fn record(a: &Args) -> ToolResult<()> {
    let path = &a.positional[1];
    let duration = a.duration.unwrap_or(Duration::from_secs(10));
    let file = std::fs::File::create(path)
        .map_err(|e| ToolError::failed(format!("cannot create `{path}`: {e}")))?;
    let header = format!(
        "recorded by tinybms {} from {} at {}",
        env!("CARGO_PKG_VERSION"),
        a.positional[0],
        monitor::utc_now()
    );
    let writer = CaptureWriter::new(Box::new(std::io::BufWriter::new(file)), &header)
        .map_err(|e| ToolError::failed(format!("writing `{path}`: {e}")))?;
    let port = port_arg(a)?;
    let (serial, mode, probe) = open_and_probe(&port, a.mode.unwrap_or(ModeChoice::Auto))?;
    let (mut tx, mut rx) = (0usize, 0usize);
    match (mode, probe) {
        (Mode::Direct, _) => {
            let _ = serial.clear(serialport::ClearBuffer::Input);
            let mut c = direct::start(serial, port.clone(), Some(writer))?;
            let _ = c.stream(0);
            let end = Instant::now() + duration;
            while Instant::now() < end {
                let _ = c.next_pushed(end.saturating_duration_since(Instant::now()))?;
            }
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
            while Instant::now() < end {
                let Some(v) = c.next_pushed(end.saturating_duration_since(Instant::now()))? else {
                    continue;
                };
                if v["type"] != "raw" {
                    continue;
                }
                let bytes = parse_hex(v["hex"].as_str().unwrap_or(""))
                    .map_err(|e| ToolError::failed(format!("a raw line the bridge sent: {e}")))?;
                if v["dir"] == "tx" {
                    writer.tx(&bytes).map_err(werr)?;
                    tx += bytes.len();
                } else {
                    writer.rx(&bytes).map_err(werr)?;
                    rx += bytes.len();
                }
            }
            let req = c.send(json!({"cmd": "capture", "on": false}))?;
            // Raw lines still queued before the answer are part of the capture.
            loop {
                let Some(v) = c.recv(Duration::from_secs(5))? else {
                    break;
                };
                if v["req"] == json!(req) {
                    break;
                }
                if v["type"] == "raw" {
                    if let Ok(bytes) = parse_hex(v["hex"].as_str().unwrap_or("")) {
                        if v["dir"] == "tx" {
                            writer.tx(&bytes).map_err(werr)?;
                        } else {
                            writer.rx(&bytes).map_err(werr)?;
                        }
                    }
                }
            }
            if let Some(dropped) = c
                .get_one("link")
                .ok()
                .and_then(|l| l["dropped_lines"].as_u64())
            {
                if dropped > 0 {
                    let _ = writer.comment(&format!(
                        "the bridge dropped {dropped} output lines since it started (raw lines may be missing)"
                    ));
                }
            }
            writer.flush().map_err(werr)?;
        }
        (Mode::Bridge, None) => return Err(ToolError::failed("internal: bridge without hello")),
    }
    println!(
        "recorded {:.1} s to {path}: {tx} bytes sent, {rx} received ({})",
        duration.as_secs_f64(),
        match mode {
            Mode::Bridge => "through the bridge's capture",
            Mode::Direct => "direct",
        }
    );
    Ok(())
}

type Probed = Option<(Value, transport::LineSplitter)>;

/// Opens the port and finds out what is on it.
fn open_and_probe(
    port: &str,
    choice: ModeChoice,
) -> ToolResult<(Box<dyn serialport::SerialPort>, Mode, Probed)> {
    let mut serial = transport::open_port(port)?;
    if choice == ModeChoice::Direct {
        return Ok((serial, Mode::Direct, None));
    }
    let (probe, split) = transport::probe(&mut serial, transport::PROBE_TIME)?;
    match (probe.hello, choice) {
        (Some(h), _) => Ok((serial, Mode::Bridge, Some((h, split)))),
        (None, ModeChoice::Bridge) => Err(ToolError::connect(format!(
            "no bridge answered on `{port}` ({} bytes heard{}): is the bridge firmware \
             running on the board behind this port? A TinyBMS on a USB-UART adapter is \
             `--mode direct` (or leave --mode out)",
            probe.bytes,
            if probe.json_lines > 0 {
                format!(", {} JSON lines that were not a hello", probe.json_lines)
            } else {
                String::new()
            }
        ))),
        (None, _) => Ok((serial, Mode::Direct, None)),
    }
}

/// Opens the port, detects the mode and returns a client speaking the protocol.
fn connect(a: &Args) -> ToolResult<Client> {
    let port = port_arg(a)?;
    let (serial, mode, probe) = open_and_probe(&port, a.mode.unwrap_or(ModeChoice::Auto))?;
    match (mode, probe) {
        (Mode::Bridge, Some((hello, split))) => Ok(Client::new(
            Box::new(SerialLines::new(serial, split)),
            Mode::Bridge,
            hello,
            port,
        )),
        _ => {
            let _ = serial.clear(serialport::ClearBuffer::Input);
            direct::start(serial, port, None)
        }
    }
}
