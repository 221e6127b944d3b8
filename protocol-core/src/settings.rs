//! Settings (registers 300-343, Rev D §3.4) as typed values with validation.
//!
//! A [`Setting`] is one setting field with a value in raw register units. It is
//! checked against Rev D's range and enumerations when built, and against the
//! BMS's own min/max (command 0x1D) with [`Setting::check_limits`]. Low-byte
//! fields (330-343) and 330's high byte are written read-modify-write: the
//! [`Setting::words`] encoder needs the current register value and keeps the
//! other byte.

use crate::registers::{self as regs, Field, Register, ValueType};
use crate::response::RegisterBlock;

macro_rules! setting_ids {
    ($( $(#[$m:meta])* $v:ident = ($addr:literal, $field:ident) ),* $(,)?) => {
        /// Every writable setting field of Rev D §3.4.
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        pub enum SettingId { $( $(#[$m])* $v, )* }

        impl SettingId {
            /// All settings, in register order.
            pub const ALL: &'static [SettingId] = &[$(SettingId::$v),*];
            /// Register address.
            pub const fn address(self) -> u16 {
                match self { $(SettingId::$v => $addr,)* }
            }
            /// Field within the register.
            pub const fn field(self) -> Field {
                match self { $(SettingId::$v => Field::$field,)* }
            }
        }
    };
}

setting_ids! {
    /// 300, mV.
    FullyChargedVoltage = (300, Whole),
    /// 301, mV.
    FullyDischargedVoltage = (301, Whole),
    /// 303, mV.
    EarlyBalancingThreshold = (303, Whole),
    /// 304, mA.
    ChargeFinishedCurrent = (304, Whole),
    /// 305, A.
    PeakDischargeCurrentCutoff = (305, Whole),
    /// 306, 0.01 Ah.
    BatteryCapacity = (306, Whole),
    /// 307, cells.
    NumberOfSeriesCells = (307, Whole),
    /// 308, mV.
    AllowedDisbalance = (308, Whole),
    /// 310, s.
    ChargerStartupDelay = (310, Whole),
    /// 311, s.
    ChargerDisableDelay = (311, Whole),
    /// 312-313, pulses per unit (32 bits).
    PulsesPerUnit = (312, Whole),
    /// 314.
    DistanceUnit = (314, Whole),
    /// 315, mV.
    OverVoltageCutoff = (315, Whole),
    /// 316, mV.
    UnderVoltageCutoff = (316, Whole),
    /// 317, A.
    DischargeOverCurrentCutoff = (317, Whole),
    /// 318, A.
    ChargeOverCurrentCutoff = (318, Whole),
    /// 319, °C.
    OverHeatCutoff = (319, Whole),
    /// 320, °C.
    LowTemperatureChargerCutoff = (320, Whole),
    /// 321, %.
    ChargeRestartLevel = (321, Whole),
    /// 322, cycles.
    BatteryMaximumCycles = (322, Whole),
    /// 323, 0.002 % (reads back 0xFFFF when accepted).
    StateOfHealth = (323, Whole),
    /// 328, 0.002 % (reads back 0xFFFF when accepted).
    StateOfCharge = (328, Whole),
    /// 329, bit flags.
    ConfigurationFlags = (329, Whole),
    /// 330 low byte.
    ChargerType = (330, LowByte),
    /// 330 high byte, s.
    DischargeOverCurrentTimeout = (330, HighByte),
    /// 331 low byte.
    LoadSwitchType = (331, LowByte),
    /// 332 low byte, s.
    AutomaticRecovery = (332, LowByte),
    /// 333 low byte.
    ChargerSwitchType = (333, LowByte),
    /// 334 low byte.
    Ignition = (334, LowByte),
    /// 335 low byte.
    ChargerDetection = (335, LowByte),
    /// 336 low byte.
    SpeedSensorInput = (336, LowByte),
    /// 337 low byte.
    PrechargePin = (337, LowByte),
    /// 338 low byte.
    PrechargeDuration = (338, LowByte),
    /// 339 low byte.
    TemperatureSensorType = (339, LowByte),
    /// 340 low byte: writing it restarts the BMS.
    OperationMode = (340, LowByte),
    /// 341 low byte.
    SinglePortSwitchType = (341, LowByte),
    /// 342 low byte.
    BroadcastTime = (342, LowByte),
    /// 343 low byte.
    Protocol = (343, LowByte),
}

/// The register-map row of each setting, indexed by `SettingId as usize` (the
/// order of [`SettingId::ALL`]), copied out of [`regs::REGISTERS`] at compile
/// time: the chip then links these rows, not the whole table with the names and
/// options of every register (with `is_continuation`'s table, 5.2 KB of flash).
/// A constant (one allocation, shared by every use) so that [`SettingId::name`]
/// and [`SettingId::from_address`] work in constant evaluation: the firmware
/// parses its start-up profile at compile time.
const SETTING_ROWS: &[Option<Register>; SettingId::ALL.len()] = &setting_rows();

// Evaluated at compile time only: an index out of bounds, or `ALL` out of
// declaration order, fails the build.
#[allow(clippy::indexing_slicing)]
const fn setting_rows<const N: usize>() -> [Option<Register>; N] {
    let mut out = [None; N];
    let mut i = 0;
    while i < N {
        let id = SettingId::ALL[i];
        assert!(id as usize == i, "SettingId::ALL is in declaration order");
        let mut rest = regs::REGISTERS;
        while let [r, tail @ ..] = rest {
            if r.address == id.address() && r.field as u8 == id.field() as u8 {
                out[i] = Some(*r);
                break;
            }
            rest = tail;
        }
        i += 1;
    }
    out
}

/// Read-back value of 323 and 328 when the BMS accepted the write (Rev D §3.4,
/// HARDWARE-NOTES).
pub const ACCEPTED_MARKER: u16 = 0xFFFF;

impl SettingId {
    /// The register-map row describing this setting (the first row of
    /// [`regs::REGISTERS`] with its address and field).
    pub const fn register(self) -> Option<&'static Register> {
        match SETTING_ROWS.split_at_checked(self as usize) {
            Some((_, [row, ..])) => row.as_ref(),
            _ => None,
        }
    }
    /// Rev D's name.
    pub const fn name(self) -> &'static str {
        match self.register() {
            Some(r) => r.name,
            None => "?",
        }
    }
    /// Looks a setting up by register address and field.
    pub const fn from_address(address: u16, field: Field) -> Option<Self> {
        let mut rest = Self::ALL;
        while let [id, tail @ ..] = rest {
            if id.address() == address && id.field() as u8 == field as u8 {
                return Some(*id);
            }
            rest = tail;
        }
        None
    }
    /// Registers the setting occupies (2 for the 32-bit 312-313).
    pub const fn register_count(self) -> u16 {
        match self {
            SettingId::PulsesPerUnit => 2,
            _ => 1,
        }
    }
    /// True when the BMS reads this register back as [`ACCEPTED_MARKER`] once it
    /// accepted a write.
    pub const fn reads_back_marker(self) -> bool {
        matches!(self, SettingId::StateOfHealth | SettingId::StateOfCharge)
    }
    /// True when writing it restarts the BMS (HARDWARE-NOTES: register 340).
    pub const fn restarts_bms(self) -> bool {
        matches!(self, SettingId::OperationMode)
    }
    /// True for the signed settings (319, 320).
    pub fn is_signed(self) -> bool {
        self.register()
            .map(|r| r.value_type == ValueType::I16)
            .unwrap_or(false)
    }

    /// Interprets raw register words as this setting's value.
    pub fn value_from_words(self, first: u16, second: Option<u16>) -> Option<i32> {
        Some(match self {
            SettingId::PulsesPerUnit => regs::u32_from_words(first, second?) as i32,
            s if s.is_signed() => i32::from(first as i16),
            s => i32::from(s.field().get(first)),
        })
    }

    /// The current value of this setting in `block`.
    pub fn read(self, block: &RegisterBlock) -> Option<i32> {
        let a = self.address();
        let second = if self.register_count() == 2 {
            Some(block.get(a + 1)?)
        } else {
            None
        };
        self.value_from_words(block.get(a)?, second)
    }

    /// The (min, max) this BMS reports through 0x1D options 0x01 and 0x02.
    pub fn limits(self, min: &RegisterBlock, max: &RegisterBlock) -> Option<(i32, i32)> {
        Some((self.read(min)?, self.read(max)?))
    }
}

/// Why a setting value is refused (before any byte is sent).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum SettingError {
    /// Outside Rev D's range.
    OutOfRange {
        /// Setting.
        id: SettingId,
        /// Value asked for.
        value: i32,
        /// Rev D minimum.
        min: i32,
        /// Rev D maximum.
        max: i32,
    },
    /// Not one of the enumerated values.
    NotAnOption {
        /// Setting.
        id: SettingId,
        /// Value asked for.
        value: i32,
    },
    /// Outside the min/max the BMS reports for itself (0x1D).
    OutsideBmsLimits {
        /// Setting.
        id: SettingId,
        /// Value asked for.
        value: i32,
        /// BMS minimum.
        min: i32,
        /// BMS maximum.
        max: i32,
    },
    /// The current register value needed for read-modify-write is missing.
    CurrentValueUnknown {
        /// Setting.
        id: SettingId,
    },
    /// A per-cell voltage plainly wrong for the pack's cell chemistry (4.2 V
    /// on a LiFePO4 pack): see [`Chemistry::range`]. Unlike a broken
    /// [`Relation`], an expert may pass this one (another chemistry than the
    /// one inferred): [`ChemistryCheck::Off`].
    OutsideChemistry {
        /// Setting.
        id: SettingId,
        /// Value asked for.
        value: i32,
        /// The chemistry it was checked against.
        chemistry: Chemistry,
        /// Lowest plausible value for it, raw.
        min: i32,
        /// Highest plausible value for it, raw.
        max: i32,
    },
    /// The value would break a relation with another setting (the value the
    /// BMS holds, or the one written with it): see [`RELATIONS`].
    Contradicts {
        /// Setting.
        id: SettingId,
        /// Value asked for.
        value: i32,
        /// The relation it breaks.
        relation: Relation,
        /// The other setting's value it was checked against.
        other: i32,
    },
}

/// `low` must stay below `high` (by at least `gap`, raw units): a relation
/// between two BMS settings that Rev D's per-register ranges cannot express.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Relation {
    /// The setting that must be lower.
    pub low: SettingId,
    /// The setting that must be higher.
    pub high: SettingId,
    /// By at least this much (0: equal is allowed).
    pub gap: i32,
}

/// The relations every write is checked against, with the BMS's other
/// values: an under-voltage cutoff above the over-voltage cutoff shuts the
/// pack down at once; a fully-charged voltage above the over-voltage cutoff
/// (4.2 V on a LiFePO4 pack) drives the cells into the cutoff before the
/// charge counts as done; a fully-discharged voltage below the under-voltage
/// cutoff never comes; a charge cut-off temperature above the overheat one
/// leaves no temperature to charge at.
pub const RELATIONS: &[Relation] = &[
    Relation {
        low: SettingId::UnderVoltageCutoff,
        high: SettingId::OverVoltageCutoff,
        gap: 1,
    },
    Relation {
        low: SettingId::FullyDischargedVoltage,
        high: SettingId::FullyChargedVoltage,
        gap: 1,
    },
    Relation {
        low: SettingId::FullyChargedVoltage,
        high: SettingId::OverVoltageCutoff,
        gap: 0,
    },
    Relation {
        low: SettingId::UnderVoltageCutoff,
        high: SettingId::FullyDischargedVoltage,
        gap: 0,
    },
    Relation {
        low: SettingId::LowTemperatureChargerCutoff,
        high: SettingId::OverHeatCutoff,
        gap: 1,
    },
];

/// Checks `s` against [`RELATIONS`], the other settings' values given by
/// `value_of` (those written with it first, else what the BMS holds; `None`:
/// unknown, not checked).
pub fn check_relations(
    s: &Setting,
    value_of: impl Fn(SettingId) -> Option<i32>,
) -> Result<(), SettingError> {
    for r in RELATIONS {
        let (other_id, low, high) = if r.low == s.id {
            (r.high, Some(s.value), value_of(r.high))
        } else if r.high == s.id {
            (r.low, value_of(r.low), Some(s.value))
        } else {
            continue;
        };
        let _ = other_id;
        if let (Some(low), Some(high)) = (low, high) {
            if high.saturating_sub(low) < r.gap {
                let other = if r.low == s.id { high } else { low };
                return Err(SettingError::Contradicts {
                    id: s.id,
                    value: s.value,
                    relation: *r,
                    other,
                });
            }
        }
    }
    Ok(())
}

/// A lithium cell chemistry: which per-cell voltages make sense for a pack
/// of it. The TinyBMS has no register that says the chemistry (Rev D §3.4
/// has none: the BMS only holds voltages), so it is inferred from the
/// voltages the BMS holds ([`Chemistry::infer`]) or given by the owner.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Chemistry {
    /// Lithium iron phosphate (3.2 V nominal, 3.65 V full).
    LiFePO4,
    /// Lithium-ion NMC / NCA (3.6-3.7 V nominal, 4.2 V full; 4.35 V for HV
    /// cells).
    LiIon,
    /// Lithium titanate (2.3-2.4 V nominal, 2.7-2.85 V full).
    Lto,
}

