//! The `.tbms` capture format: a plain-text record of one UART conversation with a
//! TinyBMS.
//!
//! ```text
//! # a comment; blank lines are ignored
//! > AA 1B 3F 1B                  # bytes sent to the BMS, one request per line
//! < AA 1B 06 16 01 14            # bytes received from the BMS ...
//! < 01 16 01 0E 4E               # ... consecutive `<` lines are one stream
//! ```
//!
//! * `#` starts a comment, at the start of a line or after the bytes.
//! * `>` lines hold exactly one request each.
//! * `<` lines are chunks of one continuous received stream: chunk boundaries are
//!   arbitrary, a frame may span lines, noise may sit between frames.
//! * Bytes are two hex digits (either case) separated by spaces or tabs. A space
//!   after the `>`/`<` marker is optional.
//!
//! Anything else is a [`CaptureError`] naming the line; the parser never panics.

use std::fmt;

/// What one line of a capture holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Entry {
    /// `>`: one request sent to the BMS.
    Tx(Vec<u8>),
    /// `<`: a chunk of the received stream.
    Rx(Vec<u8>),
}

/// A non-blank, non-comment line of a capture.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Line {
    /// 1-based line number in the capture text.
    pub number: usize,
    /// Its bytes.
    pub entry: Entry,
}

/// A parsed capture: its byte lines in order.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Capture {
    /// The `>` and `<` lines, in file order.
    pub lines: Vec<Line>,
}

/// A malformed capture line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CaptureError {
    /// 1-based line number.
    pub line: usize,
    /// What is wrong with it.
    pub message: String,
}

impl fmt::Display for CaptureError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "line {}: {}", self.line, self.message)
    }
}

impl std::error::Error for CaptureError {}

/// Longest token quoted back in an error message.
const QUOTE_MAX: usize = 24;

fn quote(token: &str) -> String {
    let mut q: String = token.chars().take(QUOTE_MAX).collect();
    if token.chars().count() > QUOTE_MAX {
        q.push('…');
    }
    format!("`{}`", q.escape_debug())
}

fn hex_digit(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'a'..=b'f' => Some(c - b'a' + 10),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    }
}

/// Parses the bytes of one `>` / `<` line (the text after the marker).
fn parse_bytes(text: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    for token in text.split_ascii_whitespace() {
        let b = token.as_bytes();
        let bad_digit = b.iter().find(|&&c| hex_digit(c).is_none());
        if let Some(&c) = bad_digit {
            return Err(if c.is_ascii() {
                format!(
                    "{} is not hex: bytes are two hex digits separated by spaces",
                    quote(token)
                )
            } else {
                format!("{} contains a non-ASCII character", quote(token))
            });
        }
        match *b {
            [hi, lo] => out.push(hex_digit(hi).unwrap_or(0) << 4 | hex_digit(lo).unwrap_or(0)),
            _ => {
                return Err(format!(
                    "{} has {} hex digit{}: each byte is exactly two digits, separated by spaces",
                    quote(token),
                    b.len(),
                    if b.len() == 1 { "" } else { "s" }
                ))
            }
        }
    }
    Ok(out)
}

/// Parses bytes written as in a capture line (`AA 03 00`), as the bridge's
/// `raw` lines carry them.
pub fn parse_hex(text: &str) -> Result<Vec<u8>, String> {
    parse_bytes(text)
}

