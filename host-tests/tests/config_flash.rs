//! A configuration save must never cost a BMS reply. On the chip a flash
//! erase or write stops the CPU (the cache is off) for up to hundreds of
//! milliseconds, and the UART's 128-byte FIFO overflows after 11 ms of reply.
//! The station therefore saves only when the bridge says no reply can be on
//! its way (`Bridge::quiet`), and sends nothing until the save is done.
//!
//! Here the bridge runs against the simulated BMS in virtual time; the
//! configuration changes every second or so and is saved to
//! `sequential-storage`'s mock flash, and the CPU is stopped for as long as the
//! chip's flash would stop it (`host_tests::flash::Timed`: worst-case erase and
//! write times), with the BMS's bytes meanwhile held in a 128-byte FIFO
//! (`Harness::stall`). The same run without the gate loses replies: the test can
//! fail.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use embassy_futures::block_on;
use host_tests::flash::{Timed, ERASE_STALL_US};
use host_tests::sim::{PackModel, SimBms, SimConfig};
use host_tests::virtual_time::Harness;
use sequential_storage::mock_flash::{MockFlashBase, WriteCountCheck};
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::state::ConfigState;
use tinybms_firmware::config::store::Store;
use tinybms_firmware::config::value::Parsed;
use tinybms_firmware::config::{Config, FieldId};
use tinybms_firmware::station::Station;
use tinybms_firmware::SECOND;

type Flash = MockFlashBase<6, 4, 1024>;

struct Run {
    lost_bytes: u64,
    /// Saves begun while the BMS had bytes on their way to the bridge.
    saves_with_reply_due: u64,
    saves: u64,
    erasing_saves: u64,
    longest_stall_us: u64,
    timeouts: u32,
    crc_errors: u32,
    retries: u32,
    wrong: u64,
    published: u64,
}

/// When a due save is written.
#[derive(Clone, Copy, PartialEq)]
enum Placement {
    /// When the station says so (only when the bridge is quiet): what the
    /// chip does.
    WhenQuiet,
    /// At the first moment the bridge is *not* quiet (a request outstanding,
    /// a reply arriving): the worst moment, what an ungated writer can hit.
    MidTransaction,
}

/// Runs `seconds` of virtual time, changing the configuration about every
/// `change_every_us`, saving at `placement`. `every_save_erases`: stop the CPU
/// for a sector erase at every save (the worst case), not only when the store
/// erases one. Gated, the station decides when to save (its `Save` action);
/// ungated, the test writes a record of its own at the worst moments.
fn run(seconds: u64, change_every_us: u64, placement: Placement, every_save_erases: bool) -> Run {
    let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 7);
    let mut h = Harness::checked(sim, Timing::default());
    h.retain = false;
    let (flash, stall): (Timed<Flash>, Rc<Cell<u64>>) =
        Timed::new(Flash::new(WriteCountCheck::Disabled, None, true));
    let store = Rc::new(RefCell::new(Store::new(flash, 0..0x6000).unwrap()));
    let loaded = block_on(store.borrow_mut().load());
    let mut state = ConfigState::new(loaded.config, loaded.source);
    let saves = Rc::new(Cell::new(0u64));
    let erasing = Rc::new(Cell::new(0u64));
    let longest = Rc::new(Cell::new(0u64));
    let reply_due = Rc::new(Cell::new(0u64));
    // One save: the store writes, the CPU stops for as long as the flash took.
    let save_one = {
        let (store, stall) = (store.clone(), stall.clone());
        let (saves, erasing, longest, reply_due) = (
            saves.clone(),
            erasing.clone(),
            longest.clone(),
            reply_due.clone(),
        );
        move |record: &Config, sim: &SimBms| {
            if sim.next_output_at().is_some() {
                reply_due.set(reply_due.get() + 1);
            }
            stall.set(0);
            let r = block_on(store.borrow_mut().save(record));
            saves.set(saves.get() + 1);
            let us = if every_save_erases {
                stall.get().max(ERASE_STALL_US)
            } else {
                stall.get()
            };
            if us >= ERASE_STALL_US {
                erasing.set(erasing.get() + 1);
            }
            longest.set(longest.get().max(us));
            (r, us)
        }
    };
    let save_own = save_one.clone();
    if placement == Placement::WhenQuiet {
        let save = save_one;
        h.saver = Some(Box::new(move |record: &Config, sim: &SimBms| {
            save(record, sim)
        }));
    }
    let mut next_change = 0;
    let mut n = 0u32;
    let mut seed = 12345u64;
    let mut hook = |station: &mut Station, sim: &SimBms, now: u64| -> u64 {
        if now >= next_change {
            n += 1;
            // A harmless at-once field, a new value each time.
            let cap = [(
                FieldId::ChargeCurrentCap,
                Parsed::Number(100 + (n % 400) as i32),
            )];
            match placement {
                Placement::WhenQuiet => {
                    station.change_config(now, &cap);
                }
                Placement::MidTransaction => {
                    state.change(&cap, false, None);
                }
            }
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            // Jitter: changes land at every phase of the poll cycle.
            next_change = now + change_every_us / 2 + (seed >> 33) % change_every_us;
        }
        // The ungated writer: at the first moment the bridge is *not* quiet.
        if placement == Placement::MidTransaction
            && state.save_due()
            && !station.bridge().quiet(now)
        {
            let (r, us) = save_own(state.stored(), sim);
            state.saved(r);
            return us;
        }
        0
    };
    h.run_until_hooked(seconds * SECOND, &mut hook);
    let stats = h.bridge().link_stats();
    let soak = h.soak.as_ref().unwrap();
    Run {
        lost_bytes: h.fifo_lost_bytes,
        saves_with_reply_due: reply_due.get(),
        saves: saves.get(),
        erasing_saves: erasing.get(),
        longest_stall_us: longest.get(),
        timeouts: stats.timeouts,
        crc_errors: stats.crc_errors,
        retries: stats.retries,
        wrong: soak.wrong,
        published: soak.published,
    }
}

