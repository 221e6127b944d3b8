//! The record's bytes in flash.
//!
//! ```text
//! 0   2   'T' 'C'           magic
//! 2   1   VERSION           layout version (super::VERSION; 1, 2 and 3 are read too)
//! 3   1   N                 fields that follow
//! 4   ..  N × (tag, len, value)
//!           tag   1         the field's stable number (Field::tag)
//!           len   1         bytes of value
//!           value len       on/off and choices: 1 byte; numbers: i32 little-endian;
//!                           text and secrets: UTF-8
//! ```
//!
//! Decoding believes nothing: the magic, the version, every tag known and
//! given once, every length right for its kind, every value within its field's
//! range, every field of the version present, nothing after the last, and the
//! rules between fields ([`Config::validate`]). A record of an older version
//! (1, 2, 3) holds the fields of that version only; those added since
//! ([`introduced`]) take their defaults, so an update keeps the owner's
//! configuration. Any of these failing is a
//! [`DecodeError`] and the bridge runs with the defaults. (`sequential-storage`
//! already checks a CRC over the item: this catches the rest — another version,
//! a bug, a record written by something else.)

use super::value::{check, Value};
use super::{Config, FieldId, Kind, FIELDS, RETIRED, VERSION};

/// The record's first two bytes.
pub const MAGIC: [u8; 2] = *b"TC";

/// Longest encoded record, bytes (every text field at its longest: 645).
pub const RECORD_MAX: usize = 672;

pub use super::introduced;

/// Why bytes are not a record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DecodeError {
    /// Shorter than its header or one of its fields says.
    Truncated,
    /// Not a configuration record.
    Magic,
    /// A layout version this firmware does not read.
    Version(u8),
    /// A tag no field has.
    UnknownTag(u8),
    /// A field given twice.
    Duplicate(FieldId),
    /// A field's length does not fit its kind.
    Length(FieldId),
    /// A field's value is outside its kind or range.
    Value(FieldId),
    /// A field of this version is missing.
    Missing(FieldId),
    /// Bytes after the last field.
    Trailing,
    /// The fields break a rule between them.
    Rule(FieldId),
}

impl DecodeError {
    /// In a few words.
    pub const fn reason(&self) -> &'static str {
        match self {
            Self::Truncated => "truncated",
            Self::Magic => "not a configuration record",
            Self::Version(_) => "another layout version",
            Self::UnknownTag(_) => "unknown field",
            Self::Duplicate(_) => "a field given twice",
            Self::Length(_) => "a field of the wrong length",
            Self::Value(_) => "a value out of range",
            Self::Missing(_) => "a field missing",
            Self::Trailing => "bytes after the last field",
            Self::Rule(_) => "fields that break a rule",
        }
    }
}

/// Writes `config` into `out`; its length, or `None` when `out` is shorter
/// than the record (at least [`RECORD_MAX`] always fits).
pub fn encode(config: &Config, out: &mut [u8]) -> Option<usize> {
    let mut w = Writer { out, at: 0 };
    w.bytes(&MAGIC)?;
    w.bytes(&[VERSION, FIELDS.len() as u8])?;
    for f in FIELDS {
        let v = config.get(f.id);
        match v {
            Value::Bool(b) => w.field(f.tag, &[u8::from(b)])?,
            Value::Choice(c) => w.field(f.tag, &[c])?,
            Value::Number(n) => w.field(f.tag, &n.to_le_bytes())?,
            Value::Text(s) => w.field(f.tag, s.as_bytes())?,
        }
    }
    Some(w.at)
}

struct Writer<'a> {
    out: &'a mut [u8],
    at: usize,
}

impl Writer<'_> {
    fn bytes(&mut self, b: &[u8]) -> Option<()> {
        let end = self.at.checked_add(b.len())?;
        self.out.get_mut(self.at..end)?.copy_from_slice(b);
        self.at = end;
        Some(())
    }
    fn field(&mut self, tag: u8, value: &[u8]) -> Option<()> {
        let len = u8::try_from(value.len()).ok()?;
        self.bytes(&[tag, len])?;
        self.bytes(value)
    }
}

