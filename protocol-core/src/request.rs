//! Requests to the BMS (Rev D chapter 1): typed values, validated, encoded
//! byte-exactly, and parsed back (for the simulator and the replay tool).
//!
//! A request that cannot be valid is refused with a [`RequestError`] before any
//! byte is produced: too many registers, an empty list, a write outside the
//! writable range 300-399, an address range past 0xFFFF.

use crate::command::{self as cmd, PREAMBLE};
use crate::crc::crc16;

/// Longest request: a 100-register 0x10 write (7 + 200 + 2 bytes).
pub const MAX_REQUEST_LEN: usize = 7 + 2 * cmd::MAX_WRITE_MODBUS + 2;

/// An encoded request.
pub type RequestBytes = heapless::Vec<u8, MAX_REQUEST_LEN>;

/// Option byte of command 0x02 (Rev D §1.1.8).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ResetOption {
    /// 0x01: clear the event log.
    ClearEvents,
    /// 0x02: clear the statistics.
    ClearStatistics,
    /// 0x05: restart the BMS (its ACK may never come, HARDWARE-NOTES).
    ResetBms,
}

impl ResetOption {
    /// Wire value.
    pub const fn to_u8(self) -> u8 {
        match self {
            Self::ClearEvents => 0x01,
            Self::ClearStatistics => 0x02,
            Self::ResetBms => 0x05,
        }
    }
    /// From the wire value.
    pub const fn from_u8(v: u8) -> Option<Self> {
        match v {
            0x01 => Some(Self::ClearEvents),
            0x02 => Some(Self::ClearStatistics),
            0x05 => Some(Self::ResetBms),
            _ => None,
        }
    }
}

/// Option byte of command 0x1D (Rev D §1.1.20).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SettingsOption {
    /// 0x01: minimum allowed values.
    Min,
    /// 0x02: maximum allowed values.
    Max,
    /// 0x03: factory defaults.
    Default,
    /// 0x04: current values.
    Current,
}

impl SettingsOption {
    /// Wire value.
    pub const fn to_u8(self) -> u8 {
        match self {
            Self::Min => 0x01,
            Self::Max => 0x02,
            Self::Default => 0x03,
            Self::Current => 0x04,
        }
    }
    /// From the wire value.
    pub const fn from_u8(v: u8) -> Option<Self> {
        match v {
            0x01 => Some(Self::Min),
            0x02 => Some(Self::Max),
            0x03 => Some(Self::Default),
            0x04 => Some(Self::Current),
            _ => None,
        }
    }
    /// Lower-case name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Min => "min",
            Self::Max => "max",
            Self::Default => "default",
            Self::Current => "current",
        }
    }
}

/// Addresses of a 0x09 read.
pub type AddressList = heapless::Vec<u16, { cmd::MAX_READ_INDIVIDUAL }>;
/// Values of a 0x10 write.
pub type BlockValues = heapless::Vec<u16, { cmd::MAX_WRITE_MODBUS }>;
/// Values of a 0x0B write.
pub type NativeBlockValues = heapless::Vec<u16, { cmd::MAX_WRITE_NATIVE }>;
/// (address, value) pairs of a 0x0D write.
pub type WritePairs = heapless::Vec<(u16, u16), { cmd::MAX_WRITE_INDIVIDUAL }>;

