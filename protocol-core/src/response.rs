//! Typed responses. A reply's layout depends on the request it answers, so
//! [`Response::decode`] takes the outstanding [`Request`] and checks the reply
//! against it (command, register count, 0x09 address echo, 0x10 echo).

use crate::command::{self as cmd};
use crate::events::{Event, OnlineStatus};
use crate::frame::{EncodeError, Frame, FrameRef, NackCode, Payload};
use crate::registers::MAX_CELLS;
use crate::request::{Request, SettingsOption};

/// Most events in one 0x11/0x12 reply that fit [`crate::frame::MAX_PAYLOAD`].
pub const MAX_EVENTS: usize = (crate::frame::MAX_PAYLOAD - 4) / 4;

/// Register values from a block read.
pub type Words = heapless::Vec<u16, { cmd::MAX_READ_MODBUS }>;

/// Consecutive register values starting at `start`.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct RegisterBlock {
    /// Address of the first value.
    pub start: u16,
    /// The values.
    pub values: Words,
}

impl RegisterBlock {
    /// Value of register `address`, if in the block.
    pub fn get(&self, address: u16) -> Option<u16> {
        let i = address.checked_sub(self.start)?;
        self.values.get(i as usize).copied()
    }

    /// Replaces the value of register `address`; false (nothing changed) when
    /// it is not in the block.
    pub fn set(&mut self, address: u16, value: u16) -> bool {
        let Some(i) = address.checked_sub(self.start) else {
            return false;
        };
        match self.values.get_mut(i as usize) {
            Some(v) => {
                *v = value;
                true
            }
            None => false,
        }
    }
    /// 32-bit value at `address` (low word) and `address + 1` (high word).
    pub fn get_u32(&self, address: u16) -> Option<u32> {
        Some(crate::registers::u32_from_words(
            self.get(address)?,
            self.get(address.checked_add(1)?)?,
        ))
    }
    /// f32 at `address` (low word) and `address + 1`.
    pub fn get_f32(&self, address: u16) -> Option<f32> {
        self.get_u32(address).map(f32::from_bits)
    }
    /// True when every address of `first..=last` is in the block.
    pub fn covers(&self, first: u16, last: u16) -> bool {
        self.get(first).is_some() && self.get(last).is_some()
    }
    /// (address, value) pairs.
    pub fn iter(&self) -> impl Iterator<Item = (u16, u16)> + '_ {
        self.values
            .iter()
            .enumerate()
            .map(|(i, v)| (self.start.wrapping_add(i as u16), *v))
    }
}

/// Temperatures in 0.1 °C; external sensors `None` when disconnected (-32768).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Temperatures {
    /// BMS internal sensor, 0.1 °C.
    pub internal_dc: i16,
    /// External sensor 1, 0.1 °C.
    pub external1_dc: Option<i16>,
    /// External sensor 2, 0.1 °C.
    pub external2_dc: Option<i16>,
}

/// Raw value of a disconnected external sensor (Rev D §1.1.18).
pub const SENSOR_DISCONNECTED: i16 = i16::MIN;

/// `None` for the disconnected marker.
pub const fn sensor(raw: i16) -> Option<i16> {
    if raw == SENSOR_DISCONNECTED {
        None
    } else {
        Some(raw)
    }
}

/// Raw value for a sensor reading.
pub const fn sensor_raw(v: Option<i16>) -> i16 {
    match v {
        Some(x) => x,
        None => SENSOR_DISCONNECTED,
    }
}

impl Temperatures {
    /// Internal temperature in °C.
    pub fn internal_c(&self) -> f32 {
        f32::from(self.internal_dc) * 0.1
    }
    /// External 1 in °C.
    pub fn external1_c(&self) -> Option<f32> {
        self.external1_dc.map(|v| f32::from(v) * 0.1)
    }
    /// External 2 in °C.
    pub fn external2_c(&self) -> Option<f32> {
        self.external2_dc.map(|v| f32::from(v) * 0.1)
    }
}

/// 0x1E reply (Rev D §1.1.21).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Version {
    /// Hardware version.
    pub hardware: u8,
    /// Hardware changes version.
    pub hardware_changes: u8,
    /// Firmware public version.
    pub firmware_public: u8,
    /// Firmware internal version.
    pub firmware_internal: u16,
}

