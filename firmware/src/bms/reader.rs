//! Block reads that survive a bad line: a register range read in one request on a
//! clean line, in smaller pieces when replies keep failing, and (for blocks that
//! do not change by themselves) confirmed by a second complete read.
//!
//! Why pieces: with a per-byte error rate `p`, a reply of `n` bytes survives with
//! probability `(1 - p)^n`. At 5 % a 117-byte live reply gets through 0.25 % of
//! the time (one snapshot every ~30 s); a 9-byte reply of 2 registers 63 %. The
//! piece size follows the line: [`LineQuality`] moves one level smaller after a
//! failed or repeated attempt and one level larger after a run of clean ones.
//!
//! A piece never splits a multi-register value (32-bit values, the serial
//! number, an event slot): every published value comes from one reply.
//!
//! The whole span goes out as one 0x03 read; pieces go out as 0x09 reads, whose
//! replies echo every address. A 0x03 reply carries no address, so a late,
//! duplicated or repeated reply to the previous piece of the same length would
//! pass for this piece's — with 0x09 it is refused by its addresses. (Whole-span
//! reads differ in length between blocks, and a stale one of the same block is
//! still a value the BMS sent for those registers.)

use protocol_core::command::MAX_READ_MODBUS;
use protocol_core::registers;
use protocol_core::request::Request;
use protocol_core::response::{RegisterBlock, Words};

use crate::Instant;

/// Registers per request at each level; level 0 reads the whole span at once
/// (0x03), the others in 0x09 pieces (at most 15 addresses: one 63-byte packet).
pub const PIECE_REGISTERS: [u16; 4] = [MAX_READ_MODBUS as u16, 15, 6, 2];

/// The deepest level.
pub const MAX_LEVEL: u8 = (PIECE_REGISTERS.len() - 1) as u8;

/// Consecutive clean attempts (first send answered, valid) before the pieces
/// grow by one level.
pub const CLEAN_TO_GROW: u16 = 12;

/// The live block's ranges (registers 16-31 are reserved).
pub const LIVE_SEGMENTS: &[(u16, u16)] = &[(0, 15), (32, 55)];
/// Statistics.
pub const STATS_SEGMENTS: &[(u16, u16)] = &[(100, 117)];
/// Settings.
pub const SETTINGS_SEGMENTS: &[(u16, u16)] = &[(300, 343)];
/// Version and serial number.
pub const VERSION_SEGMENTS: &[(u16, u16)] = &[(500, 509)];
/// The event log registers.
pub const EVENTS_SEGMENTS: &[(u16, u16)] = &[(200, 297)];

/// How well replies get through, and the piece size that follows from it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LineQuality {
    /// Current level (index into [`PIECE_REGISTERS`]).
    pub level: u8,
    clean_streak: u16,
    /// Requests (block reads) since the last [`LineQuality::take_window`].
    pub requests: u32,
    /// Of which answered at the first send.
    pub clean: u32,
}

impl LineQuality {
    /// Registers per request now.
    pub fn piece(&self) -> u16 {
        PIECE_REGISTERS
            .get(usize::from(self.level))
            .copied()
            .unwrap_or(2)
    }

    /// A block read finished: `sends` requests went out, `ok` tells whether a
    /// valid reply came back. Silence says nothing about size, but a lost reply
    /// still costs a piece: treated like a damaged one.
    pub fn note(&mut self, sends: u8, ok: bool) {
        self.requests = self.requests.wrapping_add(1);
        if ok && sends <= 1 {
            self.clean = self.clean.wrapping_add(1);
            self.clean_streak = self.clean_streak.saturating_add(1);
            if self.clean_streak >= CLEAN_TO_GROW && self.level > 0 {
                self.level -= 1;
                self.clean_streak = 0;
            }
        } else {
            self.clean_streak = 0;
            if self.level < MAX_LEVEL {
                self.level += 1;
            }
        }
    }

