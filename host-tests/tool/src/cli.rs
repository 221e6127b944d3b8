//! The command line of `tinybms`, declared with clap: per-command help and
//! options, unknown or misplaced options refused, suggestions for typos, shell
//! completions (`tinybms completions bash`).

use std::path::PathBuf;
use std::time::Duration;

use clap::{Args, Parser, Subcommand, ValueEnum};

use tinybms_desk::parse_duration;

fn duration(s: &str) -> Result<Duration, String> {
    parse_duration(s)
}

/// tinybms — read and configure a TinyBMS, through the ESP32 bridge or directly.
///
/// PORT is the serial port: the bridge's USB port (`tinybms ports` lists them),
/// or a USB-UART adapter wired to the TinyBMS (115200 8N1; then the firmware's
/// bridge runs inside this tool). Durations: 500ms, 10s, 5m, 1h.
///
/// Exit status: 0 ok, 1 failed (a write not verified...), 2 usage error,
/// 3 cannot reach the device, 130 interrupted (Ctrl-C).
#[derive(Debug, Parser)]
#[command(name = "tinybms", version, max_term_width = 100)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// How to reach the BMS: every command with a PORT has these.
#[derive(Debug, Clone, Args)]
pub struct Conn {
    /// The serial port (see `tinybms ports`).
    #[arg(value_name = "PORT")]
    pub port: String,
    /// auto: a bridge answers `{"cmd":"hello"}`; when nothing does, the port is
    /// taken to be a USB-UART adapter wired to the TinyBMS.
    #[arg(long, value_enum, default_value_t = ModeArg::Auto)]
    pub mode: ModeArg,
    /// How long to wait for the BMS to be ready.
    #[arg(long, value_parser = duration, default_value = "15s", value_name = "D")]
    pub timeout: Duration,
}

/// `--mode`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ModeArg {
    /// A bridge if one answers, else direct.
    Auto,
    /// Only a bridge (the ESP32's USB port, or `sim --bridge-pty`).
    Bridge,
    /// A TinyBMS on a USB-UART adapter.
    Direct,
}

/// The monitor's log format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FormatArg {
    /// One row per record, cells as columns.
    Csv,
    /// The telemetry line with a `time` member.
    Jsonl,
}

