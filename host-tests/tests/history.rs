//! The bridge's history in flash (`tinybms_firmware::history`), through the
//! station as the chip runs it, on the desktop chip's flash with the
//! firmware's partition table:
//!
//! * writing it moves no BMS request and no CAN frame by a microsecond (the
//!   same run with and without a history, the flash's erase and program
//!   stalling the clock as on the chip);
//! * a power cut at every flash operation of the history — before it, half-way
//!   through it, after it — leaves every record whole or absent, never half,
//!   never a wrong value, and the log goes on after it;
//! * a bridge on the table of before (no `history` partition) runs without
//!   one and says why.

use host_tests::closed_loop::ClosedLoop;
use host_tests::sim::PackModel;
use tinybms_desk::flash::RamFlash;
use tinybms_desk::ota::{chip_flash, ChipFlash};
use tinybms_firmware::history::event::{Code, Record};
use tinybms_firmware::history::log::{self, History, Listed};
use tinybms_firmware::history::ring::{Found, Kind, Op, DAY_PAYLOAD_BYTES};
use tinybms_firmware::update::flash::OtaFlash;

const S: u64 = 1_000_000;

/// The BMS requests, the CAN frames and the history's flash operations of a
/// run with `set_time` lines every 200 ms (each a new date: an event each,
/// within the rate limit).
/// A run: its BMS requests (time, bytes), its CAN frames (time, id), the
/// history's flash operations.
type Run = (Vec<(u64, Vec<u8>)>, Vec<(u64, u16)>, usize);

