//! Updates without a cable: signed update files ([`file`](mod@file)) received into the
//! inactive app slot ([`transfer`]) and booted on trial, confirmed once the
//! new image has worked or rolled back by the application ([`otadata`]).
//!
//! [`Ota`] holds it together for the station: the slots found in the
//! partition table, `otadata` as last read or written, the trial of the
//! running image, the transfer, and the update that was rolled back (if
//! one was). Every flash operation waits for the station's turn
//! ([`Ota::next_op`], asked only while no BMS reply can be on its way).
//!
//! docs/updates.md is the owner's side of it.

pub mod file;
pub mod flash;
pub mod key_text;
pub mod otadata;
pub mod transfer;

use crate::partitions::{Table, TYPE_APP, TYPE_DATA};
use crate::Instant;
use file::Key;
use otadata::{Both, Cause, Write};
use transfer::{Layout, Op, Transfer};

/// `otadata`'s data subtype.
pub const SUBTYPE_OTA: u8 = 0x00;
/// `ota_0`'s app subtype (`ota_1` is the next).
pub const SUBTYPE_OTA_0: u8 = 0x10;

/// An image on trial confirms itself at the latest after this long without a
/// reset, even without BMS data (a bridge with no BMS wired).
pub const CONFIRM_AFTER_US: Instant = 10 * 60 * crate::SECOND;

/// The bridge's update port on the network (images with Wi-Fi): the host
/// link's `update_…` commands, and nothing else, over TCP.
pub const TCP_PORT: u16 = 8232;

/// The most keys trusted at once: the one built in and one registered.
pub const KEYS_MAX: usize = 2;

/// The key built into this image (`TINYBMS_UPDATE_KEY` when it was built:
/// 64 hex digits, the release key or the owner's own), if any.
pub const BUILT_IN_KEY: Option<Key> = match option_env!("TINYBMS_UPDATE_KEY") {
    Some(hex) => match parse_key(hex.as_bytes()) {
        Some(k) => Some(k),
        None if hex.len() == 128 => panic!(
            "TINYBMS_UPDATE_KEY is a PRIVATE key (128 hex digits): build with the public key, \
             64 hex digits (the .pub file), and keep the private one secret"
        ),
        None => panic!("TINYBMS_UPDATE_KEY is not a public key (64 hex digits)"),
    },
    None => None,
};

/// A hex digit's value (either case).
pub(crate) const fn nibble(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'a'..=b'f' => Some(c - b'a' + 10),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    }
}

/// A key from its 64 hex digits.
// A const fn (the built-in key is parsed at compile time) cannot call `get`;
// the length is checked first and `i < 32`, so no index is out of bounds.
#[allow(clippy::indexing_slicing)]
pub const fn parse_key(hex: &[u8]) -> Option<Key> {
    if hex.len() != 64 {
        return None;
    }
    let mut k = [0u8; 32];
    let mut i = 0;
    while i < 32 {
        let (Some(h), Some(l)) = (nibble(hex[2 * i]), nibble(hex[2 * i + 1])) else {
            return None;
        };
        k[i] = (h << 4) | l;
        i += 1;
    }
    Some(k)
}

impl Layout {
    /// `otadata` and `ota_0`/`ota_1` from a partition table (`None`: it has
    /// not all three: a table from before updates over the air).
    pub fn from_table(t: &Table) -> Option<Self> {
        let find = |kind: u8, sub: u8| t.entries().find(|e| e.kind == kind && e.subtype == sub);
        let ota = find(TYPE_DATA, SUBTYPE_OTA)?;
        let a = find(TYPE_APP, SUBTYPE_OTA_0)?;
        let b = find(TYPE_APP, SUBTYPE_OTA_0 + 1)?;
        (ota.size >= 2 * otadata::SECTOR).then_some(Self {
            otadata: ota.offset,
            slots: [(a.offset, a.size), (b.offset, b.size)],
        })
    }
}

/// How the running image came to run (the boot's decision, for `hello`, the
/// log and MQTT).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Trial {
    /// Confirmed (or never updated).
    Confirmed,
    /// On trial since boot: confirms itself once it has worked.
    OnTrial,
}

/// The update side of a bridge. See the module's documentation.
#[derive(Debug, Clone)]
pub struct Ota {
    layout: Option<Layout>,
    otadata: Both,
    confirm_due: bool,
    transfer: Transfer,
    owner_key: Option<Key>,
}

impl Default for Ota {
    fn default() -> Self {
        Self::new(None, [None, None])
    }
}

/// What a boot does before the station starts (the shell does it at once:
/// no BMS traffic runs yet).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Start {
    /// Run.
    Run,
    /// Write this `otadata` sector, then run (on trial).
    WriteThenRun(Write),
    /// Write this `otadata` sector, then restart: the previous image boots.
    WriteThenRestart(Write),
}

