//! `tinybms`, the desktop tool: talks to a TinyBMS through the ESP32 bridge's
//! USB port, or directly over a USB-UART adapter (then the firmware's own bridge
//! and host link run inside the tool, so both ways speak the same protocol,
//! firmware/src/host_link/PROTOCOL.md). `src/bin/tinybms.rs` only calls [`main`].
//!
//! * [`transport`] — opening the port, the hello probe, lines over a serial port.
//! * [`direct`] — the in-process bridge for direct mode.
//! * [`client`] — the protocol's commands as calls.
//! * [`monitor`], [`settings`] — what the commands print.

pub mod cli;
pub mod client;
pub mod config;
pub mod direct;
pub mod live;
pub mod monitor;
pub mod picture;
pub mod settings;
pub mod transport;

use std::io::{BufRead, IsTerminal, Write};
use std::path::Path;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use clap::{CommandFactory, Parser};
use protocol_core::settings::SettingId;
use serde_json::{json, Value};

use crate::capture::{parse_hex, CaptureWriter};
use crate::profile::{find_setting, parse_profile, snake_name};
use cli::{Cli, Command, Conn, FormatArg, ModeArg};
use client::Client;
use monitor::{LogFormat, MonitorOptions, View};
use transport::{Mode, ModeChoice, SerialLines};

/// What went wrong, in a sentence for the user, and the exit status.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ToolError {
    /// The sentence.
    pub message: String,
    /// 1: the operation failed; 2: usage; 3: could not connect; 130:
    /// interrupted.
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

/// Set by Ctrl-C (SIGINT): long-running commands stop at their next step and
/// leave the bridge as they found it (the stream period, capture off).
static INTERRUPTED: AtomicBool = AtomicBool::new(false);

/// Ctrl-C was pressed.
pub fn interrupted() -> bool {
    INTERRUPTED.load(Ordering::Relaxed)
}

/// Stopped by Ctrl-C (exit 130, as a shell reports SIGINT).
pub fn interrupted_error() -> ToolError {
    ToolError {
        message: "interrupted".into(),
        status: 130,
    }
}

/// Runs the tool with `argv` (without the program name).
pub fn main(argv: &[String]) -> ExitCode {
    let cli = match Cli::try_parse_from(
        std::iter::once("tinybms".to_string()).chain(argv.iter().cloned()),
    ) {
        Ok(c) => c,
        Err(e) => {
            // Help and version go to stdout with status 0; usage errors (with
            // clap's suggestions) to stderr with status 2.
            let _ = e.print();
            return ExitCode::from(e.exit_code().clamp(0, 255) as u8);
        }
    };
    let _ = ctrlc::set_handler(|| {
        if INTERRUPTED.swap(true, Ordering::Relaxed) {
            // A second Ctrl-C: the user insists.
            std::process::exit(130);
        }
    });
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if e.status == 130 => {
            eprintln!("tinybms: interrupted");
            ExitCode::from(130)
        }
        Err(e) => {
            eprintln!("tinybms: {}", e.message);
            if e.status == 2 {
                eprintln!("(tinybms --help for the commands, tinybms COMMAND --help for one)");
            }
            ExitCode::from(e.status)
        }
    }
}

/// Says on stderr what the tool is doing while the user waits.
fn status(msg: &str) {
    eprintln!("{msg}");
}

