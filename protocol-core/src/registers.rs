//! The register map of Rev D chapter 3, as data.
//!
//! One table ([`REGISTERS`]) gives, for every documented register or field:
//! address, name, value type, scale to SI units, unit, access, and for settings
//! the Rev D range and the names of enumerated values. Registers 200-297 (the event
//! log, 49 slots of two registers) are described by [`lookup`] from a rule rather
//! than 98 rows. Reserved registers are known to [`lookup`] as such.

/// Maximum cells a TinyBMS s516 measures (registers 0-15).
pub const MAX_CELLS: usize = 16;

/// Live data block, Rev D §3.1.
pub const LIVE_FIRST: u16 = 0;
/// Last register of the live data block the bridge polls (speed, 54-55).
pub const LIVE_LAST: u16 = 55;
/// Statistics block, Rev D §3.2.
pub const STATS_FIRST: u16 = 100;
/// Last statistics register.
pub const STATS_LAST: u16 = 117;
/// Event log, Rev D §3.3: 49 slots of two registers.
pub const EVENTS_FIRST: u16 = 200;
/// Last event log register.
pub const EVENTS_LAST: u16 = 297;
/// Number of event slots.
pub const EVENT_SLOTS: usize = 49;
/// Settings block, Rev D §3.4.
pub const SETTINGS_FIRST: u16 = 300;
/// Last documented setting (343, Protocol).
pub const SETTINGS_LAST: u16 = 343;
/// Version block, Rev D §3.5.
pub const VERSION_FIRST: u16 = 500;
/// Last version register (serial number ends at 509).
pub const VERSION_LAST: u16 = 509;

/// How a register's bits are read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ValueType {
    /// Unsigned 16 bits.
    U16,
    /// Signed 16 bits.
    I16,
    /// Unsigned 32 bits over this and the next register, low word first.
    U32,
    /// IEEE-754 f32 over this and the next register, low word first.
    F32,
    /// Unsigned 8 bits in the field given by [`Field`].
    U8,
    /// Signed 8 bits in the field given by [`Field`].
    I8,
    /// A bitmap (names of bits in `options`, as (bit, name)).
    Bits,
    /// Part of a wider value described at another address (e.g. a 32-bit high word).
    Continuation,
    /// 96-bit serial number over registers 504-509.
    Serial,
    /// Reserved.
    Reserved,
}

/// Which bits of the 16-bit register a field occupies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Field {
    /// All 16 bits (or the whole multi-register value).
    Whole,
    /// Bits 0-7.
    LowByte,
    /// Bits 8-15.
    HighByte,
}

impl Field {
    /// Extracts the field from a raw register value.
    pub const fn get(self, raw: u16) -> u16 {
        match self {
            Field::Whole => raw,
            Field::LowByte => raw & 0x00FF,
            Field::HighByte => raw >> 8,
        }
    }
    /// Replaces the field in `raw` by `value`, keeping the other bits.
    pub const fn set(self, raw: u16, value: u16) -> u16 {
        match self {
            Field::Whole => value,
            Field::LowByte => (raw & 0xFF00) | (value & 0x00FF),
            Field::HighByte => (raw & 0x00FF) | ((value & 0x00FF) << 8),
        }
    }
    /// Largest value the field holds.
    pub const fn max(self) -> u16 {
        match self {
            Field::Whole => u16::MAX,
            _ => 0xFF,
        }
    }
}

/// Read-only or read/write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Access {
    /// R
    Read,
    /// R/W
    ReadWrite,
}

/// One register or register field of the map.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Register {
    /// Register address (the lower one for 32-bit values).
    pub address: u16,
    /// Rev D's name.
    pub name: &'static str,
    /// How to read it.
    pub value_type: ValueType,
    /// Which bits.
    pub field: Field,
    /// Multiply the raw value by this to get `unit`.
    pub scale: f32,
    /// SI unit after scaling ("" when dimensionless).
    pub unit: &'static str,
    /// Access.
    pub access: Access,
    /// Rev D range, in raw units, when it gives one.
    pub range: Option<(i32, i32)>,
    /// Named values (enumerations) or named bits (bitmaps).
    pub options: &'static [(u16, &'static str)],
    /// The BMS changes this setting's min/max with the current sensor (Rev D "*").
    pub sensor_dependent: bool,
}

