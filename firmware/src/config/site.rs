//! Where the configuration store lives, found and opened the one way the chip
//! and the host tests share: the partition table read from the flash itself
//! ([`crate::partitions`]), its `nvs` partition checked ([`StoreSite`]), the
//! [`Store`] opened on that range of the *whole* flash and the record loaded.
//!
//! The chip hands in its flash (esp-storage under `BlockingAsync`) and what it
//! knows of it; `host-tests/tests/store_site.rs` hands in the bytes of the
//! images CI makes, saves a record, and opens the same bytes again — a restart
//! through the chip's own lookup.

use embedded_storage_async::nor_flash::NorFlash;

use super::store::{Loaded, SiteProblem, Source, Store, StoreError, StoreSite};
use super::Config;
use crate::partitions::{Table, SUBTYPE_NVS, TABLE_MAX, TABLE_OFFSET, TYPE_DATA};

/// The store's partition: data, subtype nvs, this label (ESP-IDF's and
/// espflash's default table; the radio driver does not use it).
pub const STORE_LABEL: &str = "nvs";

/// What [`open`] found.
pub struct Opened<F: NorFlash> {
    /// The store, when the site can hold one (else changes live in RAM only).
    pub store: Option<Store<F>>,
    /// The record the bridge starts with, and where it came from.
    pub loaded: Loaded,
    /// Where the store is (or why there is none): the log and `hello` say it.
    pub site: StoreSite,
}

/// Finds the store on `flash` (the whole chip: the partition table is read at
/// its offset) and loads the record. Never fails: without a usable site the
/// bridge runs with the defaults and the site says why.
///
/// `flash_bytes` is what the chip reports of its flash; `flash_encryption`
/// whether the chip encrypts it (the record would be written plain: refused).
pub async fn open<F: NorFlash>(
    mut flash: F,
    flash_bytes: u32,
    flash_encryption: bool,
) -> Opened<F> {
    let mut site = StoreSite {
        flash_bytes,
        partition: None,
        lookup: None,
    };
    if flash_encryption {
        site.lookup = Some(SiteProblem::FlashEncryption);
    } else {
        let mut table = [0u8; TABLE_MAX];
        if flash.read(TABLE_OFFSET, &mut table).await.is_err() {
            site.lookup = Some(SiteProblem::FlashRead);
        } else {
            match Table::parse(&table) {
                Err(e) => site.lookup = Some(SiteProblem::Table(e)),
                Ok(t) => {
                    if let Some(e) = t.find(TYPE_DATA, SUBTYPE_NVS, STORE_LABEL) {
                        site.partition = Some((e.offset, e.size));
                        if e.encrypted() {
                            site.lookup = Some(SiteProblem::Encrypted);
                        }
                    }
                }
            }
        }
    }
    let range = match (site.problem(), site.partition) {
        (None, Some((offset, size))) => offset..offset.saturating_add(size),
        _ => return unusable(site, StoreError::Partition),
    };
    match Store::new(flash, range) {
        Ok(mut store) => {
            let loaded = store.load().await;
            Opened {
                store: Some(store),
                loaded,
                site,
            }
        }
        Err(e) => unusable(site, e),
    }
}

fn unusable<F: NorFlash>(site: StoreSite, e: StoreError) -> Opened<F> {
    Opened {
        store: None,
        loaded: Loaded {
            config: Config::default(),
            source: Source::Unreadable(e),
        },
        site,
    }
}
