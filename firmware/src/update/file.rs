//! The update file: a 256-byte signed header, then the app image exactly as
//! the bootloader loads it from a slot (what `pack-images` writes as
//! `…-app.bin`). Made by `tinybms sign`, read here on the bridge and by the
//! tool's `update --check`.
//!
//! | bytes | what |
//! | --- | --- |
//! | 0..8 | magic `TBMSUPD1` |
//! | 8..12 | the image's length, `u32` little-endian |
//! | 12..44 | the image's SHA-256 |
//! | 44..60 | chip (`esp32c3`, `esp32c6`), zero-padded |
//! | 60..84 | board (`c3-supermini`, …) |
//! | 84..124 | features (`can,host-link,wifi,store`) |
//! | 124..148 | version (`0.2.0`) |
//! | 148..180 | build (what it was built from) |
//! | 180..192 | zero |
//! | 192..256 | Ed25519 signature of bytes 0..192 |
//!
//! The signature covers the image through its hash: the bridge checks the
//! signature when the header is in, before it writes a byte, and the hash
//! when the last byte is in, before the image may boot.

use ed25519_dalek::{Signature, VerifyingKey};

/// The header's length.
pub const HEADER_LEN: usize = 256;
/// What the signature covers.
pub const SIGNED_LEN: usize = 192;
/// The magic.
pub const MAGIC: &[u8; 8] = b"TBMSUPD1";

const CHIP: (usize, usize) = (44, 60);
const BOARD: (usize, usize) = (60, 84);
const FEATURES: (usize, usize) = (84, 124);
const VERSION: (usize, usize) = (124, 148);
const BUILD: (usize, usize) = (148, 180);

/// An Ed25519 public key.
pub type Key = [u8; 32];

/// Why an update is refused. Nothing is written for any of them, or what was
/// written to the inactive slot is left there unused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Refusal {
    /// The file does not start with the magic.
    NotAnUpdate,
    /// A header field is not text.
    Malformed,
    /// The file is for another chip.
    WrongChip,
    /// The file is for another board.
    WrongBoard,
    /// The signature is all zeros (an unsigned file).
    Unsigned,
    /// No key this bridge trusts made the signature.
    BadSignature,
    /// The bridge trusts no key at all (a build without one, none registered).
    NoKey,
    /// The version is older than the running one (send it with `downgrade`).
    Older,
    /// The file is shorter than its header says.
    Truncated,
    /// The file is longer than its header says.
    Padded,
    /// The image is larger than the slot (the words name both tables' slot
    /// sizes: `firmware/partitions.csv`'s and the one before the history
    /// partition, which bridges updated over the network keep).
    TooBig,
    /// The image does not start as an app image for this chip.
    NotAnImage,
    /// The image's bytes do not give the signed hash.
    HashMismatch,
    /// The bridge has no second slot (its partition table has no `otadata`
    /// or not two app slots: reinstall once by cable).
    NoSlot,
    /// The update lacks a feature the running image has (Wi-Fi: the
    /// network, Home Assistant and updates without a cable would be gone)
    /// and the owner did not say to drop it.
    DropsFeatures,
}

impl Refusal {
    /// A short key (host link, MQTT).
    pub const fn key(self) -> &'static str {
        match self {
            Self::NotAnUpdate => "not_an_update",
            Self::Malformed => "malformed",
            Self::WrongChip => "wrong_chip",
            Self::WrongBoard => "wrong_board",
            Self::Unsigned => "unsigned",
            Self::BadSignature => "bad_signature",
            Self::NoKey => "no_key",
            Self::Older => "older",
            Self::Truncated => "truncated",
            Self::Padded => "padded",
            Self::TooBig => "too_big",
            Self::NotAnImage => "not_an_image",
            Self::HashMismatch => "hash_mismatch",
            Self::NoSlot => "no_slot",
            Self::DropsFeatures => "drops_features",
        }
    }

    /// The words.
    pub const fn words(self) -> &'static str {
        match self {
            Self::NotAnUpdate => "not an update file (no TBMSUPD1 header)",
            Self::Malformed => "the update file's header is malformed",
            Self::WrongChip => "the update is for another chip",
            Self::WrongBoard => "the update is for another board",
            Self::Unsigned => "the update is not signed",
            Self::BadSignature => "the signature is not from a key this bridge trusts",
            Self::NoKey => "this bridge trusts no signing key (register one over USB)",
            Self::Older => {
                "the update is older than the running firmware (send it with --downgrade)"
            }
            Self::Truncated => "the update file is shorter than its header says",
            Self::Padded => "the update file is longer than its header says",
            Self::TooBig => {
                "the image is larger than the app slot (1728 KiB; 1984 KiB on a bridge \
                 installed before the history partition)"
            }
            Self::NotAnImage => "the image is not an app image for this chip",
            Self::HashMismatch => "the image does not match its signed hash",
            Self::NoSlot => "no second app slot (reinstall once by cable: docs/updates.md)",
            Self::DropsFeatures => {
                "the update lacks a feature this bridge runs (its header's features; a Wi-Fi \
                 bridge would lose its network and updates without a cable): take the file \
                 with the same features, or drop them on purpose (tinybms update --drop)"
            }
        }
    }
}

