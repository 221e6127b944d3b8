//! `pack-images CHIP ELF MERGED APP [PARTITIONS_CSV]`: the two images of one
//! firmware ELF.
//!
//! * `MERGED`: the second-stage bootloader at 0x0, the partition table at
//!   0x8000 and the app in the first app partition (0x20000 with the
//!   firmware's `partitions.csv`), the gaps filled with 0xFF and nothing after
//!   the app (`espflash save-image --chip CHIP --merge --skip-padding
//!   --partition-table CSV`);
//! * `APP`: the app image alone, for that partition (`espflash save-image
//!   --chip CHIP`).
//!
//! Both with espflash's defaults otherwise: its bootloader for the chip, 4 MiB
//! of flash, the chip's usual crystal, minimum chip revision 0.0; without a
//! CSV, its default partition table. An ELF without an ESP-IDF app descriptor
//! is refused, as espflash refuses it.

use std::path::Path;
use std::process::ExitCode;

use espflash::flasher::{FlashData, FlashSettings, FlashSize};
use espflash::image_format::idf::{check_idf_bootloader, IdfBootloaderFormat};
use espflash::image_format::ImageFormat;
use espflash::target::Chip;

const USAGE: &str = "usage: pack-images esp32c3|esp32c6 ELF MERGED_BIN APP_BIN [PARTITIONS_CSV]";

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (chip, elf, merged, app, table) = match args.as_slice() {
        [c, e, m, a] => (c, e, m, a, None),
        [c, e, m, a, t] => (c, e, m, a, Some(Path::new(t))),
        _ => {
            eprintln!("{USAGE}");
            return ExitCode::from(2);
        }
    };
    match pack(
        chip,
        Path::new(elf),
        Path::new(merged),
        Path::new(app),
        table,
    ) {
        Ok(size) => {
            println!("{elf}: app {size} bytes");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("pack-images: {elf}: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Writes both images of `elf` (with the partition table `table`, else
/// espflash's default); the app's size in bytes.
fn pack(
    chip: &str,
    elf: &Path,
    merged: &Path,
    app: &Path,
    table: Option<&Path>,
) -> Result<usize, String> {
    let chip: Chip = match chip {
        "esp32c3" => Chip::Esp32c3,
        "esp32c6" => Chip::Esp32c6,
        other => return Err(format!("chip {other:?}: esp32c3 or esp32c6")),
    };
    let data = std::fs::read(elf).map_err(|e| format!("cannot read: {e}"))?;
    check_idf_bootloader(&data).map_err(|e| format!("{e}"))?;
    let image = image(&data, chip, table)?;
    let merged_bytes = merge(image.clone().flash_segments())?;
    let ota = image.ota_segments();
    let [single] = ota.as_slice() else {
        return Err(format!("{} app segments, expected one", ota.len()));
    };
    std::fs::write(merged, &merged_bytes).map_err(|e| format!("{}: {e}", merged.display()))?;
    std::fs::write(app, &single.data).map_err(|e| format!("{}: {e}", app.display()))?;
    Ok(single.data.len())
}

/// espflash's image of `elf` for `chip`, with its defaults and `table`.
fn image<'a>(elf: &'a [u8], chip: Chip, table: Option<&Path>) -> Result<ImageFormat<'a>, String> {
    let settings = FlashSettings::new(None, Some(FlashSize::default()), None);
    let flash = FlashData::new(settings, 0, None, chip, chip.default_xtal_frequency());
    IdfBootloaderFormat::new(elf, &flash, table, None, None, None)
        .map(ImageFormat::from)
        .map_err(|e| format!("{e}"))
}

/// The segments at their addresses, the gaps filled with 0xFF.
fn merge(segments: Vec<espflash::image_format::Segment<'_>>) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    for s in segments {
        let at = s.addr as usize;
        if at < out.len() {
            return Err(format!("segment at {at:#x} overlaps the one before it"));
        }
        out.resize(at, 0xFF);
        out.extend_from_slice(&s.data);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use espflash::image_format::Segment;

    #[test]
    fn segments_land_at_their_addresses_with_erased_flash_between() {
        let a = [1u8, 2];
        let b = [3u8];
        let out = merge(vec![Segment::new(0, &a), Segment::new(4, &b)]).unwrap();
        assert_eq!(out, [1, 2, 0xFF, 0xFF, 3]);
    }

    #[test]
    fn overlapping_segments_are_refused() {
        let a = [1u8, 2, 3];
        let b = [4u8];
        assert!(merge(vec![Segment::new(0, &a), Segment::new(2, &b)]).is_err());
    }

    #[test]
    fn only_the_two_chips_and_only_elf_files() {
        let dir = std::env::temp_dir().join(format!("pack-images-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let elf = dir.join("not.elf");
        std::fs::write(&elf, b"not an ELF at all").unwrap();
        let (m, a) = (dir.join("m.bin"), dir.join("a.bin"));
        assert!(pack("esp32", &elf, &m, &a, None)
            .unwrap_err()
            .contains("esp32c3 or esp32c6"));
        assert!(pack("esp32c3", &elf, &m, &a, None).is_err());
        assert!(pack("esp32c3", &dir.join("missing.elf"), &m, &a, None)
            .unwrap_err()
            .contains("cannot read"));
        assert!(
            !m.exists() && !a.exists(),
            "nothing written for a refused ELF"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