/// The commands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// List the serial ports.
    Ports,
    /// Live view: cells (lowest and highest marked, balancing), pack, SOC/SOH,
    /// temperatures, status, the age of the data, link quality.
    ///
    /// On a terminal a full-screen view (q quits); piped, plain text. The data
    /// age keeps counting between updates: data older than 5 s shows as NO DATA.
    Monitor {
        #[command(flatten)]
        conn: Conn,
        /// Print the telemetry lines (JSON Lines) instead.
        #[arg(long, conflicts_with = "plain")]
        json: bool,
        /// Plain text, also on a terminal (no full-screen view, no colours).
        #[arg(long)]
        plain: bool,
        /// Also log to FILE (CSV, or JSON Lines for .jsonl/.json).
        #[arg(long, value_name = "FILE")]
        log: Option<PathBuf>,
        /// Log period.
        #[arg(long, value_parser = duration, default_value = "10s", value_name = "D", requires = "log")]
        every: Duration,
        /// Log format (default: from the file's extension).
        #[arg(long, value_enum, requires = "log")]
        format: Option<FormatArg>,
        /// Telemetry period asked of the bridge (100ms to 60s); the bridge's own
        /// comes back when the monitor ends, Ctrl-C included.
        #[arg(long, value_parser = duration, default_value = "1s", value_name = "D")]
        period: Duration,
        /// Stop after N updates.
        #[arg(long, value_name = "N")]
        count: Option<u64>,
        /// Stop after D.
        #[arg(long, value_parser = duration, value_name = "D")]
        duration: Option<Duration>,
    },
    /// The bridge's own log lines, as they come (its reports, the inverter
    /// output's, Wi-Fi and MQTT).
    Log {
        #[command(flatten)]
        conn: Conn,
        /// Stop after D.
        #[arg(long, value_parser = duration, value_name = "D")]
        duration: Option<Duration>,
    },
    /// Every setting, grouped as in the BMS's own tool: value, raw, Rev D range,
    /// the BMS's min/max.
    Settings {
        #[command(flatten)]
        conn: Conn,
        /// Write them to FILE as a profile (`name = raw  # physical`).
        #[arg(long, value_name = "FILE", conflicts_with = "json")]
        save: Option<PathBuf>,
        /// Print the `setting` lines (JSON Lines) instead.
        #[arg(long)]
        json: bool,
    },
    /// Show what a profile changes, then write and verify each setting.
    Apply {
        #[command(flatten)]
        conn: Conn,
        /// The profile (`name = value` lines; values raw, with a unit, or a name).
        #[arg(value_name = "FILE")]
        file: PathBuf,
        /// Check everything, write nothing.
        #[arg(long)]
        dry_run: bool,
        /// Do not ask for confirmation.
        #[arg(long, short)]
        yes: bool,
        #[command(flatten)]
        chemistry: ChemistryArgs,
    },
    /// Write and verify settings: NAME=VALUE, VALUE in the unit `settings`
    /// prints (3.65 or 3.65V or 3650mV), or an enumeration value's name.
    Set {
        #[command(flatten)]
        conn: Conn,
        /// NAME=VALUE, at least one.
        #[arg(value_name = "NAME=VALUE", required = true)]
        assignments: Vec<String>,
        /// VALUE in raw register units instead (3650).
        #[arg(long)]
        raw: bool,
        /// Check everything, write nothing.
        #[arg(long)]
        dry_run: bool,
        /// Do not ask for confirmation.
        #[arg(long, short)]
        yes: bool,
        #[command(flatten)]
        chemistry: ChemistryArgs,
    },
    /// The BMS's event log, oldest first, with the wall-clock time.
    Events {
        #[command(flatten)]
        conn: Conn,
        /// Print the `event` lines (JSON Lines) instead.
        #[arg(long)]
        json: bool,
    },
    /// The bridge's own history in flash: its events (why it restarted, stale
    /// episodes, stops, configuration changes, updates, network losses) and
    /// its daily records of the pack (energy, cells, capacity).
    History {
        #[command(flatten)]
        conn: Conn,
        /// The daily records instead of the events.
        #[arg(long)]
        days: bool,
        /// Output: text, csv or json (JSON Lines).
        #[arg(long, value_name = "F", default_value = "text")]
        format: String,
    },
    /// The inverter's wire in words: why each limit is what it is, the
    /// inverter's heartbeat, what the doctor found and what to do — from a
    /// bridge, or from a candump capture of its CAN bus (`--capture`).
    Doctor {
        /// The bridge's serial port (not with --capture).
        #[arg(value_name = "PORT")]
        port: Option<String>,
        /// A capture file (candump log with the T/R direction flag).
        #[arg(long, value_name = "FILE")]
        capture: Option<std::path::PathBuf>,
        /// The protocol the bridge spoke in the capture.
        #[arg(long, value_name = "P", default_value = "victron")]
        protocol: String,
        /// From a bridge: also save its CAN capture (a candump log) to FILE.
        #[arg(long, value_name = "FILE")]
        out: Option<std::path::PathBuf>,
    },
    /// The statistics (registers 100-117).
    Stats {
        #[command(flatten)]
        conn: Conn,
        /// Print the `statistics` line (JSON) instead.
        #[arg(long)]
        json: bool,
    },
    /// Hardware/firmware version, serial number.
    Version {
        #[command(flatten)]
        conn: Conn,
        /// Print the `version` line (JSON) instead.
        #[arg(long)]
        json: bool,
    },
    /// Restart the BMS (asks for confirmation).
    Reset {
        #[command(flatten)]
        conn: Conn,
        /// Do not ask for confirmation.
        #[arg(long, short)]
        yes: bool,
    },
    /// Clear the BMS's event log (asks for confirmation).
    ClearEvents {
        #[command(flatten)]
        conn: Conn,
        /// Do not ask for confirmation.
        #[arg(long, short)]
        yes: bool,
    },
    /// Clear the BMS's statistics (asks for confirmation).
    ClearStats {
        #[command(flatten)]
        conn: Conn,
        /// Do not ask for confirmation.
        #[arg(long, short)]
        yes: bool,
    },
    /// Record the raw UART exchange as a capture `replay` reads.
    Record {
        #[command(flatten)]
        conn: Conn,
        /// The capture file (`.tbms`).
        #[arg(value_name = "FILE.tbms")]
        file: PathBuf,
        /// How long.
        #[arg(long, value_parser = duration, default_value = "10s", value_name = "D")]
        duration: Duration,
    },
    /// The bridge's own configuration (kept in its flash): every field, one
    /// field explained (NAME), or changes (NAME=VALUE..., a unit may be given:
    /// 50A), saved to the bridge's flash.
    Config {
        #[command(flatten)]
        conn: Conn,
        /// NAME, or NAME=VALUE...
        #[arg(value_name = "NAME[=VALUE]")]
        args: Vec<String>,
        /// Write the configuration to FILE (secrets left out).
        #[arg(long, value_name = "FILE", conflicts_with_all = ["load", "reset", "args"])]
        save: Option<PathBuf>,
        /// Show what FILE changes, then change it.
        #[arg(long, value_name = "FILE", conflicts_with_all = ["reset", "args"])]
        load: Option<PathBuf>,
        /// With --load or NAME=VALUE: check and show the changes only.
        #[arg(long)]
        dry_run: bool,
        /// Every field back to its default.
        #[arg(long, conflicts_with = "args")]
        reset: bool,
        /// Do not ask for confirmation.
        #[arg(long, short)]
        yes: bool,
    },
    /// The Wi-Fi network: asks for its passphrase and stores the WPA2 key
    /// derived from it (never the passphrase itself). Applies at the next restart.
    Wifi {
        #[command(flatten)]
        conn: Conn,
        /// The network's name.
        #[arg(long, value_name = "NAME")]
        ssid: String,
    },
    /// The MQTT broker (and user: asks for the password). Applies at the next
    /// restart.
    Mqtt {
        #[command(flatten)]
        conn: Conn,
        /// The broker's IPv4 address (or a name DNS resolves: an mDNS name
        /// such as homeassistant.local is likely not found by the bridge).
        #[arg(long, value_name = "HOST")]
        host: String,
        /// The broker's TCP port (PORT, the first argument, is the serial
        /// port of the bridge).
        #[arg(
            long = "port",
            id = "tcp_port",
            value_name = "P",
            default_value_t = 1883
        )]
        tcp_port: u16,
        /// User name at the broker (asks for its password).
        #[arg(long, value_name = "U")]
        user: Option<String>,
    },
    /// Update the bridge's firmware without a cable: the whole update file is
    /// checked first (its hash, and chip, board, version, features and
    /// signature against the bridge), then by the bridge, written to its
    /// other app slot while it keeps working, and booted on trial; a new image
    /// that fails before it confirms itself is rolled back by the bridge.
    Update {
        /// The bridge: its serial port, or its address on the network
        /// (HOST or HOST:PORT; its update port is 8232).
        #[arg(value_name = "PORT|HOST")]
        target: String,
        /// The update file (`tinybms-BOARD.tbu` of a release, or `tinybms sign`'s).
        #[arg(value_name = "FILE")]
        file: PathBuf,
        /// Take a version older than the running one.
        #[arg(long)]
        downgrade: bool,
        /// Take a file without features the bridge runs (wifi, can,
        /// host-link, store; comma-separated): they are gone after it.
        #[arg(long, value_name = "FEATURES")]
        drop: Option<String>,
        /// Check the whole file and ask the bridge whether it would take it
        /// (nothing is written).
        #[arg(long)]
        check: bool,
        /// Do not ask for confirmation.
        #[arg(long, short)]
        yes: bool,
    },
    /// A new signing key for updates: FILE (private) and FILE.pub.
    Keygen {
        /// Where to write the private key (never overwritten).
        #[arg(value_name = "FILE")]
        out: PathBuf,
    },
    /// The public key of a signing key (what a bridge is told to trust).
    PublicKey {
        /// The private key's file.
        #[arg(value_name = "KEY")]
        key: PathBuf,
    },
    /// Make an update file: an app image, what it is for, signed.
    Sign {
        /// The private key's file (`tinybms keygen`).
        #[arg(long, value_name = "KEY")]
        key: PathBuf,
        /// esp32c3 or esp32c6.
        #[arg(long)]
        chip: String,
        /// The board (its name in `tinybms version`'s hello: c3-supermini, …).
        #[arg(long)]
        board: String,
        /// The version: read from the image; if given, it must be the one
        /// the image reports.
        #[arg(long)]
        version: Option<String>,
        /// What is built in, comma-separated (can,host-link,wifi,store):
        /// read from the image; if given, it must be the image's (only an
        /// image of an older build needs it).
        #[arg(long)]
        features: Option<String>,
        /// What it was built from: read from the image; if given, it must be
        /// the image's (only an image of an older build needs it).
        #[arg(long)]
        build: Option<String>,
        /// The app image (`tinybms-BOARD-app.bin`).
        #[arg(value_name = "APP.bin")]
        image: PathBuf,
        /// The update file to write.
        #[arg(long, short, value_name = "OUT.tbu")]
        out: PathBuf,
    },
    /// Shell completions: `tinybms completions bash > /etc/bash_completion.d/tinybms`.
    Completions {
        /// bash, zsh, fish, elvish or powershell.
        #[arg(value_enum)]
        shell: clap_complete::Shell,
    },
}

