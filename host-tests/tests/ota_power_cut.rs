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
//! Also: the desktop station's partition table is these bytes, and every
//! refused file leaves the flash as it was.

use ed25519_dalek::{Signer, SigningKey};
use embassy_futures::block_on;
use esp_idf_part::PartitionTable;
use sha2::{Digest, Sha256};
use tinybms_desk::flash::RamFlash;
use tinybms_desk::ota::{ChipFlash, PARTITIONS_CSV};
use tinybms_firmware::config::site;
use tinybms_firmware::config::Config;
use tinybms_firmware::update::file::{self, Permit, Target, SIGNED_LEN};
use tinybms_firmware::update::flash::{self as uflash, Booted, OtaFlash};
use tinybms_firmware::update::otadata::Cause;
use tinybms_firmware::update::transfer::{Answer, CHUNK_MAX};
use tinybms_firmware::update::{Done, Ota};

const MIB4: usize = 4 * 1024 * 1024;
const OTADATA: usize = 0x10000;
const SLOTS: [usize; 2] = [0x20000, 0x210000];

fn table() -> Vec<u8> {
    PartitionTable::try_from_str(PARTITIONS_CSV)
        .expect("firmware/partitions.csv is a table")
        .to_bin()
        .expect("its bytes")
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
    let mut bytes = vec![0xFF; MIB4];
    let t = table();
    bytes[0x8000..0x8000 + t.len()].copy_from_slice(&t);
    match start {
        Start::FirstInstall => bytes[SLOTS[0]..SLOTS[0] + old.len()].copy_from_slice(old),
        Start::AfterAnUpdate => {
            bytes[SLOTS[1]..SLOTS[1] + old.len()].copy_from_slice(old);
            let older = image(30_000, "0.1.0", 9);
            bytes[SLOTS[0]..SLOTS[0] + older.len()].copy_from_slice(&older);
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
        let holds = |img: &[u8]| data.get(SLOTS[slot]..SLOTS[slot] + img.len()) == Some(img);
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
                .all(|&j| (SLOTS[1]..SLOTS[1] + 0x1F_0000).contains(&j)),
            "case {i}: bytes outside the other slot changed"
        );
        assert_eq!(boot_after_cut(&flash, &old, &new).0, "old", "case {i}");
    }
}
