//! The transfer and the trial on a flash in RAM (the power cut at every write,
//! through a model of the bootloader, is host-tests' `ota_power_cut.rs`).

use ed25519_dalek::{Signer, SigningKey};
use sha2::{Digest, Sha256};

use super::file::{self, Permit, Refusal, Target, HEADER_LEN, SIGNED_LEN};
use super::otadata::{self, Cause};
use super::transfer::{Answer, Ended, Layout, Op, Phase, CHUNK_MAX, STALL_US};
use super::*;

extern crate std;
use std::vec::Vec;

const LAYOUT: Layout = Layout {
    otadata: 0x10000,
    slots: [(0x20000, 0x1E_0000), (0x20_0000, 0x1E_0000)],
};

const ME: Target<'static> = Target {
    chip: "esp32c3",
    board: "c3-supermini",
    version: "0.2.0",
    features: 0,
    slot_size: 0,
};

fn key() -> SigningKey {
    SigningKey::from_bytes(&[42; 32])
}

/// An app image of `len` bytes for `chip`, its version in the descriptor.
pub(crate) fn image(len: usize, chip: u16, version: &str) -> Vec<u8> {
    let mut v: Vec<u8> = (0..len).map(|i| (i * 7 + i / 251) as u8).collect();
    v[0] = 0xE9;
    v[12..14].copy_from_slice(&chip.to_le_bytes());
    v[32..36].copy_from_slice(&0xABCD_5432u32.to_le_bytes());
    v[48..80].fill(0);
    v[48..48 + version.len()].copy_from_slice(version.as_bytes());
    v
}

/// The update file of `img`, signed by `key` (or unsigned).
pub(crate) fn update_file(
    img: &[u8],
    chip: &str,
    board: &str,
    version: &str,
    key: Option<&SigningKey>,
) -> Vec<u8> {
    let hash: [u8; 32] = Sha256::digest(img).into();
    let mut h = file::unsigned_header(
        img.len() as u32,
        &hash,
        chip,
        board,
        "can,host-link",
        version,
        "test",
    )
    .unwrap();
    if let Some(k) = key {
        let sig = k.sign(&h[..SIGNED_LEN]);
        h[SIGNED_LEN..].copy_from_slice(&sig.to_bytes());
    }
    let mut f = h.to_vec();
    f.extend_from_slice(img);
    f
}

struct Bench {
    ota: Ota,
    flash: Vec<u8>,
    now: Instant,
    ops: usize,
}

impl Bench {
    fn new() -> Self {
        let mut ota = Ota::new(Some(LAYOUT), [None, None]);
        ota.set_owner_key(Some(key().verifying_key().to_bytes()));
        Self {
            ota,
            flash: std::vec![0xFF; 0x40_0000],
            now: 0,
            ops: 0,
        }
    }

    fn flash_ops(&mut self) -> Option<Done> {
        let mut last = None;
        while let Some(op) = self.ota.next_op() {
            match op {
                Op::Erase(at) => self.flash[at as usize..at as usize + 0x1000].fill(0xFF),
                Op::Program(at) => {
                    let b = self.ota.transfer().program_bytes().to_vec();
                    assert_eq!(at % 0x1000, 0);
                    assert!(
                        self.flash[at as usize..at as usize + b.len()]
                            .iter()
                            .all(|&x| x == 0xFF),
                        "programmed unerased"
                    );
                    self.flash[at as usize..at as usize + b.len()].copy_from_slice(&b);
                }
                Op::Otadata(w) => {
                    let at = (LAYOUT.otadata + w.sector as u32 * 0x1000) as usize;
                    self.flash[at..at + 0x1000].fill(0xFF);
                    self.flash[at..at + 32].copy_from_slice(&w.entry.to_bytes());
                }
            }
            self.ops += 1;
            last = Some(self.ota.op_done(true));
        }
        last
    }

    fn begin(&mut self, size: usize, downgrade: bool, check: bool) -> Answer {
        self.ota.transfer_mut().begin(
            self.now,
            size as u32,
            Permit {
                downgrade,
                ..Permit::NONE
            },
            check,
        )
    }

    fn chunk(&mut self, at: usize, data: &[u8]) -> Answer {
        let keys = self.ota.keys();
        let running = self.ota.running_slot();
        let layout = self.ota.layout;
        self.ota.transfer_mut().chunk(
            self.now,
            at as u32,
            data,
            &ME,
            &keys,
            layout.as_ref(),
            running,
        )
    }

