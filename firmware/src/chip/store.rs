//! The configuration store on the chip: the default partition table's `nvs`
//! partition (0x9000, 24 KiB: espflash's and ESP-IDF's default table; esp-radio
//! does not use it), through `esp-storage` and `embassy-embedded-hal`'s
//! `BlockingAsync` adapter into the library's `config::store::Store`.
//!
//! Everything about the record — its codec, power-loss safety, when it may be
//! written — is the library's (tested on the host); this file finds the
//! partition.
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
    use esp_bootloader_esp_idf::partitions::{self, FlashRegion, NorFlashRegion};
    use esp_hal::peripherals::FLASH;
    use esp_storage::FlashStorage;
    use static_cell::StaticCell;
    use tinybms_firmware::config::store::{Loaded, Saved, Source, Store, StoreError, StoreSite};
    use tinybms_firmware::config::Config;

    /// The flash the store works on.
    pub type Flash = BlockingAsync<NorFlashRegion<'static, 'static, 'static>>;

    /// The store on the chip.
    pub type ChipStore = Store<Flash>;

    /// Partition table entry of the store: type data (1), subtype nvs (2), label.
    const NVS_TYPE: u8 = 1;
    const NVS_SUBTYPE: u8 = 2;
    const NVS_LABEL: &[u8] = b"nvs";

    static STORAGE: StaticCell<FlashStorage<'static>> = StaticCell::new();
    static REGION: StaticCell<FlashRegion<'static, 'static>> = StaticCell::new();

    /// Opens the store and loads the record. Without a usable partition the bridge
    /// runs with the defaults (and says so) and changes are kept in RAM only.
    ///
    /// Not `async`: the flash under `BlockingAsync` never makes a future wait, so
    /// the load is driven to completion here on the stack (an `async fn` would
    /// keep the 3 KiB partition table buffer and the load's state in the main
    /// task's static future for good).
    pub fn open(flash: FLASH<'static>) -> (Option<Store<Flash>>, Loaded, StoreSite) {
        let storage = STORAGE.init(FlashStorage::new(flash));
        // What the flash says of its size (its read-ID answer): named in the
        // log and `hello` with the partition, so a failing store says why.
        let flash_bytes = u32::try_from(storage.capacity()).unwrap_or(u32::MAX);
        let mut site = StoreSite {
            flash_bytes,
            partition: None,
        };
        let entry = {
            let mut table = [0u8; partitions::PARTITION_TABLE_MAX_LEN];
            match partitions::read_partition_table(storage, &mut table) {
                // By raw type and label: `partition_type()` panics on a subtype
                // it does not know, and a custom table may have one.
                Ok(t) => t.iter().find(|e| {
                    e.raw_type() == NVS_TYPE
                        && e.raw_subtype() == NVS_SUBTYPE
                        && e.label() == NVS_LABEL
                }),
                Err(_) => None,
            }
        };
        let Some(entry) = entry else {
            warn!("no `nvs` partition in the partition table: configuration in RAM only");
            return (None, defaults(StoreError::Partition), site);
        };
        site.partition = Some((entry.offset(), entry.len()));
        if let Some(p) = site.problem() {
            warn!(
                "configuration in RAM only: {=str} (flash {=u32} KiB, nvs at {=u32:#x}, {=u32} bytes)",
                p.reason(),
                flash_bytes / 1024,
                entry.offset(),
                entry.len()
            );
            return (None, defaults(StoreError::Partition), site);
        }
        let region = REGION.init(entry.as_flash_region(storage));
        let Ok(nor) = region.as_nor_flash() else {
            warn!("the `nvs` partition is encrypted: configuration in RAM only");
            return (None, defaults(StoreError::Partition), site);
        };
        let len = entry.len();
        match Store::new(BlockingAsync::new(nor), 0..len) {
            Ok(mut store) => {
                let loaded = embassy_futures::block_on(store.load());
                (Some(store), loaded, site)
            }
            Err(e) => {
                warn!(
                    "the `nvs` partition cannot hold the store ({=u32} bytes)",
                    len
                );
                (None, defaults(e), site)
            }
        }
    }

    fn defaults(e: StoreError) -> Loaded {
        Loaded {
            config: Config::default(),
            source: Source::Unreadable(e),
        }
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