/// Every request of Rev D chapter 1.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Request {
    /// 0x02: reset the BMS, clear events or statistics.
    ResetClear(ResetOption),
    /// 0x03: read `count` registers from `start`, MODBUS compatible (big-endian).
    ReadRegisters {
        /// First register.
        start: u16,
        /// 1..=127.
        count: u8,
    },
    /// 0x07: read `count` registers from `start`, native (little-endian).
    ReadRegistersNative {
        /// First register.
        start: u16,
        /// 1..=127 (replies over 63 bytes arrive in several packets).
        count: u8,
    },
    /// 0x09: read individual registers.
    ReadIndividual(AddressList),
    /// 0x0B: write a block of registers, native.
    WriteRegistersNative {
        /// First register (300..=399).
        start: u16,
        /// 1..=30 values.
        values: NativeBlockValues,
    },
    /// 0x0D: write individual registers, native.
    WriteIndividual(WritePairs),
    /// 0x10: write a block of registers, MODBUS compatible.
    WriteRegisters {
        /// First register (300..=399).
        start: u16,
        /// 1..=100 values.
        values: BlockValues,
    },
    /// 0x11
    ReadNewestEvents,
    /// 0x12
    ReadAllEvents,
    /// 0x14
    ReadPackVoltage,
    /// 0x15
    ReadPackCurrent,
    /// 0x16
    ReadMaxCellVoltage,
    /// 0x17
    ReadMinCellVoltage,
    /// 0x18
    ReadOnlineStatus,
    /// 0x19
    ReadLifetime,
    /// 0x1A
    ReadSoc,
    /// 0x1B
    ReadTemperatures,
    /// 0x1C
    ReadCellVoltages,
    /// 0x1D: settings values from register 300 on.
    ReadSettings {
        /// Which values.
        option: SettingsOption,
        /// 1..=100 registers.
        count: u8,
    },
    /// 0x1E
    ReadVersion,
    /// 0x1F
    ReadExtendedVersion,
    /// 0x20
    ReadSpeedDistanceTime,
}

/// Why a request was refused (before any byte) or could not be parsed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum RequestError {
    /// No register given.
    Empty,
    /// More registers than the command allows.
    TooMany {
        /// Registers asked for.
        count: usize,
        /// The command's maximum.
        max: usize,
    },
    /// A write outside 300..=399 (Rev D §1.1.4).
    NotWritable {
        /// The offending address.
        address: u16,
    },
    /// `start + count` runs past register 0xFFFF.
    AddressOverflow,
    /// The output buffer is too small.
    BufferTooSmall {
        /// Bytes needed.
        need: usize,
    },
    /// Parsing: fewer bytes than the layout needs.
    Truncated,
    /// Parsing: more bytes than the layout has.
    TrailingBytes,
    /// Parsing: the first byte is not 0xAA.
    NoPreamble,
    /// Parsing: the CRC does not match.
    Crc {
        /// Computed over the bytes.
        computed: u16,
        /// Carried by the frame.
        received: u16,
    },
    /// Parsing: no such command.
    UnknownCommand(u8),
    /// Parsing: a PL/RL/option byte inconsistent with the rest.
    Malformed,
}

impl RequestError {
    /// Short snake_case reason.
    pub const fn reason(&self) -> &'static str {
        match self {
            Self::Empty => "empty",
            Self::TooMany { .. } => "too_many_registers",
            Self::NotWritable { .. } => "not_writable",
            Self::AddressOverflow => "address_overflow",
            Self::BufferTooSmall { .. } => "buffer_too_small",
            Self::Truncated => "truncated",
            Self::TrailingBytes => "trailing_bytes",
            Self::NoPreamble => "no_preamble",
            Self::Crc { .. } => "crc_mismatch",
            Self::UnknownCommand(_) => "unknown_command",
            Self::Malformed => "malformed",
        }
    }
}

fn check_count(count: usize, max: usize) -> Result<(), RequestError> {
    if count == 0 {
        Err(RequestError::Empty)
    } else if count > max {
        Err(RequestError::TooMany { count, max })
    } else {
        Ok(())
    }
}

fn check_span(start: u16, count: usize) -> Result<(), RequestError> {
    if start as usize + count > 0x1_0000 {
        Err(RequestError::AddressOverflow)
    } else {
        Ok(())
    }
}

fn check_writable_span(start: u16, count: usize) -> Result<(), RequestError> {
    check_span(start, count)?;
    let last = start as usize + count - 1;
    for a in [start as usize, last] {
        let a = a as u16;
        if !cmd::WRITABLE.contains(&a) {
            return Err(RequestError::NotWritable { address: a });
        }
    }
    Ok(())
}

