//! # protocol-core
//!
//! The TinyBMS (Energus/Enepaq s516) UART protocol, Revision D, for `no_std`
//! targets without an allocator.
//!
//! * [`crc`] — CRC-16/MODBUS from a compile-time table.
//! * [`request`] — every request of Rev D chapter 1, validated and encoded.
//! * [`frame`] / [`decoder`] — response framing and the streaming decoder
//!   (resynchronisation, multi-packet reassembly, ASCII broadcasts skipped).
//! * [`response`] — responses decoded into typed values, checked against the
//!   request they answer.
//! * [`registers`] — the register map of Rev D chapter 3 as data.
//! * [`views`], [`settings`], [`events`] — typed views over the map.
//!
//! ## No-panic contract
//! No function of this crate panics on any input bytes. `clippy::unwrap_used`,
//! `expect_used`, `panic` and `indexing_slicing` are denied outside tests; the
//! few local exceptions index fixed-size tables with a `u8` and say so.
//!
//! ## Example
//! ```
//! use protocol_core::{decoder::Decoder, request::Request, response::Response};
//! let req = Request::read_registers(5, 5)?;               // 0x03, cells 6-10
//! assert_eq!(req.to_bytes()?.as_slice(), &[0xAA, 0x03, 0x00, 0x05, 0x00, 0x05, 0x8C, 0x13]);
//!
//! let rx = [0xAA, 0x03, 0x0A, 0x97, 0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C, 0x3E, 0xC7];
//! let mut dec = Decoder::new();
//! assert_eq!(dec.push(&rx), rx.len()); // bounded buffer: push says how much it took
//! let frame = dec.poll().unwrap()?;
//! let Response::Registers(block) = Response::decode(&req, &frame)? else { unreachable!() };
//! assert_eq!(block.get(5), Some(38720)); // 0.1 mV: 3.872 V
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![no_std]
#![deny(missing_docs)]
// Frames and responses hold their payload inline (no allocator): the data variants
// are deliberately larger than ACK/NACK.
#![allow(clippy::large_enum_variant)]
#![cfg_attr(
    test,
    allow(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing
    )
)]

pub mod command;
pub mod crc;
pub mod decoder;
pub mod events;
pub mod frame;
pub mod registers;
pub mod request;
pub mod response;
pub mod settings;
pub mod views;

pub use decoder::{DecodeError, Decoder, DecoderStats};
pub use frame::{Frame, FrameRef, NackCode};
pub use request::{Request, RequestError};
pub use response::{Response, ResponseError};

macro_rules! display_via_debug {
    ($($t:ty),*) => {$(
        impl core::fmt::Display for $t {
            fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
                core::fmt::Debug::fmt(self, f)
            }
        }
        impl core::error::Error for $t {}
    )*};
}
display_via_debug!(
    DecodeError,
    RequestError,
    ResponseError,
    frame::EncodeError,
    settings::SettingError,
    views::MissingRegisters
);
