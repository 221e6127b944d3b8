//! Where the chip finds its configuration store: the partition table read from
//! the flash's own bytes (`tinybms_firmware::partitions`), the `nvs` partition
//! checked, the store opened on the whole flash (`config::site::open`, the
//! function the chip calls at boot) — against tables as espflash writes them
//! (`esp-idf-part`, the crate espflash uses), against tables with other
//! labels, subtypes, an encrypted flag or a bad MD5, and against the merged
//! images CI makes (`TINYBMS_IMAGES=DIR`: every `tinybms-*.bin` there that is
//! a merged image; `TINYBMS_IMAGES_REQUIRED=1` fails when there is none).
//!
//! End to end: a record saved through the lookup, the flash's bytes kept, the
//! "restarted" bridge finding the same record through the same lookup.
//!
//! The history partition (issue 55) the same way: found by the chip's lookup
//! (`partitions::history`) in the bytes espflash writes for
//! `firmware/partitions.csv` and in every merged image CI makes, clear of the
//! store; and absent, in words, from the table bridges installed before it
//! keep (`firmware/partitions-pre-history.csv`).

use embassy_futures::block_on;
use esp_idf_part::PartitionTable;
use tinybms_desk::flash::RamFlash;
use tinybms_firmware::config::site::{self, Opened};
use tinybms_firmware::config::store::{Saved, SiteProblem, Source, StoreError};
use tinybms_firmware::config::Config;
use tinybms_firmware::partitions::{
    self, Checksum, HistoryProblem, Table, TableError, TABLE_MAX, TABLE_OFFSET,
};

const MIB4: usize = 4 * 1024 * 1024;

/// espflash's default table for a 4 MiB chip (what every image of this
/// project carries): nvs, phy_init, factory.
const DEFAULT_CSV: &str = "\
# Name,   Type, SubType, Offset,  Size,    Flags
nvs,      data, nvs,     0x9000,  0x6000,
phy_init, data, phy,     0xf000,  0x1000,
factory,  app,  factory, 0x10000, 0x3f0000,
";

/// Every image's table.
const PARTITIONS_CSV: &str = include_str!("../../firmware/partitions.csv");
/// The table of every bridge installed before the history partition.
const PRE_HISTORY_CSV: &str = include_str!("../../firmware/partitions-pre-history.csv");
/// Where every image's history partition is.
const HISTORY: std::ops::Range<u32> = 0x38_0000..0x40_0000;

fn table_bin(csv: &str) -> Vec<u8> {
    let t = PartitionTable::try_from_str(csv).expect("a valid table");
    t.to_bin().expect("table bytes")
}

/// An erased 4 MiB chip with `table` at its offset.
fn chip_with(table: &[u8]) -> Vec<u8> {
    let mut flash = vec![0xFF; MIB4];
    let at = TABLE_OFFSET as usize;
    flash[at..at + table.len()].copy_from_slice(table);
    flash
}

fn open(flash: &RamFlash, bytes: u32) -> Opened<RamFlash> {
    block_on(site::open(flash.clone(), bytes, false))
}

#[test]
fn espflashs_default_table_gives_the_store_at_0x9000() {
    let bin = table_bin(DEFAULT_CSV);
    let t = Table::parse(&bin).unwrap();
    assert_eq!(t.checksum(), Checksum::Verified);
    assert_eq!(t.entries().count(), 3);
    let flash = RamFlash::from_bytes(chip_with(&bin));
    let o = open(&flash, MIB4 as u32);
    assert_eq!(o.site.partition, Some((0x9000, 0x6000)));
    assert_eq!(o.site.problem(), None);
    assert_eq!(
        o.loaded.source,
        Source::Empty,
        "an erased partition: the defaults"
    );
    assert!(o.store.is_some());
}

