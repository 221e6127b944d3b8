//! A field's value, its checks, and its text: what `tinybms config` prints and
//! what it (and the host link's `set_config`) accepts.
//!
//! Text forms, by kind:
//! * on/off: `on`, `off` (also `true`/`false`, `yes`/`no`, `1`/`0`);
//! * a choice: its name (`victron`, `sma`);
//! * a number: a decimal with at most the field's decimals, with or without the
//!   field's unit, with or without a space (`50`, `50 A`, `50.5A`); a related unit
//!   is converted exactly (`3.45 V` for a field in mV, `2 min` for one in s,
//!   `1.5 s` for one in ms); the field's word for 0 (`none`, `bms`, `auto`,
//!   `alone`, `off`) where it has one — a typed `0` means the word only for
//!   `off`: a cap of `0` is refused, never read as `none` (no cap);
//! * text: as it is (empty: not set);
//! * a secret: as it is; shown only as `set` or `unset`.
//!
//! Parsing is exact: digits are scaled as integers, never through floating
//! point, so `3.45 V` is 3450 mV and `0.15 A` in a 0.1 A field is refused, not
//! rounded.

use heapless::String;

use super::{Field, Kind, TextRule, TEXT_MAX};
use crate::log_line::Line;

/// A value of some field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Value<'a> {
    /// On/off.
    Bool(bool),
    /// Index into the field's choices.
    Choice(u8),
    /// Raw number (`10^-decimals` of the field's unit).
    Number(i32),
    /// Text or a secret.
    Text(&'a str),
}

/// Why a typed 0 is refused for a field whose 0 is `word` (`None`: 0 means
/// the word, as `off` does).
fn zero_is_not(word: &str) -> Option<&'static str> {
    match word {
        "off" => None,
        "none" => Some(
            "0 would read as `none` (no cap at all): give the cap (the smallest is the range's low end), or `none` for no cap",
        ),
        "bms" => Some("0 is not a voltage: `bms` takes the BMS's own setting"),
        "auto" => Some("0 is not a voltage: `auto` derives it from absorption"),
        "alone" => Some("node numbers start at 1: `alone` for a bridge of one pack"),
        _ => Some("0 is not a value of this field: use its word"),
    }
}

/// A value parsed from text, owning its text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Parsed {
    /// On/off.
    Bool(bool),
    /// Index into the field's choices.
    Choice(u8),
    /// Raw number.
    Number(i32),
    /// Text or a secret.
    Text(String<TEXT_MAX>),
}

impl Parsed {
    /// As a [`Value`].
    pub fn as_value(&self) -> Value<'_> {
        match self {
            Self::Bool(b) => Value::Bool(*b),
            Self::Choice(c) => Value::Choice(*c),
            Self::Number(n) => Value::Number(*n),
            Self::Text(t) => Value::Text(t),
        }
    }
}

/// Why a value was refused, with the host link's error code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FieldError {
    /// `true`: outside the field's range (`out_of_range`); `false`: not a value
    /// of this kind at all (`invalid_value`).
    pub out_of_range: bool,
    /// A sentence.
    pub detail: &'static str,
}

impl FieldError {
    const fn range(detail: &'static str) -> Self {
        Self {
            out_of_range: true,
            detail,
        }
    }
    const fn invalid(detail: &'static str) -> Self {
        Self {
            out_of_range: false,
            detail,
        }
    }
    /// Text longer than the field holds.
    pub const TOO_LONG: Self = Self::range("too long");
    /// A value of another kind than the field's.
    pub const WRONG_KIND: Self = Self::invalid("not a value of this field's kind");
}

