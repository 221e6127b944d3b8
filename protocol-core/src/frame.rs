//! Response frames on the wire: length rules per command, the plain-data [`Frame`]
//! and its encoder.
//!
//! Layouts (Rev D §1.1, HARDWARE-NOTES "Framing"):
//!
//! | first bytes      | total length            | what                                  |
//! |------------------|-------------------------|---------------------------------------|
//! | `AA 00 CMD ERR`  | 6                       | NACK                                  |
//! | `AA 01 CMD`      | 5                       | ACK                                   |
//! | `AA 10`          | 8                       | 0x10 write echo `ADDR:MSB ADDR:LSB 00 RL` |
//! | `AA 14/15/19/1A` | 8                       | 4 data bytes, no PL                   |
//! | `AA 16/17/18`    | 6                       | 2 data bytes, no PL                   |
//! | `AA 20`          | 16                      | 12 data bytes, no PL                  |
//! | `AA 03/1B..1F PL`| 5 + PL                  | PL = plain byte count                 |
//! | `AA 07/09/11/12 PL` | 5 + 63 if PL bit 7 else 5 + PL | packetized native replies   |
//!
//! The length of a frame is never derived from "byte 3 + 5": for an ACK byte 3 is a
//! command code (HARDWARE-NOTES, "Mistakes seen").

use crate::command::{self as cmd, PREAMBLE};
use crate::crc::crc16;

/// Largest single frame on the wire: preamble, command, PL, 255 bytes, CRC.
pub const MAX_FRAME_LEN: usize = 3 + 255 + 2;
/// Payload bytes in one packet of a packetized native reply: PL bits 0-5.
pub const MAX_PACKET_PAYLOAD: usize = 63;
/// PL bit 7: this packet is not the last; bits 0-5 are then the packet ID.
pub const PL_MORE_PACKETS: u8 = 0x80;
/// PL bit 6: reserved, always 0.
pub const PL_RESERVED: u8 = 0x40;
/// PL bits 0-5: payload size (last packet) or packet ID (other packets).
pub const PL_VALUE_MASK: u8 = 0x3F;
/// ID of the first packet of a packetized reply as this crate encodes it. Decoding
/// accepts any first ID (the one real-unit observation shows 0x82 first) and then
/// requires consecutive IDs.
pub const FIRST_PACKET_ID: u8 = 1;
/// Largest reassembled payload: a 127-register 0x07 read (254 bytes) or 0x12 with
/// its 49 events (200 bytes) fit.
pub const MAX_PAYLOAD: usize = 256;

/// A payload, bounded by [`MAX_PAYLOAD`].
pub type Payload = heapless::Vec<u8, MAX_PAYLOAD>;

/// NACK error code (Rev D §1.1.1). Unknown codes are kept.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum NackCode {
    /// 0x00: command error (also what an invalid register address gets).
    CommandError,
    /// 0x01: CRC error.
    CrcError,
    /// Any other code.
    Unknown(u8),
}

impl NackCode {
    /// From the wire byte.
    pub const fn from_u8(code: u8) -> Self {
        match code {
            0x00 => Self::CommandError,
            0x01 => Self::CrcError,
            other => Self::Unknown(other),
        }
    }
    /// To the wire byte.
    pub const fn to_u8(self) -> u8 {
        match self {
            Self::CommandError => 0x00,
            Self::CrcError => 0x01,
            Self::Unknown(c) => c,
        }
    }
    /// Short name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::CommandError => "command_error",
            Self::CrcError => "crc_error",
            Self::Unknown(_) => "unknown",
        }
    }
}

/// One complete, CRC-checked response as received (multi-packet replies reassembled).
#[derive(Debug, Clone, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Frame {
    /// `AA 01 CMD`: the command was accepted.
    Ack {
        /// The command acknowledged.
        command: u8,
    },
    /// `AA 00 CMD ERR`: the command was refused.
    Nack {
        /// The command refused.
        command: u8,
        /// Why.
        code: NackCode,
    },
    /// A data reply. `payload` holds the bytes between the PL byte (or the command
    /// byte when there is no PL) and the CRC; for packetized replies, the
    /// concatenated payloads of all packets.
    Data {
        /// The command answered.
        command: u8,
        /// The payload bytes.
        payload: Payload,
        /// Number of packets it arrived in (1 for a single frame).
        packets: u8,
    },
}