impl Request {
    /// 0x03 read, validated.
    pub fn read_registers(start: u16, count: usize) -> Result<Self, RequestError> {
        check_count(count, cmd::MAX_READ_MODBUS)?;
        check_span(start, count)?;
        Ok(Self::ReadRegisters {
            start,
            count: count as u8,
        })
    }
    /// 0x07 read, validated.
    pub fn read_registers_native(start: u16, count: usize) -> Result<Self, RequestError> {
        check_count(count, cmd::MAX_READ_NATIVE)?;
        check_span(start, count)?;
        Ok(Self::ReadRegistersNative {
            start,
            count: count as u8,
        })
    }
    /// 0x09 read, validated.
    pub fn read_individual(addresses: &[u16]) -> Result<Self, RequestError> {
        check_count(addresses.len(), cmd::MAX_READ_INDIVIDUAL)?;
        Ok(Self::ReadIndividual(
            AddressList::from_slice(addresses).map_err(|_| RequestError::TooMany {
                count: addresses.len(),
                max: cmd::MAX_READ_INDIVIDUAL,
            })?,
        ))
    }
    /// 0x10 write, validated.
    pub fn write_registers(start: u16, values: &[u16]) -> Result<Self, RequestError> {
        check_count(values.len(), cmd::MAX_WRITE_MODBUS)?;
        check_writable_span(start, values.len())?;
        Ok(Self::WriteRegisters {
            start,
            values: BlockValues::from_slice(values).map_err(|_| RequestError::TooMany {
                count: values.len(),
                max: cmd::MAX_WRITE_MODBUS,
            })?,
        })
    }
    /// 0x0B write, validated.
    pub fn write_registers_native(start: u16, values: &[u16]) -> Result<Self, RequestError> {
        check_count(values.len(), cmd::MAX_WRITE_NATIVE)?;
        check_writable_span(start, values.len())?;
        Ok(Self::WriteRegistersNative {
            start,
            values: NativeBlockValues::from_slice(values).map_err(|_| RequestError::TooMany {
                count: values.len(),
                max: cmd::MAX_WRITE_NATIVE,
            })?,
        })
    }
    /// 0x0D write, validated.
    pub fn write_individual(pairs: &[(u16, u16)]) -> Result<Self, RequestError> {
        check_count(pairs.len(), cmd::MAX_WRITE_INDIVIDUAL)?;
        for &(a, _) in pairs {
            check_writable_span(a, 1)?;
        }
        Ok(Self::WriteIndividual(
            WritePairs::from_slice(pairs).map_err(|_| RequestError::TooMany {
                count: pairs.len(),
                max: cmd::MAX_WRITE_INDIVIDUAL,
            })?,
        ))
    }
    /// 0x1D read, validated.
    pub fn read_settings(option: SettingsOption, count: usize) -> Result<Self, RequestError> {
        check_count(count, cmd::MAX_READ_SETTINGS)?;
        Ok(Self::ReadSettings {
            option,
            count: count as u8,
        })
    }

