//! Improv Wi-Fi's serial packets (improv-wifi.com, "Improv via Serial",
//! protocol version 1), both ways:
//!
//! ```text
//! offset  0..6   "IMPROV"
//!         6      version (1)
//!         7      type: 0x01 current state, 0x02 error state (bridge → host),
//!                      0x03 RPC command (host → bridge), 0x04 RPC result (bridge → host)
//!         8      length of the data, n
//!         9..9+n data
//!         9+n    checksum: the low byte of the sum of every byte before it
//! ```
//!
//! Both sides follow a packet with `\n` (the host's reader looks for
//! `IMPROV` only at the start of a line). An RPC command's data is the
//! command, the length of what follows, then its arguments; an RPC result's
//! is the command it answers, the length of what follows, then strings,
//! each a length byte and its bytes.
//!
//! [`parse`] never panics and takes nothing it cannot check: a wrong
//! checksum, version or type, a length that disagrees with the bytes, or
//! arguments that overrun the command are errors, never a command.

use heapless::Vec;

/// The first six bytes of every packet.
pub const HEADER: &[u8; 6] = b"IMPROV";

/// The protocol version this bridge speaks.
pub const VERSION: u8 = 1;

/// Longest packet, bytes: header, version, type, length, 255 bytes of data,
/// checksum.
pub const PACKET_MAX: usize = HEADER.len() + 3 + 255 + 1;

/// A packet for the host, `\n` included.
pub type Packet = Vec<u8, { PACKET_MAX + 1 }>;

/// Packet types.
mod kind {
    pub const CURRENT_STATE: u8 = 0x01;
    pub const ERROR_STATE: u8 = 0x02;
    pub const RPC: u8 = 0x03;
    pub const RPC_RESULT: u8 = 0x04;
}

/// RPC commands (the first byte of an RPC's data).
pub mod command {
    /// Send Wi-Fi settings: SSID and passphrase.
    pub const WIFI_SETTINGS: u8 = 0x01;
    /// Request the current state (and, when provisioned, the URLs).
    pub const CURRENT_STATE: u8 = 0x02;
    /// Request device information.
    pub const DEVICE_INFO: u8 = 0x03;
    /// Request the Wi-Fi networks in range.
    pub const SCAN: u8 = 0x04;
}

/// The provisioning state, as the host is told it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum State {
    /// This image has no Wi-Fi: nothing can be provisioned (0x00, which
    /// ESP Web Tools shows as "Wi-Fi turned off").
    Stopped,
    /// Ready for credentials (0x02).
    Ready,
    /// Credentials received: joining (0x03).
    Provisioning,
    /// Joined the network (0x04).
    Provisioned,
}

impl State {
    /// The byte on the wire.
    pub const fn code(self) -> u8 {
        match self {
            Self::Stopped => 0x00,
            Self::Ready => 0x02,
            Self::Provisioning => 0x03,
            Self::Provisioned => 0x04,
        }
    }
}

/// Errors the host is told (error state packets).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ErrorState {
    /// No error (sent when a new command starts).
    None,
    /// The packet was malformed: checksum, version, type or lengths (0x01).
    InvalidRpc,
    /// A command this bridge does not know or does not do (0x02).
    UnknownCommand,
    /// The network could not be joined: not found, the key refused, no
    /// address (0x03).
    UnableToConnect,
}

impl ErrorState {
    /// The byte on the wire.
    pub const fn code(self) -> u8 {
        match self {
            Self::None => 0x00,
            Self::InvalidRpc => 0x01,
            Self::UnknownCommand => 0x02,
            Self::UnableToConnect => 0x03,
        }
    }
}

/// A command from the host.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rpc<'a> {
    /// Join this network with this passphrase (empty: an open network).
    WifiSettings {
        /// The network's name, as sent.
        ssid: &'a [u8],
        /// The passphrase, as sent.
        passphrase: &'a [u8],
    },
    /// What is the state?
    CurrentState,
    /// Who are you?
    DeviceInfo,
    /// Which networks are in range?
    Scan,
    /// Any other command (its number).
    Other(u8),
}

/// Why a packet is not a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PacketError {
    /// Shorter than a packet can be, or its length byte disagrees with the
    /// bytes received.
    Length,
    /// Not the `IMPROV` header.
    Header,
    /// Not version 1.
    Version,
    /// The checksum does not match.
    Checksum,
    /// Not an RPC command (a host sends nothing else).
    NotRpc,
    /// The command's own length, or its arguments' lengths, overrun its data.
    Arguments,
}

