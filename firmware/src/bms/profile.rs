//! The settings profile the firmware applies at start-up — the one place to
//! change what this device writes to the BMS — and the profile text format it is
//! written in, shared with `sim --profile` and the desktop tool.
//!
//! **Empty by default: out of the box the firmware never writes to the BMS.**
//!
//! The profile is the text file `firmware/profile.txt`, compiled in
//! ([`PROFILE_TEXT`]) and parsed at compile time: the parser is made of `const
//! fn`s, and a profile that does not parse fails the firmware build (the chip then
//! links neither the parser, nor the snake_case keys it matches names against, nor
//! the file's text). At run time the same functions read `sim --profile` files, the
//! desktop tool's and the host link's names.
//!
//! ## Format
//!
//! ```text
//! # comment (from `#` to the end of the line); blank lines are ignored
//! over_voltage_cutoff = 3650     # snake_case of the setting, or
//! Under-Voltage Cutoff = 2700    # Rev D's name (any case), or
//! 316 = 2700                     # the register address (whole-register and low-byte settings)
//! ```
//!
//! A value is an integer in raw register units (mV, A, s, 0.01 Ah, enumeration
//! values, as in Rev D §3.4), or a number with its unit (`3.65 V`, `3650 mV`,
//! `60 A`, `-10 °C`: converted exactly, refused unless it is a whole number of
//! the register's steps), or an enumeration value's name (`CC/CV`, `Kilometer`,
//! `Kilometer (2)` as `tinybms settings` prints it; case, spaces and punctuation
//! do not matter): [`parse_value`]. A setting given twice is refused. At
//! start-up every entry goes through the
//! write/verify machine: validated against Rev D's range and the BMS's own
//! min/max, read, skipped when already equal, written, read back and compared;
//! each outcome is logged.
//!
//! The setting names (the snake_case [`setting_key`] and the lookup
//! [`find_setting`]) live here and nowhere else: the host link and the host
//! tools use them too.

use protocol_core::registers::Field;
use protocol_core::settings::SettingId;

/// The start-up profile: the text of `firmware/profile.txt`.
pub const PROFILE_TEXT: &str = include_str!("../../profile.txt");

/// Most assignments a profile can hold: what the bridge's command queue takes
/// ([`crate::bms::timing::COMMAND_QUEUE`] groups of
/// [`crate::bms::timing::MAX_SETTINGS_GROUP`]).
pub const MAX_PROFILE_ENTRIES: usize =
    crate::bms::timing::COMMAND_QUEUE * crate::bms::timing::MAX_SETTINGS_GROUP;

/// snake_case name of a setting: its `SettingId` variant (`OverVoltageCutoff` →
/// `over_voltage_cutoff`). A host test checks every entry against the variant name.
pub const fn setting_key(id: SettingId) -> &'static str {
    match id {
        SettingId::FullyChargedVoltage => "fully_charged_voltage",
        SettingId::FullyDischargedVoltage => "fully_discharged_voltage",
        SettingId::EarlyBalancingThreshold => "early_balancing_threshold",
        SettingId::ChargeFinishedCurrent => "charge_finished_current",
        SettingId::PeakDischargeCurrentCutoff => "peak_discharge_current_cutoff",
        SettingId::BatteryCapacity => "battery_capacity",
        SettingId::NumberOfSeriesCells => "number_of_series_cells",
        SettingId::AllowedDisbalance => "allowed_disbalance",
        SettingId::ChargerStartupDelay => "charger_startup_delay",
        SettingId::ChargerDisableDelay => "charger_disable_delay",
        SettingId::PulsesPerUnit => "pulses_per_unit",
        SettingId::DistanceUnit => "distance_unit",
        SettingId::OverVoltageCutoff => "over_voltage_cutoff",
        SettingId::UnderVoltageCutoff => "under_voltage_cutoff",
        SettingId::DischargeOverCurrentCutoff => "discharge_over_current_cutoff",
        SettingId::ChargeOverCurrentCutoff => "charge_over_current_cutoff",
        SettingId::OverHeatCutoff => "over_heat_cutoff",
        SettingId::LowTemperatureChargerCutoff => "low_temperature_charger_cutoff",
        SettingId::ChargeRestartLevel => "charge_restart_level",
        SettingId::BatteryMaximumCycles => "battery_maximum_cycles",
        SettingId::StateOfHealth => "state_of_health",
        SettingId::StateOfCharge => "state_of_charge",
        SettingId::ConfigurationFlags => "configuration_flags",
        SettingId::ChargerType => "charger_type",
        SettingId::DischargeOverCurrentTimeout => "discharge_over_current_timeout",
        SettingId::LoadSwitchType => "load_switch_type",
        SettingId::AutomaticRecovery => "automatic_recovery",
        SettingId::ChargerSwitchType => "charger_switch_type",
        SettingId::Ignition => "ignition",
        SettingId::ChargerDetection => "charger_detection",
        SettingId::SpeedSensorInput => "speed_sensor_input",
        SettingId::PrechargePin => "precharge_pin",
        SettingId::PrechargeDuration => "precharge_duration",
        SettingId::TemperatureSensorType => "temperature_sensor_type",
        SettingId::OperationMode => "operation_mode",
        SettingId::SinglePortSwitchType => "single_port_switch_type",
        SettingId::BroadcastTime => "broadcast_time",
        SettingId::Protocol => "protocol",
    }
}