const fn reg(
    address: u16,
    name: &'static str,
    value_type: ValueType,
    scale: f32,
    unit: &'static str,
) -> Register {
    Register {
        address,
        name,
        value_type,
        field: Field::Whole,
        scale,
        unit,
        access: Access::Read,
        range: None,
        options: &[],
        sensor_dependent: false,
    }
}

const fn rw(
    address: u16,
    name: &'static str,
    value_type: ValueType,
    scale: f32,
    unit: &'static str,
    lo: i32,
    hi: i32,
) -> Register {
    Register {
        access: Access::ReadWrite,
        range: Some((lo, hi)),
        ..reg(address, name, value_type, scale, unit)
    }
}

const fn with_options(
    r: Register,
    field: Field,
    options: &'static [(u16, &'static str)],
) -> Register {
    Register {
        field,
        options,
        ..r
    }
}

const fn hi(r: Register) -> Register {
    Register {
        field: Field::HighByte,
        ..r
    }
}

const fn lo(r: Register) -> Register {
    Register {
        field: Field::LowByte,
        ..r
    }
}

const fn sensor(r: Register) -> Register {
    Register {
        sensor_dependent: true,
        ..r
    }
}

const fn cont(address: u16, name: &'static str, access: Access) -> Register {
    Register {
        access,
        ..reg(address, name, ValueType::Continuation, 1.0, "")
    }
}

use ValueType::*;

const CELL_SCALE: f32 = 0.0001; // 0.1 mV -> V

/// Online status values (register 50).
pub const STATUS_OPTIONS: &[(u16, &str)] = &[
    (0x91, "Charging"),
    (0x92, "Fully Charged"),
    (0x93, "Discharging"),
    (0x96, "Regeneration"),
    (0x97, "Idle"),
    (0x9B, "Fault"),
];

/// Register 314 values.
pub const DISTANCE_UNIT_OPTIONS: &[(u16, &str)] = &[
    (0x01, "Meter"),
    (0x02, "Kilometer"),
    (0x03, "Feet"),
    (0x04, "Mile"),
    (0x05, "Yard"),
];
/// Register 329 bits.
pub const CONFIG_FLAG_BITS: &[(u16, &str)] = &[
    (0, "Invert External Current Sensor Direction"),
    (1, "Disable Load/Charger Switch Diagnostics"),
    (2, "Enable Charger Restart Level"),
];
/// Register 330 low byte.
pub const CHARGER_TYPE_OPTIONS: &[(u16, &str)] = &[
    (0x00, "Variable (Reserved)"),
    (0x01, "CC/CV"),
    (0x02, "CAN (Reserved)"),
];
/// Registers 331 and 341 low byte.
pub const SWITCH_TYPE_OPTIONS: &[(u16, &str)] = &[
    (0x00, "FET"),
    (0x01, "AIDO1"),
    (0x02, "AIDO2"),
    (0x03, "DIDO1"),
    (0x04, "DIDO2"),
    (0x05, "AIHO1 Active Low"),
    (0x06, "AIHO1 Active High"),
    (0x07, "AIHO2 Active Low"),
    (0x08, "AIHO2 Active High"),
];
/// Register 333 low byte.
pub const CHARGER_SWITCH_OPTIONS: &[(u16, &str)] = &[
    (0x01, "Charge FET"),
    (0x02, "AIDO1"),
    (0x03, "AIDO2"),
    (0x04, "DIDO1"),
    (0x05, "DIDO2"),
    (0x06, "AIHO1 Active Low"),
    (0x07, "AIHO1 Active High"),
    (0x08, "AIHO2 Active Low"),
    (0x09, "AIHO2 Active High"),
];
/// Register 334 low byte.
pub const IGNITION_OPTIONS: &[(u16, &str)] = &[
    (0x00, "Disabled"),
    (0x01, "AIDO1"),
    (0x02, "AIDO2"),
    (0x03, "DIDO1"),
    (0x04, "DIDO2"),
    (0x05, "AIHO1"),
    (0x06, "AIHO2"),
];
/// Register 335 low byte.
pub const CHARGER_DETECTION_OPTIONS: &[(u16, &str)] = &[
    (0x01, "Internal"),
    (0x02, "AIDO1"),
    (0x03, "AIDO2"),
    (0x04, "DIDO1"),
    (0x05, "DIDO2"),
    (0x06, "AIHO1"),
    (0x07, "AIHO2"),
];
/// Register 336 low byte.
pub const SPEED_SENSOR_OPTIONS: &[(u16, &str)] =
    &[(0x00, "Disabled"), (0x01, "DIDO1"), (0x02, "DIDO2")];