#[test]
fn a_record_survives_a_restart_through_the_chips_lookup() {
    let flash = RamFlash::from_bytes(chip_with(&table_bin(DEFAULT_CSV)));
    let mut o = open(&flash, MIB4 as u32);
    let mut record = Config {
        stream_period_ms: 2000,
        ..Config::default()
    };
    record.charge_current_cap_da = 500;
    let store = o.store.as_mut().unwrap();
    assert_eq!(block_on(store.save(&record)), Ok(Saved::Written));
    drop(o);
    // The restarted chip: the same bytes, a new lookup.
    let again = open(&flash.copy(), MIB4 as u32);
    assert_eq!(again.loaded.source, Source::Flash);
    assert_eq!(again.loaded.config, record);
    // Only the nvs partition was written.
    let before = chip_with(&table_bin(DEFAULT_CSV));
    let after = flash.lock().clone();
    let changed: Vec<usize> = (0..MIB4 / 4096)
        .filter(|s| before[s * 4096..][..4096] != after[s * 4096..][..4096])
        .collect();
    assert!(!changed.is_empty());
    assert!(
        changed.iter().all(|s| (0x9..0xF).contains(s)),
        "sectors written outside nvs: {changed:?}"
    );
}

#[test]
fn tables_without_a_usable_nvs_partition_say_why_and_leave_flash_alone() {
    let cases: [(&str, String, Option<SiteProblem>); 7] = [
        (
            "another label",
            DEFAULT_CSV.replace("nvs,      data", "config,   data"),
            Some(SiteProblem::NoPartition),
        ),
        (
            "a longer label that starts with nvs",
            DEFAULT_CSV.replace("nvs,      data", "nvs_keys2, data"),
            Some(SiteProblem::NoPartition),
        ),
        (
            "the label on another subtype",
            DEFAULT_CSV.replace("data, nvs,     0x9000", "data, fat,     0x9000"),
            Some(SiteProblem::NoPartition),
        ),
        (
            "encrypted",
            DEFAULT_CSV.replace("0x6000,", "0x6000, encrypted"),
            Some(SiteProblem::Encrypted),
        ),
        (
            "read-only but plain: still the store",
            DEFAULT_CSV.replace("0x6000,", "0x6000, readonly"),
            None,
        ),
        (
            "too small",
            DEFAULT_CSV.replace("0x9000,  0x6000", "0x9000,  0x1000"),
            Some(SiteProblem::TooSmall),
        ),
        (
            "the nvs partition moved, with a custom partition before it",
            "\
fact,     0x40, 0x01,    0x9000,  0x1000,
phy_init, data, phy,     0xa000,  0x1000,
nvs,      data, nvs,     0xb000,  0x5000,
factory,  app,  factory, 0x10000, 0x3f0000,
"
            .to_string(),
            None,
        ),
    ];
    for (what, csv, problem) in cases {
        let bin = table_bin(&csv);
        let bytes = chip_with(&bin);
        let flash = RamFlash::from_bytes(bytes.clone());
        let o = open(&flash, MIB4 as u32);
        assert_eq!(o.site.problem(), problem, "{what}");
        assert_eq!(o.store.is_some(), problem.is_none(), "{what}");
        if problem.is_some() {
            assert_eq!(
                o.loaded.source,
                Source::Unreadable(StoreError::Partition),
                "{what}"
            );
        }
        assert!(*flash.lock() == bytes, "{what}: opening wrote flash");
    }
}

/// A table with a data subtype no tool here knows (espflash's crate cannot
/// write one): its bytes patched, its MD5 made anew. The nvs partition after
/// it is still found; the same label on that subtype is not the store.
#[test]
fn a_subtype_nobody_knows_is_read_past() {
    use md5::{Digest, Md5};
    let reseal = |bin: &mut Vec<u8>, entries: usize| {
        let digest: [u8; 16] = Md5::digest(&bin[..entries * 32]).into();
        bin[entries * 32 + 16..entries * 32 + 32].copy_from_slice(&digest);
    };
    let csv = "\
phy_init, data, phy,     0x9000,  0x1000,
nvs,      data, nvs,     0xa000,  0x6000,
factory,  app,  factory, 0x10000, 0x3f0000,
";
    let mut bin = table_bin(csv);
    bin[3] = 0x40; // phy_init's subtype
    reseal(&mut bin, 3);
    let t = Table::parse(&bin).unwrap();
    assert_eq!(t.entries().next().unwrap().subtype, 0x40);
    let o = open(&RamFlash::from_bytes(chip_with(&bin)), MIB4 as u32);
    assert_eq!(o.site.partition, Some((0xa000, 0x6000)));
    assert_eq!(o.site.problem(), None);
    let mut bin = table_bin(csv);
    bin[32 + 3] = 0x40; // nvs's subtype
    reseal(&mut bin, 3);
    let o = open(&RamFlash::from_bytes(chip_with(&bin)), MIB4 as u32);
    assert_eq!(o.site.problem(), Some(SiteProblem::NoPartition));
}

