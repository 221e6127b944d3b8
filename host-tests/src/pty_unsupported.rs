//! Pseudo-terminals where there are none (Windows): [`Pty::open`] says so, and
//! `sim --pty` / `sim --bridge-pty` report it. Everything else of the desktop
//! side (the `tinybms` tool on a real serial port included) works without them.
//! The Unix implementation is `pty.rs`.

use std::convert::Infallible;
use std::io;
use std::path::Path;
use std::time::Duration;

/// A pseudo-terminal pair: never exists on this system.
#[derive(Debug)]
pub struct Pty {
    never: Infallible,
}

impl Pty {
    /// Always an [`io::ErrorKind::Unsupported`] error here.
    pub fn open() -> io::Result<Self> {
        Err(io::Error::new(
            io::ErrorKind::Unsupported,
            "pseudo-terminals need Linux or macOS (sim --pty / --bridge-pty)",
        ))
    }
    /// See the Unix implementation.
    pub fn path(&self) -> &Path {
        match self.never {}
    }
    /// See the Unix implementation.
    pub fn read(&self, _buf: &mut [u8], _timeout: Duration) -> io::Result<usize> {
        match self.never {}
    }
    /// See the Unix implementation.
    pub fn write(&self, _bytes: &[u8]) -> io::Result<usize> {
        match self.never {}
    }
    /// See the Unix implementation.
    pub fn unread(&self) -> usize {
        match self.never {}
    }
    /// See the Unix implementation.
    pub fn discard_unread(&self) {
        match self.never {}
    }
}