/// Register 337 low byte. Rev D lists 0x10 for "AIHO2 Active High", right
/// after 0x09: almost surely decimal 10 (0x0A), a slip of the document. Both are
/// accepted: 0x0A as the likely value, 0x10 as the document's.
pub const PRECHARGE_PIN_OPTIONS: &[(u16, &str)] = &[
    (0x00, "Disabled"),
    (0x02, "Discharge FET"),
    (0x03, "AIDO1"),
    (0x04, "AIDO2"),
    (0x05, "DIDO1"),
    (0x06, "DIDO2"),
    (0x07, "AIHO1 Active Low"),
    (0x08, "AIHO1 Active High"),
    (0x09, "AIHO2 Active Low"),
    (0x0A, "AIHO2 Active High"),
    (0x10, "AIHO2 Active High"),
];
/// Register 338 low byte.
pub const PRECHARGE_DURATION_OPTIONS: &[(u16, &str)] = &[
    (0x00, "0.1 s"),
    (0x01, "0.2 s"),
    (0x02, "0.5 s"),
    (0x03, "1 s"),
    (0x04, "2 s"),
    (0x05, "3 s"),
    (0x06, "4 s"),
    (0x07, "5 s"),
];
/// Register 339 low byte.
pub const TEMP_SENSOR_OPTIONS: &[(u16, &str)] =
    &[(0x00, "Dual 10K NTC"), (0x01, "Multipoint Active Sensor")];
/// Register 340 low byte.
pub const OPERATION_MODE_OPTIONS: &[(u16, &str)] = &[
    (0x00, "Dual Port Operation"),
    (0x01, "Single Port Operation"),
];
/// Register 342 low byte.
pub const BROADCAST_TIME_OPTIONS: &[(u16, &str)] = &[
    (0x00, "Disabled"),
    (0x01, "0.1 s"),
    (0x02, "0.2 s"),
    (0x03, "0.5 s"),
    (0x04, "1 s"),
    (0x05, "2 s"),
    (0x06, "5 s"),
    (0x07, "10 s"),
];
/// Register 343 low byte.
pub const PROTOCOL_OPTIONS: &[(u16, &str)] = &[(0x00, "CA V3"), (0x01, "ASCII"), (0x02, "SOC BAR")];
/// Register 114 low byte.
pub const RESET_OPTIONS: &[(u16, &str)] = &[
    (0x00, "Unknown"),
    (0x01, "Low power reset"),
    (0x02, "Window watchdog reset"),
    (0x03, "Independent watchdog reset"),
    (0x04, "Software reset"),
    (0x05, "POR/PDR reset"),
    (0x06, "PIN reset"),
    (0x07, "Options bytes loading reset"),
];
/// Register 114 high byte.
pub const WAKEUP_OPTIONS: &[(u16, &str)] = &[
    (0x00, "Charger connected"),
    (0x01, "Ignition"),
    (0x02, "Discharging detected"),
    (0x03, "UART communication detected"),
];
/// Register 501 bits: bit 0 BPT, bits 1-2 BCS (see [`crate::views::VersionInfo`]).
pub const FW_FLAG_BITS: &[(u16, &str)] = &[
    (8, "BMS Power Type (0 low, 1 high)"),
    (
        9,
        "Current Sensor (2 bits: 0 internal resistor, 1 internal HALL, 2 external)",
    ),
];

