//! The CAN capture: the last frames both ways on the inverter's bus — what
//! this bridge sent (acknowledged or not), what it heard, and the bus's
//! errors — in a bounded ring of [`CAPTURE_FRAMES`] entries (about a minute
//! on a bus with one pack: 6-8 frames a second), 14 bytes each.
//!
//! It leaves the bridge as a candump log (`candump -l`'s format with its
//! direction flag, `T` for what this bridge sent and `R` for what it heard,
//! which can-utils, python-can and cantools read), on channel `can0`; a
//! frame nobody acknowledged and a bus-off are error frames as SocketCAN
//! writes them (`CAN_ERR_FLAG | CAN_ERR_BUSERROR` with `CAN_ERR_ACK` or
//! `CAN_ERR_BUSOFF`, 8 data bytes). The time is the bridge's since its
//! start, in seconds. [`parse_line`] reads
//! such a line back: the doctor ([`super::doctor`]) runs on a capture file
//! exactly as on the bridge.

use super::dialect::CanFrame;
use crate::log_line::Line;
use crate::Instant;

/// Entries kept.
pub const CAPTURE_FRAMES: usize = 512;

/// SocketCAN's error-frame flag in a candump identifier.
pub const CAN_ERR_FLAG: u32 = 0x2000_0000;
/// SocketCAN's error class: no acknowledgement on transmission.
pub const CAN_ERR_ACK: u32 = 0x20;
/// SocketCAN's error class: bus off.
pub const CAN_ERR_BUSOFF: u32 = 0x40;
/// SocketCAN's error class: bus error (set with both above).
pub const CAN_ERR_BUSERROR: u32 = 0x80;

/// What an entry is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Seen {
    /// A frame this bridge sent, acknowledged.
    Sent(CanFrame),
    /// A frame heard on the bus.
    Heard(CanFrame),
    /// A frame this bridge sent that nobody acknowledged.
    NoAck,
    /// The controller left the bus.
    BusOff,
}

/// One entry: when (ms since the start) and what.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Entry {
    at_ms: [u16; 2],
    /// Identifier (11 bits), length (bits 11-14; 15 = an error), sent (bit 15).
    word: u16,
    data: [u8; 8],
}

const LEN_SHIFT: u16 = 11;
const LEN_ERROR: u16 = 15;
const SENT_BIT: u16 = 1 << 15;
const ID_MASK: u16 = 0x7FF;

impl Entry {
    /// `seen` at `at_us` (kept in ms: wraps after 49 days).
    pub fn new(at_us: Instant, seen: Seen) -> Self {
        let ms = (at_us / crate::MS) as u32;
        let at_ms = [ms as u16, (ms >> 16) as u16];
        let (word, data) = match seen {
            Seen::Sent(f) | Seen::Heard(f) => {
                let len = u16::from(f.len.min(8));
                let sent = if matches!(seen, Seen::Sent(_)) {
                    SENT_BIT
                } else {
                    0
                };
                ((f.id & ID_MASK) | len << LEN_SHIFT | sent, f.data)
            }
            Seen::NoAck => (LEN_ERROR << LEN_SHIFT | SENT_BIT, [0; 8]),
            Seen::BusOff => (1 | LEN_ERROR << LEN_SHIFT | SENT_BIT, [0; 8]),
        };
        Self { at_ms, word, data }
    }

    /// When, µs since the start (ms resolution).
    pub fn at_us(&self) -> Instant {
        let ms = u32::from(self.at_ms[0]) | u32::from(self.at_ms[1]) << 16;
        Instant::from(ms) * crate::MS
    }

    /// What.
    pub fn seen(&self) -> Seen {
        let len = (self.word >> LEN_SHIFT) & 0xF;
        if len == LEN_ERROR {
            return if self.word & ID_MASK == 0 {
                Seen::NoAck
            } else {
                Seen::BusOff
            };
        }
        let f = CanFrame::new(self.word & ID_MASK, len.min(8) as u8, self.data);
        if self.word & SENT_BIT != 0 {
            Seen::Sent(f)
        } else {
            Seen::Heard(f)
        }
    }

    /// As a candump log line (no newline).
    pub fn write_candump(&self, out: &mut Line) {
        let ms = self.at_us() / crate::MS;
        let frac = ms % 1000;
        out.push("(")
            .uint(ms / 1000)
            .push(".")
            .uint(frac / 100)
            .uint(frac / 10 % 10)
            .uint(frac % 10)
            .push("000) ");
        out.push("can0 ");
        match self.seen() {
            Seen::Sent(f) | Seen::Heard(f) => {
                hex_id(out, u32::from(f.id), 3);
                out.push("#").hex_bytes(f.bytes());
                out.push(if matches!(self.seen(), Seen::Sent(_)) {
                    " T"
                } else {
                    " R"
                });
            }
            Seen::NoAck | Seen::BusOff => {
                let class = if self.seen() == Seen::NoAck {
                    CAN_ERR_ACK
                } else {
                    CAN_ERR_BUSOFF
                };
                hex_id(out, CAN_ERR_FLAG | CAN_ERR_BUSERROR | class, 8);
                out.push("#0000000000000000 T");
            }
        }
    }
}

