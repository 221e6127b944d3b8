//! The record in flash, through `sequential-storage`'s map: one key, the
//! encoded record ([`super::codec`]) as its value.
//!
//! `sequential-storage` appends each new version of an item after the last and
//! marks the old one erased only afterwards; every item carries a CRC, and
//! after a cut it repairs the page states on the next access. So a write cut at
//! any point leaves either the old record or the new one readable — never a
//! mixture (host-tests/tests/config_store.rs cuts the power after every byte
//! of several saves on `sequential-storage`'s mock flash and checks just that).
//!
//! [`Store::save`] writes only when the record differs from the one in flash,
//! and reads the new one back before it reports success.
//!
//! The flash is any `embedded-storage-async` `NorFlash`: on the chip the
//! default partition table's `nvs` partition (24 KiB, 6 pages; esp-radio does
//! not use it) through `esp-storage` and `embassy-embedded-hal`'s
//! `BlockingAsync`; on the host `sequential-storage`'s mock flash or a file.
//!
//! **When to call `save` on the chip:** a flash erase or write stops the CPU's
//! cache for up to tens of milliseconds, while the UART's 128-byte FIFO fills in
//! 11 ms at 115 200 Bd. The bridge task saves only when
//! [`crate::Bridge::quiet`] says no BMS reply can be on its way, and sends no
//! request until the save is done (see [`super::state`]).

use core::ops::Range;

use embedded_storage_async::nor_flash::NorFlash;
use sequential_storage::cache::Cache;
use sequential_storage::map::{MapConfig, MapStorage};

use super::codec::{self, DecodeError, RECORD_MAX};
use super::Config;

/// The map key of the record.
const RECORD_KEY: u8 = 1;

/// The working buffer: a record, its key and item header, rounded up to the
/// flash word (4 bytes), 4-byte aligned as the ESP flash ROM wants it.
#[repr(C, align(4))]
struct Buffer([u8; RECORD_MAX + 32]);

type Uncached = Cache<
    sequential_storage::cache::Uncached,
    sequential_storage::cache::Uncached,
    sequential_storage::cache::Uncached,
    u8,
>;

/// A flash sector (the unit the store erases), bytes.
pub const SECTOR_BYTES: u32 = 4096;
/// What the store needs at least: two sectors (sequential-storage's map
/// always keeps one erased), bytes.
pub const STORE_MIN_BYTES: u32 = 2 * SECTOR_BYTES;

/// Where the store lives and what the chip says it has: named in the log and
/// in `hello`, so that an owner whose store fails can tell why (no partition
/// table, one whose checksum fails, a table without `nvs`, a partition marked
/// encrypted, too small or not on sector boundaries, a flash smaller than the
/// table says). Found by [`super::site::open`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StoreSite {
    /// The flash size the chip reports (the flash's answer to its read-ID
    /// command), bytes; 0: no answer.
    pub flash_bytes: u32,
    /// The `nvs` partition found: offset and size, bytes (`None`: none found).
    pub partition: Option<(u32, u32)>,
    /// What the lookup itself ran into before the partition's size was looked
    /// at (the table could not be read, the partition is marked encrypted).
    pub lookup: Option<SiteProblem>,
}

/// Why a [`StoreSite`] cannot hold the store.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SiteProblem {
    /// The flash could not be read where the partition table is.
    FlashRead,
    /// The chip encrypts its flash (not supported: the record is written plain).
    FlashEncryption,
    /// The partition table is missing or not valid.
    Table(crate::partitions::TableError),
    /// The partition table has no `nvs` partition.
    NoPartition,
    /// The `nvs` partition is marked encrypted.
    Encrypted,
    /// Fewer than [`STORE_MIN_BYTES`].
    TooSmall,
    /// Not on [`SECTOR_BYTES`] boundaries.
    NotAligned,
    /// It ends past the flash the chip reports.
    BeyondFlash,
}

impl SiteProblem {
    /// In words.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::FlashRead => "the flash cannot be read at the partition table",
            Self::FlashEncryption => "flash encryption is on (not supported)",
            Self::Table(e) => e.reason(),
            Self::NoPartition => "no `nvs` partition in the partition table",
            Self::Encrypted => "the `nvs` partition is marked encrypted (not supported)",
            Self::TooSmall => "the `nvs` partition is smaller than the store needs",
            Self::NotAligned => "the `nvs` partition is not on 4 KiB sector boundaries",
            Self::BeyondFlash => "the `nvs` partition ends past the flash the chip reports",
        }
    }
}

impl StoreSite {
    /// Why the store cannot live here, if it cannot.
    pub fn problem(&self) -> Option<SiteProblem> {
        if let Some(p) = self.lookup {
            return Some(p);
        }
        let Some((offset, size)) = self.partition else {
            return Some(SiteProblem::NoPartition);
        };
        if size < STORE_MIN_BYTES {
            Some(SiteProblem::TooSmall)
        } else if offset % SECTOR_BYTES != 0 || size % SECTOR_BYTES != 0 {
            Some(SiteProblem::NotAligned)
        } else if u64::from(offset) + u64::from(size) > u64::from(self.flash_bytes) {
            Some(SiteProblem::BeyondFlash)
        } else {
            None
        }
    }
}