/// The first decision of a boot: `both` as read, `cause` what reset the chip.
pub fn start(both: &Both, cause: Cause) -> Start {
    match otadata::boot(both, cause) {
        otadata::Boot::Run | otadata::Boot::StillOnTrial => Start::Run,
        otadata::Boot::Trial(w) => Start::WriteThenRun(w),
        otadata::Boot::RollBack(w) => Start::WriteThenRestart(w),
    }
}

impl Ota {
    /// After the boot: where the slots are, `otadata` as it now is (the
    /// boot's own write done).
    pub fn new(layout: Option<Layout>, otadata: Both) -> Self {
        Self {
            layout,
            otadata,
            confirm_due: false,
            transfer: Transfer::new(),
            owner_key: None,
        }
    }

    /// The slots (`None`: no room for an update in this partition table).
    pub fn layout(&self) -> Option<&Layout> {
        self.layout.as_ref()
    }

    /// The slot running now (the bootloader's choice).
    pub fn running_slot(&self) -> u32 {
        otadata::booted_slot(&self.otadata)
    }

    /// `otadata` as the bridge knows it.
    pub fn otadata(&self) -> &Both {
        &self.otadata
    }

    /// The trial (what `otadata` says of the running image).
    pub fn trial(&self) -> Trial {
        if otadata::on_trial(&self.otadata) {
            Trial::OnTrial
        } else {
            Trial::Confirmed
        }
    }

    /// An update that was rolled back: its version and why.
    pub fn rolled_back(&self) -> Option<(&str, Cause)> {
        otadata::rolled_back(&self.otadata)
    }

    /// The transfer.
    pub fn transfer(&self) -> &Transfer {
        &self.transfer
    }

    /// The transfer, to feed it.
    pub fn transfer_mut(&mut self) -> &mut Transfer {
        &mut self.transfer
    }

    /// The key the owner registered (the record's `update_key`).
    pub fn set_owner_key(&mut self, key: Option<Key>) {
        self.owner_key = key;
    }

    /// The newest version known to exist that is newer than `running`: an
    /// update rolled back, or a file whose header passed every check (a
    /// `check` too) since start-up. `None`: none known (the bridge does not
    /// look for releases).
    pub fn latest(&self, running: &str) -> Option<&str> {
        let rolled = self.rolled_back().map(|(v, _)| v);
        [rolled, self.transfer.offered()]
            .into_iter()
            .flatten()
            .filter(|v| file::older(running, v))
            .fold(None, |best: Option<&str>, v| match best {
                Some(b) if !file::older(b, v) => Some(b),
                _ => Some(v),
            })
    }

    /// The owner's key (`update_key`), if one is set.
    pub fn owner_key(&self) -> Option<Key> {
        self.owner_key
    }

    /// Every key trusted now: the one built in, the owner's.
    pub fn keys(&self) -> heapless::Vec<Key, KEYS_MAX> {
        let mut v = heapless::Vec::new();
        for k in [BUILT_IN_KEY, self.owner_key].into_iter().flatten() {
            let _ = v.push(k);
        }
        v
    }

    /// The trial's work at `now` (since boot): `worked` when BMS data came
    /// and the inverter output runs (or has nothing to run). True when the
    /// confirmation became due.
    pub fn tick(&mut self, now: Instant, worked: bool) -> bool {
        if self.trial() == Trial::OnTrial
            && !self.confirm_due
            && (worked || now >= CONFIRM_AFTER_US)
        {
            self.confirm_due = true;
            return true;
        }
        false
    }

    /// The flash operation due, if any: the confirmation first, then the
    /// transfer's.
    pub fn next_op(&self) -> Option<Op> {
        if self.confirm_due {
            if let Some(w) = otadata::confirm(&self.otadata) {
                return Some(Op::Otadata(w));
            }
        }
        self.transfer.next_op(self.layout.as_ref())
    }

    /// The shell did [`Ota::next_op`]'s operation; what it meant.
    pub fn op_done(&mut self, ok: bool) -> Done {
        if self.confirm_due {
            self.confirm_due = false;
            if ok {
                if let Some(w) = otadata::confirm(&self.otadata) {
                    otadata::apply(&mut self.otadata, &w);
                }
                return Done::Confirmed;
            }
            // Tried again at the next boot's trial (still pending).
            return Done::ConfirmFailed;
        }
        match self.transfer.op_done(ok, &mut self.otadata) {
            Some(e) => Done::Ended(e),
            None if self.transfer.phase() == transfer::Phase::Installed => Done::Installed,
            None => Done::Nothing,
        }
    }
}

/// What a flash operation's end meant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Done {
    /// Nothing to say.
    Nothing,
    /// The running image is confirmed.
    Confirmed,
    /// The confirmation could not be written.
    ConfirmFailed,
    /// The transfer ended without an update.
    Ended(transfer::Ended),
    /// The new image is installed: restart.
    Installed,
}

#[cfg(test)]
mod tests;
