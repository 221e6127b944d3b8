//! The history as the station keeps it: the three rings of the `history`
//! partition (events, days, the day under way), what waits to be written,
//! the date when the bridge knows it, and the listing a host reads.
//!
//! ## When it writes
//! Never by itself: the station asks [`History::next_op`] only in a gap of
//! the BMS poll and the CAN output long enough for a sector's erase (the
//! update's rule, [`crate::station::ota::FLASH_WINDOW_US`]), so a write
//! delays neither a request nor a frame. What waits is kept in RAM
//! ([`PENDING`] records; beyond, counted and said by a `dropped` event).
//!
//! ## How much
//! Events are limited to a burst of [`BURST`] and one every
//! [`REFILL_US`] after it: at worst 8 640 a day, 137 sectors (of 63 events)
//! erased a day over the 96 of the event ring — each sector 1.4 times a day,
//! about 5 200 times in ten years, against the flash's 100 000. A day is one
//! record, the day under way one every hour.
//!
//! ## Where
//! The partition (`history`, 512 KiB in the table of every image) is cut in
//! three: checkpoints 1/16 (8 sectors of 31: 217 hours at least), days 3/16
//! (24 sectors of 31 days: 713 days at least), events the rest (96 sectors
//! of 63: 5 985 events at least). A bridge whose table has no such partition (installed before it
//! came) runs without history and says why ([`History::problem`]).

use core::ops::Range;

use heapless::Deque;

use super::event::{Code, Record, Who};
use super::ring::{Found, Kind, Op, Payload, Reader, Ring, SECTOR_BYTES, SLOT_MAX};
use crate::update::flash::OtaFlash;
use crate::{Instant, SECOND};

/// Records waiting to be written, at most.
pub const PENDING: usize = 12;
/// Events written in a burst before the rate limit.
pub const BURST: u16 = 60;
/// One event more is allowed every this long after a burst, µs.
pub const REFILL_US: Instant = 10 * SECOND;
/// Attempts at writing one record before it is given up.
const ATTEMPTS: u8 = 3;

/// The regions of a partition of `sectors` sectors starting at `start`:
/// events, days, checkpoints.
pub fn regions(start: u32, sectors: u32) -> [Range<u32>; 3] {
    let points = (sectors / 16).max(2);
    let days = (sectors * 3 / 16).max(2);
    let events = sectors.saturating_sub(points + days);
    let at = |n: u32| start + n * SECTOR_BYTES;
    [
        at(0)..at(events),
        at(events)..at(events + days),
        at(events + days)..at(events + days + points),
    ]
}

/// One item of a listing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Listed {
    /// An event (its record id).
    Event(u32, Record),
    /// A day (its record id, its payload).
    Day(u32, Payload),
    /// A slot skipped: the ring's kind, its address and why.
    Skipped(Kind, u32, &'static str),
}

/// A host's listing under way.
#[derive(Debug, Clone)]
struct Listing {
    readers: Deque<Reader, 2>,
    ready: Option<Listed>,
}

/// See the module documentation.
#[derive(Debug, Clone)]
pub struct History {
    /// Why there is no history (`None`: there is).
    problem: Option<&'static str>,
    /// Events, days, checkpoints.
    rings: Option<[Ring; 3]>,
    pending: Deque<(Kind, Payload), PENDING>,
    attempts: u8,
    boot: u16,
    /// The date: Unix seconds at an instant.
    clock: Option<(Instant, u64)>,
    tokens: u16,
    refilled: Instant,
    /// Events not kept since the last `dropped` event.
    dropped: u32,
    written: u32,
    failed: u32,
    last_checkpoint: Option<Payload>,
    last_day: Option<Payload>,
    listing: Option<Listing>,
}

impl History {
    /// The history of a bridge without a partition for it (`problem`: why).
    pub fn without(problem: &'static str) -> Self {
        Self {
            problem: Some(problem),
            rings: None,
            pending: Deque::new(),
            attempts: 0,
            boot: 1,
            clock: None,
            tokens: BURST,
            refilled: 0,
            dropped: 0,
            written: 0,
            failed: 0,
            last_checkpoint: None,
            last_day: None,
            listing: None,
        }
    }

