//! Fuzz target: the streaming decoder, the typed response decoder and the request
//! parser on arbitrary bytes.
//!
//! Input layout:
//! * byte 0 — chunk size for feeding the decoder (0 means byte at a time);
//! * byte 1 — bits 0-4 pick the outstanding request from [`request`], bit 7 also
//!   announces it to the decoder with `Decoder::expect`;
//! * the rest — the received byte stream.
//!
//! Invariants checked (beyond "never panics, never stalls"):
//! * every input byte is accounted for, nothing stays buffered after `flush`;
//! * every frame the decoder returns is encodable, fits in the input, and its
//!   encoding decodes back to the same command and payload;
//! * a frame `Response::decode` accepts re-encodes (`to_frame`) to the same payload
//!   (0x1E/0x1F: a prefix, they tolerate trailing bytes);
//! * whatever `Request::parse` accepts encodes back to exactly the same bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use protocol_core::command as cmd;
use protocol_core::decoder::decode_all;
use protocol_core::frame::MAX_FRAME_LEN;
use protocol_core::request::{ResetOption, SettingsOption};
use protocol_core::{Decoder, Frame, Request, Response};

/// The outstanding request, from a selector byte: one of every kind, with the
/// sizes a client really uses (and the limits).
fn request(sel: u8) -> Request {
    let r = match sel & 0x1F {
        0 => Request::read_registers(0, 56),
        1 => Request::read_registers(0, 127),
        2 => Request::read_registers_native(0, 45),
        3 => Request::read_registers_native(0, 127),
        4 => Request::read_registers_native(300, 31),
        5 => Request::read_individual(&[36, 37, 38, 39, 46, 47]),
        6 => Request::read_individual(&[0; 31]),
        7 => Request::write_registers(315, &[4200, 2500]),
        8 => Request::write_registers_native(300, &[3650]),
        9 => Request::write_individual(&[(342, 4), (343, 1)]),
        10 => Request::read_settings(SettingsOption::Current, 44),
        11 => Request::read_settings(SettingsOption::Max, 100),
        12 => Ok(Request::ResetClear(ResetOption::ClearEvents)),
        13 => Ok(Request::ReadNewestEvents),
        14 => Ok(Request::ReadAllEvents),
        15 => Ok(Request::ReadPackVoltage),
        16 => Ok(Request::ReadPackCurrent),
        17 => Ok(Request::ReadMaxCellVoltage),
        18 => Ok(Request::ReadMinCellVoltage),
        19 => Ok(Request::ReadOnlineStatus),
        20 => Ok(Request::ReadLifetime),
        21 => Ok(Request::ReadSoc),
        22 => Ok(Request::ReadTemperatures),
        23 => Ok(Request::ReadCellVoltages),
        24 => Ok(Request::ReadVersion),
        25 => Ok(Request::ReadExtendedVersion),
        26 => Ok(Request::ReadSpeedDistanceTime),
        27 => Request::read_registers(100, 18),
        28 => Request::read_registers(200, 98),
        29 => Request::read_registers(500, 10),
        30 => Request::write_registers(300, &[0; 100]),
        _ => Request::read_individual(&[0xFFFF]),
    };
    r.unwrap_or(Request::ReadSoc)
}

fn payload(f: &Frame) -> &[u8] {
    match f {
        Frame::Data { payload, .. } => payload,
        _ => &[],
    }
}

fn check_frame(f: &Frame, req: &Request, input_len: usize) {
    // Encodable, and no longer than the input it came from.
    let len = f.encoded_len().expect("decoded frame must be encodable");
    assert!(
        len <= input_len,
        "frame of {len} bytes from {input_len} input bytes"
    );
    let mut buf = [0u8; 2 * MAX_FRAME_LEN];
    let n = f.encode(&mut buf).expect("encode");
    assert_eq!(n, len);
    // Re-encoding decodes to the same frame (the packet count may differ: a reply
    // received as 63 + 0 bytes re-encodes as one 63-byte packet).
    let mut again = Vec::new();
    decode_all(&buf[..n], |r| again.push(r));
    assert_eq!(again.len(), 1, "{f:?} -> {:02X?} -> {again:?}", &buf[..n]);
    let g = again[0].as_ref().expect("re-encoded frame must decode");
    assert_eq!(g.command(), f.command());
    assert_eq!(payload(g), payload(f));
    assert_eq!(std::mem::discriminant(g), std::mem::discriminant(f));

    // Typed decoding: what is accepted re-encodes to the same payload.
    if let Ok(resp) = Response::decode(req, f) {
        let back = resp
            .to_frame(req)
            .expect("accepted response must re-encode");
        assert_eq!(back.command(), f.command());
        match f {
            Frame::Data { command, .. }
                if *command == cmd::READ_VERSION || *command == cmd::READ_EXTENDED_VERSION =>
            {
                assert!(payload(f).starts_with(payload(&back)));
            }
            Frame::Data { .. } => assert_eq!(payload(&back), payload(f)),
            _ => assert_eq!(&back, f),
        }
    }
}

fn check_request_parse(bytes: &[u8]) {
    let _ = Request::frame_len(bytes);
    if let Ok(req) = Request::parse(bytes) {
        assert_eq!(req.validate(), Ok(()));
        let again = req.to_bytes().expect("parsed request must encode");
        assert_eq!(again.as_slice(), bytes, "{req:?}");
    }
}

fuzz_target!(|data: &[u8]| {
    check_request_parse(data);
    let [chunk, sel, stream @ ..] = data else {
        return;
    };
    check_request_parse(stream);

    let chunk = usize::from(*chunk).max(1);
    let req = request(*sel);
    let mut dec = Decoder::new();
    if sel & 0x80 != 0 {
        dec.expect(&req);
    }

    let mut frames = 0usize;
    for piece in stream.chunks(chunk) {
        let mut rest = piece;
        while !rest.is_empty() {
            let n = dec.push(rest);
            rest = &rest[n..];
            while let Some(r) = dec.poll() {
                if let Ok(f) = r {
                    frames += 1;
                    check_frame(&f, &req, stream.len());
                }
            }
            assert!(
                n > 0 || dec.buffered() < MAX_FRAME_LEN,
                "decoder stalled with a full buffer"
            );
        }
    }
    let mut guard = 0usize;
    while let Some(r) = dec.flush() {
        if let Ok(f) = r {
            frames += 1;
            check_frame(&f, &req, stream.len());
        }
        guard += 1;
        assert!(guard <= 2 * stream.len() + 2, "flush does not terminate");
    }

    assert_eq!(dec.buffered(), 0);
    assert!(!dec.in_packets());
    let st = dec.stats();
    assert_eq!(st.bytes_in as usize, stream.len());
    assert_eq!(st.frames as usize, frames);
    assert!(st.skipped_bytes as usize <= stream.len());
});
