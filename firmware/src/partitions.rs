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
}
