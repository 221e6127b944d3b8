//! A ring of fixed-size records in flash sectors: the history's storage
//! (the event log, the days, the checkpoints of the day under way each have
//! one, in the `history` partition).
//!
//! ## The layout
//! A region is whole 4 KiB sectors of slots of one size ([`SLOT_BYTES`]
//! for events, [`DAY_SLOT_BYTES`] for days and checkpoints): slot 0 is the
//! sector's header (its sequence number), slots 1.. hold records. A slot is
//! `"HR"`, its kind, the format version, an id (the record's place: sector
//! sequence × 64 + slot), its payload and a CRC-32 of everything before it.
//! An erased slot is all `FF`.
//!
//! ## Why fixed slots
//! A record is programmed in one operation at a place known in advance. A
//! power cut half-way through leaves that slot damaged (its CRC fails: it is
//! skipped, with that reason) and nothing else: the next record goes to the
//! next slot, and no length field can send a reader astray. A sector is
//! erased only just before its header is written, and only the oldest
//! sector (the one after the newest): a cut erase or a cut header leaves a
//! sector without a valid header, which no reader takes and the next write
//! erases again. So a record is whole or absent, never half, and its id says
//! where it belongs (a record whose id does not match its place is refused).
//!
//! ## Wear
//! Each sector is erased once per lap of the ring: a region of `n` sectors
//! takes `63 n` records per lap (see `docs/history.md` for the figures).
//!
//! Sans-IO: [`Ring::scan`] reads through the update flash trait ([`OtaFlash`],
//! the one the chip and the desktop already hand in) at start (before the
//! bridge runs); appends are planned as [`Op`]s the station has the chip
//! shell carry out in a gap of the BMS poll and the CAN output
//! ([`crate::station`]), reported back with [`Ring::done`].

use core::ops::Range;

use crate::update::flash::OtaFlash;

/// A flash sector, bytes.
pub const SECTOR_BYTES: u32 = 4096;
/// A slot of the event log, bytes.
pub const SLOT_BYTES: usize = 64;
/// A slot of the days and the checkpoints, bytes (a day's record is longer
/// than an event).
pub const DAY_SLOT_BYTES: usize = 128;
/// The largest slot, bytes.
pub const SLOT_MAX: usize = DAY_SLOT_BYTES;
/// A slot's bytes that are not its payload (`HR`, kind, version, id, CRC).
pub const OVERHEAD: usize = 12;
/// Payload bytes of an event (a 64-byte slot).
pub const PAYLOAD_BYTES: usize = SLOT_BYTES - OVERHEAD;
/// Payload bytes of a day (a 128-byte slot).
pub const DAY_PAYLOAD_BYTES: usize = DAY_SLOT_BYTES - OVERHEAD;
/// The largest payload, bytes.
pub const PAYLOAD_MAX: usize = SLOT_MAX - OVERHEAD;
/// A record's payload as read (its ring's payload length is used, the rest
/// is 0).
pub type Payload = [u8; PAYLOAD_MAX];
/// Format version of a slot.
pub const VERSION: u8 = 1;

const MAGIC: [u8; 2] = *b"HR";
const KIND_HEADER: u8 = 0x7F;
const CRC: crc::Crc<u32, crc::NoTable> = crc::Crc::<u32, crc::NoTable>::new(&crc::CRC_32_ISO_HDLC);

/// What a ring holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Kind {
    /// The bridge's event log.
    Event = 1,
    /// Closed days.
    Day = 2,
    /// The day under way, saved hourly.
    Checkpoint = 3,
}

impl Kind {
    fn from_byte(b: u8) -> Option<Self> {
        match b {
            1 => Some(Self::Event),
            2 => Some(Self::Day),
            3 => Some(Self::Checkpoint),
            _ => None,
        }
    }
}

/// Why a slot that is not erased holds no record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Damage {
    /// Its CRC fails: a write cut by a power loss, or a flash that changed.
    Crc,
    /// No `HR` at its start: not a record of this format.
    Magic,
    /// A format version this firmware does not know.
    Version,
    /// A record of another kind than its ring's.
    Kind,
    /// Its id is not its place: a record left from an earlier lap.
    Misplaced,
}

