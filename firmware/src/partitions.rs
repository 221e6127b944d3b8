//! The ESP-IDF partition table, read from its bytes: what the second-stage
//! bootloader and every flashing tool (espflash, esptool, the browser
//! installer) put at [`TABLE_OFFSET`]. The chip reads [`TABLE_MAX`] bytes
//! there and hands them to [`Table::parse`]; the host tests hand it the bytes
//! of the images CI makes. Nothing here touches flash.
//!
//! The format (ESP-IDF's `gen_esp32part.py`, espflash's `esp-idf-part`): one
//! 32-byte entry per partition — magic `AA 50`, type, subtype, offset and size
//! (little-endian `u32`), a 16-byte label padded with zeros, flags (bit 0:
//! encrypted, bit 1: read-only) — then, optionally, an MD5 entry (`EB EB`,
//! 14 bytes `FF`, the MD5 of every entry before it), then `FF` bytes.
//!
//! Lookups compare the label's *text* (the bytes before its padding), never
//! the padded 16-byte field, and read type and subtype as raw numbers, so a
//! table with partitions this firmware does not know still reads.
//!
//! [`history`] finds the history partition (issue 55: the bridge's event log
//! and daily records) and says why it cannot be used ([`HistoryProblem`]);
//! bridges installed before `firmware/partitions.csv` had it keep a table
//! without it (`firmware/partitions-pre-history.csv`) through every update
//! over the network.

use md5::{Digest, Md5};

/// Where the table starts on flash (ESP-IDF's default, espflash's and
/// esp-bootloader-esp-idf's).
pub const TABLE_OFFSET: u32 = 0x8000;
/// The most bytes a table may take (ESP-IDF's `ESP_PARTITION_TABLE_MAX_LEN`).
pub const TABLE_MAX: usize = 0xC00;
/// Bytes per entry.
pub const ENTRY_LEN: usize = 32;

const ENTRY_MAGIC: [u8; 2] = [0xAA, 0x50];
const MD5_MAGIC: [u8; 2] = [0xEB, 0xEB];
/// Flags: the partition is encrypted (ESP-IDF's `PART_FLAG_ENCRYPTED`).
const FLAG_ENCRYPTED: u32 = 1 << 0;
/// Flags: the partition is read-only (`PART_FLAG_READONLY`).
const FLAG_READ_ONLY: u32 = 1 << 1;

/// Partition type: data.
pub const TYPE_DATA: u8 = 0x01;
/// Partition type: application.
pub const TYPE_APP: u8 = 0x00;
/// Data subtype: NVS (the configuration store's).
pub const SUBTYPE_NVS: u8 = 0x02;
/// Data subtype: ESP-IDF's `undefined` (0x06), for data no ESP-IDF component
/// reads or writes (the history's).
pub const SUBTYPE_UNDEFINED: u8 = 0x06;

/// The history partition's label: the bridge's event log and daily records
/// (issue 55), in every table since `firmware/partitions.csv` had it.
pub const HISTORY_LABEL: &str = "history";
/// The history partition's type: data.
pub const HISTORY_TYPE: u8 = TYPE_DATA;
/// The history partition's subtype: `undefined` (in the CSV by that name).
pub const HISTORY_SUBTYPE: u8 = SUBTYPE_UNDEFINED;
/// The smallest history partition [`history`] takes, bytes (16 sectors).
pub const HISTORY_MIN: u32 = 64 * 1024;
/// The flash's erase unit, bytes: the history partition starts and ends on
/// one.
pub const SECTOR: u32 = 4096;
/// The bootloader and the table: below here no partition may lie (the table's
/// sector ends where ESP-IDF's first partition may start).
const RESERVED_END: u32 = TABLE_OFFSET + SECTOR;

/// Why bytes are not a partition table.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TableError {
    /// The first entry has no entry magic: no table was written (an erased
    /// or foreign flash).
    Missing,
    /// An entry is neither a partition, the MD5 entry nor the end.
    Malformed,
    /// The MD5 entry does not match the entries before it.
    Checksum,
}

impl TableError {
    /// In words.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::Missing => "no partition table at 0x8000",
            Self::Malformed => "the partition table has an entry that is not one",
            Self::Checksum => "the partition table's MD5 does not match its entries",
        }
    }
}

/// One partition.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Entry {
    /// Type (0 app, 1 data, others custom).
    pub kind: u8,
    /// Subtype.
    pub subtype: u8,
    /// Offset on flash, bytes.
    pub offset: u32,
    /// Size, bytes.
    pub size: u32,
    label: [u8; 16],
    /// Raw flags.
    pub flags: u32,
}