#[test]
fn a_damaged_or_missing_table_is_named_not_guessed() {
    // A bad MD5: one bit of the digest.
    let mut bin = table_bin(DEFAULT_CSV);
    bin[3 * 32 + 16] ^= 0x01;
    let o = open(&RamFlash::from_bytes(chip_with(&bin)), MIB4 as u32);
    assert_eq!(
        o.site.problem(),
        Some(SiteProblem::Table(TableError::Checksum))
    );
    assert!(o.store.is_none());
    // An entry changed under a good MD5: the same.
    let mut bin = table_bin(DEFAULT_CSV);
    bin[4] ^= 0x10;
    let o = open(&RamFlash::from_bytes(chip_with(&bin)), MIB4 as u32);
    assert_eq!(
        o.site.problem(),
        Some(SiteProblem::Table(TableError::Checksum))
    );
    // No MD5 entry at all (ESP-IDF's --disable-md5sum): read, and said.
    let mut bin = table_bin(DEFAULT_CSV);
    bin[3 * 32..4 * 32].fill(0xFF);
    assert_eq!(Table::parse(&bin).unwrap().checksum(), Checksum::Absent);
    let o = open(&RamFlash::from_bytes(chip_with(&bin)), MIB4 as u32);
    assert_eq!(o.site.problem(), None);
    // An erased chip, a chip of zeros.
    for fill in [0xFF, 0x00] {
        let o = open(&RamFlash::from_bytes(vec![fill; MIB4]), MIB4 as u32);
        assert_eq!(
            o.site.problem(),
            Some(SiteProblem::Table(TableError::Missing))
        );
    }
    // A flash too short to hold a table cannot be read there.
    let o = open(&RamFlash::from_bytes(vec![0xFF; 0x8000]), 0x8000);
    assert_eq!(o.site.problem(), Some(SiteProblem::FlashRead));
    // Flash encryption on: refused before anything is read.
    let o = block_on(site::open(
        RamFlash::from_bytes(chip_with(&table_bin(DEFAULT_CSV))),
        MIB4 as u32,
        true,
    ));
    assert_eq!(o.site.problem(), Some(SiteProblem::FlashEncryption));
}

#[test]
fn the_flash_size_the_chip_reports_bounds_the_partition() {
    let flash = RamFlash::from_bytes(chip_with(&table_bin(DEFAULT_CSV)));
    // The emulator's flash answered no read-ID: 0 bytes reported.
    let o = open(&flash, 0);
    assert_eq!(o.site.problem(), Some(SiteProblem::BeyondFlash));
    assert!(o.store.is_none());
}

/// espflash's library (what packs every image) takes the history's subtype
/// by its name, `undefined`, and writes ESP-IDF's number for it, 0x06.
#[test]
fn espflash_writes_the_history_partition_as_data_undefined() {
    use esp_idf_part::{DataType, SubType, Type};
    let t = PartitionTable::try_from_str(PARTITIONS_CSV).expect("espflash takes the table");
    let p = t
        .find(partitions::HISTORY_LABEL)
        .expect("a history partition");
    assert_eq!(p.ty(), Type::Data);
    assert_eq!(p.subtype(), SubType::Data(DataType::Undefined));
    let bin = table_bin(PARTITIONS_CSV);
    let at = t.partitions().iter().position(|q| q == p).unwrap() * 32;
    assert_eq!(
        (bin[at + 2], bin[at + 3]),
        (partitions::HISTORY_TYPE, partitions::HISTORY_SUBTYPE)
    );
    assert_eq!(partitions::HISTORY_SUBTYPE, 0x06);
}

/// The table of every image, in espflash's bytes: the store at 0x9000 and the
/// history in the last 512 KiB, both found by the chip's lookups; a record
/// saved leaves the history's sectors erased.
#[test]
fn every_images_table_gives_the_store_and_the_history() {
    let bin = table_bin(PARTITIONS_CSV);
    let t = Table::parse(&bin).unwrap();
    assert_eq!(t.checksum(), Checksum::Verified);
    assert_eq!(partitions::history(&t, MIB4 as u32), Ok(HISTORY));
    let flash = RamFlash::from_bytes(chip_with(&bin));
    let mut o = open(&flash, MIB4 as u32);
    assert_eq!(o.site.problem(), None);
    assert_eq!(o.site.partition, Some((0x9000, 0x6000)));
    let record = Config {
        stream_period_ms: 2000,
        ..Config::default()
    };
    block_on(o.store.as_mut().unwrap().save(&record)).unwrap();
    let bytes = flash.lock().clone();
    assert!(bytes[HISTORY.start as usize..HISTORY.end as usize]
        .iter()
        .all(|&b| b == 0xFF));
}

