//! How the tool reaches the bridge's protocol: lines in, lines out.
//!
//! * [`SerialLines`] — **through the bridge**: the ESP32's USB port (or `sim
//!   --bridge-pty`) speaks the JSON Lines protocol itself.
//! * [`super::direct::DirectLines`] — **direct**: a USB-UART adapter wired to
//!   the TinyBMS; the firmware's bridge and host link run inside the tool
//!   (`tinybms_desk::Driver`), so everything above this layer is the same.
//!
//! [`open_port`] opens the port (with a helpful sentence for each way that
//! fails); [`probe`] sends `{"cmd":"hello"}` and reports what answers, from
//! which the tool picks the mode.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use serde_json::Value;
use tinybms_firmware::host_link::schema::{self, Hello, HostLine};

use super::{ToolError, ToolResult};

/// Longest line accepted from the bridge; longer ones are discarded up to the
/// next newline (a settings line is ≈ 200 bytes, a 16-cell telemetry line ≈ 900).
pub const MAX_LINE: usize = 16 * 1024;

/// Which side of the protocol the tool talks to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// An ESP32 running the bridge firmware (or `sim --bridge-pty`).
    Bridge,
    /// A TinyBMS on a USB-UART adapter; the bridge runs in the tool.
    Direct,
}

impl Mode {
    /// For messages.
    pub fn describe(self) -> &'static str {
        match self {
            Mode::Bridge => "through the bridge",
            Mode::Direct => "direct to the TinyBMS (the firmware's bridge runs in this tool)",
        }
    }
}

/// What `--mode` asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModeChoice {
    /// Detect: a `hello` answer means a bridge.
    Auto,
    /// Only a bridge.
    Bridge,
    /// Only direct.
    Direct,
}

/// A bidirectional stream of protocol lines.
pub trait Lines: Send {
    /// Sends one line (the newline is added).
    fn send_line(&mut self, line: &str) -> ToolResult<()>;
    /// The next line, waiting up to `timeout`; `None` when none came.
    fn recv_line(&mut self, timeout: Duration) -> ToolResult<Option<String>>;
}

/// Splits a byte stream into lines: `\n`-terminated, a `\r` before it dropped,
/// a line over [`MAX_LINE`] discarded up to the next newline.
#[derive(Debug, Default)]
pub struct LineSplitter {
    lines: std::collections::VecDeque<String>,
    cur: Vec<u8>,
    discarding: bool,
    /// Lines discarded for length.
    pub too_long: u64,
}

impl LineSplitter {
    /// Adds bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        for &b in bytes {
            if b == b'\n' {
                if !self.discarding {
                    if self.cur.last() == Some(&b'\r') {
                        self.cur.pop();
                    }
                    self.lines
                        .push_back(String::from_utf8_lossy(&self.cur).into_owned());
                }
                self.discarding = false;
                self.cur.clear();
            } else if !self.discarding {
                if self.cur.len() >= MAX_LINE {
                    self.discarding = true;
                    self.cur.clear();
                    self.too_long += 1;
                } else {
                    self.cur.push(b);
                }
            }
        }
    }

    /// The next complete line, if any.
    pub fn next_line(&mut self) -> Option<String> {
        self.lines.pop_front()
    }

    /// The next line within `timeout`, reading with `read(buf, time left)`:
    /// the bytes it got (0: none yet). `None` when no line came in time.
    pub fn next_within(
        &mut self,
        timeout: Duration,
        mut read: impl FnMut(&mut [u8], Duration) -> ToolResult<usize>,
    ) -> ToolResult<Option<String>> {
        let end = Instant::now() + timeout;
        let mut buf = [0u8; 1024];
        loop {
            if let Some(l) = self.next_line() {
                return Ok(Some(l));
            }
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            let n = read(&mut buf, left)?;
            self.push(buf.get(..n).unwrap_or(&[]));
        }
    }
}

/// Lines over a serial port (through the bridge).
pub struct SerialLines {
    port: Box<dyn serialport::SerialPort>,
    split: LineSplitter,
}