    /// The command code.
    pub const fn command(&self) -> u8 {
        match self {
            Self::ResetClear(_) => cmd::RESET_CLEAR,
            Self::ReadRegisters { .. } => cmd::READ_BLOCK_MODBUS,
            Self::ReadRegistersNative { .. } => cmd::READ_BLOCK,
            Self::ReadIndividual(_) => cmd::READ_INDIVIDUAL,
            Self::WriteRegistersNative { .. } => cmd::WRITE_BLOCK,
            Self::WriteIndividual(_) => cmd::WRITE_INDIVIDUAL,
            Self::WriteRegisters { .. } => cmd::WRITE_BLOCK_MODBUS,
            Self::ReadNewestEvents => cmd::READ_NEWEST_EVENTS,
            Self::ReadAllEvents => cmd::READ_ALL_EVENTS,
            Self::ReadPackVoltage => cmd::READ_PACK_VOLTAGE,
            Self::ReadPackCurrent => cmd::READ_PACK_CURRENT,
            Self::ReadMaxCellVoltage => cmd::READ_MAX_CELL_VOLTAGE,
            Self::ReadMinCellVoltage => cmd::READ_MIN_CELL_VOLTAGE,
            Self::ReadOnlineStatus => cmd::READ_ONLINE_STATUS,
            Self::ReadLifetime => cmd::READ_LIFETIME,
            Self::ReadSoc => cmd::READ_SOC,
            Self::ReadTemperatures => cmd::READ_TEMPERATURES,
            Self::ReadCellVoltages => cmd::READ_CELL_VOLTAGES,
            Self::ReadSettings { .. } => cmd::READ_SETTINGS,
            Self::ReadVersion => cmd::READ_VERSION,
            Self::ReadExtendedVersion => cmd::READ_EXTENDED_VERSION,
            Self::ReadSpeedDistanceTime => cmd::READ_SPEED_DISTANCE_TIME,
        }
    }

    /// True for requests answered by ACK/NACK only (0x02, 0x0B, 0x0D).
    pub const fn expects_ack(&self) -> bool {
        matches!(
            self,
            Self::ResetClear(_) | Self::WriteRegistersNative { .. } | Self::WriteIndividual(_)
        )
    }

    /// True for the writes (0x0B, 0x0D, 0x10).
    pub const fn is_write(&self) -> bool {
        matches!(
            self,
            Self::WriteRegistersNative { .. }
                | Self::WriteIndividual(_)
                | Self::WriteRegisters { .. }
        )
    }

    /// Checks every limit of Rev D chapter 1 (also for values built directly).
    pub fn validate(&self) -> Result<(), RequestError> {
        match self {
            Self::ReadRegisters { start, count } => {
                check_count(*count as usize, cmd::MAX_READ_MODBUS)?;
                check_span(*start, *count as usize)
            }
            Self::ReadRegistersNative { start, count } => {
                check_count(*count as usize, cmd::MAX_READ_NATIVE)?;
                check_span(*start, *count as usize)
            }
            Self::ReadIndividual(a) => check_count(a.len(), cmd::MAX_READ_INDIVIDUAL),
            Self::WriteRegistersNative { start, values } => {
                check_count(values.len(), cmd::MAX_WRITE_NATIVE)?;
                check_writable_span(*start, values.len())
            }
            Self::WriteIndividual(p) => {
                check_count(p.len(), cmd::MAX_WRITE_INDIVIDUAL)?;
                p.iter().try_for_each(|&(a, _)| check_writable_span(a, 1))
            }
            Self::WriteRegisters { start, values } => {
                check_count(values.len(), cmd::MAX_WRITE_MODBUS)?;
                check_writable_span(*start, values.len())
            }
            Self::ReadSettings { count, .. } => {
                check_count(*count as usize, cmd::MAX_READ_SETTINGS)
            }
            _ => Ok(()),
        }
    }

    /// Bytes the encoded request takes.
    pub fn encoded_len(&self) -> usize {
        2 + match self {
            Self::ResetClear(_) => 3,
            Self::ReadRegisters { .. } => 6,
            Self::ReadRegistersNative { .. } => 5,
            Self::ReadIndividual(a) => 3 + 2 * a.len(),
            Self::WriteRegistersNative { values, .. } => 5 + 2 * values.len(),
            Self::WriteIndividual(p) => 3 + 4 * p.len(),
            Self::WriteRegisters { values, .. } => 7 + 2 * values.len(),
            Self::ReadSettings { .. } => 5,
            _ => 2,
        }
    }

    /// Encodes into `out` (validated first); returns the number of bytes written.
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, RequestError> {
        self.validate()?;
        let mut v = RequestBytes::new();
        self.encode_into(&mut v)?;
        let dst = out
            .get_mut(..v.len())
            .ok_or(RequestError::BufferTooSmall { need: v.len() })?;
        dst.copy_from_slice(&v);
        Ok(v.len())
    }