/// The per-cell window (raw, mV) of each voltage setting for LiFePO4,
/// Li-ion and LTO, in that order: outside it the setting is plainly wrong for
/// that chemistry. Generous on purpose (the cell makers' limits and a
/// margin): it catches a value meant for another chemistry, not a tuning.
/// The over-voltage and fully-charged windows of the three do not overlap,
/// so either names one chemistry.
pub const CHEMISTRY_RANGES: &[(SettingId, [(i32, i32); 3])] = &[
    (
        SettingId::OverVoltageCutoff,
        [(3400, 3800), (4000, 4350), (2600, 2950)],
    ),
    (
        SettingId::FullyChargedVoltage,
        [(3300, 3700), (3900, 4300), (2500, 2900)],
    ),
    (
        SettingId::EarlyBalancingThreshold,
        [(3200, 3700), (3600, 4300), (2300, 2900)],
    ),
    (
        SettingId::UnderVoltageCutoff,
        [(2000, 3000), (2500, 3400), (1500, 2300)],
    ),
    (
        SettingId::FullyDischargedVoltage,
        [(2500, 3200), (2800, 3500), (1700, 2400)],
    ),
];

impl Chemistry {
    /// Every chemistry, in the order of [`CHEMISTRY_RANGES`]' windows.
    pub const ALL: [Chemistry; 3] = [Chemistry::LiFePO4, Chemistry::LiIon, Chemistry::Lto];