/// Parses a whole capture. The first malformed line is reported with its number.
pub fn parse_capture(text: &str) -> Result<Capture, CaptureError> {
    let mut lines = Vec::new();
    // `lines()` splits on `\n` and strips a trailing `\r`.
    for (i, raw) in text.lines().enumerate() {
        let number = i + 1;
        let err = |message: String| CaptureError {
            line: number,
            message,
        };
        let content = raw.split_once('#').map_or(raw, |(before, _)| before).trim();
        if content.is_empty() {
            continue;
        }
        let (marker, rest) = content.split_at(content.chars().next().map_or(0, char::len_utf8));
        let entry = match marker {
            ">" | "<" => {
                let bytes = parse_bytes(rest).map_err(&err)?;
                if bytes.is_empty() {
                    return Err(err(format!("`{marker}` line without any byte")));
                }
                if marker == ">" {
                    Entry::Tx(bytes)
                } else {
                    Entry::Rx(bytes)
                }
            }
            _ => {
                return Err(err(format!(
                    "unknown line start {}: expected `>` (sent), `<` (received), `#` (comment) or a blank line",
                    quote(marker)
                )))
            }
        };
        lines.push(Line { number, entry });
    }
    Ok(Capture { lines })
}

/// Parses capture bytes that may not be UTF-8: invalid UTF-8 is reported on the
/// line where it occurs.
pub fn parse_capture_bytes(bytes: &[u8]) -> Result<Capture, CaptureError> {
    match std::str::from_utf8(bytes) {
        Ok(text) => parse_capture(text),
        Err(e) => {
            let valid = bytes.get(..e.valid_up_to()).unwrap_or(&[]);
            let line = 1 + valid.iter().filter(|&&b| b == b'\n').count();
            // Still report an earlier malformed line first, if any.
            let before = valid
                .iter()
                .rposition(|&b| b == b'\n')
                .map_or(&[][..], |p| valid.get(..p).unwrap_or(&[]));
            if let Ok(text) = std::str::from_utf8(before) {
                parse_capture(text)?;
            }
            Err(CaptureError {
                line,
                message: "not valid UTF-8 text".into(),
            })
        }
    }
}

/// Formats bytes the way captures write them: `AA 14 7F 1F`.
pub fn hex(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len() * 3);
    for (i, b) in bytes.iter().enumerate() {
        if i > 0 {
            s.push(' ');
        }
        s.push_str(&format!("{b:02X}"));
    }
    s
}

/// Writes a capture as it happens: each transmission is one `>` line, each
/// received chunk one `<` line (consecutive chunks are one stream, as the
/// format says), so `replay` reads the file back.
pub struct CaptureWriter {
    out: Box<dyn std::io::Write + Send>,
}

impl CaptureWriter {
    /// A writer on `out`, starting with `header` as `#` comment lines.
    pub fn new(mut out: Box<dyn std::io::Write + Send>, header: &str) -> std::io::Result<Self> {
        for line in header.lines() {
            writeln!(out, "# {line}")?;
        }
        Ok(Self { out })
    }

    /// One request sent to the BMS.
    pub fn tx(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        if bytes.is_empty() {
            return Ok(());
        }
        writeln!(self.out, "> {}", hex(bytes))
    }

    /// A chunk received from the BMS.
    pub fn rx(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        if bytes.is_empty() {
            return Ok(());
        }
        writeln!(self.out, "< {}", hex(bytes))
    }

    /// A `#` comment line.
    pub fn comment(&mut self, text: &str) -> std::io::Result<()> {
        writeln!(self.out, "# {text}")
    }

    /// Flushes the underlying writer.
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(text: &str) -> CaptureError {
        parse_capture(text).expect_err("should fail")
    }

    #[test]
    fn parses_directions_comments_and_case() {
        let c = parse_capture(
            "# header\n\n> AA 14 7F 1F\n<aa 14 b8 1e   # comment\r\n\t< 5F 42 00 00\n",
        )
        .unwrap();
        assert_eq!(
            c.lines,
            vec![
                Line {
                    number: 3,
                    entry: Entry::Tx(vec![0xAA, 0x14, 0x7F, 0x1F])
                },
                Line {
                    number: 4,
                    entry: Entry::Rx(vec![0xAA, 0x14, 0xB8, 0x1E])
                },
                Line {
                    number: 5,
                    entry: Entry::Rx(vec![0x5F, 0x42, 0, 0])
                },
            ]
        );
        assert_eq!(parse_capture("").unwrap(), Capture::default());
    }