/// A [`Frame`] borrowed where it was received: what
/// [`Decoder::poll_ref`](crate::decoder::Decoder::poll_ref) gives, the payload
/// left in the decoder's buffer instead of copied out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameRef<'a> {
    /// As [`Frame::Ack`].
    Ack {
        /// The command acknowledged.
        command: u8,
    },
    /// As [`Frame::Nack`].
    Nack {
        /// The command refused.
        command: u8,
        /// Why.
        code: NackCode,
    },
    /// As [`Frame::Data`].
    Data {
        /// The command answered.
        command: u8,
        /// The payload bytes.
        payload: &'a [u8],
        /// Number of packets it arrived in (1 for a single frame).
        packets: u8,
    },
}

impl FrameRef<'_> {
    /// The command this frame answers (for ACK/NACK, the acknowledged command).
    pub const fn command(&self) -> u8 {
        match self {
            FrameRef::Ack { command }
            | FrameRef::Nack { command, .. }
            | FrameRef::Data { command, .. } => *command,
        }
    }
}

impl Frame {
    /// The frame as a [`FrameRef`].
    pub fn as_frame_ref(&self) -> FrameRef<'_> {
        match self {
            Frame::Ack { command } => FrameRef::Ack { command: *command },
            Frame::Nack { command, code } => FrameRef::Nack {
                command: *command,
                code: *code,
            },
            Frame::Data {
                command,
                payload,
                packets,
            } => FrameRef::Data {
                command: *command,
                payload,
                packets: *packets,
            },
        }
    }

    /// The command this frame answers (for ACK/NACK, the acknowledged command).
    pub const fn command(&self) -> u8 {
        match self {
            Frame::Ack { command } | Frame::Nack { command, .. } | Frame::Data { command, .. } => {
                *command
            }
        }
    }

    /// A single-packet data frame. Fails when `payload` exceeds [`MAX_PAYLOAD`].
    pub fn data(command: u8, payload: &[u8]) -> Result<Self, EncodeError> {
        Ok(Frame::Data {
            command,
            payload: Payload::from_slice(payload).map_err(|_| EncodeError::PayloadTooLong {
                len: payload.len(),
                max: MAX_PAYLOAD,
            })?,
            packets: 1,
        })
    }

    /// Length on the wire once encoded (all packets).
    pub fn encoded_len(&self) -> Result<usize, EncodeError> {
        match self {
            Frame::Ack { .. } => Ok(5),
            Frame::Nack { .. } => Ok(6),
            Frame::Data {
                command, payload, ..
            } => match layout(*command) {
                Layout::Fixed(n) | Layout::Echo(n) => {
                    if payload.len() + 4 == n {
                        Ok(n)
                    } else {
                        Err(EncodeError::WrongPayloadLength {
                            command: *command,
                            len: payload.len(),
                        })
                    }
                }
                Layout::Counted(rule) => {
                    if rule.accepts(payload.len()) {
                        Ok(payload.len() + 5)
                    } else {
                        Err(EncodeError::WrongPayloadLength {
                            command: *command,
                            len: payload.len(),
                        })
                    }
                }
                Layout::Packetized => {
                    let full = payload.len() / MAX_PACKET_PAYLOAD;
                    let rest = payload.len() % MAX_PACKET_PAYLOAD;
                    // A payload that is an exact multiple of 63 still ends with a
                    // last packet; we send the final 63 bytes as that last packet.
                    let packets = if rest == 0 && full > 0 {
                        full
                    } else {
                        full + 1
                    };
                    Ok(payload.len() + 5 * packets)
                }
                Layout::NotAResponse => Err(EncodeError::NotAResponse { command: *command }),
            },
        }
    }

    /// Encodes the frame (all its packets) into `out`; returns the bytes written.
    /// Packetized native replies longer than 63 bytes are split into packets
    /// numbered from [`FIRST_PACKET_ID`].
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, EncodeError> {
        let need = self.encoded_len()?;
        if out.len() < need {
            return Err(EncodeError::BufferTooSmall {
                need,
                have: out.len(),
            });
        }
        let mut w = Writer { out, pos: 0 };
        match self {
            Frame::Ack { command } => {
                w.frame(&[PREAMBLE, cmd::ACK, *command], &[]);
            }
            Frame::Nack { command, code } => {
                w.frame(&[PREAMBLE, cmd::NACK, *command, code.to_u8()], &[]);
            }
            Frame::Data {
                command, payload, ..
            } => match layout(*command) {
                Layout::Fixed(_) | Layout::Echo(_) => w.frame(&[PREAMBLE, *command], payload),
                Layout::Counted(_) => {
                    // `accepts` bounded the length to <= 255 in encoded_len.
                    let pl = u8::try_from(payload.len()).unwrap_or(u8::MAX);
                    w.frame(&[PREAMBLE, *command, pl], payload)
                }
                Layout::Packetized => {
                    let mut rest: &[u8] = payload;
                    let mut id = FIRST_PACKET_ID;
                    while rest.len() > MAX_PACKET_PAYLOAD {
                        let (head, tail) = rest.split_at(MAX_PACKET_PAYLOAD);
                        w.frame(
                            &[PREAMBLE, *command, PL_MORE_PACKETS | (id & PL_VALUE_MASK)],
                            head,
                        );
                        id = id.wrapping_add(1);
                        rest = tail;
                    }
                    let pl = u8::try_from(rest.len()).unwrap_or(0);
                    w.frame(&[PREAMBLE, *command, pl], rest);
                }
                Layout::NotAResponse => {}
            },
        }
        Ok(w.pos)
    }
}