impl Damage {
    /// In words.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::Crc => "its CRC fails (a write cut by a power loss)",
            Self::Magic => "not a history record",
            Self::Version => "a record format this firmware does not know",
            Self::Kind => "a record of another kind",
            Self::Misplaced => "a record whose id is not its place",
        }
    }

    /// A short key.
    pub const fn key(self) -> &'static str {
        match self {
            Self::Crc => "crc",
            Self::Magic => "magic",
            Self::Version => "version",
            Self::Kind => "kind",
            Self::Misplaced => "misplaced",
        }
    }
}

/// What a slot holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    /// Erased: nothing was written.
    Empty,
    /// A record (or a header: kind [`None`]) whose CRC matches.
    Record {
        /// Its kind (`None`: a sector header).
        kind: Option<Kind>,
        /// Its id (a header: the sector's sequence number).
        id: u32,
        /// Its payload.
        payload: Payload,
    },
    /// Written but not a record.
    Damaged(Damage),
}

/// A slot's bytes (the first `len` of the array; `len` is [`SLOT_BYTES`] or
/// [`DAY_SLOT_BYTES`]): `kind` (`None`: a header), `id`, `payload` (cut or
/// padded with zeros to the slot's payload).
pub fn encode(kind: Option<Kind>, id: u32, payload: &[u8], len: usize) -> [u8; SLOT_MAX] {
    let len = len.clamp(OVERHEAD, SLOT_MAX);
    let mut b = [0u8; SLOT_MAX];
    b[..2].copy_from_slice(&MAGIC);
    b[2] = kind.map_or(KIND_HEADER, |k| k as u8);
    b[3] = VERSION;
    b[4..8].copy_from_slice(&id.to_le_bytes());
    let (body, tail) = b.split_at_mut(len - 4);
    for (d, s) in body.iter_mut().skip(8).zip(payload) {
        *d = *s;
    }
    let crc = CRC.checksum(body);
    for (d, s) in tail.iter_mut().zip(crc.to_le_bytes()) {
        *d = s;
    }
    b
}

/// Reads a slot's bytes (all of them: 64 or 128). Never panics.
pub fn decode(b: &[u8]) -> Slot {
    if b.iter().all(|&x| x == 0xFF) {
        return Slot::Empty;
    }
    if b.len() < OVERHEAD || b.len() > SLOT_MAX {
        return Slot::Damaged(Damage::Magic);
    }
    let (body, crc) = b.split_at(b.len() - 4);
    let mut c = [0u8; 4];
    c.copy_from_slice(crc);
    if CRC.checksum(body) != u32::from_le_bytes(c) {
        return Slot::Damaged(Damage::Crc);
    }
    if body.get(..2) != Some(&MAGIC[..]) {
        return Slot::Damaged(Damage::Magic);
    }
    if body.get(3) != Some(&VERSION) {
        return Slot::Damaged(Damage::Version);
    }
    let kind = match body.get(2).copied().unwrap_or(0) {
        KIND_HEADER => None,
        k => match Kind::from_byte(k) {
            Some(k) => Some(k),
            None => return Slot::Damaged(Damage::Kind),
        },
    };
    let mut id = [0u8; 4];
    id.copy_from_slice(body.get(4..8).unwrap_or(&[0; 4]));
    let mut payload = [0u8; PAYLOAD_MAX];
    for (d, s) in payload.iter_mut().zip(body.get(8..).unwrap_or(&[])) {
        *d = *s;
    }
    Slot::Record {
        kind,
        id: u32::from_le_bytes(id),
        payload,
    }
}

/// A flash operation of an append.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Op {
    /// Erase the sector at this address.
    Erase(u32),
    /// Program the first `.2` of these bytes at this address (then read them
    /// back).
    Program(u32, [u8; SLOT_MAX], u16),
}

/// Where the ring's next append goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Next {
    /// Into sector `index` (sequence `seq`), slot `slot`.
    Slot { index: u16, seq: u32, slot: u8 },
    /// Sector `index` is to be erased, then headed with `seq`.
    Erase { index: u16, seq: u32 },
    /// Sector `index` is erased: its header `seq` goes next.
    Head { index: u16, seq: u32 },
}

/// One ring. See the module documentation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ring {
    kind: Kind,
    start: u32,
    sectors: u16,
    /// Slot size, bytes.
    slot_bytes: u16,
    next: Next,
    /// The newest sector with a valid header: index and sequence number.
    newest: Option<(u16, u32)>,
}

