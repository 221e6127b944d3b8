//! The configuration record in flash (`tinybms_firmware::config::store`) on
//! `sequential-storage`'s mock flash, laid out as the chip's `nvs` partition
//! (6 pages of 4 KiB, 4-byte words): load, save only on change, what a
//! corrupted or foreign store gives, and the power cut after every byte of a
//! save — old record or new, every time.

#![allow(clippy::field_reassign_with_default)]

use embassy_futures::block_on;
use sequential_storage::mock_flash::{MockFlashBase, WriteCountCheck};
use tinybms_firmware::config::codec::{self, RECORD_MAX};
use tinybms_firmware::config::store::{Saved, Source, Store};
use tinybms_firmware::config::{Config, VERSION};
use tinybms_firmware::inverter::Protocol;

/// The default partition table's `nvs`: 0x6000 bytes.
type Flash = MockFlashBase<6, 4, 1024>;
const RANGE: core::ops::Range<u32> = 0..0x6000;

fn flash() -> Flash {
    // NOR flash: bits only go from 1 to 0 between erases; any number of writes.
    Flash::new(WriteCountCheck::Disabled, None, true)
}

fn store(f: Flash) -> Store<Flash> {
    Store::new(f, RANGE).unwrap()
}

/// The `n`-th of a sequence of distinct valid records.
fn record(n: u32) -> Config {
    let mut c = Config::default();
    c.charge_current_cap_da = 10 + (n % 7000) as u16;
    c.stale_after_s = 1 + (n % 60) as u16;
    c.protocol = if n.is_multiple_of(2) {
        Protocol::Victron
    } else {
        Protocol::SmaSunnyIsland
    };
    if n.is_multiple_of(3) {
        c.mqtt_host.push_str("broker.lan").unwrap();
        c.wifi_ssid
            .push_str(&"w".repeat((n % 32) as usize))
            .unwrap();
    }
    c
}

#[test]
fn an_empty_store_gives_the_defaults() {
    let mut s = store(flash());
    let l = block_on(s.load());
    assert_eq!(l.source, Source::Empty);
    assert_eq!(l.config, Config::default());
}

#[test]
fn a_saved_record_is_there_after_a_restart() {
    let mut s = store(flash());
    block_on(s.load());
    assert_eq!(block_on(s.save(&record(1))), Ok(Saved::Written));
    let f = s.into_flash();
    let mut s = store(f);
    let l = block_on(s.load());
    assert_eq!(l.source, Source::Flash);
    assert_eq!(l.config, record(1));
}

#[test]
fn it_writes_only_on_change() {
    let mut s = store(flash());
    block_on(s.load());
    block_on(s.save(&record(1))).unwrap();
    let f = s.into_flash();
    let before = f.stats_snapshot();
    let mut s = store(f);
    block_on(s.load());
    for _ in 0..10 {
        assert_eq!(block_on(s.save(&record(1))), Ok(Saved::Unchanged));
    }
    let d = before.compare_to(s.into_flash().stats_snapshot());
    assert_eq!((d.writes, d.erases), (0, 0), "{d:?}");
}

#[test]
fn many_saves_wrap_around_the_pages() {
    let mut s = store(flash());
    block_on(s.load());
    for n in 0..200 {
        assert_eq!(block_on(s.save(&record(n))), Ok(Saved::Written), "save {n}");
    }
    let f = s.into_flash();
    let d = flash().stats_snapshot().compare_to(f.stats_snapshot());
    println!(
        "200 saves: {} erases, {} bytes written",
        d.erases, d.bytes_written
    );
    assert!(d.erases > 6, "the pages were reused");
    let mut s = store(f);
    assert_eq!(block_on(s.load()).config, record(199));
}

#[test]
fn garbage_in_flash_gives_the_defaults_and_a_store_that_still_saves() {
    for seed in 0..20u32 {
        let mut f = flash();
        let mut x = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
        for b in f.as_bytes_mut().iter_mut() {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            *b = x as u8;
        }
        let mut s = store(f);
        let l = block_on(s.load());
        assert_eq!(l.config, Config::default(), "seed {seed}");
        assert_ne!(l.source, Source::Flash, "seed {seed}");
        assert_eq!(
            block_on(s.save(&record(seed))),
            Ok(Saved::Written),
            "seed {seed}"
        );
        let mut s = store(s.into_flash());
        let l = block_on(s.load());
        assert_eq!(
            (l.source, l.config),
            (Source::Flash, record(seed)),
            "seed {seed}"
        );
    }
}