/// Why the store could not do what was asked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StoreError {
    /// The partition is not usable for a store (alignment, fewer than 2 pages).
    Partition,
    /// The flash driver failed.
    Flash,
    /// The storage is full (cannot happen with one key of at most a page).
    Full,
    /// The storage's own structure is broken beyond its repair.
    Corrupted,
    /// What was read back after a write is not what was written.
    Verify,
    /// Anything else `sequential-storage` reported.
    Other,
}

impl StoreError {
    /// In a few words.
    pub const fn reason(&self) -> &'static str {
        match self {
            Self::Partition => "the partition cannot hold a store",
            Self::Flash => "flash driver error",
            Self::Full => "storage full",
            Self::Corrupted => "storage corrupted",
            Self::Verify => "read back differs from what was written",
            Self::Other => "storage error",
        }
    }
}

fn store_error<E>(e: sequential_storage::Error<E>) -> StoreError {
    match e {
        sequential_storage::Error::Storage { .. } => StoreError::Flash,
        sequential_storage::Error::FullStorage => StoreError::Full,
        sequential_storage::Error::Corrupted { .. } => StoreError::Corrupted,
        _ => StoreError::Other,
    }
}

/// Where the record the bridge started with came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Source {
    /// The record in flash.
    Flash,
    /// Nothing stored yet (a new or erased chip): the defaults.
    Empty,
    /// A stored record that is not a valid record of this version: the defaults.
    Invalid(DecodeError),
    /// The store could not be read: the defaults.
    Unreadable(StoreError),
}

impl Source {
    /// As printed (`flash`, `defaults`, `defaults: …`).
    pub const fn name(&self) -> &'static str {
        match self {
            Self::Flash => "flash",
            Self::Empty => "defaults",
            Self::Invalid(_) => "defaults (the stored record is not valid)",
            Self::Unreadable(_) => "defaults (the store cannot be read)",
        }
    }
}

/// The record loaded at start-up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Loaded {
    /// What the bridge runs with.
    pub config: Config,
    /// Where it came from.
    pub source: Source,
}

/// What [`Store::save`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Saved {
    /// Flash already held this record: nothing written.
    Unchanged,
    /// Written and read back equal.
    Written,
}

/// The record's store on a flash range.
pub struct Store<S: NorFlash> {
    map: MapStorage<u8, S, Uncached>,
    buf: Buffer,
    /// The record flash holds, as far as this store knows (`None`: unknown or
    /// none).
    in_flash: Option<Config>,
}

impl<S: NorFlash> Store<S> {
    /// A store on `range` of `flash` (whole pages, at least two).
    pub fn new(flash: S, range: Range<u32>) -> Result<Self, StoreError> {
        let config = MapConfig::try_new(range).map_err(|_| StoreError::Partition)?;
        Ok(Self {
            map: MapStorage::new(flash, config, Cache::new_uncached()),
            buf: Buffer([0; RECORD_MAX + 32]),
            in_flash: None,
        })
    }

    /// The flash back (to read its state in tests, or to reuse it).
    pub fn into_flash(self) -> S {
        self.map.destroy().0
    }

    /// Reads the record. Never fails: anything but a valid record of this
    /// version gives the defaults, and says why.
    pub async fn load(&mut self) -> Loaded {
        let fetched = self
            .map
            .fetch_item::<&[u8]>(&mut self.buf.0, &RECORD_KEY)
            .await;
        let (config, source) = match fetched {
            Ok(Some(bytes)) => match codec::decode(bytes) {
                Ok(c) => (c, Source::Flash),
                Err(e) => (Config::default(), Source::Invalid(e)),
            },
            Ok(None) => (Config::default(), Source::Empty),
            Err(e) => (Config::default(), Source::Unreadable(store_error(e))),
        };
        self.in_flash = (source == Source::Flash).then(|| config.clone());
        Loaded { config, source }
    }

    /// Stores `config` unless flash already holds it; then reads it back.
    pub async fn save(&mut self, config: &Config) -> Result<Saved, StoreError> {
        if self.in_flash.as_ref() == Some(config) {
            return Ok(Saved::Unchanged);
        }
        let mut record = [0u8; RECORD_MAX];
        let len = codec::encode(config, &mut record).ok_or(StoreError::Other)?;
        let bytes = record.get(..len).ok_or(StoreError::Other)?;
        let stored = self
            .map
            .store_item(&mut self.buf.0, &RECORD_KEY, &bytes)
            .await;
        match stored {
            Ok(()) => {}
            // Broken beyond repair (the record in it was unreadable anyway):
            // start the store afresh, once.
            Err(sequential_storage::Error::Corrupted { .. }) => {
                self.in_flash = None;
                self.map.erase_all().await.map_err(store_error)?;
                self.map
                    .store_item(&mut self.buf.0, &RECORD_KEY, &bytes)
                    .await
                    .map_err(store_error)?;
            }
            Err(e) => {
                self.in_flash = None;
                return Err(store_error(e));
            }
        }
        self.in_flash = None;
        let back = self
            .map
            .fetch_item::<&[u8]>(&mut self.buf.0, &RECORD_KEY)
            .await
            .map_err(store_error)?;
        if back != Some(bytes) {
            return Err(StoreError::Verify);
        }
        self.in_flash = Some(config.clone());
        Ok(Saved::Written)
    }

    /// Erases the whole store (the next start-up runs with the defaults).
    pub async fn erase(&mut self) -> Result<(), StoreError> {
        self.in_flash = None;
        self.map.erase_all().await.map_err(store_error)
    }
}