fn run(with_history: bool, end: u64) -> Run {
    let mut l = ClosedLoop::from_flash_as(
        PackModel::LiFePO4_16S,
        7,
        RamFlash::new(),
        100.0,
        tinybms_firmware::identity::Identity::desktop(
            "esp32c3",
            tinybms_firmware::identity::Features {
                can: true,
                host_link: true,
                ..Default::default()
            },
        ),
    );
    l.h.tx_log = Some(Vec::new());
    let mut chip = ChipFlash(chip_flash());
    if with_history {
        let h = tinybms_desk::station::open_history(&mut chip);
        assert_eq!(h.problem(), None);
        l.h.station.set_history(l.h.now, h, Some(1));
    }
    l.h.ota = Some(chip);
    let mut t = S;
    let mut date = 1_765_000_000u64;
    while t < end {
        l.run_until(t);
        l.host_line(&format!(r#"{{"cmd":"set_time","at":{date}}}"#));
        date += 3600;
        t += 200_000;
    }
    l.run_until(end);
    let ops =
        l.h.flash_ops
            .iter()
            .filter(|(_, n)| n.starts_with("history"))
            .count();
    (l.h.tx_log.take().unwrap(), l.sent_ids.clone(), ops)
}

#[test]
fn writing_the_history_moves_no_request_and_no_frame() {
    let end = 120 * S;
    let (tx_h, can_h, ops) = run(true, end);
    let (tx_b, can_b, ops_b) = run(false, end);
    assert_eq!(ops_b, 0);
    // 60 events in the first burst, one every 10 s after: more than a
    // sector's 63, so a sector was erased too.
    assert!(ops >= 70, "{ops} history flash operations");
    eprintln!(
        "{ops} history flash operations; {} BMS requests and {} CAN frames in both runs",
        tx_b.len(),
        can_b.len()
    );
    assert_eq!(tx_h.len(), tx_b.len(), "BMS requests");
    for (i, (h, b)) in tx_h.iter().zip(&tx_b).enumerate() {
        assert_eq!(
            h, b,
            "BMS request {i}: with history at {} µs, without at {} µs",
            h.0, b.0
        );
    }
    assert_eq!(can_h, can_b, "the CAN frames' times and ids");
    assert!(can_b.len() >= 200 && tx_b.len() >= 200);
}

/// A chip flash whose power goes during operation number `cut` (counted
/// from 0): `half` leaves half of it done, else none of it; every operation
/// after it fails.
struct Cutting {
    flash: ChipFlash,
    ops: usize,
    cut: usize,
    half: bool,
}

impl OtaFlash for Cutting {
    fn read(&mut self, at: u32, buf: &mut [u8]) -> bool {
        self.flash.read(at, buf)
    }
    fn erase_sector(&mut self, at: u32) -> bool {
        self.ops += 1;
        if self.ops - 1 < self.cut {
            return self.flash.erase_sector(at);
        }
        if self.ops - 1 == self.cut && self.half {
            // Half the sector erased.
            let ff = vec![0xFF; 2048];
            let mut b = self.flash.0.lock();
            b[at as usize..at as usize + 2048].copy_from_slice(&ff);
        }
        false
    }
    fn program(&mut self, at: u32, bytes: &[u8]) -> bool {
        self.ops += 1;
        if self.ops - 1 < self.cut {
            return self.flash.program(at, bytes);
        }
        if self.ops - 1 == self.cut && self.half {
            let n = bytes.len() / 2;
            let mut b = self.flash.0.lock();
            for (d, s) in b[at as usize..at as usize + n].iter_mut().zip(bytes) {
                *d &= s;
            }
        }
        false
    }
}

/// What was appended: events by their `a`, days and checkpoints by their
/// first byte.
#[derive(Default, Debug)]
struct Written {
    events: Vec<u32>,
    days: Vec<u8>,
    points: Vec<u8>,
}

/// Appends `n` records (events, with a day after every 10th and a
/// checkpoint after every 4th) to the history on `f`, doing every flash
/// operation; returns what was confirmed written (the power may go).
fn append(f: &mut impl OtaFlash, h: &mut History, n: u32, from: u32, w: &mut Written) {
    for i in from..from + n {
        h.event(u64::from(i) * 20 * S, Code::Bms, i, 0, "x");
        let day = (i % 10 == 9).then_some(i as u8);
        if let Some(d) = day {
            h.record(Kind::Day, &[d; DAY_PAYLOAD_BYTES]);
        }
        let point = (i % 4 == 3).then_some(i as u8);
        if let Some(p) = point {
            h.record(Kind::Checkpoint, &[p; 40]);
        }
        // Everything pending, one operation at a time, as the station does.
        let mut kinds = vec![Kind::Event];
        kinds.extend(day.map(|_| Kind::Day));
        kinds.extend(point.map(|_| Kind::Checkpoint));
        let mut k = 0;
        while let Some(op) = h.next_op() {
            let before = h.counts().0;
            let ok = log::run(f, op);
            h.done(ok);
            if !ok {
                return;
            }
            if h.counts().0 > before {
                match kinds.get(k) {
                    Some(Kind::Event) => w.events.push(i),
                    Some(Kind::Day) => w.days.push(i as u8),
                    Some(Kind::Checkpoint) => w.points.push(i as u8),
                    None => {}
                }
                k += 1;
            }
            let _ = matches!(op, Op::Erase(_));
        }
    }
}

/// Everything the history on `f` reads back, and the reasons of what it
/// skipped.
fn read_back(f: &mut ChipFlash) -> (Written, Vec<&'static str>) {
    let h = tinybms_desk::station::open_history(f);
    let mut w = Written::default();
    let mut bad = Vec::new();
    for kind in [Kind::Event, Kind::Day, Kind::Checkpoint] {
        h.read_ring(f, kind, |x| match x {
            Found::Record(_, p) => match kind {
                Kind::Event => {
                    let e = Record::decode_payload(&p).expect("an event reads");
                    assert_eq!((e.code, e.text()), (Code::Bms, "x"));
                    w.events.push(e.a);
                }
                Kind::Day => {
                    assert!(
                        p[..DAY_PAYLOAD_BYTES].iter().all(|&b| b == p[0]),
                        "a day whole"
                    );
                    w.days.push(p[0]);
                }
                Kind::Checkpoint => {
                    assert!(
                        p[..40].iter().all(|&b| b == p[0])
                            && p[40..DAY_PAYLOAD_BYTES].iter().all(|&b| b == 0)
                    );
                    w.points.push(p[0]);
                }
            },
            Found::Skipped(_, d) => bad.push(d.reason()),
        });
    }
    (w, bad)
}

#[test]
fn a_power_cut_at_every_flash_operation_leaves_the_history_whole() {
    // A history that has lapped its event ring once would take minutes per
    // cut here; the ring's own test cuts at every byte of a lap. This one
    // cuts at every operation of 130 events (two sectors and more), 13 days
    // and 32 checkpoints on the partition of the firmware's table.
    let mut base = ChipFlash(chip_flash());
    let mut h = tinybms_desk::station::open_history(&mut base);
    assert_eq!(h.problem(), None);
    let mut all = Written::default();
    let clean = ChipFlash(base.0.copy());
    append(&mut base, &mut h, 130, 0, &mut all);
    let total_ops = {
        let mut f = Cutting {
            flash: ChipFlash(clean.0.copy()),
            ops: 0,
            cut: usize::MAX,
            half: false,
        };
        let mut h = tinybms_desk::station::open_history(&mut f.flash);
        append(&mut f, &mut h, 130, 0, &mut Written::default());
        f.ops
    };
    assert!(total_ops > 130 + 13 + 32, "{total_ops} operations");
    eprintln!("{total_ops} flash operations, the power cut before and half-way through each");
    for cut in 0..total_ops {
        for half in [false, true] {
            let mut f = Cutting {
                flash: ChipFlash(clean.0.copy()),
                ops: 0,
                cut,
                half,
            };
            let mut h = tinybms_desk::station::open_history(&mut f.flash);
            let mut w = Written::default();
            append(&mut f, &mut h, 130, 0, &mut w);
            let (got, bad) = read_back(&mut f.flash);
            // Every record confirmed before the cut reads back, in order;
            // at most the one cut short is also there (whole) or skipped for
            // its CRC.
            for (name, confirmed, read) in [
                (
                    "events",
                    w.events.iter().map(|&x| x as u64).collect::<Vec<_>>(),
                    got.events.iter().map(|&x| x as u64).collect::<Vec<_>>(),
                ),
                (
                    "days",
                    w.days.iter().map(|&x| x as u64).collect(),
                    got.days.iter().map(|&x| x as u64).collect(),
                ),
                (
                    "checkpoints",
                    w.points.iter().map(|&x| x as u64).collect(),
                    got.points.iter().map(|&x| x as u64).collect(),
                ),
            ] {
                assert!(
                    read.len() == confirmed.len() || read.len() == confirmed.len() + 1,
                    "cut {cut} half {half}: {name} confirmed {confirmed:?} read {read:?}"
                );
                assert_eq!(
                    &read[..confirmed.len()],
                    &confirmed[..],
                    "cut {cut} half {half}: {name}"
                );
            }
            assert!(
                bad.iter().all(|r| r.contains("CRC")) && bad.len() <= 1,
                "cut {cut} half {half}: {bad:?}"
            );
            // After the restart the history goes on: the next records read.
            let mut f2 = ChipFlash(f.flash.0.copy());
            let mut h = tinybms_desk::station::open_history(&mut f2);
            let mut w2 = Written::default();
            append(&mut f2, &mut h, 5, 1000, &mut w2);
            assert_eq!(w2.events, vec![1000, 1001, 1002, 1003, 1004], "cut {cut}");
            let (got2, _) = read_back(&mut f2);
            assert_eq!(
                &got2.events[got2.events.len() - 5..],
                &[1000, 1001, 1002, 1003, 1004]
            );
        }
    }
    let (got, bad) = read_back(&mut base);
    assert!(bad.is_empty());
    assert_eq!(got.events, all.events);
    assert_eq!(got.days, all.days);
    assert_eq!(got.points, all.points);
}

#[test]
fn a_bridge_on_the_table_of_before_runs_without_history_and_says_why() {
    // The table every image had before the history partition: the two
    // 1984-KiB slots fill the 4 MiB.
    let before = "nvs, data, nvs, 0x9000, 0x6000,\nphy_init, data, phy, 0xf000, 0x1000,\notadata, data, ota, 0x10000, 0x2000,\nota_0, app, ota_0, 0x20000, 0x1f0000,\nota_1, app, ota_1, 0x210000, 0x1f0000,\n";
    let mut bytes = vec![0xFF; tinybms_desk::ota::CHIP_BYTES];
    let table = tinybms_desk::ota::table_bytes(before).unwrap();
    bytes[0x8000..0x8000 + table.len()].copy_from_slice(&table);
    let mut chip = ChipFlash(RamFlash::from_bytes(bytes));
    let h = tinybms_desk::station::open_history(&mut chip);
    let why = h.problem().expect("no history");
    assert!(why.contains("reinstall"), "{why}");
    // Nothing is written, and nothing waits.
    let mut h = h;
    h.event(0, Code::Started, 1, 0, "0.9.0");
    assert!(!h.pending() && h.next_op().is_none());
    // The slots of that table still serve updates.
    assert!(tinybms_firmware::update::flash::layout(&mut chip).is_some());
}

#[test]
fn a_listing_reads_what_was_written_oldest_first() {
    let mut chip = ChipFlash(chip_flash());
    let mut h = tinybms_desk::station::open_history(&mut chip);
    for i in 0..70u32 {
        h.event(u64::from(i) * 10 * S, Code::Bms, i, 0, "x");
        while let Some(op) = h.next_op() {
            let ok = log::run(&mut chip, op);
            h.done(ok);
        }
    }
    h.list();
    let mut got = Vec::new();
    let mut ended = false;
    for _ in 0..10_000 {
        if let Some((at, len)) = h.want_read() {
            let mut b = vec![0u8; len];
            let ok = chip.read(at, &mut b);
            h.read_done(ok.then_some(&b[..]));
        }
        match h.take_listed() {
            Some(Some(Listed::Event(_, e))) => got.push(e.a),
            Some(Some(x)) => panic!("{x:?}"),
            Some(None) => {
                ended = true;
                break;
            }
            None => {}
        }
    }
    assert!(ended, "the listing came to its end");
    assert_eq!(got, (0..70).collect::<Vec<_>>());
}

/// A chip flash whose history holds a closed day `last` and a checkpoint of
/// day `point`.
fn with_days(last: Option<u32>, point: Option<u32>) -> ChipFlash {
    use tinybms_firmware::history::day::DayRecord;
    let mut chip = ChipFlash(chip_flash());
    let mut h = tinybms_desk::station::open_history(&mut chip);
    if let Some(d) = last {
        let r = DayRecord {
            day: d,
            covered_s: 86_400,
            top_spread_mv: 23,
            top_cell: 4,
            highest_cell_mv: 3550,
            lowest_cell_mv: 3300,
            capacity_cah: 27_100,
            capacity_uncertainty_permille: 21,
            ..Default::default()
        };
        h.record(Kind::Day, &r.encode());
    }
    if let Some(d) = point {
        let r = DayRecord {
            day: d,
            partial: true,
            covered_s: 7_200,
            energy_in_wh: 1_234,
            ..Default::default()
        };
        h.record(Kind::Checkpoint, &r.encode());
    }
    while let Some(op) = h.next_op() {
        let ok = log::run(&mut chip, op);
        h.done(ok);
    }
    chip
}

#[test]
fn after_a_restart_the_day_goes_on_from_its_checkpoint_or_the_next_one_begins() {
    let station = |chip: &mut ChipFlash| {
        let mut l = ClosedLoop::from_flash(PackModel::LiFePO4_16S, 1, RamFlash::new(), 100.0);
        let h = tinybms_desk::station::open_history(chip);
        l.h.station.set_history(0, h, Some(1));
        l
    };
    // A checkpoint of a day newer than the last closed one: that day goes on.
    let l = station(&mut with_days(Some(4), Some(5)));
    assert_eq!(l.h.station.day_book().day(), 5);
    let p = l.h.station.day_book().checkpoint(0);
    assert!(
        p.cut_by_restart && p.covered_s == 7_200 && p.energy_in_wh == 1_234,
        "{p:?}"
    );
    // The checkpoint of a day already closed: the next day begins.
    let l = station(&mut with_days(Some(5), Some(5)));
    assert_eq!(l.h.station.day_book().day(), 6);
    assert!(!l.h.station.day_book().checkpoint(0).cut_by_restart);
    // Nothing yet: day 0.
    let l = station(&mut with_days(None, None));
    assert_eq!(l.h.station.day_book().day(), 0);
    // The last closed day's spread and capacity are what Home Assistant shows
    // until new ones come.
    let l = station(&mut with_days(Some(9), None));
    let a = l.h.station.published(0).aging;
    assert_eq!(a.top_spread_mv, Some(23));
    assert_eq!(a.capacity, Some((27_100, 21)));
    assert!(a.recording);
}

/// A bridge with nothing else to wake it (no host, no CAN output): the
/// station looks at the BMS poll's gap itself when the link turns quiet, so
/// the history is written.
#[test]
fn a_bridge_alone_writes_its_history_in_the_polls_gaps() {
    use host_tests::sim::{SimBms, SimConfig};
    use host_tests::virtual_time::Harness;
    let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 7);
    let mut h = Harness::checked(sim, Default::default());
    let mut chip = ChipFlash(chip_flash());
    let history = tinybms_desk::station::open_history(&mut chip);
    h.station.set_history(0, history, Some(1));
    assert!(h.station.history().pending());
    h.ota = Some(chip);
    h.run_until(30 * S);
    assert!(!h.station.history().pending());
    assert_eq!(h.station.history().counts(), (1, 0));
    // Erase, header, record: each in a gap of 100 ms or more before the
    // next request.
    assert_eq!(h.flash_ops.len(), 3, "{:?}", h.flash_ops);
}