/// 0x1F reply (Rev D §1.1.22).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ExtendedVersion {
    /// The 0x1E fields.
    pub version: Version,
    /// Bootloader version.
    pub bootloader: u8,
    /// Register map version.
    pub register_map: u8,
}

/// 0x11 / 0x12 reply: the BMS clock and the events.
#[derive(Debug, Clone, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct EventList {
    /// BMS timestamp, seconds.
    pub bms_timestamp_s: u32,
    /// Events in the order received.
    pub events: heapless::Vec<Event, MAX_EVENTS>,
}

/// Every typed response.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Response {
    /// The request was accepted (0x02, 0x0B, 0x0D).
    Ack {
        /// Command acknowledged.
        command: u8,
    },
    /// The request was refused.
    Nack {
        /// Command refused.
        command: u8,
        /// Why.
        code: NackCode,
    },
    /// 0x03 or 0x07 block.
    Registers(RegisterBlock),
    /// 0x09: (address, value) pairs, addresses checked against the request.
    Individual(heapless::Vec<(u16, u16), { cmd::MAX_READ_INDIVIDUAL }>),
    /// 0x10 echo, checked against the request.
    WriteEcho {
        /// First register written.
        start: u16,
        /// Registers written.
        count: u8,
    },
    /// 0x11 or 0x12.
    Events(EventList),
    /// 0x14: volts.
    PackVoltage(f32),
    /// 0x15: amps (negative = discharge).
    PackCurrent(f32),
    /// 0x16: mV.
    MaxCellVoltage(u16),
    /// 0x17: mV.
    MinCellVoltage(u16),
    /// 0x18.
    OnlineStatus(OnlineStatus),
    /// 0x19: seconds.
    Lifetime(u32),
    /// 0x1A: SOC in 0.000001 %.
    Soc(u32),
    /// 0x1B.
    Temperatures(Temperatures),
    /// 0x1C: cell voltages in 0.1 mV.
    CellVoltages(heapless::Vec<u16, MAX_CELLS>),
    /// 0x1D: values of registers 300.. for the option asked.
    Settings {
        /// Which values.
        option: SettingsOption,
        /// Values from register 300 on.
        values: RegisterBlock,
    },
    /// 0x1E.
    Version(Version),
    /// 0x1F.
    ExtendedVersion(ExtendedVersion),
    /// 0x20.
    SpeedDistanceTime {
        /// km/h.
        speed_kmh: f32,
        /// km.
        distance_left_km: u32,
        /// seconds.
        time_left_s: u32,
    },
}

/// Why a frame is not a valid answer to the outstanding request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum ResponseError {
    /// The frame answers another command.
    UnexpectedResponse {
        /// Command of the outstanding request.
        expected: u8,
        /// Command the frame answers.
        got: u8,
    },
    /// An ACK to a request that expects data, or data to one that expects an ACK.
    UnexpectedKind {
        /// Command of the outstanding request.
        command: u8,
    },
    /// The payload length does not fit the request.
    Length {
        /// Command.
        command: u8,
        /// Expected payload bytes.
        expected: usize,
        /// Received payload bytes.
        actual: usize,
    },
    /// A 0x09 address echo or 0x10 echo differs from the request.
    EchoMismatch {
        /// Command.
        command: u8,
        /// Expected address (or count).
        expected: u16,
        /// Received.
        got: u16,
    },
}

impl ResponseError {
    /// Short snake_case reason.
    pub const fn reason(&self) -> &'static str {
        match self {
            Self::UnexpectedResponse { .. } => "unexpected_response",
            Self::UnexpectedKind { .. } => "unexpected_kind",
            Self::Length { .. } => "length_mismatch",
            Self::EchoMismatch { .. } => "echo_mismatch",
        }
    }
}

fn le16(p: &[u8], i: usize) -> u16 {
    u16::from_le_bytes([
        p.get(i).copied().unwrap_or(0),
        p.get(i + 1).copied().unwrap_or(0),
    ])
}
fn be16(p: &[u8], i: usize) -> u16 {
    u16::from_be_bytes([
        p.get(i).copied().unwrap_or(0),
        p.get(i + 1).copied().unwrap_or(0),
    ])
}
fn le32(p: &[u8], i: usize) -> u32 {
    crate::registers::u32_from_words(le16(p, i), le16(p, i + 2))
}
fn byte(p: &[u8], i: usize) -> u8 {
    p.get(i).copied().unwrap_or(0)
}