    /// Encodes into a [`RequestBytes`] (validated first).
    pub fn to_bytes(&self) -> Result<RequestBytes, RequestError> {
        self.validate()?;
        let mut v = RequestBytes::new();
        self.encode_into(&mut v)?;
        Ok(v)
    }

    /// Encodes into `out` in place (validated first; `out` is cleared first).
    /// On an error `out` holds no valid request.
    pub fn encode_to(&self, out: &mut RequestBytes) -> Result<(), RequestError> {
        out.clear();
        self.validate()?;
        self.encode_into(out)
    }

    fn encode_into(&self, v: &mut RequestBytes) -> Result<(), RequestError> {
        let overflow = RequestError::BufferTooSmall {
            need: self.encoded_len(),
        };
        {
            let mut put = |bytes: &[u8]| v.extend_from_slice(bytes).map_err(|_| overflow);
            put(&[PREAMBLE, self.command()])?;
            match self {
                Self::ResetClear(o) => put(&[o.to_u8()])?,
                Self::ReadRegisters { start, count } => {
                    put(&start.to_be_bytes())?;
                    put(&[0x00, *count])?;
                }
                Self::ReadRegistersNative { start, count } => {
                    put(&[*count])?;
                    put(&start.to_le_bytes())?;
                }
                Self::ReadIndividual(a) => {
                    put(&[(2 * a.len()) as u8])?;
                    for addr in a {
                        put(&addr.to_le_bytes())?;
                    }
                }
                Self::WriteRegistersNative { start, values } => {
                    // PL = 2 + 2n: address included (HARDWARE-NOTES; unconfirmed on hardware).
                    put(&[(2 + 2 * values.len()) as u8])?;
                    put(&start.to_le_bytes())?;
                    for x in values {
                        put(&x.to_le_bytes())?;
                    }
                }
                Self::WriteIndividual(p) => {
                    put(&[(4 * p.len()) as u8])?;
                    for (a, x) in p {
                        put(&a.to_le_bytes())?;
                        put(&x.to_le_bytes())?;
                    }
                }
                Self::WriteRegisters { start, values } => {
                    put(&start.to_be_bytes())?;
                    put(&[0x00, values.len() as u8, (2 * values.len()) as u8])?;
                    for x in values {
                        put(&x.to_be_bytes())?;
                    }
                }
                Self::ReadSettings { option, count } => put(&[option.to_u8(), 0x00, *count])?,
                _ => {}
            }
        }
        let crc = crc16(v);
        v.extend_from_slice(&crc.to_le_bytes())
            .map_err(|_| overflow)
    }

    /// Length of the request frame at the start of `bytes`, once enough bytes are
    /// there to tell: `Ok(None)` means "need more".
    pub fn frame_len(bytes: &[u8]) -> Result<Option<usize>, RequestError> {
        match bytes.first() {
            None => return Ok(None),
            Some(&PREAMBLE) => {}
            Some(_) => return Err(RequestError::NoPreamble),
        }
        let Some(&c) = bytes.get(1) else {
            return Ok(None);
        };
        let pl_based = |extra: usize| Ok(bytes.get(2).map(|&pl| pl as usize + extra));
        match c {
            cmd::RESET_CLEAR => Ok(Some(5)),
            cmd::READ_BLOCK_MODBUS => Ok(Some(8)),
            cmd::READ_BLOCK => Ok(Some(7)),
            cmd::READ_INDIVIDUAL | cmd::WRITE_INDIVIDUAL | cmd::WRITE_BLOCK => pl_based(5),
            cmd::WRITE_BLOCK_MODBUS => Ok(bytes.get(6).map(|&pl| pl as usize + 9)),
            cmd::READ_SETTINGS => Ok(Some(7)),
            cmd::READ_NEWEST_EVENTS..=cmd::READ_SPEED_DISTANCE_TIME if c != 0x13 => Ok(Some(4)),
            other => Err(RequestError::UnknownCommand(other)),
        }
    }

