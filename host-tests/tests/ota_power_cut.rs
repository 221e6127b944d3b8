//! Power cut at every flash write of an update: the chip's 4 MiB flash with
//! the firmware's partition table in the bytes espflash writes (its
//! `esp-idf-part`), a configuration record in `nvs`, an old image in `ota_0`
//! as a first install leaves it. The whole update — the transfer into the
//! other slot, `otadata`'s activation, the trial's mark at the next boot and
//! the confirmation — runs through the firmware's own procedure
//! (`tinybms_firmware::update`), and the power goes at each erase and
//! each program in turn: before it, half-way through it, or just after it.
//! Each time the chip boots again: a model of ESP-IDF's second-stage
//! bootloader written here from its documented rules (not the firmware's
//! code) picks the slot, the firmware's boot runs its trial or rollback, and
//! the bootloader picks again. It must boot the old or the new image,
//! complete, never anything else, and the record must be intact.
//!
//! Also: the desktop station's partition table is these bytes, every
//! refused file leaves the flash as it was, an image larger than the slot is
//! refused before a byte is written, and a bridge still on the table from
//! before the history partition (`firmware/partitions-pre-history.csv`: a
//! running image cannot rewrite its table) updates into its two 1984 KiB
//! slots as before and finds no history partition.

use ed25519_dalek::{Signer, SigningKey};
use embassy_futures::block_on;
use esp_idf_part::PartitionTable;
use sha2::{Digest, Sha256};
use tinybms_desk::flash::RamFlash;
use tinybms_desk::ota::{ChipFlash, PARTITIONS_CSV, PRE_HISTORY_CSV};
use tinybms_firmware::config::site;
use tinybms_firmware::config::Config;
use tinybms_firmware::partitions::{self, Checksum, HistoryProblem, Table};
use tinybms_firmware::update::file::{self, Permit, Refusal, Target, SIGNED_LEN};
use tinybms_firmware::update::flash::{self as uflash, Booted, OtaFlash};
use tinybms_firmware::update::otadata::Cause;
use tinybms_firmware::update::transfer::{Answer, Ended, Layout, CHUNK_MAX};
use tinybms_firmware::update::{Done, Ota};

const MIB4: usize = 4 * 1024 * 1024;
const OTADATA: usize = 0x10000;
/// The app slots of every image's table (`firmware/partitions.csv`).
const SLOTS: [usize; 2] = [0x20000, 0x1D_0000];
/// Their size: 1728 KiB.
const SLOT_BYTES: usize = 0x1B_0000;

fn table() -> Vec<u8> {
    table_of(PARTITIONS_CSV)
}

/// The bytes espflash writes for `csv`.
fn table_of(csv: &str) -> Vec<u8> {
    PartitionTable::try_from_str(csv)
        .expect("a partition table")
        .to_bin()
        .expect("its bytes")
}

/// `(offset, size)` of `ota_0` and `ota_1` in the table on `flash` (as the
/// bootloader reads it: espflash's crate, not the firmware's reader).
fn slots_on(flash: &[u8]) -> [(usize, usize); 2] {
    let t = PartitionTable::try_from_bytes(&flash[0x8000..0x8000 + 0xC00]).expect("a table");
    ["ota_0", "ota_1"].map(|l| {
        let p = t.find(l).expect(l);
        (p.offset() as usize, p.size() as usize)
    })
}

#[test]
fn the_slots_here_are_the_tables() {
    assert_eq!(
        slots_on(&chip_with(&table())),
        [(SLOTS[0], SLOT_BYTES), (SLOTS[1], SLOT_BYTES)]
    );
    assert_eq!(
        slots_on(&chip_with(&table_of(PRE_HISTORY_CSV))),
        [(0x20000, 0x1F_0000), (0x21_0000, 0x1F_0000)]
    );
}

/// An erased 4 MiB chip with `table` at 0x8000.
fn chip_with(table: &[u8]) -> Vec<u8> {
    let mut bytes = vec![0xFF; MIB4];
    bytes[0x8000..0x8000 + table.len()].copy_from_slice(table);
    bytes
}