/// Finds a setting by snake_case name or Rev D name (both case-insensitive, spaces
/// around ignored) or register address (whole-register and low-byte settings).
pub const fn find_setting(name: &str) -> Option<SettingId> {
    let n = trim(name);
    if let Ok(addr) = u16::from_str_radix(n, 10) {
        return match SettingId::from_address(addr, Field::Whole) {
            Some(id) => Some(id),
            None => SettingId::from_address(addr, Field::LowByte),
        };
    }
    let mut rest = SettingId::ALL;
    while let [id, tail @ ..] = rest {
        if setting_key(*id).eq_ignore_ascii_case(n) || id.name().eq_ignore_ascii_case(n) {
            return Some(*id);
        }
        rest = tail;
    }
    None
}

/// `str::trim` as a `const fn`: `s` without the leading and trailing characters
/// that are `char::is_whitespace` (Unicode's White_Space, listed here as UTF-8).
pub const fn trim(mut s: &str) -> &str {
    const fn leading(b: &[u8]) -> usize {
        match b {
            [0x09..=0x0D | 0x20, ..] => 1,
            [0xC2, 0x85 | 0xA0, ..] => 2,
            [0xE1, 0x9A, 0x80, ..]
            | [0xE2, 0x80, 0x80..=0x8A | 0xA8 | 0xA9 | 0xAF, ..]
            | [0xE2, 0x81, 0x9F, ..]
            | [0xE3, 0x80, 0x80, ..] => 3,
            _ => 0,
        }
    }
    const fn trailing(b: &[u8]) -> usize {
        match b {
            [.., 0x09..=0x0D | 0x20] => 1,
            [.., 0xC2, 0x85 | 0xA0] => 2,
            [.., 0xE1, 0x9A, 0x80]
            | [.., 0xE2, 0x80, 0x80..=0x8A | 0xA8 | 0xA9 | 0xAF]
            | [.., 0xE2, 0x81, 0x9F]
            | [.., 0xE3, 0x80, 0x80] => 3,
            _ => 0,
        }
    }
    loop {
        let n = leading(s.as_bytes());
        match s.split_at_checked(n) {
            Some((_, rest)) if n > 0 => s = rest,
            _ => break,
        }
    }
    loop {
        let n = trailing(s.as_bytes());
        match s.split_at_checked(s.len() - n) {
            Some((rest, _)) if n > 0 => s = rest,
            _ => break,
        }
    }
    s
}

/// `s` split at its last `byte` (ASCII), the byte itself dropped.
const fn rsplit_once(s: &str, byte: u8) -> Option<(&str, &str)> {
    let mut i = s.len();
    while i > 0 {
        i -= 1;
        if let Some((head, tail)) = s.split_at_checked(i) {
            if let [b, ..] = tail.as_bytes() {
                if *b == byte {
                    return match tail.split_at_checked(1) {
                        Some((_, tail)) => Some((head, tail)),
                        None => None,
                    };
                }
            }
        }
    }
    None
}

