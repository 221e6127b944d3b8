//! Bounded line assembly for the bytes a host sends: `\n`-terminated lines of
//! at most [`LINE_MAX`] bytes (a `\r` before the `\n` is dropped). A longer line
//! is reported once as [`Piece::TooLong`] and discarded up to and including the
//! next `\n`: no part of it is ever handed out as a line, and the line after it
//! is read normally (resync at the newline).
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
}

/// Collects host bytes into lines. See the module documentation.
#[derive(Debug, Clone)]
pub struct LineAssembler {
    /// One more than [`LINE_MAX`]: room for the `\r` of a full-length line.
    buf: [u8; LINE_MAX + 1],
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
            buf: [0; LINE_MAX + 1],
            len: 0,
            discarding: false,
        }
    }

    /// True while an over-long line is being discarded.
    pub fn discarding(&self) -> bool {
        self.discarding
    }

    /// Takes bytes from the front of `input` until a line is complete or a line
    /// turns out too long. Returns how many bytes were used (call again with the
    /// rest) and what they completed, if anything. Uses at least one byte of a
    /// non-empty input.
    pub fn push(&mut self, input: &[u8]) -> (usize, Option<Piece<'_>>) {
        for (i, &b) in input.iter().enumerate() {
            let used = i + 1;
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
            match self.buf.get_mut(self.len) {
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