/// Writes frames into a buffer already checked to be large enough.
struct Writer<'a> {
    out: &'a mut [u8],
    pos: usize,
}

impl Writer<'_> {
    fn put(&mut self, bytes: &[u8]) {
        if let Some(dst) = self.out.get_mut(self.pos..self.pos + bytes.len()) {
            dst.copy_from_slice(bytes);
        }
        self.pos += bytes.len();
    }
    fn frame(&mut self, head: &[u8], body: &[u8]) {
        let start = self.pos;
        self.put(head);
        self.put(body);
        let crc = crc16(self.out.get(start..self.pos).unwrap_or(&[]));
        self.put(&crc.to_le_bytes());
    }
}

/// Why a frame could not be encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum EncodeError {
    /// The output buffer is too small.
    BufferTooSmall {
        /// Bytes needed.
        need: usize,
        /// Bytes available.
        have: usize,
    },
    /// The payload does not fit a frame of this command.
    WrongPayloadLength {
        /// Command code.
        command: u8,
        /// Payload length given.
        len: usize,
    },
    /// The payload exceeds [`MAX_PAYLOAD`].
    PayloadTooLong {
        /// Payload length given.
        len: usize,
        /// The maximum.
        max: usize,
    },
    /// This command has no data reply (only ACK/NACK), or is unknown.
    NotAResponse {
        /// Command code.
        command: u8,
    },
    /// The request is invalid (see [`crate::request::RequestError`]).
    InvalidRequest(crate::request::RequestError),
}

/// Which payload lengths a PL-counted reply may have (framing-level plausibility,
/// so a corrupt PL byte is rejected at once rather than waited for).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct PlRule {
    pub min: usize,
    pub max: usize,
    pub even: bool,
}

impl PlRule {
    pub(crate) const fn accepts(self, len: usize) -> bool {
        len >= self.min && len <= self.max && (!self.even || len.is_multiple_of(2))
    }
}

/// Wire layout of a data reply, by command byte.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Layout {
    /// Fixed total length, no PL byte.
    Fixed(usize),
    /// The 0x10 echo: fixed 8 bytes.
    Echo(usize),
    /// `AA CMD PL payload CRC` with PL a plain byte count.
    Counted(PlRule),
    /// Native reply with PL bit 7 = more packets.
    Packetized,
    /// No data reply exists for this byte.
    NotAResponse,
}

pub(crate) const fn layout(command: u8) -> Layout {
    match command {
        cmd::WRITE_BLOCK_MODBUS => Layout::Echo(8),
        cmd::READ_PACK_VOLTAGE | cmd::READ_PACK_CURRENT | cmd::READ_LIFETIME | cmd::READ_SOC => {
            Layout::Fixed(8)
        }
        cmd::READ_MAX_CELL_VOLTAGE | cmd::READ_MIN_CELL_VOLTAGE | cmd::READ_ONLINE_STATUS => {
            Layout::Fixed(6)
        }
        cmd::READ_SPEED_DISTANCE_TIME => Layout::Fixed(16),
        cmd::READ_BLOCK_MODBUS => Layout::Counted(PlRule {
            min: 2,
            max: 2 * cmd::MAX_READ_MODBUS,
            even: true,
        }),
        cmd::READ_TEMPERATURES => Layout::Counted(PlRule {
            min: 6,
            max: 6,
            even: true,
        }),
        cmd::READ_CELL_VOLTAGES => Layout::Counted(PlRule {
            min: 0,
            max: 2 * crate::registers::MAX_CELLS,
            even: true,
        }),
        cmd::READ_SETTINGS => Layout::Counted(PlRule {
            min: 2,
            max: 2 * cmd::MAX_READ_SETTINGS,
            even: true,
        }),
        // Rev D: 5 bytes. Longer replies are tolerated (the French guide's example
        // declares more), the extra bytes are ignored by the typed decoder.
        cmd::READ_VERSION => Layout::Counted(PlRule {
            min: 5,
            max: 16,
            even: false,
        }),
        cmd::READ_EXTENDED_VERSION => Layout::Counted(PlRule {
            min: 7,
            max: 16,
            even: false,
        }),
        c if cmd::is_packetized(c) => Layout::Packetized,
        _ => Layout::NotAResponse,
    }
}