    /// As a command line or the host link names it: `lifepo4`, `li-ion`, `lto`.
    pub const fn key(self) -> &'static str {
        match self {
            Self::LiFePO4 => "lifepo4",
            Self::LiIon => "li-ion",
            Self::Lto => "lto",
        }
    }

    /// In words.
    pub const fn name(self) -> &'static str {
        match self {
            Self::LiFePO4 => "LiFePO4",
            Self::LiIon => "Li-ion (NMC/NCA)",
            Self::Lto => "LTO",
        }
    }

    /// From its key or a usual name (`lfp`, `nmc`, `nca`, `liion`; ASCII
    /// case ignored).
    pub fn from_key(s: &str) -> Option<Self> {
        let is = |k: &str| s.eq_ignore_ascii_case(k);
        if is("lifepo4") || is("lfp") {
            Some(Self::LiFePO4)
        } else if is("li-ion") || is("liion") || is("nmc") || is("nca") {
            Some(Self::LiIon)
        } else if is("lto") {
            Some(Self::Lto)
        } else {
            None
        }
    }

    const fn index(self) -> usize {
        match self {
            Self::LiFePO4 => 0,
            Self::LiIon => 1,
            Self::Lto => 2,
        }
    }

    /// The plausible window of `id` for this chemistry (raw, mV per cell);
    /// `None` for a setting that is not a cell voltage.
    pub fn range(self, id: SettingId) -> Option<(i32, i32)> {
        CHEMISTRY_RANGES
            .iter()
            .find(|(s, _)| *s == id)
            .and_then(|(_, w)| w.get(self.index()).copied())
    }

    /// The chemistry the BMS's own voltages name (`value_of`: what it holds):
    /// its over-voltage cutoff, else its fully-charged voltage, in one
    /// chemistry's window. `None` when neither is known or neither fits one.
    pub fn infer(value_of: impl Fn(SettingId) -> Option<i32>) -> Option<(Self, SettingId, i32)> {
        for id in [SettingId::OverVoltageCutoff, SettingId::FullyChargedVoltage] {
            let Some(v) = value_of(id) else { continue };
            for c in Self::ALL {
                if let Some((lo, hi)) = c.range(id) {
                    if (lo..=hi).contains(&v) {
                        return Some((c, id, v));
                    }
                }
            }
        }
        None
    }
}