impl Command {
    /// The connection options, for the commands that have a PORT.
    pub fn conn(&self) -> Option<&Conn> {
        match self {
            Command::Ports
            | Command::Completions { .. }
            | Command::Update { .. }
            | Command::Keygen { .. }
            | Command::PublicKey { .. }
            | Command::Doctor { .. }
            | Command::Sign { .. } => None,
            Command::Monitor { conn, .. }
            | Command::Log { conn, .. }
            | Command::Settings { conn, .. }
            | Command::Apply { conn, .. }
            | Command::Set { conn, .. }
            | Command::Events { conn, .. }
            | Command::History { conn, .. }
            | Command::Stats { conn, .. }
            | Command::Version { conn, .. }
            | Command::Reset { conn, .. }
            | Command::ClearEvents { conn, .. }
            | Command::ClearStats { conn, .. }
            | Command::Record { conn, .. }
            | Command::Config { conn, .. }
            | Command::Wifi { conn, .. }
            | Command::Mqtt { conn, .. } => Some(conn),
        }
    }
}

/// The cell chemistry the cell voltages of `set` / `apply` are checked
/// against. The TinyBMS does not say its chemistry: by default it is inferred
/// from the over-voltage cutoff (else the fully-charged voltage) the BMS holds.
#[derive(Debug, Clone, Copy, clap::Args)]
pub struct ChemistryArgs {
    /// The pack's cell chemistry: lifepo4, li-ion (NMC/NCA) or lto (default:
    /// inferred from the cutoffs the BMS holds).
    #[arg(long, value_parser = chemistry, value_name = "CHEM")]
    pub chemistry: Option<protocol_core::settings::Chemistry>,
    /// Write cell voltages outside the chemistry's plausible window anyway
    /// (an expert's other chemistry). The relations between settings (under-
    /// below over-voltage cutoff, …) are checked all the same.
    #[arg(long, conflicts_with = "chemistry")]
    pub force: bool,
}

impl ChemistryArgs {
    /// What the bridge checks the values against.
    pub fn check(self) -> protocol_core::settings::ChemistryCheck {
        use protocol_core::settings::ChemistryCheck;
        match (self.force, self.chemistry) {
            (true, _) => ChemistryCheck::Off,
            (false, Some(c)) => ChemistryCheck::Given(c),
            (false, None) => ChemistryCheck::Inferred,
        }
    }
}

fn chemistry(s: &str) -> Result<protocol_core::settings::Chemistry, String> {
    protocol_core::settings::Chemistry::from_key(s)
        .ok_or_else(|| format!("`{s}`: lifepo4, li-ion or lto"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn the_command_line_is_consistent() {
        Cli::command().debug_assert();
    }
}