/// Stores raw bytes under the record's key, as another firmware might have.
fn store_raw(bytes: &[u8]) -> Flash {
    use sequential_storage::cache::Cache;
    use sequential_storage::map::{MapConfig, MapStorage};
    let mut map =
        MapStorage::<u8, _, _>::new(flash(), MapConfig::new(RANGE), Cache::new_uncached());
    #[repr(align(4))]
    struct B([u8; RECORD_MAX + 32]);
    let mut buf = B([0; RECORD_MAX + 32]);
    block_on(map.store_item(&mut buf.0, &1u8, &bytes)).unwrap();
    map.destroy().0
}

#[test]
fn a_record_of_another_version_gives_the_defaults() {
    let mut bytes = [0u8; RECORD_MAX];
    let n = codec::encode(&record(3), &mut bytes).unwrap();
    bytes[2] = VERSION + 1;
    let mut s = store(store_raw(&bytes[..n]));
    let l = block_on(s.load());
    assert_eq!(l.config, Config::default());
    assert_eq!(
        l.source,
        Source::Invalid(codec::DecodeError::Version(VERSION + 1))
    );
    // Saving over it works, and the next start-up has the new record.
    block_on(s.save(&record(4))).unwrap();
    let mut s = store(s.into_flash());
    assert_eq!(block_on(s.load()).config, record(4));
}

/// Cuts the power after every byte written or erased by one save of `new`
/// over a store holding `old` (after `history` earlier saves): each time the
/// next start-up finds `old` or `new`, never anything else, and saves again.
/// Returns the number of cut points tried.
fn cut_everywhere(history: u32) -> u64 {
    let mut f = flash();
    let mut s = store(f.clone());
    block_on(s.load());
    for n in 0..history {
        block_on(s.save(&record(n))).unwrap();
    }
    f = s.into_flash();
    let old = (history > 0).then(|| record(history - 1));
    let new = record(history + 1000);
    let mut cuts = 0u64;
    let mut saw_old = 0u64;
    let mut saw_new = 0u64;
    for cut in 0.. {
        let mut g = f.clone();
        g.bytes_until_shutoff = Some(cut);
        let mut s = store(g);
        // Nothing of the save may reach the flash before the load: a store
        // always starts with a load.
        block_on(s.load());
        let result = block_on(s.save(&new));
        let mut g = s.into_flash();
        let finished = g.bytes_until_shutoff.is_some();
        g.bytes_until_shutoff = None;
        // Restart: what is there?
        let mut s = store(g);
        let l = block_on(s.load());
        match &old {
            Some(o) if l.config == *o => saw_old += 1,
            None if l.source == Source::Empty || l.config == Config::default() => saw_old += 1,
            _ if l.config == new => saw_new += 1,
            _ => panic!(
                "history {history}, cut after {cut} bytes: neither old nor new: {:?}",
                l.source
            ),
        }
        if l.config == new {
            assert_eq!(l.source, Source::Flash);
        }
        // And the store is usable: the next save lands and reads back.
        let again = record(history + 2000);
        assert_eq!(
            block_on(s.save(&again)),
            Ok(Saved::Written),
            "history {history}, cut {cut}: the store did not recover"
        );
        let mut s = store(s.into_flash());
        assert_eq!(block_on(s.load()).config, again);
        cuts += 1;
        if finished {
            assert_eq!(result, Ok(Saved::Written));
            break;
        }
    }
    assert!(saw_new > 0 && (saw_old > 0 || history == 0));
    println!("history {history}: {cuts} cut points, old {saw_old}, new {saw_new}");
    cuts
}

#[test]
fn a_power_cut_during_the_first_save_leaves_nothing_or_the_new_record() {
    cut_everywhere(0);
}

