//! Updates on the chip: esp-storage handed to the library's update flash
//! work (`tinybms_firmware::update::flash`): at boot the partition table and
//! `otadata` read and the boot's own write (the trial's mark, or the
//! rollback and its restart), then the operations of
//! [`Action::Flash`](tinybms_firmware::station::Action::Flash), each read
//! back. What any of it means is the library's, tested on the host.

use defmt::{info, warn};
use esp_hal::peripherals::FLASH;
use esp_storage::FlashStorage;
use tinybms_firmware::update::flash::{self, Booted, OtaFlash};
use tinybms_firmware::update::otadata::Cause;
use tinybms_firmware::update::transfer::Op;
use tinybms_firmware::update::Ota;

/// The flash for updates.
pub struct ChipOta(FlashStorage<'static>);

impl OtaFlash for ChipOta {
    fn read(&mut self, at: u32, buf: &mut [u8]) -> bool {
        self.0.read_nor(at, buf).is_ok()
    }
    fn erase_sector(&mut self, at: u32) -> bool {
        self.0.erase(at, at + flash::ERASE).is_ok()
    }
    fn program(&mut self, at: u32, bytes: &[u8]) -> bool {
        self.0.write_nor(at, bytes).is_ok()
    }
}

/// Reads the partition table and `otadata`, does the boot's write (and
/// restarts when the previous image must boot), and returns the update side.
pub fn boot() -> (ChipOta, Ota) {
    // SAFETY: a second handle to the flash peripheral. The store's handle and
    // this one are used only from the station task (and, before it runs, from
    // `main`), one operation at a time; esp-storage runs each operation in a
    // critical section through the ROM's routines, which keep no state
    // between calls.
    let mut chip = ChipOta(FlashStorage::new(unsafe { FLASH::steal() }));
    let cause = Cause::from_reset_reason(esp_hal::system::reset_reason().map(|r| r as u8));
    match flash::boot(&mut chip, cause) {
        Booted::Run(ota) => {
            if ota.layout().is_none() {
                warn!("update: the partition table has no otadata and two app slots: updates need one reinstall by cable");
            }
            (chip, ota)
        }
        Booted::Restart { written } => {
            info!(
                "update: rolling back (written: {=bool}), restarting",
                written
            );
            esp_hal::system::software_reset();
        }
    }
}

impl ChipOta {
    /// Opens the history in its partition (or says why there is none).
    pub fn open_history(&mut self) -> tinybms_firmware::history::log::History {
        use tinybms_firmware::history::log::{find, History};
        let flash_bytes = u32::try_from(self.0.capacity()).unwrap_or(u32::MAX);
        let range = find(self, flash_bytes);
        History::open(self, range)
    }

    /// Does `op` for the station (`program`: a program's bytes); true when it
    /// worked and reads back the same.
    pub fn run(&mut self, ota: &Ota, op: Op, program: &[u8]) -> bool {
        let layout = ota.layout().copied();
        flash::run(self, layout.as_ref(), op, program)
    }
}
