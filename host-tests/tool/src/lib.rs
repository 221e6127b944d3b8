//! `tinybms`, the desktop tool: talks to a TinyBMS through the ESP32 bridge's
//! USB port, or directly over a USB-UART adapter (then the firmware's own bridge
//! and host link run inside the tool, so both ways speak the same protocol,
//! firmware/src/host_link/PROTOCOL.md). `src/main.rs` only calls [`main`].
//!
//! * [`transport`] — opening the port, the hello probe, lines over a serial port.
//! * [`direct`] — the in-process bridge for direct mode.
//! * [`client`] — the protocol's commands as calls.
//! * [`monitor`], [`settings`] — what the commands print.

pub mod cli;
pub mod client;
pub mod cmd;
pub mod config;
pub mod direct;
pub mod live;
pub mod monitor;
pub mod picture;
pub mod settings;
pub mod transport;

use std::io::{BufRead, Write};
use std::path::Path;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use clap::{CommandFactory, Parser};
use protocol_core::settings::SettingId;
use tinybms_firmware::host_link::schema::{Hello, HostLine, Read};
use tinybms_firmware::host_link::PROTOCOL_VERSION;

use tinybms_rules::profile::{find_setting, snake_name};

use cli::{Cli, Command, Conn, ModeArg};
use client::Client;
pub use tinybms_desk::end_quietly_on_a_closed_pipe;
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

/// A question waits for the user's answer on stdin.
static PROMPTING: AtomicBool = AtomicBool::new(false);

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
        if INTERRUPTED.swap(true, Ordering::Relaxed) || PROMPTING.load(Ordering::Relaxed) {
            // A second Ctrl-C (the user insists), or one at a question
            // (reading stdin would wait for Enter): nothing was changed yet.
            eprintln!("\ntinybms: interrupted");
            std::process::exit(130);
        }
    });
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if e.status == 130 => {
            eprintln!("tinybms: interrupted");
            ExitCode::from(130)
        }
        Err(e) if e.status == 2 => {
            // A usage error reads as clap's own (`error: …`, then where help is).
            eprintln!(
                "error: {}\n\nFor more information, try '--help'.",
                e.message
            );
            ExitCode::from(2)
        }
        Err(e) => {
            eprintln!("tinybms: {}", e.message);
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
        Command::Ports => cmd::ports::run(),
        Command::Completions { shell } => {
            // `config`'s NAME=VALUE completes the configuration's field
            // names (for the completions only: the parser takes any text
            // and says what is wrong with it).
            // (Leaked: the command prints and ends; clap's names are 'static.)
            let names: Vec<&'static str> = tinybms_firmware::config::FIELDS
                .iter()
                .map(|f| &*Box::leak(format!("{}=", f.name).into_boxed_str()))
                .collect();
            let mut cmd = Cli::command().mut_subcommand("config", |c| {
                c.mut_arg("args", |a| {
                    a.value_parser(clap::builder::PossibleValuesParser::new(names))
                })
            });
            clap_complete::generate(shell, &mut cmd, "tinybms", &mut std::io::stdout());
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
        } => cmd::monitor::run(
            conn, json, plain, log, every, format, period, count, duration,
        ),
        Command::Log { conn, duration } => cmd::log::run(conn, duration),
        Command::Settings { conn, save, json } => cmd::settings::run(conn, save, json),
        Command::Apply {
            conn,
            file,
            dry_run,
            yes,
            chemistry,
        } => cmd::apply::run(conn, file, dry_run, yes, chemistry.check()),
        Command::Set {
            conn,
            assignments,
            raw,
            dry_run,
            yes,
            chemistry,
        } => cmd::set::run(conn, assignments, raw, dry_run, yes, chemistry.check()),
        Command::Events { conn, json } => cmd::events::run(conn, json),
        Command::History { conn, days, format } => cmd::history::run(conn, days, &format),
        Command::Doctor {
            port,
            capture,
            protocol,
            out,
        } => cmd::doctor::run(port, capture.as_deref(), &protocol, out.as_deref()),
        Command::Stats { conn, json } => cmd::show::show_one(&conn, "statistics", json),
        Command::Version { conn, json } => cmd::show::version(&conn, json),
        Command::Reset { conn, yes } => cmd::clear::clear_or_reset(&conn, yes, "reset"),
        Command::ClearEvents { conn, yes } => cmd::clear::clear_or_reset(&conn, yes, "events"),
        Command::ClearStats { conn, yes } => cmd::clear::clear_or_reset(&conn, yes, "statistics"),
        Command::Record {
            conn,
            file,
            duration,
        } => cmd::record::record(&conn, &file, duration),
        Command::Config {
            conn,
            args,
            save,
            load,
            dry_run,
            reset,
            yes,
        } => cmd::config::run_config(
            &conn,
            &args,
            save.as_deref(),
            load.as_deref(),
            dry_run,
            reset,
            yes,
        ),
        Command::Wifi { conn, ssid } => cmd::wifi::run(conn, ssid),
        Command::Update {
            target,
            file,
            downgrade,
            drop,
            check,
            yes,
        } => update(&target, &file, downgrade, drop.as_deref(), check, yes),
        Command::Keygen { out } => cmd::update::keygen(&out),
        Command::PublicKey { key } => cmd::update::public_key(&key),
        Command::Sign {
            key,
            chip,
            board,
            version,
            features,
            build,
            image,
            out,
        } => cmd::update::sign(&cmd::update::SignArgs {
            key,
            image,
            out,
            chip,
            board,
            version,
            features,
            build,
        }),
        Command::Mqtt {
            conn,
            host,
            tcp_port,
            user,
        } => cmd::mqtt::run(conn, host, tcp_port, user),
    }
}

