//! The update's flash work on any flash: the boot's part (the partition
//! table and `otadata` read, the trial's mark or the rollback written) and an
//! [`Op`] done and read back. The chip hands in esp-storage, the desktop
//! station and the tests a flash in RAM: one procedure for all of them.

use super::otadata::{self, Both, Cause, Entry, Write};
use super::transfer::{Layout, Op, SECTOR};
use super::{start, Ota, Start};
use crate::partitions::{Table, TABLE_MAX, TABLE_OFFSET};

/// A flash, as the update needs it. Each call is one operation; `false`:
/// it failed.
pub trait OtaFlash {
    /// Reads `buf.len()` bytes (a multiple of 4) at `at`.
    fn read(&mut self, at: u32, buf: &mut [u8]) -> bool;
    /// Erases the sector at `at`.
    fn erase_sector(&mut self, at: u32) -> bool;
    /// Programs `bytes` (a multiple of 4) at `at` (erased before).
    fn program(&mut self, at: u32, bytes: &[u8]) -> bool;
}

/// What a boot found.
#[derive(Debug, Clone)]
pub enum Booted {
    /// Run with this update side (on trial or not).
    Run(Ota),
    /// The previous image must boot: restart now (the rollback is written,
    /// or could not be: `written`).
    Restart {
        /// The rollback's entry was written.
        written: bool,
    },
}

/// The partition table's slots, if it has them.
pub fn layout<F: OtaFlash>(flash: &mut F) -> Option<Layout> {
    let mut table = [0u8; TABLE_MAX];
    if !flash.read(TABLE_OFFSET, &mut table) {
        return None;
    }
    Table::parse(&table)
        .ok()
        .as_ref()
        .and_then(Layout::from_table)
}

/// Both `otadata` entries.
pub fn read_otadata<F: OtaFlash>(flash: &mut F, layout: &Layout) -> Both {
    let mut both: Both = [None, None];
    for (i, slot) in both.iter_mut().enumerate() {
        let mut b = [0u8; otadata::ENTRY_LEN];
        if flash.read(layout.otadata + i as u32 * otadata::SECTOR, &mut b) {
            *slot = Entry::parse(&b);
        }
    }
    both
}

/// Erases an `otadata` sector and programs its entry; read back.
pub fn write_otadata<F: OtaFlash>(flash: &mut F, layout: &Layout, w: &Write) -> bool {
    let at = layout.otadata + w.sector as u32 * otadata::SECTOR;
    let bytes = w.entry.to_bytes();
    flash.erase_sector(at) && flash.program(at, &bytes) && same(flash, at, &bytes)
}

/// The flash at `at` holds `bytes` (an update's program, the history's
/// record: read back).
pub(crate) fn same<F: OtaFlash>(flash: &mut F, at: u32, bytes: &[u8]) -> bool {
    let mut buf = [0u8; 256];
    let mut offset = at;
    for piece in bytes.chunks(buf.len()) {
        let Some(b) = buf.get_mut(..piece.len()) else {
            return false;
        };
        if !flash.read(offset, b) || b != piece {
            return false;
        }
        offset += piece.len() as u32;
    }
    true
}

/// The boot's part: reads the table and `otadata` and writes what the boot
/// must (`cause`: what reset the chip).
pub fn boot<F: OtaFlash>(flash: &mut F, cause: Cause) -> Booted {
    let Some(layout) = layout(flash) else {
        return Booted::Run(Ota::new(None, [None, None]));
    };
    let mut both = read_otadata(flash, &layout);
    match start(&both, cause) {
        Start::Run => {}
        Start::WriteThenRun(w) => {
            // Unwritten, the entry stays new and the next boot tries again.
            if write_otadata(flash, &layout, &w) {
                otadata::apply(&mut both, &w);
            }
        }
        Start::WriteThenRestart(w) => {
            return Booted::Restart {
                written: write_otadata(flash, &layout, &w),
            };
        }
    }
    Booted::Run(Ota::new(Some(layout), both))
}

/// Does `op` (`program`: the bytes of a program); true when it worked and
/// reads back the same.
pub fn run<F: OtaFlash>(flash: &mut F, layout: Option<&Layout>, op: Op, program: &[u8]) -> bool {
    match op {
        Op::Erase(at) => flash.erase_sector(at),
        Op::Program(at) => flash.program(at, program) && same(flash, at, program),
        Op::Otadata(w) => layout.is_some_and(|l| write_otadata(flash, l, &w)),
    }
}

/// The sector size the operations erase.
pub const ERASE: u32 = SECTOR;