/// A parsed header (its signature not yet checked: [`Header::verify`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Header {
    bytes: [u8; HEADER_LEN],
    /// The image's length.
    pub image_len: u32,
}

fn text(b: &[u8; HEADER_LEN], (from, to): (usize, usize)) -> Result<&str, Refusal> {
    let f = b.get(from..to).ok_or(Refusal::Malformed)?;
    let end = f.iter().position(|&c| c == 0).unwrap_or(f.len());
    let (t, pad) = f.split_at(end);
    if pad.iter().any(|&c| c != 0) {
        return Err(Refusal::Malformed);
    }
    let s = core::str::from_utf8(t).map_err(|_| Refusal::Malformed)?;
    if s.bytes().all(|c| c.is_ascii_graphic()) {
        Ok(s)
    } else {
        Err(Refusal::Malformed)
    }
}

impl Header {
    /// Reads the first [`HEADER_LEN`] bytes of a file.
    pub fn parse(bytes: &[u8; HEADER_LEN]) -> Result<Self, Refusal> {
        if bytes.get(..8) != Some(&MAGIC[..]) {
            return Err(Refusal::NotAnUpdate);
        }
        let mut len = [0u8; 4];
        len.copy_from_slice(bytes.get(8..12).ok_or(Refusal::Malformed)?);
        for f in [CHIP, BOARD, FEATURES, VERSION, BUILD] {
            text(bytes, f)?;
        }
        if bytes
            .get(180..192)
            .is_none_or(|z| z.iter().any(|&c| c != 0))
        {
            return Err(Refusal::Malformed);
        }
        Ok(Self {
            bytes: *bytes,
            image_len: u32::from_le_bytes(len),
        })
    }

    /// The header's bytes (for a builder: sign 0..[`SIGNED_LEN`]).
    pub fn bytes(&self) -> &[u8; HEADER_LEN] {
        &self.bytes
    }

    /// The image's signed SHA-256.
    pub fn image_sha256(&self) -> [u8; 32] {
        let mut h = [0u8; 32];
        h.copy_from_slice(self.bytes.get(12..44).unwrap_or(&[0; 32]));
        h
    }

    fn field(&self, f: (usize, usize)) -> &str {
        text(&self.bytes, f).unwrap_or("")
    }

    /// The chip it is for.
    pub fn chip(&self) -> &str {
        self.field(CHIP)
    }
    /// The board it is for.
    pub fn board(&self) -> &str {
        self.field(BOARD)
    }
    /// What is built in, comma-separated.
    pub fn features(&self) -> &str {
        self.field(FEATURES)
    }
    /// Its version.
    pub fn version(&self) -> &str {
        self.field(VERSION)
    }
    /// What it was built from.
    pub fn build(&self) -> &str {
        self.field(BUILD)
    }

    /// The signature's bytes.
    pub fn signature(&self) -> [u8; 64] {
        let mut s = [0u8; 64];
        s.copy_from_slice(self.bytes.get(SIGNED_LEN..).unwrap_or(&[0; 64]));
        s
    }

    /// Checks the signature against every key trusted; the index of the one
    /// that made it.
    pub fn verify(&self, keys: &[Key]) -> Result<usize, Refusal> {
        let sig = self.signature();
        if sig.iter().all(|&b| b == 0) {
            return Err(Refusal::Unsigned);
        }
        if keys.is_empty() {
            return Err(Refusal::NoKey);
        }
        let signature = Signature::from_bytes(&sig);
        let signed = self.bytes.get(..SIGNED_LEN).unwrap_or(&[]);
        keys.iter()
            .position(|k| {
                VerifyingKey::from_bytes(k)
                    .is_ok_and(|vk| vk.verify_strict(signed, &signature).is_ok())
            })
            .ok_or(Refusal::BadSignature)
    }

