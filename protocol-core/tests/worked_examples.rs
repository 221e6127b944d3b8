//! Every worked example of Rev D §1.3 and of the French reference guide
//! (`000_7ec840d42bb9f71b.txt`), byte for byte, in both directions: the typed
//! request/response encodes to the documented bytes, and the documented bytes
//! decode to the documented values. Where the guide omits the CRC, it is computed;
//! where it is wrong, the correction is stated.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

use protocol_core::crc::crc16;
use protocol_core::decoder::decode_all;
use protocol_core::events::{Event, EventId, OnlineStatus};
use protocol_core::frame::Frame;
use protocol_core::request::{Request, ResetOption};
use protocol_core::response::{
    EventList, ExtendedVersion, RegisterBlock, Response, Temperatures, Version,
};

fn with_crc(body: &[u8]) -> Vec<u8> {
    let mut v = body.to_vec();
    v.extend_from_slice(&crc16(body).to_le_bytes());
    v
}

fn encode(resp: &Response, req: &Request) -> Vec<u8> {
    let mut b = [0u8; 600];
    let n = resp.to_frame(req).unwrap().encode(&mut b).unwrap();
    b[..n].to_vec()
}

/// Both directions: `req` encodes to `tx`; `resp` encodes to `rx`; `rx` decodes
/// (as the answer to `req`) to `resp`; `tx` parses back to `req`.
fn both_ways(req: Request, tx: &[u8], resp: Response, rx: &[u8]) {
    assert_eq!(req.to_bytes().unwrap().as_slice(), tx, "request bytes");
    assert_eq!(Request::parse(tx).unwrap(), req, "request parse");
    assert_eq!(encode(&resp, &req), rx, "response bytes");
    let mut frames = Vec::new();
    let stats = decode_all(rx, |f| frames.push(f.unwrap()));
    assert_eq!((frames.len(), stats.skipped_bytes), (1, 0));
    assert_eq!(
        Response::decode(&req, &frames[0]).unwrap(),
        resp,
        "response decode"
    );
}

fn block(start: u16, values: &[u16]) -> RegisterBlock {
    RegisterBlock {
        start,
        values: heapless::Vec::from_slice(values).unwrap(),
    }
}

#[test]
fn rev_d_1_3_1_modbus_write() {
    both_ways(
        Request::write_registers(315, &[4200, 2500]).unwrap(),
        &[
            0xAA, 0x10, 0x01, 0x3B, 0x00, 0x02, 0x04, 0x10, 0x68, 0x09, 0xC4, 0x19, 0x61,
        ],
        Response::WriteEcho {
            start: 315,
            count: 2,
        },
        &[0xAA, 0x10, 0x01, 0x3B, 0x00, 0x02, 0x28, 0x22],
    );
}

#[test]
fn rev_d_1_3_2_modbus_read() {
    both_ways(
        Request::read_registers(5, 5).unwrap(),
        &[0xAA, 0x03, 0x00, 0x05, 0x00, 0x05, 0x8C, 0x13],
        Response::Registers(block(5, &[38720, 38720, 38700, 38700, 38700])),
        &[
            0xAA, 0x03, 0x0A, 0x97, 0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C, 0x3E,
            0xC7,
        ],
    );
}

#[test]
fn rev_d_1_3_3_temperatures() {
    both_ways(
        Request::ReadTemperatures,
        &[0xAA, 0x1B, 0x3F, 0x1B],
        Response::Temperatures(Temperatures {
            internal_dc: 278,
            external1_dc: Some(276),
            external2_dc: Some(278),
        }),
        &[
            0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4E,
        ],
    );
}

#[test]
fn guide_0x07_read_block() {
    // "0xAA 0x07 0x05 0x05 0x00 [CRC]" / "0xAA 0x07 0x0A 0x40 0x97 ... [CRC]".
    both_ways(
        Request::read_registers_native(5, 5).unwrap(),
        &with_crc(&[0xAA, 0x07, 0x05, 0x05, 0x00]),
        Response::Registers(block(5, &[38720, 38720, 38700, 38700, 38700])),
        &with_crc(&[
            0xAA, 0x07, 0x0A, 0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C, 0x97,
        ]),
    );
}

