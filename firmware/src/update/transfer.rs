//! The transfer of an update file into the inactive app slot: one sans-IO
//! machine behind every way a file comes in (the host link on USB; the same
//! commands from any other link).
//!
//! The sender sends the file in chunks of at most [`CHUNK_MAX`] bytes at file
//! offsets, each inside one [`SECTOR`] of the image (chunks of 128 bytes
//! from offset 0 always are). Every chunk is answered with the offset the
//! bridge wants next:
//! * a chunk at that offset is taken (the answer moves on);
//! * a chunk before it (a duplicate) and a chunk after it (one was lost in
//!   between) change nothing: the answer says where to go on;
//! * while a full sector waits for the flash, a chunk is answered `busy`
//!   (send it again a little later).
//!
//! The header is checked when its 256 bytes are in (magic, chip, board,
//! size, version, signature) and refused before anything is written. The
//! image's start is checked with its first chunk. Each full sector is
//! erased and programmed in the inactive slot when the station lets the
//! flash work ([`Transfer::next_op`]: only while no BMS reply can be on its
//! way). When the last byte is in, the SHA-256 of what came must be the
//! signed one; only then is `otadata` written to boot the new image on trial
//! ([`super::otadata::activate`]). A transfer that gets no chunk for
//! [`STALL_US`] is abandoned with that reason; nothing of the running image
//! or of `otadata` has changed by then.

use sha2::{Digest, Sha256};

use super::file::{image_start_ok, Header, Key, Permit, Refusal, Target, HEADER_LEN};
use super::otadata::{self, Both, Write};
use crate::Instant;

/// The most bytes in one chunk.
pub const CHUNK_MAX: usize = 128;
/// The unit the slot is erased and programmed in.
pub const SECTOR: u32 = 0x1000;
/// A transfer without a chunk for this long is abandoned.
pub const STALL_US: Instant = 30 * crate::SECOND;
/// What of the image must be in before its start is checked.
const START_LEN: usize = 80;

/// Where the app slots and `otadata` are (from the partition table).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    /// `otadata`'s offset (two sectors).
    pub otadata: u32,
    /// `ota_0` and `ota_1`: offset and size.
    pub slots: [(u32, u32); 2],
}

/// One flash operation for the shell; report it with [`Transfer::op_done`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Op {
    /// Erase the sector at this flash address.
    Erase(u32),
    /// Program [`Transfer::program_bytes`] at this address, then read it
    /// back (a difference is a failure).
    Program(u32),
    /// Erase `otadata`'s sector `write.sector` and program the entry at its
    /// start (read back the same way).
    Otadata(Write),
}

/// Why a transfer ended without an update.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Ended {
    /// Refused (the file).
    Refused(Refusal),
    /// No chunk came for [`STALL_US`].
    Stalled,
    /// The flash failed to erase or program (or read back differently).
    FlashFailed,
    /// The sender cancelled it.
    Cancelled,
    /// Another transfer began.
    Replaced,
}

impl Ended {
    /// A short key.
    pub const fn key(self) -> &'static str {
        match self {
            Self::Refused(r) => r.key(),
            Self::Stalled => "stalled",
            Self::FlashFailed => "flash_failed",
            Self::Cancelled => "cancelled",
            Self::Replaced => "replaced",
        }
    }

    /// The words.
    pub const fn words(self) -> &'static str {
        match self {
            Self::Refused(r) => r.words(),
            Self::Stalled => "no data for 30 s: the transfer was abandoned",
            Self::FlashFailed => "the flash could not be written",
            Self::Cancelled => "cancelled by the sender",
            Self::Replaced => "replaced by a new transfer",
        }
    }
}

/// The answer to a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answer {
    /// Send the chunk at this offset next (`size` when all is in).
    Next(u32),
    /// A sector is waiting for the flash: send the chunk at this offset again
    /// a little later.
    Busy(u32),
    /// `check`: the header would be accepted (nothing was written).
    Acceptable,
    /// The transfer ended (see [`Ended`]).
    Ended(Ended),
    /// A chunk outside the file or the rules above (the transfer goes on).
    BadChunk,
    /// No transfer is running.
    NotStarted,
}