/// Appends `count` register words of `payload` to `values`: big-endian words
/// for 0x03 (`big`), little-endian for the native commands. The caller has
/// checked the payload length.
fn fill_words(
    values: &mut Words,
    payload: &[u8],
    count: usize,
    big: bool,
    command: u8,
) -> Result<(), ResponseError> {
    // The usual case in one pass over whole words: every word in the payload
    // and room for all of them (what the loop below does, without a bounds
    // check per byte and a capacity check per word).
    let old = values.len();
    let (words, _) = payload.as_chunks::<2>();
    if let Some(words) = words.get(..count) {
        if values.resize(old + count, 0).is_ok() {
            if let Some(dst) = values.get_mut(old..) {
                if big {
                    // Two words per pass (the 0x03 live reply: 56 of them).
                    let (pairs, last) = dst.as_chunks_mut::<2>();
                    let (quads, _) = payload.as_chunks::<4>();
                    for (d, q) in pairs.iter_mut().zip(quads) {
                        *d = [
                            u16::from_be_bytes([q[0], q[1]]),
                            u16::from_be_bytes([q[2], q[3]]),
                        ];
                    }
                    let odd = count.checked_sub(1).and_then(|i| words.get(i));
                    if let (Some(d), Some(w)) = (last.first_mut(), odd) {
                        *d = u16::from_be_bytes(*w);
                    }
                } else {
                    for (d, w) in dst.iter_mut().zip(words) {
                        *d = u16::from_le_bytes(*w);
                    }
                }
            }
            return Ok(());
        }
    }
    for i in 0..count {
        let w = if big {
            be16(payload, 2 * i)
        } else {
            le16(payload, 2 * i)
        };
        values.push(w).map_err(|_| ResponseError::Length {
            command,
            expected: 2 * cmd::MAX_READ_MODBUS,
            actual: payload.len(),
        })?;
    }
    Ok(())
}

impl Response {
    /// As [`Response::decode`], into `out`: a register block (the live path) is
    /// filled in place, so that a caller keeping the response in a long-lived
    /// slot moves no whole `Response` (516 bytes on RV32). The checks and errors
    /// are [`Response::decode`]'s; on an error `out` holds some other valid value.
    pub fn decode_into(
        request: &Request,
        frame: &Frame,
        out: &mut Response,
    ) -> Result<(), ResponseError> {
        Self::decode_ref_into(request, frame.as_frame_ref(), out)
    }

    /// As [`Response::decode_into`], from a borrowed frame (see
    /// [`Decoder::poll_ref`](crate::decoder::Decoder::poll_ref)).
    pub fn decode_ref_into(
        request: &Request,
        frame: FrameRef<'_>,
        out: &mut Response,
    ) -> Result<(), ResponseError> {
        if let (
            Request::ReadRegisters { start, count } | Request::ReadRegistersNative { start, count },
            FrameRef::Data {
                command, payload, ..
            },
        ) = (request, frame)
        {
            if command == request.command() {
                let count = usize::from(*count);
                let big = matches!(request, Request::ReadRegisters { .. });
                if payload.len() != 2 * count {
                    return Err(ResponseError::Length {
                        command,
                        expected: 2 * count,
                        actual: payload.len(),
                    });
                }
                *out = Response::Registers(RegisterBlock {
                    start: *start,
                    values: Words::new(),
                });
                if let Response::Registers(block) = out {
                    fill_words(&mut block.values, payload, count, big, command)?;
                }
                return Ok(());
            }
        }
        *out = Self::decode_ref(request, frame)?;
        Ok(())
    }

    /// Decodes `frame` as the answer to `request`.
    pub fn decode(request: &Request, frame: &Frame) -> Result<Self, ResponseError> {
        Self::decode_ref(request, frame.as_frame_ref())
    }