/// Checks `v` against `field`'s kind and range.
pub fn check(field: &Field, v: &Value<'_>) -> Result<(), FieldError> {
    match (field.kind, v) {
        (Kind::Bool, Value::Bool(_)) => Ok(()),
        (Kind::Choice(names), Value::Choice(c)) => {
            if usize::from(*c) < names.len() {
                Ok(())
            } else {
                Err(FieldError::invalid("not one of the choices"))
            }
        }
        (Kind::Number { min, max, off, .. }, Value::Number(n)) => {
            if (min..=max).contains(n) || (off.is_some() && *n == 0) {
                Ok(())
            } else {
                Err(FieldError::range("outside the field's range"))
            }
        }
        (Kind::Text { max, rule }, Value::Text(s)) => {
            // A key's kind first: a private key is longer than a public one,
            // and "too long" would not say what it is.
            if rule == TextRule::Key {
                check_text(rule, s)?;
            }
            if s.len() > usize::from(max) {
                return Err(FieldError::TOO_LONG);
            }
            check_text(rule, s)
        }
        (Kind::Secret { max, hex64 }, Value::Text(s)) => {
            if s.len() > usize::from(max) {
                return Err(FieldError::TOO_LONG);
            }
            if hex64
                && !s.is_empty()
                && (s.len() != 64 || !s.bytes().all(|b| b.is_ascii_hexdigit()))
            {
                return Err(FieldError::invalid(
                    "not 64 hex digits (`tinybms wifi` derives them from the passphrase)",
                ));
            }
            check_text(TextRule::Printable, s)
        }
        _ => Err(FieldError::WRONG_KIND),
    }
}

fn check_text(rule: TextRule, s: &str) -> Result<(), FieldError> {
    match rule {
        TextRule::Ascii => {
            if s.bytes().all(|b| (0x20..0x7F).contains(&b)) {
                Ok(())
            } else {
                Err(FieldError::invalid(
                    "only ASCII letters, digits, punctuation and spaces (it goes out byte for \
                     byte in a CAN frame: no accents)",
                ))
            }
        }
        TextRule::Printable => {
            if s.chars().any(char::is_control) {
                Err(FieldError::invalid("holds a control character"))
            } else {
                Ok(())
            }
        }
        TextRule::Host => {
            let ok = s
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'.')
                && !s.starts_with(['-', '.'])
                && !s.ends_with(['-', '.'])
                && !s.contains("..");
            // `….local`, any case.
            let name = s.as_bytes();
            let local = name.len() > 6
                && name
                    .get(name.len() - 6..)
                    .is_some_and(|t| t.eq_ignore_ascii_case(b".local"));
            if !ok {
                Err(FieldError::invalid(
                    "not a host name or IPv4 address (letters, digits, - and .)",
                ))
            } else if local {
                // mDNS names (homeassistant.local) are answered by the hosts
                // themselves, not by a DNS server: the bridge's resolver
                // never finds them, so the session could never connect.
                Err(FieldError::invalid(
                    "a .local name is resolved by mDNS, which the bridge does not do: \
                     give the broker's IP address (Home Assistant: Settings > System > \
                     Network), or a name your router's DNS answers",
                ))
            } else {
                Ok(())
            }
        }
        TextRule::Key => {
            use crate::update::key_text::{parse, KeyText, PRIVATE_REFUSED};
            match parse(s) {
                _ if s.is_empty() => Ok(()),
                Ok(KeyText::Private { .. }) => Err(FieldError::invalid(PRIVATE_REFUSED)),
                Ok(KeyText::Public(_)) => Ok(()),
                _ => Err(FieldError::invalid(
                    "not a public update key: 64 hex digits (the .pub file of tinybms keygen, \
                     whole or its key line), or empty",
                )),
            }
        }
        TextRule::Topic => {
            let ok = s
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'/')
                && !s.is_empty()
                && !s.starts_with('/')
                && !s.ends_with('/')
                && !s.contains("//");
            if ok {
                Ok(())
            } else {
                Err(FieldError::invalid(
                    "not a topic prefix (letters, digits, - _ and / between levels)",
                ))
            }
        }
    }
}

/// Units a number may be written in, as (unit, unit it converts to, decimal
/// exponent: the value in the second unit is the value in the first × 10^exp,
/// or for minutes and hours, × factor).
/// Durations take `m` for minutes too (`5m`, as the help writes them).
const CONVERSIONS: &[(&str, &str, i32, i64)] = &[
    ("v", "mV", 3, 1),
    ("mv", "V", -3, 1),
    ("ma", "A", -3, 1),
    ("ms", "s", -3, 1),
    ("min", "s", 0, 60),
    ("m", "s", 0, 60),
    ("h", "s", 0, 3600),
    ("s", "ms", 3, 1),
    ("min", "ms", 3, 60),
    ("m", "ms", 3, 60),
    ("c", "°C", 0, 1),
];

