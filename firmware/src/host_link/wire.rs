//! The values the firmware's lines are made of ([`Wire`](super::schema::Wire)'s
//! members), and how each is written: exact decimals ([`Dec`]) as `serde_json`
//! prints an `f64`, names from the BMS's tables ([`Name`]), cell voltages
//! ([`Cells`]) and bytes as hex ([`Hex`]). No allocation, no `core::fmt`.

use heapless::String;
use serde::ser::{Serialize, SerializeSeq, Serializer};

use crate::units::{fixed, Dec};

impl Serialize for Dec {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut out: String<40> = String::new();
        write_dec(&mut out, self.n, self.k);
        s.serialize_bytes(out.as_bytes())
    }
}

/// `ryu`'s formatting of the decimal `n * 10^-k` (its `format64` rules: plain
/// digits up to 16 before the point, `0.0000ddd` down to 5 zeros, else
/// scientific `d.ddde-7`).
fn write_dec(out: &mut String<40>, n: i64, k: u32) {
    if n == 0 {
        let _ = out.push_str("0.0");
        return;
    }
    if n < 0 {
        let _ = out.push('-');
    }
    // Digits of |n| without trailing zeros; value = digits * 10^exp.
    let mut m = n.unsigned_abs();
    let mut exp = -(k as i32);
    while m.is_multiple_of(10) {
        m /= 10;
        exp += 1;
    }
    let mut digits = [0u8; 20];
    let mut len = 0usize;
    while m > 0 {
        if let Some(d) = digits.get_mut(len) {
            *d = b'0' + (m % 10) as u8;
        }
        m /= 10;
        len += 1;
    }
    digits.get_mut(..len).unwrap_or(&mut []).reverse();
    let d = digits.get(..len).unwrap_or(&[]);
    let push = |out: &mut String<40>, b: &[u8]| {
        for &c in b {
            let _ = out.push(char::from(c));
        }
    };
    let olen = len as i32;
    let kk = olen + exp;
    if exp >= 0 && kk <= 16 {
        push(out, d);
        for _ in 0..exp {
            let _ = out.push('0');
        }
        let _ = out.push_str(".0");
    } else if kk > 0 && kk <= 16 {
        let (int, frac) = d.split_at((kk as usize).min(d.len()));
        push(out, int);
        let _ = out.push('.');
        push(out, frac);
    } else if kk > -5 && kk <= 0 {
        let _ = out.push_str("0.");
        for _ in 0..(-kk) {
            let _ = out.push('0');
        }
        push(out, d);
    } else {
        let (first, rest) = d.split_at(1.min(d.len()));
        push(out, first);
        if !rest.is_empty() {
            let _ = out.push('.');
            push(out, rest);
        }
        let _ = out.push('e');
        let mut e = kk - 1;
        if e < 0 {
            let _ = out.push('-');
            e = -e;
        }
        let mut buf = [0u8; 4];
        let mut i = buf.len();
        loop {
            i -= 1;
            if let Some(b) = buf.get_mut(i) {
                *b = b'0' + (e % 10) as u8;
            }
            e /= 10;
            if e == 0 || i == 0 {
                break;
            }
        }
        push(out, buf.get(i..).unwrap_or(&[]));
    }
}

/// `unknown_0xNN` (at least two upper-case hex digits, as replay prints).
fn unknown_hex(raw: u16) -> String<14> {
    let mut s = String::new();
    let _ = s.push_str("unknown_0x");
    let digits = if raw > 0xFFF {
        4
    } else if raw > 0xFF {
        3
    } else {
        2
    };
    for i in (0..digits).rev() {
        let _ = s.push(hex_digit((raw >> (4 * i)) as u8));
    }
    s
}

fn hex_digit(n: u8) -> char {
    char::from(
        b"0123456789ABCDEF"
            .get(usize::from(n & 0xF))
            .copied()
            .unwrap_or(b'0'),
    )
}

/// A name from a table, or `unknown_0xNN`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Name {
    /// Known.
    Known(&'static str),
    /// Known, printed as replay's snake_case key of the document name
    /// ("POR/PDR reset" → `por_pdr_reset`).
    Snake(&'static str),
    /// Not in the table.
    Unknown(u16),
}

impl Serialize for Name {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match *self {
            Name::Known(n) => s.serialize_str(n),
            Name::Snake(n) => {
                let mut out: String<64> = String::new();
                for c in n.bytes() {
                    if c.is_ascii_alphanumeric() {
                        let _ = out.push(char::from(c.to_ascii_lowercase()));
                    } else if !out.is_empty() && !out.ends_with('_') {
                        let _ = out.push('_');
                    }
                }
                while out.ends_with('_') {
                    out.pop();
                }
                s.serialize_str(&out)
            }
            Name::Unknown(raw) => s.serialize_str(&unknown_hex(raw)),
        }
    }
}

/// Cell voltages (0.1 mV) as a JSON array of volts.
#[derive(Debug, Clone, PartialEq)]
pub struct Cells<'a>(pub &'a [u16]);

impl Serialize for Cells<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut seq = s.serialize_seq(Some(self.0.len()))?;
        for &c in self.0 {
            seq.serialize_element(&fixed(i64::from(c), 4))?;
        }
        seq.end()
    }
}

/// Upper-case hex, bytes separated by spaces (the capture format's).
#[derive(Debug, Clone, PartialEq)]
pub struct Hex<'a>(pub &'a [u8], pub bool);

impl Serialize for Hex<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut out: String<{ 3 * super::RAW_CHUNK }> = String::new();
        for (i, &b) in self.0.iter().enumerate() {
            if i > 0 && self.1 {
                let _ = out.push(' ');
            }
            let _ = out.push(hex_digit(b >> 4));
            let _ = out.push(hex_digit(b));
        }
        s.serialize_str(&out)
    }
}