    /// Sends `f` in order, flashing whenever busy; the last answer.
    fn send(&mut self, f: &[u8]) -> Answer {
        let mut a = self.begin(f.len(), false, false);
        let mut at = 0;
        while let Answer::Next(n) | Answer::Busy(n) = a {
            if matches!(a, Answer::Busy(_)) {
                self.flash_ops();
            }
            at = n as usize;
            if at >= f.len() {
                break;
            }
            let end = (at + CHUNK_MAX).min(f.len());
            a = self.chunk(at, &f[at..end]);
            self.now += 1000;
        }
        let _ = at;
        a
    }
}

#[test]
fn a_whole_update_lands_in_the_other_slot_and_boots_on_trial() {
    let mut b = Bench::new();
    let img = image(10_000, 5, "0.3.0");
    let f = update_file(&img, "esp32c3", "c3-supermini", "0.3.0", Some(&key()));
    assert_eq!(b.send(&f), Answer::Next(f.len() as u32));
    assert_eq!(b.ota.transfer().phase(), Phase::Finishing);
    assert_eq!(b.flash_ops(), Some(Done::Installed));
    let slot = LAYOUT.slots[1].0 as usize;
    assert_eq!(&b.flash[slot..slot + img.len()], &img[..]);
    assert!(b.flash[slot + img.len()..slot + 0x3000]
        .iter()
        .all(|&x| x == 0xFF));
    // The running slot (0) untouched.
    assert!(b.flash[0x20000..0x30000].iter().all(|&x| x == 0xFF));
    // otadata boots slot 1, new; the first boot marks it pending.
    let both = read_otadata(&b.flash);
    assert_eq!(otadata::booted_slot(&both), 1);
    let Start::WriteThenRun(w) = start(&both, Cause::Reset) else {
        panic!("no trial")
    };
    let mut both = both;
    both[w.sector] = Some(w.entry);
    let mut ota = Ota::new(Some(LAYOUT), both);
    assert_eq!(ota.trial(), Trial::OnTrial);
    assert!(!ota.tick(1000, false));
    assert!(ota.tick(2000, true));
    assert!(matches!(ota.next_op(), Some(Op::Otadata(_))));
    assert_eq!(ota.op_done(true), Done::Confirmed);
    assert_eq!(ota.trial(), Trial::Confirmed);
    assert_eq!(otadata::booted_slot(ota.otadata()), 1);
}

pub(crate) fn read_otadata(flash: &[u8]) -> otadata::Both {
    let at = LAYOUT.otadata as usize;
    [
        otadata::Entry::parse(&flash[at..at + 32]),
        otadata::Entry::parse(&flash[at + 0x1000..at + 0x1020]),
    ]
}

#[test]
fn with_no_bms_the_trial_confirms_after_ten_minutes() {
    let e = otadata::Entry::new(2, otadata::State::PendingVerify, "0.3.0");
    let mut ota = Ota::new(
        Some(LAYOUT),
        [
            Some(otadata::Entry::new(1, otadata::State::Valid, "")),
            Some(e),
        ],
    );
    assert!(!ota.tick(CONFIRM_AFTER_US - 1, false));
    assert!(ota.tick(CONFIRM_AFTER_US, false));
}

#[test]
fn duplicates_gaps_and_busy_change_nothing() {
    let mut b = Bench::new();
    let img = image(9000, 5, "0.3.0");
    let f = update_file(&img, "esp32c3", "c3-supermini", "0.3.0", Some(&key()));
    assert_eq!(b.begin(f.len(), false, false), Answer::Next(0));
    assert_eq!(b.chunk(0, &f[..128]), Answer::Next(128));
    // A duplicate, then a chunk after a lost one.
    assert_eq!(b.chunk(0, &f[..128]), Answer::Next(128));
    assert_eq!(b.chunk(384, &f[384..512]), Answer::Next(128));
    assert_eq!(b.chunk(128, &f[128..256]), Answer::Next(256));
    // Chunks that break the rules.
    assert_eq!(b.chunk(256, &[]), Answer::Next(256));
    assert_eq!(b.chunk(256, &f[256..256 + 200]), Answer::BadChunk);
    assert_eq!(b.chunk(f.len() - 10, &f[f.len() - 10..]), Answer::Next(256));
    assert_eq!(b.chunk(f.len(), &[1, 2]), Answer::BadChunk);
    // Across a sector of the image.
    assert_eq!(b.chunk(256, &f[256..256 + 100]), Answer::Next(356));
    let mut at = 356;
    while at + 128 <= 256 + 4096 {
        assert_eq!(b.chunk(at, &f[at..at + 128]), Answer::Next(at as u32 + 128));
        at += 128;
    }
    assert_eq!(
        b.chunk(at, &f[at..at + 128]),
        Answer::BadChunk,
        "crosses a sector"
    );
    let end = 256 + 4096;
    assert_eq!(b.chunk(at, &f[at..end]), Answer::Next(end as u32));
    // The full sector waits for the flash.
    assert_eq!(b.chunk(end, &f[end..end + 128]), Answer::Busy(end as u32));
    assert_eq!(b.chunk(end, &f[end..end + 128]), Answer::Busy(end as u32));
    b.flash_ops();
    assert_eq!(
        b.chunk(end, &f[end..end + 128]),
        Answer::Next(end as u32 + 128)
    );
    // The rest, with every chunk sent twice.
    let mut at = end + 128;
    while at < f.len() {
        let e = (at + 128)
            .min(f.len())
            .min(256 + (at - 256) / 4096 * 4096 + 4096);
        let mut a = b.chunk(at, &f[at..e]);
        if let Answer::Busy(_) = a {
            b.flash_ops();
            a = b.chunk(at, &f[at..e]);
        }
        assert_eq!(a, Answer::Next(e as u32));
        // The duplicate: where to go on (even while a sector waits).
        assert_eq!(b.chunk(at, &f[at..e]), Answer::Next(e as u32));
        at = e;
    }
    assert_eq!(b.flash_ops(), Some(Done::Installed));
    assert_eq!(&b.flash[0x20_0000..0x20_0000 + img.len()], &img[..]);
}

