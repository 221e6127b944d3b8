//! `serial-ws`: serial ports as WebSockets on loopback, for the browser
//! tests of the console and the installer (host-tests/web/tests): the test
//! injects a `navigator.serial` whose port is one of these sockets, so the
//! page's own code runs unchanged against a real serial port — the
//! pseudo-terminal of `sim --bridge-pty`, opened with `serialport` as the
//! desktop tool opens it.
//!
//! ```text
//! serial-ws --allow PATH [--allow PATH…] [--listen 127.0.0.1:0] [--max-time 10m]
//! ```
//!
//! Prints `ws://127.0.0.1:PORT` as its first line. Per connection: the first
//! message is text, `{"open": PATH, "baudRate": N}` (PATH one of the
//! allowed ones); then binary messages are bytes both ways, a text message
//! `{"signals": {"dataTerminalReady": b, "requestToSend": b}}` sets the
//! lines, and closing the socket closes the port (as closing the page's
//! port does). The process ends by itself after `--max-time`.

use std::io::Write;
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use tungstenite::{Message, WebSocket};

fn usage() -> ! {
    eprintln!(
        "usage: serial-ws --allow PATH [--allow PATH…] [--listen 127.0.0.1:0] [--max-time 10m]"
    );
    std::process::exit(2)
}

fn main() {
    let mut allow: Vec<String> = Vec::new();
    let mut listen = "127.0.0.1:0".to_string();
    let mut max = Duration::from_secs(600);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--allow" => allow.push(args.next().unwrap_or_else(|| usage())),
            "--listen" => listen = args.next().unwrap_or_else(|| usage()),
            "--max-time" => {
                let v = args.next().unwrap_or_else(|| usage());
                max = tinybms_desk::parse_duration(&v).unwrap_or_else(|e| {
                    eprintln!("serial-ws: --max-time {v}: {e}");
                    std::process::exit(2)
                });
            }
            _ => usage(),
        }
    }
    if allow.is_empty() {
        usage();
    }
    let listener = TcpListener::bind(&listen).unwrap_or_else(|e| {
        eprintln!("serial-ws: {listen}: {e}");
        std::process::exit(1)
    });
    let addr = listener
        .local_addr()
        .expect("a bound socket has an address");
    if !addr.ip().is_loopback() {
        eprintln!("serial-ws: listens on loopback only");
        std::process::exit(2);
    }
    println!("ws://{addr}");
    let _ = std::io::stdout().flush();
    let end = Instant::now() + max;
    listener
        .set_nonblocking(true)
        .expect("a listener can be non-blocking");
    while Instant::now() < end {
        match listener.accept() {
            Ok((stream, _)) => {
                let allow = allow.clone();
                std::thread::spawn(move || {
                    if let Err(e) = serve(stream, &allow, end) {
                        eprintln!("serial-ws: {e}");
                    }
                });
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(20));
            }
            Err(e) => {
                eprintln!("serial-ws: accept: {e}");
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    }
}

fn timed_out(e: &tungstenite::Error) -> bool {
    matches!(e, tungstenite::Error::Io(io)
        if matches!(io.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut))
}

fn serve(stream: TcpStream, allow: &[String], end: Instant) -> Result<(), String> {
    stream.set_nonblocking(false).map_err(|e| e.to_string())?;
    let mut ws = tungstenite::accept(stream).map_err(|e| format!("handshake: {e}"))?;
    // The open request.
    let open: Value = match ws.read().map_err(|e| e.to_string())? {
        Message::Text(t) => serde_json::from_str(t.as_str()).map_err(|e| e.to_string())?,
        other => return Err(format!("want the open request first, got {other:?}")),
    };
    let path = open["open"].as_str().unwrap_or("").to_string();
    let baud = open["baudRate"].as_u64().unwrap_or(115_200) as u32;
    if !allow.contains(&path) {
        let _ = ws.send(Message::text(
            json!({"error": format!("{path}: not allowed")}).to_string(),
        ));
        return Err(format!("{path}: not allowed"));
    }
    let mut port = match serialport::new(&path, baud)
        .timeout(Duration::from_millis(5))
        .open()
    {
        Ok(p) => p,
        Err(e) => {
            let _ = ws.send(Message::text(json!({"error": e.to_string()}).to_string()));
            return Err(format!("{path}: {e}"));
        }
    };
    ws.send(Message::text(json!({"opened": path}).to_string()))
        .map_err(|e| e.to_string())?;
    ws.get_mut()
        .set_read_timeout(Some(Duration::from_millis(5)))
        .map_err(|e| e.to_string())?;
    pump(&mut ws, port.as_mut(), end)
}

fn pump(
    ws: &mut WebSocket<TcpStream>,
    port: &mut dyn serialport::SerialPort,
    end: Instant,
) -> Result<(), String> {
    let mut buf = vec![0u8; 4096];
    while Instant::now() < end {
        match ws.read() {
            Ok(Message::Binary(b)) => port.write_all(&b).map_err(|e| e.to_string())?,
            Ok(Message::Text(t)) => {
                let v: Value = serde_json::from_str(t.as_str()).unwrap_or(Value::Null);
                let s = &v["signals"];
                if let Some(dtr) = s["dataTerminalReady"].as_bool() {
                    let _ = port.write_data_terminal_ready(dtr);
                }
                if let Some(rts) = s["requestToSend"].as_bool() {
                    let _ = port.write_request_to_send(rts);
                }
            }
            Ok(Message::Close(_)) => return Ok(()),
            Ok(_) => {}
            Err(e) if timed_out(&e) => {}
            Err(tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed) => {
                return Ok(())
            }
            Err(e) => return Err(e.to_string()),
        }
        match port.read(&mut buf) {
            Ok(0) => {}
            Ok(n) => ws
                .send(Message::binary(buf[..n].to_vec()))
                .map_err(|e| e.to_string())?,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => {
                let _ = ws.close(None);
                return Err(format!("the port: {e}"));
            }
        }
    }
    let _ = ws.close(None);
    Ok(())
}