impl SerialLines {
    /// Lines over `port`, with bytes already received.
    pub fn new(port: Box<dyn serialport::SerialPort>, split: LineSplitter) -> Self {
        Self { port, split }
    }
}

fn io_error(what: &str, e: std::io::Error) -> ToolError {
    ToolError::failed(format!(
        "{what}: {e} (was the device unplugged or reset? run `tinybms ports`)"
    ))
}

impl Lines for SerialLines {
    fn send_line(&mut self, line: &str) -> ToolResult<()> {
        let mut bytes = Vec::with_capacity(line.len() + 1);
        bytes.extend_from_slice(line.as_bytes());
        bytes.push(b'\n');
        self.port
            .write_all(&bytes)
            .and_then(|()| self.port.flush())
            .map_err(|e| io_error("writing to the port", e))
    }

    fn recv_line(&mut self, timeout: Duration) -> ToolResult<Option<String>> {
        let port = &mut self.port;
        self.split.next_within(timeout, |buf, left| {
            let _ = port.set_timeout(left.max(Duration::from_millis(1)));
            match port.read(buf) {
                Ok(0) => {
                    std::thread::sleep(Duration::from_millis(5));
                    Ok(0)
                }
                Ok(n) => Ok(n),
                Err(e) if quiet(&e) => Ok(0),
                Err(e) => Err(io_error("reading from the port", e)),
            }
        })
    }
}

/// Lines over TCP (a bridge's update port on the network).
pub struct TcpLines {
    stream: std::net::TcpStream,
    split: LineSplitter,
}

impl TcpLines {
    /// Connects to `addr` within `timeout`.
    pub fn connect(addr: &std::net::SocketAddr, timeout: Duration) -> ToolResult<Self> {
        let stream = std::net::TcpStream::connect_timeout(addr, timeout)
            .map_err(|e| ToolError::connect(format!("cannot reach the bridge at {addr}: {e}")))?;
        let _ = stream.set_nodelay(true);
        Ok(Self {
            stream,
            split: LineSplitter::default(),
        })
    }
}

impl Lines for TcpLines {
    fn send_line(&mut self, line: &str) -> ToolResult<()> {
        let mut bytes = Vec::with_capacity(line.len() + 1);
        bytes.extend_from_slice(line.as_bytes());
        bytes.push(b'\n');
        self.stream
            .write_all(&bytes)
            .map_err(|e| ToolError::failed(format!("writing to the bridge: {e}")))
    }

    fn recv_line(&mut self, timeout: Duration) -> ToolResult<Option<String>> {
        let stream = &mut self.stream;
        self.split.next_within(timeout, |buf, left| {
            let _ = stream.set_read_timeout(Some(left.max(Duration::from_millis(1))));
            match stream.read(buf) {
                Ok(0) => Err(ToolError::failed("the bridge closed the connection")),
                Ok(n) => Ok(n),
                Err(e) if quiet(&e) || e.kind() == std::io::ErrorKind::WouldBlock => Ok(0),
                Err(e) => Err(ToolError::failed(format!("reading from the bridge: {e}"))),
            }
        })
    }
}

/// Sends `hello` on `lines` and waits up to `time` for the bridge's.
pub fn hello_over(lines: &mut dyn Lines, time: Duration) -> ToolResult<Hello<schema::Read>> {
    lines.send_line(r#"{"cmd":"hello"}"#)?;
    let end = Instant::now() + time;
    loop {
        let left = end.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(ToolError::connect(
                "no hello from the bridge (not its update port?)",
            ));
        }
        if let Some(l) = lines.recv_line(left)? {
            if let Ok(HostLine::Hello(h)) = serde_json::from_str::<HostLine>(&l) {
                return Ok(h);
            }
        }
    }
}