    /// As [`Response::decode`], from a borrowed frame.
    pub fn decode_ref(request: &Request, frame: FrameRef<'_>) -> Result<Self, ResponseError> {
        let expected = request.command();
        let got = frame.command();
        if got != expected {
            return Err(ResponseError::UnexpectedResponse { expected, got });
        }
        let (payload, command) = match frame {
            FrameRef::Nack { command, code } => return Ok(Response::Nack { command, code }),
            FrameRef::Ack { command } => {
                return if request.expects_ack() {
                    Ok(Response::Ack { command })
                } else {
                    Err(ResponseError::UnexpectedKind { command })
                };
            }
            FrameRef::Data {
                payload, command, ..
            } => (payload, command),
        };
        if request.expects_ack() {
            return Err(ResponseError::UnexpectedKind { command });
        }
        // Register blocks (the live path) are filled in place in the value
        // returned: a 0x03 reply is not built on the stack and moved twice.
        if let Request::ReadRegisters { start, count }
        | Request::ReadRegistersNative { start, count } = request
        {
            let big = matches!(request, Request::ReadRegisters { .. });
            let count = usize::from(*count);
            need(command, payload, 2 * count)?;
            let mut out = Ok(Response::Registers(RegisterBlock {
                start: *start,
                values: Words::new(),
            }));
            if let Ok(Response::Registers(block)) = &mut out {
                fill_words(&mut block.values, payload, count, big, command)?;
            }
            return out;
        }
        Self::decode_payload(request, command, payload)
    }

    /// A data reply's payload by the layout of its request's family.
    fn decode_payload(
        request: &Request,
        command: u8,
        payload: &[u8],
    ) -> Result<Self, ResponseError> {
        Ok(match request {
            // Handled by `decode_ref`, in place.
            Request::ReadRegisters { .. } | Request::ReadRegistersNative { .. } => {
                return Err(ResponseError::UnexpectedKind { command })
            }
            Request::ReadSettings { option, count } => {
                let count = *count as usize;
                need(command, payload, 2 * count)?;
                let mut values = Words::new();
                fill_words(&mut values, payload, count, false, command)?;
                Response::Settings {
                    option: *option,
                    values: RegisterBlock {
                        start: cmd::SETTINGS_FIRST_REGISTER,
                        values,
                    },
                }
            }
            Request::ReadIndividual(addresses) => individual(command, payload, addresses)?,
            Request::WriteRegisters { start, values } => {
                write_echo(command, payload, *start, values.len())?
            }
            Request::ReadNewestEvents | Request::ReadAllEvents => events(command, payload)?,
            Request::ReadCellVoltages => cell_voltages(command, payload)?,
            Request::ReadVersion => {
                at_least(command, payload, 5)?;
                Response::Version(version(payload))
            }
            Request::ReadExtendedVersion => {
                at_least(command, payload, 7)?;
                Response::ExtendedVersion(ExtendedVersion {
                    version: version(payload),
                    bootloader: byte(payload, 5),
                    register_map: byte(payload, 6),
                })
            }
            Request::ResetClear(_)
            | Request::WriteRegistersNative { .. }
            | Request::WriteIndividual(_) => return Err(ResponseError::UnexpectedKind { command }),
            Request::ReadPackVoltage
            | Request::ReadPackCurrent
            | Request::ReadMaxCellVoltage
            | Request::ReadMinCellVoltage
            | Request::ReadOnlineStatus
            | Request::ReadLifetime
            | Request::ReadSoc
            | Request::ReadTemperatures
            | Request::ReadSpeedDistanceTime => measurement(request, command, payload)?,
        })
    }