/// Every documented register and field of Rev D chapter 3 except the event slots
/// (see [`lookup`]), in address order; a register with two fields has two rows.
pub const REGISTERS: &[Register] = &[
    reg(0, "Cell 1 Voltage", U16, CELL_SCALE, "V"),
    reg(1, "Cell 2 Voltage", U16, CELL_SCALE, "V"),
    reg(2, "Cell 3 Voltage", U16, CELL_SCALE, "V"),
    reg(3, "Cell 4 Voltage", U16, CELL_SCALE, "V"),
    reg(4, "Cell 5 Voltage", U16, CELL_SCALE, "V"),
    reg(5, "Cell 6 Voltage", U16, CELL_SCALE, "V"),
    reg(6, "Cell 7 Voltage", U16, CELL_SCALE, "V"),
    reg(7, "Cell 8 Voltage", U16, CELL_SCALE, "V"),
    reg(8, "Cell 9 Voltage", U16, CELL_SCALE, "V"),
    reg(9, "Cell 10 Voltage", U16, CELL_SCALE, "V"),
    reg(10, "Cell 11 Voltage", U16, CELL_SCALE, "V"),
    reg(11, "Cell 12 Voltage", U16, CELL_SCALE, "V"),
    reg(12, "Cell 13 Voltage", U16, CELL_SCALE, "V"),
    reg(13, "Cell 14 Voltage", U16, CELL_SCALE, "V"),
    reg(14, "Cell 15 Voltage", U16, CELL_SCALE, "V"),
    reg(15, "Cell 16 Voltage", U16, CELL_SCALE, "V"),
    reg(32, "BMS Lifetime Counter", U32, 1.0, "s"),
    cont(33, "BMS Lifetime Counter (high word)", Access::Read),
    reg(34, "Estimated Time Left", U32, 1.0, "s"),
    cont(35, "Estimated Time Left (high word)", Access::Read),
    reg(36, "Battery Pack Voltage", F32, 1.0, "V"),
    cont(37, "Battery Pack Voltage (high word)", Access::Read),
    reg(38, "Battery Pack Current", F32, 1.0, "A"),
    cont(39, "Battery Pack Current (high word)", Access::Read),
    reg(40, "Minimal Cell Voltage", U16, 0.001, "V"),
    reg(41, "Maximal Cell Voltage", U16, 0.001, "V"),
    reg(42, "External Temp. Sensor #1 Temperature", I16, 0.1, "°C"),
    reg(43, "External Temp. Sensor #2 Temperature", I16, 0.1, "°C"),
    reg(44, "Distance Left To Empty Battery", U16, 1.0, "km"),
    Register {
        range: Some((0, 50000)),
        ..reg(45, "State Of Health", U16, 0.002, "%")
    },
    reg(46, "State Of Charge", U32, 0.000_001, "%"),
    cont(47, "State Of Charge (high word)", Access::Read),
    reg(48, "BMS Internal Temperature", I16, 0.1, "°C"),
    with_options(
        reg(50, "BMS Online Status", U16, 1.0, ""),
        Field::Whole,
        STATUS_OPTIONS,
    ),
    reg(51, "Balancing Decision Bits", Bits, 1.0, ""),
    reg(52, "Real Balancing Bits", Bits, 1.0, ""),
    reg(53, "Number Of Detected Cells", U16, 1.0, ""),
    reg(54, "Speed", F32, 1.0, "km/h"),
    cont(55, "Speed (high word)", Access::Read),
    reg(100, "Total Distance", U32, 0.01, "km"),
    cont(101, "Total Distance (high word)", Access::Read),
    reg(102, "Maximal Discharge Current", U16, 0.1, "A"),
    reg(103, "Maximal Charge Current", U16, 0.1, "A"),
    reg(104, "Maximal Cell Voltage Difference", U16, CELL_SCALE, "V"),
    reg(105, "Under-Voltage Protection Count", U16, 1.0, ""),
    reg(106, "Over-Voltage Protection Count", U16, 1.0, ""),
    reg(107, "Discharge Over-Current Protection Count", U16, 1.0, ""),
    reg(108, "Charge Over-Current Protection Count", U16, 1.0, ""),
    reg(109, "Over-Heat Protection Count", U16, 1.0, ""),
    reg(111, "Charging Count", U16, 1.0, ""),
    reg(112, "Full Charge Count", U16, 1.0, ""),
    lo(reg(113, "Min. Pack Temperature", I8, 1.0, "°C")),
    hi(reg(113, "Max. Pack Temperature", I8, 1.0, "°C")),
    with_options(
        reg(114, "Last BMS Reset Event", U8, 1.0, ""),
        Field::LowByte,
        RESET_OPTIONS,
    ),
    with_options(
        reg(114, "Last Wakeup From BMS Sleep Mode Event", U8, 1.0, ""),
        Field::HighByte,
        WAKEUP_OPTIONS,
    ),
    reg(116, "Statistics Last Cleared On Timestamp", U32, 1.0, "s"),
    cont(
        117,
        "Statistics Last Cleared On Timestamp (high word)",
        Access::Read,
    ),
    rw(300, "Fully Charged Voltage", U16, 0.001, "V", 1200, 4500),
    rw(301, "Fully Discharged Voltage", U16, 0.001, "V", 1000, 3500),
    rw(
        303,
        "Early Balancing Threshold",
        U16,
        0.001,
        "V",
        1000,
        4500,
    ),
    sensor(rw(
        304,
        "Charge Finished Current",
        U16,
        0.001,
        "A",
        100,
        5000,
    )),
    // Rev D gives no range for 305; the French guide gives 1-750 A, and the BMS
    // reports its own through 0x1D (HARDWARE-NOTES).
    sensor(rw(
        305,
        "Peak Discharge Current Cutoff",
        U16,
        1.0,
        "A",
        1,
        750,
    )),
    rw(306, "Battery Capacity", U16, 0.01, "Ah", 10, 65500),
    rw(307, "Number Of Series Cells", U16, 1.0, "", 4, 16),
    rw(308, "Allowed Disbalance", U16, 0.001, "V", 15, 100),
    rw(310, "Charger Startup Delay", U16, 1.0, "s", 5, 60),
    rw(311, "Charger Disable Delay", U16, 1.0, "s", 0, 60),
    rw(312, "Pulses Per Unit", U32, 1.0, "", 1, 100_000),
    cont(313, "Pulses Per Unit (high word)", Access::ReadWrite),
    with_options(
        rw(314, "Distance Unit Name", U16, 1.0, "", 1, 5),
        Field::Whole,
        DISTANCE_UNIT_OPTIONS,
    ),
    rw(315, "Over-Voltage Cutoff", U16, 0.001, "V", 1200, 4500),
    rw(316, "Under-Voltage Cutoff", U16, 0.001, "V", 800, 3500),
    sensor(rw(
        317,
        "Discharge Over-Current Cutoff",
        U16,
        1.0,
        "A",
        1,
        750,
    )),
    sensor(rw(318, "Charge Over-Current Cutoff", U16, 1.0, "A", 1, 750)),
    rw(319, "Over-Heat Cutoff", I16, 1.0, "°C", 20, 90),
    rw(
        320,
        "Low Temperature Charger Cutoff",
        I16,
        1.0,
        "°C",
        -40,
        10,
    ),
    rw(321, "Charge Restart Level", U16, 1.0, "%", 60, 95),
    rw(322, "Battery Maximum Cycles Count", U16, 1.0, "", 10, 65000),
    rw(323, "State Of Health", U16, 0.002, "%", 0, 50000),
    rw(328, "State Of Charge", U16, 0.002, "%", 0, 50000),
    with_options(
        rw(329, "Configuration Flags", Bits, 1.0, "", 0, 0b111),
        Field::Whole,
        CONFIG_FLAG_BITS,
    ),
    with_options(
        rw(330, "Charger Type", U8, 1.0, "", 0, 2),
        Field::LowByte,
        CHARGER_TYPE_OPTIONS,
    ),
    hi(rw(
        330,
        "Discharge Over-Current Cutoff Timeout",
        U8,
        1.0,
        "s",
        0,
        30,
    )),
    with_options(
        rw(331, "Load Switch Type", U8, 1.0, "", 0, 8),
        Field::LowByte,
        SWITCH_TYPE_OPTIONS,
    ),
    lo(rw(332, "Automatic Recovery", U8, 1.0, "s", 1, 30)),
    with_options(
        rw(333, "Charger Switch Type", U8, 1.0, "", 1, 9),
        Field::LowByte,
        CHARGER_SWITCH_OPTIONS,
    ),
    with_options(
        rw(334, "Ignition", U8, 1.0, "", 0, 6),
        Field::LowByte,
        IGNITION_OPTIONS,
    ),
    with_options(
        rw(335, "Charger Detection", U8, 1.0, "", 1, 7),
        Field::LowByte,
        CHARGER_DETECTION_OPTIONS,
    ),
    with_options(
        rw(336, "Speed Sensor Input", U8, 1.0, "", 0, 2),
        Field::LowByte,
        SPEED_SENSOR_OPTIONS,
    ),
    with_options(
        rw(337, "Precharge Pin", U8, 1.0, "", 0, 0x10),
        Field::LowByte,
        PRECHARGE_PIN_OPTIONS,
    ),
    with_options(
        rw(338, "Precharge Duration", U8, 1.0, "", 0, 7),
        Field::LowByte,
        PRECHARGE_DURATION_OPTIONS,
    ),
    with_options(
        rw(339, "Temperature Sensor Type", U8, 1.0, "", 0, 1),
        Field::LowByte,
        TEMP_SENSOR_OPTIONS,
    ),
    with_options(
        rw(340, "BMS Operation Mode", U8, 1.0, "", 0, 1),
        Field::LowByte,
        OPERATION_MODE_OPTIONS,
    ),
    with_options(
        rw(341, "Single Port Switch Type", U8, 1.0, "", 0, 8),
        Field::LowByte,
        SWITCH_TYPE_OPTIONS,
    ),
    with_options(
        rw(342, "Broadcast Time", U8, 1.0, "", 0, 7),
        Field::LowByte,
        BROADCAST_TIME_OPTIONS,
    ),
    with_options(
        rw(343, "Protocol", U8, 1.0, "", 0, 2),
        Field::LowByte,
        PROTOCOL_OPTIONS,
    ),
    lo(reg(500, "Hardware Version", U8, 1.0, "")),
    hi(reg(500, "Hardware Changes Version", U8, 1.0, "")),
    lo(reg(501, "Public Release Firmware Version", U8, 1.0, "")),
    with_options(
        reg(501, "BPT / BCS flags", Bits, 1.0, ""),
        Field::HighByte,
        FW_FLAG_BITS,
    ),
    reg(502, "Internal Firmware Version", U16, 1.0, ""),
    lo(reg(503, "Bootloader Version", U8, 1.0, "")),
    hi(reg(503, "Profile Version", U8, 1.0, "")),
    reg(504, "Product Serial Number", Serial, 1.0, ""),
    cont(505, "Product Serial Number (continued)", Access::Read),
    cont(506, "Product Serial Number (continued)", Access::Read),
    cont(507, "Product Serial Number (continued)", Access::Read),
    cont(508, "Product Serial Number (continued)", Access::Read),
    cont(509, "Product Serial Number (continued)", Access::Read),
];