#[test]
fn a_stalled_transfer_is_abandoned_and_nothing_boots_differently() {
    let mut b = Bench::new();
    let img = image(9000, 5, "0.3.0");
    let f = update_file(&img, "esp32c3", "c3-supermini", "0.3.0", Some(&key()));
    b.begin(f.len(), false, false);
    for at in (0..4096 + 256).step_by(128) {
        b.chunk(at, &f[at..at + 128]);
    }
    b.flash_ops();
    assert_eq!(b.ota.transfer_mut().poll(b.now + STALL_US - 1), None);
    assert_eq!(
        b.ota.transfer_mut().poll(b.now + STALL_US),
        Some(Ended::Stalled)
    );
    assert_eq!(b.ota.transfer().outcome(), Some(Ended::Stalled));
    assert_eq!(b.ota.transfer().phase(), Phase::Idle);
    assert_eq!(b.chunk(4352, &f[4352..4480]), Answer::NotStarted);
    assert_eq!(b.ota.next_op(), None);
    assert_eq!(
        read_otadata(&b.flash),
        [None, None].map(|_: Option<()>| otadata::Entry::parse(&[0xFF; 32]))
    );
    assert_eq!(otadata::booted_slot(&read_otadata(&b.flash)), 0);
}

fn refused(b: &mut Bench, f: &[u8], downgrade: bool) -> Answer {
    let mut a = b.begin(f.len(), downgrade, false);
    let mut at = 0;
    while let Answer::Next(n) | Answer::Busy(n) = a {
        if matches!(a, Answer::Busy(_)) {
            b.flash_ops();
        }
        at = n as usize;
        if at >= f.len() {
            break;
        }
        let end = (at + CHUNK_MAX).min(f.len());
        a = b.chunk(at, &f[at..end]);
    }
    // The hash is checked once the last sector is written.
    if let Some(Done::Ended(e)) = b.flash_ops() {
        return Answer::Ended(e);
    }
    let _ = at;
    a
}

