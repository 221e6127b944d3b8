//! ESP-IDF's `otadata` partition, and the trial boot this firmware runs on it.
//!
//! **The format** (ESP-IDF's `esp_ota_select_entry_t`, what the second-stage
//! bootloader reads): two flash sectors, each starting with one 32-byte entry —
//! `ota_seq` (`u32` LE), a 20-byte label, `ota_state` (`u32` LE) and a CRC-32
//! of the four `ota_seq` bytes (the ROM's `crc32_le(UINT32_MAX, …)`: CRC-32
//! with a zero start and the final inversion). An entry counts when its
//! `ota_seq` is not `FFFF_FFFF`, its state is neither `INVALID` nor `ABORTED`
//! and its CRC matches; the bootloader boots the app slot
//! `(ota_seq - 1) % 2` of the counting entry with the higher `ota_seq` (the
//! first sector's on a tie), and `ota_0` when none counts. The label is not
//! in the CRC and the bootloader never reads it.
//!
//! **The trial boot.** The bootloader `espflash` ships is built without
//! ESP-IDF's rollback, so it never changes an entry's state. This firmware
//! does what that rollback would, from the application ([`boot`]):
//!
//! 1. An update is activated by writing an entry for its slot, state `NEW`,
//!    with its version in the label, into the sector that does not hold the
//!    running image's entry ([`activate`]). When the running image has no
//!    entry of its own (a first install leaves `otadata` erased), one is
//!    written for it first, so that there is always something to go back to.
//! 2. The new image's first boot sees `NEW` and marks it `PENDING_VERIFY`.
//! 3. It confirms itself once it has worked ([`confirm`]) by writing an entry
//!    two sequence numbers on (the same slot), state `VALID`, into the
//!    *other* sector: the pending entry stays readable until the new one is
//!    complete.
//! 4. A boot that finds its own entry still `PENDING_VERIFY` follows a reset
//!    before the confirmation (a panic, a watchdog, a power cut): it marks
//!    the entry `ABORTED`, with the reset's cause in the label, and restarts;
//!    the bootloader then boots the previous image, which reports
//!    "update to X rolled back: reason" from that entry ([`rolled_back`]).
//!
//! Every write is one sector: erase, then program 32 bytes. A cut at any
//! point leaves the sector erased, half-programmed (its CRC, written last,
//! still erased: the entry does not count) or complete; host-tests'
//! `ota_power_cut.rs` cuts at every write and boots each result through a
//! model of the bootloader.

/// Bytes per `otadata` sector; the second entry is this far after the first.
pub const SECTOR: u32 = 0x1000;
/// Bytes per entry.
pub const ENTRY_LEN: usize = 32;
/// The label's length.
pub const LABEL_LEN: usize = 20;
/// Where, in the label, the reset cause of a rollback is kept (the version
/// takes the bytes before it).
const CAUSE_AT: usize = LABEL_LEN - 1;
/// App slots (`ota_0`, `ota_1`).
pub const SLOTS: u32 = 2;

/// `ota_state`, ESP-IDF's `esp_ota_img_states_t`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum State {
    /// Written by an update; not yet booted.
    New,
    /// Booted on trial; not yet confirmed.
    PendingVerify,
    /// Confirmed.
    Valid,
    /// Marked unusable.
    Invalid,
    /// Rolled back.
    Aborted,
    /// `FFFF_FFFF` (ESP-IDF's `UNDEFINED`: an entry written without a state).
    Undefined,
    /// Any other value (counts, as the bootloader reads it).
    Other(u32),
}

impl State {
    /// The raw value.
    pub const fn raw(self) -> u32 {
        match self {
            Self::New => 0,
            Self::PendingVerify => 1,
            Self::Valid => 2,
            Self::Invalid => 3,
            Self::Aborted => 4,
            Self::Undefined => u32::MAX,
            Self::Other(v) => v,
        }
    }