    /// The frame a BMS sends for this response (used by the simulator and the
    /// round-trip tests).
    pub fn to_frame(&self, request: &Request) -> Result<Frame, EncodeError> {
        let command = request.command();
        let mut p = Payload::new();
        let overflow = EncodeError::PayloadTooLong {
            len: crate::frame::MAX_PAYLOAD + 1,
            max: crate::frame::MAX_PAYLOAD,
        };
        let mut put = |b: &[u8]| p.extend_from_slice(b).map_err(|_| overflow);
        match self {
            Response::Ack { command } => return Ok(Frame::Ack { command: *command }),
            Response::Nack { command, code } => {
                return Ok(Frame::Nack {
                    command: *command,
                    code: *code,
                })
            }
            Response::Registers(block) => {
                let big = command == cmd::READ_BLOCK_MODBUS;
                for v in &block.values {
                    put(&if big {
                        v.to_be_bytes()
                    } else {
                        v.to_le_bytes()
                    })?;
                }
            }
            Response::Settings { values, .. } => {
                for v in &values.values {
                    put(&v.to_le_bytes())?;
                }
            }
            Response::Individual(pairs) => {
                for (a, v) in pairs {
                    put(&a.to_le_bytes())?;
                    put(&v.to_le_bytes())?;
                }
            }
            Response::WriteEcho { start, count } => {
                put(&start.to_be_bytes())?;
                put(&[0, *count])?;
            }
            Response::Events(list) => {
                put(&list.bms_timestamp_s.to_le_bytes())?;
                for e in &list.events {
                    put(&e.to_bytes())?;
                }
            }
            Response::PackVoltage(v) | Response::PackCurrent(v) => put(&v.to_bits().to_le_bytes())?,
            Response::MaxCellVoltage(v) | Response::MinCellVoltage(v) => put(&v.to_le_bytes())?,
            Response::OnlineStatus(s) => put(&s.raw().to_le_bytes())?,
            Response::Lifetime(v) | Response::Soc(v) => put(&v.to_le_bytes())?,
            Response::Temperatures(t) => {
                put(&t.internal_dc.to_le_bytes())?;
                put(&sensor_raw(t.external1_dc).to_le_bytes())?;
                put(&sensor_raw(t.external2_dc).to_le_bytes())?;
            }
            Response::CellVoltages(cells) => {
                for c in cells {
                    put(&c.to_le_bytes())?;
                }
            }
            Response::Version(v) => put_version(&mut put, v)?,
            Response::ExtendedVersion(x) => {
                put_version(&mut put, &x.version)?;
                put(&[x.bootloader, x.register_map])?;
            }
            Response::SpeedDistanceTime {
                speed_kmh,
                distance_left_km,
                time_left_s,
            } => {
                put(&speed_kmh.to_bits().to_le_bytes())?;
                put(&distance_left_km.to_le_bytes())?;
                put(&time_left_s.to_le_bytes())?;
            }
        }
        Ok(Frame::Data {
            command,
            payload: p,
            packets: 1,
        })
    }
}

fn put_version(
    put: &mut impl FnMut(&[u8]) -> Result<(), EncodeError>,
    v: &Version,
) -> Result<(), EncodeError> {
    put(&[v.hardware, v.hardware_changes, v.firmware_public])?;
    put(&v.firmware_internal.to_le_bytes())
}

fn version(p: &[u8]) -> Version {
    Version {
        hardware: byte(p, 0),
        hardware_changes: byte(p, 1),
        firmware_public: byte(p, 2),
        firmware_internal: le16(p, 3),
    }
}

/// The payload is exactly `n` bytes.
fn need(command: u8, payload: &[u8], n: usize) -> Result<(), ResponseError> {
    length(command, payload, n, payload.len() == n)
}

/// The payload is at least `n` bytes.
fn at_least(command: u8, payload: &[u8], n: usize) -> Result<(), ResponseError> {
    length(command, payload, n, payload.len() >= n)
}

/// A length error expecting `n` bytes, unless `ok`.
fn length(command: u8, payload: &[u8], n: usize, ok: bool) -> Result<(), ResponseError> {
    if ok {
        Ok(())
    } else {
        Err(ResponseError::Length {
            command,
            expected: n,
            actual: payload.len(),
        })
    }
}

/// 0x09: (address, value) pairs, each address the one asked for.
fn individual(command: u8, payload: &[u8], addresses: &[u16]) -> Result<Response, ResponseError> {
    need(command, payload, 4 * addresses.len())?;
    let mut pairs = heapless::Vec::new();
    for (i, &a) in addresses.iter().enumerate() {
        let echo = le16(payload, 4 * i);
        if echo != a {
            return Err(ResponseError::EchoMismatch {
                command,
                expected: a,
                got: echo,
            });
        }
        let _within_capacity = pairs.push((a, le16(payload, 4 * i + 2)));
    }
    Ok(Response::Individual(pairs))
}

/// 0x10: the start and count written, echoed (big-endian).
fn write_echo(
    command: u8,
    payload: &[u8],
    start: u16,
    count: usize,
) -> Result<Response, ResponseError> {
    need(command, payload, 4)?;
    let echo_start = be16(payload, 0);
    let echo_count = be16(payload, 2);
    if echo_start != start {
        return Err(ResponseError::EchoMismatch {
            command,
            expected: start,
            got: echo_start,
        });
    }
    if echo_count != count as u16 {
        return Err(ResponseError::EchoMismatch {
            command,
            expected: count as u16,
            got: echo_count,
        });
    }
    Ok(Response::WriteEcho {
        start: echo_start,
        count: echo_count as u8,
    })
}