/// A profile FILE: a regular file (a serial port there means PORT and FILE
/// were swapped: reading it would wait forever).
fn read_profile(file: &Path, port: &str) -> ToolResult<String> {
    let shown = file.display();
    let meta = std::fs::metadata(file)
        .map_err(|e| ToolError::failed(format!("cannot read the profile `{shown}`: {e}")))?;
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

pub use tinybms_rules::words::suggest;

fn serial_suffix(c: &mut Client) -> String {
    match c.get_one("version").map(|r| r.line) {
        Ok(HostLine::Version(v)) => format!(", BMS serial {}", v.serial_number),
        _ => String::new(),
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

fn confirm(question: &str) -> ToolResult<bool> {
    print!("{question}? Type `yes` to go on: ");
    let _ = std::io::stdout().flush();
    let mut line = String::new();
    // Ctrl-C while the question waits ends the tool at once (the handler
    // sees this flag), not at the next Enter.
    PROMPTING.store(true, Ordering::Relaxed);
    let read = std::io::stdin().lock().read_line(&mut line);
    PROMPTING.store(false, Ordering::Relaxed);
    read.map_err(|e| ToolError::failed(format!("reading the answer: {e}")))?;
    if interrupted() {
        return Err(interrupted_error());
    }
    Ok(line.trim().eq_ignore_ascii_case("yes") || line.trim().eq_ignore_ascii_case("y"))
}

/// Writes settings (raw values) in groups of 8 (the protocol's limit),
/// printing each outcome; fails when any did not end verified or unchanged.
fn write_settings(
    c: &mut Client,
    items: &[(SettingId, i32)],
    chemistry: protocol_core::settings::ChemistryCheck,
) -> ToolResult<()> {
    let (mut bad, mut verified, mut unchanged) = (0, 0, 0);
    for group in items.chunks(8) {
        let named: Vec<(String, f64)> = group
            .iter()
            .map(|(id, v)| (snake_name(*id), f64::from(*v)))
            .collect();
        let outcomes = c.set(&named, true, chemistry, Duration::from_secs(15), |v| {
            let follow = if v.follow_up { " (follow-up)" } else { "" };
            let detail = v
                .detail
                .as_deref()
                .filter(|d| !d.is_empty())
                .map(|d| format!(": {d}"))
                .unwrap_or_default();
            let shown = match find_setting(&v.name) {
                Some(id) => settings::physical(id, i64::from(v.raw)),
                None => v.raw.to_string(),
            };
            println!(
                "{:<36} {:>24}  {}{follow}{detail}",
                v.name, shown, v.outcome
            );
        })?;
        // The last word on each setting: a follow-up settles an unconfirmed one.
        for (name, _) in &named {
            let last = outcomes.iter().rev().find(|v| v.name == *name);
            match last.map(|v| v.outcome.as_str()) {
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

type Probed = Option<(Hello<Read>, transport::LineSplitter)>;

/// Opens the port and finds out what is on it.
fn open_and_probe(
    port: &str,
    choice: ModeChoice,
) -> ToolResult<(Box<dyn serialport::SerialPort>, Mode, Probed)> {
    let mut serial = transport::open_port(port)?;
    if choice == ModeChoice::Direct {
        return Ok((serial, Mode::Direct, None));
    }
    // The ESP32's own USB is a bridge or nothing this tool can use: it waits
    // the whole probe and never falls back to direct mode. Any other port in
    // auto mode that stays silent is taken for a TinyBMS's adapter at once.
    let esp32 = transport::is_esp32_usb(port);
    let silent_is_no = choice == ModeChoice::Auto && !esp32;
    let (probe, split) = transport::probe(&mut serial, transport::PROBE_TIME, silent_is_no)?;
    if let Some(raw) = &probe.unread_hello {
        return Err(other_protocol(port, raw));
    }
    match (probe.hello, choice) {
        (Some(h), _) if h.protocol != PROTOCOL_VERSION => Err(other_protocol(
            port,
            &serde_json::json!({"protocol": h.protocol, "firmware": h.firmware}),
        )),
        (Some(h), _) => Ok((serial, Mode::Bridge, Some((h, split)))),
        // JSON lines are a bridge's, never a TinyBMS's: TinyBMS frames sent
        // at it would only be refused.
        (None, ModeChoice::Auto) if probe.json_lines > 0 => Err(ToolError::connect(format!(
            "something on `{port}` writes JSON lines ({} heard) but did not answer the \
             hello: a bridge busy or stuck? Unplug it and plug it in again, then retry",
            probe.json_lines
        ))),
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
        (None, _) if esp32 => Err(ToolError::connect(format!(
            "the ESP32 on `{port}` (its own USB) did not answer the hello ({} bytes heard): \
             is the bridge firmware flashed on it (docs/flashing.md)? If it was just plugged \
             in, retry in a few seconds",
            probe.bytes
        ))),
        (None, _) => Ok((serial, Mode::Direct, None)),
    }
}

/// A bridge whose hello this tool does not read, or whose protocol is not
/// this tool's: its lines would be misread, so nothing more is sent to it.
fn other_protocol(port: &str, hello: &serde_json::Value) -> ToolError {
    let said = |k: &str| match hello.get(k) {
        Some(serde_json::Value::String(s)) => s.clone(),
        Some(v) if !v.is_null() => v.to_string(),
        _ => "not given".to_string(),
    };
    ToolError::connect(format!(
        "the bridge on `{port}` speaks another version of the host-link protocol \
         (its protocol {}, firmware {}; this tool reads protocol {PROTOCOL_VERSION}, \
         firmware {}): flash the firmware that matches this tool (docs/flashing.md), \
         or use the tool released with the bridge's firmware",
        said("protocol"),
        said("firmware"),
        env!("CARGO_PKG_VERSION"),
    ))
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

/// `tinybms update PORT|HOST FILE`: a serial port (a path that exists, or
/// COMn), else a bridge on the network at its update port.
fn update(
    target: &str,
    file: &Path,
    downgrade: bool,
    drop: Option<&str>,
    check: bool,
    yes: bool,
) -> ToolResult<()> {
    refuse_swapped_update(target, file)?;
    let drop_bits = match drop {
        None => 0,
        Some(list) => tinybms_firmware::update::file::feature_bits(list).ok_or_else(|| {
            ToolError::usage(format!(
                "--drop {list}: not feature names (can, host-link, wifi, store)"
            ))
        })?,
    };
    let permit = tinybms_firmware::update::file::Permit {
        downgrade,
        drop: drop_bits,
    };
    let (bytes, header) = cmd::update::read_update(file)?;
    // The whole file before anything else: a damaged download never starts.
    cmd::update::check_whole(file, &bytes, &header)?;
    let mut c = connect_bridge_or_host(target)?;
    let h = &c.hello;
    println!(
        "bridge: {} {} on {}, firmware {}",
        h.chip, h.board, c.port, h.firmware
    );
    println!(
        "update: {} {} {} ({} KiB, built from {}, with {})",
        header.chip(),
        header.board(),
        header.version(),
        header.image_len / 1024,
        if header.build().is_empty() {
            "?"
        } else {
            header.build()
        },
        if header.features().is_empty() {
            "?"
        } else {
            header.features()
        },
    );
    cmd::update::check_for(&header, &c.hello, permit)?;
    if check {
        cmd::update::send(&mut c, &bytes, permit, true, true)?;
        println!(
            "the whole file checked (its hash and signature), and the bridge would take it \
             (nothing was sent beyond the header)"
        );
        return Ok(());
    }
    if !yes && !confirm("Update the bridge (it restarts into the new firmware, on trial)")? {
        return Err(ToolError::failed("not confirmed: nothing sent"));
    }
    let v = cmd::update::send(&mut c, &bytes, permit, false, false)?;
    println!(
        "installed {v}: the bridge restarts into it on trial; it confirms itself once BMS data \
         and the inverter output run, else the bridge goes back to {} by itself \
         (`tinybms version PORT` or its hello says which runs)",
        c.hello.firmware
    );
    if let Some(note) = cmd::update::history_note(&c.hello) {
        println!("{note}");
    }
    Ok(())
}

/// `update FILE PORT` instead of `update PORT FILE`: said at once (the file
/// opened as a port would wait forever).
fn refuse_swapped_update(target: &str, file: &Path) -> ToolResult<()> {
    let is_update_file = |p: &Path| {
        std::fs::File::open(p).is_ok_and(|mut f| {
            use std::io::Read as _;
            let mut magic = [0u8; 8];
            p.is_file()
                && f.read_exact(&mut magic).is_ok()
                && &magic == tinybms_firmware::update::file::MAGIC
        })
    };
    let target_path = Path::new(target);
    let file_is_port = file.exists() && !file.is_file();
    if is_update_file(target_path) || (target_path.is_file() && file_is_port) {
        return Err(ToolError::usage(format!(
            "`{target}` is the update file and `{}` the bridge: the bridge comes first \
             (tinybms update {} {target})",
            file.display(),
            file.display()
        )));
    }
    if target_path.is_file() {
        return Err(ToolError::usage(format!(
            "`{target}` is a file, not the bridge's serial port or network address \
             (tinybms update PORT|HOST FILE)"
        )));
    }
    if file_is_port {
        return Err(ToolError::usage(format!(
            "`{}` is not an update file (a device, a folder): give the .tbu file",
            file.display()
        )));
    }
    Ok(())
}

/// HOST or HOST:PORT, resolved (the update port by default).
/// A serial port (a path that exists, or `COMn`): not a host on the network.
pub(crate) fn is_serial(target: &str) -> bool {
    Path::new(target).exists() || target.to_ascii_uppercase().starts_with("COM")
}

/// A bridge on a serial port, or on its update port over the network
/// (`HOST[:PORT]`, TCP 8232 by default; only `hello`, `get can` and the
/// update commands are answered there).
pub(crate) fn connect_bridge_or_host(target: &str) -> ToolResult<Client> {
    if is_serial(target) {
        let conn = Conn {
            port: target.to_string(),
            mode: ModeArg::Bridge,
            timeout: Duration::from_secs(15),
        };
        let c = connect(&conn)?;
        config::require_bridge(&c)?;
        return Ok(c);
    }
    let addr = tcp_address(target)?;
    status(&format!("connecting to {addr}…"));
    let mut lines = transport::TcpLines::connect(&addr, Duration::from_secs(5))?;
    let hello = transport::hello_over(&mut lines, Duration::from_secs(5))?;
    Ok(Client::new(
        Box::new(lines),
        Mode::Bridge,
        hello,
        addr.to_string(),
    ))
}

fn tcp_address(target: &str) -> ToolResult<std::net::SocketAddr> {
    use std::net::ToSocketAddrs;
    let with_port = if target.contains(':') {
        target.to_string()
    } else {
        format!("{target}:{}", cmd::update::TCP_PORT)
    };
    with_port
        .to_socket_addrs()
        .ok()
        .and_then(|mut a| a.next())
        .ok_or_else(|| {
            ToolError::usage(format!(
                "`{target}` is neither a serial port nor a host name or address"
            ))
        })
}

/// Opens the port, detects the mode and returns a client speaking the protocol.
fn connect(conn: &Conn) -> ToolResult<Client> {
    let port = conn.port.clone();
    status(&format!("connecting to {port}…"));
    let (serial, mode, probe) = open_and_probe(&port, choice(conn))?;
    if mode == Mode::Direct && conn.mode == ModeArg::Auto {
        status(&format!(
            "no bridge answered on {port}: trying a TinyBMS on it directly (a USB-UART \
             adapter; the firmware's bridge runs in this tool)"
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
