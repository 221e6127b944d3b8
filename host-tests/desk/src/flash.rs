//! Flash for the bridge's configuration store on the desktop, erased and
//! written as the chip's NOR flash is (erase sets bytes to 0xFF, a write can
//! only clear bits):
//!
//! * [`FileFlash`] — in a file (`sim --bridge-pty --flash FILE`): a restart
//!   of the simulated bridge finds what it stored, as the chip does.
//! * [`RamFlash`] — in RAM (the tool's direct mode, the tests).
//! * [`DeskFlash`] — one or the other, as a desktop station is given it.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::Path;

use embedded_storage_async::nor_flash::{
    ErrorType, MultiwriteNorFlash, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};

/// Size of the chip's `nvs` partition (the default partition table's), bytes.
pub const PARTITION_BYTES: u32 = 0x6000;
/// Erase unit of the chip's flash, bytes.
pub const SECTOR_BYTES: usize = 4096;
/// Write unit of the chip's flash through `esp-storage`, bytes.
pub const WORD_BYTES: usize = 4;

/// A flash operation failed.
#[derive(Debug)]
pub enum FlashError {
    /// Outside the flash or not aligned.
    Bounds,
    /// The file failed.
    Io(std::io::Error),
}

impl NorFlashError for FlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            Self::Bounds => NorFlashErrorKind::OutOfBounds,
            Self::Io(_) => NorFlashErrorKind::Other,
        }
    }
}

/// NOR flash of [`PARTITION_BYTES`] in a file (created erased when missing).
pub struct FileFlash {
    file: File,
}

impl FileFlash {
    /// Opens (or creates, erased) the file at `path`. A file of another size is
    /// refused: it is not this flash.
    pub fn open(path: &Path) -> std::io::Result<Self> {
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(path)?;
        let len = file.metadata()?.len();
        if len == 0 {
            file.write_all(&vec![0xFF; PARTITION_BYTES as usize])?;
            file.flush()?;
        } else if len != u64::from(PARTITION_BYTES) {
            return Err(std::io::Error::other(format!(
                "{}: {len} bytes, not a {PARTITION_BYTES}-byte flash image",
                path.display()
            )));
        }
        Ok(Self { file })
    }

    fn check(&self, offset: u32, len: usize, align: usize) -> Result<(), FlashError> {
        let end = u64::from(offset) + len as u64;
        if end > u64::from(PARTITION_BYTES)
            || !(offset as usize).is_multiple_of(align)
            || !len.is_multiple_of(align)
        {
            return Err(FlashError::Bounds);
        }
        Ok(())
    }
}

impl ErrorType for FileFlash {
    type Error = FlashError;
}

impl ReadNorFlash for FileFlash {
    const READ_SIZE: usize = WORD_BYTES;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.check(offset, bytes.len(), Self::READ_SIZE)?;
        self.file
            .seek(SeekFrom::Start(u64::from(offset)))
            .map_err(FlashError::Io)?;
        self.file.read_exact(bytes).map_err(FlashError::Io)
    }

    fn capacity(&self) -> usize {
        PARTITION_BYTES as usize
    }
}

impl NorFlash for FileFlash {
    const WRITE_SIZE: usize = WORD_BYTES;
    const ERASE_SIZE: usize = SECTOR_BYTES;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        if to < from {
            return Err(FlashError::Bounds);
        }
        self.check(from, (to - from) as usize, SECTOR_BYTES)?;
        self.file
            .seek(SeekFrom::Start(u64::from(from)))
            .map_err(FlashError::Io)?;
        self.file
            .write_all(&vec![0xFF; (to - from) as usize])
            .map_err(FlashError::Io)?;
        self.file.sync_data().map_err(FlashError::Io)
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.check(offset, bytes.len(), WORD_BYTES)?;
        let mut old = vec![0u8; bytes.len()];
        self.file
            .seek(SeekFrom::Start(u64::from(offset)))
            .map_err(FlashError::Io)?;
        self.file.read_exact(&mut old).map_err(FlashError::Io)?;
        // NOR: a write can only turn 1s into 0s.
        for (o, b) in old.iter_mut().zip(bytes) {
            *o &= b;
        }
        self.file
            .seek(SeekFrom::Start(u64::from(offset)))
            .map_err(FlashError::Io)?;
        self.file.write_all(&old).map_err(FlashError::Io)?;
        self.file.sync_data().map_err(FlashError::Io)
    }
}

impl MultiwriteNorFlash for FileFlash {}