    /// Parses one complete request frame (exactly `bytes`), checking its CRC and
    /// layout. Limits are checked too: what parses, encodes back to the same bytes.
    pub fn parse(bytes: &[u8]) -> Result<Self, RequestError> {
        let len = Self::frame_len(bytes)?.ok_or(RequestError::Truncated)?;
        if bytes.len() < len {
            return Err(RequestError::Truncated);
        }
        if bytes.len() > len {
            return Err(RequestError::TrailingBytes);
        }
        let (body, crc) = bytes
            .split_last_chunk::<2>()
            .ok_or(RequestError::Truncated)?;
        let computed = crc16(body);
        let received = u16::from_le_bytes(*crc);
        if computed != received {
            return Err(RequestError::Crc { computed, received });
        }
        let c = body.get(1).copied().unwrap_or(0);
        let p = Payload(body.get(2..).unwrap_or(&[]));
        let (le, be, byte) = (|i| p.le(i), |i| p.be(i), |i| p.byte(i));
        let req = match c {
            cmd::RESET_CLEAR => {
                Self::ResetClear(ResetOption::from_u8(byte(0)).ok_or(RequestError::Malformed)?)
            }
            cmd::READ_BLOCK_MODBUS => {
                if byte(2) != 0 {
                    return Err(RequestError::Malformed);
                }
                Self::ReadRegisters {
                    start: be(0),
                    count: byte(3),
                }
            }
            cmd::READ_BLOCK => Self::ReadRegistersNative {
                count: byte(0),
                start: le(1),
            },
            cmd::READ_INDIVIDUAL => {
                let pl = byte(0) as usize;
                if !pl.is_multiple_of(2) {
                    return Err(RequestError::Malformed);
                }
                let mut a = AddressList::new();
                for i in 0..pl / 2 {
                    a.push(le(1 + 2 * i)).map_err(|_| RequestError::TooMany {
                        count: pl / 2,
                        max: cmd::MAX_READ_INDIVIDUAL,
                    })?;
                }
                Self::ReadIndividual(a)
            }
            cmd::WRITE_BLOCK | cmd::WRITE_INDIVIDUAL | cmd::WRITE_BLOCK_MODBUS => {
                Self::parse_write(c, p)?
            }
            cmd::READ_SETTINGS => {
                if byte(1) != 0 {
                    return Err(RequestError::Malformed);
                }
                Self::ReadSettings {
                    option: SettingsOption::from_u8(byte(0)).ok_or(RequestError::Malformed)?,
                    count: byte(2),
                }
            }
            cmd::READ_NEWEST_EVENTS => Self::ReadNewestEvents,
            cmd::READ_ALL_EVENTS => Self::ReadAllEvents,
            cmd::READ_PACK_VOLTAGE => Self::ReadPackVoltage,
            cmd::READ_PACK_CURRENT => Self::ReadPackCurrent,
            cmd::READ_MAX_CELL_VOLTAGE => Self::ReadMaxCellVoltage,
            cmd::READ_MIN_CELL_VOLTAGE => Self::ReadMinCellVoltage,
            cmd::READ_ONLINE_STATUS => Self::ReadOnlineStatus,
            cmd::READ_LIFETIME => Self::ReadLifetime,
            cmd::READ_SOC => Self::ReadSoc,
            cmd::READ_TEMPERATURES => Self::ReadTemperatures,
            cmd::READ_CELL_VOLTAGES => Self::ReadCellVoltages,
            cmd::READ_VERSION => Self::ReadVersion,
            cmd::READ_EXTENDED_VERSION => Self::ReadExtendedVersion,
            cmd::READ_SPEED_DISTANCE_TIME => Self::ReadSpeedDistanceTime,
            other => return Err(RequestError::UnknownCommand(other)),
        };
        req.validate()?;
        Ok(req)
    }