/// Which chemistry a write is checked against.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ChemistryCheck {
    /// The one the BMS's own voltages name ([`Chemistry::infer`]); none (no
    /// check) when they name none.
    Inferred,
    /// This one (the owner said).
    Given(Chemistry),
    /// None: the owner forces the values (never the [`RELATIONS`]).
    Off,
}

impl ChemistryCheck {
    /// The chemistry to check against, the BMS holding `value_of`.
    pub fn chemistry(self, value_of: impl Fn(SettingId) -> Option<i32>) -> Option<Chemistry> {
        match self {
            Self::Inferred => Chemistry::infer(value_of).map(|(c, _, _)| c),
            Self::Given(c) => Some(c),
            Self::Off => None,
        }
    }
}

/// Checks `s` against `chemistry`'s window ([`Chemistry::range`]); a
/// setting that is not a cell voltage always passes.
pub fn check_chemistry(s: &Setting, chemistry: Chemistry) -> Result<(), SettingError> {
    match chemistry.range(s.id) {
        Some((min, max)) if s.value < min || s.value > max => Err(SettingError::OutsideChemistry {
            id: s.id,
            value: s.value,
            chemistry,
            min,
            max,
        }),
        _ => Ok(()),
    }
}

impl SettingError {
    /// Short snake_case reason.
    pub const fn reason(&self) -> &'static str {
        match self {
            Self::OutOfRange { .. } => "out_of_rev_d_range",
            Self::NotAnOption { .. } => "not_an_option",
            Self::OutsideBmsLimits { .. } => "outside_bms_limits",
            Self::CurrentValueUnknown { .. } => "current_value_unknown",
            Self::Contradicts { .. } => "contradicts_another_setting",
            Self::OutsideChemistry { .. } => "outside_chemistry_range",
        }
    }
}