    #[test]
    fn bad_hex_names_the_line() {
        let e = err("# ok\n> AA 14\n< AA 1G\n");
        assert_eq!(e.line, 3);
        assert!(e.message.contains("`1G` is not hex"), "{e}");
        assert!(e.to_string().starts_with("line 3: "), "{e}");
    }

    #[test]
    fn odd_digit_counts_are_refused() {
        let e = err("> AA 1\n");
        assert_eq!(e.line, 1);
        assert!(e.message.contains("1 hex digit:"), "{e}");
        let e = err("\n\n< AA14 7F\n");
        assert_eq!(e.line, 3);
        assert!(e.message.contains("`AA14` has 4 hex digits"), "{e}");
        let e = err("< AAB\n");
        assert!(e.message.contains("3 hex digits"), "{e}");
    }

    #[test]
    fn unknown_prefix_and_empty_lines() {
        let e = err("> AA 14 7F 1F\nAA 14\n");
        assert_eq!(e.line, 2);
        assert!(e.message.contains("unknown line start `A`"), "{e}");
        let e = err("= AA\n");
        assert!(e.message.contains("`=`"), "{e}");
        let e = err("\n>   # nothing\n");
        assert_eq!(e.line, 2);
        assert!(e.message.contains("without any byte"), "{e}");
        let e = err("é AA\n");
        assert!(e.message.contains("unknown line start `é`"), "{e}");
        let e = err("< AA ü1\n");
        assert!(e.message.contains("non-ASCII"), "{e}");
        let e = err("< 0x AA\n");
        assert!(e.message.contains("`0x` is not hex"), "{e}");
    }

    #[test]
    fn invalid_utf8_names_the_line() {
        let e = parse_capture_bytes(b"> AA 14 7F 1F\n< AA\xFF\n").unwrap_err();
        assert_eq!(e.line, 2);
        assert!(e.message.contains("UTF-8"));
        // An earlier syntax error wins.
        let e = parse_capture_bytes(b"? x\n< AA\n< \xFF\n").unwrap_err();
        assert_eq!(e.line, 1);
    }

    #[test]
    fn the_writer_writes_what_the_parser_reads() {
        #[derive(Clone, Default)]
        struct Shared(std::sync::Arc<std::sync::Mutex<Vec<u8>>>);
        impl std::io::Write for Shared {
            fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
                self.0.lock().unwrap().extend_from_slice(b);
                Ok(b.len())
            }
            fn flush(&mut self) -> std::io::Result<()> {
                Ok(())
            }
        }
        let buf = Shared::default();
        let mut w = CaptureWriter::new(Box::new(buf.clone()), "two\nlines").unwrap();
        w.tx(&[0xAA, 0x14, 0x7F, 0x1F]).unwrap();
        w.rx(&[0xAA, 0x14]).unwrap();
        w.rx(&[]).unwrap();
        w.comment("gap").unwrap();
        w.rx(&[0xB8]).unwrap();
        let text = String::from_utf8(buf.0.lock().unwrap().clone()).unwrap();
        assert!(
            text.starts_with("# two\n# lines\n> AA 14 7F 1F\n"),
            "{text}"
        );
        let c = parse_capture(&text).unwrap();
        let entries: Vec<Entry> = c.lines.into_iter().map(|l| l.entry).collect();
        assert_eq!(
            entries,
            vec![
                Entry::Tx(vec![0xAA, 0x14, 0x7F, 0x1F]),
                Entry::Rx(vec![0xAA, 0x14]),
                Entry::Rx(vec![0xB8])
            ]
        );
    }

    #[test]
    fn hex_formats_back() {
        assert_eq!(hex(&[0xAA, 0x14, 0x7F, 0x1F]), "AA 14 7F 1F");
        assert_eq!(hex(&[]), "");
    }
}