/// 0x11 / 0x12: the BMS's time, then 4 bytes per event.
fn events(command: u8, payload: &[u8]) -> Result<Response, ResponseError> {
    at_least(command, payload, 4)?;
    if !(payload.len() - 4).is_multiple_of(4) || payload.len() > 4 + 4 * MAX_EVENTS {
        return Err(ResponseError::Length {
            command,
            expected: 4 + (payload.len() - 4) / 4 * 4,
            actual: payload.len(),
        });
    }
    let mut events = heapless::Vec::new();
    for chunk in payload.get(4..).unwrap_or(&[]).chunks_exact(4) {
        let b = [
            byte(chunk, 0),
            byte(chunk, 1),
            byte(chunk, 2),
            byte(chunk, 3),
        ];
        let _within_capacity = events.push(Event::from_bytes(b));
    }
    Ok(Response::Events(EventList {
        bms_timestamp_s: le32(payload, 0),
        events,
    }))
}

/// 0x1C: one 16-bit voltage per cell.
fn cell_voltages(command: u8, payload: &[u8]) -> Result<Response, ResponseError> {
    if !payload.len().is_multiple_of(2) || payload.len() > 2 * MAX_CELLS {
        return Err(ResponseError::Length {
            command,
            expected: (payload.len() / 2).min(MAX_CELLS) * 2,
            actual: payload.len(),
        });
    }
    let mut cells = heapless::Vec::new();
    for i in 0..payload.len() / 2 {
        let _within_capacity = cells.push(le16(payload, 2 * i));
    }
    Ok(Response::CellVoltages(cells))
}

