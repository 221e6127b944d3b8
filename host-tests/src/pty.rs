//! Pseudo-terminals (Linux and macOS, through `libc::openpty`): the simulated BMS and the
//! simulated bridge are exposed on one so that a client opens a real tty path
//! (`/dev/pts/N`) with real termios calls, exactly like a USB-UART adapter or the
//! ESP32's USB port.
//!
//! * The slave side is put in raw mode (no echo, no line editing, no CR/LF
//!   translation, 8-bit) before its path is published; a client (e.g. the
//!   `serialport` crate) sets its own settings on top when it opens the path.
//! * This side keeps its own descriptor of the slave open for as long as the
//!   [`Pty`] lives. Without it the master reads `EIO` whenever no client has the
//!   path open; with it the master survives a client closing and reopening the
//!   path, and the pty is never torn down between two clients.
//! * The master is non-blocking; [`Pty::read`] waits with `poll(2)` up to a
//!   timeout, [`Pty::write`] never blocks (bytes a full buffer cannot take are
//!   reported, not waited for: nobody may be reading).

use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// One pseudo-terminal pair.
#[derive(Debug)]
pub struct Pty {
    master: OwnedFd,
    slave: OwnedFd,
    path: PathBuf,
}

fn check(r: libc::c_int) -> io::Result<libc::c_int> {
    if r < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(r)
    }
}

impl Pty {
    /// Opens a new pair, slave in raw mode, master non-blocking.
    pub fn open() -> io::Result<Self> {
        let mut master: libc::c_int = -1;
        let mut slave: libc::c_int = -1;
        // SAFETY: openpty writes two descriptors into the out-pointers; the name,
        // termios and winsize arguments may be null.
        check(unsafe {
            libc::openpty(
                &mut master,
                &mut slave,
                std::ptr::null_mut(),
                // `*const` on Linux, `*mut` on macOS: null either way.
                std::ptr::null_mut(),
                std::ptr::null_mut(),
            )
        })?;
        // SAFETY: both descriptors were just opened and are owned by nobody else.
        let (master, slave) =
            unsafe { (OwnedFd::from_raw_fd(master), OwnedFd::from_raw_fd(slave)) };
        // SAFETY: a zeroed termios is a valid out-buffer for tcgetattr.
        let mut t: libc::termios = unsafe { std::mem::zeroed() };
        // SAFETY: valid descriptor and pointer.
        check(unsafe { libc::tcgetattr(slave.as_raw_fd(), &mut t) })?;
        // SAFETY: `t` was filled by tcgetattr.
        unsafe { libc::cfmakeraw(&mut t) };
        // SAFETY: as above; B115200 is a valid speed constant.
        unsafe {
            libc::cfsetispeed(&mut t, libc::B115200);
            libc::cfsetospeed(&mut t, libc::B115200);
        }
        // SAFETY: valid descriptor and a termios filled above.
        check(unsafe { libc::tcsetattr(slave.as_raw_fd(), libc::TCSANOW, &t) })?;
        // SAFETY: F_GETFL/F_SETFL on a valid descriptor.
        unsafe {
            let flags = check(libc::fcntl(master.as_raw_fd(), libc::F_GETFL))?;
            check(libc::fcntl(
                master.as_raw_fd(),
                libc::F_SETFL,
                flags | libc::O_NONBLOCK,
            ))?;
            // Not inherited by children (the tests spawn processes).
            check(libc::fcntl(
                master.as_raw_fd(),
                libc::F_SETFD,
                libc::FD_CLOEXEC,
            ))?;
            check(libc::fcntl(
                slave.as_raw_fd(),
                libc::F_SETFD,
                libc::FD_CLOEXEC,
            ))?;
        }
        let mut name = [0 as libc::c_char; 128];
        // SAFETY: the buffer is writable for its whole length.
        let r = unsafe { libc::ttyname_r(slave.as_raw_fd(), name.as_mut_ptr(), name.len()) };
        if r != 0 {
            return Err(io::Error::from_raw_os_error(r));
        }
        // SAFETY: ttyname_r succeeded, so the buffer holds a NUL-terminated string.
        let cstr = unsafe { std::ffi::CStr::from_ptr(name.as_ptr()) };
        let path = PathBuf::from(cstr.to_string_lossy().into_owned());
        Ok(Self {
            master,
            slave,
            path,
        })
    }

