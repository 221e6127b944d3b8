//! `Response::decode_into` (the link's in-place path) answers exactly as
//! `Response::decode`, value or error, for every kind of request and frame.
#![allow(clippy::unwrap_used, clippy::indexing_slicing, clippy::panic)]

use protocol_core::frame::{NackCode, Payload};
use protocol_core::request::Request;
use protocol_core::response::Response;
use protocol_core::Frame;

fn data(command: u8, payload: &[u8]) -> Frame {
    Frame::Data {
        command,
        payload: Payload::from_slice(payload).unwrap(),
        packets: 1,
    }
}

fn same(request: &Request, frame: &Frame) {
    let expected = Response::decode(request, frame);
    // Start from a value of another kind: decode_into must overwrite it.
    let mut out = Response::PackVoltage(1.5);
    let got = Response::decode_into(request, frame, &mut out);
    match expected {
        Ok(v) => {
            assert_eq!(got, Ok(()), "{request:?} / {frame:?}");
            assert_eq!(out, v, "{request:?} / {frame:?}");
        }
        Err(e) => assert_eq!(got, Err(e), "{request:?} / {frame:?}"),
    }
}

#[test]
fn decode_into_matches_decode() {
    let bytes: Vec<u8> = (0..=255u8).map(|b| b.wrapping_mul(37)).collect();
    let requests = [
        Request::read_registers(0, 56).unwrap(),
        Request::read_registers(100, 18).unwrap(),
        Request::read_registers_native(0, 127).unwrap(),
        Request::read_individual(&[1, 2, 3]).unwrap(),
        Request::ReadNewestEvents,
        Request::ReadVersion,
    ];
    for request in &requests {
        for command in [0x03, 0x07, 0x09, 0x11, 0x1E] {
            for len in [0, 1, 36, 111, 112, 113, 254] {
                same(request, &data(command, &bytes[..len]));
            }
            same(request, &Frame::Ack { command });
            same(
                request,
                &Frame::Nack {
                    command,
                    code: NackCode::CrcError,
                },
            );
        }
    }
}