    /// Opens the history in `partition` (or says why there is none): reads
    /// the rings' headers and newest records (before the bridge runs). The
    /// start's number follows the newest event's.
    pub fn open(flash: &mut impl OtaFlash, partition: Result<Range<u32>, &'static str>) -> Self {
        let range = match partition {
            Ok(r) => r,
            Err(p) => return Self::without(p),
        };
        let sectors = range.end.saturating_sub(range.start) / SECTOR_BYTES;
        let [e, d, c] = regions(range.start, sectors);
        let rings = [
            Ring::scan(flash, Kind::Event, e),
            Ring::scan(flash, Kind::Day, d),
            Ring::scan(flash, Kind::Checkpoint, c),
        ];
        let mut h = Self::without("");
        h.problem = None;
        if let Some(p) = rings[0].newest_record(flash) {
            if let Ok(r) = Record::decode_payload(&p) {
                h.boot = r.boot.wrapping_add(1).max(1);
            }
        }
        h.last_day = rings[1].newest_record(flash);
        h.last_checkpoint = rings[2].newest_record(flash);
        h.rings = Some(rings);
        h
    }

    /// Why there is no history (`None`: there is).
    pub fn problem(&self) -> Option<&'static str> {
        self.problem
    }

    /// This start's number.
    pub fn boot(&self) -> u16 {
        self.boot
    }

    /// The newest day record found at start (its payload).
    pub fn last_day(&self) -> Option<&Payload> {
        self.last_day.as_ref()
    }

    /// The newest checkpoint found at start (the day that was under way).
    pub fn last_checkpoint(&self) -> Option<&Payload> {
        self.last_checkpoint.as_ref()
    }

    /// Records written since start, and given up (flash failures, or no room
    /// in RAM).
    pub fn counts(&self) -> (u32, u32) {
        (self.written, self.failed)
    }

    /// The date at `now`, Unix seconds, once a host or the network said it.
    pub fn unix(&self, now: Instant) -> Option<u64> {
        self.clock
            .map(|(at, s)| s.saturating_add(now.saturating_sub(at) / SECOND))
    }

    /// A host said the date (Unix seconds): kept, and an event says so
    /// when it moved it by more than a minute (or it was unknown).
    pub fn set_date(&mut self, now: Instant, unix_s: u64, who: Who) {
        let before = self.unix(now);
        self.clock = Some((now, unix_s));
        if before.is_none_or(|b| b.abs_diff(unix_s) > 60) {
            self.event(now, Code::TimeSet, 0, who as u32, "");
        }
    }

    /// Records an event at `now` (rate-limited; see the module
    /// documentation).
    pub fn event(&mut self, now: Instant, code: Code, a: u32, b: u32, text: &str) {
        if self.rings.is_none() {
            return;
        }
        let refill = now.saturating_sub(self.refilled) / REFILL_US;
        if refill > 0 {
            self.tokens = self
                .tokens
                .saturating_add(u16::try_from(refill).unwrap_or(u16::MAX))
                .min(BURST);
            self.refilled = self.refilled.saturating_add(refill * REFILL_US);
        }
        if self.dropped > 0 && self.tokens > 1 && self.pending.len() + 1 < PENDING {
            self.tokens -= 1;
            let n = core::mem::take(&mut self.dropped);
            self.push_event(now, Code::Dropped, n, 0, "");
        }
        if self.tokens == 0 || self.pending.is_full() {
            self.dropped = self.dropped.saturating_add(1);
            return;
        }
        self.tokens -= 1;
        self.push_event(now, code, a, b, text);
    }

    fn push_event(&mut self, now: Instant, code: Code, a: u32, b: u32, text: &str) {
        let unix = self
            .unix(now)
            .map_or(0, |s| u32::try_from(s).unwrap_or(u32::MAX));
        let r = Record::new(code, self.boot, now / 1000, unix, a, b, text);
        let mut p = [0u8; super::ring::PAYLOAD_MAX];
        for (d, s) in p.iter_mut().zip(r.encode()) {
            *d = s;
        }
        let _ = self.pending.push_back((Kind::Event, p));
    }

    /// Records a closed day, or the day under way (`Kind::Day` or
    /// `Kind::Checkpoint`; the payload's first
    /// [`DAY_PAYLOAD_BYTES`](super::ring::DAY_PAYLOAD_BYTES) or
    /// [`PAYLOAD_BYTES`](super::ring::PAYLOAD_BYTES) bytes are kept). A
    /// checkpoint waiting to be written is replaced by a newer one.
    pub fn record(&mut self, kind: Kind, payload: &[u8]) {
        if self.rings.is_none() {
            return;
        }
        let mut p = [0u8; super::ring::PAYLOAD_MAX];
        for (d, s) in p.iter_mut().zip(payload) {
            *d = *s;
        }
        if kind == Kind::Checkpoint {
            // Not the front one: it may be half-way through its write.
            for (i, item) in self.pending.iter_mut().enumerate() {
                if i > 0 && item.0 == Kind::Checkpoint {
                    item.1 = p;
                    return;
                }
            }
        }
        if self.pending.push_back((kind, p)).is_err() {
            self.failed = self.failed.saturating_add(1);
        }
    }

    fn ring_index(kind: Kind) -> usize {
        match kind {
            Kind::Event => 0,
            Kind::Day => 1,
            Kind::Checkpoint => 2,
        }
    }

    /// Something waits to be written.
    pub fn pending(&self) -> bool {
        self.rings.is_some() && !self.pending.is_empty()
    }

    /// The flash operation to do next (in a gap long enough for it: see the
    /// module documentation), if something waits.
    pub fn next_op(&self) -> Option<Op> {
        let (kind, p) = self.pending.front()?;
        let ring = self.rings.as_ref()?.get(Self::ring_index(*kind))?;
        ring.next_op(p.get(..ring.payload_bytes()).unwrap_or(p))
    }

    /// The operation of [`History::next_op`] is done (`ok`: it worked and
    /// read back the same).
    pub fn done(&mut self, ok: bool) {
        let Some(kind) = self.pending.front().map(|(k, _)| *k) else {
            return;
        };
        let Some(ring) = self
            .rings
            .as_mut()
            .and_then(|r| r.get_mut(Self::ring_index(kind)))
        else {
            return;
        };
        if ring.done(ok) {
            self.pending.pop_front();
            self.written = self.written.saturating_add(1);
            self.attempts = 0;
        } else if !ok {
            self.attempts += 1;
            if self.attempts >= ATTEMPTS {
                self.pending.pop_front();
                self.failed = self.failed.saturating_add(1);
                self.attempts = 0;
            }
        }
    }

    // ---- a host's listing ----

    /// Starts a listing of the events, then the days (a listing under way
    /// starts again).
    pub fn list(&mut self) {
        let Some(rings) = self.rings.as_ref() else {
            return;
        };
        let mut readers = Deque::new();
        for r in [rings[0].reader(), rings[1].reader()] {
            // A ring with nothing in it has nothing to read.
            if r.want().is_some() {
                let _ = readers.push_back(r);
            }
        }
        self.listing = Some(Listing {
            readers,
            ready: None,
        });
    }

    /// The slot the listing needs read (address, bytes), while it has room
    /// for what it finds.
    pub fn want_read(&self) -> Option<(u32, usize)> {
        let l = self.listing.as_ref()?;
        if l.ready.is_some() {
            return None;
        }
        let r = l.readers.front()?;
        Some((r.want()?, r.slot_bytes()))
    }

    /// The bytes of [`History::want_read`] (`None`: the read failed).
    pub fn read_done(&mut self, bytes: Option<&[u8]>) {
        let Some(l) = self.listing.as_mut() else {
            return;
        };
        let Some(r) = l.readers.front_mut() else {
            return;
        };
        let kind = r.kind();
        let found = r.feed(bytes);
        if r.want().is_none() {
            l.readers.pop_front();
        }
        l.ready = match found {
            None => None,
            Some(Found::Skipped(at, d)) => Some(Listed::Skipped(kind, at, d.reason())),
            Some(Found::Record(id, p)) => Some(match kind {
                Kind::Event => match Record::decode_payload(&p) {
                    Ok(e) => Listed::Event(id, e),
                    Err(e) => Listed::Skipped(kind, id, e.reason()),
                },
                _ => Listed::Day(id, p),
            }),
        };
    }

    /// The listing's next item, if one was read (`Some(None)`: the listing
    /// is over; `None`: not yet read, or no listing).
    pub fn take_listed(&mut self) -> Option<Option<Listed>> {
        let l = self.listing.as_mut()?;
        if let Some(x) = l.ready.take() {
            return Some(Some(x));
        }
        if l.readers.is_empty() {
            self.listing = None;
            return Some(None);
        }
        None
    }

    /// A listing is under way.
    pub fn listing(&self) -> bool {
        self.listing.is_some()
    }

    /// Reads a whole ring at once, oldest first (the desktop's tools and the
    /// tests).
    pub fn read_ring(&self, flash: &mut impl OtaFlash, kind: Kind, each: impl FnMut(Found)) {
        if let Some(r) = self
            .rings
            .as_ref()
            .and_then(|r| r.get(Self::ring_index(kind)))
        {
            r.reader().read_all(flash, each);
        }
    }
}