/// True when `address` carries the rest of a value that starts at a lower
/// address: the high word of a 32-bit value, a later register of the serial
/// number, the second register of an event slot. A read that splits a value
/// must not end just before such an address.
pub fn is_continuation(address: u16) -> bool {
    if (EVENTS_FIRST..=EVENTS_LAST).contains(&address) {
        // Event slots are two registers, from 200.
        return (address - EVENTS_FIRST) % 2 == 1;
    }
    // The rows of [`lookup`] that are continuations are the table's: a row built
    // by rule never is.
    CONTINUATIONS.contains(&address)
}

/// The addresses of [`REGISTERS`]' continuation rows, taken from the table at
/// compile time: [`is_continuation`] then needs a few bytes instead of the
/// whole table with its names (5 KB of flash on the chip).
const CONTINUATIONS: [u16; count_continuations()] = continuation_addresses();

const fn count_continuations() -> usize {
    let mut n = 0;
    let mut rest = REGISTERS;
    while let [r, tail @ ..] = rest {
        if matches!(r.value_type, ValueType::Continuation) {
            n += 1;
        }
        rest = tail;
    }
    n
}

// Evaluated at compile time only: an index out of bounds would fail the build.
#[allow(clippy::indexing_slicing)]
const fn continuation_addresses<const N: usize>() -> [u16; N] {
    let mut out = [0; N];
    let mut n = 0;
    let mut rest = REGISTERS;
    while let [r, tail @ ..] = rest {
        if matches!(r.value_type, ValueType::Continuation) {
            out[n] = r.address;
            n += 1;
        }
        rest = tail;
    }
    out
}