    /// The body of a write request (0x0D, 0x0E, 0x10).
    fn parse_write(c: u8, p: Payload<'_>) -> Result<Self, RequestError> {
        let (le, be, byte) = (|i| p.le(i), |i| p.be(i), |i| p.byte(i));
        Ok(match c {
            cmd::WRITE_BLOCK => {
                let pl = byte(0) as usize;
                if pl < 2 || !pl.is_multiple_of(2) {
                    return Err(RequestError::Malformed);
                }
                let mut values = NativeBlockValues::new();
                for i in 0..(pl - 2) / 2 {
                    values
                        .push(le(3 + 2 * i))
                        .map_err(|_| RequestError::TooMany {
                            count: (pl - 2) / 2,
                            max: cmd::MAX_WRITE_NATIVE,
                        })?;
                }
                Self::WriteRegistersNative {
                    start: le(1),
                    values,
                }
            }
            cmd::WRITE_INDIVIDUAL => {
                let pl = byte(0) as usize;
                if !pl.is_multiple_of(4) {
                    return Err(RequestError::Malformed);
                }
                let mut pairs = WritePairs::new();
                for i in 0..pl / 4 {
                    pairs.push((le(1 + 4 * i), le(3 + 4 * i))).map_err(|_| {
                        RequestError::TooMany {
                            count: pl / 4,
                            max: cmd::MAX_WRITE_INDIVIDUAL,
                        }
                    })?;
                }
                Self::WriteIndividual(pairs)
            }
            cmd::WRITE_BLOCK_MODBUS => {
                let rl = byte(3) as usize;
                if byte(2) != 0 || byte(4) as usize != 2 * rl {
                    return Err(RequestError::Malformed);
                }
                let mut values = BlockValues::new();
                for i in 0..rl {
                    values
                        .push(be(5 + 2 * i))
                        .map_err(|_| RequestError::TooMany {
                            count: rl,
                            max: cmd::MAX_WRITE_MODBUS,
                        })?;
                }
                Self::WriteRegisters {
                    start: be(0),
                    values,
                }
            }
            other => return Err(RequestError::UnknownCommand(other)),
        })
    }
}

/// A request's bytes after its address and command; a byte past the end
/// reads as 0 (the layout checks reject such a request).
#[derive(Clone, Copy)]
struct Payload<'a>(&'a [u8]);