#[test]
fn the_desktop_stations_table_is_the_bytes_espflash_writes() {
    let ours = tinybms_desk::ota::table_bytes(PARTITIONS_CSV).unwrap();
    let theirs = table();
    assert_eq!(
        &ours[..theirs.len().min(ours.len())],
        &theirs[..theirs.len().min(ours.len())]
    );
    assert!(ours[theirs.len()..].iter().all(|&b| b == 0xFF));
}

fn image(len: usize, version: &str, seed: u8) -> Vec<u8> {
    let mut v: Vec<u8> = (0..len)
        .map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed))
        .collect();
    v[0] = 0xE9;
    v[12..14].copy_from_slice(&5u16.to_le_bytes());
    v[32..36].copy_from_slice(&0xABCD_5432u32.to_le_bytes());
    v[48..80].fill(0);
    v[48..48 + version.len()].copy_from_slice(version.as_bytes());
    v
}

fn key() -> SigningKey {
    SigningKey::from_bytes(&[3; 32])
}

fn update_file(img: &[u8], board: &str, version: &str) -> Vec<u8> {
    let hash: [u8; 32] = Sha256::digest(img).into();
    let mut h = file::unsigned_header(
        img.len() as u32,
        &hash,
        "esp32c3",
        board,
        "can",
        version,
        "t",
    )
    .unwrap();
    let sig = key().sign(&h[..SIGNED_LEN]);
    h[SIGNED_LEN..].copy_from_slice(&sig.to_bytes());
    let mut f = h.to_vec();
    f.extend_from_slice(img);
    f
}

const ME: Target<'static> = Target {
    chip: "esp32c3",
    board: "c3-supermini",
    version: "0.2.0",
    features: 0,
    slot_size: 0,
};

fn record() -> Config {
    Config {
        stream_period_ms: 2500,
        pack_node: 3,
        ..Config::default()
    }
}

/// Where the old image runs from.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Start {
    /// A first install: the old image in ota_0, otadata erased.
    FirstInstall,
    /// After an earlier update: the old image in ota_1, confirmed in
    /// otadata; ota_0 holds an image older still, which must never boot.
    AfterAnUpdate,
}

/// The chip before the update: table, a record in nvs, the old image.
fn installed(old: &[u8], start: Start) -> RamFlash {
    installed_on(&table(), old, start)
}

/// The same on the partition table `table`.
fn installed_on(table: &[u8], old: &[u8], start: Start) -> RamFlash {
    let mut bytes = chip_with(table);
    let [(a, _), (b, _)] = slots_on(&bytes);
    match start {
        Start::FirstInstall => bytes[a..a + old.len()].copy_from_slice(old),
        Start::AfterAnUpdate => {
            bytes[b..b + old.len()].copy_from_slice(old);
            let older = image(30_000, "0.1.0", 9);
            bytes[a..a + older.len()].copy_from_slice(&older);
            // ESP-IDF's entry for ota_1, confirmed: sequence 4.
            let e = tinybms_firmware::update::otadata::Entry::new(
                4,
                tinybms_firmware::update::otadata::State::Valid,
                "0.2.0",
            );
            bytes[OTADATA + 0x1000..OTADATA + 0x1020].copy_from_slice(&e.to_bytes());
        }
    }
    let flash = RamFlash::from_bytes(bytes);
    let mut o = block_on(site::open(flash.clone(), MIB4 as u32, false));
    block_on(o.store.as_mut().unwrap().save(&record())).unwrap();
    flash
}

fn first_install(old: &[u8]) -> RamFlash {
    installed(old, Start::FirstInstall)
}

/// How a cut operation leaves its bytes.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Cut {
    /// Before it started.
    Before,
    /// Half-way: half the sector erased, half the bytes programmed.
    Half,
    /// Done, but the chip died before it heard.
    After,
}

/// The flash with a power cut: after `budget` erase/program calls the next
/// is cut as `how`, and nothing after it happens.
struct CutFlash {
    inner: ChipFlash,
    budget: usize,
    how: Cut,
    dead: bool,
    calls: usize,
}