impl PacketError {
    /// In words, for the log.
    pub const fn text(self) -> &'static str {
        match self {
            Self::Length => "its length does not match its bytes",
            Self::Header => "no IMPROV header",
            Self::Version => "not version 1",
            Self::Checksum => "wrong checksum",
            Self::NotRpc => "not an RPC command",
            Self::Arguments => "its arguments overrun the command",
        }
    }
}

/// The checksum of `bytes` (the low byte of their sum).
pub fn checksum(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |s, b| s.wrapping_add(*b))
}

/// Reads one whole packet (without a trailing `\n`).
pub fn parse(packet: &[u8]) -> Result<Rpc<'_>, PacketError> {
    let head = packet.get(..HEADER.len()).ok_or(PacketError::Length)?;
    if head != HEADER {
        return Err(PacketError::Header);
    }
    let (&version, &ty, &len) = match packet.get(6..9) {
        Some([v, t, l]) => (v, t, l),
        _ => return Err(PacketError::Length),
    };
    if packet.len() != 9 + usize::from(len) + 1 {
        return Err(PacketError::Length);
    }
    let (body, sum) = packet.split_at(packet.len() - 1);
    if sum != [checksum(body)] {
        return Err(PacketError::Checksum);
    }
    if version != VERSION {
        return Err(PacketError::Version);
    }
    if ty != kind::RPC {
        return Err(PacketError::NotRpc);
    }
    let data = body.get(9..).unwrap_or(&[]);
    let (&cmd, &args_len, args) = match data {
        [c, l, rest @ ..] => (c, l, rest),
        _ => return Err(PacketError::Arguments),
    };
    let args = args
        .get(..usize::from(args_len))
        .ok_or(PacketError::Arguments)?;
    Ok(match cmd {
        command::WIFI_SETTINGS => {
            let (ssid, rest) = string(args)?;
            let (passphrase, rest) = string(rest)?;
            if !rest.is_empty() {
                return Err(PacketError::Arguments);
            }
            Rpc::WifiSettings { ssid, passphrase }
        }
        command::CURRENT_STATE => Rpc::CurrentState,
        command::DEVICE_INFO => Rpc::DeviceInfo,
        command::SCAN => Rpc::Scan,
        other => Rpc::Other(other),
    })
}

/// A length-prefixed string and what follows it.
fn string(b: &[u8]) -> Result<(&[u8], &[u8]), PacketError> {
    let (&n, rest) = b.split_first().ok_or(PacketError::Arguments)?;
    let n = usize::from(n);
    if rest.len() < n {
        return Err(PacketError::Arguments);
    }
    Ok(rest.split_at(n))
}

/// A packet of `ty` around `data` (at most 255 bytes; longer data is cut).
fn packet(ty: u8, data: &[u8]) -> Packet {
    let data = data.get(..255).unwrap_or(data);
    let mut p = Packet::new();
    let _ = p.extend_from_slice(HEADER);
    let _ = p.push(VERSION);
    let _ = p.push(ty);
    let _ = p.push(data.len() as u8);
    let _ = p.extend_from_slice(data);
    let sum = checksum(&p);
    let _ = p.push(sum);
    let _ = p.push(b'\n');
    p
}

/// "The state is `s`."
pub fn current_state(s: State) -> Packet {
    packet(kind::CURRENT_STATE, &[s.code()])
}

/// "The error is `e`."
pub fn error_state(e: ErrorState) -> Packet {
    packet(kind::ERROR_STATE, &[e.code()])
}

/// The result of `command`: these strings, each cut to fit (the whole result
/// holds at most 253 bytes of strings; strings that do not fit are left out).
pub fn result(command: u8, strings: &[&[u8]]) -> Packet {
    let mut data: Vec<u8, 255> = Vec::new();
    let _ = data.push(command);
    let _ = data.push(0);
    for s in strings {
        let s = s.get(..usize::from(u8::MAX)).unwrap_or(s);
        if data.len() + 1 + s.len() > data.capacity() {
            break;
        }
        let _ = data.push(s.len() as u8);
        let _ = data.extend_from_slice(s);
    }
    let total = (data.len() - 2) as u8;
    if let Some(l) = data.get_mut(1) {
        *l = total;
    }
    packet(kind::RPC_RESULT, &data)
}