/// `s` split at its first `byte` (an ASCII byte, so both sides are `str`s), the
/// byte itself dropped.
const fn split_once(s: &str, byte: u8) -> Option<(&str, &str)> {
    let mut i = 0;
    let mut rest = s.as_bytes();
    while let [b, tail @ ..] = rest {
        if *b == byte {
            return match s.split_at_checked(i) {
                Some((head, tail)) => match tail.split_at_checked(1) {
                    Some((_, tail)) => Some((head, tail)),
                    None => None,
                },
                None => None,
            };
        }
        i += 1;
        rest = tail;
    }
    None
}

/// Why a profile line was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ProfileErrorKind {
    /// No `=` in the line.
    ExpectedAssignment,
    /// No setting by that name or address.
    UnknownSetting,
    /// The value is not an integer that fits in 32 bits, nor a number with a
    /// unit, nor the name of an enumeration value.
    BadValue,
    /// A number with a unit that is not the setting's (nor its milli-unit).
    WrongUnit,
    /// A decimal without a unit (plain numbers are raw register units).
    DecimalWithoutUnit,
    /// A physical value between two of the register's steps.
    NotAStep,
    /// A name that is none of the setting's enumeration values.
    NotAnOption,
    /// A name two enumeration values share: give the number too (`Name (N)`).
    AmbiguousName,
    /// The setting was given before in the same profile.
    Duplicate,
}

impl ProfileErrorKind {
    /// Short snake_case reason.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::ExpectedAssignment => "expected NAME = VALUE",
            Self::UnknownSetting => "no such setting",
            Self::BadValue => "not a number, a number with its unit, or a name",
            Self::WrongUnit => "not the setting's unit",
            Self::DecimalWithoutUnit => "a decimal needs its unit (plain numbers are raw units)",
            Self::NotAStep => "not a whole number of the register's steps",
            Self::NotAnOption => "not one of the setting's values",
            Self::AmbiguousName => "two values have this name: add the number, `NAME (N)`",
            Self::Duplicate => "given twice",
        }
    }
}

/// A profile line that does not parse, with the evidence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProfileError<'a> {
    /// 1-based line number (1 for [`parse_assignment`]).
    pub line: u32,
    /// What is wrong.
    pub kind: ProfileErrorKind,
    /// The offending text: the whole assignment, the name or the value.
    pub text: &'a str,
}

/// Parses one `NAME = VALUE` assignment (no comment).
pub const fn parse_assignment(s: &str) -> Result<(SettingId, i32), ProfileError<'_>> {
    const fn err(kind: ProfileErrorKind, text: &str) -> ProfileError<'_> {
        ProfileError {
            line: 1,
            kind,
            text,
        }
    }
    let Some((name, value)) = split_once(s, b'=') else {
        return Err(err(ProfileErrorKind::ExpectedAssignment, trim(s)));
    };
    let Some(id) = find_setting(name) else {
        return Err(err(ProfileErrorKind::UnknownSetting, trim(name)));
    };
    let value = trim(value);
    match parse_value(id, value) {
        Ok(v) => Ok((id, v)),
        Err(kind) => Err(err(kind, value)),
    }
}

/// A register's scale as an integer step and decimals, `scale = step ×
/// 10^-decimals` (0.001 → (1, 3), 0.002 → (2, 3), 1.0 → (1, 0)); a `const fn`
/// twin of [`crate::units::scale_parts`] (a host test checks they agree).
pub const fn scale_parts(scale: f32) -> (i64, u32) {
    let scale = scale as f64;
    let mut k = 0;
    let mut p = 1.0f64;
    while k <= 6 {
        let m = scale * p;
        let step = (m + 0.5) as i64;
        let d = m - step as f64;
        let d = if d < 0.0 { -d } else { d };
        if step >= 1 && d < 1e-6 * m {
            return (step, k);
        }
        k += 1;
        p *= 10.0;
    }
    (1, 0)
}