    /// (requests, clean) since the previous call, and starts a new window.
    pub fn take_window(&mut self) -> (u32, u32) {
        let w = (self.requests, self.clean);
        self.requests = 0;
        self.clean = 0;
        w
    }
}

/// True when a piece may not end at `address` because `address + 1` continues
/// the value that starts at or before `address`.
fn continues_after(address: u16) -> bool {
    registers::is_continuation(address.wrapping_add(1))
}

/// Most pieces a window read keeps apart (a piece of the live block at the
/// deepest level holds one or two registers: 40 registers, at most 24
/// pieces). Beyond, two neighbouring pieces are kept as one with the older
/// time; a read where no two are neighbours starts over.
pub const WINDOW_PIECES: usize = 32;

/// Registers `first..=last` of a window read were asked for at `at`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Stamp {
    first: u16,
    last: u16,
    at: Instant,
}

/// What a block read is for: how its pieces are accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mode {
    /// Values that change by themselves (live): every piece of the block asked
    /// for within `window_us` of every other. The pieces are read in order;
    /// when the last one is in but the oldest is too old for the window, the
    /// oldest is read again (and the next oldest, ...) until the block's pieces
    /// lie within the window, instead of starting the whole read over: on a
    /// bad line, where a read takes about as long as the window, starting over
    /// threw away the pieces that were still good (issue 54).
    Window(Instant),
    /// Values that do not change by themselves (settings, version, statistics,
    /// the event log): complete passes until two in a row are identical.
    Confirmed,
}

/// A read of one or more register ranges, in pieces.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlockRead {
    segments: &'static [(u16, u16)],
    mode: Mode,
    /// Next address to read.
    cursor: u16,
    /// Address of the piece in flight, and its length.
    in_flight: Option<(u16, u16)>,
    /// The values read so far (`start` is the span's first address).
    block: RegisterBlock,
    /// A pass completed and its values are still in `block` (lent out as
    /// [`Assembled::block`]): the next pass starts with the next request.
    restart_due: bool,
    previous_pass: Option<Words>,
    started_at: Instant,
    pieces: u8,
    passes: u8,
    /// Pieces are believed only when unchanged or read twice alike (see
    /// [`BlockRead::confirm_pieces`]).
    confirm: bool,
    /// Offsets into `block` holding a value a confirmed read stored (bit i:
    /// register `first + i`); a piece equal to them is read twice alike.
    believed: u128,
    /// First read of the piece in flight, waiting for a second that agrees.
    first_read: Option<heapless::Vec<(u16, u16), 16>>,
    second_reads: u32,
    /// When the piece in flight was asked for.
    in_flight_at: Instant,
    /// Window reads: which registers hold a piece, and when it was asked for
    /// (disjoint ranges).
    stamps: heapless::Vec<Stamp, WINDOW_PIECES>,
}

/// A finished block read, lent by the [`BlockRead`] that assembled it (the
/// block is not copied out; the read starts its next pass at its next request).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Assembled<'a> {
    /// Every register of the span (reserved gaps read as 0).
    pub block: &'a RegisterBlock,
    /// Requests that made it up (in the last pass).
    pub pieces: u8,
    /// First piece sent to last piece received, µs.
    pub span_us: Instant,
    /// When the first piece of the (last) pass was asked for.
    pub started_at: Instant,
}

impl BlockRead {
    /// A read of `segments` (ascending, inclusive ranges).
    pub fn new(segments: &'static [(u16, u16)], mode: Mode, now: Instant) -> Self {
        let mut r = Self {
            segments,
            mode,
            cursor: 0,
            in_flight: None,
            block: RegisterBlock {
                start: 0,
                values: Words::new(),
            },
            restart_due: false,
            previous_pass: None,
            started_at: now,
            pieces: 0,
            passes: 0,
            confirm: false,
            believed: 0,
            first_read: None,
            second_reads: 0,
            in_flight_at: now,
            stamps: heapless::Vec::new(),
        };
        r.restart(now);
        r
    }