fn run(cli: Cli) -> ToolResult<()> {
    match cli.command {
        Command::Ports => {
            let list = transport::port_list();
            if list.is_empty() {
                println!("no serial port found (plug the adapter or the ESP32 in; `dmesg` shows it arriving)");
            }
            for p in list {
                println!("{p}");
            }
            Ok(())
        }
        Command::Completions { shell } => {
            clap_complete::generate(
                shell,
                &mut Cli::command(),
                "tinybms",
                &mut std::io::stdout(),
            );
            Ok(())
        }
        Command::Monitor {
            conn,
            json,
            plain,
            log,
            every,
            format,
            period,
            count,
            duration,
        } => {
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
                period_ms: period.as_millis().clamp(100, 60_000) as u32,
                ready_timeout: conn.timeout,
            };
            let mut c = connect(&conn)?;
            monitor::run(&mut c, &o)
        }
        Command::Log { conn, duration } => {
            let mut c = connect(&conn)?;
            monitor::log(&mut c, duration)
        }
        Command::Settings { conn, save, json } => {
            let mut c = connect_ready(&conn)?;
            let lines = c.get("settings")?;
            if json {
                for l in &lines {
                    println!("{l}");
                }
                return Ok(());
            }
            print!("{}", settings::render_groups(&lines));
            if let Some(path) = &save {
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
                let (text, saved) = settings::profile_text(&lines, &header);
                std::fs::write(path, text).map_err(|e| {
                    ToolError::failed(format!("cannot write `{}`: {e}", path.display()))
                })?;
                let skipped = lines.len().saturating_sub(saved);
                println!(
                    "saved {saved} settings to {}{}",
                    path.display(),
                    if skipped > 0 {
                        format!(" ({skipped} left out: not read, or write-only)")
                    } else {
                        String::new()
                    }
                );
            }
            Ok(())
        }
        Command::Apply {
            conn,
            file,
            dry_run,
            yes,
        } => {
            let text = read_profile(&file, &conn.port)?;
            let wanted = parse_profile(&text)
                .map_err(|e| ToolError::usage(format!("{}: {e}", file.display())))?;
            let mut c = connect_ready(&conn)?;
            let current = c.get("settings")?;
            settings::check_all(&current, &wanted, None).map_err(ToolError::failed)?;
            let changes = settings::diff(&current, &wanted);
            let unchanged = wanted.len().saturating_sub(changes.len());
            println!("{}: {} settings", file.display(), wanted.len());
            print!("{}", settings::render_diff(&changes, unchanged));
            if dry_run {
                println!("dry run: every value checked, nothing written");
                return Ok(());
            }
            if changes.is_empty() {
                return Ok(());
            }
            let items: Vec<(SettingId, i32)> =
                changes.iter().map(|ch| (ch.id, ch.to as i32)).collect();
            confirm_restart(yes, &items)?;
            write_settings(&mut c, &items)
        }
        Command::Set {
            conn,
            assignments,
            raw,
            dry_run,
            yes,
        } => {
            let mut items: Vec<(SettingId, i32)> = Vec::new();
            let mut bare: Vec<SettingId> = Vec::new();
            for a in &assignments {
                let (id, value, was_bare) =
                    settings::parse_set_arg(a, raw).map_err(ToolError::usage)?;
                // One value per setting: which one is meant is not clear.
                if items.iter().any(|(i, _)| *i == id) {
                    return Err(ToolError::usage(format!(
                        "`{}` is given twice: give each setting once",
                        snake_name(id)
                    )));
                }
                if was_bare {
                    bare.push(id);
                }
                items.push((id, value));
            }
            let mut c = connect_ready(&conn)?;
            let current = c.get("settings")?;
            settings::check_all(&current, &items, Some(&bare)).map_err(ToolError::failed)?;
            if dry_run {
                let changes = settings::diff(&current, &items);
                print!(
                    "{}",
                    settings::render_diff(&changes, items.len().saturating_sub(changes.len()))
                );
                println!("dry run: every value checked, nothing written");
                return Ok(());
            }
            confirm_restart(yes, &items)?;
            write_settings(&mut c, &items)
        }
        Command::Events { conn, json } => {
            let mut c = connect_ready(&conn)?;
            let events = c.get("events")?;
            // The BMS's clock: its lifetime counter now, against ours.
            let lifetime = c
                .get_one("snapshot")
                .ok()
                .and_then(|t| t["lifetime_s"].as_u64());
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs() as i64)
                .unwrap_or(0);
            let wall = |ts: u64| lifetime.map(|l| monitor::utc(now - (l as i64 - ts as i64), 0));
            let list: Vec<&Value> = events.iter().filter(|e| e["type"] == "event").collect();
            if json {
                for e in list {
                    let mut e = e.clone();
                    let w = wall(e["timestamp_s"].as_u64().unwrap_or(0));
                    if let (Some(m), Some(w)) = (e.as_object_mut(), w) {
                        m.insert("time".into(), json!(w));
                    }
                    println!("{e}");
                }
                return Ok(());
            }
            if list.is_empty() {
                println!("no events");
            }
            for e in list {
                let t = e["timestamp_s"].as_u64().unwrap_or(0);
                let when = wall(t)
                    .map(|w| format!("{}  ", &w[..19].replace('T', " ")))
                    .unwrap_or_default();
                println!(
                    "{when}BMS {:>3}d {:02}:{:02}:{:02}  0x{:02X}  {:<8} {}",
                    t / 86_400,
                    t / 3600 % 24,
                    t / 60 % 60,
                    t % 60,
                    e["id"].as_u64().unwrap_or(0),
                    e["severity"].as_str().unwrap_or("?"),
                    e["name"].as_str().unwrap_or("?")
                );
            }
            if lifetime.is_some() {
                println!(
                    "(times from the BMS's lifetime counter, which stops while the BMS is off: \
                     events before a power-down are earlier than shown)"
                );
            }
            Ok(())
        }
        Command::Stats { conn, json } => show_one(&conn, "statistics", json),
        Command::Version { conn, json } => show_one(&conn, "version", json),
        Command::Reset { conn, yes } => clear_or_reset(&conn, yes, "reset"),
        Command::ClearEvents { conn, yes } => clear_or_reset(&conn, yes, "events"),
        Command::ClearStats { conn, yes } => clear_or_reset(&conn, yes, "statistics"),
        Command::Record {
            conn,
            file,
            duration,
        } => record(&conn, &file, duration),
        Command::Config {
            conn,
            args,
            save,
            load,
            dry_run,
            reset,
            yes,
        } => run_config(
            &conn,
            &args,
            save.as_deref(),
            load.as_deref(),
            dry_run,
            reset,
            yes,
        ),
        Command::Wifi { conn, ssid } => {
            let pass = config::ask_secret(&format!("Passphrase of `{ssid}` (not shown): "))?;
            let key = config::wpa2_psk(&ssid, &pass).map_err(ToolError::usage)?;
            let changes = vec![
                config::check_assignment("wifi_ssid", &ssid)?,
                config::check_assignment("wifi_key", &key)?,
            ];
            let mut c = connect(&conn)?;
            config::require_bridge(&c)?;
            config::apply(&mut c, &changes)?;
            println!(
                "Wi-Fi: the bridge joins `{ssid}` after its next restart (power-cycle or RESET)"
            );
            Ok(())
        }
        Command::Mqtt {
            conn,
            host,
            tcp_port,
            user,
        } => {
            let mut changes = vec![
                config::check_assignment("mqtt_host", &host)?,
                config::check_assignment("mqtt_port", &tcp_port.to_string())?,
            ];
            match &user {
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
            let mut c = connect(&conn)?;
            config::require_bridge(&c)?;
            let (fields, _) = config::fetch(&mut c).map_err(config::fetch_error)?;
            config::check_locally(&config::record_of(&fields), &changes)?;
            config::apply(&mut c, &changes)?;
            println!("MQTT: the bridge publishes to {host} after its next restart");
            Ok(())
        }
    }
}