impl CutFlash {
    fn spend(&mut self) -> Option<Cut> {
        if self.dead {
            return Some(Cut::Before);
        }
        self.calls += 1;
        if self.budget == 0 {
            self.dead = true;
            return Some(self.how);
        }
        self.budget -= 1;
        None
    }
}

impl OtaFlash for CutFlash {
    fn read(&mut self, at: u32, buf: &mut [u8]) -> bool {
        !self.dead && self.inner.read(at, buf)
    }
    fn erase_sector(&mut self, at: u32) -> bool {
        match self.spend() {
            None => self.inner.erase_sector(at),
            Some(Cut::Before) => false,
            Some(Cut::Half) => {
                let mut d = self.inner.0.lock();
                d[at as usize..at as usize + 2048].fill(0xFF);
                false
            }
            Some(Cut::After) => {
                self.inner.erase_sector(at);
                false
            }
        }
    }
    fn program(&mut self, at: u32, bytes: &[u8]) -> bool {
        match self.spend() {
            None => self.inner.program(at, bytes),
            Some(Cut::Before) => false,
            Some(Cut::Half) => {
                let half = bytes.len() / 2 / 4 * 4;
                self.inner.program(at, &bytes[..half]);
                false
            }
            Some(Cut::After) => {
                self.inner.program(at, bytes);
                false
            }
        }
    }
}

/// ESP-IDF's second-stage bootloader, from its rules: an otadata entry
/// counts when its sequence is not erased, its state is neither INVALID (3)
/// nor ABORTED (4) and its CRC-32 of the sequence's 4 bytes (zero start,
/// inverted end) matches; the higher sequence wins (sector 0 on a tie);
/// slot (seq - 1) % 2; none counts: ota_0.
fn bootloader_slot(bytes: &[u8]) -> usize {
    fn crc(seq: u32) -> u32 {
        let mut c = 0u32;
        for b in seq.to_le_bytes() {
            c ^= u32::from(b);
            for _ in 0..8 {
                c = if c & 1 == 1 {
                    (c >> 1) ^ 0xEDB8_8320
                } else {
                    c >> 1
                };
            }
        }
        !c
    }
    let entry = |i: usize| {
        let at = OTADATA + i * 0x1000;
        let w = |o: usize| u32::from_le_bytes(bytes[at + o..at + o + 4].try_into().unwrap());
        let (seq, state, c) = (w(0), w(24), w(28));
        (seq != u32::MAX && state != 3 && state != 4 && c == crc(seq)).then_some(seq)
    };
    let seq = match (entry(0), entry(1)) {
        (Some(a), Some(b)) => Some(if b > a { b } else { a }),
        (a, b) => a.or(b),
    };
    seq.map_or(0, |s| (s.wrapping_sub(1) % 2) as usize)
}

/// The image the chip runs after the power came back: the firmware's boot
/// (its trial or rollback, restarting as often as it says), then the
/// bootloader's choice. Panics when the chosen slot holds neither image.
fn boot_after_cut(flash: &RamFlash, old: &[u8], new: &[u8]) -> (&'static str, Ota) {
    let mut chip = ChipFlash(flash.clone());
    let mut cause = Cause::PowerCut;
    for _ in 0..4 {
        let slot = bootloader_slot(&flash.lock());
        let data = flash.lock();
        let at = slots_on(&data)[slot].0;
        let holds = |img: &[u8]| data.get(at..at + img.len()) == Some(img);
        let which = if holds(old) {
            "old"
        } else if holds(new) {
            "new"
        } else {
            panic!("the bootloader would boot slot {slot}, which holds neither image");
        };
        drop(data);
        match uflash::boot(&mut chip, cause) {
            Booted::Run(ota) => return (which, ota),
            Booted::Restart { .. } => cause = Cause::Reset,
        }
    }
    panic!("the chip keeps restarting");
}

