//! The desktop station's chip flash for updates: a 4 MiB flash in RAM with
//! the firmware's own partition table (`firmware/partitions.csv`, in the
//! bytes ESP-IDF's and espflash's table format gives it), on which the
//! station's update work runs through the same procedure as on the chip
//! (`tinybms_firmware::update::flash`). A restart boots what `otadata`
//! says; the image in a slot is known by its app descriptor (its version;
//! an image whose project name is [`PANICS`] stands for one that panics
//! when it has run long enough to confirm itself, before it does).

use embedded_storage_async::nor_flash::{NorFlash, ReadNorFlash};
use md5::{Digest, Md5};
use tinybms_firmware::update::flash::{self, Booted, OtaFlash};
use tinybms_firmware::update::otadata::{self, Cause};
use tinybms_firmware::update::transfer::Layout;
use tinybms_firmware::update::Ota;

use crate::flash::RamFlash;

/// The firmware's partition table, as its images carry it.
pub const PARTITIONS_CSV: &str = include_str!("../../../firmware/partitions.csv");
/// The table every image carried before the history partition (issue 55): a
/// bridge installed with it keeps it through updates over the network.
pub const PRE_HISTORY_CSV: &str = include_str!("../../../firmware/partitions-pre-history.csv");
/// The chip's flash, bytes.
pub const CHIP_BYTES: usize = 4 * 1024 * 1024;
/// The project name of a simulated image that panics before it confirms
/// itself.
pub const PANICS: &str = "tinybms-panics";

/// The partition table's bytes from a CSV of ESP-IDF's form (name, type,
/// subtype, offset, size, flags): 32 bytes per entry, then the MD5 entry,
/// then erased bytes up to 0xC00.
pub fn table_bytes(csv: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    for line in csv
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
    {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        let [name, kind, sub, offset, size, ..] = f.as_slice() else {
            return Err(format!("not a partition: {line}"));
        };
        let kind = match *kind {
            "app" => 0u8,
            "data" => 1,
            k => return Err(format!("type {k}")),
        };
        let sub = match *sub {
            "factory" => 0x00u8,
            "ota" => 0x00,
            "phy" => 0x01,
            "nvs" => 0x02,
            "undefined" => 0x06,
            s if s.starts_with("ota_") => 0x10 + s[4..].parse::<u8>().map_err(|e| e.to_string())?,
            s => return Err(format!("subtype {s}")),
        };
        let num = |s: &str| {
            u32::from_str_radix(s.trim_start_matches("0x"), 16).map_err(|e| e.to_string())
        };
        let mut e = [0u8; 32];
        e[..2].copy_from_slice(&[0xAA, 0x50]);
        e[2] = kind;
        e[3] = sub;
        e[4..8].copy_from_slice(&num(offset)?.to_le_bytes());
        e[8..12].copy_from_slice(&num(size)?.to_le_bytes());
        if name.len() > 16 {
            return Err(format!("label {name}"));
        }
        e[12..12 + name.len()].copy_from_slice(name.as_bytes());
        out.extend_from_slice(&e);
    }
    let md5 = Md5::digest(&out);
    out.extend_from_slice(&[0xEB, 0xEB]);
    out.extend_from_slice(&[0xFF; 14]);
    out.extend_from_slice(&md5);
    out.resize(0xC00, 0xFF);
    Ok(out)
}

/// A chip's flash, erased, with the partition table at 0x8000.
pub fn chip_flash() -> RamFlash {
    let mut bytes = vec![0xFF; CHIP_BYTES];
    let table = table_bytes(PARTITIONS_CSV).unwrap_or_default();
    bytes[0x8000..0x8000 + table.len()].copy_from_slice(&table);
    RamFlash::from_bytes(bytes)
}

/// The update flash work on a [`RamFlash`] (NOR semantics: a program only
/// clears bits).
#[derive(Debug, Clone)]
pub struct ChipFlash(pub RamFlash);

impl OtaFlash for ChipFlash {
    fn read(&mut self, at: u32, buf: &mut [u8]) -> bool {
        embassy_futures::block_on(self.0.read(at, buf)).is_ok()
    }
    fn erase_sector(&mut self, at: u32) -> bool {
        embassy_futures::block_on(self.0.erase(at, at + flash::ERASE)).is_ok()
    }
    fn program(&mut self, at: u32, bytes: &[u8]) -> bool {
        // The flash's own NOR write (a program only clears bits).
        embassy_futures::block_on(self.0.write(at, bytes)).is_ok()
    }
}

/// What a boot of the desktop chip runs.
#[derive(Debug, Clone)]
pub struct Image {
    /// The update side for the station.
    pub ota: Ota,
    /// The version the image says (`None`: the slot holds no app image: the
    /// desktop station's own build).
    pub version: Option<String>,
    /// It stands for an image that panics before it confirms itself.
    pub panics: bool,
}

/// The descriptor's text at `at..at + 32` of an app image.
fn desc_text(image: &[u8], at: usize) -> Option<String> {
    let f = image.get(at..at + 32)?;
    let end = f.iter().position(|&b| b == 0).unwrap_or(f.len());
    String::from_utf8(f[..end].to_vec()).ok()
}

/// The app image in `slot`: its version and project name.
pub fn image_in_slot(flash: &RamFlash, layout: &Layout, slot: u32) -> Option<(String, String)> {
    let (offset, _) = *layout.slots.get(slot as usize)?;
    let data = flash.lock();
    let head = data.get(offset as usize..offset as usize + 112)?;
    if head[0] != 0xE9 || head[32..36] != 0xABCD_5432u32.to_le_bytes() {
        return None;
    }
    Some((desc_text(head, 48)?, desc_text(head, 80)?))
}

/// Boots the chip: the bootloader's choice, the image's trial or rollback
/// (a rollback restarts at once, as on the chip).
pub fn boot(flash: &RamFlash, mut cause: Cause) -> Image {
    let mut chip = ChipFlash(flash.clone());
    let mut rollbacks = 0;
    loop {
        match flash::boot(&mut chip, cause) {
            Booted::Restart { .. } if rollbacks < 4 => {
                rollbacks += 1;
                cause = Cause::Reset;
            }
            Booted::Restart { .. } => {
                return Image {
                    ota: Ota::default(),
                    version: None,
                    panics: false,
                }
            }
            Booted::Run(ota) => {
                let slot = otadata::booted_slot(ota.otadata());
                let found = ota.layout().and_then(|l| image_in_slot(flash, l, slot));
                return Image {
                    panics: found.as_ref().is_some_and(|(_, p)| p == PANICS),
                    version: found.map(|(v, _)| v),
                    ota,
                };
            }
        }
    }
}