/// The table bridges installed before the history partition keep through
/// updates over the network: the store where it always was, no history, and
/// the words send the owner to one reinstall by cable.
#[test]
fn the_pre_history_table_gives_the_store_and_no_history() {
    let bin = table_bin(PRE_HISTORY_CSV);
    let t = Table::parse(&bin).unwrap();
    assert_eq!(
        partitions::history(&t, MIB4 as u32),
        Err(HistoryProblem::Missing)
    );
    let words = HistoryProblem::Missing.reason();
    assert!(
        words.contains("predates the history partition") && words.contains("reinstall by cable"),
        "{words}"
    );
    let o = open(&RamFlash::from_bytes(chip_with(&bin)), MIB4 as u32);
    assert_eq!(o.site.problem(), None);
    assert_eq!(o.site.partition, Some((0x9000, 0x6000)));
}

/// The merged images CI makes (`firmware/make-images.sh`): the table each one
/// carries is read by the chip's lookup, the store is where the docs say, and
/// a record saved on the image's bytes is found again.
#[test]
fn every_merged_image_ci_makes_carries_a_table_the_chip_finds_its_store_in() {
    let Ok(dir) = std::env::var("TINYBMS_IMAGES") else {
        assert!(
            std::env::var_os("TINYBMS_IMAGES_REQUIRED").is_none(),
            "TINYBMS_IMAGES_REQUIRED without TINYBMS_IMAGES"
        );
        eprintln!(
            "TINYBMS_IMAGES not set: the images' tables are checked in CI after make-images.sh"
        );
        return;
    };
    let mut merged = Vec::new();
    for e in std::fs::read_dir(&dir).expect("the images' folder") {
        let path = e.expect("an entry").path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if name.starts_with("tinybms-")
            && name.ends_with(".bin")
            && !name.ends_with("-app.bin")
            && !name.ends_with("-boot.bin")
            && !name.ends_with("-otadata.bin")
        {
            merged.push(path);
        }
    }
    merged.sort();
    if std::env::var_os("TINYBMS_IMAGES_REQUIRED").is_some() {
        assert!(!merged.is_empty(), "no merged image in {dir}");
    }
    for path in &merged {
        let image = std::fs::read(path).unwrap();
        let at = TABLE_OFFSET as usize;
        assert!(
            image.len() > at + TABLE_MAX,
            "{}: too short",
            path.display()
        );
        let table = Table::parse(&image[at..at + TABLE_MAX])
            .unwrap_or_else(|e| panic!("{}: {}", path.display(), e.reason()));
        assert_eq!(table.checksum(), Checksum::Verified, "{}", path.display());
        assert_eq!(
            partitions::history(&table, MIB4 as u32),
            Ok(HISTORY),
            "{}: the history partition",
            path.display()
        );
        let mut bytes = image.clone();
        assert!(bytes.len() <= MIB4);
        bytes.resize(MIB4, 0xFF);
        let flash = RamFlash::from_bytes(bytes);
        let mut o = open(&flash, MIB4 as u32);
        assert_eq!(o.site.problem(), None, "{}", path.display());
        assert_eq!(
            o.site.partition,
            Some((0x9000, 0x6000)),
            "{}",
            path.display()
        );
        let record = Config {
            stream_period_ms: 2000,
            ..Config::default()
        };
        block_on(o.store.as_mut().unwrap().save(&record)).unwrap();
        drop(o);
        let again = open(&flash.copy(), MIB4 as u32);
        assert_eq!(again.loaded.source, Source::Flash, "{}", path.display());
        assert_eq!(again.loaded.config.stream_period_ms, 2000);
        eprintln!(
            "{}: store at 0x9000 (24 KiB), found again after a restart; history at \
             0x380000 (512 KiB)",
            path.display()
        );
    }
    eprintln!("{} merged image(s) checked", merged.len());
}