impl Payload<'_> {
    fn byte(self, i: usize) -> u8 {
        self.0.get(i).copied().unwrap_or(0)
    }

    fn le(self, i: usize) -> u16 {
        u16::from_le_bytes([self.byte(i), self.byte(i + 1)])
    }

    fn be(self, i: usize) -> u16 {
        u16::from_be_bytes([self.byte(i), self.byte(i + 1)])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bytes(r: &Request) -> heapless::Vec<u8, MAX_REQUEST_LEN> {
        r.to_bytes().unwrap()
    }

    #[test]
    fn rev_d_1_3_1_modbus_write() {
        let r = Request::write_registers(315, &[4200, 2500]).unwrap();
        assert_eq!(
            bytes(&r).as_slice(),
            &[0xAA, 0x10, 0x01, 0x3B, 0x00, 0x02, 0x04, 0x10, 0x68, 0x09, 0xC4, 0x19, 0x61]
        );
        assert_eq!(Request::parse(&bytes(&r)).unwrap(), r);
    }

    #[test]
    fn rev_d_1_3_2_modbus_read() {
        let r = Request::read_registers(5, 5).unwrap();
        assert_eq!(
            bytes(&r).as_slice(),
            &[0xAA, 0x03, 0x00, 0x05, 0x00, 0x05, 0x8C, 0x13]
        );
    }

    #[test]
    fn rev_d_1_3_3_and_guide_fixed_requests() {
        assert_eq!(
            bytes(&Request::ReadTemperatures).as_slice(),
            &[0xAA, 0x1B, 0x3F, 0x1B]
        );
        // The guide's slip corrected: AA 14 7F 1F.
        assert_eq!(
            bytes(&Request::ReadPackVoltage).as_slice(),
            &[0xAA, 0x14, 0x7F, 0x1F]
        );
    }

    #[test]
    fn guide_native_read_block() {
        // 000: "0xAA 0x07 0x05 0x05 0x00" + CRC.
        let r = Request::read_registers_native(5, 5).unwrap();
        let b = bytes(&r);
        assert_eq!(&b[..5], &[0xAA, 0x07, 0x05, 0x05, 0x00]);
        assert_eq!(crc16(&b[..5]).to_le_bytes(), [b[5], b[6]]);
    }

    #[test]
    fn refused_before_any_byte() {
        assert_eq!(Request::read_registers(0, 0), Err(RequestError::Empty));
        assert_eq!(
            Request::read_registers(0, 128),
            Err(RequestError::TooMany {
                count: 128,
                max: 127
            })
        );
        assert_eq!(
            Request::write_registers(299, &[1]),
            Err(RequestError::NotWritable { address: 299 })
        );
        assert_eq!(
            Request::write_registers(399, &[1, 2]),
            Err(RequestError::NotWritable { address: 400 })
        );
        assert_eq!(
            Request::write_individual(&[(300, 1), (500, 2)]),
            Err(RequestError::NotWritable { address: 500 })
        );
        assert_eq!(
            Request::read_registers(0xFFFF, 2),
            Err(RequestError::AddressOverflow)
        );
        assert_eq!(Request::read_individual(&[]), Err(RequestError::Empty));
        assert_eq!(
            Request::read_settings(SettingsOption::Max, 101),
            Err(RequestError::TooMany {
                count: 101,
                max: 100
            })
        );
        let bad = Request::WriteRegisters {
            start: 10,
            values: BlockValues::from_slice(&[1]).unwrap(),
        };
        let mut out = [0u8; 32];
        assert_eq!(
            bad.encode(&mut out),
            Err(RequestError::NotWritable { address: 10 })
        );
        assert_eq!(out, [0u8; 32]);
        let mut small = [0u8; 3];
        assert_eq!(
            Request::ReadSoc.encode(&mut small),
            Err(RequestError::BufferTooSmall { need: 4 })
        );
    }

    #[test]
    fn parse_rejects_bad_bytes() {
        assert_eq!(
            Request::parse(&[0xAA, 0x14, 0x3F, 0x1B]),
            Err(RequestError::Crc {
                computed: 0x1F7F,
                received: 0x1B3F
            })
        );
        assert_eq!(
            Request::parse(&[0xAA, 0x13, 0, 0]),
            Err(RequestError::UnknownCommand(0x13))
        );
        assert_eq!(
            Request::parse(&[0xAA, 0x14, 0x7F]),
            Err(RequestError::Truncated)
        );
        assert_eq!(Request::parse(&[0x55]), Err(RequestError::NoPreamble));
        assert_eq!(Request::parse(&[]), Err(RequestError::Truncated));
    }

    #[test]
    fn encoded_len_matches() {
        let all = [
            Request::ResetClear(ResetOption::ResetBms),
            Request::read_registers(0, 56).unwrap(),
            Request::read_registers_native(0, 56).unwrap(),
            Request::read_individual(&[1, 2, 3]).unwrap(),
            Request::write_registers_native(300, &[1, 2]).unwrap(),
            Request::write_individual(&[(300, 1)]).unwrap(),
            Request::write_registers(300, &[1, 2, 3]).unwrap(),
            Request::read_settings(SettingsOption::Current, 44).unwrap(),
            Request::ReadSpeedDistanceTime,
        ];
        for r in all {
            let b = bytes(&r);
            assert_eq!(b.len(), r.encoded_len(), "{r:?}");
            assert_eq!(Request::frame_len(&b), Ok(Some(b.len())));
            assert_eq!(Request::parse(&b).unwrap(), r);
        }
    }
}