/// Splits `text` into its number and its unit (`"50.5 A"` → `("50.5", "A")`).
fn split_unit(text: &str) -> (&str, &str) {
    let t = text.trim();
    let end = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-' || c == '+'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(end);
    (num.trim(), unit.trim())
}

/// A decimal number as `digits · 10^-frac` (`"-3.45"` → (-345, 2)); `None`
/// when it is not one or has more than 12 significant digits.
fn decimal(s: &str) -> Option<(i64, u32)> {
    let (neg, body) = match s.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, s.strip_prefix('+').unwrap_or(s)),
    };
    let (int, frac) = body.split_once('.').unwrap_or((body, ""));
    if int.is_empty() && frac.is_empty() {
        return None;
    }
    if !int.bytes().all(|b| b.is_ascii_digit()) || !frac.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    if int.len() + frac.len() > 12 {
        return None;
    }
    let mut n: i64 = 0;
    for b in int.bytes().chain(frac.bytes()) {
        n = n * 10 + i64::from(b - b'0');
    }
    Some((if neg { -n } else { n }, frac.len() as u32))
}

/// `n · 10^exp` exactly, `None` when it is not a whole number or too large.
fn scale(n: i64, exp: i32) -> Option<i64> {
    if exp >= 0 {
        n.checked_mul(10i64.checked_pow(exp as u32)?)
    } else {
        let d = 10i64.checked_pow(exp.unsigned_abs())?;
        (n % d == 0).then_some(n / d)
    }
}

/// Parses the text form of a value of `field` (see the module documentation).
pub fn parse(field: &Field, text: &str) -> Result<Parsed, FieldError> {
    let t = text.trim();
    let parsed = match field.kind {
        Kind::Bool => Parsed::Bool(match t.to_ascii_lowercase_fixed().as_str() {
            "on" | "true" | "yes" | "1" => true,
            "off" | "false" | "no" | "0" => false,
            _ => return Err(FieldError::invalid("not on or off")),
        }),
        Kind::Choice(names) => match names.iter().position(|n| n.eq_ignore_ascii_case(t)) {
            Some(i) => Parsed::Choice(i as u8),
            None => return Err(FieldError::invalid("not one of the choices")),
        },
        Kind::Number { decimals, off, .. } => {
            if let Some(word) = off {
                if t.eq_ignore_ascii_case(word) {
                    return Ok(Parsed::Number(0));
                }
            }
            let (num, unit) = split_unit(t);
            let Some((digits, frac)) = decimal(num) else {
                return Err(FieldError::invalid("not a number"));
            };
            // digits · 10^-frac in `unit` → raw = value in the field's unit · 10^decimals.
            let (exp, factor) = if unit.is_empty() || unit.eq_ignore_ascii_case(field.unit) {
                (0, 1)
            } else {
                match CONVERSIONS
                    .iter()
                    .find(|(from, to, _, _)| from.eq_ignore_ascii_case(unit) && *to == field.unit)
                {
                    Some(&(_, _, exp, factor)) => (exp, factor),
                    None => return Err(FieldError::invalid("not in this field's unit")),
                }
            };
            let exp = exp + i32::from(decimals) - frac as i32;
            let raw = digits
                .checked_mul(factor)
                .and_then(|d| scale(d, exp))
                .ok_or(FieldError::range(
                    "more decimals than the field holds, or too large",
                ))?;
            let raw = i32::try_from(raw).map_err(|_| FieldError::range("too large"))?;
            // A field whose 0 has a word of its own: a typed 0 never means the
            // word (a cap of 0 is not "no cap", 0 mV is not "the BMS's own").
            if raw == 0 {
                if let Some(word) = off {
                    if let Some(why) = zero_is_not(word) {
                        return Err(FieldError::range(why));
                    }
                }
            }
            Parsed::Number(raw)
        }
        Kind::Text { .. } | Kind::Secret { .. } => {
            // A key says what it is before its length does (a private key
            // is longer than a public one).
            if let Kind::Text {
                rule: TextRule::Key,
                ..
            } = field.kind
            {
                check_text(TextRule::Key, text)?;
                // The .pub file whole (its `#` lines, then the key) is the
                // key: kept as its 64 hex digits alone.
                if let Ok(crate::update::key_text::KeyText::Public(key)) =
                    crate::update::key_text::parse(text)
                {
                    return Ok(Parsed::Text(crate::text::hex32(&key)));
                }
            }
            let mut s = String::new();
            // Text is taken as given (not trimmed): a Wi-Fi name may end in a space.
            if s.push_str(text).is_err() {
                return Err(FieldError::TOO_LONG);
            }
            Parsed::Text(s)
        }
    };
    check(field, &parsed.as_value())?;
    Ok(parsed)
}