    /// From the raw value.
    pub const fn from_raw(v: u32) -> Self {
        match v {
            0 => Self::New,
            1 => Self::PendingVerify,
            2 => Self::Valid,
            3 => Self::Invalid,
            4 => Self::Aborted,
            u32::MAX => Self::Undefined,
            v => Self::Other(v),
        }
    }
}

/// Why a trial boot ended before its confirmation (kept in the aborted
/// entry's label).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Cause {
    /// The image panicked (a software reset).
    Panic,
    /// A watchdog reset the chip.
    Watchdog,
    /// The power went (power-on or brown-out reset).
    PowerCut,
    /// Another reset.
    Reset,
}

impl Cause {
    /// From the chip's reset reason (ESP32-C3/C6 `SocResetReason`; `None`:
    /// unknown): power-on, brown-out and power glitch are a power cut, the
    /// software resets (the panic handler's) a panic, the watchdogs a
    /// watchdog.
    pub const fn from_reset_reason(code: Option<u8>) -> Self {
        match code {
            Some(0x01 | 0x0F | 0x17) => Self::PowerCut,
            Some(0x03 | 0x0C) => Self::Panic,
            Some(0x07 | 0x08 | 0x09 | 0x0B | 0x0D | 0x10 | 0x11 | 0x12) => Self::Watchdog,
            _ => Self::Reset,
        }
    }

    const fn code(self) -> u8 {
        match self {
            Self::Panic => 1,
            Self::Watchdog => 2,
            Self::PowerCut => 3,
            Self::Reset => 4,
        }
    }

    fn from_code(c: u8) -> Self {
        match c {
            1 => Self::Panic,
            2 => Self::Watchdog,
            3 => Self::PowerCut,
            _ => Self::Reset,
        }
    }

    /// The words of "rolled back: …".
    pub const fn words(self) -> &'static str {
        match self {
            Self::Panic => "it panicked before confirming itself",
            Self::Watchdog => "a watchdog reset it before it confirmed itself",
            Self::PowerCut => "the power went before it confirmed itself",
            Self::Reset => "it was reset before it confirmed itself",
        }
    }

    /// A short key (host link, MQTT).
    pub const fn key(self) -> &'static str {
        match self {
            Self::Panic => "panic",
            Self::Watchdog => "watchdog",
            Self::PowerCut => "power_cut",
            Self::Reset => "reset",
        }
    }
}

/// One entry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Entry {
    /// `ota_seq`.
    pub seq: u32,
    /// The label (this firmware: the version, then the rollback's cause).
    pub label: [u8; LABEL_LEN],
    /// `ota_state`.
    pub state: State,
    /// The CRC as stored.
    pub crc: u32,
}

/// The CRC the bootloader expects for `seq`.
pub fn crc(seq: u32) -> u32 {
    // CRC-32 (reflected, polynomial EDB88320) started at 0, inverted at the
    // end: the ROM's crc32_le called with UINT32_MAX.
    let mut c: u32 = 0;
    for b in seq.to_le_bytes() {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0xEDB8_8320
            } else {
                c >> 1
            };
        }
    }
    !c
}

impl Entry {
    /// An entry for `seq` in `state` with `version` in its label (cut at
    /// what fits) and a correct CRC.
    pub fn new(seq: u32, state: State, version: &str) -> Self {
        let mut label = [0u8; LABEL_LEN];
        for (d, s) in label.iter_mut().take(CAUSE_AT).zip(version.bytes()) {
            *d = s;
        }
        if let Some(c) = label.get_mut(CAUSE_AT) {
            *c = 0xFF;
        }
        Self {
            seq,
            label,
            state,
            crc: crc(seq),
        }
    }

    /// From the first 32 bytes of a sector (`None`: fewer bytes).
    pub fn parse(bytes: &[u8]) -> Option<Self> {
        let b: &[u8; ENTRY_LEN] = bytes.get(..ENTRY_LEN)?.try_into().ok()?;
        let word = |at: usize| {
            let mut w = [0u8; 4];
            w.copy_from_slice(b.get(at..at + 4).unwrap_or(&[0xFF; 4]));
            u32::from_le_bytes(w)
        };
        let mut label = [0u8; LABEL_LEN];
        label.copy_from_slice(b.get(4..4 + LABEL_LEN)?);
        Some(Self {
            seq: word(0),
            label,
            state: State::from_raw(word(24)),
            crc: word(28),
        })
    }

