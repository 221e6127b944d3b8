//! Command codes (Rev D §1.1) and per-command wire constants.

/// First byte of every frame, in both directions (Rev D §1.1).
pub const PREAMBLE: u8 = 0xAA;

/// NACK response code byte (Rev D §1.1.1): `AA 00 CMD ERROR CRC CRC`.
pub const NACK: u8 = 0x00;
/// ACK response code byte (Rev D §1.1.1): `AA 01 CMD CRC CRC`.
pub const ACK: u8 = 0x01;
/// Reset BMS, clear events or statistics (Rev D §1.1.8).
pub const RESET_CLEAR: u8 = 0x02;
/// Read registers block, MODBUS compatible, big-endian (Rev D §1.1.6).
pub const READ_BLOCK_MODBUS: u8 = 0x03;
/// Read registers block, native, little-endian (Rev D §1.1.2).
pub const READ_BLOCK: u8 = 0x07;
/// Read individual registers, native (Rev D §1.1.3).
pub const READ_INDIVIDUAL: u8 = 0x09;
/// Write registers block, native (Rev D §1.1.4).
pub const WRITE_BLOCK: u8 = 0x0B;
/// Write individual registers, native (Rev D §1.1.5).
pub const WRITE_INDIVIDUAL: u8 = 0x0D;
/// Write registers block, MODBUS compatible, big-endian (Rev D §1.1.7).
pub const WRITE_BLOCK_MODBUS: u8 = 0x10;
/// Read newest events (Rev D §1.1.9).
pub const READ_NEWEST_EVENTS: u8 = 0x11;
/// Read all events (Rev D §1.1.10).
pub const READ_ALL_EVENTS: u8 = 0x12;
/// Read pack voltage, register 36 (Rev D §1.1.11).
pub const READ_PACK_VOLTAGE: u8 = 0x14;
/// Read pack current, register 38 (Rev D §1.1.12).
pub const READ_PACK_CURRENT: u8 = 0x15;
/// Read max cell voltage, register 41 (Rev D §1.1.13).
pub const READ_MAX_CELL_VOLTAGE: u8 = 0x16;
/// Read min cell voltage, register 40 (Rev D §1.1.14).
pub const READ_MIN_CELL_VOLTAGE: u8 = 0x17;
/// Read online status, register 50 (Rev D §1.1.15).
pub const READ_ONLINE_STATUS: u8 = 0x18;
/// Read lifetime counter, register 32 (Rev D §1.1.16).
pub const READ_LIFETIME: u8 = 0x19;
/// Read estimated SOC, register 46 (Rev D §1.1.17).
pub const READ_SOC: u8 = 0x1A;
/// Read temperatures, registers 48, 42, 43 (Rev D §1.1.18).
pub const READ_TEMPERATURES: u8 = 0x1B;
/// Read cell voltages (Rev D §1.1.19).
pub const READ_CELL_VOLTAGES: u8 = 0x1C;
/// Read settings values: min, max, default or current (Rev D §1.1.20).
pub const READ_SETTINGS: u8 = 0x1D;
/// Read version (Rev D §1.1.21).
pub const READ_VERSION: u8 = 0x1E;
/// Read extended version (Rev D §1.1.22).
pub const READ_EXTENDED_VERSION: u8 = 0x1F;
/// Read speed, distance left and time left (Rev D §1.1.23).
pub const READ_SPEED_DISTANCE_TIME: u8 = 0x20;

/// Maximum registers in one 0x03 read (Rev D §1.1.6: "Max. 127 registers").
pub const MAX_READ_MODBUS: usize = 127;
/// Maximum registers in one 0x07 read. Rev D gives no limit; replies over 63 bytes
/// arrive as several packets, and this keeps the reassembled reply within
/// [`crate::frame::MAX_PAYLOAD`].
pub const MAX_READ_NATIVE: usize = 127;
/// Maximum addresses in one 0x09 request: its PL byte is a packet size (bits 0-5),
/// so one request packet carries at most 63 bytes, i.e. 31 addresses.
pub const MAX_READ_INDIVIDUAL: usize = 31;
/// Maximum registers in one 0x0B write: PL = 2 (address) + 2n <= 63.
pub const MAX_WRITE_NATIVE: usize = 30;
/// Maximum registers in one 0x0D write: PL = 4n <= 63.
pub const MAX_WRITE_INDIVIDUAL: usize = 15;
/// Maximum registers in one 0x10 write (Rev D §1.1.7: "Max. 100 registers").
pub const MAX_WRITE_MODBUS: usize = 100;
/// Maximum registers in one 0x1D read (Rev D §1.1.20: "Max. 100 registers").
pub const MAX_READ_SETTINGS: usize = 100;
/// First register whose values 0x1D returns (the settings block, Rev D §3.4).
pub const SETTINGS_FIRST_REGISTER: u16 = 300;
/// Writable register range (Rev D §1.1.4/§1.1.5: "valid addresses to write 0x012C to 0x018F").
pub const WRITABLE: core::ops::RangeInclusive<u16> = 300..=399;

/// Human-readable command name, for logs and the replay tool.
pub const fn name(code: u8) -> &'static str {
    match code {
        NACK => "nack",
        ACK => "ack",
        RESET_CLEAR => "reset_clear",
        READ_BLOCK_MODBUS => "read_block_modbus",
        READ_BLOCK => "read_block",
        READ_INDIVIDUAL => "read_individual",
        WRITE_BLOCK => "write_block",
        WRITE_INDIVIDUAL => "write_individual",
        WRITE_BLOCK_MODBUS => "write_block_modbus",
        READ_NEWEST_EVENTS => "read_newest_events",
        READ_ALL_EVENTS => "read_all_events",
        READ_PACK_VOLTAGE => "read_pack_voltage",
        READ_PACK_CURRENT => "read_pack_current",
        READ_MAX_CELL_VOLTAGE => "read_max_cell_voltage",
        READ_MIN_CELL_VOLTAGE => "read_min_cell_voltage",
        READ_ONLINE_STATUS => "read_online_status",
        READ_LIFETIME => "read_lifetime",
        READ_SOC => "read_soc",
        READ_TEMPERATURES => "read_temperatures",
        READ_CELL_VOLTAGES => "read_cell_voltages",
        READ_SETTINGS => "read_settings",
        READ_VERSION => "read_version",
        READ_EXTENDED_VERSION => "read_extended_version",
        READ_SPEED_DISTANCE_TIME => "read_speed_distance_time",
        _ => "unknown",
    }
}

/// Native commands whose replies may be split into several packets
/// (HARDWARE-NOTES "Framing": PL bit 7 marks a non-last packet).
pub const fn is_packetized(code: u8) -> bool {
    matches!(
        code,
        READ_BLOCK | READ_INDIVIDUAL | READ_NEWEST_EVENTS | READ_ALL_EVENTS
    )
}