/// Every serial port the system lists, as `path  description` lines.
pub fn port_list() -> Vec<String> {
    let mut out = Vec::new();
    if let Ok(ports) = serialport::available_ports() {
        for p in ports {
            let what = match p.port_type {
                serialport::SerialPortType::UsbPort(u) => {
                    let mut s = format!("USB {:04x}:{:04x}", u.vid, u.pid);
                    for part in [u.manufacturer, u.product].into_iter().flatten() {
                        s.push(' ');
                        s.push_str(&part);
                    }
                    if (u.vid, u.pid) == (0x303a, 0x1001) {
                        s.push_str(" (ESP32 USB-Serial-JTAG: a bridge?)");
                    }
                    s
                }
                serialport::SerialPortType::PciPort => "PCI".into(),
                serialport::SerialPortType::BluetoothPort => "Bluetooth".into(),
                serialport::SerialPortType::Unknown => "unknown".into(),
            };
            out.push(format!("{:<20} {what}", p.port_name));
        }
    }
    out.sort();
    out
}

fn ports_hint() -> String {
    let list = port_list();
    if list.is_empty() {
        "No serial port is present at all: plug the adapter or the ESP32 in (and check \
         `dmesg` for it)."
            .into()
    } else {
        format!("Serial ports present:\n  {}", list.join("\n  "))
    }
}

/// Opens `path` at 115200 8N1, with a helpful sentence for the usual failures.
pub fn open_port(path: &str) -> ToolResult<Box<dyn serialport::SerialPort>> {
    let r = serialport::new(path, 115_200)
        .data_bits(serialport::DataBits::Eight)
        .parity(serialport::Parity::None)
        .stop_bits(serialport::StopBits::One)
        .flow_control(serialport::FlowControl::None)
        .timeout(Duration::from_millis(100))
        .open();
    match r {
        Ok(p) => Ok(p),
        Err(e) => {
            use serialport::ErrorKind as K;
            use std::io::ErrorKind as IO;
            let msg = match e.kind() {
                K::Io(IO::NotFound) | K::InvalidInput if !std::path::Path::new(path).exists() => {
                    format!("there is no serial port `{path}`. {}", ports_hint())
                }
                _ if not_a_tty_device(path) || not_a_terminal(&e) => {
                    format!(
                        "`{path}` is not a serial port (not a tty device). {}",
                        ports_hint()
                    )
                }
                K::Io(IO::PermissionDenied) => format!(
                    "permission denied on `{path}`: your user may not open serial ports. \
                     On most Linux systems: `sudo usermod -aG dialout $USER` (then log out \
                     and in again), or a udev rule giving the device to your user (e.g. \
                     /etc/udev/rules.d/99-tinybms.rules with \
                     SUBSYSTEM==\"tty\", MODE=\"0660\", GROUP=\"dialout\")."
                ),
                K::NoDevice => format!(
                    "`{path}` is in use by another program (a serial monitor, ModemManager, \
                     another tinybms?): close it and try again ({e})"
                ),
                _ => format!("cannot open `{path}`: {e}. {}", ports_hint()),
            };
            Err(ToolError::connect(msg))
        }
    }
}

/// What the probe heard besides a hello.
#[derive(Debug, Default)]
pub struct ProbeResult {
    /// The `hello` line, when a bridge answered.
    pub hello: Option<Hello<schema::Read>>,
    /// Bytes received in all.
    pub bytes: usize,
    /// Complete JSON objects received that were not a hello.
    pub json_lines: usize,
    /// A line that says it is a `hello` but that this tool's line types do
    /// not read (a bridge whose firmware speaks another version of the
    /// protocol): kept to name it in the error.
    pub unread_hello: Option<Value>,
}

/// How long the probe waits for a `hello` answer (twice: the hello is sent
/// again halfway, in case the first one met a bridge still booting).
pub const PROBE_TIME: Duration = Duration::from_millis(1600);

/// A port that stays silent this long after the hello is no bridge: a
/// running bridge answers in milliseconds, and one that the port's opening
/// reset (a USB-UART bridge's DTR) prints its ROM's boot text within tens of
/// milliseconds, so bytes arrive either way. A silent port is a TinyBMS
/// behind a USB-UART adapter (it never answers JSON) or nothing at all.
pub const SILENT_AFTER: Duration = Duration::from_millis(200);