    /// The 32 bytes.
    pub fn to_bytes(&self) -> [u8; ENTRY_LEN] {
        let mut b = [0u8; ENTRY_LEN];
        b[..4].copy_from_slice(&self.seq.to_le_bytes());
        b[4..24].copy_from_slice(&self.label);
        b[24..28].copy_from_slice(&self.state.raw().to_le_bytes());
        b[28..].copy_from_slice(&self.crc.to_le_bytes());
        b
    }

    /// Written whole: the sequence is not erased and the CRC matches (the
    /// state aside).
    pub fn intact(&self) -> bool {
        self.seq != u32::MAX && self.crc == crc(self.seq)
    }

    /// Counts for the bootloader.
    pub fn counts(&self) -> bool {
        self.intact() && !matches!(self.state, State::Invalid | State::Aborted)
    }

    /// The slot it boots: `(seq - 1) % 2`, as the bootloader computes it.
    pub const fn slot(&self) -> u32 {
        self.seq.wrapping_sub(1) % SLOTS
    }

    /// The version in the label.
    pub fn version(&self) -> &str {
        let v = self.label.get(..CAUSE_AT).unwrap_or(&[]);
        let end = v.iter().position(|&b| b == 0).unwrap_or(v.len());
        core::str::from_utf8(v.get(..end).unwrap_or(&[])).unwrap_or("?")
    }

    /// The rollback's cause in the label.
    pub fn cause(&self) -> Cause {
        Cause::from_code(self.label.get(CAUSE_AT).copied().unwrap_or(0xFF))
    }

    fn with_state(mut self, state: State) -> Self {
        self.state = state;
        self
    }
}

/// Both sectors' entries as read (`None`: the read failed or was short,
/// taken as an erased sector).
pub type Both = [Option<Entry>; 2];

/// Sector `i`'s entry.
pub fn at(both: &Both, i: usize) -> Option<Entry> {
    both.get(i).copied().flatten()
}

/// `both` after `w`.
pub fn apply(both: &mut Both, w: &Write) {
    if let Some(e) = both.get_mut(w.sector) {
        *e = Some(w.entry);
    }
}

/// The entry the bootloader boots: its sector (0 or 1), or `None` (it boots
/// `ota_0`).
pub fn selected(both: &Both) -> Option<usize> {
    let counts = |i: usize| at(both, i).filter(Entry::counts);
    match (counts(0), counts(1)) {
        (Some(a), Some(b)) => Some(if b.seq > a.seq { 1 } else { 0 }),
        (Some(_), None) => Some(0),
        (None, Some(_)) => Some(1),
        (None, None) => None,
    }
}

/// The slot the bootloader boots.
pub fn booted_slot(both: &Both) -> u32 {
    selected(both)
        .and_then(|i| at(both, i))
        .map_or(0, |e| e.slot())
}

/// One sector to write: erase it, then program `entry` at its start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Write {
    /// The sector (0 or 1).
    pub sector: usize,
    /// What goes there.
    pub entry: Entry,
}

/// The writes that make the bootloader boot `slot` next, on trial, with
/// `version` in its entry: at most two (an entry for the running image
/// first, when it has none), in order.
pub fn activate(both: &Both, slot: u32, version: &str) -> heapless::Vec<Write, 2> {
    let mut out = heapless::Vec::new();
    let (running_sector, running_seq) = match selected(both).and_then(|i| Some((i, at(both, i)?))) {
        Some((i, e)) => (i, e.seq),
        None => {
            // A first install: the bootloader boots ota_0 from an erased
            // otadata. Give it an entry (seq 1 is ota_0), kept valid.
            let running = Entry::new(1, State::Valid, "");
            let _ = out.push(Write {
                sector: 0,
                entry: running,
            });
            (0, 1)
        }
    };
    // The next sequence number that boots `slot`.
    let mut seq = running_seq.wrapping_add(1);
    while (seq.wrapping_sub(1)) % SLOTS != slot % SLOTS {
        seq = seq.wrapping_add(1);
    }
    let _ = out.push(Write {
        sector: 1 - running_sector,
        entry: Entry::new(seq, State::New, version),
    });
    out
}