/// An identifier in upper-case hex, at least `digits` wide.
fn hex_id(out: &mut Line, id: u32, digits: u32) {
    let mut d = digits;
    while d < 8 && id >> (4 * d) != 0 {
        d += 1;
    }
    for k in (0..d).rev() {
        let nibble = ((id >> (4 * k)) & 0xF) as usize;
        out.push(&"0123456789ABCDEF"[nibble..nibble + 1]);
    }
}

/// The ring.
#[derive(Debug, Clone)]
pub struct Capture {
    ring: heapless::Deque<Entry, CAPTURE_FRAMES>,
    /// Entries ever recorded (the sequence number of the next one).
    recorded: u32,
}

impl Default for Capture {
    fn default() -> Self {
        Self::new()
    }
}

impl Capture {
    /// Empty.
    pub const fn new() -> Self {
        Self {
            ring: heapless::Deque::new(),
            recorded: 0,
        }
    }

    /// Records `seen` at `at_us`, dropping the oldest when full.
    pub fn record(&mut self, at_us: Instant, seen: Seen) {
        let e = Entry::new(at_us, seen);
        if self.ring.is_full() {
            self.ring.pop_front();
        }
        let _fits = self.ring.push_back(e); // room made above
        self.recorded = self.recorded.wrapping_add(1);
    }

    /// Sequence numbers held: `first..end` (entry `k` is `get(k)`).
    pub fn span(&self) -> (u32, u32) {
        (
            self.recorded.wrapping_sub(self.ring.len() as u32),
            self.recorded,
        )
    }

    /// The entry of sequence number `seq`, if still held.
    pub fn get(&self, seq: u32) -> Option<Entry> {
        let (first, _) = self.span();
        let i = seq.wrapping_sub(first) as usize;
        self.ring.iter().nth(i).copied()
    }

    /// Entries held, oldest first.
    pub fn iter(&self) -> impl Iterator<Item = &Entry> {
        self.ring.iter()
    }
}

/// Why a capture line was not read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParseError {
    /// Not `(SECONDS) CHANNEL ID#DATA T|R`.
    Shape,
    /// No direction flag (`T` sent, `R` heard) at the end.
    Direction,
    /// The identifier is not hex, or neither 11-bit nor an error frame.
    Id,
    /// The data is not whole hex bytes, or more than 8 of them.
    Data,
    /// The time is not seconds with a fraction.
    Time,
}

impl ParseError {
    /// In words.
    pub const fn text(self) -> &'static str {
        match self {
            Self::Shape => "not a candump line: (SECONDS) CHANNEL ID#DATA T|R",
            Self::Direction => "no direction flag (T sent, R heard) at the end",
            Self::Id => "the identifier is not an 11-bit or error frame in hex",
            Self::Data => "the data is not 0-8 bytes in hex",
            Self::Time => "the time is not seconds.fraction",
        }
    }
}

/// Reads one candump line of a capture: when (µs) and what.
pub fn parse_line(line: &str) -> Result<(Instant, Seen), ParseError> {
    let line = line.trim();
    let rest = line.strip_prefix('(').ok_or(ParseError::Shape)?;
    let (time, rest) = rest.split_once(')').ok_or(ParseError::Shape)?;
    let at_us = parse_time(time)?;
    let mut parts = rest.split_whitespace();
    let _channel = parts.next().ok_or(ParseError::Shape)?;
    let frame = parts.next().ok_or(ParseError::Shape)?;
    let sent = match parts.next() {
        Some("T") => true,
        Some("R") => false,
        _ => return Err(ParseError::Direction),
    };
    if parts.next().is_some() {
        return Err(ParseError::Shape);
    }
    let (id, data) = frame.split_once('#').ok_or(ParseError::Shape)?;
    if id.is_empty() || id.len() > 8 {
        return Err(ParseError::Id);
    }
    let id = u32::from_str_radix(id, 16).map_err(|_| ParseError::Id)?;
    if data.len() % 2 != 0 || data.len() > 16 {
        return Err(ParseError::Data);
    }
    let mut bytes = [0u8; 8];
    for (k, b) in bytes.iter_mut().enumerate().take(data.len() / 2) {
        let h = data.get(2 * k..2 * k + 2).ok_or(ParseError::Data)?;
        *b = u8::from_str_radix(h, 16).map_err(|_| ParseError::Data)?;
    }
    if id & CAN_ERR_FLAG != 0 {
        let class = id & !(CAN_ERR_FLAG | CAN_ERR_BUSERROR);
        return match class {
            CAN_ERR_ACK => Ok((at_us, Seen::NoAck)),
            CAN_ERR_BUSOFF => Ok((at_us, Seen::BusOff)),
            _ => Err(ParseError::Id),
        };
    }
    if id > u32::from(ID_MASK) {
        return Err(ParseError::Id);
    }
    let f = CanFrame::new(id as u16, (data.len() / 2) as u8, bytes);
    Ok((at_us, if sent { Seen::Sent(f) } else { Seen::Heard(f) }))
}