/// The ESP32's own USB (USB-Serial-JTAG: the SuperMini, the XIAO, the
/// DevKitC-1's "USB" port): a bridge or an ESP32 without this firmware,
/// never a USB-UART adapter to a TinyBMS.
pub fn is_esp32_usb(path: &str) -> bool {
    serialport::available_ports().is_ok_and(|ports| {
        ports.iter().any(|p| {
            p.port_name == path
                && matches!(&p.port_type, serialport::SerialPortType::UsbPort(u) if (u.vid, u.pid) == (0x303a, 0x1001))
        })
    })
}

/// Sends `{"cmd":"hello"}` and listens. Returns the splitter holding what came
/// after the hello, for [`SerialLines`].
///
/// `silent_is_no`: a port silent for [`SILENT_AFTER`] ends the probe (auto
/// mode on a port that may be a TinyBMS's adapter).
pub fn probe(
    port: &mut Box<dyn serialport::SerialPort>,
    time: Duration,
    silent_is_no: bool,
) -> ToolResult<(ProbeResult, LineSplitter)> {
    let mut result = ProbeResult::default();
    let mut split = LineSplitter::default();
    let _ = port.clear(serialport::ClearBuffer::Input);
    let start = Instant::now();
    let mut sent = 0;
    let mut buf = [0u8; 512];
    // JSON lines that are not a hello (telemetry pushed by a bridge) mean a
    // bridge is there, maybe slow to answer: then wait three times as long.
    while start.elapsed()
        < if result.json_lines > 0 {
            time * 3
        } else {
            time
        }
    {
        if silent_is_no && result.bytes == 0 && start.elapsed() >= SILENT_AFTER {
            return Ok((result, split));
        }
        if sent == 0 || (sent == 1 && start.elapsed() >= time / 2) {
            // The leading newline ends whatever partial line the bridge holds.
            port.write_all(b"\n{\"cmd\":\"hello\"}\n")
                .and_then(|()| port.flush())
                .map_err(|e| io_error("writing to the port", e))?;
            sent += 1;
        }
        let _ = port.set_timeout(Duration::from_millis(50));
        match port.read(&mut buf) {
            Ok(n) if n > 0 => {
                result.bytes += n;
                split.push(&buf[..n]);
            }
            Ok(_) => {}
            Err(e) if quiet(&e) => {}
            Err(e) => return Err(io_error("reading from the port", e)),
        }
        while let Some(line) = split.next_line() {
            match serde_json::from_str::<Value>(&line) {
                Ok(v) if v.is_object() => match serde_json::from_value::<HostLine>(v.clone()) {
                    Ok(HostLine::Hello(h)) => {
                        result.hello = Some(h);
                        return Ok((result, split));
                    }
                    _ if v.get("type").and_then(Value::as_str) == Some("hello") => {
                        result.unread_hello = Some(v);
                        return Ok((result, split));
                    }
                    _ => result.json_lines += 1,
                },
                _ => {}
            }
        }
    }
    Ok((result, split))
}

/// The error an open gives for a device that is no terminal (`/dev/null`:
/// "Inappropriate ioctl for device", ENOTTY), whatever words the C library
/// has for it.
fn not_a_terminal(e: &serialport::Error) -> bool {
    #[cfg(unix)]
    {
        let enotty = std::io::Error::from_raw_os_error(libc::ENOTTY).to_string();
        e.to_string().contains(&enotty)
            || e.to_string().contains("Not a typewriter")
            || e.to_string().contains("Inappropriate ioctl")
    }
    #[cfg(not(unix))]
    {
        let _ = e;
        false
    }
}

/// `path` exists and is not a character device (Unix); never on other systems,
/// whose port names are not paths.
fn not_a_tty_device(path: &str) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        std::fs::metadata(path).is_ok_and(|m| !m.file_type().is_char_device())
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        false
    }
}

/// A read that timed out or was interrupted: nothing came, nothing is wrong.
fn quiet(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted
    )
}