/// The kind of a retired tag a record of `version` may carry.
fn retired(tag: u8, version: u8) -> Option<Kind> {
    RETIRED
        .iter()
        .find(|(t, from, until, _)| *t == tag && *from <= version && version < *until)
        .map(|r| r.3)
}

/// Reads a record. Never panics, whatever the bytes.
pub fn decode(bytes: &[u8]) -> Result<Config, DecodeError> {
    let header = bytes.get(..4).ok_or(DecodeError::Truncated)?;
    if header.get(..2) != Some(&MAGIC[..]) {
        return Err(DecodeError::Magic);
    }
    let version = header.get(2).copied().unwrap_or(0);
    if version == 0 || version > VERSION {
        return Err(DecodeError::Version(version));
    }
    let count = header.get(3).copied().unwrap_or(0);
    let mut seen = [false; FIELDS.len()];
    let mut config = Config::default();
    let mut rest = bytes.get(4..).unwrap_or(&[]);
    for _ in 0..count {
        let (&tag, after) = rest.split_first().ok_or(DecodeError::Truncated)?;
        let (&len, after) = after.split_first().ok_or(DecodeError::Truncated)?;
        let value = after
            .get(..usize::from(len))
            .ok_or(DecodeError::Truncated)?;
        rest = after.get(usize::from(len)..).unwrap_or(&[]);
        if let Some(kind) = retired(tag, version) {
            // A field this layout no longer has: its value's length is
            // checked, the value dropped (the field's successor takes its
            // default).
            let fits = match kind {
                Kind::Bool | Kind::Choice(_) => value.len() == 1,
                Kind::Number { .. } => value.len() == 4,
                Kind::Text { .. } | Kind::Secret { .. } => true,
            };
            if !fits {
                return Err(DecodeError::UnknownTag(tag));
            }
            continue;
        }
        let id = FieldId::from_tag(tag)
            .filter(|_| introduced(tag) <= version)
            .ok_or(DecodeError::UnknownTag(tag))?;
        let index = FIELDS
            .iter()
            .position(|f| f.id == id)
            .ok_or(DecodeError::UnknownTag(tag))?;
        let slot = seen.get_mut(index).ok_or(DecodeError::UnknownTag(tag))?;
        if *slot {
            return Err(DecodeError::Duplicate(id));
        }
        *slot = true;
        let field = id.field();
        let v = match (field.kind, value) {
            (Kind::Bool, [0]) => Value::Bool(false),
            (Kind::Bool, [1]) => Value::Bool(true),
            (Kind::Bool, [_]) => return Err(DecodeError::Value(id)),
            (Kind::Choice(_), [c]) => Value::Choice(*c),
            (Kind::Number { .. }, &[a, b, c, d]) => Value::Number(i32::from_le_bytes([a, b, c, d])),
            (Kind::Text { .. } | Kind::Secret { .. }, t) => {
                Value::Text(core::str::from_utf8(t).map_err(|_| DecodeError::Value(id))?)
            }
            _ => return Err(DecodeError::Length(id)),
        };
        check(field, &v).map_err(|_| DecodeError::Value(id))?;
        config.set(id, v).map_err(|_| DecodeError::Value(id))?;
    }
    if !rest.is_empty() {
        return Err(DecodeError::Trailing);
    }
    let missing = seen
        .iter()
        .zip(FIELDS)
        .position(|(s, f)| !s && introduced(f.tag) <= version);
    if let Some(i) = missing {
        let id = FIELDS.get(i).map(|f| f.id).unwrap_or(FieldId::CanOutput);
        return Err(DecodeError::Missing(id));
    }
    config.validate().map_err(|e| DecodeError::Rule(e.field))?;
    Ok(config)
}