impl Ring {
    /// Reads the region's sector headers and the newest sector's slots, and
    /// knows where the next record goes. `region` must be whole sectors (a
    /// region of fewer than two sectors holds nothing: every append waits).
    pub fn scan(flash: &mut impl OtaFlash, kind: Kind, region: Range<u32>) -> Self {
        let slot_bytes = if kind != Kind::Event {
            DAY_SLOT_BYTES
        } else {
            SLOT_BYTES
        } as u16;
        let sectors = u16::try_from(region.end.saturating_sub(region.start) / SECTOR_BYTES)
            .unwrap_or(u16::MAX);
        let mut r = Self {
            kind,
            start: region.start,
            sectors,
            slot_bytes,
            next: Next::Erase { index: 0, seq: 1 },
            newest: None,
        };
        for i in 0..sectors {
            if let Some(seq) = r.header(flash, i) {
                if r.newest.is_none_or(|(_, s)| seq > s) {
                    r.newest = Some((i, seq));
                }
            }
        }
        if let Some((index, seq)) = r.newest {
            // The first slot after the last one written (a damaged slot is
            // passed over: never written twice).
            let mut slot = 1;
            for s in (1..r.slots()).rev() {
                if !matches!(r.read_slot(flash, index, s), Some(Slot::Empty)) {
                    slot = s + 1;
                    break;
                }
            }
            r.next = if slot < r.slots() {
                Next::Slot { index, seq, slot }
            } else {
                r.after(index, seq)
            };
        }
        r
    }

    /// The sector after `index` (sequence `seq`) is next: to be erased.
    fn after(&self, index: u16, seq: u32) -> Next {
        Next::Erase {
            index: (index + 1) % self.sectors.max(1),
            seq: seq.wrapping_add(1),
        }
    }

    /// Slots per sector (slot 0: the header).
    pub fn slots(&self) -> u8 {
        (SECTOR_BYTES / u32::from(self.slot_bytes.max(1))).min(64) as u8
    }

    /// Payload bytes of a record.
    pub fn payload_bytes(&self) -> usize {
        usize::from(self.slot_bytes).saturating_sub(OVERHEAD)
    }

    fn sector_at(&self, index: u16) -> u32 {
        self.start + u32::from(index) * SECTOR_BYTES
    }

    fn slot_at(&self, index: u16, slot: u8) -> u32 {
        self.sector_at(index) + u32::from(slot) * u32::from(self.slot_bytes)
    }

    fn read_slot(&self, flash: &mut impl OtaFlash, index: u16, slot: u8) -> Option<Slot> {
        let mut b = [0u8; SLOT_MAX];
        let b = b.get_mut(..usize::from(self.slot_bytes))?;
        flash.read(self.slot_at(index, slot), b).then(|| decode(b))
    }

    /// Sector `index`'s sequence number, when its header is valid.
    fn header(&self, flash: &mut impl OtaFlash, index: u16) -> Option<u32> {
        match self.read_slot(flash, index, 0)? {
            Slot::Record {
                kind: None,
                id,
                payload,
            } if payload[0] == self.kind as u8 => Some(id),
            _ => None,
        }
    }

    /// The newest record's payload (in the newest sector, or the one before
    /// it when the newest holds none yet).
    pub fn newest_record(&self, flash: &mut impl OtaFlash) -> Option<Payload> {
        let (newest, _) = self.newest?;
        let before = (newest + self.sectors.max(1) - 1) % self.sectors.max(1);
        for index in [newest, before] {
            let Some(seq) = self.header(flash, index) else {
                continue;
            };
            for slot in (1..self.slots()).rev() {
                if let Some(Slot::Record { kind, id, payload }) = self.read_slot(flash, index, slot)
                {
                    if kind == Some(self.kind) && id == record_id(seq, slot) {
                        return Some(payload);
                    }
                }
            }
        }
        None
    }

    /// The region holds records at all (two sectors at least).
    pub fn usable(&self) -> bool {
        self.sectors >= 2
    }

    /// The flash operation the append of `payload` needs next (several may
    /// be needed: an erase and a header before a new sector's first record).
    pub fn next_op(&self, payload: &[u8]) -> Option<Op> {
        if !self.usable() {
            return None;
        }
        Some(match self.next {
            Next::Erase { index, .. } => Op::Erase(self.sector_at(index)),
            Next::Head { index, seq } => {
                let p = [self.kind as u8];
                Op::Program(
                    self.sector_at(index),
                    encode(None, seq, &p, usize::from(self.slot_bytes)),
                    self.slot_bytes,
                )
            }
            Next::Slot { index, seq, slot } => Op::Program(
                self.slot_at(index, slot),
                encode(
                    Some(self.kind),
                    record_id(seq, slot),
                    payload,
                    usize::from(self.slot_bytes),
                ),
                self.slot_bytes,
            ),
        })
    }