/// The table rows for `address` (one or two fields), or an event slot / reserved
/// description built by rule. Returns at most two rows.
pub fn lookup(address: u16) -> heapless::Vec<Register, 2> {
    let mut out = heapless::Vec::new();
    for r in REGISTERS.iter().filter(|r| r.address == address) {
        if out.push(*r).is_err() {
            break;
        }
    }
    if out.is_empty() {
        let r = if (EVENTS_FIRST..=EVENTS_LAST).contains(&address) {
            if (address - EVENTS_FIRST).is_multiple_of(2) {
                reg(address, "Event Timestamp (low 16 bits)", U16, 1.0, "s")
            } else {
                reg(
                    address,
                    "Event Timestamp (high 8 bits) / Event Message ID",
                    U16,
                    1.0,
                    "",
                )
            }
        } else if (SETTINGS_FIRST..=399).contains(&address) {
            Register {
                access: Access::ReadWrite,
                ..reg(address, "Reserved", Reserved, 1.0, "")
            }
        } else {
            reg(address, "Reserved", Reserved, 1.0, "")
        };
        let _one_row_always_fits = out.push(r);
    }
    out
}

/// The row named `name` (exact, case-sensitive), if any.
pub fn by_name(name: &str) -> Option<&'static Register> {
    REGISTERS.iter().find(|r| r.name == name)
}