/// NOR flash in RAM, of [`PARTITION_BYTES`] ([`RamFlash::new`]: what
/// [`FileFlash`] is, without the file) or of a whole chip's image
/// ([`RamFlash::from_bytes`]). Clones share the same bytes (the same chip's flash, seen by the
/// store and by a test); [`RamFlash::copy`] makes an independent one (the flash
/// as a restarted chip finds it).
#[derive(Debug, Clone)]
pub struct RamFlash {
    bytes: std::sync::Arc<std::sync::Mutex<Vec<u8>>>,
}

impl Default for RamFlash {
    fn default() -> Self {
        Self {
            bytes: std::sync::Arc::new(std::sync::Mutex::new(vec![0xFF; PARTITION_BYTES as usize])),
        }
    }
}

impl RamFlash {
    /// Erased.
    pub fn new() -> Self {
        Self::default()
    }

    /// A flash holding `bytes` (a whole chip's image, say), of their size.
    pub fn from_bytes(bytes: Vec<u8>) -> Self {
        Self {
            bytes: std::sync::Arc::new(std::sync::Mutex::new(bytes)),
        }
    }

    /// An independent flash with the same contents.
    pub fn copy(&self) -> Self {
        Self {
            bytes: std::sync::Arc::new(std::sync::Mutex::new(self.lock().clone())),
        }
    }

    /// The contents.
    pub fn lock(&self) -> std::sync::MutexGuard<'_, Vec<u8>> {
        self.bytes.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn range(
        len_total: usize,
        offset: u32,
        len: usize,
        align: usize,
    ) -> Result<std::ops::Range<usize>, FlashError> {
        let start = offset as usize;
        let end = start.checked_add(len).ok_or(FlashError::Bounds)?;
        if end > len_total || !start.is_multiple_of(align) || !len.is_multiple_of(align) {
            return Err(FlashError::Bounds);
        }
        Ok(start..end)
    }
}

impl ErrorType for RamFlash {
    type Error = FlashError;
}

impl ReadNorFlash for RamFlash {
    const READ_SIZE: usize = WORD_BYTES;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        let data = self.lock();
        let r = Self::range(data.len(), offset, bytes.len(), Self::READ_SIZE)?;
        bytes.copy_from_slice(&data[r]);
        Ok(())
    }

    fn capacity(&self) -> usize {
        self.lock().len()
    }
}

impl NorFlash for RamFlash {
    const WRITE_SIZE: usize = WORD_BYTES;
    const ERASE_SIZE: usize = SECTOR_BYTES;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let mut data = self.lock();
        let r = Self::range(
            data.len(),
            from,
            to.saturating_sub(from) as usize,
            SECTOR_BYTES,
        )?;
        data[r].fill(0xFF);
        Ok(())
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let mut data = self.lock();
        let r = Self::range(data.len(), offset, bytes.len(), WORD_BYTES)?;
        for (o, b) in data[r].iter_mut().zip(bytes) {
            *o &= b;
        }
        Ok(())
    }
}

impl MultiwriteNorFlash for RamFlash {}

/// The store on a flash of [`PARTITION_BYTES`] (the chip's `nvs` partition).
pub fn store<F: NorFlash>(flash: F) -> tinybms_firmware::config::store::Store<F> {
    match tinybms_firmware::config::store::Store::new(flash, 0..PARTITION_BYTES) {
        Ok(s) => s,
        // 6 whole sectors: always a valid range.
        Err(e) => panic!("store on the partition: {e:?}"),
    }
}

/// The flash of a desktop station: a file (kept across restarts) or RAM.
pub enum DeskFlash {
    /// `sim --bridge-pty --flash FILE`.
    File(FileFlash),
    /// Gone when the program ends.
    Ram(RamFlash),
}

impl ErrorType for DeskFlash {
    type Error = FlashError;
}

impl ReadNorFlash for DeskFlash {
    const READ_SIZE: usize = WORD_BYTES;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        match self {
            Self::File(f) => f.read(offset, bytes).await,
            Self::Ram(f) => f.read(offset, bytes).await,
        }
    }

    fn capacity(&self) -> usize {
        PARTITION_BYTES as usize
    }
}

impl NorFlash for DeskFlash {
    const WRITE_SIZE: usize = WORD_BYTES;
    const ERASE_SIZE: usize = SECTOR_BYTES;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        match self {
            Self::File(f) => f.erase(from, to).await,
            Self::Ram(f) => f.erase(from, to).await,
        }
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        match self {
            Self::File(f) => f.write(offset, bytes).await,
            Self::Ram(f) => f.write(offset, bytes).await,
        }
    }
}

impl MultiwriteNorFlash for DeskFlash {}