/// One setting and the value to give it, in raw register units.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Setting {
    /// Which setting.
    pub id: SettingId,
    /// Raw value (mV, A, s, enumeration value, ...).
    pub value: i32,
}

/// The register words of one setting write: (address, value), one or two.
pub type SettingWords = heapless::Vec<(u16, u16), 2>;

impl Setting {
    /// A setting checked against Rev D's range and enumerations.
    pub fn new(id: SettingId, value: i32) -> Result<Self, SettingError> {
        let s = Setting { id, value };
        s.validate()?;
        Ok(s)
    }

    /// Checks Rev D's range and enumerations.
    pub fn validate(&self) -> Result<(), SettingError> {
        self.validate_with(None)
    }

    /// Checks a value before it is written, given the (min, max) the BMS
    /// reported for this setting through 0x1D, when known.
    ///
    /// Rev D marks 304, 305, 317 and 318 as changed by the BMS "according to the
    /// current sensor" (its `*` note), and HARDWARE-NOTES says to prefer the 0x1D
    /// limits: for those, the BMS's limits replace the static range when known
    /// (e.g. 317 = 900 A on a unit whose external sensor allows it). Every other
    /// setting must pass both. Enumerations are always checked.
    pub fn validate_with(&self, bms_limits: Option<(i32, i32)>) -> Result<(), SettingError> {
        let Some(r) = self.id.register() else {
            return Err(SettingError::NotAnOption {
                id: self.id,
                value: self.value,
            });
        };
        let static_range = match bms_limits {
            Some(_) if r.sensor_dependent => None,
            _ => r.range,
        };
        if let Some((min, max)) = static_range {
            if self.value < min || self.value > max {
                return Err(SettingError::OutOfRange {
                    id: self.id,
                    value: self.value,
                    min,
                    max,
                });
            }
        }
        if !r.options.is_empty()
            && r.value_type != ValueType::Bits
            && !r.options.iter().any(|&(v, _)| i32::from(v) == self.value)
        {
            return Err(SettingError::NotAnOption {
                id: self.id,
                value: self.value,
            });
        }
        if let Some((min, max)) = bms_limits {
            self.check_limits(min, max)?;
        }
        Ok(())
    }