/// Name of an enumerated value of a register row.
pub fn option_name(r: &Register, value: u16) -> Option<&'static str> {
    r.options.iter().find(|(v, _)| *v == value).map(|(_, n)| *n)
}

/// Assembles a 32-bit value from two registers, low word at the lower address
/// (HARDWARE-NOTES "Values"), whatever the byte order each word travelled in.
pub const fn u32_from_words(low: u16, high: u16) -> u32 {
    ((high as u32) << 16) | low as u32
}

/// Same as [`u32_from_words`], reinterpreted as an IEEE-754 f32.
pub fn f32_from_words(low: u16, high: u16) -> f32 {
    f32::from_bits(u32_from_words(low, high))
}

/// Splits a 32-bit value into (low word, high word).
pub const fn words_from_u32(v: u32) -> (u16, u16) {
    (v as u16, (v >> 16) as u16)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_is_sorted_and_complete() {
        for w in REGISTERS.windows(2) {
            assert!(
                w[0].address <= w[1].address,
                "{} then {}",
                w[0].address,
                w[1].address
            );
        }
        // Live 0-15 cells, 32-55 documented; settings 300-343 minus reserved 302, 309, 324-327.
        let settings: usize = REGISTERS
            .iter()
            .filter(|r| (300..=343).contains(&r.address))
            .count();
        assert_eq!(settings, 44 - 6 + 1); // +1: register 330 has two fields
        for a in 0..=15 {
            assert_eq!(lookup(a)[0].name, REGISTERS[a as usize].name);
        }
        for a in [302, 309, 324, 325, 326, 327] {
            assert_eq!(lookup(a)[0].value_type, Reserved);
        }
        assert_eq!(lookup(330).len(), 2);
        assert_eq!(
            lookup(201)[0].name,
            "Event Timestamp (high 8 bits) / Event Message ID"
        );
        assert_eq!(lookup(1000)[0].value_type, Reserved);
    }

    #[test]
    fn rev_d_chapter_3_spot_checks() {
        let r = by_name("Over-Voltage Cutoff").unwrap();
        assert_eq!(
            (r.address, r.range, r.access),
            (315, Some((1200, 4500)), Access::ReadWrite)
        );
        let r = by_name("Low Temperature Charger Cutoff").unwrap();
        assert_eq!(r.range, Some((-40, 10)));
        let r = by_name("Discharge Over-Current Cutoff Timeout").unwrap();
        assert_eq!(
            (r.address, r.field, r.range),
            (330, Field::HighByte, Some((0, 30)))
        );
        assert!(
            by_name("Charge Over-Current Cutoff")
                .unwrap()
                .sensor_dependent
        );
        assert_eq!(option_name(by_name("Protocol").unwrap(), 1), Some("ASCII"));
        assert_eq!(
            option_name(by_name("Precharge Pin").unwrap(), 0x10),
            Some("AIHO2 Active High")
        );
        assert_eq!(by_name("Cell 1 Voltage").unwrap().scale, 0.0001);
        for r in REGISTERS {
            let writable = crate::command::WRITABLE.contains(&r.address);
            assert_eq!(writable, r.access == Access::ReadWrite, "{}", r.name);
        }
    }

    #[test]
    fn words_low_first() {
        // HARDWARE-NOTES: registers 36/37 = 0x1EB8, 0x425F is 55.78 V.
        let v = f32_from_words(0x1EB8, 0x425F);
        assert!((v - 55.78).abs() < 0.005, "{v}");
        assert_eq!(words_from_u32(0x425F_1EB8), (0x1EB8, 0x425F));
    }

    #[test]
    fn field_set_preserves_other_byte() {
        assert_eq!(Field::LowByte.set(0x1E05, 0x01), 0x1E01);
        assert_eq!(Field::HighByte.set(0x1E05, 0x0A), 0x0A05);
    }
}
