//! Bounded line assembly for the bytes a host sends: `\n`-terminated lines of
//! at most [`LINE_MAX`] bytes (a `\r` before the `\n` is dropped). A longer line
//! is reported once as [`Piece::TooLong`] and discarded up to and including the
//! next `\n`: no part of it is ever handed out as a line, and the line after it
//! is read normally (resync at the newline).
//!
//! A line that starts with `IMPROV` is an Improv Wi-Fi packet
//! ([`crate::improv::wire`]), which the installer in a browser sends on the
//! same port: binary, with its own length byte, so a `\n` inside it does not
//! end it. It comes out whole as [`Piece::Improv`] once its length and
//! checksum byte are in (the `\n` after it is then an empty line).
//!
//! Never panics, never allocates; the lines come out the same whatever the
//! chunking of the input (host-tests/tests/host_link.rs checks both by property).

/// Longest line from the host, bytes, without the `\r\n` (PROTOCOL.md, "Flow
/// control").
pub const LINE_MAX: usize = 256;

/// What one call to [`LineAssembler::push`] produced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Piece<'a> {
    /// A complete line, without its `\r\n` (may be empty).
    Line(&'a [u8]),
    /// A line grew past [`LINE_MAX`]: it is being discarded up to the next `\n`.
    TooLong,
    /// An Improv packet, whole (its checksum is not checked here).
    Improv(&'a [u8]),
}

/// Room for the longest line with its `\r`, or the longest Improv packet.
const BUF: usize = if LINE_MAX + 1 > IMPROV_MAX {
    LINE_MAX + 1
} else {
    IMPROV_MAX
};

/// The Improv header.
const IMPROV: &[u8; 6] = b"IMPROV";

/// Longest Improv packet: header, version, type, length, 255 bytes, checksum.
const IMPROV_MAX: usize = IMPROV.len() + 3 + 255 + 1;

/// Collects host bytes into lines. See the module documentation.
#[derive(Debug, Clone)]
pub struct LineAssembler {
    /// One more than [`LINE_MAX`] (room for the `\r` of a full-length line),
    /// or an Improv packet.
    buf: [u8; BUF],
    len: usize,
    /// Inside an over-long line: drop everything up to the next `\n`.
    discarding: bool,
}

impl Default for LineAssembler {
    fn default() -> Self {
        Self::new()
    }
}

impl LineAssembler {
    /// An empty assembler.
    pub const fn new() -> Self {
        Self {
            buf: [0; BUF],
            len: 0,
            discarding: false,
        }
    }

    /// True while an over-long line is being discarded.
    pub fn discarding(&self) -> bool {
        self.discarding
    }

    /// True while the bytes so far are the start of an Improv packet.
    pub fn is_improv(&self) -> bool {
        self.len >= IMPROV.len() && self.buf.get(..IMPROV.len()) == Some(&IMPROV[..])
    }

    /// Drops what was collected of the current line or packet (a packet that
    /// stopped half-way: the host gave up on it). Returns true when there was
    /// something.
    pub fn drop_partial(&mut self) -> bool {
        core::mem::take(&mut self.len) > 0
    }

    /// Takes bytes from the front of `input` until a line is complete or a line
    /// turns out too long. Returns how many bytes were used (call again with the
    /// rest) and what they completed, if anything. Uses at least one byte of a
    /// non-empty input.
    pub fn push(&mut self, input: &[u8]) -> (usize, Option<Piece<'_>>) {
        for (i, &b) in input.iter().enumerate() {
            let used = i + 1;
            if !self.discarding && self.is_improv() {
                // Inside an Improv packet every byte counts, `\n` too.
                if let Some(slot) = self.buf.get_mut(self.len) {
                    *slot = b;
                    self.len += 1;
                }
                let need = match self.buf.get(8) {
                    Some(&n) if self.len > 8 => IMPROV.len() + 3 + usize::from(n) + 1,
                    _ => usize::MAX,
                };
                if self.len >= need {
                    let len = core::mem::take(&mut self.len);
                    return (
                        used,
                        Some(Piece::Improv(self.buf.get(..len).unwrap_or(&[]))),
                    );
                }
                continue;
            }
            if b == b'\n' {
                if core::mem::take(&mut self.discarding) {
                    continue;
                }
                let mut len = core::mem::take(&mut self.len);
                if len > 0 && self.buf.get(len - 1) == Some(&b'\r') {
                    len -= 1;
                }
                if len > LINE_MAX {
                    // LINE_MAX + 1 bytes and no `\r` at the end: one too many.
                    return (used, Some(Piece::TooLong));
                }
                return (used, Some(Piece::Line(self.buf.get(..len).unwrap_or(&[]))));
            }
            if self.discarding {
                continue;
            }
            let room = self.len <= LINE_MAX;
            match self.buf.get_mut(self.len).filter(|_| room) {
                Some(slot) => {
                    *slot = b;
                    self.len += 1;
                }
                None => {
                    // Full (LINE_MAX + 1 bytes) and more than a `\n` follows.
                    self.len = 0;
                    self.discarding = true;
                    return (used, Some(Piece::TooLong));
                }
            }
        }
        (input.len(), None)
    }
}