/// What a boot must do first, from the entries as read and what reset the
/// chip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Boot {
    /// Nothing: a confirmed image (or a first install).
    Run,
    /// The first boot of an update: write this (its entry, pending), then run
    /// on trial until [`confirm`].
    Trial(Write),
    /// Still on trial from the boot before (that one ended before its
    /// confirmation): run on trial, nothing to write.
    StillOnTrial,
    /// The boot before was a trial that was reset before it confirmed
    /// itself: write this (its entry, aborted, the cause in its label), then
    /// restart: the bootloader boots the previous image.
    RollBack(Write),
}

/// What the first boot of an image does (see the module's documentation).
/// `cause` is what reset the chip before this boot.
pub fn boot(both: &Both, cause: Cause) -> Boot {
    let Some(i) = selected(both) else {
        return Boot::Run;
    };
    let Some(e) = at(both, i) else {
        return Boot::Run;
    };
    match e.state {
        State::New => Boot::Trial(Write {
            sector: i,
            entry: e.with_state(State::PendingVerify),
        }),
        State::PendingVerify => {
            let other = at(both, 1 - i).filter(|o| o.counts() && o.slot() != e.slot());
            if other.is_none() {
                // Nothing to go back to: only a cut during the confirmation
                // leaves a pending entry alone (the activation always writes
                // the previous image's entry first). That image ran.
                Boot::StillOnTrial
            } else {
                let mut aborted = e.with_state(State::Aborted);
                if let Some(c) = aborted.label.get_mut(CAUSE_AT) {
                    *c = cause.code();
                }
                Boot::RollBack(Write {
                    sector: i,
                    entry: aborted,
                })
            }
        }
        _ => Boot::Run,
    }
}

/// The write that confirms the image on trial (`None`: it is not on trial).
pub fn confirm(both: &Both) -> Option<Write> {
    let i = selected(both)?;
    let e = at(both, i)?;
    (e.state == State::PendingVerify).then(|| Write {
        sector: 1 - i,
        entry: Entry::new(e.seq.wrapping_add(SLOTS), State::Valid, e.version()),
    })
}

/// The image is on trial (its entry is pending).
pub fn on_trial(both: &Both) -> bool {
    selected(both)
        .and_then(|i| at(both, i))
        .is_some_and(|e| e.state == State::PendingVerify)
}