/// Where the transfer is, for `update_status`, the log and MQTT.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Nothing.
    Idle,
    /// Receiving: bytes in, of the file's size.
    Receiving(u32, u32),
    /// All in: the last sector, the hash and `otadata` are being written.
    Finishing,
    /// `otadata` now boots the new image: restart.
    Installed,
}

#[derive(Debug, Clone)]
enum State {
    Idle,
    Header {
        size: u32,
        permit: Permit,
        check: bool,
        got: usize,
        buf: [u8; HEADER_LEN],
    },
    Image(Receiving),
    Activate {
        writes: heapless::Vec<Write, 2>,
        done: usize,
        version: Version,
    },
    Installed(Version),
}

/// A version's text, as the header holds it.
pub type Version = heapless::String<24>;

fn version_of(h: &Header) -> Version {
    let mut v = Version::new();
    let _ = v.push_str(h.version());
    v
}

/// The image being received.
#[derive(Debug, Clone)]
struct Receiving {
    header: Header,
    size: u32,
    slot: u32,
    next: u32,
    hasher: Sha256,
    /// The bytes of the sector being filled (image offset `sector_at`).
    fill: usize,
    sector_at: u32,
    flush: Flush,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Flush {
    None,
    Erase,
    Program,
}

fn out_of_order(at: u32, len: u32, next: u32, size: u32) -> Answer {
    if len as usize > CHUNK_MAX || at.saturating_add(len) > size {
        Answer::BadChunk
    } else {
        // A duplicate (before) or a chunk after a lost one: where to go on.
        Answer::Next(next)
    }
}

/// The machine. See the module's documentation.
#[derive(Debug, Clone)]
pub struct Transfer {
    state: State,
    buf: [u8; SECTOR as usize],
    last: Instant,
    /// How the last transfer ended (until the next begins).
    outcome: Option<Ended>,
    /// The newest version whose file passed every check of its header
    /// (a `check` too): what Home Assistant may show as available.
    offered: Option<Version>,
}

impl Default for Transfer {
    fn default() -> Self {
        Self::new()
    }
}

impl Transfer {
    /// No transfer.
    pub const fn new() -> Self {
        Self {
            state: State::Idle,
            buf: [0xFF; SECTOR as usize],
            last: 0,
            outcome: None,
            offered: None,
        }
    }

    /// The newest version a file that passed every check of its header
    /// offered since start-up.
    pub fn offered(&self) -> Option<&str> {
        self.offered.as_deref()
    }

    /// Where it is.
    pub fn phase(&self) -> Phase {
        match &self.state {
            State::Idle => Phase::Idle,
            State::Header { size, got, .. } => Phase::Receiving(*got as u32, *size),
            State::Image(b) if b.next >= b.size => Phase::Finishing,
            State::Image(b) => Phase::Receiving(b.next, b.size),
            State::Activate { .. } => Phase::Finishing,
            State::Installed(_) => Phase::Installed,
        }
    }

    /// How the last transfer ended without an update (`None`: none did, or
    /// one is running).
    pub fn outcome(&self) -> Option<Ended> {
        self.outcome
    }

    /// The version being received or installed.
    pub fn version(&self) -> Option<&str> {
        match &self.state {
            State::Image(b) => Some(b.header.version()),
            State::Activate { version, .. } | State::Installed(version) => Some(version),
            _ => None,
        }
    }

    fn end(&mut self, why: Ended) -> Answer {
        self.state = State::Idle;
        self.outcome = Some(why);
        Answer::Ended(why)
    }

    /// `update_begin`: a file of `size` bytes comes. Replaces a transfer
    /// that was running. `check`: only its header, to say whether it would
    /// be taken.
    pub fn begin(&mut self, now: Instant, size: u32, permit: Permit, check: bool) -> Answer {
        if matches!(self.state, State::Installed(_) | State::Activate { .. }) {
            // The new image is (being) made the one to boot: nothing else
            // starts before the restart.
            return Answer::Busy(0);
        }
        self.last = now;
        self.outcome = None;
        if (size as usize) < HEADER_LEN {
            return self.end(Ended::Refused(Refusal::Truncated));
        }
        self.state = State::Header {
            size,
            permit,
            check,
            got: 0,
            buf: [0; HEADER_LEN],
        };
        Answer::Next(0)
    }