/// What the bytes at the start of a buffer (which begins with the preamble) are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Framing {
    /// Not enough bytes yet to know.
    NeedMore,
    /// Not enough bytes yet: the candidate is complete at this total length.
    Short(usize),
    /// A candidate frame of this total length.
    Complete(usize),
    /// The command byte cannot start a response: skip the preamble silently.
    NotAFrame,
    /// A known command with an impossible PL byte.
    BadLength { command: u8, pl: u8 },
}

/// Length rule applied to `buf` (which starts with [`PREAMBLE`]).
pub(crate) fn framing(buf: &[u8]) -> Framing {
    let Some(&command) = buf.get(1) else {
        return Framing::NeedMore;
    };
    let fixed = |n: usize| {
        if buf.len() >= n {
            Framing::Complete(n)
        } else {
            Framing::Short(n)
        }
    };
    match command {
        cmd::NACK => fixed(6),
        cmd::ACK => fixed(5),
        _ => match layout(command) {
            Layout::Fixed(n) | Layout::Echo(n) => fixed(n),
            Layout::NotAResponse => Framing::NotAFrame,
            Layout::Counted(rule) => match buf.get(2) {
                None => Framing::NeedMore,
                Some(&pl) if rule.accepts(pl as usize) => fixed(pl as usize + 5),
                Some(&pl) => Framing::BadLength { command, pl },
            },
            Layout::Packetized => match buf.get(2) {
                None => Framing::NeedMore,
                Some(&pl) if pl & PL_RESERVED != 0 => Framing::BadLength { command, pl },
                Some(&pl) if pl & PL_MORE_PACKETS != 0 => fixed(MAX_PACKET_PAYLOAD + 5),
                Some(&pl) => fixed(pl as usize + 5),
            },
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ack_and_nack_bytes() {
        let mut b = [0u8; 8];
        let n = Frame::Ack { command: 0x0D }.encode(&mut b).unwrap();
        assert_eq!(n, 5);
        assert_eq!(&b[..3], &[0xAA, 0x01, 0x0D]);
        assert_eq!(crc16(&b[..3]).to_le_bytes(), [b[3], b[4]]);
        let n = Frame::Nack {
            command: 0x10,
            code: NackCode::CommandError,
        }
        .encode(&mut b)
        .unwrap();
        assert_eq!(n, 6);
        assert_eq!(&b[..4], &[0xAA, 0x00, 0x10, 0x00]);
    }

    #[test]
    fn packetized_split_is_63_plus_rest() {
        let payload: heapless::Vec<u8, 90> = (0..90u8).collect();
        let f = Frame::data(cmd::READ_BLOCK, &payload).unwrap();
        let mut b = [0u8; 200];
        let n = f.encode(&mut b).unwrap();
        assert_eq!(n, 90 + 10);
        assert_eq!(b[2], 0x80 | FIRST_PACKET_ID);
        assert_eq!(b[68], 0xAA);
        assert_eq!(b[70], 27);
    }

    #[test]
    fn framing_rules() {
        assert_eq!(framing(&[0xAA]), Framing::NeedMore);
        assert_eq!(framing(&[0xAA, 0x01, 0x02, 0, 0]), Framing::Complete(5));
        assert_eq!(framing(&[0xAA, 0x42]), Framing::NotAFrame);
        assert_eq!(framing(&[0xAA, 0x02]), Framing::NotAFrame);
        assert_eq!(
            framing(&[0xAA, 0x1B, 0x07]),
            Framing::BadLength {
                command: 0x1B,
                pl: 7
            }
        );
        assert_eq!(
            framing(&[0xAA, 0x07, 0x40]),
            Framing::BadLength {
                command: 0x07,
                pl: 0x40
            }
        );
        assert_eq!(framing(&[0xAA, 0x03, 0x0A]), Framing::Short(15));
    }
}