/// The update from start to confirmation on `f`; stops at the first failed
/// write (the power went).
fn update(f: &mut CutFlash, file_bytes: &[u8]) {
    let layout = uflash::layout(f).unwrap();
    let mut ota = Ota::new(Some(layout), uflash::read_otadata(f, &layout));
    ota.set_owner_key(Some(key().verifying_key().to_bytes()));
    let keys = ota.keys();
    let running = ota.running_slot();
    let mut a = ota
        .transfer_mut()
        .begin(0, file_bytes.len() as u32, Permit::NONE, false);
    while let Answer::Next(n) | Answer::Busy(n) = a {
        while let Some(op) = ota.next_op() {
            let program = ota.transfer().program_bytes().to_vec();
            let ok = uflash::run(f, Some(&layout), op, &program);
            if !ok {
                return;
            }
            if let Done::Ended(e) = ota.op_done(true) {
                panic!("the transfer ended: {e:?}");
            }
        }
        let at = n as usize;
        if at >= file_bytes.len() {
            break;
        }
        let end = (at + CHUNK_MAX).min(file_bytes.len());
        a = ota.transfer_mut().chunk(
            1,
            at as u32,
            &file_bytes[at..end],
            &ME,
            &keys,
            Some(&layout),
            running,
        );
    }
    while let Some(op) = ota.next_op() {
        let program = ota.transfer().program_bytes().to_vec();
        if !uflash::run(f, Some(&layout), op, &program) {
            return;
        }
        ota.op_done(true);
    }
    // The restart into it: the trial's mark, then the confirmation.
    let Booted::Run(mut ota) = uflash::boot(f, Cause::Reset) else {
        panic!("the new image rolled back without a reset");
    };
    if f.dead {
        return;
    }
    assert!(ota.tick(10, true), "on trial after the update");
    let op = ota.next_op().expect("the confirmation");
    if uflash::run(f, Some(&layout), op, &[]) {
        assert_eq!(ota.op_done(true), Done::Confirmed);
    }
}

#[test]
fn a_power_cut_at_every_write_boots_the_old_or_the_new_image_with_the_record_intact() {
    for start in [Start::FirstInstall, Start::AfterAnUpdate] {
        cut_everywhere(start);
    }
}

fn cut_everywhere(start: Start) {
    let old = image(20_000, "0.2.0", 1);
    let new = image(9_000, "0.3.0", 2);
    let file_bytes = update_file(&new, "c3-supermini", "0.3.0");
    // The writes of a whole update, counted.
    let flash = installed(&old, start);
    let mut whole = CutFlash {
        inner: ChipFlash(flash.clone()),
        budget: usize::MAX,
        how: Cut::Before,
        dead: false,
        calls: 0,
    };
    update(&mut whole, &file_bytes);
    let writes = whole.calls;
    assert!(writes >= 12, "{writes} writes");
    assert_eq!(boot_after_cut(&flash, &old, &new).0, "new");
    let (mut booted_old, mut booted_new) = (0, 0);
    for k in 0..writes {
        for how in [Cut::Before, Cut::Half, Cut::After] {
            let flash = installed(&old, start);
            let mut f = CutFlash {
                inner: ChipFlash(flash.clone()),
                budget: k,
                how,
                dead: false,
                calls: 0,
            };
            update(&mut f, &file_bytes);
            assert!(f.dead, "{start:?}: write {k} was not reached");
            let (which, ota) = boot_after_cut(&flash, &old, &new);
            match which {
                "old" => booted_old += 1,
                _ => booted_new += 1,
            }
            // The configuration record is the one saved before.
            let o = block_on(site::open(flash.clone(), MIB4 as u32, false));
            assert_eq!(
                o.loaded.config,
                record(),
                "write {k} cut {how:?}: the record"
            );
            // And the bridge can go on: a new image on trial confirms itself,
            // and the next boot runs it for good.
            let slot_before = ota.running_slot();
            let mut ota = ota;
            let mut chip = ChipFlash(flash.clone());
            if ota.tick(10, true) {
                let op = ota.next_op().unwrap();
                assert!(uflash::run(
                    &mut chip,
                    ota.layout().copied().as_ref(),
                    op,
                    &[]
                ));
                ota.op_done(true);
            }
            let (again, _) = boot_after_cut(&flash, &old, &new);
            assert_eq!(
                again, which,
                "write {k} cut {how:?}: a second boot changed the image"
            );
            assert_eq!(bootloader_slot(&flash.lock()) as u32, slot_before);
        }
    }
    eprintln!(
        "{start:?}: {writes} writes, 3 ways each: the old image booted {booted_old} times, the new {booted_new}"
    );
    assert!(booted_old > 0 && booted_new > 0);
}