impl Entry {
    /// From one 32-byte entry whose magic was checked.
    fn from_bytes(e: &[u8; ENTRY_LEN]) -> Self {
        let word = |at: usize| {
            let mut w = [0u8; 4];
            if let Some(b) = e.get(at..at + 4) {
                w.copy_from_slice(b);
            }
            u32::from_le_bytes(w)
        };
        let mut label = [0u8; 16];
        if let Some(l) = e.get(12..28) {
            label.copy_from_slice(l);
        }
        Self {
            kind: e[2],
            subtype: e[3],
            offset: word(4),
            size: word(8),
            label,
            flags: word(28),
        }
    }

    /// The label's text: its bytes before the first zero (or `FF`) of the
    /// padding.
    pub fn label(&self) -> &[u8] {
        let len = self
            .label
            .iter()
            .position(|&b| b == 0 || b == 0xFF)
            .unwrap_or(self.label.len());
        self.label.get(..len).unwrap_or(&[])
    }

    /// The table marks it encrypted.
    pub const fn encrypted(&self) -> bool {
        self.flags & FLAG_ENCRYPTED != 0
    }

    /// The table marks it read-only.
    pub const fn read_only(&self) -> bool {
        self.flags & FLAG_READ_ONLY != 0
    }
}

/// Whether the table carried an MD5 entry (it matched, or [`Table::parse`]
/// would have refused it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Checksum {
    /// Present and equal to the entries' MD5.
    Verified,
    /// The table has none (ESP-IDF's `--disable-md5sum`; the bootloader
    /// accepts it too).
    Absent,
}

/// A partition table that parsed: its entries, in order.
#[derive(Debug, Clone, Copy)]
pub struct Table<'a> {
    entries: &'a [[u8; ENTRY_LEN]],
    checksum: Checksum,
}

impl<'a> Table<'a> {
    /// Reads a table from the bytes at [`TABLE_OFFSET`] (up to [`TABLE_MAX`]
    /// of them; more are ignored). Never panics on any bytes.
    pub fn parse(bytes: &'a [u8]) -> Result<Self, TableError> {
        let bytes = bytes.get(..TABLE_MAX).unwrap_or(bytes);
        let (chunks, _) = bytes.as_chunks::<ENTRY_LEN>();
        let mut count = 0;
        let mut checksum = Checksum::Absent;
        for chunk in chunks {
            let magic = [chunk[0], chunk[1]];
            if magic == ENTRY_MAGIC {
                count += 1;
                continue;
            }
            if magic == MD5_MAGIC {
                let entries = chunks.get(..count).unwrap_or(&[]);
                let mut md5 = Md5::new();
                for e in entries {
                    md5.update(e);
                }
                let digest: [u8; 16] = md5.finalize().into();
                if chunk.get(16..32) != Some(&digest[..]) {
                    return Err(TableError::Checksum);
                }
                checksum = Checksum::Verified;
                break;
            }
            if chunk.iter().all(|&b| b == 0xFF) {
                break;
            }
            return Err(if count == 0 {
                TableError::Missing
            } else {
                TableError::Malformed
            });
        }
        if count == 0 {
            return Err(TableError::Missing);
        }
        Ok(Self {
            entries: chunks.get(..count).unwrap_or(&[]),
            checksum,
        })
    }

    /// Whether an MD5 entry vouched for the entries.
    pub const fn checksum(&self) -> Checksum {
        self.checksum
    }

    /// The partitions, in table order.
    pub fn entries(&self) -> impl Iterator<Item = Entry> + 'a {
        self.entries.iter().map(Entry::from_bytes)
    }

    /// The first partition of this type and subtype whose label's text is
    /// `label`.
    pub fn find(&self, kind: u8, subtype: u8, label: &str) -> Option<Entry> {
        self.entries()
            .find(|e| e.kind == kind && e.subtype == subtype && e.label() == label.as_bytes())
    }
}

/// Why the bridge has no history partition it may write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum HistoryProblem {
    /// No data partition of subtype `undefined` labelled [`HISTORY_LABEL`]:
    /// a table from before the history partition (every bridge installed
    /// before it, and updated over the network since).
    Missing,
    /// The table marks it encrypted (this firmware writes it plain).
    Encrypted,
    /// Its offset or size is not a whole number of [`SECTOR`]s.
    Unaligned,
    /// Smaller than [`HISTORY_MIN`].
    TooSmall,
    /// It overlaps the bootloader or the partition table (below 0x9000).
    OverlapsTable,
    /// It overlaps an app slot.
    OverlapsApp,
    /// It overlaps another data partition (the store, `otadata`, …).
    OverlapsData,
    /// It ends past the flash the chip reports.
    BeyondFlash,
}