    /// Everything but the signature and the image, against the running
    /// bridge: chip, board, size, version, and the features it runs (each
    /// one the update lacks must be in the permit's `drop`).
    pub fn check(&self, me: &Target<'_>, permit: Permit) -> Result<(), Refusal> {
        let Permit { downgrade, drop } = permit;
        if self.chip() != me.chip {
            return Err(Refusal::WrongChip);
        }
        if self.board() != me.board {
            return Err(Refusal::WrongBoard);
        }
        if self.image_len > me.slot_size || self.image_len == 0 {
            return Err(Refusal::TooBig);
        }
        if !downgrade && older(self.version(), me.version) {
            return Err(Refusal::Older);
        }
        if lacks(self.features(), me.features) & !drop != 0 {
            return Err(Refusal::DropsFeatures);
        }
        Ok(())
    }
}

/// What the owner allows an update that the bridge would otherwise refuse.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Permit {
    /// A version older than the running one.
    pub downgrade: bool,
    /// Features the update may lack (bits of [`FEATURE_NAMES`]).
    pub drop: u8,
}

impl Permit {
    /// Nothing beyond the rules.
    pub const NONE: Self = Self {
        downgrade: false,
        drop: 0,
    };
    /// An older version.
    pub const DOWNGRADE: Self = Self {
        downgrade: true,
        drop: 0,
    };
}

/// The features an image can have, by name (bit n for the n-th): what an
/// update may not lack unless the owner says so.
pub use crate::identity::FEATURE_NAMES;

/// The bits of a comma-separated list of [`FEATURE_NAMES`] (`None`: a name
/// not among them). White space around a name is allowed; empty = none.
pub fn feature_bits(list: &str) -> Option<u8> {
    let mut bits = 0u8;
    for name in list.split(',').map(str::trim).filter(|n| !n.is_empty()) {
        let i = FEATURE_NAMES.iter().position(|&f| f == name)?;
        bits |= 1 << i;
    }
    Some(bits)
}

/// The features `running` has (bits) that an update naming `update` lacks.
/// An unknown name in the update's list is ignored (a later feature).
pub fn lacks(update: &str, running: u8) -> u8 {
    let has = update
        .split(',')
        .filter_map(|n| FEATURE_NAMES.iter().position(|&f| f == n.trim()))
        .fold(0u8, |b, i| b | (1 << i));
    running & !has
}

/// The bridge an update is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Target<'a> {
    /// Its chip.
    pub chip: &'a str,
    /// Its board.
    pub board: &'a str,
    /// The running version.
    pub version: &'a str,
    /// The features the running image has (bits of [`FEATURE_NAMES`]).
    pub features: u8,
    /// The inactive slot's size, bytes.
    pub slot_size: u32,
}

/// A version as `major.minor.patch`, a `-suffix` (a pre-release) before the
/// release of the same numbers.
fn parts(v: &str) -> Option<(u32, u32, u32, bool)> {
    let (nums, pre) = match v.split_once('-') {
        Some((n, _)) => (n, true),
        None => (v, false),
    };
    let mut it = nums.split('.').map(|p| p.parse::<u32>().ok());
    let t = (it.next()??, it.next()??, it.next()??);
    it.next().is_none().then_some((t.0, t.1, t.2, !pre))
}

/// `new` is older than `running` (an unreadable version counts as older:
/// only `downgrade` takes it).
pub fn older(new: &str, running: &str) -> bool {
    match (parts(new), parts(running)) {
        (Some(n), Some(r)) => n < r,
        _ => true,
    }
}

/// The chip id in an ESP app image's extended header, by chip name.
pub fn chip_id(chip: &str) -> Option<u16> {
    match chip {
        "esp32c3" => Some(0x0005),
        "esp32c6" => Some(0x000D),
        _ => None,
    }
}

/// The first bytes of an image are an ESP app image for `chip`: magic `E9`
/// and the chip id of the extended header (bytes 12..14), then the app
/// descriptor's magic `ABCD5432` at byte 32 (the first segment's start).
pub fn image_start_ok(first: &[u8], chip: &str) -> bool {
    let Some(id) = chip_id(chip) else {
        return false;
    };
    let word = |at: usize| {
        first
            .get(at..at + 4)
            .and_then(|b| <[u8; 4]>::try_from(b).ok())
            .map(u32::from_le_bytes)
    };
    first.first() == Some(&0xE9)
        && first.get(12..14) == Some(&id.to_le_bytes()[..])
        && word(32) == Some(0xABCD_5432)
}

