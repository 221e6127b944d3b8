//! A flash that counts how long the chip's CPU would be stopped by its
//! operations (the cache is off during a flash erase or write), so
//! virtual-time tests can stall the bridge by as much. The flashes it wraps
//! are the desktop station's ([`tinybms_desk::flash`]).

use std::cell::Cell;
use std::rc::Rc;

use embedded_storage_async::nor_flash::{ErrorType, MultiwriteNorFlash, NorFlash, ReadNorFlash};

/// How long the chip's CPU stops for each flash operation, µs: the worst
/// case of common 4 MB SPI NOR flash parts (a 4 KiB sector erase up to
/// 400 ms, a page program up to 3 ms), and a read from the ROM routines.
pub const ERASE_STALL_US: u64 = 400_000;
/// See [`ERASE_STALL_US`].
pub const WRITE_STALL_US: u64 = 3_000;
/// See [`ERASE_STALL_US`].
pub const READ_STALL_US: u64 = 50;

/// Any flash, counting how long its operations would stop the chip's CPU.
pub struct Timed<F> {
    inner: F,
    stall: Rc<Cell<u64>>,
}

impl<F> Timed<F> {
    /// `inner`, and the counter its operations add to (µs).
    pub fn new(inner: F) -> (Self, Rc<Cell<u64>>) {
        let stall = Rc::new(Cell::new(0));
        (
            Self {
                inner,
                stall: stall.clone(),
            },
            stall,
        )
    }

    fn add(&self, us: u64) {
        self.stall.set(self.stall.get() + us);
    }
}

impl<F: ErrorType> ErrorType for Timed<F> {
    type Error = F::Error;
}

impl<F: ReadNorFlash> ReadNorFlash for Timed<F> {
    const READ_SIZE: usize = F::READ_SIZE;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.add(READ_STALL_US);
        self.inner.read(offset, bytes).await
    }

    fn capacity(&self) -> usize {
        self.inner.capacity()
    }
}

impl<F: NorFlash> NorFlash for Timed<F> {
    const WRITE_SIZE: usize = F::WRITE_SIZE;
    const ERASE_SIZE: usize = F::ERASE_SIZE;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let sectors = u64::from(to.saturating_sub(from)).div_ceil(F::ERASE_SIZE as u64);
        self.add(ERASE_STALL_US * sectors);
        self.inner.erase(from, to).await
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.add(WRITE_STALL_US * (bytes.len() as u64).div_ceil(256));
        self.inner.write(offset, bytes).await
    }
}

impl<F: MultiwriteNorFlash> MultiwriteNorFlash for Timed<F> {}