#[test]
fn every_refusal_is_refused_with_its_reason_and_nothing_boots_differently() {
    let k = key();
    let stranger = SigningKey::from_bytes(&[7; 32]);
    let img = image(5000, 5, "0.3.0");
    let good = update_file(&img, "esp32c3", "c3-supermini", "0.3.0", Some(&k));
    let mut truncated = good.clone();
    truncated.truncate(good.len() - 1);
    let mut padded = good.clone();
    padded.push(0);
    let mut corrupt = good.clone();
    corrupt[3000] ^= 0x10;
    let cases: Vec<(&str, Vec<u8>, bool, Refusal)> = std::vec![
        (
            "wrong chip",
            update_file(
                &image(5000, 13, "0.3.0"),
                "esp32c6",
                "c6-devkitc-1",
                "0.3.0",
                Some(&k)
            ),
            false,
            Refusal::WrongChip
        ),
        (
            "wrong board",
            update_file(&img, "esp32c3", "c3-devkitm-1", "0.3.0", Some(&k)),
            false,
            Refusal::WrongBoard
        ),
        (
            "unsigned",
            update_file(&img, "esp32c3", "c3-supermini", "0.3.0", None),
            false,
            Refusal::Unsigned
        ),
        (
            "a stranger's key",
            update_file(&img, "esp32c3", "c3-supermini", "0.3.0", Some(&stranger)),
            false,
            Refusal::BadSignature
        ),
        (
            "older",
            update_file(
                &image(5000, 5, "0.1.0"),
                "esp32c3",
                "c3-supermini",
                "0.1.0",
                Some(&k)
            ),
            false,
            Refusal::Older
        ),
        ("truncated", truncated, false, Refusal::Truncated),
        ("padded", padded, false, Refusal::Padded),
        (
            "corrupted on the way",
            corrupt,
            false,
            Refusal::HashMismatch
        ),
        (
            "an image for the other chip",
            update_file(
                &image(5000, 13, "0.3.0"),
                "esp32c3",
                "c3-supermini",
                "0.3.0",
                Some(&k)
            ),
            false,
            Refusal::NotAnImage
        ),
        ("not an update", img.clone(), false, Refusal::NotAnUpdate),
    ];
    for (what, f, downgrade, why) in cases {
        let mut b = Bench::new();
        assert_eq!(
            refused(&mut b, &f, downgrade),
            Answer::Ended(Ended::Refused(why)),
            "{what}"
        );
        assert_eq!(
            b.ota.transfer().outcome(),
            Some(Ended::Refused(why)),
            "{what}"
        );
        assert!(
            b.flash[LAYOUT.otadata as usize..LAYOUT.otadata as usize + 0x2000]
                .iter()
                .all(|&x| x == 0xFF),
            "{what}: otadata written"
        );
        assert!(
            b.flash[0x20000..0x20_0000].iter().all(|&x| x == 0xFF),
            "{what}: the running slot written"
        );
    }
    // The older one with downgrade: taken.
    let mut b = Bench::new();
    let old = update_file(
        &image(5000, 5, "0.1.0"),
        "esp32c3",
        "c3-supermini",
        "0.1.0",
        Some(&k),
    );
    assert_eq!(refused(&mut b, &old, true), Answer::Next(old.len() as u32));
    assert_eq!(b.ota.transfer().phase(), Phase::Installed);
    // Without a second slot.
    let mut b = Bench::new();
    b.ota.layout = None;
    assert_eq!(
        refused(&mut b, &good, false),
        Answer::Ended(Ended::Refused(Refusal::NoSlot))
    );
}

#[test]
fn check_reads_the_header_only() {
    let mut b = Bench::new();
    let f = update_file(
        &image(5000, 5, "0.3.0"),
        "esp32c3",
        "c3-supermini",
        "0.3.0",
        Some(&key()),
    );
    assert_eq!(b.begin(f.len(), false, true), Answer::Next(0));
    assert_eq!(b.chunk(0, &f[..128]), Answer::Next(128));
    assert_eq!(b.chunk(128, &f[128..256]), Answer::Acceptable);
    assert_eq!(b.ota.transfer().phase(), Phase::Idle);
    assert_eq!(b.ops, 0);
    assert_eq!(b.chunk(256, &f[256..384]), Answer::NotStarted);
    assert!(b.begin(100, false, true) == Answer::Ended(Ended::Refused(Refusal::Truncated)));
}

/// Issue 51, item 9: the newest version a file that passed every check
/// offered (a `check` too) is what Home Assistant may call the latest; an
/// older one or a refused one changes nothing; nothing known: `None`.
#[test]
fn the_latest_known_version_is_the_newest_checked_file() {
    let mut b = Bench::new();
    assert_eq!(b.ota.latest("0.2.0"), None);
    let offer = |b: &mut Bench, version: &str, k: &SigningKey| {
        let f = update_file(
            &image(5000, 5, version),
            "esp32c3",
            "c3-supermini",
            version,
            Some(k),
        );
        b.begin(f.len(), true, true);
        b.chunk(0, &f[..128]);
        b.chunk(128, &f[128..256])
    };
    assert_eq!(offer(&mut b, "0.3.0", &key()), Answer::Acceptable);
    assert_eq!(b.ota.latest("0.2.0"), Some("0.3.0"));
    assert_eq!(
        b.ota.latest("0.3.0"),
        None,
        "not newer than the running one"
    );
    // Older, or signed by a stranger: the latest stays.
    assert_eq!(offer(&mut b, "0.2.5", &key()), Answer::Acceptable);
    let stranger = SigningKey::from_bytes(&[7; 32]);
    assert!(matches!(
        offer(&mut b, "0.9.0", &stranger),
        Answer::Ended(_)
    ));
    assert_eq!(b.ota.latest("0.2.0"), Some("0.3.0"));
}

#[test]
fn keys_come_from_the_hex_digits() {
    let hex = b"00112233445566778899aabbccddeeff00112233445566778899AABBCCDDEEFF";
    let k = parse_key(hex).unwrap();
    assert_eq!(k[1], 0x11);
    assert_eq!(k[31], 0xFF);
    assert!(parse_key(&hex[..63]).is_none());
    assert!(
        parse_key(b"zz112233445566778899aabbccddeeff00112233445566778899AABBCCDDEEFF").is_none()
    );
    let _ = HEADER_LEN;
}
