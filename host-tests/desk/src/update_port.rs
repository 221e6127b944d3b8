//! The update port on the desktop: what the chip's `update_port_task` does
//! with its TCP socket, on a real TCP listener (`sim --bridge-pty
//! --update-port ADDR`): one connection at a time, its bytes into the
//! station's update-port link, the link's lines back.

use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};

use tinybms_firmware::station::Station;
use tinybms_firmware::Instant;

/// The listener and the connection it has.
pub struct UpdatePort {
    listener: TcpListener,
    conn: Option<TcpStream>,
    line: Vec<u8>,
}

impl UpdatePort {
    /// Listens on `addr` (non-blocking: [`UpdatePort::round`] never waits).
    pub fn bind(addr: SocketAddr) -> io::Result<Self> {
        let listener = TcpListener::bind(addr)?;
        listener.set_nonblocking(true)?;
        Ok(Self {
            listener,
            conn: None,
            line: vec![0; tinybms_firmware::host_link::OUT_LINE_MAX],
        })
    }

    /// The chip restarted: its connection is gone (the sender sees it
    /// closed).
    pub fn drop_connection(&mut self) {
        self.conn = None;
    }

    /// Where it listens.
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// One round at `now`: a new connection (it replaces one there was),
    /// bytes in, lines out, a closed connection said.
    pub fn round(&mut self, station: &mut Station, now: Instant) {
        if let Ok((s, _)) = self.listener.accept() {
            let _ = s.set_nonblocking(true);
            let _ = s.set_nodelay(true);
            self.conn = Some(s);
            station.update_port_connected(now);
        }
        let Some(conn) = self.conn.as_mut() else {
            return;
        };
        let mut closed = false;
        let mut buf = [0u8; 1024];
        loop {
            match conn.read(&mut buf) {
                Ok(0) => {
                    closed = true;
                    break;
                }
                Ok(n) => station.update_port_rx(now, &buf[..n]),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(_) => {
                    closed = true;
                    break;
                }
            }
        }
        while let Some(n) = station.next_update_port_line(now, &mut self.line) {
            if write_whole(conn, &self.line[..n]).is_err() {
                closed = true;
                break;
            }
        }
        if closed {
            self.conn = None;
            station.update_port_closed();
        }
    }
}

/// Writes every byte on a non-blocking stream (a line is short: the kernel's
/// buffer takes it, or the peer is gone).
fn write_whole(s: &mut TcpStream, mut bytes: &[u8]) -> io::Result<()> {
    let mut tries = 0;
    while !bytes.is_empty() {
        match s.write(bytes) {
            Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
            Ok(n) => bytes = &bytes[n..],
            Err(e) if e.kind() == io::ErrorKind::WouldBlock && tries < 1000 => {
                tries += 1;
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
            Err(e) => return Err(e),
        }
    }
    Ok(())
}