    /// Makes this read what [`BlockRead::new`] returns, in place: the live read
    /// is restarted at every snapshot, and building a new one (about 900 bytes)
    /// and moving it into place cost more than the rest of the read.
    pub fn reset(&mut self, segments: &'static [(u16, u16)], mode: Mode, now: Instant) {
        // The same constant is the same read (compared by address first).
        let same = core::ptr::eq(self.segments, segments) || self.segments == segments;
        if !same || self.mode != mode {
            // Another read: nothing of the old block may stay (cleared below).
            self.block.values.clear();
        }
        self.segments = segments;
        self.mode = mode;
        self.cursor = 0;
        self.in_flight = None;
        self.previous_pass = None;
        self.started_at = now;
        self.pieces = 0;
        self.passes = 0;
        self.confirm = false;
        self.first_read = None;
        self.second_reads = 0;
        self.restart(now);
    }

    /// First address of the span.
    pub fn first(&self) -> u16 {
        self.segments.first().map(|s| s.0).unwrap_or(0)
    }

    fn last(&self) -> u16 {
        self.segments.last().map(|s| s.1).unwrap_or(0)
    }

    fn restart(&mut self, now: Instant) {
        self.restart_due = false;
        self.cursor = self.first();
        self.in_flight = None;
        self.block.start = self.first();
        let len = usize::from(self.last().saturating_sub(self.first())) + 1;
        let len = len.min(MAX_READ_MODBUS);
        if self.block.values.len() == len {
            // A window read writes its block only with pieces, which lie in the
            // segments and are all written again before a pass completes; the
            // gaps between segments keep their 0 (a reply of the whole span is
            // lent, not copied: see `on_block`). Nothing to clear.
            if self.mode == Mode::Confirmed {
                self.block.values.fill(0);
                self.believed = 0;
            }
        } else {
            self.block.values.clear();
            let _fits = self.block.values.resize(len, 0); // min: fits
            self.believed = 0;
        }
        self.started_at = now;
        self.pieces = 0;
        self.stamps.clear();
    }

    /// The piece in flight failed: it is asked again next time.
    pub fn on_failure(&mut self) {
        self.in_flight = None;
    }

    /// Every piece (a part of the span, read with 0x09) is believed only when
    /// its values equal the reference given with it ([`BlockRead::on_pairs`]:
    /// the last published block), or when two reads of it in a row agree. A
    /// CRC-16 lets a damaged frame through with probability 2^-16, and on a bad
    /// line millions of damaged pieces go by; the consistency checks catch a
    /// value far off, not a cell or a current slightly off (soaks found both).
    /// Pieces are then at most 15 registers (0x09, whose replies echo every
    /// address); a reply of the whole span (0x03) is believed on its checks.
    pub fn confirm_pieces(&mut self) {
        self.confirm = true;
    }

    /// Second reads made to confirm pieces.
    pub fn second_reads(&self) -> u32 {
        self.second_reads
    }

    /// Complete passes so far.
    pub fn passes(&self) -> u8 {
        self.passes
    }

    /// The request for the next piece, at the given piece size. The same piece is
    /// asked again until [`BlockRead::on_block`] accepts it.
    pub fn next_request(&mut self, now: Instant, piece: u16) -> Request {
        let mut request = Request::ReadVersion;
        self.request_into(now, piece, &mut request);
        request
    }

    /// As [`BlockRead::next_request`], written into `out` (where the link
    /// keeps it) instead of returned.
    pub fn request_into(&mut self, now: Instant, piece: u16, out: &mut Request) {
        let (start, count) = self.next_piece(now, piece);
        if usize::from(count) == usize::from(self.last() - self.first()) + 1
            && start == self.first()
            || count > 15
        {
            *out = Request::ReadRegisters {
                start,
                count: count as u8,
            };
            return;
        }
        *out = Request::ReadIndividual(protocol_core::request::AddressList::new());
        if let Request::ReadIndividual(addresses) = out {
            for a in start..start + count {
                let _fits = addresses.push(a); // count <= 15 < 31
            }
        }
    }