fn parse_time(t: &str) -> Result<Instant, ParseError> {
    let (s, frac) = t.split_once('.').ok_or(ParseError::Time)?;
    if s.is_empty() || frac.is_empty() || frac.len() > 9 {
        return Err(ParseError::Time);
    }
    let s: u64 = s.parse().map_err(|_| ParseError::Time)?;
    if !frac.bytes().all(|b| b.is_ascii_digit()) {
        return Err(ParseError::Time);
    }
    let mut us: u64 = 0;
    for b in frac.bytes().chain(core::iter::repeat(b'0')).take(6) {
        us = us * 10 + u64::from(b - b'0');
    }
    s.checked_mul(1_000_000)
        .and_then(|x| x.checked_add(us))
        .ok_or(ParseError::Time)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        let mut d = [0u8; 8];
        d[..data.len()].copy_from_slice(data);
        CanFrame::new(id, data.len() as u8, d)
    }

    #[test]
    fn an_entry_round_trips_through_its_candump_line() {
        let cases = [
            (
                1_234_567_000,
                Seen::Sent(frame(0x351, &[0x28, 0x02, 0x64, 0, 0x64, 0, 0xE0, 0x01])),
            ),
            (5_000, Seen::Heard(frame(0x305, &[0; 8]))),
            (61_000_000, Seen::Heard(frame(0x7FF, &[]))),
            (99_999_000, Seen::NoAck),
            (100_001_000, Seen::BusOff),
        ];
        for (at, seen) in cases {
            let e = Entry::new(at, seen);
            assert_eq!(e.seen(), seen);
            assert_eq!(e.at_us(), at);
            let mut l = Line::new();
            e.write_candump(&mut l);
            assert_eq!(parse_line(l.as_str()), Ok((at, seen)), "{}", l.as_str());
        }
        let mut l = Line::new();
        Entry::new(5_000, Seen::Heard(frame(0x305, &[0; 8]))).write_candump(&mut l);
        assert_eq!(l.as_str(), "(0.005000) can0 305#0000000000000000 R");
        let mut l = Line::new();
        Entry::new(2_000_000, Seen::BusOff).write_candump(&mut l);
        assert_eq!(l.as_str(), "(2.000000) can0 200000C0#0000000000000000 T");
    }

    #[test]
    fn the_ring_keeps_the_newest_and_numbers_them() {
        let mut c = Capture::new();
        for k in 0..(CAPTURE_FRAMES as u64 + 10) {
            c.record(k * 1000, Seen::Heard(frame(0x305, &[])));
        }
        let (first, end) = c.span();
        assert_eq!(end - first, CAPTURE_FRAMES as u32);
        assert_eq!(first, 10);
        assert_eq!(c.get(first).map(|e| e.at_us()), Some(10_000));
        assert_eq!(c.get(first - 1), None);
        assert_eq!(c.get(end), None);
        assert_eq!(core::mem::size_of::<Entry>(), 14);
    }

    #[test]
    fn a_malformed_line_is_refused_with_its_reason() {
        for (line, e) in [
            ("", ParseError::Shape),
            ("(1.0) can0 351#00", ParseError::Direction),
            ("(1.0) can0 351#00 X", ParseError::Direction),
            ("(1.0) can0 351#0 T", ParseError::Data),
            ("(1.0) can0 351#001122334455667788 T", ParseError::Data),
            ("(1.0) can0 351#zz T", ParseError::Data),
            ("(1.0) can0 800#00 T", ParseError::Id),
            ("(1.0) can0 #00 T", ParseError::Id),
            ("(1.0) can0 20000084#0000000000000000 T", ParseError::Id),
            ("(x.0) can0 351#00 T", ParseError::Time),
            ("(1) can0 351#00 T", ParseError::Time),
            ("(1.0) can0 351#00 T extra", ParseError::Shape),
            ("(99999999999999999999.0) can0 351#00 T", ParseError::Time),
        ] {
            assert_eq!(parse_line(line).map(|_| ()), Err(e), "{line}");
        }
    }
}