    /// The operation [`Ring::next_op`] gave is done (`ok`: it worked and read
    /// back the same). True when the record itself is written (the append is
    /// over). A failed program passes over its slot (it may be half written);
    /// a failed erase is tried again.
    pub fn done(&mut self, ok: bool) -> bool {
        match self.next {
            Next::Erase { index, seq } => {
                if ok {
                    self.next = Next::Head { index, seq };
                }
                false
            }
            Next::Head { index, seq } => {
                self.next = if ok {
                    self.newest = Some((index, seq));
                    Next::Slot {
                        index,
                        seq,
                        slot: 1,
                    }
                } else {
                    Next::Erase { index, seq }
                };
                false
            }
            Next::Slot { index, seq, slot } => {
                self.next = if slot + 1 < self.slots() {
                    Next::Slot {
                        index,
                        seq,
                        slot: slot + 1,
                    }
                } else {
                    self.after(index, seq)
                };
                ok
            }
        }
    }

    /// A reader from the oldest record to the newest.
    pub fn reader(&self) -> Reader {
        let first = match self.newest {
            // The sector after the newest is the oldest (or erased).
            Some((i, _)) => (i + 1) % self.sectors.max(1),
            None => 0,
        };
        Reader {
            ring: self.clone(),
            step: 0,
            first,
            slot: 0,
            seq: None,
            done: self.newest.is_none(),
        }
    }

    /// Records the region holds at most.
    pub fn capacity(&self) -> u32 {
        u32::from(self.sectors.saturating_sub(1)) * u32::from(self.slots().saturating_sub(1))
    }
}

/// A record's id: its sector's sequence number and its slot.
pub const fn record_id(seq: u32, slot: u8) -> u32 {
    seq.wrapping_mul(64).wrapping_add(slot as u32)
}

/// What a [`Reader`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Found {
    /// A record: its id and payload.
    Record(u32, Payload),
    /// A slot skipped, at this address, and why.
    Skipped(u32, Damage),
}

/// Reads a ring oldest first, one slot per [`Reader::feed`] (sans-IO: the
/// station has the shell read [`Reader::want`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reader {
    ring: Ring,
    /// Sectors passed since the first.
    step: u16,
    first: u16,
    /// Slot to read in the current sector (0: its header).
    slot: u8,
    /// The current sector's sequence (after its header was read).
    seq: Option<u32>,
    done: bool,
}

impl Reader {
    fn index(&self) -> u16 {
        (self.first + self.step) % self.ring.sectors.max(1)
    }

    /// The address of the slot to read next (`None`: the reader is at the
    /// end).
    pub fn want(&self) -> Option<u32> {
        (!self.done).then(|| self.ring.slot_at(self.index(), self.slot))
    }

    fn next_sector(&mut self) {
        self.step += 1;
        self.slot = 0;
        self.seq = None;
        if self.step >= self.ring.sectors {
            self.done = true;
        }
    }

    /// Bytes of the slot to read.
    pub fn slot_bytes(&self) -> usize {
        usize::from(self.ring.slot_bytes)
    }

    /// The kind of the ring it reads.
    pub fn kind(&self) -> Kind {
        self.ring.kind
    }

    /// The bytes at [`Reader::want`] (`None`: the read failed: the slot is
    /// passed over). Returns what the slot held when it is worth saying.
    pub fn feed(&mut self, bytes: Option<&[u8]>) -> Option<Found> {
        if self.done {
            return None;
        }
        let at = self.ring.slot_at(self.index(), self.slot);
        let slot = bytes.map(decode);
        if self.slot == 0 {
            match slot {
                Some(Slot::Record {
                    kind: None,
                    id,
                    payload,
                }) if payload[0] == self.ring.kind as u8 => {
                    self.seq = Some(id);
                    self.slot = 1;
                }
                // No header: never headed, an erase or a header cut short.
                _ => self.next_sector(),
            }
            return None;
        }
        let seq = self.seq.unwrap_or(0);
        let found = match slot {
            None => None,
            Some(Slot::Empty) => {
                // Erased slots end a sector's records.
                self.next_sector();
                return None;
            }
            Some(Slot::Record { kind, id, payload }) => {
                if kind != Some(self.ring.kind) {
                    Some(Found::Skipped(at, Damage::Kind))
                } else if id != record_id(seq, self.slot) {
                    Some(Found::Skipped(at, Damage::Misplaced))
                } else {
                    Some(Found::Record(id, payload))
                }
            }
            Some(Slot::Damaged(d)) => Some(Found::Skipped(at, d)),
        };
        self.slot += 1;
        if self.slot >= self.ring.slots() {
            self.next_sector();
        }
        found
    }