    fn next_piece(&mut self, now: Instant, piece: u16) -> (u16, u16) {
        if self.restart_due {
            self.restart(now);
        }
        if self.cursor == self.first() && self.in_flight.is_none() && self.stamps.is_empty() {
            self.started_at = now;
        }
        self.in_flight_at = now;
        // Confirmed pieces are 0x09 pieces (at most 15 registers): only the
        // whole span is read with 0x03.
        let piece = if self.confirm && self.cursor != self.first() {
            piece.min(PIECE_REGISTERS[1])
        } else {
            piece
        };
        let (start, count) = self.piece_at(self.cursor, piece);
        if let Some(f) = &self.first_read {
            // A first read waits for a second one of the same piece only.
            if f.first().map(|p| p.0) != Some(start) || f.len() != usize::from(count) {
                self.first_read = None;
            }
        }
        self.in_flight = Some((start, count));
        (start, count)
    }

    fn piece_at(&self, cursor: u16, piece: u16) -> (u16, u16) {
        let first = self.first();
        let last = self.last();
        if usize::from(piece) >= MAX_READ_MODBUS && cursor == first {
            // Level 0: the whole span in one request.
            let n = (last - first + 1).min(MAX_READ_MODBUS as u16);
            return (first, n);
        }
        let seg_end = self
            .segments
            .iter()
            .find(|(a, b)| (*a..=*b).contains(&cursor))
            .map(|s| s.1)
            .unwrap_or(last);
        let piece = piece.clamp(2, MAX_READ_MODBUS as u16);
        let mut end = cursor.saturating_add(piece - 1).min(seg_end);
        while end > cursor && continues_after(end) {
            end -= 1;
        }
        if continues_after(end) {
            // A value wider than the piece (the serial number): take all of it.
            while end < seg_end && continues_after(end) {
                end += 1;
            }
        }
        (cursor, end - cursor + 1)
    }