/// A profile FILE: a regular file (a serial port there means PORT and FILE
/// were swapped: reading it would wait forever).
fn read_profile(file: &Path, port: &str) -> ToolResult<String> {
    let shown = file.display();
    let meta = std::fs::metadata(file)
        .map_err(|e| ToolError::usage(format!("cannot read the profile `{shown}`: {e}")))?;
    if !meta.is_file() {
        let swapped = Path::new(port).is_file();
        return Err(ToolError::usage(if swapped {
            format!(
                "`{shown}` is a port and `{port}` a file: the order is `tinybms apply PORT FILE` \
                 (tinybms apply {shown} {port})"
            )
        } else {
            format!("`{shown}` is not a regular file: the profile is a text file (`tinybms apply PORT FILE`)")
        }));
    }
    std::fs::read_to_string(file)
        .map_err(|e| ToolError::failed(format!("cannot read `{shown}`: {e}")))
}

fn show_one(conn: &Conn, what: &str, json: bool) -> ToolResult<()> {
    let mut c = connect_ready(conn)?;
    let v = c.get_one(what)?;
    if json {
        let mut v = v;
        if let Some(m) = v.as_object_mut() {
            m.shift_remove("req");
        }
        println!("{v}");
    } else {
        print_fields(&v);
    }
    Ok(())
}