    /// Checks the min/max the BMS reports (0x1D), which depend on the current
    /// sensor for 304, 305, 317 and 318 (HARDWARE-NOTES).
    pub fn check_limits(&self, min: i32, max: i32) -> Result<(), SettingError> {
        if self.value < min || self.value > max {
            Err(SettingError::OutsideBmsLimits {
                id: self.id,
                value: self.value,
                min,
                max,
            })
        } else {
            Ok(())
        }
    }

    /// The register words to write. `current` is the present value of the
    /// setting's register, needed for byte fields (read-modify-write).
    pub fn words(&self, current: Option<u16>) -> Result<SettingWords, SettingError> {
        let a = self.id.address();
        let mut out = SettingWords::new();
        match self.id.field() {
            Field::Whole if self.id.register_count() == 2 => {
                let (lo, hi) = regs::words_from_u32(self.value as u32);
                let _ = out.push((a, lo));
                let _ = out.push((a + 1, hi));
            }
            Field::Whole => {
                let _ = out.push((a, self.value as u16));
            }
            field => {
                let cur = current.ok_or(SettingError::CurrentValueUnknown { id: self.id })?;
                let _ = out.push((a, field.set(cur, self.value as u16)));
            }
        }
        Ok(out)
    }

    /// True when `readback` (raw words of the setting's registers) shows the
    /// value was taken: equal, or [`ACCEPTED_MARKER`] for 323/328.
    pub fn matches_readback(&self, first: u16, second: Option<u16>) -> bool {
        if self.id.reads_back_marker() && first == ACCEPTED_MARKER {
            return true;
        }
        self.id.value_from_words(first, second) == Some(self.value)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_setting_has_a_row() {
        for id in SettingId::ALL {
            let r = id.register().unwrap();
            assert!(crate::command::WRITABLE.contains(&r.address), "{id:?}");
            assert!(r.range.is_some(), "{id:?}");
        }
        assert_eq!(SettingId::ALL.len(), 38);
    }

    #[test]
    fn rev_d_ranges_enforced() {
        assert!(Setting::new(SettingId::OverVoltageCutoff, 4200).is_ok());
        assert_eq!(
            Setting::new(SettingId::OverVoltageCutoff, 4600),
            Err(SettingError::OutOfRange {
                id: SettingId::OverVoltageCutoff,
                value: 4600,
                min: 1200,
                max: 4500
            })
        );
        assert!(Setting::new(SettingId::LowTemperatureChargerCutoff, -40).is_ok());
        assert!(Setting::new(SettingId::LowTemperatureChargerCutoff, -41).is_err());
        assert_eq!(
            Setting::new(SettingId::PrechargePin, 1),
            Err(SettingError::NotAnOption {
                id: SettingId::PrechargePin,
                value: 1
            })
        );
        assert!(Setting::new(SettingId::PrechargePin, 0x10).is_ok());
        assert!(Setting::new(SettingId::DischargeOverCurrentTimeout, 31).is_err());
        let s = Setting::new(SettingId::ChargeOverCurrentCutoff, 200).unwrap();
        assert_eq!(
            s.check_limits(1, 100),
            Err(SettingError::OutsideBmsLimits {
                id: SettingId::ChargeOverCurrentCutoff,
                value: 200,
                min: 1,
                max: 100
            })
        );
    }

    #[test]
    fn byte_fields_keep_the_other_byte() {
        let s = Setting::new(SettingId::ChargerType, 1).unwrap();
        assert_eq!(s.words(Some(0x0A02)).unwrap().as_slice(), &[(330, 0x0A01)]);
        assert_eq!(
            s.words(None),
            Err(SettingError::CurrentValueUnknown {
                id: SettingId::ChargerType
            })
        );
        let t = Setting::new(SettingId::DischargeOverCurrentTimeout, 5).unwrap();
        assert_eq!(t.words(Some(0x0A01)).unwrap().as_slice(), &[(330, 0x0501)]);
        let b = Setting::new(SettingId::BroadcastTime, 4).unwrap();
        assert_eq!(b.words(Some(0xAB00)).unwrap().as_slice(), &[(342, 0xAB04)]);
        assert!(b.matches_readback(0xAB04, None));
        assert!(!b.matches_readback(0xAB05, None));
    }

    #[test]
    fn wide_signed_and_marker() {
        let p = Setting::new(SettingId::PulsesPerUnit, 100_000).unwrap();
        assert_eq!(
            p.words(None).unwrap().as_slice(),
            &[(312, 0x86A0), (313, 0x0001)]
        );
        assert!(p.matches_readback(0x86A0, Some(1)));
        let t = Setting::new(SettingId::LowTemperatureChargerCutoff, -10).unwrap();
        assert_eq!(t.words(None).unwrap().as_slice(), &[(320, 0xFFF6)]);
        assert!(t.matches_readback(0xFFF6, None));
        let soc = Setting::new(SettingId::StateOfCharge, 25000).unwrap();
        assert!(soc.matches_readback(0xFFFF, None));
        assert!(soc.matches_readback(25000, None));
        assert!(!soc.matches_readback(24999, None));
        let ov = Setting::new(SettingId::OverVoltageCutoff, 4200).unwrap();
        assert!(!ov.matches_readback(0xFFFF, None));
    }

    #[test]
    fn sensor_dependent_settings_follow_the_bms_limits_when_known() {
        for id in [
            SettingId::DischargeOverCurrentCutoff,
            SettingId::ChargeOverCurrentCutoff,
        ] {
            let r = id.register().unwrap();
            assert!(r.sensor_dependent, "{id:?}");
            let (_, rev_d_max) = r.range.unwrap();
            let big = Setting {
                id,
                value: rev_d_max + 150,
            };
            // Unknown BMS limits: Rev D's range applies.
            assert!(matches!(
                big.validate_with(None),
                Err(SettingError::OutOfRange { .. })
            ));
            // The BMS allows more with its sensor: its limits win.
            assert_eq!(big.validate_with(Some((1, rev_d_max + 500))), Ok(()));
            // ... and bind in both directions.
            assert!(matches!(
                big.validate_with(Some((1, rev_d_max + 100))),
                Err(SettingError::OutsideBmsLimits { .. })
            ));
        }
        // Not sensor-dependent: both the Rev D range and the BMS limits apply.
        let ov = Setting {
            id: SettingId::OverVoltageCutoff,
            value: 5000,
        };
        assert!(matches!(
            ov.validate_with(Some((1000, 6000))),
            Err(SettingError::OutOfRange { .. })
        ));
    }

    /// Issue 26, item 2: a per-cell voltage of another chemistry (4.2 V on a
    /// LiFePO4 pack) passed Rev D's range and every relation.
    #[test]
    fn cell_voltages_are_checked_against_the_chemistry() {
        let held =
            |ov: i32| move |id: SettingId| (id == SettingId::OverVoltageCutoff).then_some(ov);
        let infer = |ov| Chemistry::infer(held(ov)).map(|(c, _, _)| c);
        assert_eq!(infer(3650), Some(Chemistry::LiFePO4));
        assert_eq!(infer(4200), Some(Chemistry::LiIon));
        assert_eq!(infer(2800), Some(Chemistry::Lto));
        // Between the windows, or unknown: no chemistry, no check.
        assert_eq!(infer(3900), None);
        assert_eq!(Chemistry::infer(|_| None), None);
        // The fully-charged voltage when the cutoff says nothing.
        let fc = |id: SettingId| match id {
            SettingId::OverVoltageCutoff => Some(3900),
            SettingId::FullyChargedVoltage => Some(4150),
            _ => None,
        };
        assert_eq!(
            Chemistry::infer(fc),
            Some((Chemistry::LiIon, SettingId::FullyChargedVoltage, 4150))
        );
        let s = |id, value| Setting { id, value };
        let lfp = Chemistry::LiFePO4;
        assert_eq!(
            check_chemistry(&s(SettingId::FullyChargedVoltage, 4200), lfp),
            Err(SettingError::OutsideChemistry {
                id: SettingId::FullyChargedVoltage,
                value: 4200,
                chemistry: lfp,
                min: 3300,
                max: 3700
            })
        );
        assert_eq!(
            check_chemistry(&s(SettingId::FullyChargedVoltage, 3650), lfp),
            Ok(())
        );
        assert!(check_chemistry(&s(SettingId::UnderVoltageCutoff, 3200), Chemistry::Lto).is_err());
        // Not a cell voltage: never the chemistry's business.
        assert_eq!(
            check_chemistry(&s(SettingId::ChargerStartupDelay, 9999), lfp),
            Ok(())
        );
        // Every window inside Rev D's range; the keys round-trip.
        for (id, windows) in CHEMISTRY_RANGES {
            let (lo, hi) = id.register().unwrap().range.unwrap();
            for (a, b) in windows {
                assert!(lo <= *a && a < b && *b <= hi, "{id:?}");
            }
        }
        for c in Chemistry::ALL {
            assert_eq!(Chemistry::from_key(c.key()), Some(c));
        }
        assert_eq!(Chemistry::from_key("LFP"), Some(lfp));
        assert_eq!(Chemistry::from_key("lead"), None);
        assert_eq!(ChemistryCheck::Off.chemistry(held(3650)), None);
        assert_eq!(
            ChemistryCheck::Given(Chemistry::Lto).chemistry(held(3650)),
            Some(Chemistry::Lto)
        );
    }

    #[test]
    fn precharge_pin_accepts_0x0a_and_the_documents_0x10() {
        for v in [0x0A, 0x10] {
            assert_eq!(
                Setting::new(SettingId::PrechargePin, v).map(|s| s.value),
                Ok(v)
            );
        }
        assert!(Setting::new(SettingId::PrechargePin, 0x0B).is_err());
    }
}