#[test]
fn no_bms_reply_is_lost_to_a_flash_write() {
    let r = run(12 * 60, SECOND, Placement::WhenQuiet, false);
    println!(
        "gated: {} saves ({} erasing a sector), longest stall {} ms, {} snapshots, \
         lost bytes {}, timeouts {}, CRC errors {}, retries {}",
        r.saves,
        r.erasing_saves,
        r.longest_stall_us / 1000,
        r.published,
        r.lost_bytes,
        r.timeouts,
        r.crc_errors,
        r.retries
    );
    assert!(r.saves > 500, "{}", r.saves);
    assert!(r.erasing_saves > 0, "no save erased a sector");
    // No save began while a reply was on its way: that holds whatever the
    // flash's timing is.
    assert_eq!(r.saves_with_reply_due, 0);
    assert_eq!(r.lost_bytes, 0);
    assert_eq!((r.timeouts, r.crc_errors, r.retries), (0, 0, 0));
    assert_eq!(r.wrong, 0);
    // The poll was held, not starved: snapshots kept coming (4 a second).
    assert!(r.published > 12 * 60 * 3, "{}", r.published);
}

/// The same changes saved mid-transaction, each stopping the CPU for a sector
/// erase: a reply longer than the FIFO (the event log's 98 registers, the
/// BMS's 0x1D limits at start-up) is cut. The gated run with the same changes
/// and the same stalls loses nothing.
#[test]
fn without_the_gate_flash_writes_lose_replies() {
    let r = run(60, SECOND / 100, Placement::MidTransaction, true);
    println!(
        "mid-transaction: {} saves ({} with a reply on its way), lost bytes {}, timeouts {}, \
         CRC errors {}, retries {}",
        r.saves, r.saves_with_reply_due, r.lost_bytes, r.timeouts, r.crc_errors, r.retries
    );
    assert!(r.saves_with_reply_due > 0);
    assert!(
        r.lost_bytes > 0 || r.timeouts > 0 || r.crc_errors > 0,
        "saving at any moment lost nothing: the test above proves nothing"
    );
    // Even then no wrong value is published: the link's checks hold.
    assert_eq!(r.wrong, 0);
    let g = run(60, SECOND / 100, Placement::WhenQuiet, true);
    println!(
        "gated, every save erasing: {} saves, lost bytes {}, timeouts {}",
        g.saves, g.lost_bytes, g.timeouts
    );
    assert_eq!(g.saves_with_reply_due, 0);
    assert_eq!((g.lost_bytes, g.timeouts, g.crc_errors), (0, 0, 0));
    assert!(g.saves > 50, "{}", g.saves);
}