#[test]
fn a_refused_file_leaves_every_byte_of_the_flash_as_it_was() {
    let old = image(20_000, "0.2.0", 1);
    let new = image(9_000, "0.3.0", 2);
    let good = update_file(&new, "c3-supermini", "0.3.0");
    let mut corrupt = good.clone();
    corrupt[5000] ^= 1;
    let cases = [
        update_file(&new, "c3-devkitm-1", "0.3.0"),
        update_file(&new, "c3-supermini", "0.1.0"),
        good[..good.len() - 3].to_vec(),
        [good.clone(), vec![0; 4]].concat(),
        corrupt,
    ];
    for (i, f) in cases.iter().enumerate() {
        let flash = first_install(&old);
        let before = flash.lock().clone();
        let mut cf = CutFlash {
            inner: ChipFlash(flash.clone()),
            budget: usize::MAX,
            how: Cut::Before,
            dead: false,
            calls: 0,
        };
        let layout = uflash::layout(&mut cf).unwrap();
        let mut ota = Ota::new(Some(layout), uflash::read_otadata(&mut cf, &layout));
        ota.set_owner_key(Some(key().verifying_key().to_bytes()));
        let keys = ota.keys();
        let mut a = ota
            .transfer_mut()
            .begin(0, f.len() as u32, Permit::NONE, false);
        let mut ended = None;
        while let Answer::Next(n) | Answer::Busy(n) = a {
            while let Some(op) = ota.next_op() {
                let p = ota.transfer().program_bytes().to_vec();
                assert!(uflash::run(&mut cf, Some(&layout), op, &p));
                if let Done::Ended(e) = ota.op_done(true) {
                    ended = Some(e);
                }
            }
            let at = n as usize;
            if at >= f.len() || ended.is_some() {
                break;
            }
            let end = (at + CHUNK_MAX).min(f.len());
            a = ota
                .transfer_mut()
                .chunk(1, at as u32, &f[at..end], &ME, &keys, Some(&layout), 0);
        }
        if let Answer::Ended(e) = a {
            ended = Some(e);
        }
        assert!(ended.is_some(), "case {i} was not refused");
        let after = flash.lock().clone();
        // The slot being written may hold what came before the hash failed;
        // everything else (the running image, otadata, nvs) is untouched.
        let differs: Vec<usize> = (0..MIB4).filter(|&j| before[j] != after[j]).collect();
        assert!(
            differs
                .iter()
                .all(|&j| (SLOTS[1]..SLOTS[1] + SLOT_BYTES).contains(&j)),
            "case {i}: bytes outside the other slot changed"
        );
        assert_eq!(boot_after_cut(&flash, &old, &new).0, "old", "case {i}");
    }
}

/// Sends `f` to a bridge on `flash` until the transfer asks for more than
/// the header or ends; the answer then.
fn answer_after_header(flash: &RamFlash, f: &[u8]) -> Answer {
    let mut chip = ChipFlash(flash.clone());
    let layout = uflash::layout(&mut chip).expect("two slots");
    let mut ota = Ota::new(Some(layout), uflash::read_otadata(&mut chip, &layout));
    ota.set_owner_key(Some(key().verifying_key().to_bytes()));
    let keys = ota.keys();
    let mut a = ota
        .transfer_mut()
        .begin(0, f.len() as u32, Permit::NONE, false);
    while let Answer::Next(n) | Answer::Busy(n) = a {
        assert!(
            ota.next_op().is_none(),
            "a flash operation before the header"
        );
        let at = n as usize;
        if at >= file::HEADER_LEN {
            break;
        }
        let end = (at + CHUNK_MAX).min(f.len());
        a = ota
            .transfer_mut()
            .chunk(1, at as u32, &f[at..end], &ME, &keys, Some(&layout), 0);
    }
    a
}