    /// The path a client opens (`/dev/pts/N`).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Waits up to `timeout` for bytes from the client; `Ok(0)` when none came.
    pub fn read(&self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        let mut pfd = libc::pollfd {
            fd: self.master.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = timeout.as_millis().min(i32::MAX as u128) as libc::c_int;
        // Round a sub-millisecond wait up, so a short deadline is not a busy loop.
        let ms = if ms == 0 && !timeout.is_zero() { 1 } else { ms };
        // SAFETY: one valid pollfd.
        let n = unsafe { libc::poll(&mut pfd, 1, ms) };
        if n < 0 {
            let e = io::Error::last_os_error();
            return if e.kind() == io::ErrorKind::Interrupted {
                Ok(0)
            } else {
                Err(e)
            };
        }
        if n == 0 {
            return Ok(0);
        }
        // SAFETY: the buffer is writable for its length.
        let r = unsafe { libc::read(self.master.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len()) };
        if r < 0 {
            let e = io::Error::last_os_error();
            return match e.kind() {
                io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted => Ok(0),
                _ => Err(e),
            };
        }
        Ok(r as usize)
    }

    /// Writes as much of `bytes` as the pty takes now; returns how many.
    pub fn write(&self, bytes: &[u8]) -> io::Result<usize> {
        let mut done = 0;
        while done < bytes.len() {
            let rest = bytes.get(done..).unwrap_or(&[]);
            // SAFETY: reading `rest.len()` bytes from a valid slice.
            let r =
                unsafe { libc::write(self.master.as_raw_fd(), rest.as_ptr().cast(), rest.len()) };
            if r < 0 {
                let e = io::Error::last_os_error();
                return match e.kind() {
                    io::ErrorKind::Interrupted => continue,
                    io::ErrorKind::WouldBlock => Ok(done),
                    _ => Err(e),
                };
            }
            done += r as usize;
        }
        Ok(done)
    }

    /// Bytes written by this side that no client has read yet (the slave's
    /// input queue). Large when nobody has the path open.
    pub fn unread(&self) -> usize {
        let mut n: libc::c_int = 0;
        // SAFETY: FIONREAD writes one int.
        let r = unsafe { libc::ioctl(self.slave.as_raw_fd(), libc::FIONREAD, &mut n) };
        if r < 0 {
            0
        } else {
            n.max(0) as usize
        }
    }

    /// Discards what no client has read (stale lines for a client to come).
    pub fn discard_unread(&self) {
        // SAFETY: tcflush on a valid descriptor.
        unsafe {
            libc::tcflush(self.slave.as_raw_fd(), libc::TCIFLUSH);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};

    #[test]
    fn bytes_cross_both_ways_raw_and_survive_a_reopen() {
        let pty = Pty::open().unwrap();
        assert!(pty.path().starts_with("/dev/pts"), "{:?}", pty.path());
        let mut buf = [0u8; 64];
        for round in 0..2u8 {
            let mut client = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .open(pty.path())
                .unwrap();
            // Raw: CR, LF, 0xAA and 0x03 (^C) pass untouched, nothing echoed.
            let sent = [0xAA, 0x03, b'\r', b'\n', 0xFF, round];
            client.write_all(&sent).unwrap();
            let mut got = Vec::new();
            while got.len() < sent.len() {
                let n = pty.read(&mut buf, Duration::from_secs(5)).unwrap();
                assert!(n > 0, "timed out");
                got.extend_from_slice(&buf[..n]);
            }
            assert_eq!(got, sent);
            assert_eq!(pty.write(&[b'\r', b'\n', 0xAA]).unwrap(), 3);
            let mut back = [0u8; 3];
            client.read_exact(&mut back).unwrap();
            assert_eq!(back, [b'\r', b'\n', 0xAA]);
            drop(client);
            // No client: the master does not fail.
            assert_eq!(pty.read(&mut buf, Duration::from_millis(10)).unwrap(), 0);
        }
        pty.write(b"stale").unwrap();
        // The line discipline takes written bytes in from a kernel worker: right
        // after the write FIONREAD may still say 0 (the test failed about one
        // run in two).
        let end = std::time::Instant::now() + Duration::from_secs(5);
        while pty.unread() < 5 && std::time::Instant::now() < end {
            std::thread::sleep(Duration::from_millis(1));
        }
        assert_eq!(pty.unread(), 5);
        pty.discard_unread();
        assert_eq!(pty.unread(), 0);
    }
}