/// The saves (by how many came before) that erase a page to make room: the
/// interesting ones for a power cut.
fn erasing_saves(limit: u32) -> Vec<u32> {
    let mut s = store(flash());
    block_on(s.load());
    let mut out = Vec::new();
    let mut f = s.into_flash();
    for n in 0..limit {
        let before = f.stats_snapshot();
        let mut s = store(f);
        block_on(s.load());
        block_on(s.save(&record(n))).unwrap();
        f = s.into_flash();
        if before.compare_to(f.stats_snapshot()).erases > 0 {
            out.push(n);
        }
    }
    out
}

#[test]
fn a_power_cut_during_a_save_leaves_the_old_record_or_the_new() {
    // 1: a page with room; then the first two saves that erase a page to make
    // room (every byte of the erase is a cut point too), and the one after.
    let erasing = erasing_saves(260);
    println!("saves that erase a page: {erasing:?}");
    assert!(erasing.len() >= 2, "{erasing:?}");
    let mut total = 0;
    for history in [1, erasing[0], erasing[0] + 1, erasing[1]] {
        total += cut_everywhere(history);
    }
    assert!(total > 2 * 4096, "{total}");
}

#[test]
fn every_save_of_a_long_history_survives_a_cut_at_its_start_middle_and_end() {
    // Wider than `cut_everywhere` (which is exhaustive at a few points): across
    // 60 saves — every page boundary — a cut at a few points of each.
    let mut f = flash();
    let mut s = store(f.clone());
    block_on(s.load());
    f = s.into_flash();
    for n in 0..60u32 {
        // Bytes this save touches.
        let mut g = f.clone();
        let before = g.stats_snapshot();
        let mut s = store(g);
        block_on(s.load());
        block_on(s.save(&record(n))).unwrap();
        g = s.into_flash();
        let d = before.compare_to(g.stats_snapshot());
        let touched = d.bytes_written + 4096 * d.erases;
        for cut in [0, 1, touched / 3, touched / 2, touched.saturating_sub(1)] {
            let mut h = f.clone();
            h.bytes_until_shutoff = Some(cut as u32);
            let mut s = store(h);
            block_on(s.load());
            let _ = block_on(s.save(&record(n)));
            let mut h = s.into_flash();
            h.bytes_until_shutoff = None;
            let mut s = store(h);
            let got = block_on(s.load()).config;
            let old = if n == 0 {
                Config::default()
            } else {
                record(n - 1)
            };
            assert!(got == old || got == record(n), "save {n}, cut {cut}");
        }
        f = g;
    }
}

/// The check above can fail: a store that erases its page and then writes the
/// record in place (no second copy) loses the record when the power is cut in
/// between — the same cut-everywhere loop finds such a cut.
#[test]
fn the_cut_check_catches_a_store_that_is_not_power_safe() {
    use embedded_storage_async::nor_flash::{NorFlash, ReadNorFlash};
    #[repr(align(4))]
    struct B([u8; 4 + RECORD_MAX]);
    fn naive_save(f: &mut Flash, c: &Config) -> Result<(), ()> {
        let mut b = B([0xFF; 4 + RECORD_MAX]);
        let n = codec::encode(c, &mut b.0[4..]).unwrap();
        b.0[..4].copy_from_slice(&(n as u32).to_le_bytes());
        let len = (4 + n).div_ceil(4) * 4;
        block_on(f.erase(0, 4096)).map_err(|_| ())?;
        block_on(f.write(0, &b.0[..len])).map_err(|_| ())
    }
    fn naive_load(f: &mut Flash) -> Option<Config> {
        let mut b = B([0; 4 + RECORD_MAX]);
        block_on(f.read(0, &mut b.0)).ok()?;
        let n = u32::from_le_bytes(b.0[..4].try_into().unwrap()) as usize;
        codec::decode(b.0.get(4..4 + n)?).ok()
    }
    let mut f = flash();
    naive_save(&mut f, &record(1)).unwrap();
    let mut lost = 0;
    for cut in (0..4096 + 300).step_by(7) {
        let mut g = f.clone();
        g.bytes_until_shutoff = Some(cut);
        let _ = naive_save(&mut g, &record(2));
        g.bytes_until_shutoff = None;
        let got = naive_load(&mut g);
        if got != Some(record(1)) && got != Some(record(2)) {
            lost += 1;
        }
    }
    assert!(
        lost > 0,
        "the naive store survived every cut: the check is blind"
    );
}