fn clear_or_reset(conn: &Conn, yes: bool, what: &str) -> ToolResult<()> {
    let (question, cmd, done) = match what {
        "reset" => ("Restart the BMS", json!({"cmd": "reset"}), "reset_done"),
        "events" => (
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
    if !yes && !confirm(question)? {
        return Err(ToolError::failed("not confirmed: nothing done"));
    }
    let mut c = connect_ready(conn)?;
    let v = c.command(cmd, done, Duration::from_secs(30))?;
    let ok = v["ok"] == true || v["confirmed"] == true;
    match (done, ok) {
        ("reset_done", true) => println!("the BMS restarted (confirmed by its reset reason)"),
        ("reset_done", false) => {
            println!("reset sent, but the BMS's reset reason does not confirm a software reset")
        }
        (_, true) => println!("cleared"),
        (_, false) => return Err(ToolError::failed("the BMS did not acknowledge the clear")),
    }
    Ok(())
}

/// `tinybms config …` (see [`config`]).
fn run_config(
    conn: &Conn,
    args: &[String],
    save: Option<&Path>,
    load: Option<&Path>,
    dry_run: bool,
    reset: bool,
    yes: bool,
) -> ToolResult<()> {
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
            "tinybms config PORT NAME (one field), or NAME=VALUE... to change fields",
        ));
    }
    if dry_run && load.is_none() {
        return Err(ToolError::usage("--dry-run goes with --load"));
    }
    let explain = match (&assignments, args.first()) {
        (None, Some(name)) => Some(config::field_named(name)?),
        _ => None,
    };
    // Secrets the saved bridge had set (the file names them, without values).
    let mut secrets_in_file: Vec<String> = Vec::new();
    let loaded = match load {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| ToolError::failed(format!("cannot read `{}`: {e}", path.display())))?;
            secrets_in_file = text
                .lines()
                .filter_map(|l| l.strip_prefix("# "))
                .filter_map(|l| l.strip_suffix(": set (secrets are not saved)"))
                .map(str::to_string)
                .collect();
            Some(
                config::parse_file(&text)
                    .map_err(|e| ToolError::usage(format!("{}: {e}", path.display())))?,
            )
        }
        None => None,
    };
    if reset
        && !yes
        && !confirm("Set every field of the bridge's configuration back to its default")?
    {
        return Err(ToolError::failed("not confirmed: nothing changed"));
    }
    let mut c = connect(conn)?;
    config::require_bridge(&c)?;
    let (fields, end) = config::fetch(&mut c).map_err(config::fetch_error)?;
    let current = config::record_of(&fields);
    if let Some(changes) = assignments {
        config::check_locally(&current, &changes)?;
        confirm_one_way(yes, &current, &changes)?;
        return config::apply(&mut c, &changes);
    }
    if let Some(wanted) = loaded {
        let changes = config::diff(&current, &wanted);
        config::check_locally(&current, &changes)?;
        println!(
            "{}: {} fields, {} differ from the bridge's",
            load.map(|p| p.display().to_string()).unwrap_or_default(),
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
        // Secrets are never in a file: say which the bridge now lacks, and how.
        let missing: Vec<&String> = secrets_in_file
            .iter()
            .filter(|name| {
                fields
                    .iter()
                    .any(|f| f.line["name"] == name.as_str() && f.line["value"] == "unset")
            })
            .collect();
        let say_missing = || {
            if !missing.is_empty() {
                let names: Vec<&str> = missing.iter().map(|s| s.as_str()).collect();
                println!(
                    "not restored: {} (secrets are never saved in a file). Set {} again: {}",
                    names.join(", "),
                    if names.len() == 1 { "it" } else { "them" },
                    secrets_hint(&names)
                );
            }
        };
        if dry_run || changes.is_empty() {
            if dry_run {
                println!("dry run: nothing changed");
            }
            say_missing();
            return Ok(());
        }
        confirm_one_way(yes, &current, &changes)?;
        config::apply(&mut c, &changes)?;
        say_missing();
        return Ok(());
    }
    if reset {
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
    if let Some(path) = save {
        let header = format!(
            "saved by tinybms {} from {} at {}",
            env!("CARGO_PKG_VERSION"),
            c.port,
            monitor::utc_now()
        );
        std::fs::write(path, config::file_text(&fields, &header))
            .map_err(|e| ToolError::failed(format!("cannot write `{}`: {e}", path.display())))?;
        let secrets = fields.iter().filter(|f| f.line["secret"] == true).count();
        println!(
            "saved {} fields to {} ({secrets} secrets left out)",
            fields.len() - secrets,
            path.display()
        );
    }
    Ok(())
}

pub use crate::words::suggest;

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
fn confirm_restart(yes: bool, items: &[(SettingId, i32)]) -> ToolResult<()> {
    let restarting: Vec<String> = items
        .iter()
        .filter(|(id, _)| id.restarts_bms())
        .map(|(id, _)| snake_name(*id))
        .collect();
    if restarting.is_empty() || yes {
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

/// The commands that set the secrets `names` again.
fn secrets_hint(names: &[&str]) -> String {
    let mut out = Vec::new();
    if names.contains(&"wifi_key") {
        out.push("`tinybms wifi PORT --ssid NAME` (asks for the passphrase)");
    }
    if names.contains(&"mqtt_password") {
        out.push("`tinybms mqtt PORT --host HOST --user USER` (asks for the password)");
    }
    if out.is_empty() {
        out.push("`tinybms config PORT NAME=VALUE`");
    }
    out.join(" and ")
}

/// A change that nothing over the host link can undo (`read_only=on`: from
/// then on the bridge refuses every change, this one's undoing included) is
/// made only when confirmed (or `--yes`), like `reset`.
fn confirm_one_way(
    yes: bool,
    current: &tinybms_firmware::config::Config,
    changes: &[(
        tinybms_firmware::config::FieldId,
        tinybms_firmware::config::value::Parsed,
    )],
) -> ToolResult<()> {
    use tinybms_firmware::config::value::Parsed;
    use tinybms_firmware::config::FieldId;
    let locks = !current.read_only
        && changes
            .iter()
            .any(|(id, p)| *id == FieldId::ReadOnly && *p == Parsed::Bool(true));
    if !locks || yes {
        return Ok(());
    }
    let question = "read_only=on is one-way: from then on the bridge refuses every change \
                    over USB, turning it off included; only the BOOT button held 5 s while the \
                    bridge runs (or erasing the flash) lifts it. Turn it on";
    if confirm(question)? {
        Ok(())
    } else {
        Err(ToolError::failed("not confirmed: nothing changed"))
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

/// Writes settings (raw values) in groups of 8 (the protocol's limit),
/// printing each outcome; fails when any did not end verified or unchanged.
fn write_settings(c: &mut Client, items: &[(SettingId, i32)]) -> ToolResult<()> {
    let (mut bad, mut verified, mut unchanged) = (0, 0, 0);
    for group in items.chunks(8) {
        let named: Vec<(String, f64)> = group
            .iter()
            .map(|(id, v)| (snake_name(*id), f64::from(*v)))
            .collect();
        let outcomes = c.set(&named, true, Duration::from_secs(15), |v| {
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
            let shown = match (v["name"].as_str().and_then(find_setting), v["raw"].as_i64()) {
                (Some(id), Some(raw)) => settings::physical(id, raw),
                _ => v["raw"].to_string(),
            };
            println!(
                "{:<36} {:>24}  {}{follow}{detail}",
                v["name"].as_str().unwrap_or("?"),
                shown,
                v["outcome"].as_str().unwrap_or("?")
            );
        })?;
        // The last word on each setting: a follow-up settles an unconfirmed one.
        for (name, _) in &named {
            let last = outcomes.iter().rev().find(|v| v["name"] == name.as_str());
            match last.and_then(|v| v["outcome"].as_str()) {
                Some("verified") => verified += 1,
                Some("unchanged") => unchanged += 1,
                _ => bad += 1,
            }
        }
    }
    let plural = |n: usize| if n == 1 { "" } else { "s" };
    let summary = match (verified, unchanged) {
        (v, 0) => format!("{v} setting{} verified", plural(v)),
        (0, u) => format!(
            "{u} setting{} already held that value (unchanged)",
            plural(u)
        ),
        (v, u) => format!("{v} setting{} verified, {u} unchanged", plural(v)),
    };
    if bad > 0 {
        return Err(ToolError::failed(format!(
            "{bad} of {} settings not verified on the BMS ({summary})",
            items.len()
        )));
    }
    println!("{summary}");
    Ok(())
}

fn record(conn: &Conn, file: &Path, duration: Duration) -> ToolResult<()> {
    let path = file.display().to_string();
    let f = std::fs::File::create(file)
        .map_err(|e| ToolError::failed(format!("cannot create `{path}`: {e}")))?;
    let header = format!(
        "recorded by tinybms {} from {} at {}",
        env!("CARGO_PKG_VERSION"),
        conn.port,
        monitor::utc_now()
    );
    let writer = CaptureWriter::new(Box::new(std::io::BufWriter::new(f)), &header)
        .map_err(|e| ToolError::failed(format!("writing `{path}`: {e}")))?;
    let port = conn.port.clone();
    let (serial, mode, probe) = open_and_probe(&port, choice(conn))?;
    let (mut tx, mut rx) = (0usize, 0usize);
    match (mode, probe) {
        (Mode::Direct, _) => {
            let _ = serial.clear(serialport::ClearBuffer::Input);
            let mut c = direct::start(serial, port.clone(), Some(writer))?;
            let _ = c.stream(0);
            let end = Instant::now() + duration;
            while Instant::now() < end && !interrupted() {
                let left = end.saturating_duration_since(Instant::now());
                let _ = c.next_pushed(left.min(Duration::from_millis(200)))?;
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
            // Ctrl-C ends the recording early; capture goes off all the same.
            while Instant::now() < end && !interrupted() {
                let left = end.saturating_duration_since(Instant::now());
                let Some(v) = c.next_pushed(left.min(Duration::from_millis(200)))? else {
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

fn choice(conn: &Conn) -> ModeChoice {
    match conn.mode {
        ModeArg::Auto => ModeChoice::Auto,
        ModeArg::Bridge => ModeChoice::Bridge,
        ModeArg::Direct => ModeChoice::Direct,
    }
}

/// [`connect`], then waits until the BMS is ready (settings and limits read).
fn connect_ready(conn: &Conn) -> ToolResult<Client> {
    let mut c = connect(conn)?;
    c.wait_ready(conn.timeout)?;
    Ok(c)
}

/// Opens the port, detects the mode and returns a client speaking the protocol.
fn connect(conn: &Conn) -> ToolResult<Client> {
    let port = conn.port.clone();
    status(&format!("connecting to {port}…"));
    let (serial, mode, probe) = open_and_probe(&port, choice(conn))?;
    if mode == Mode::Direct && conn.mode == ModeArg::Auto {
        status(&format!(
            "no bridge answered on {port}: talking to a TinyBMS on it directly (a USB-UART adapter; the firmware's bridge runs in this tool)"
        ));
    }
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
