//! The configuration store on the chip: the flash through `esp-storage` and
//! `embassy-embedded-hal`'s `BlockingAsync` adapter, handed to the library's
//! `config::site::open`, which reads the partition table, finds the `nvs`
//! partition (0x9000, 24 KiB in espflash's and ESP-IDF's default table;
//! esp-radio does not use it) and opens the `config::store::Store` on it.
//!
//! Everything about the record — where it lives, its codec, power-loss
//! safety, when it may be written — is the library's (tested on the host,
//! against the tables of the images CI makes); this file hands over the flash.
//!
//! Only with something to configure (feature `store`, implied by `can` and
//! `host-link`); a bridge-only image runs with the defaults and links none of it.

#[cfg(not(feature = "store"))]
pub use off::*;
#[cfg(feature = "store")]
pub use on::*;

#[cfg(feature = "store")]
mod on {
    use defmt::warn;
    use embassy_embedded_hal::adapter::BlockingAsync;
    use esp_hal::peripherals::FLASH;
    use esp_storage::FlashStorage;
    use tinybms_firmware::config::site;
    use tinybms_firmware::config::store::{Loaded, Saved, Store, StoreError, StoreSite};
    use tinybms_firmware::config::Config;

    /// The flash the store works on: the whole chip (the library finds the
    /// partition in the partition table and keeps to its range).
    pub type Flash = BlockingAsync<FlashStorage<'static>>;

    /// The store on the chip.
    pub type ChipStore = Store<Flash>;

    /// Opens the store and loads the record (`tinybms_firmware::config::site`:
    /// the table's lookup, the checks, the defaults and why). Without a usable
    /// partition the bridge runs with the defaults and changes are kept in RAM
    /// only.
    ///
    /// Not `async`: the flash under `BlockingAsync` never makes a future wait, so
    /// the lookup and the load are driven to completion here on the stack (an
    /// `async fn` would keep the 3 KiB table buffer and the load's state in the
    /// main task's static future for good).
    pub fn open(flash: FLASH<'static>) -> (Option<Store<Flash>>, Loaded, StoreSite) {
        let storage = FlashStorage::new(flash);
        // What the flash says of its size (its read-ID answer): named in the
        // log and `hello` with the partition, so a failing store says why.
        let flash_bytes = u32::try_from(storage.capacity()).unwrap_or(u32::MAX);
        let opened = embassy_futures::block_on(site::open(
            BlockingAsync::new(storage),
            flash_bytes,
            esp_storage::flash_encryption(),
        ));
        if let Some(p) = opened.site.problem() {
            warn!("configuration in RAM only: {=str}", p.reason());
        }
        (opened.store, opened.loaded, opened.site)
    }

    /// Writes the record (when the station says so: the BMS link is quiet),
    /// driven to completion here: `BlockingAsync` never waits, and its state
    /// stays on the stack instead of in the station task's static future.
    /// Without a store the save fails at once (the change holds in RAM).
    pub fn save(store: &mut Option<Store<Flash>>, record: &Config) -> Result<Saved, StoreError> {
        match store.as_mut() {
            Some(s) => embassy_futures::block_on(s.save(record)),
            None => Err(StoreError::Partition),
        }
    }
}

/// Without anything to configure: the defaults, no flash code.
#[cfg(not(feature = "store"))]
mod off {
    use esp_hal::peripherals::FLASH;
    use tinybms_firmware::config::store::{Loaded, Saved, Source, StoreError};
    use tinybms_firmware::config::Config;

    /// No store.
    pub enum ChipStore {}

    /// The defaults (and no site: nothing is stored).
    pub fn open(_: FLASH<'static>) -> (Option<ChipStore>, Loaded, Option<()>) {
        (
            None,
            Loaded {
                config: Config::default(),
                source: Source::Empty,
            },
            None,
        )
    }

    /// Nothing changes the record without the host link (never called).
    pub fn save(_: &mut Option<ChipStore>, _: &Config) -> Result<Saved, StoreError> {
        Err(StoreError::Partition)
    }
}