    /// The reply (0x03 block) to the piece in flight. Returns the assembled block
    /// when the read is complete. A window read answered by one reply of the
    /// whole span (the live read on a clean line) lends that reply as the
    /// block instead of copying it.
    pub fn on_block<'a>(
        &'a mut self,
        now: Instant,
        reply: &'a RegisterBlock,
    ) -> Option<Assembled<'a>> {
        let (start, count) = self.in_flight?;
        if reply.start != start || reply.values.len() != usize::from(count) {
            self.in_flight = None;
            return None;
        }
        let first = self.first();
        let span = usize::from(self.last().saturating_sub(first)) + 1;
        let whole = matches!(self.mode, Mode::Window(_))
            && start == first
            && reply.values.len() == span
            && span == self.block.values.len();
        if !whole {
            // The piece lies in the span: copied as one slice.
            let dst = start.checked_sub(first).and_then(|i| {
                let i = usize::from(i);
                self.block.values.get_mut(i..i + reply.values.len())
            });
            match dst {
                Some(dst) => dst.copy_from_slice(&reply.values),
                None => self.write(reply.iter()),
            }
            // Copied, not confirmed: those registers no longer hold a
            // confirmed value.
            self.unbelieve(start, reply.values.len());
        }
        if !self.advance(now) {
            return None;
        }
        Some(self.assembled(now, if whole { reply } else { &self.block }))
    }

    /// The reply (0x09 address/value pairs) to the piece in flight; `reference`
    /// is what pieces are believed against (see [`BlockRead::confirm_pieces`]).
    pub fn on_pairs(
        &mut self,
        now: Instant,
        pairs: &[(u16, u16)],
        reference: Option<&RegisterBlock>,
    ) -> Option<Assembled<'_>> {
        let (start, count) = self.in_flight?;
        let expected = pairs.len() == usize::from(count)
            && pairs
                .iter()
                .enumerate()
                .all(|(i, (a, _))| *a == start + i as u16);
        if !expected {
            self.in_flight = None;
            return None;
        }
        if self.confirm {
            let first = self.first();
            let unchanged = reference
                .is_some_and(|r| pairs.iter().all(|&(a, v)| r.get(a) == Some(v)))
                || pairs.iter().all(|&(a, v)| {
                    let i = a.wrapping_sub(first);
                    i < 128 && self.believed & (1u128 << i) != 0 && self.block.get(a) == Some(v)
                });
            let confirmed = self
                .first_read
                .as_ref()
                .is_some_and(|f| f.as_slice() == pairs);
            if !unchanged && !confirmed {
                // Ask again; believed when the next read agrees.
                self.first_read = heapless::Vec::from_slice(pairs).ok();
                self.second_reads = self.second_reads.wrapping_add(1);
                self.in_flight = None;
                return None;
            }
        }
        self.first_read = None;
        self.write(pairs.iter().copied());
        if !self.advance(now) {
            return None;
        }
        Some(self.assembled(now, &self.block))
    }

    /// Forgets that `count` registers from `start` hold a confirmed value.
    fn unbelieve(&mut self, start: u16, count: usize) {
        let first = self.first();
        for a in (0..count).map(|k| start.wrapping_add(k as u16)) {
            if let Some(i) = a.checked_sub(first).filter(|&i| i < 128) {
                self.believed &= !(1u128 << i);
            }
        }
    }

    /// Stores the values of the piece in flight.
    fn write(&mut self, values: impl Iterator<Item = (u16, u16)>) {
        let first = self.first();
        for (a, v) in values {
            if let Some(i) = a.checked_sub(first) {
                if let Some(slot) = self.block.values.get_mut(usize::from(i)) {
                    *slot = v;
                    if self.confirm && i < 128 {
                        self.believed |= 1u128 << i;
                    }
                }
            }
        }
    }

    /// The piece in flight is stored: on to the next one, or the read is
    /// complete (true; for a confirmed read, only when this pass equals the
    /// previous one).
    fn advance(&mut self, now: Instant) -> bool {
        let Some((start, count)) = self.in_flight.take() else {
            return false;
        };
        self.pieces = self.pieces.saturating_add(1);
        let next = start.saturating_add(count);
        if let Mode::Window(w) = self.mode {
            return self.advance_window(now, start, count, w);
        }
        // Segments ascend: the first one holding `next` or starting after it.
        let cursor = self.segments.iter().find_map(|&(a, b)| {
            if (a..=b).contains(&next) {
                Some(next)
            } else {
                (a >= next).then_some(a)
            }
        });
        match cursor {
            Some(c) => {
                self.cursor = c;
                false
            }
            None => self.complete(now),
        }
    }

    /// [`Self::advance`] for a window read: the piece `start..start + count`
    /// is stamped; the next piece is the first register no piece holds yet,
    /// else, when the pieces lie further apart than `w`, the oldest one.
    fn advance_window(&mut self, now: Instant, start: u16, count: u16, w: Instant) -> bool {
        let at = self.in_flight_at;
        if !self.stamp(start, start.saturating_add(count - 1), at) {
            // More pieces than kept apart: start over (never seen with the
            // piece sizes of PIECE_REGISTERS).
            self.restart(now);
            return false;
        }
        let next = start.saturating_add(count);
        if let Some(c) = self
            .uncovered_from(next)
            .or_else(|| self.uncovered_from(self.first()))
        {
            self.cursor = c;
            return false;
        }
        let oldest = self.stamps.iter().min_by_key(|s| s.at).copied();
        let newest = self.stamps.iter().map(|s| s.at).max().unwrap_or(at);
        match oldest {
            Some(o) if newest.saturating_sub(o.at) > w => {
                // Too far apart: the oldest piece is read again.
                self.cursor = o.first;
                false
            }
            _ => {
                self.started_at = oldest.map(|o| o.at).unwrap_or(at);
                self.complete(now)
            }
        }
    }

    /// Records that `first..=last` were asked for at `at`, trimming the
    /// ranges it covers. False when there is no room left.
    fn stamp(&mut self, first: u16, last: u16, at: Instant) -> bool {
        // Wholly covered: gone.
        self.stamps.retain(|s| s.first < first || s.last > last);
        let mut split = None;
        for s in self.stamps.iter_mut() {
            if s.last < first || s.first > last {
                continue;
            }
            if s.first < first && s.last > last {
                // The new piece lies inside an older one: split it.
                split = Some(Stamp {
                    first: last.saturating_add(1),
                    ..*s
                });
                s.last = first.saturating_sub(1);
            } else if s.first < first {
                s.last = first.saturating_sub(1);
            } else {
                s.first = last.saturating_add(1);
            }
        }
        for new in split.into_iter().chain([Stamp { first, last, at }]) {
            if self.stamps.is_full() && !self.merge_two() {
                return false;
            }
            if self.stamps.push(new).is_err() {
                return false;
            }
        }
        true
    }

    /// Makes room: two stamps with nothing of the segments between them
    /// become one, with the older time (a window that holds for it holds for
    /// both). False when no two are that close.
    fn merge_two(&mut self) -> bool {
        let segments = self.segments;
        let close = |a: &Stamp, b: &Stamp| {
            a.last < b.first
                && !segments.iter().any(|&(x, y)| {
                    // A register of the segments strictly between a and b.
                    x < b.first && y > a.last && x.max(a.last.saturating_add(1)) < b.first
                })
        };
        let pair = self.stamps.iter().enumerate().find_map(|(i, a)| {
            self.stamps
                .iter()
                .enumerate()
                .find(|(_, b)| close(a, b))
                .map(|(j, b)| {
                    (
                        i,
                        j,
                        a.first.min(b.first),
                        a.last.max(b.last),
                        a.at.min(b.at),
                    )
                })
        });
        let Some((i, j, first, last, at)) = pair else {
            return false;
        };
        if let Some(a) = self.stamps.get_mut(i) {
            *a = Stamp { first, last, at };
        }
        let _ = self.stamps.swap_remove(j);
        true
    }

    /// The first register of the segments at or after `from` that no piece
    /// holds.
    fn uncovered_from(&self, from: u16) -> Option<u16> {
        let mut r = from;
        loop {
            let seg = self.segments.iter().find(|&&(_, b)| b >= r)?;
            r = r.max(seg.0);
            match self.stamps.iter().find(|s| (s.first..=s.last).contains(&r)) {
                Some(s) => r = s.last.checked_add(1)?,
                None => return Some(r),
            }
        }
    }

    fn complete(&mut self, _now: Instant) -> bool {
        self.passes = self.passes.saturating_add(1);
        // The next pass starts at the next request; until then the block stays
        // where it was assembled, lent out by the caller.
        self.restart_due = true;
        match self.mode {
            Mode::Window(_) => true,
            Mode::Confirmed => {
                let same = self.previous_pass.as_ref() == Some(&self.block.values);
                match &mut self.previous_pass {
                    Some(p) => p.clone_from(&self.block.values),
                    None => self.previous_pass = Some(self.block.values.clone()),
                }
                same
            }
        }
    }

    /// The finished pass, lending `block`.
    fn assembled<'a>(&self, now: Instant, block: &'a RegisterBlock) -> Assembled<'a> {
        Assembled {
            block,
            pieces: self.pieces,
            span_us: now.saturating_sub(self.started_at),
            started_at: self.started_at,
        }
    }
}