    /// Reads the whole ring at once (tests, the desktop).
    pub fn read_all(mut self, flash: &mut impl OtaFlash, mut each: impl FnMut(Found)) {
        while let Some(at) = self.want() {
            let mut b = [0u8; SLOT_MAX];
            let b = b.get_mut(..self.slot_bytes()).unwrap_or(&mut []);
            let ok = flash.read(at, b);
            if let Some(f) = self.feed(ok.then_some(&*b)) {
                each(f);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;
    use std::vec::Vec;

    /// NOR flash in RAM: erase sets `FF`, a program clears bits; `cut` stops
    /// a program or an erase after this many bytes.
    struct Nor {
        b: Vec<u8>,
        cut: Option<usize>,
    }

    impl OtaFlash for Nor {
        // The tests cut the power in [`Nor::run`]; the ring only reads.
        fn erase_sector(&mut self, _: u32) -> bool {
            false
        }
        fn program(&mut self, _: u32, _: &[u8]) -> bool {
            false
        }
        fn read(&mut self, at: u32, buf: &mut [u8]) -> bool {
            let at = at as usize;
            match self.b.get(at..at + buf.len()) {
                Some(s) => {
                    buf.copy_from_slice(s);
                    true
                }
                None => false,
            }
        }
    }

    impl Nor {
        fn new(sectors: usize) -> Self {
            Self {
                b: vec![0xFF; sectors * SECTOR_BYTES as usize],
                cut: None,
            }
        }
        /// Carries out `op`; false when the power went during it.
        fn run(&mut self, op: Op) -> bool {
            let (at, bytes): (usize, Vec<u8>) = match op {
                Op::Erase(a) => (a as usize, vec![0xFF; SECTOR_BYTES as usize]),
                Op::Program(a, b, n) => (a as usize, b[..n as usize].to_vec()),
            };
            for (i, v) in bytes.iter().enumerate() {
                if let Some(c) = self.cut.as_mut() {
                    if *c == 0 {
                        return false;
                    }
                    *c -= 1;
                }
                let d = &mut self.b[at + i];
                *d = if matches!(op, Op::Erase(_)) {
                    0xFF
                } else {
                    *d & v
                };
            }
            true
        }
    }

    fn payload(n: u32) -> Payload {
        let mut p = [0u8; PAYLOAD_MAX];
        p[..4].copy_from_slice(&n.to_le_bytes());
        p[4..PAYLOAD_BYTES].fill(n as u8);
        p
    }

    fn append(r: &mut Ring, f: &mut Nor, n: u32) -> bool {
        for _ in 0..4 {
            let Some(op) = r.next_op(&payload(n)) else {
                return false;
            };
            let ok = f.run(op);
            if !ok {
                return false;
            }
            if r.done(ok) {
                return true;
            }
        }
        false
    }

    fn records(f: &mut Nor, sectors: u16) -> (Vec<u32>, Vec<Damage>) {
        let r = Ring::scan(f, Kind::Event, 0..u32::from(sectors) * SECTOR_BYTES);
        let (mut got, mut bad) = (Vec::new(), Vec::new());
        r.reader().read_all(f, |x| match x {
            Found::Record(_, p) => {
                assert_eq!(p, payload(u32::from_le_bytes([p[0], p[1], p[2], p[3]])));
                got.push(u32::from_le_bytes([p[0], p[1], p[2], p[3]]));
            }
            Found::Skipped(_, d) => bad.push(d),
        });
        (got, bad)
    }

    #[test]
    fn records_come_back_oldest_first_and_the_oldest_sector_goes() {
        let mut f = Nor::new(3);
        let mut r = Ring::scan(&mut f, Kind::Event, 0..3 * SECTOR_BYTES);
        assert_eq!(records(&mut f, 3).0, Vec::<u32>::new());
        for n in 0..200 {
            assert!(append(&mut r, &mut f, n));
        }
        // 3 sectors of 63: the first lap (0..189) then the fourth sector
        // erased the first: 63..200 are left.
        let (got, bad) = records(&mut f, 3);
        assert!(bad.is_empty());
        assert_eq!(got, (63..200).collect::<Vec<_>>());
        // A restart goes on where it was.
        let mut r2 = Ring::scan(&mut f, Kind::Event, 0..3 * SECTOR_BYTES);
        assert_eq!(r2, r);
        assert!(append(&mut r2, &mut f, 200));
        assert_eq!(records(&mut f, 3).0.last(), Some(&200));
        assert_eq!(r.capacity(), 126);
    }

    #[test]
    fn a_power_cut_at_every_byte_leaves_each_record_whole_or_absent() {
        // A ring that has lapped, then one more append (an erase, a header, a
        // record), cut after every byte of it.
        let mut base = Nor::new(2);
        let mut r = Ring::scan(&mut base, Kind::Event, 0..2 * SECTOR_BYTES);
        for n in 0..126 {
            assert!(append(&mut r, &mut base, n));
        }
        let total = SECTOR_BYTES as usize + 2 * SLOT_BYTES;
        for cut in 0..total {
            let mut f = Nor {
                b: base.b.clone(),
                cut: Some(cut),
            };
            let mut r = Ring::scan(&mut f, Kind::Event, 0..2 * SECTOR_BYTES);
            assert!(!append(&mut r, &mut f, 126), "cut {cut}");
            f.cut = None;
            let (got, bad) = records(&mut f, 2);
            // Every record read is one that was written, in order, with its
            // payload (checked in `records`); a half-written one is skipped
            // for its CRC.
            assert!(got.windows(2).all(|w| w[1] == w[0] + 1), "cut {cut}");
            assert!(got.iter().all(|&n| n <= 126));
            assert!(bad.iter().all(|&d| d == Damage::Crc), "cut {cut}: {bad:?}");
            // The log goes on after the restart, and the next record reads.
            let mut r = Ring::scan(&mut f, Kind::Event, 0..2 * SECTOR_BYTES);
            assert!(append(&mut r, &mut f, 127), "cut {cut}");
            let (got, _) = records(&mut f, 2);
            assert_eq!(got.last(), Some(&127), "cut {cut}");
        }
    }

    #[test]
    fn damaged_slots_are_skipped_with_their_reason() {
        let mut f = Nor::new(2);
        let mut r = Ring::scan(&mut f, Kind::Event, 0..2 * SECTOR_BYTES);
        for n in 0..5 {
            assert!(append(&mut r, &mut f, n));
        }
        // Slot 2 (record 1): a bit flipped.
        f.b[2 * SLOT_BYTES + 20] ^= 0x10;
        // Slot 3 (record 2): a record of a future format, CRC right.
        let mut b = [0u8; SLOT_BYTES];
        b.copy_from_slice(&f.b[3 * SLOT_BYTES..4 * SLOT_BYTES]);
        b[3] = 9;
        let c = CRC.checksum(&b[..60]);
        b[60..].copy_from_slice(&c.to_le_bytes());
        f.b[3 * SLOT_BYTES..4 * SLOT_BYTES].copy_from_slice(&b);
        // Slot 4 (record 3): a record copied from elsewhere (wrong id).
        let moved = encode(Some(Kind::Event), 12345, &payload(3), SLOT_BYTES);
        f.b[4 * SLOT_BYTES..5 * SLOT_BYTES].copy_from_slice(&moved[..SLOT_BYTES]);
        let (got, bad) = records(&mut f, 2);
        assert_eq!(got, vec![0, 4]);
        assert_eq!(bad, vec![Damage::Crc, Damage::Version, Damage::Misplaced]);
        // A ring of days does not read the events' sectors.
        let days = Ring::scan(&mut f, Kind::Day, 0..2 * SECTOR_BYTES);
        assert_eq!(days.newest, None);
    }

    #[test]
    fn any_bytes_decode_without_a_panic() {
        let mut x: u32 = 0x9E37_79B9;
        for _ in 0..20_000 {
            let mut b = [0u8; SLOT_BYTES];
            for v in b.iter_mut() {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                *v = x as u8;
            }
            assert!(matches!(decode(&b), Slot::Damaged(_)));
        }
        let rec = encode(Some(Kind::Event), 7, &payload(7), SLOT_BYTES);
        assert_eq!(
            decode(&rec[..SLOT_BYTES]),
            Slot::Record {
                kind: Some(Kind::Event),
                id: 7,
                payload: payload(7)
            }
        );
    }
}