/// The largest slot a shell reads for a listing, bytes.
pub const READ_MAX: usize = SLOT_MAX;

/// Carries out `op` of [`Action::History`](crate::station::Action::History)
/// on `flash` and reads it back: true when it worked (an erased sector reads
/// all `FF`, a program reads back its bytes).
pub fn run(flash: &mut impl OtaFlash, op: Op) -> bool {
    match op {
        Op::Erase(at) => {
            if !flash.erase_sector(at) {
                return false;
            }
            let mut b = [0u8; SLOT_MAX];
            (0..SECTOR_BYTES / SLOT_MAX as u32).all(|i| {
                flash.read(at + i * SLOT_MAX as u32, &mut b) && b.iter().all(|&x| x == 0xFF)
            })
        }
        Op::Program(at, bytes, len) => {
            let Some(bytes) = bytes.get(..usize::from(len)) else {
                return false;
            };
            flash.program(at, bytes) && crate::update::flash::same(flash, at, bytes)
        }
    }
}

/// The `history` partition in the partition table `flash` (of
/// `flash_bytes`) holds ([`crate::partitions::history`]), or why there is
/// none.
pub fn find(flash: &mut impl OtaFlash, flash_bytes: u32) -> Result<Range<u32>, &'static str> {
    use crate::partitions::{Table, TABLE_MAX, TABLE_OFFSET};
    let mut table = [0u8; TABLE_MAX];
    if !flash.read(TABLE_OFFSET, &mut table) {
        return Err("the partition table could not be read");
    }
    let table = Table::parse(&table).map_err(|e| e.reason())?;
    crate::partitions::history(&table, flash_bytes).map_err(|p| p.reason())
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;
    use std::vec::Vec;

    /// Flash in RAM for the history's operations.
    struct Ram(Vec<u8>);

    impl OtaFlash for Ram {
        fn read(&mut self, at: u32, buf: &mut [u8]) -> bool {
            let at = at as usize;
            match self.0.get(at..at + buf.len()) {
                Some(s) => {
                    buf.copy_from_slice(s);
                    true
                }
                None => false,
            }
        }
        fn erase_sector(&mut self, at: u32) -> bool {
            let at = at as usize;
            self.0
                .get_mut(at..at + SECTOR_BYTES as usize)
                .map(|s| s.fill(0xFF))
                .is_some()
        }
        fn program(&mut self, at: u32, bytes: &[u8]) -> bool {
            let at = at as usize;
            match self.0.get_mut(at..at + bytes.len()) {
                Some(s) => {
                    for (d, b) in s.iter_mut().zip(bytes) {
                        *d &= b;
                    }
                    true
                }
                None => false,
            }
        }
    }

    fn events(h: &History, f: &mut Ram) -> Vec<Record> {
        let mut out = Vec::new();
        h.read_ring(f, Kind::Event, |x| {
            if let Found::Record(_, p) = x {
                out.push(Record::decode_payload(&p).unwrap());
            }
        });
        out
    }

    #[test]
    fn a_flood_of_events_is_cut_to_the_rate_and_said_with_a_count() {
        let mut f = Ram(vec![0xFF; 64 * SECTOR_BYTES as usize]);
        let mut h = History::open(&mut f, Ok(0..64 * SECTOR_BYTES));
        // 1000 events in 100 s, each written as it comes.
        for i in 0..1000u64 {
            h.event(i * 100_000, Code::Bms, i as u32, 0, "x");
            while let Some(op) = h.next_op() {
                let ok = run(&mut f, op);
                h.done(ok);
            }
        }
        // Then one more, 10 s on: it says how many were not kept.
        h.event(110 * SECOND, Code::Bms, 1000, 0, "x");
        while let Some(op) = h.next_op() {
            let ok = run(&mut f, op);
            h.done(ok);
        }
        let got = events(&h, &mut f);
        let kept = got.iter().filter(|e| e.code == Code::Bms).count();
        // The burst of 60, then one every 10 s: 69 in the 100 s, the last one.
        assert_eq!(kept, 60 + 9 + 1, "{kept}");
        let dropped: u32 = got
            .iter()
            .filter(|e| e.code == Code::Dropped)
            .map(|e| e.a)
            .sum();
        assert_eq!(dropped as usize + kept, 1001);
        // A history reopened goes on with the next start's number.
        let h2 = History::open(&mut f, Ok(0..64 * SECTOR_BYTES));
        assert_eq!(h2.boot(), 2);
    }

    #[test]
    fn without_a_partition_nothing_waits_and_the_reason_is_kept() {
        let mut h = History::without("no history partition");
        h.event(0, Code::Started, 0, 0, "");
        h.record(Kind::Day, &[1; 56]);
        assert!(!h.pending() && h.next_op().is_none());
        assert_eq!(h.problem(), Some("no history partition"));
    }
}