#[test]
fn guide_0x14_request_corrected() {
    // The guide prints AA 14 3F 1B; 3F 1B is the CRC of AA 1B. AA 14 is 0x1F7F.
    assert_eq!(
        Request::ReadPackVoltage.to_bytes().unwrap().as_slice(),
        &[0xAA, 0x14, 0x7F, 0x1F]
    );
    assert!(Request::parse(&[0xAA, 0x14, 0x3F, 0x1B]).is_err());
    // HARDWARE-NOTES: 0x1EB8, 0x425F = 55.78 V, one little-endian f32 natively.
    let rx = with_crc(&[0xAA, 0x14, 0xB8, 0x1E, 0x5F, 0x42]);
    let resp = Response::PackVoltage(f32::from_bits(0x425F_1EB8));
    assert_eq!(encode(&resp, &Request::ReadPackVoltage), rx);
}

#[test]
fn guide_example_4_online_status() {
    for (byte, status) in [
        (0x91, OnlineStatus::Charging),
        (0x93, OnlineStatus::Discharging),
        (0x9B, OnlineStatus::Fault),
    ] {
        both_ways(
            Request::ReadOnlineStatus,
            &with_crc(&[0xAA, 0x18]),
            Response::OnlineStatus(status),
            &with_crc(&[0xAA, 0x18, byte, 0x00]),
        );
    }
}

#[test]
fn guide_example_5_events_in_the_uart_layout() {
    // The guide splits the reply into CAN-style messages; on the UART it is one
    // frame: BMS timestamp, then 3-byte timestamp + ID per event (Rev D §1.1.9).
    let payload = [
        0x00, 0x2A, 0x3B, 0x00, 0x10, 0x28, 0x3B, 0x62, 0x50, 0x29, 0x3B, 0x63,
    ];
    let mut body = vec![0xAA, 0x11, 0x0C];
    body.extend_from_slice(&payload);
    let events = heapless::Vec::from_slice(&[
        Event {
            timestamp_s: 0x3B2810,
            id: EventId::ChargingStarted,
        },
        Event {
            timestamp_s: 0x3B2950,
            id: EventId::ChargingDone,
        },
    ])
    .unwrap();
    both_ways(
        Request::ReadNewestEvents,
        &with_crc(&[0xAA, 0x11]),
        Response::Events(EventList {
            bms_timestamp_s: 3_877_376,
            events,
        }),
        &with_crc(&body),
    );
}

#[test]
fn guide_example_6_soc() {
    // Bytes 00 24 F4 01 are 0x01F42400 = 32 777 216 (32.777216 %); the guide's
    // "= 32800000 = 32.8 %" is an arithmetic slip.
    both_ways(
        Request::ReadSoc,
        &with_crc(&[0xAA, 0x1A]),
        Response::Soc(0x01F4_2400),
        &with_crc(&[0xAA, 0x1A, 0x00, 0x24, 0xF4, 0x01]),
    );
}

#[test]
fn guide_example_7_clear_statistics() {
    both_ways(
        Request::ResetClear(ResetOption::ClearStatistics),
        &with_crc(&[0xAA, 0x02, 0x02]),
        Response::Ack { command: 0x02 },
        &with_crc(&[0xAA, 0x01, 0x02]),
    );
}

#[test]
fn guide_example_8_extended_version() {
    // The guide declares PL = 0x08 over 7 data bytes; Rev D's layout is 7 bytes.
    let resp = Response::ExtendedVersion(ExtendedVersion {
        version: Version {
            hardware: 1,
            hardware_changes: 0,
            firmware_public: 0x14,
            firmware_internal: 0x3A,
        },
        bootloader: 2,
        register_map: 5,
    });
    both_ways(
        Request::ReadExtendedVersion,
        &with_crc(&[0xAA, 0x1F]),
        resp.clone(),
        &with_crc(&[0xAA, 0x1F, 0x07, 0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05]),
    );
    // As printed (PL 8, 7 bytes, then a CRC): not a valid frame, never a value.
    let printed = with_crc(&[0xAA, 0x1F, 0x08, 0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05]);
    let mut oks = 0;
    decode_all(&printed, |f| oks += usize::from(f.is_ok()));
    assert_eq!(oks, 0);
    // With an eighth byte the reply is accepted, the extra byte ignored.
    let eight = Frame::data(0x1F, &[0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05, 0xEE]).unwrap();
    assert_eq!(
        Response::decode(&Request::ReadExtendedVersion, &eight).unwrap(),
        resp
    );
}
