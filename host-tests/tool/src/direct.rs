//! Direct mode: a TinyBMS on a USB-UART adapter. The firmware's bridge and
//! host link run in a thread of the tool ([`tinybms_desk::Hosted`]) on the
//! serial port; the rest of the tool talks to them through channels with the
//! same JSON lines as to a real bridge.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::Config;
use tinybms_firmware::host_link::schema::HostLine;

use super::client::{Client, Received};
use super::transport::{Lines, Mode};
use super::{ToolError, ToolResult};
use tinybms_desk::capture::CaptureWriter;
use tinybms_desk::{ChannelSide, Hosted};

/// The in-process bridge thread.
struct Worker {
    stop: Arc<AtomicBool>,
    join: Option<JoinHandle<Result<(), String>>>,
    tx_bytes: Arc<AtomicU64>,
    rx_bytes: Arc<AtomicU64>,
}

/// Lines to and from the in-process bridge.
pub struct DirectLines {
    to_bridge: mpsc::Sender<Vec<u8>>,
    from_bridge: mpsc::Receiver<String>,
    worker: Arc<Mutex<Worker>>,
}

impl DirectLines {
    fn thread_error(&self) -> ToolError {
        let mut w = self.worker.lock().unwrap_or_else(|e| e.into_inner());
        let msg = match w.join.take().map(JoinHandle::join) {
            Some(Ok(Err(e))) => e,
            _ => "stopped".into(),
        };
        ToolError::failed(format!("the in-process bridge stopped: {msg}"))
    }
}

impl Lines for DirectLines {
    fn send_line(&mut self, line: &str) -> ToolResult<()> {
        let mut b = line.as_bytes().to_vec();
        b.push(b'\n');
        self.to_bridge.send(b).map_err(|_| self.thread_error())
    }

    fn recv_line(&mut self, timeout: Duration) -> ToolResult<Option<String>> {
        match self.from_bridge.recv_timeout(timeout) {
            Ok(l) => Ok(Some(l)),
            Err(mpsc::RecvTimeoutError::Timeout) => Ok(None),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(self.thread_error()),
        }
    }
}

impl Drop for DirectLines {
    fn drop(&mut self) {
        let mut w = self.worker.lock().unwrap_or_else(|e| e.into_inner());
        w.stop.store(true, Ordering::Relaxed);
        if let Some(j) = w.join.take() {
            let _ = j.join();
        }
    }
}

/// Starts the firmware's bridge and host link on `serial` (recording the raw
/// exchange to `capture` if given) and says hello through them.
pub fn start(
    serial: Box<dyn serialport::SerialPort>,
    port: String,
    capture: Option<CaptureWriter>,
) -> ToolResult<Client> {
    let (to_bridge, from_host) = mpsc::channel::<Vec<u8>>();
    let (to_host, from_bridge) = mpsc::channel::<String>();
    let stop = Arc::new(AtomicBool::new(false));
    let tx_bytes = Arc::new(AtomicU64::new(0));
    let rx_bytes = Arc::new(AtomicU64::new(0));
    let (s, t, r) = (stop.clone(), tx_bytes.clone(), rx_bytes.clone());
    let join = std::thread::Builder::new()
        .name("bridge".into())
        .spawn(move || -> Result<(), String> {
            // No bridge of its own to configure: the record is the defaults
            // with streaming off, chosen here (so the log says nothing of it).
            let record = Config {
                stream_period_ms: 0,
                ..Config::default()
            };
            let mut h = Hosted::direct(serial, Timing::default(), record, "host (tinybms direct)");
            if let Some(c) = capture {
                h.driver.record(c);
            }
            h.connected();
            let mut side = ChannelSide { from_host, to_host };
            let result = loop {
                if s.load(Ordering::Relaxed) {
                    break Ok(());
                }
                if let Err(e) = h.step(&mut side) {
                    break Err(e);
                }
                t.store(h.driver.tx_bytes, Ordering::Relaxed);
                r.store(h.driver.rx_bytes, Ordering::Relaxed);
            };
            let _ = h.driver.stop_recording();
            match result {
                Ok(()) => Ok(()),
                // The tool went away: not an error of the bridge.
                Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
                Err(e) => Err(format!("serial port: {e} (was the adapter unplugged?)")),
            }
        })
        .map_err(|e| ToolError::failed(format!("cannot start the bridge thread: {e}")))?;
    let worker = Arc::new(Mutex::new(Worker {
        stop,
        join: Some(join),
        tx_bytes,
        rx_bytes,
    }));
    let mut lines = DirectLines {
        to_bridge,
        from_bridge,
        worker: worker.clone(),
    };
    // The host link queued a hello when it was told of the connection; what
    // came before it is kept for the client, as it would have.
    let mut before = std::collections::VecDeque::new();
    let mut garbage = 0;
    let end = Instant::now() + Duration::from_secs(5);
    while Instant::now() < end {
        let Some(text) = lines.recv_line(Duration::from_millis(500))? else {
            continue;
        };
        match Received::parse(&text) {
            Some(Received {
                line: HostLine::Hello(hello),
                ..
            }) => {
                let mut c = Client::new(Box::new(lines), Mode::Direct, hello, port);
                c.pushed = before;
                c.garbage_lines = garbage;
                c.finish = Some(Box::new(move || stop_worker(&worker)));
                return Ok(c);
            }
            Some(r) => before.push_back(r),
            None => garbage += 1,
        }
    }
    Err(ToolError::failed(
        "the in-process bridge did not say hello (internal error)",
    ))
}

/// Stops the in-process bridge of direct mode (flushing a capture) and
/// returns the bytes it sent and received.
pub fn stop(client: &mut Client) -> ToolResult<(u64, u64)> {
    match client.finish.take() {
        Some(mut f) => f(),
        None => Ok((0, 0)),
    }
}

fn stop_worker(worker: &Mutex<Worker>) -> ToolResult<(u64, u64)> {
    let mut w = worker.lock().unwrap_or_else(|e| e.into_inner());
    w.stop.store(true, Ordering::Relaxed);
    if let Some(j) = w.join.take() {
        match j.join() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(ToolError::failed(e)),
            Err(_) => return Err(ToolError::failed("the in-process bridge panicked")),
        }
    }
    Ok((
        w.tx_bytes.load(Ordering::Relaxed),
        w.rx_bytes.load(Ordering::Relaxed),
    ))
}