impl HistoryProblem {
    /// In words.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::Missing => {
                "this bridge's partition table predates the history partition (an update \
                 over the network keeps the table): one reinstall by cable adds it, the \
                 browser installer's Update or esptool (docs/updates.md)"
            }
            Self::Encrypted => "the history partition is marked encrypted",
            Self::Unaligned => "the history partition is not on 4096-byte sector boundaries",
            Self::TooSmall => "the history partition is smaller than 64 KiB",
            Self::OverlapsTable => {
                "the history partition overlaps the bootloader or the partition table"
            }
            Self::OverlapsApp => "the history partition overlaps an app slot",
            Self::OverlapsData => "the history partition overlaps another data partition",
            Self::BeyondFlash => "the history partition ends past the chip's flash",
        }
    }
}

/// Where the history partition is on the whole flash (`flash_bytes`: what
/// the chip reports of its flash): the data partition of subtype
/// [`HISTORY_SUBTYPE`] labelled [`HISTORY_LABEL`], plain, on sector
/// boundaries, at least [`HISTORY_MIN`] bytes, clear of the bootloader, the
/// table and every other partition, within the flash. Nothing else of the
/// flash may be erased for the history, so anything less is refused.
pub fn history(table: &Table, flash_bytes: u32) -> Result<core::ops::Range<u32>, HistoryProblem> {
    let e = table
        .find(HISTORY_TYPE, HISTORY_SUBTYPE, HISTORY_LABEL)
        .ok_or(HistoryProblem::Missing)?;
    if e.encrypted() {
        return Err(HistoryProblem::Encrypted);
    }
    if e.offset % SECTOR != 0 || e.size % SECTOR != 0 {
        return Err(HistoryProblem::Unaligned);
    }
    if e.size < HISTORY_MIN {
        return Err(HistoryProblem::TooSmall);
    }
    let end = e
        .offset
        .checked_add(e.size)
        .ok_or(HistoryProblem::BeyondFlash)?;
    if e.offset < RESERVED_END {
        return Err(HistoryProblem::OverlapsTable);
    }
    let overlapping = || {
        table.entries().filter(move |o| {
            *o != e && o.offset < end && e.offset < o.offset.saturating_add(o.size)
        })
    };
    if overlapping().any(|o| o.kind == TYPE_APP) {
        return Err(HistoryProblem::OverlapsApp);
    }
    if overlapping().next().is_some() {
        return Err(HistoryProblem::OverlapsData);
    }
    if end > flash_bytes {
        return Err(HistoryProblem::BeyondFlash);
    }
    Ok(e.offset..end)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(kind: u8, subtype: u8, offset: u32, size: u32, label: &str, flags: u32) -> [u8; 32] {
        let mut e = [0u8; 32];
        e[..2].copy_from_slice(&ENTRY_MAGIC);
        e[2] = kind;
        e[3] = subtype;
        e[4..8].copy_from_slice(&offset.to_le_bytes());
        e[8..12].copy_from_slice(&size.to_le_bytes());
        e[12..12 + label.len()].copy_from_slice(label.as_bytes());
        e[28..].copy_from_slice(&flags.to_le_bytes());
        e
    }

    fn table(entries: &[[u8; 32]], md5: bool) -> [u8; TABLE_MAX] {
        let mut t = [0xFFu8; TABLE_MAX];
        for (i, e) in entries.iter().enumerate() {
            t[i * 32..][..32].copy_from_slice(e);
        }
        if md5 {
            let n = entries.len() * 32;
            let digest: [u8; 16] = Md5::digest(&t[..n]).into();
            t[n..n + 2].copy_from_slice(&MD5_MAGIC);
            t[n + 16..n + 32].copy_from_slice(&digest);
        }
        t
    }

    #[test]
    fn the_label_is_compared_as_text_not_as_its_padded_field() {
        let t = table(&[entry(1, 2, 0x9000, 0x6000, "nvs", 0)], true);
        let t = Table::parse(&t).unwrap();
        assert_eq!(t.checksum(), Checksum::Verified);
        let e = t.find(TYPE_DATA, SUBTYPE_NVS, "nvs").unwrap();
        assert_eq!((e.offset, e.size, e.label()), (0x9000, 0x6000, &b"nvs"[..]));
        assert!(t.find(TYPE_DATA, SUBTYPE_NVS, "nv").is_none());
        assert!(t.find(TYPE_DATA, SUBTYPE_NVS, "nvs2").is_none());
    }

    #[test]
    fn flags_follow_esp_idf() {
        let t = table(
            &[
                entry(1, 2, 0x9000, 0x6000, "nvs", 1),
                entry(1, 1, 0xF000, 0x1000, "phy", 2),
            ],
            false,
        );
        let t = Table::parse(&t).unwrap();
        let mut es = t.entries();
        let (a, b) = (es.next().unwrap(), es.next().unwrap());
        assert!(a.encrypted() && !a.read_only());
        assert!(!b.encrypted() && b.read_only());
        assert_eq!(t.checksum(), Checksum::Absent);
    }

    #[test]
    fn erased_foreign_and_broken_tables_are_refused() {
        assert_eq!(
            Table::parse(&[0xFF; TABLE_MAX]).unwrap_err(),
            TableError::Missing
        );
        assert_eq!(
            Table::parse(&[0x00; TABLE_MAX]).unwrap_err(),
            TableError::Missing
        );
        assert_eq!(Table::parse(&[]).unwrap_err(), TableError::Missing);
        let mut t = table(&[entry(1, 2, 0x9000, 0x6000, "nvs", 0)], true);
        t[48] ^= 1; // the first byte of the MD5 entry's digest
        assert_eq!(Table::parse(&t).unwrap_err(), TableError::Checksum);
        let mut t = table(&[entry(1, 2, 0x9000, 0x6000, "nvs", 0)], false);
        t[32] = 0x12;
        assert_eq!(Table::parse(&t).unwrap_err(), TableError::Malformed);
    }

    #[test]
    fn any_bytes_parse_or_are_refused_without_a_panic() {
        let mut x: u32 = 0x1234_5678;
        for len in [0usize, 1, 31, 32, 33, 64, 3071, 3072, 4096] {
            for _ in 0..50 {
                let mut b = [0u8; 4096];
                for v in b.iter_mut().take(len) {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    *v = x as u8;
                }
                b[0] = 0xAA;
                b[1] = 0x50;
                let _ = Table::parse(&b[..len]);
            }
        }
    }

    /// The bytes of a table in ESP-IDF's CSV form (the types, subtypes and
    /// flags the project's tables use; espflash's own bytes of the same CSVs
    /// are checked in host-tests' `store_site.rs`).
    fn csv_table(csv: &str) -> [u8; TABLE_MAX] {
        let mut entries = std::vec::Vec::new();
        for line in csv.lines().map(str::trim) {
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let f: std::vec::Vec<&str> = line.split(',').map(str::trim).collect();
            let num = |t: &str| u32::from_str_radix(t.trim_start_matches("0x"), 16).unwrap();
            let kind = match f[1] {
                "app" => TYPE_APP,
                "data" => TYPE_DATA,
                t => panic!("type {t}"),
            };
            let subtype = match f[2] {
                "ota" => 0x00,
                "phy" => 0x01,
                "nvs" => SUBTYPE_NVS,
                "undefined" => SUBTYPE_UNDEFINED,
                t if t.starts_with("ota_") => 0x10 + t[4..].parse::<u8>().unwrap(),
                t => panic!("subtype {t}"),
            };
            let flags = u32::from(f.get(5) == Some(&"encrypted"));
            entries.push(entry(kind, subtype, num(f[3]), num(f[4]), f[0], flags));
        }
        table(&entries, true)
    }

    extern crate std;
    const MIB4: u32 = 4 * 1024 * 1024;
    /// Every image's table.
    const CSV: &str = include_str!("../partitions.csv");
    /// The table of every bridge installed before the history partition.
    const PRE_HISTORY_CSV: &str = include_str!("../partitions-pre-history.csv");

    #[test]
    fn every_images_table_has_the_history_in_its_last_512_kib() {
        let bytes = csv_table(CSV);
        let t = Table::parse(&bytes).unwrap();
        assert_eq!(history(&t, MIB4), Ok(0x38_0000..0x40_0000));
        let e = t
            .find(HISTORY_TYPE, HISTORY_SUBTYPE, HISTORY_LABEL)
            .unwrap();
        assert_eq!((e.kind, e.subtype, e.flags), (0x01, 0x06, 0));
        // On a 2 MiB chip it would lie past the flash (and wrap onto a slot).
        assert_eq!(
            history(&t, 2 * 1024 * 1024),
            Err(HistoryProblem::BeyondFlash)
        );
    }

    #[test]
    fn the_pre_history_table_has_none_and_says_a_cable_reinstall_adds_it() {
        let bytes = csv_table(PRE_HISTORY_CSV);
        let t = Table::parse(&bytes).unwrap();
        assert_eq!(t.entries().count(), 5);
        assert_eq!(history(&t, MIB4), Err(HistoryProblem::Missing));
        let words = HistoryProblem::Missing.reason();
        for w in [
            "predates the history partition",
            "reinstall by cable",
            "browser installer",
        ] {
            assert!(words.contains(w), "{words}");
        }
    }

    /// The real table with its history line replaced by `line`.
    fn with_history(line: &str) -> [u8; TABLE_MAX] {
        let csv: std::string::String = CSV
            .lines()
            .map(|l| if l.starts_with("history,") { line } else { l })
            .flat_map(|l| [l, "\n"])
            .collect();
        csv_table(&csv)
    }

    #[test]
    fn a_history_partition_that_cannot_be_written_safely_is_refused_with_its_reason() {
        let cases = [
            (
                "the label on another subtype",
                "history, data, nvs, 0x380000, 0x80000,",
                HistoryProblem::Missing,
            ),
            (
                "another label",
                "historic, data, undefined, 0x380000, 0x80000,",
                HistoryProblem::Missing,
            ),
            (
                "a label the history's is the start of",
                "hist, data, undefined, 0x380000, 0x80000,",
                HistoryProblem::Missing,
            ),
            (
                "encrypted",
                "history, data, undefined, 0x380000, 0x80000, encrypted",
                HistoryProblem::Encrypted,
            ),
            (
                "off a sector",
                "history, data, undefined, 0x380800, 0x7f000,",
                HistoryProblem::Unaligned,
            ),
            (
                "not whole sectors",
                "history, data, undefined, 0x380000, 0x7f800,",
                HistoryProblem::Unaligned,
            ),
            (
                "too small",
                "history, data, undefined, 0x3f1000, 0xf000,",
                HistoryProblem::TooSmall,
            ),
            (
                "over the table",
                "history, data, undefined, 0x0, 0x10000,",
                HistoryProblem::OverlapsTable,
            ),
            (
                "over the bootloader",
                "history, data, undefined, 0x7000, 0x10000,",
                HistoryProblem::OverlapsTable,
            ),
            (
                "over ota_1's end",
                "history, data, undefined, 0x370000, 0x80000,",
                HistoryProblem::OverlapsApp,
            ),
            (
                "over ota_0",
                "history, data, undefined, 0x20000, 0x10000,",
                HistoryProblem::OverlapsApp,
            ),
            (
                "over the store",
                "history, data, undefined, 0x9000, 0x10000,",
                HistoryProblem::OverlapsData,
            ),
            (
                "over the store and ota_0",
                "history, data, undefined, 0x9000, 0x20000,",
                HistoryProblem::OverlapsApp,
            ),
            (
                "past 4 MiB",
                "history, data, undefined, 0x3c0000, 0x80000,",
                HistoryProblem::BeyondFlash,
            ),
            (
                "past the address space",
                "history, data, undefined, 0xfffff000, 0x10000,",
                HistoryProblem::BeyondFlash,
            ),
        ];
        for (what, line, problem) in cases {
            let bytes = with_history(line);
            let t = Table::parse(&bytes).unwrap();
            assert_eq!(history(&t, MIB4), Err(problem), "{what}");
        }
        // The smallest, at the flash's end: taken.
        let t = with_history("history, data, undefined, 0x3f0000, 0x10000,");
        assert_eq!(
            history(&Table::parse(&t).unwrap(), MIB4),
            Ok(0x3f_0000..0x40_0000)
        );
        let all = [
            HistoryProblem::Missing,
            HistoryProblem::Encrypted,
            HistoryProblem::Unaligned,
            HistoryProblem::TooSmall,
            HistoryProblem::OverlapsTable,
            HistoryProblem::OverlapsApp,
            HistoryProblem::OverlapsData,
            HistoryProblem::BeyondFlash,
        ];
        for (i, p) in all.iter().enumerate() {
            assert!(p.reason().starts_with("th"), "{p:?}");
            assert!(all[..i].iter().all(|q| q.reason() != p.reason()), "{p:?}");
        }
    }
}
