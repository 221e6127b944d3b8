//! Update keys as text, so that the two halves of a key pair can never be
//! taken for each other: a **public** key is 64 hex digits (what a bridge is
//! given to trust), a **private** key 128 (its 32-byte seed, then its public
//! key: what `tinybms sign` takes). The lengths differ on purpose; a key
//! file also says in `#` comment lines what it holds. The bridge refuses a
//! private key wherever a key is given to it, and never stores or says one.

use super::file::Key;
use super::nibble;

/// A key's text, understood.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyText {
    /// A public key (64 hex digits).
    Public(Key),
    /// A private key (128 hex digits): its seed, and the public key written
    /// with it (which the signing tool checks against the seed).
    Private {
        /// The Ed25519 seed.
        seed: [u8; 32],
        /// The public key as written after it.
        public: Key,
    },
}

/// Why a text is no key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyTextError {
    /// Nothing but comments and white space.
    Empty,
    /// A character that is not a hex digit.
    NotHex,
    /// Hex digits, but neither 64 (public) nor 128 (private) of them.
    Length(usize),
}

impl KeyTextError {
    /// In words.
    pub const fn words(self) -> &'static str {
        match self {
            Self::Empty => "no key in it",
            Self::NotHex => "not a key: only hex digits (and # comment lines) belong in it",
            Self::Length(_) => {
                "not a key: a public key is 64 hex digits, a private key 128 (tinybms keygen)"
            }
        }
    }
}

/// What a bridge says when it is given a private key: nothing is stored.
pub const PRIVATE_REFUSED: &str = "this is a PRIVATE key (128 hex digits): never give it to a \
     bridge or anyone; a bridge needs the public key, 64 hex digits (the .pub file, or \
     `tinybms public-key FILE`); nothing was stored";

/// The key in `text`: lines starting with `#` are comments; the rest,
/// without white space, must be 64 or 128 hex digits.
pub fn parse(text: &str) -> Result<KeyText, KeyTextError> {
    let mut digits = [0u8; 128];
    let mut n = 0usize;
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('#') {
            continue;
        }
        for c in line.bytes().filter(|c| !c.is_ascii_whitespace()) {
            let d = nibble(c).ok_or(KeyTextError::NotHex)?;
            if let Some(slot) = digits.get_mut(n) {
                *slot = d;
            }
            n = n.saturating_add(1);
        }
    }
    let byte = |i: usize| -> u8 {
        let hi = digits.get(2 * i).copied().unwrap_or(0);
        let lo = digits.get(2 * i + 1).copied().unwrap_or(0);
        (hi << 4) | lo
    };
    let bytes = |from: usize| -> [u8; 32] { core::array::from_fn(|i| byte(from + i)) };
    match n {
        0 => Err(KeyTextError::Empty),
        64 => Ok(KeyText::Public(bytes(0))),
        128 => Ok(KeyText::Private {
            seed: bytes(0),
            public: bytes(32),
        }),
        other => Err(KeyTextError::Length(other)),
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::format;

    const PUBLIC: &str = "5f69a1b2c3d4e5f60718293a4b5c6d7e8f9012345678abcdef0123456789abcd";

    #[test]
    fn the_halves_are_told_apart_by_their_length() {
        let public = parse(PUBLIC).unwrap();
        assert!(matches!(public, KeyText::Public(k) if k[0] == 0x5f && k[31] == 0xcd));
        let private = format!("# a comment\n{}\n{PUBLIC}\n", "0".repeat(63) + "1");
        match parse(&private).unwrap() {
            KeyText::Private { seed, public } => {
                assert_eq!(seed[31], 1);
                assert_eq!(public[0], 0x5f);
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(parse("# only\n  \n"), Err(KeyTextError::Empty));
        assert_eq!(parse(&PUBLIC[1..]), Err(KeyTextError::Length(63)));
        assert_eq!(parse("5f69 zz"), Err(KeyTextError::NotHex));
        assert_eq!(
            crate::text::hex32(
                &parse(PUBLIC)
                    .map(|k| match k {
                        KeyText::Public(k) => k,
                        KeyText::Private { public, .. } => public,
                    })
                    .unwrap()
            ),
            PUBLIC
        );
        assert_eq!(
            parse(&PUBLIC.repeat(3)),
            Err(KeyTextError::Length(192)),
            "never cut to a key"
        );
    }
}