/// ASCII lowercase of letters and digits only (what names are compared on).
const fn next_alnum(b: &[u8], mut i: usize) -> (Option<u8>, usize) {
    while let Some((_, [c, ..])) = b.split_at_checked(i) {
        let c = *c;
        i += 1;
        if c.is_ascii_alphanumeric() {
            return (Some(c.to_ascii_lowercase()), i);
        }
        if c >= 0x80 {
            return (Some(c), i);
        }
    }
    (None, i)
}

/// `a` and `b` equal but for case, spaces and punctuation (`CC/CV` = `cccv`).
const fn loose_eq(a: &[u8], b: &[u8]) -> bool {
    let (mut i, mut j) = (0, 0);
    loop {
        let (x, ni) = next_alnum(a, i);
        let (y, nj) = next_alnum(b, j);
        match (x, y) {
            (None, None) => return true,
            (Some(x), Some(y)) if x == y => {}
            _ => return false,
        }
        (i, j) = (ni, nj);
    }
}

/// An enumeration value by its name, maybe followed by `(N)` (which must agree).
const fn option_value(options: &[(u16, &str)], text: &str) -> Result<i32, ProfileErrorKind> {
    // `Name (N)`: the number in the last parentheses (names may hold some).
    let (name, number) = match rsplit_once(text, b'(') {
        Some((name, rest)) => match split_once(rest, b')') {
            Some((n, tail)) if trim(tail).is_empty() => match u16::from_str_radix(trim(n), 10) {
                Ok(v) => (name, Some(v)),
                Err(_) => (text, None),
            },
            _ => (text, None),
        },
        None => (text, None),
    };
    // Rev D gives two values one name (337: 0x0A and 0x10): then the number
    // decides, and the name alone is refused.
    let mut found: Option<u16> = None;
    let mut rest = options;
    while let [(v, n), tail @ ..] = rest {
        if loose_eq(n.as_bytes(), name.as_bytes()) {
            match number {
                Some(x) if x == *v => return Ok(*v as i32),
                Some(_) => {}
                None if found.is_some() => return Err(ProfileErrorKind::AmbiguousName),
                None => found = Some(*v),
            }
        }
        rest = tail;
    }
    match found {
        Some(v) => Ok(v as i32),
        None => Err(ProfileErrorKind::NotAnOption),
    }
}

/// A flags register's value from its bits' names joined by `+` (`none`: 0),
/// maybe followed by `(N)` (which must agree). `options` are (bit, name).
const fn bits_value(options: &[(u16, &str)], text: &str) -> Result<i32, ProfileErrorKind> {
    let (names, number) = match rsplit_once(text, b'(') {
        Some((names, rest)) => match split_once(rest, b')') {
            Some((n, tail)) if trim(tail).is_empty() => match u16::from_str_radix(trim(n), 10) {
                Ok(v) => (names, Some(v)),
                Err(_) => return Err(ProfileErrorKind::NotAnOption),
            },
            _ => return Err(ProfileErrorKind::NotAnOption),
        },
        None => (text, None),
    };
    let mut value: u16 = 0;
    if !loose_eq(trim(names).as_bytes(), b"none") {
        let mut rest = names;
        loop {
            let (one, tail) = match split_once(rest, b'+') {
                Some(split) => split,
                None => (rest, ""),
            };
            let mut bit: Option<u16> = None;
            let mut opts = options;
            while let [(b, n), more @ ..] = opts {
                if loose_eq(n.as_bytes(), one.as_bytes()) {
                    bit = Some(*b);
                }
                opts = more;
            }
            match bit {
                Some(b) if b < 16 => value |= 1 << b,
                _ => return Err(ProfileErrorKind::NotAnOption),
            }
            if tail.is_empty() {
                break;
            }
            rest = tail;
        }
    }
    match number {
        Some(n) if n != value => Err(ProfileErrorKind::NotAnOption),
        _ => Ok(value as i32),
    }
}