/// Issue 55: the slots are 1728 KiB now. An image one byte larger is refused
/// on its header, before anything is written, in words that give the slot's
/// size; one that fills the slot exactly is taken.
#[test]
fn an_image_larger_than_the_slot_is_refused_before_a_byte_is_written() {
    let old = image(20_000, "0.2.0", 1);
    let flash = first_install(&old);
    let before = flash.lock().clone();
    let big = update_file(&image(SLOT_BYTES + 1, "0.3.0", 2), "c3-supermini", "0.3.0");
    let a = answer_after_header(&flash, &big);
    assert_eq!(a, Answer::Ended(Ended::Refused(Refusal::TooBig)));
    let words = Ended::Refused(Refusal::TooBig).words();
    assert!(
        words.contains(&format!("{} KiB", SLOT_BYTES / 1024)),
        "{words}"
    );
    assert!(*flash.lock() == before, "the flash changed");
    let exact = update_file(&image(SLOT_BYTES, "0.3.0", 2), "c3-supermini", "0.3.0");
    assert_eq!(
        answer_after_header(&flash, &exact),
        Answer::Next(file::HEADER_LEN as u32)
    );
}

/// Issue 55: a bridge installed before the history partition keeps its table
/// when it is updated over the network (a running image cannot rewrite it).
/// The new firmware reads that table: its two 1984 KiB slots, into which an
/// update lands as before — an image larger than today's 1728 KiB slots too,
/// from either slot —, no history partition (in the words that send the owner
/// to a cable reinstall), the record and the table untouched.
#[test]
fn a_bridge_on_the_pre_history_table_updates_as_before_without_history() {
    let old_table = table_of(PRE_HISTORY_CSV);
    let t = Table::parse(&old_table).unwrap();
    assert_eq!(t.checksum(), Checksum::Verified);
    let layout = Layout::from_table(&t).expect("two slots");
    assert_eq!(layout.slots, [(0x20000, 0x1F_0000), (0x21_0000, 0x1F_0000)]);
    assert_eq!(
        partitions::history(&t, MIB4 as u32),
        Err(HistoryProblem::Missing)
    );
    assert!(HistoryProblem::Missing
        .reason()
        .contains("reinstall by cable"));
    let small = image(20_000, "0.2.0", 1);
    let new = image(SLOT_BYTES + 64 * 1024, "0.3.0", 2);
    let file_bytes = update_file(&new, "c3-supermini", "0.3.0");
    for start in [Start::FirstInstall, Start::AfterAnUpdate] {
        let flash = installed_on(&old_table, &small, start);
        let mut f = CutFlash {
            inner: ChipFlash(flash.clone()),
            budget: usize::MAX,
            how: Cut::Before,
            dead: false,
            calls: 0,
        };
        update(&mut f, &file_bytes);
        let (which, ota) = boot_after_cut(&flash, &small, &new);
        assert_eq!(which, "new", "{start:?}");
        let into = match start {
            Start::FirstInstall => 1,
            Start::AfterAnUpdate => 0,
        };
        assert_eq!(ota.running_slot(), into, "{start:?}");
        assert_eq!(ota.layout(), Some(&layout));
        let bytes = flash.lock().clone();
        assert_eq!(&bytes[0x8000..0x8000 + old_table.len()], &old_table[..]);
        let at = [0x20000, 0x21_0000][into as usize];
        assert_eq!(&bytes[at..at + new.len()], &new[..], "{start:?}");
        let o = block_on(site::open(flash.clone(), MIB4 as u32, false));
        assert_eq!(o.loaded.config, record(), "{start:?}");
        let t = Table::parse(&bytes[0x8000..0x8000 + 0xC00]).unwrap();
        assert_eq!(
            partitions::history(&t, MIB4 as u32),
            Err(HistoryProblem::Missing)
        );
    }
    // Past its own slot, refused there too, before anything is written.
    let flash = installed_on(&old_table, &small, Start::FirstInstall);
    let before = flash.lock().clone();
    let big = update_file(&image(0x1F_0001, "0.3.0", 2), "c3-supermini", "0.3.0");
    assert_eq!(
        answer_after_header(&flash, &big),
        Answer::Ended(Ended::Refused(Refusal::TooBig))
    );
    assert!(Refusal::TooBig.words().contains("1984 KiB"));
    assert!(*flash.lock() == before);
}