/// An update that was rolled back, as the image now running sees it: the
/// other sector's entry, whole, aborted, newer than the running one.
pub fn rolled_back(both: &Both) -> Option<(&str, Cause)> {
    let i = selected(both)?;
    let running = at(both, i)?;
    let other = both.get(1 - i)?.as_ref()?;
    (other.intact() && other.state == State::Aborted && other.seq > running.seq)
        .then(|| (other.version(), other.cause()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn both(a: Option<Entry>, b: Option<Entry>) -> Both {
        [a, b]
    }

    #[test]
    fn the_crc_is_the_roms() {
        // ESP-IDF's otadata for ota_0 after one update cycle (seq 1) and
        // ota_1 (seq 2), as `otatool.py` and esp-bootloader-esp-idf write
        // them.
        assert_eq!(crc(1), 0x4743_989A);
        assert_eq!(crc(2), 0x55F6_3774);
        assert_ne!(crc(3), u32::MAX);
    }

    #[test]
    fn an_entry_round_trips_and_counts_only_whole() {
        let e = Entry::new(5, State::Valid, "1.2.3");
        let b = e.to_bytes();
        assert_eq!(Entry::parse(&b), Some(e));
        assert_eq!(e.version(), "1.2.3");
        assert!(e.counts());
        let mut torn = b;
        torn[28..].copy_from_slice(&[0xFF; 4]);
        assert!(!Entry::parse(&torn).unwrap().counts());
        assert!(!Entry::parse(&[0xFF; 32]).unwrap().counts());
        assert!(Entry::parse(&b[..31]).is_none());
        assert!(!e.with_state(State::Aborted).counts());
        assert!(!e.with_state(State::Invalid).counts());
        assert!(e.with_state(State::Undefined).counts());
    }

    #[test]
    fn the_bootloader_takes_the_higher_sequence() {
        let a = Entry::new(3, State::Valid, "");
        let b = Entry::new(4, State::Valid, "");
        assert_eq!(selected(&both(Some(a), Some(b))), Some(1));
        assert_eq!(booted_slot(&both(Some(a), Some(b))), 1);
        assert_eq!(selected(&both(Some(b), Some(a))), Some(0));
        assert_eq!(selected(&both(Some(a), Some(a))), Some(0));
        assert_eq!(booted_slot(&both(None, None)), 0);
        assert_eq!(booted_slot(&both(None, Some(a))), 0);
    }

    #[test]
    fn a_first_install_gets_its_own_entry_before_the_update() {
        let w = activate(&both(None, None), 1, "0.2.0");
        assert_eq!(w.len(), 2);
        assert_eq!((w[0].sector, w[0].entry.slot()), (0, 0));
        assert_eq!((w[1].sector, w[1].entry.slot()), (1, 1));
        assert_eq!(w[1].entry.state, State::New);
        assert_eq!(w[1].entry.version(), "0.2.0");
    }

    #[test]
    fn a_whole_cycle_trial_confirm_and_rollback() {
        let mut b: Both = [None, None];
        let apply = |b: &mut Both, w: Write| b[w.sector] = Some(w.entry);
        for w in activate(&b, 1, "0.2.0") {
            apply(&mut b, w);
        }
        assert_eq!(booted_slot(&b), 1);
        let Boot::Trial(w) = boot(&b, Cause::Reset) else {
            panic!("not a trial")
        };
        apply(&mut b, w);
        assert!(on_trial(&b));
        assert_eq!(boot(&b, Cause::Panic), rollback_of(&b, Cause::Panic));
        let mut rolled = b;
        let Boot::RollBack(w) = boot(&rolled, Cause::Watchdog) else {
            panic!("no rollback")
        };
        apply(&mut rolled, w);
        assert_eq!(booted_slot(&rolled), 0);
        assert_eq!(boot(&rolled, Cause::Reset), Boot::Run);
        assert_eq!(rolled_back(&rolled), Some(("0.2.0", Cause::Watchdog)));
        // The confirmation instead.
        let w = confirm(&b).unwrap();
        apply(&mut b, w);
        assert_eq!(booted_slot(&b), 1);
        assert!(!on_trial(&b));
        assert_eq!(boot(&b, Cause::Panic), Boot::Run);
        assert_eq!(rolled_back(&b), None);
        assert!(confirm(&b).is_none());
        // And the next update goes back to slot 0, into the other sector.
        let w = activate(&b, 0, "0.3.0");
        assert_eq!(w.len(), 1);
        assert_eq!(w[0].entry.slot(), 0);
        assert_ne!(w[0].sector, selected(&b).unwrap());
    }

    fn rollback_of(b: &Both, cause: Cause) -> Boot {
        let i = selected(b).unwrap();
        let mut e = b[i].unwrap().with_state(State::Aborted);
        e.label[CAUSE_AT] = cause.code();
        Boot::RollBack(Write {
            sector: i,
            entry: e,
        })
    }

    #[test]
    fn a_pending_entry_alone_stays_on_trial() {
        let e = Entry::new(2, State::PendingVerify, "0.2.0");
        assert_eq!(boot(&both(Some(e), None), Cause::Panic), Boot::StillOnTrial);
    }
}