/// ASCII lower case into a small buffer (the words `parse` compares).
trait LowerFixed {
    fn to_ascii_lowercase_fixed(&self) -> String<8>;
}

impl LowerFixed for str {
    fn to_ascii_lowercase_fixed(&self) -> String<8> {
        let mut s = String::new();
        for c in self.chars() {
            if s.push(c.to_ascii_lowercase()).is_err() {
                // Longer than any word: nothing matches.
                s.clear();
                let _ = s.push('\u{1}');
                break;
            }
        }
        s
    }
}

/// Writes the text form of `v` (a value of `field`) into `out`: what
/// [`parse`] reads back. Secrets are written as `set` or `unset`, never their
/// text; with `unit`, numbers carry the field's unit (`50.0 A`).
pub fn write(field: &Field, v: &Value<'_>, unit: bool, out: &mut Line) {
    match (field.kind, v) {
        (Kind::Bool, Value::Bool(b)) => {
            out.push(if *b { "on" } else { "off" });
        }
        (Kind::Choice(names), Value::Choice(c)) => {
            out.push(names.get(usize::from(*c)).copied().unwrap_or("?"));
        }
        (Kind::Number { decimals, off, .. }, Value::Number(n)) => match off {
            Some(word) if *n == 0 => {
                out.push(word);
            }
            _ => {
                out.fixed(i64::from(*n), u32::from(decimals));
                if unit && !field.unit.is_empty() {
                    out.push(" ").push(field.unit);
                }
            }
        },
        (Kind::Secret { .. }, Value::Text(s)) => {
            out.push(if s.is_empty() { "unset" } else { "set" });
        }
        (Kind::Text { .. }, Value::Text(s)) => {
            out.push(s);
        }
        _ => {
            out.push("?");
        }
    }
}

/// Writes the values `lo..=hi` (raw) of a number field as its range is
/// written (`0.1 A to 60.0 A`); for another kind, its range.
pub fn write_bounds(field: &Field, lo: i32, hi: i32, out: &mut Line) {
    let Kind::Number { decimals, .. } = field.kind else {
        write_range(field, out);
        return;
    };
    for (i, v) in [lo, hi].into_iter().enumerate() {
        if i > 0 {
            out.push(" to ");
        }
        out.fixed(i64::from(v), u32::from(decimals));
        if !field.unit.is_empty() {
            out.push(" ").push(field.unit);
        }
    }
}

/// The range of a field as text (`0.1 A to 750.0 A, or none`), for
/// refusals and `tinybms config`.
pub fn write_range(field: &Field, out: &mut Line) {
    match field.kind {
        Kind::Number {
            min,
            max,
            decimals,
            off,
        } => {
            out.fixed(i64::from(min), u32::from(decimals));
            if !field.unit.is_empty() {
                out.push(" ").push(field.unit);
            }
            out.push(" to ").fixed(i64::from(max), u32::from(decimals));
            if !field.unit.is_empty() {
                out.push(" ").push(field.unit);
            }
            if let Some(word) = off {
                out.push(", or ").push(word);
            }
        }
        Kind::Bool => {
            out.push("on or off");
        }
        Kind::Choice(names) => {
            for (i, n) in names.iter().enumerate() {
                if i > 0 {
                    out.push(if i + 1 == names.len() { " or " } else { ", " });
                }
                out.push(n);
            }
        }
        Kind::Text {
            rule: TextRule::Key,
            ..
        } => {
            out.push("a public key: 64 hex digits (the .pub file of tinybms keygen), or empty");
        }
        Kind::Text { max, .. } => {
            out.push("text, at most ")
                .uint(u64::from(max))
                .push(" bytes");
        }
        Kind::Secret { hex64: true, .. } => {
            out.push("64 hex digits");
        }
        Kind::Secret { max, .. } => {
            out.push("text, at most ")
                .uint(u64::from(max))
                .push(" bytes");
        }
    }
}