/// The value of a setting from its text (see the module's "Format"): a raw
/// integer, a number with the setting's unit (or its milli-unit: `mV`, `mA`,
/// `mAh`; `C` for `°C`) converted exactly, or an enumeration value's name
/// (optionally followed by its number in parentheses, which must agree).
pub const fn parse_value(id: SettingId, text: &str) -> Result<i32, ProfileErrorKind> {
    let text = trim(text);
    if let Ok(v) = i32::from_str_radix(text, 10) {
        return Ok(v);
    }
    let Some(r) = id.register() else {
        return Err(ProfileErrorKind::BadValue);
    };
    // Flags by name: `Name + Name`, `none`, maybe with `(N)`.
    if matches!(r.value_type, protocol_core::registers::ValueType::Bits) && !r.options.is_empty() {
        return bits_value(r.options, text);
    }
    // A name first: some names look like numbers (338: `0.1 s`).
    if !r.options.is_empty() {
        match option_value(r.options, text) {
            Err(ProfileErrorKind::NotAnOption) => {}
            other => return other,
        }
    }
    let b = text.as_bytes();
    // A number: [sign] digits [. digits], then the unit.
    let mut i = 0;
    let negative = matches!(b.first(), Some(b'-'));
    if matches!(b.first(), Some(b'-' | b'+')) {
        i = 1;
    }
    let mut mantissa: i64 = 0;
    let mut decimals: u32 = 0;
    let mut digits = 0;
    let mut point = false;
    while let Some((_, [c, ..])) = b.split_at_checked(i) {
        let c = *c;
        if c.is_ascii_digit() {
            mantissa = match mantissa.checked_mul(10) {
                Some(m) => m + (c - b'0') as i64,
                None => return Err(ProfileErrorKind::BadValue),
            };
            if mantissa > 1_000_000_000_000 {
                return Err(ProfileErrorKind::BadValue);
            }
            digits += 1;
            if point {
                decimals += 1;
            }
        } else if c == b'.' && !point {
            point = true;
        } else {
            break;
        }
        i += 1;
    }
    if digits > 0 {
        let unit = trim(match text.split_at_checked(i) {
            Some((_, u)) => u,
            None => "",
        });
        if unit.is_empty() {
            return Err(if point {
                ProfileErrorKind::DecimalWithoutUnit
            } else {
                ProfileErrorKind::BadValue
            });
        }
        // The unit's power of ten relative to the register's unit.
        let u = unit.as_bytes();
        let base = r.unit.as_bytes();
        let exp: i32 = if r.unit.is_empty() {
            return Err(ProfileErrorKind::WrongUnit);
        } else if unit.eq_ignore_ascii_case(r.unit) {
            0
        } else if matches!(u, [b'm', ..])
            && matches!(base, b"V" | b"A" | b"Ah")
            && match unit.split_at_checked(1) {
                Some((_, rest)) => rest.eq_ignore_ascii_case(r.unit),
                None => false,
            }
        {
            -3
        } else if matches!(base, b"\xC2\xB0C")
            && (unit.eq_ignore_ascii_case("C") || unit.eq_ignore_ascii_case("degC"))
        {
            0
        } else {
            return Err(ProfileErrorKind::WrongUnit);
        };
        // raw = mantissa × 10^(exp - decimals) / (step × 10^-k)
        let (step, k) = scale_parts(r.scale);
        let mut x = k as i32 + exp - decimals as i32;
        let mut n = mantissa;
        while x > 0 {
            n = match n.checked_mul(10) {
                Some(n) => n,
                None => return Err(ProfileErrorKind::BadValue),
            };
            x -= 1;
        }
        while x < 0 {
            if n % 10 != 0 {
                return Err(ProfileErrorKind::NotAStep);
            }
            n /= 10;
            x += 1;
        }
        if n % step != 0 {
            return Err(ProfileErrorKind::NotAStep);
        }
        let raw = if negative { -(n / step) } else { n / step };
        if raw < i32::MIN as i64 || raw > i32::MAX as i64 {
            return Err(ProfileErrorKind::BadValue);
        }
        return Ok(raw as i32);
    }
    Err(if r.options.is_empty() {
        ProfileErrorKind::BadValue
    } else {
        ProfileErrorKind::NotAnOption
    })
}

