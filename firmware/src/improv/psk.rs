//! The WPA2 pre-shared key of a passphrase, derived a little at a time.
//!
//! IEEE 802.11i: PSK = PBKDF2-HMAC-SHA1(passphrase, SSID, 4096 rounds, 32
//! bytes) — two 20-byte blocks of 4096 HMACs each, about 16,000 SHA-1
//! compressions. Done in one go that would hold the station (and the BMS's
//! UART) for a few hundred milliseconds on the chip, so [`PskDerivation`]
//! does [`ROUNDS_PER_STEP`] rounds per [`PskDerivation::step`] and the
//! station steps it between its other work.
//!
//! The passphrase lives only in the HMAC's keyed state while the key is
//! derived and is never stored: the record keeps the 64 hex digits of the
//! key, which the Wi-Fi driver takes as the PSK itself. The state is
//! overwritten when the derivation is dropped.

use hmac::{Hmac, KeyInit, Mac};
use sha1::Sha1;

/// Rounds of PBKDF2 (IEEE 802.11i).
pub const ROUNDS: u16 = 4096;

/// Rounds per [`PskDerivation::step`]: two SHA-1 compressions each, about
/// 4,000 RV32IMC instructions each (bench-rv32) — a step is about 128,000
/// instructions, under 1 ms at 160 MHz, well inside the 5.5 ms the UART's
/// FIFO leaves above its interrupt threshold. The whole key takes 512 steps.
pub const ROUNDS_PER_STEP: u16 = 16;

/// Why a passphrase cannot give a key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PskError {
    /// An SSID has 1 to 32 bytes.
    SsidLength,
    /// A WPA2 passphrase has 8 to 63 printable ASCII characters (or is 64
    /// hex digits: the key itself).
    Passphrase,
}

impl PskError {
    /// In words, for the log (never the passphrase itself).
    pub const fn text(self) -> &'static str {
        match self {
            Self::SsidLength => "an SSID has 1 to 32 bytes",
            Self::Passphrase => "a WPA2 passphrase has 8 to 63 printable ASCII characters",
        }
    }
}

/// The key as the record keeps it: 64 lower-case hex digits.
pub type PskHex = heapless::String<64>;

/// A derivation under way. See the module documentation.
#[derive(Clone)]
pub struct PskDerivation {
    /// HMAC keyed with the passphrase (cloned for every round).
    prf: Hmac<Sha1>,
    ssid: heapless::Vec<u8, 32>,
    /// Block 1 or 2; round 1..=ROUNDS within it.
    block: u8,
    round: u16,
    u: [u8; 20],
    t: [u8; 20],
    key: [u8; 32],
}

impl core::fmt::Debug for PskDerivation {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        // Nothing of the passphrase or the key.
        f.debug_struct("PskDerivation")
            .field("block", &self.block)
            .field("round", &self.round)
            .finish_non_exhaustive()
    }
}

impl PartialEq for PskDerivation {
    fn eq(&self, other: &Self) -> bool {
        // Two derivations are "the same" when they work on the same network
        // and have come as far (the station's state compares; the keyed
        // HMAC has no equality).
        self.ssid == other.ssid && self.block == other.block && self.round == other.round
    }
}

impl Drop for PskDerivation {
    fn drop(&mut self) {
        self.u = [0; 20];
        self.t = [0; 20];
        self.key = [0; 32];
        // The keyed state: replaced by one keyed with nothing.
        if let Ok(blank) = Hmac::<Sha1>::new_from_slice(&[]) {
            self.prf = blank;
        }
    }
}

/// True for a passphrase that is the key itself: 64 hex digits.
fn is_hex_key(p: &[u8]) -> bool {
    p.len() == 64 && p.iter().all(u8::is_ascii_hexdigit)
}

/// What a passphrase gives at once, or a derivation to step.
#[derive(Debug)]
pub enum Start {
    /// An open network (no passphrase): no key.
    Open,
    /// The passphrase was the key (64 hex digits).
    Key(PskHex),
    /// Step this until it gives the key.
    Derive(PskDerivation),
}

impl PskDerivation {
    /// Starts the key of `passphrase` on the network `ssid`.
    pub fn start(ssid: &[u8], passphrase: &[u8]) -> Result<Start, PskError> {
        if ssid.is_empty() || ssid.len() > 32 {
            return Err(PskError::SsidLength);
        }
        if passphrase.is_empty() {
            return Ok(Start::Open);
        }
        if is_hex_key(passphrase) {
            let mut k = PskHex::new();
            for &c in passphrase {
                let _ = k.push(char::from(c.to_ascii_lowercase()));
            }
            return Ok(Start::Key(k));
        }
        if !(8..=63).contains(&passphrase.len())
            || !passphrase.iter().all(|c| (b' '..=b'~').contains(c))
        {
            return Err(PskError::Passphrase);
        }
        let prf = Hmac::<Sha1>::new_from_slice(passphrase).map_err(|_| PskError::Passphrase)?;
        let mut d = Self {
            prf,
            ssid: heapless::Vec::from_slice(ssid).map_err(|_| PskError::SsidLength)?,
            block: 1,
            round: 0,
            u: [0; 20],
            t: [0; 20],
            key: [0; 32],
        };
        d.begin_block();
        Ok(Start::Derive(d))
    }

    /// U1 = PRF(P, S || INT(block)).
    fn begin_block(&mut self) {
        let mut mac = self.prf.clone();
        mac.update(&self.ssid);
        mac.update(&u32::from(self.block).to_be_bytes());
        self.u.copy_from_slice(&mac.finalize().into_bytes());
        self.t = self.u;
        self.round = 1;
    }

    /// Up to [`ROUNDS_PER_STEP`] rounds; the key once the last is done.
    pub fn step(&mut self) -> Option<PskHex> {
        for _ in 0..ROUNDS_PER_STEP {
            if self.round >= ROUNDS {
                // This block is done: into the key, then the next block.
                let at = (usize::from(self.block) - 1) * 20;
                for (i, b) in self.t.iter().enumerate() {
                    if let Some(k) = self.key.get_mut(at + i) {
                        *k = *b;
                    }
                }
                if self.block == 2 {
                    return Some(crate::text::hex32(&self.key));
                }
                self.block = 2;
                self.begin_block();
                continue;
            }
            let mut mac = self.prf.clone();
            mac.update(&self.u);
            self.u.copy_from_slice(&mac.finalize().into_bytes());
            for (t, u) in self.t.iter_mut().zip(self.u.iter()) {
                *t ^= u;
            }
            self.round += 1;
        }
        None
    }

    /// Rounds done so far, of 2 × [`ROUNDS`].
    pub fn progress(&self) -> u32 {
        (u32::from(self.block) - 1) * u32::from(ROUNDS) + u32::from(self.round)
    }
}