    /// `update_cancel`.
    pub fn cancel(&mut self) -> Answer {
        match self.state {
            State::Header { .. } | State::Image(_) => self.end(Ended::Cancelled),
            _ => Answer::NotStarted,
        }
    }

    /// `update_chunk`: `data` at file offset `at`.
    #[allow(clippy::too_many_arguments)]
    pub fn chunk(
        &mut self,
        now: Instant,
        at: u32,
        data: &[u8],
        me: &Target<'_>,
        keys: &[Key],
        layout: Option<&Layout>,
        running_slot: u32,
    ) -> Answer {
        let len = data.len() as u32;
        match &mut self.state {
            State::Idle | State::Installed(_) | State::Activate { .. } => Answer::NotStarted,
            State::Header {
                size,
                permit,
                check,
                got,
                buf,
            } => {
                let next = *got as u32;
                if at != next || data.is_empty() {
                    return out_of_order(at, len, next, *size);
                }
                let end = *got + data.len();
                if data.len() > CHUNK_MAX || end > HEADER_LEN {
                    return Answer::BadChunk;
                }
                self.last = now;
                if let Some(dst) = buf.get_mut(*got..end) {
                    dst.copy_from_slice(data);
                }
                *got = end;
                if end < HEADER_LEN {
                    return Answer::Next(end as u32);
                }
                let (size, permit, check, buf) = (*size, *permit, *check, *buf);
                self.header_in(size, permit, check, &buf, me, keys, layout, running_slot)
            }
            State::Image(b) => {
                if at != b.next || data.is_empty() {
                    return out_of_order(at, len, b.next, b.size);
                }
                if data.len() > CHUNK_MAX || at + len > b.size {
                    return Answer::BadChunk;
                }
                let in_image = at - HEADER_LEN as u32;
                if in_image / SECTOR != (in_image + len - 1) / SECTOR {
                    return Answer::BadChunk;
                }
                if b.flush != Flush::None {
                    return Answer::Busy(b.next);
                }
                self.last = now;
                let from = (in_image - b.sector_at) as usize;
                if let Some(dst) = self.buf.get_mut(from..from + data.len()) {
                    dst.copy_from_slice(data);
                }
                b.hasher.update(data);
                b.fill = from + data.len();
                b.next += len;
                if b.sector_at == 0
                    && b.fill >= START_LEN.min(b.header.image_len as usize)
                    && in_image < START_LEN as u32
                {
                    let first = self.buf.get(..b.fill).unwrap_or(&[]);
                    if !image_start_ok(first, me.chip) {
                        return self.end(Ended::Refused(Refusal::NotAnImage));
                    }
                }
                if b.fill == SECTOR as usize || b.next == b.size {
                    b.flush = Flush::Erase;
                }
                Answer::Next(b.next)
            }
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn header_in(
        &mut self,
        size: u32,
        permit: Permit,
        check: bool,
        buf: &[u8; HEADER_LEN],
        me: &Target<'_>,
        keys: &[Key],
        layout: Option<&Layout>,
        running_slot: u32,
    ) -> Answer {
        let header = match Header::parse(buf) {
            Ok(h) => h,
            Err(r) => return self.end(Ended::Refused(r)),
        };
        let Some(layout) = layout else {
            return self.end(Ended::Refused(Refusal::NoSlot));
        };
        let slot = 1 - (running_slot % 2);
        let Some(&(_, slot_size)) = layout.slots.get(slot as usize) else {
            return self.end(Ended::Refused(Refusal::NoSlot));
        };
        let target = Target { slot_size, ..*me };
        let whole = HEADER_LEN as u64 + u64::from(header.image_len);
        let verdict = header
            .check(&target, permit)
            .and_then(|_| header.verify(keys).map(|_| ()))
            .and_then(|_| match u64::from(size).cmp(&whole) {
                core::cmp::Ordering::Less => Err(Refusal::Truncated),
                core::cmp::Ordering::Greater => Err(Refusal::Padded),
                core::cmp::Ordering::Equal => Ok(()),
            });
        if let Err(r) = verdict {
            return self.end(Ended::Refused(r));
        }
        let newer = self
            .offered
            .as_deref()
            .is_none_or(|o| super::file::older(o, header.version()));
        if newer {
            self.offered = Some(version_of(&header));
        }
        if check {
            self.state = State::Idle;
            return Answer::Acceptable;
        }
        self.state = State::Image(Receiving {
            header,
            size,
            slot,
            next: HEADER_LEN as u32,
            hasher: Sha256::new(),
            fill: 0,
            sector_at: 0,
            flush: Flush::None,
        });
        self.buf.fill(0xFF);
        Answer::Next(HEADER_LEN as u32)
    }

    /// Abandons a stalled transfer (call at every poll); the reason when it
    /// did.
    pub fn poll(&mut self, now: Instant) -> Option<Ended> {
        let receiving = match &self.state {
            State::Header { .. } => true,
            State::Image(b) => b.flush == Flush::None && b.next < b.size,
            _ => false,
        };
        if receiving && now.saturating_sub(self.last) >= STALL_US {
            self.end(Ended::Stalled);
            return Some(Ended::Stalled);
        }
        None
    }

    /// The flash operation due, if any (the station asks only when the flash
    /// may work).
    pub fn next_op(&self, layout: Option<&Layout>) -> Option<Op> {
        let layout = layout?;
        match &self.state {
            State::Image(b) => {
                let base = layout.slots.get(b.slot as usize)?.0 + b.sector_at;
                match b.flush {
                    Flush::None => None,
                    Flush::Erase => Some(Op::Erase(base)),
                    Flush::Program => Some(Op::Program(base)),
                }
            }
            State::Activate { writes, done, .. } => writes.get(*done).map(|w| Op::Otadata(*w)),
            _ => None,
        }
    }

    /// The bytes of [`Op::Program`] (the sector's, rounded up to whole
    /// 4-byte words with erased bytes).
    pub fn program_bytes(&self) -> &[u8] {
        let fill = match &self.state {
            State::Image(b) => b.fill,
            _ => 0,
        };
        self.buf.get(..fill.div_ceil(4) * 4).unwrap_or(&[])
    }

    /// The shell did [`Transfer::next_op`]: `ok` when it worked (and read
    /// back the same). `otadata` is kept up to date with what was written.
    /// Returns how a transfer ended, if it did.
    pub fn op_done(&mut self, ok: bool, otadata: &mut Both) -> Option<Ended> {
        if !ok {
            if matches!(self.state, State::Image(_) | State::Activate { .. }) {
                self.end(Ended::FlashFailed);
                return Some(Ended::FlashFailed);
            }
            return None;
        }
        match &mut self.state {
            State::Image(b) => match b.flush {
                Flush::Erase => b.flush = Flush::Program,
                Flush::Program => {
                    b.flush = Flush::None;
                    b.sector_at += SECTOR;
                    b.fill = 0;
                    self.buf.fill(0xFF);
                    if b.next >= b.size {
                        let hash: [u8; 32] = b.hasher.clone().finalize().into();
                        if hash != b.header.image_sha256() {
                            self.end(Ended::Refused(Refusal::HashMismatch));
                            return Some(Ended::Refused(Refusal::HashMismatch));
                        }
                        let writes = otadata::activate(otadata, b.slot, b.header.version());
                        let version = version_of(&b.header);
                        self.state = State::Activate {
                            writes,
                            done: 0,
                            version,
                        };
                    }
                }
                Flush::None => {}
            },
            State::Activate {
                writes,
                done,
                version,
            } => {
                if let Some(w) = writes.get(*done) {
                    otadata::apply(otadata, w);
                }
                *done += 1;
                if *done >= writes.len() {
                    self.state = State::Installed(version.clone());
                }
            }
            _ => {}
        }
        None
    }
}