/// A text field of an app image's descriptor (C string, at most its width).
fn descriptor_text(first: &[u8], (from, to): (usize, usize)) -> Option<&str> {
    let v = first.get(from..to)?;
    let end = v.iter().position(|&b| b == 0).unwrap_or(v.len());
    core::str::from_utf8(v.get(..end)?).ok()
}

/// The version in an app image's descriptor (`esp_app_desc_t.version`, bytes
/// 48..80 of the image): the version the image reports.
pub fn image_version(first: &[u8]) -> Option<&str> {
    descriptor_text(first, (48, 80))
}

/// The build in an app image's descriptor (`esp_app_desc_t.project_name`,
/// bytes 80..112 of the image): what the image says it was built from
/// (`hello`'s `build`; the firmware puts it there).
pub fn image_build(first: &[u8]) -> Option<&str> {
    descriptor_text(first, (80, 112))
}

/// A header for an image (for the signing tool and the tests): unsigned.
#[allow(clippy::too_many_arguments)]
pub fn unsigned_header(
    image_len: u32,
    sha256: &[u8; 32],
    chip: &str,
    board: &str,
    features: &str,
    version: &str,
    build: &str,
) -> Result<[u8; HEADER_LEN], Refusal> {
    let mut b = [0u8; HEADER_LEN];
    b[..8].copy_from_slice(MAGIC);
    b[8..12].copy_from_slice(&image_len.to_le_bytes());
    b[12..44].copy_from_slice(sha256);
    for ((from, to), s) in [
        (CHIP, chip),
        (BOARD, board),
        (FEATURES, features),
        (VERSION, version),
        (BUILD, build),
    ] {
        let f = b.get_mut(from..to).ok_or(Refusal::Malformed)?;
        if s.len() > f.len() {
            return Err(Refusal::Malformed);
        }
        f.get_mut(..s.len())
            .ok_or(Refusal::Malformed)?
            .copy_from_slice(s.as_bytes());
    }
    Header::parse(&b).map(|_| b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ed25519_dalek::{Signer, SigningKey};

    fn signed(key: &SigningKey, version: &str) -> Header {
        let mut b = unsigned_header(
            1000,
            &[7; 32],
            "esp32c3",
            "c3-supermini",
            "can,host-link",
            version,
            "v1",
        )
        .unwrap();
        let sig = key.sign(&b[..SIGNED_LEN]);
        b[SIGNED_LEN..].copy_from_slice(&sig.to_bytes());
        Header::parse(&b).unwrap()
    }

    const ME: Target<'static> = Target {
        chip: "esp32c3",
        board: "c3-supermini",
        version: "0.2.0",
        features: 0b0011,
        slot_size: 0x1E_0000,
    };

    #[test]
    fn a_signed_header_verifies_with_its_key_only() {
        let k = SigningKey::from_bytes(&[1; 32]);
        let other = SigningKey::from_bytes(&[2; 32]);
        let h = signed(&k, "0.3.0");
        assert_eq!(
            h.verify(&[
                other.verifying_key().to_bytes(),
                k.verifying_key().to_bytes()
            ]),
            Ok(1)
        );
        assert_eq!(
            h.verify(&[other.verifying_key().to_bytes()]),
            Err(Refusal::BadSignature)
        );
        assert_eq!(h.verify(&[]), Err(Refusal::NoKey));
        assert_eq!(
            (h.chip(), h.board(), h.version(), h.build()),
            ("esp32c3", "c3-supermini", "0.3.0", "v1")
        );
        // Any bit of the signed part changed: refused.
        for at in [0usize, 8, 12, 50, 70, 130, 191] {
            let mut b = *h.bytes();
            b[at] ^= 1;
            if let Ok(t) = Header::parse(&b) {
                assert_eq!(
                    t.verify(&[k.verifying_key().to_bytes()]),
                    Err(Refusal::BadSignature),
                    "byte {at}"
                );
            }
        }
    }

    #[test]
    fn unsigned_and_foreign_files_are_refused() {
        let b = unsigned_header(10, &[0; 32], "esp32c3", "c3-supermini", "", "1.0.0", "").unwrap();
        let h = Header::parse(&b).unwrap();
        assert_eq!(h.verify(&[[9; 32]]), Err(Refusal::Unsigned));
        let mut not = b;
        not[0] = b'X';
        assert_eq!(Header::parse(&not), Err(Refusal::NotAnUpdate));
        let mut junk = b;
        junk[45] = 0x01;
        assert_eq!(Header::parse(&junk), Err(Refusal::Malformed));
        let mut trailing = b;
        trailing[185] = 1;
        assert_eq!(Header::parse(&trailing), Err(Refusal::Malformed));
    }

    #[test]
    fn chip_board_size_and_version_are_checked() {
        let k = SigningKey::from_bytes(&[1; 32]);
        assert_eq!(signed(&k, "0.3.0").check(&ME, Permit::NONE), Ok(()));
        assert_eq!(signed(&k, "0.2.0").check(&ME, Permit::NONE), Ok(()));
        assert_eq!(
            signed(&k, "0.1.9").check(&ME, Permit::NONE),
            Err(Refusal::Older)
        );
        assert_eq!(signed(&k, "0.1.9").check(&ME, Permit::DOWNGRADE), Ok(()));
        assert_eq!(
            signed(&k, "0.2.0-rc1").check(&ME, Permit::NONE),
            Err(Refusal::Older)
        );
        assert_eq!(
            signed(&k, "junk").check(&ME, Permit::NONE),
            Err(Refusal::Older)
        );
        let c6 = Target {
            chip: "esp32c6",
            ..ME
        };
        assert_eq!(
            signed(&k, "0.3.0").check(&c6, Permit::NONE),
            Err(Refusal::WrongChip)
        );
        let board = Target {
            board: "c3-devkitm-1",
            ..ME
        };
        assert_eq!(
            signed(&k, "0.3.0").check(&board, Permit::NONE),
            Err(Refusal::WrongBoard)
        );
        let small = Target {
            slot_size: 999,
            ..ME
        };
        assert_eq!(
            signed(&k, "0.3.0").check(&small, Permit::NONE),
            Err(Refusal::TooBig)
        );
    }

    #[test]
    fn an_update_that_lacks_a_running_feature_needs_the_owner_s_word() {
        let k = SigningKey::from_bytes(&[1; 32]);
        // The file has can,host-link.
        let wifi = Target {
            features: feature_bits("can,host-link,wifi,store").unwrap(),
            ..ME
        };
        assert_eq!(
            signed(&k, "0.3.0").check(&wifi, Permit::NONE),
            Err(Refusal::DropsFeatures)
        );
        let only_wifi = feature_bits("wifi").unwrap();
        assert_eq!(
            signed(&k, "0.3.0").check(
                &wifi,
                Permit {
                    drop: only_wifi,
                    ..Permit::NONE
                }
            ),
            Err(Refusal::DropsFeatures),
            "store too"
        );
        let both = feature_bits("wifi, store").unwrap();
        assert_eq!(
            signed(&k, "0.3.0").check(
                &wifi,
                Permit {
                    drop: both,
                    ..Permit::NONE
                }
            ),
            Ok(())
        );
        // Gaining one needs nothing.
        let less = Target {
            features: feature_bits("can").unwrap(),
            ..ME
        };
        assert_eq!(signed(&k, "0.3.0").check(&less, Permit::NONE), Ok(()));
        assert_eq!(feature_bits("wifi,radio"), None);
        assert_eq!(feature_bits(""), Some(0));
        assert_eq!(
            lacks("can,host-link,later", feature_bits("can,wifi").unwrap()),
            1 << 2
        );
    }

    #[test]
    fn versions_order_as_releases() {
        assert!(older("0.1.0", "0.2.0"));
        assert!(older("0.2.0-rc1", "0.2.0"));
        assert!(!older("0.2.0", "0.2.0-rc1"));
        assert!(!older("0.10.0", "0.9.9"));
        assert!(older("1.2", "0.1.0"));
    }

    #[test]
    fn an_app_image_start_names_its_chip() {
        let mut first = [0u8; 80];
        first[0] = 0xE9;
        first[12..14].copy_from_slice(&5u16.to_le_bytes());
        first[32..36].copy_from_slice(&0xABCD_5432u32.to_le_bytes());
        first[48..53].copy_from_slice(b"0.2.0");
        assert!(image_start_ok(&first, "esp32c3"));
        assert!(!image_start_ok(&first, "esp32c6"));
        assert!(!image_start_ok(&first[..20], "esp32c3"));
        assert_eq!(image_version(&first), Some("0.2.0"));
        first[0] = 0xE8;
        assert!(!image_start_ok(&first, "esp32c3"));
    }
}