/// The single-measurement commands (0x14-0x1B, 0x20): fixed layouts.
fn measurement(request: &Request, command: u8, payload: &[u8]) -> Result<Response, ResponseError> {
    let need = |n| need(command, payload, n);
    Ok(match request {
        Request::ReadPackVoltage => {
            need(4)?;
            Response::PackVoltage(f32::from_bits(le32(payload, 0)))
        }
        Request::ReadPackCurrent => {
            need(4)?;
            Response::PackCurrent(f32::from_bits(le32(payload, 0)))
        }
        Request::ReadMaxCellVoltage => {
            need(2)?;
            Response::MaxCellVoltage(le16(payload, 0))
        }
        Request::ReadMinCellVoltage => {
            need(2)?;
            Response::MinCellVoltage(le16(payload, 0))
        }
        Request::ReadOnlineStatus => {
            need(2)?;
            Response::OnlineStatus(OnlineStatus::from_raw(le16(payload, 0)))
        }
        Request::ReadLifetime => {
            need(4)?;
            Response::Lifetime(le32(payload, 0))
        }
        Request::ReadSoc => {
            need(4)?;
            Response::Soc(le32(payload, 0))
        }
        Request::ReadTemperatures => {
            need(6)?;
            Response::Temperatures(Temperatures {
                internal_dc: le16(payload, 0) as i16,
                external1_dc: sensor(le16(payload, 2) as i16),
                external2_dc: sensor(le16(payload, 4) as i16),
            })
        }
        Request::ReadSpeedDistanceTime => {
            need(12)?;
            Response::SpeedDistanceTime {
                speed_kmh: f32::from_bits(le32(payload, 0)),
                distance_left_km: le32(payload, 4),
                time_left_s: le32(payload, 8),
            }
        }
        _ => return Err(ResponseError::UnexpectedKind { command }),
    })
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::decoder::decode_all;
    use std::vec;
    use std::vec::Vec;

    fn decode_bytes(req: &Request, bytes: &[u8]) -> Vec<Result<Response, ResponseError>> {
        let mut out = Vec::new();
        decode_all(bytes, |f| out.push(Response::decode(req, &f.unwrap())));
        out
    }

    /// The one-pass path of `fill_words` gives what the word-by-word loop gives
    /// (short payloads, odd lengths, a full vector, both byte orders).
    #[test]
    fn fill_words_matches_word_by_word() {
        fn reference(values: &mut Words, p: &[u8], count: usize, big: bool) -> bool {
            for i in 0..count {
                let w = if big { be16(p, 2 * i) } else { le16(p, 2 * i) };
                if values.push(w).is_err() {
                    return false;
                }
            }
            true
        }
        let payload: std::vec::Vec<u8> = (0..=255u8).collect();
        for big in [false, true] {
            for pre in [0usize, 1, 100, 127] {
                for len in [0usize, 1, 2, 3, 10, 11, 112, 254, 256] {
                    for count in [0usize, 1, 5, 56, 127, 128] {
                        let p = &payload[..len];
                        let mut a = Words::new();
                        a.resize(pre, 7).unwrap();
                        let mut b = a.clone();
                        let ok = fill_words(&mut a, p, count, big, 3).is_ok();
                        assert_eq!(ok, reference(&mut b, p, count, big));
                        assert_eq!(a, b, "big {big} pre {pre} len {len} count {count}");
                    }
                }
            }
        }
    }

    #[test]
    fn rev_d_1_3_2_modbus_read_reply() {
        let req = Request::read_registers(5, 5).unwrap();
        let bytes = [
            0xAA, 0x03, 0x0A, 0x97, 0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C, 0x3E,
            0xC7,
        ];
        let r = decode_bytes(&req, &bytes);
        let Ok(Response::Registers(block)) = &r[0] else {
            panic!("{r:?}")
        };
        assert_eq!(block.start, 5);
        assert_eq!(
            block.values.as_slice(),
            &[38720, 38720, 38700, 38700, 38700]
        );
        // And back.
        let mut b = [0u8; 32];
        let n = r[0]
            .as_ref()
            .unwrap()
            .to_frame(&req)
            .unwrap()
            .encode(&mut b)
            .unwrap();
        assert_eq!(&b[..n], &bytes);
    }

    #[test]
    fn rev_d_1_3_1_write_echo() {
        let req = Request::write_registers(315, &[4200, 2500]).unwrap();
        let bytes = [0xAA, 0x10, 0x01, 0x3B, 0x00, 0x02, 0x28, 0x22];
        assert_eq!(
            decode_bytes(&req, &bytes),
            vec![Ok(Response::WriteEcho {
                start: 315,
                count: 2
            })]
        );
        // An echo of another address is refused.
        let other = Request::write_registers(316, &[4200, 2500]).unwrap();
        assert_eq!(
            decode_bytes(&other, &bytes),
            vec![Err(ResponseError::EchoMismatch {
                command: 0x10,
                expected: 316,
                got: 315
            })]
        );
    }

    #[test]
    fn rev_d_1_3_3_temperatures() {
        let bytes = [
            0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4E,
        ];
        let r = decode_bytes(&Request::ReadTemperatures, &bytes);
        assert_eq!(
            r,
            vec![Ok(Response::Temperatures(Temperatures {
                internal_dc: 278,
                external1_dc: Some(276),
                external2_dc: Some(278)
            }))]
        );
    }

    #[test]
    fn disconnected_sensor_is_none() {
        let t = Response::Temperatures(Temperatures {
            internal_dc: -5,
            external1_dc: None,
            external2_dc: Some(-400),
        });
        let f = t.to_frame(&Request::ReadTemperatures).unwrap();
        let Frame::Data { payload, .. } = &f else {
            panic!()
        };
        assert_eq!(&payload[2..4], &[0x00, 0x80]);
        assert_eq!(Response::decode(&Request::ReadTemperatures, &f), Ok(t));
    }

    #[test]
    fn ack_only_for_ack_requests() {
        let ack = Frame::Ack { command: 0x0D };
        let w = Request::write_individual(&[(300, 3650)]).unwrap();
        assert_eq!(
            Response::decode(&w, &ack),
            Ok(Response::Ack { command: 0x0D })
        );
        let ack10 = Frame::Ack { command: 0x10 };
        let w10 = Request::write_registers(300, &[1]).unwrap();
        assert_eq!(
            Response::decode(&w10, &ack10),
            Err(ResponseError::UnexpectedKind { command: 0x10 })
        );
        assert_eq!(
            Response::decode(&w, &Frame::Ack { command: 0x0B }),
            Err(ResponseError::UnexpectedResponse {
                expected: 0x0D,
                got: 0x0B
            })
        );
        let nack = Frame::Nack {
            command: 0x03,
            code: NackCode::Unknown(7),
        };
        let r = Request::read_registers(0, 1).unwrap();
        assert_eq!(
            Response::decode(&r, &nack),
            Ok(Response::Nack {
                command: 3,
                code: NackCode::Unknown(7)
            })
        );
    }

    #[test]
    fn individual_echo_is_checked() {
        let req = Request::read_individual(&[36, 37]).unwrap();
        let good = Frame::data(0x09, &[36, 0, 0xB8, 0x1E, 37, 0, 0x5F, 0x42]).unwrap();
        assert_eq!(
            Response::decode(&req, &good),
            Ok(Response::Individual(
                heapless::Vec::from_slice(&[(36, 0x1EB8), (37, 0x425F)]).unwrap()
            ))
        );
        let bad = Frame::data(0x09, &[36, 0, 0xB8, 0x1E, 38, 0, 0x5F, 0x42]).unwrap();
        assert_eq!(
            Response::decode(&req, &bad),
            Err(ResponseError::EchoMismatch {
                command: 9,
                expected: 37,
                got: 38
            })
        );
    }

    #[test]
    fn guide_native_block_reply() {
        // 000, 0x07 example: the same cells as the 0x03 example, little-endian words.
        let req = Request::read_registers_native(5, 5).unwrap();
        let f = Frame::data(
            0x07,
            &[0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C, 0x97],
        )
        .unwrap();
        let Ok(Response::Registers(b)) = Response::decode(&req, &f) else {
            panic!()
        };
        assert_eq!(b.values.as_slice(), &[38720, 38720, 38700, 38700, 38700]);
        let short = Frame::data(0x07, &[0x40, 0x97]).unwrap();
        assert_eq!(
            Response::decode(&req, &short),
            Err(ResponseError::Length {
                command: 7,
                expected: 10,
                actual: 2
            })
        );
    }

    #[test]
    fn guide_soc_status_version_events() {
        // 000 example 6: bytes 00 24 F4 01 are 0x01F42400 = 32 777 216 (32.777216 %);
        // the guide's "= 32800000" is an arithmetic slip (32.8 % is 0x01F47D00).
        let f = Frame::data(0x1A, &[0x00, 0x24, 0xF4, 0x01]).unwrap();
        assert_eq!(
            Response::decode(&Request::ReadSoc, &f),
            Ok(Response::Soc(0x01F4_2400))
        );
        let f = Frame::data(0x1A, &[0x00, 0x7D, 0xF4, 0x01]).unwrap();
        assert_eq!(
            Response::decode(&Request::ReadSoc, &f),
            Ok(Response::Soc(32_800_000))
        );
        // 000 example 4: status 0x0091 charging.
        let f = Frame::data(0x18, &[0x91, 0x00]).unwrap();
        assert_eq!(
            Response::decode(&Request::ReadOnlineStatus, &f),
            Ok(Response::OnlineStatus(OnlineStatus::Charging))
        );
        // 000 example 8 (its PL says 8 over 7 data bytes; decoded with PL = 7).
        let f = Frame::data(0x1F, &[0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05]).unwrap();
        assert_eq!(
            Response::decode(&Request::ReadExtendedVersion, &f),
            Ok(Response::ExtendedVersion(ExtendedVersion {
                version: Version {
                    hardware: 1,
                    hardware_changes: 0,
                    firmware_public: 20,
                    firmware_internal: 58
                },
                bootloader: 2,
                register_map: 5
            }))
        );
        // 000 example 5, in the UART layout (one frame, Rev D §1.1.9).
        let f = Frame::data(
            0x11,
            &[
                0x00, 0x2A, 0x3B, 0x00, 0x10, 0x28, 0x3B, 0x62, 0x50, 0x29, 0x3B, 0x63,
            ],
        )
        .unwrap();
        let Ok(Response::Events(list)) = Response::decode(&Request::ReadNewestEvents, &f) else {
            panic!()
        };
        assert_eq!(list.bms_timestamp_s, 0x003B2A00);
        assert_eq!(list.events[0].timestamp_s, 0x3B2810);
        assert_eq!(list.events[1].id, crate::events::EventId::ChargingDone);
        let bad = Frame::data(0x11, &[0, 0, 0, 0, 1, 2, 3]).unwrap();
        assert!(Response::decode(&Request::ReadNewestEvents, &bad).is_err());
    }
}