/// The next assignment of a profile text after `line` lines were read from it,
/// skipping comments and blank lines: the assignment (or the error, with its line
/// number), the rest of the text and the lines read; `None` at the end.
#[allow(clippy::type_complexity)]
const fn next_entry(
    mut text: &str,
    mut line: u32,
) -> Option<(Result<(SettingId, i32), ProfileError<'_>>, &str, u32)> {
    while !text.is_empty() {
        let raw;
        (raw, text) = match split_once(text, b'\n') {
            Some(split) => split,
            None => (text, ""),
        };
        line = line.saturating_add(1);
        let content = match split_once(raw, b'#') {
            Some((before, _)) => before,
            None => raw,
        };
        let content = trim(content);
        if content.is_empty() {
            continue;
        }
        let entry = match parse_assignment(content) {
            Ok(a) => Ok(a),
            Err(e) => Err(ProfileError { line, ..e }),
        };
        return Some((entry, text, line));
    }
    None
}

/// The assignments of a profile text, in order, each with its line number in
/// the error. Comments and blank lines are skipped.
#[derive(Debug, Clone)]
pub struct Entries<'a> {
    rest: &'a str,
    line: u32,
}

impl Entries<'_> {
    /// The line number of the assignment (or error) read last.
    pub fn line(&self) -> u32 {
        self.line
    }
}

/// Iterates over the assignments of a profile text.
pub fn entries(text: &str) -> Entries<'_> {
    Entries {
        rest: text,
        line: 0,
    }
}

impl<'a> Iterator for Entries<'a> {
    type Item = Result<(SettingId, i32), ProfileError<'a>>;

    fn next(&mut self) -> Option<Self::Item> {
        let (entry, rest, line) = next_entry(self.rest, self.line)?;
        (self.rest, self.line) = (rest, line);
        Some(entry)
    }
}

/// Why a whole profile was refused by [`parse`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParseError<'a> {
    /// A line does not parse.
    Line(ProfileError<'a>),
    /// More than `N` assignments (the line of the first one too many).
    TooMany {
        /// Line number.
        line: u32,
    },
}

/// The assignments of a whole profile, in order (at most `N`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Profile<const N: usize> {
    entries: [(SettingId, i32); N],
    len: usize,
}

impl<const N: usize> Profile<N> {
    /// The assignments.
    pub fn as_slice(&self) -> &[(SettingId, i32)] {
        self.entries.get(..self.len).unwrap_or(&[])
    }
    /// How many.
    pub const fn len(&self) -> usize {
        self.len
    }
    /// None at all.
    pub const fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// Parses a whole profile: every assignment, or the first error (then nothing
/// is to be written). A `const fn`: the firmware parses its start-up profile at
/// compile time.
pub const fn parse<const N: usize>(text: &str) -> Result<Profile<N>, ParseError<'_>> {
    let mut out = Profile {
        entries: [(SettingId::FullyChargedVoltage, 0); N],
        len: 0,
    };
    let (mut rest, mut line) = (text, 0);
    while let Some((entry, tail, at)) = next_entry(rest, line) {
        (rest, line) = (tail, at);
        let entry = match entry {
            Ok(entry) => entry,
            Err(e) => return Err(ParseError::Line(e)),
        };
        let mut seen: &[(SettingId, i32)] = match out.entries.split_at_checked(out.len) {
            Some((seen, _)) => seen,
            None => &out.entries,
        };
        while let [(id, _), tail @ ..] = seen {
            if *id as u8 == entry.0 as u8 {
                return Err(ParseError::Line(ProfileError {
                    line,
                    kind: ProfileErrorKind::Duplicate,
                    text: setting_key(entry.0),
                }));
            }
            seen = tail;
        }
        match out.entries.split_at_mut_checked(out.len) {
            Some((_, [slot, ..])) => *slot = entry,
            _ => return Err(ParseError::TooMany { line }),
        }
        out.len += 1;
    }
    Ok(out)
}
