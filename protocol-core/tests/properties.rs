//! Property tests for protocol-core: request and response round trips, the
//! streaming decoder against noise, chunking and corruption, and "never panics"
//! on arbitrary input.
//!
//! Every property runs [`CASES`] cases (`PROPTEST_CASES` overrides); the whole file takes a few seconds in the
//! workspace test profile (opt-level 1, proptest itself at opt-level 3).
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

use proptest::prelude::*;
use proptest::sample::{select, Index};
use protocol_core::command::{self as cmd, is_packetized};
use protocol_core::crc::crc16;
use protocol_core::decoder::decode_all;
use protocol_core::events::{Event, EventId, OnlineStatus};
use protocol_core::frame::{MAX_PACKET_PAYLOAD, MAX_PAYLOAD};
use protocol_core::registers::{self as regs, MAX_CELLS};
use protocol_core::request::{
    AddressList, BlockValues, NativeBlockValues, ResetOption, SettingsOption, WritePairs,
};
use protocol_core::response::{
    sensor, EventList, ExtendedVersion, RegisterBlock, Temperatures, Version, Words, MAX_EVENTS,
};
use protocol_core::settings::{Setting, SettingId};
use protocol_core::views::{self, Cells, LiveSnapshot, Statistics, VersionInfo};
use protocol_core::{DecodeError, Decoder, Frame, NackCode, Request, RequestError, Response};

/// Cases per property, unless `PROPTEST_CASES` says otherwise (for a longer soak).
const CASES: u32 = 256;

fn config() -> ProptestConfig {
    let cases = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(CASES);
    ProptestConfig {
        cases,
        // Failures are turned into named regression tests below, not files.
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

// ---------------------------------------------------------------------------
// Strategies
// ---------------------------------------------------------------------------

fn reset_option() -> impl Strategy<Value = ResetOption> {
    prop_oneof![
        Just(ResetOption::ClearEvents),
        Just(ResetOption::ClearStatistics),
        Just(ResetOption::ResetBms),
    ]
}

fn settings_option() -> impl Strategy<Value = SettingsOption> {
    prop_oneof![
        Just(SettingsOption::Min),
        Just(SettingsOption::Max),
        Just(SettingsOption::Default),
        Just(SettingsOption::Current),
    ]
}

/// `count` in `1..=max` and a start such that the span stays within 0..=0xFFFF.
fn span(max: usize) -> impl Strategy<Value = (u16, usize)> {
    (1..=max).prop_flat_map(|count| {
        let last_start = (0x1_0000 - count) as u32;
        (
            prop_oneof![0..=last_start, Just(0), Just(last_start)],
            Just(count),
        )
            .prop_map(|(start, count)| (start as u16, count))
    })
}

/// `count` in `1..=max` and a start such that the whole span is writable (300..=399).
fn writable_span(max: usize) -> impl Strategy<Value = (u16, usize)> {
    (1..=max).prop_flat_map(|count| (300u16..=(400 - count as u16), Just(count)))
}

/// Every valid request, built through the validated constructors.
fn arb_request() -> impl Strategy<Value = Request> {
    prop_oneof![
        reset_option().prop_map(Request::ResetClear),
        span(cmd::MAX_READ_MODBUS).prop_map(|(s, c)| Request::read_registers(s, c).unwrap()),
        span(cmd::MAX_READ_NATIVE).prop_map(|(s, c)| Request::read_registers_native(s, c).unwrap()),
        prop::collection::vec(any::<u16>(), 1..=cmd::MAX_READ_INDIVIDUAL)
            .prop_map(|a| Request::read_individual(&a).unwrap()),
        writable_span(cmd::MAX_WRITE_NATIVE).prop_flat_map(|(s, c)| {
            prop::collection::vec(any::<u16>(), c)
                .prop_map(move |v| Request::write_registers_native(s, &v).unwrap())
        }),
        prop::collection::vec((300u16..=399, any::<u16>()), 1..=cmd::MAX_WRITE_INDIVIDUAL)
            .prop_map(|p| Request::write_individual(&p).unwrap()),
        writable_span(cmd::MAX_WRITE_MODBUS).prop_flat_map(|(s, c)| {
            prop::collection::vec(any::<u16>(), c)
                .prop_map(move |v| Request::write_registers(s, &v).unwrap())
        }),
        (settings_option(), 1..=cmd::MAX_READ_SETTINGS)
            .prop_map(|(o, c)| Request::read_settings(o, c).unwrap()),
        select(vec![
            Request::ReadNewestEvents,
            Request::ReadAllEvents,
            Request::ReadPackVoltage,
            Request::ReadPackCurrent,
            Request::ReadMaxCellVoltage,
            Request::ReadMinCellVoltage,
            Request::ReadOnlineStatus,
            Request::ReadLifetime,
            Request::ReadSoc,
            Request::ReadTemperatures,
            Request::ReadCellVoltages,
            Request::ReadVersion,
            Request::ReadExtendedVersion,
            Request::ReadSpeedDistanceTime,
        ]),
    ]
}

/// Any address, biased towards the writable window and the top of the map.
fn address() -> impl Strategy<Value = u16> {
    prop_oneof![
        any::<u16>(),
        290u16..=410,
        0xFFF0u16..=0xFFFF,
        Just(0u16),
        Just(299u16),
        Just(400u16),
    ]
}

/// Requests built directly (no validation): valid or not, every field arbitrary.
fn arb_raw_request() -> impl Strategy<Value = Request> {
    prop_oneof![
        arb_request(),
        (address(), any::<u8>()).prop_map(|(start, count)| Request::ReadRegisters { start, count }),
        (address(), any::<u8>())
            .prop_map(|(start, count)| Request::ReadRegistersNative { start, count }),
        prop::collection::vec(any::<u16>(), 0..=cmd::MAX_READ_INDIVIDUAL)
            .prop_map(|a| Request::ReadIndividual(AddressList::from_slice(&a).unwrap())),
        (
            address(),
            prop::collection::vec(any::<u16>(), 0..=cmd::MAX_WRITE_NATIVE)
        )
            .prop_map(|(start, v)| Request::WriteRegistersNative {
                start,
                values: NativeBlockValues::from_slice(&v).unwrap(),
            }),
        prop::collection::vec((address(), any::<u16>()), 0..=cmd::MAX_WRITE_INDIVIDUAL)
            .prop_map(|p| Request::WriteIndividual(WritePairs::from_slice(&p).unwrap())),
        (
            address(),
            prop::collection::vec(any::<u16>(), 0..=cmd::MAX_WRITE_MODBUS)
        )
            .prop_map(|(start, v)| Request::WriteRegisters {
                start,
                values: BlockValues::from_slice(&v).unwrap(),
            }),
        (settings_option(), any::<u8>())
            .prop_map(|(option, count)| Request::ReadSettings { option, count }),
    ]
}

fn nack_code() -> impl Strategy<Value = NackCode> {
    // Through `from_u8`, the canonical form (`Unknown(0)` would encode as 0x00 and
    // come back as `CommandError`).
    any::<u8>().prop_map(NackCode::from_u8)
}

fn block(start: u16, count: usize) -> impl Strategy<Value = RegisterBlock> {
    prop::collection::vec(any::<u16>(), count).prop_map(move |v| RegisterBlock {
        start,
        values: Words::from_slice(&v).unwrap(),
    })
}

fn event() -> impl Strategy<Value = Event> {
    (0..=Event::MAX_TIMESTAMP, any::<u8>()).prop_map(|(timestamp_s, id)| Event {
        timestamp_s,
        id: EventId::from_raw(id),
    })
}

fn events(n: std::ops::RangeInclusive<usize>) -> impl Strategy<Value = Response> {
    (any::<u32>(), prop::collection::vec(event(), n)).prop_map(|(ts, ev)| {
        Response::Events(EventList {
            bms_timestamp_s: ts,
            events: heapless::Vec::from_slice(&ev).unwrap(),
        })
    })
}

fn version() -> impl Strategy<Value = Version> {
    (any::<u8>(), any::<u8>(), any::<u8>(), any::<u16>()).prop_map(|(h, hc, fp, fi)| Version {
        hardware: h,
        hardware_changes: hc,
        firmware_public: fp,
        firmware_internal: fi,
    })
}

/// The data response a BMS could send to `req` (for data requests).
fn data_response(req: &Request) -> BoxedStrategy<Response> {
    match req.clone() {
        Request::ReadRegisters { start, count } | Request::ReadRegistersNative { start, count } => {
            block(start, count as usize)
                .prop_map(Response::Registers)
                .boxed()
        }
        Request::ReadSettings { option, count } => {
            block(cmd::SETTINGS_FIRST_REGISTER, count as usize)
                .prop_map(move |values| Response::Settings { option, values })
                .boxed()
        }
        Request::ReadIndividual(addresses) => prop::collection::vec(any::<u16>(), addresses.len())
            .prop_map(move |v| {
                let pairs: Vec<(u16, u16)> =
                    addresses.iter().copied().zip(v.iter().copied()).collect();
                Response::Individual(heapless::Vec::from_slice(&pairs).unwrap())
            })
            .boxed(),
        Request::WriteRegisters { start, values } => Just(Response::WriteEcho {
            start,
            count: values.len() as u8,
        })
        .boxed(),
        Request::ReadNewestEvents | Request::ReadAllEvents => events(0..=MAX_EVENTS).boxed(),
        Request::ReadPackVoltage => any::<u32>()
            .prop_map(|b| Response::PackVoltage(f32::from_bits(b)))
            .boxed(),
        Request::ReadPackCurrent => any::<u32>()
            .prop_map(|b| Response::PackCurrent(f32::from_bits(b)))
            .boxed(),
        Request::ReadMaxCellVoltage => any::<u16>().prop_map(Response::MaxCellVoltage).boxed(),
        Request::ReadMinCellVoltage => any::<u16>().prop_map(Response::MinCellVoltage).boxed(),
        Request::ReadOnlineStatus => any::<u16>()
            .prop_map(|r| Response::OnlineStatus(OnlineStatus::from_raw(r)))
            .boxed(),
        Request::ReadLifetime => any::<u32>().prop_map(Response::Lifetime).boxed(),
        Request::ReadSoc => any::<u32>().prop_map(Response::Soc).boxed(),
        Request::ReadTemperatures => (
            any::<i16>(),
            prop_oneof![any::<i16>(), Just(i16::MIN)],
            prop_oneof![any::<i16>(), Just(i16::MIN)],
        )
            .prop_map(|(i, e1, e2)| {
                Response::Temperatures(Temperatures {
                    internal_dc: i,
                    external1_dc: sensor(e1),
                    external2_dc: sensor(e2),
                })
            })
            .boxed(),
        Request::ReadCellVoltages => prop::collection::vec(any::<u16>(), 0..=MAX_CELLS)
            .prop_map(|c| Response::CellVoltages(heapless::Vec::from_slice(&c).unwrap()))
            .boxed(),
        Request::ReadVersion => version().prop_map(Response::Version).boxed(),
        Request::ReadExtendedVersion => (version(), any::<u8>(), any::<u8>())
            .prop_map(|(version, bootloader, register_map)| {
                Response::ExtendedVersion(ExtendedVersion {
                    version,
                    bootloader,
                    register_map,
                })
            })
            .boxed(),
        Request::ReadSpeedDistanceTime => (any::<u32>(), any::<u32>(), any::<u32>())
            .prop_map(|(s, d, t)| Response::SpeedDistanceTime {
                speed_kmh: f32::from_bits(s),
                distance_left_km: d,
                time_left_s: t,
            })
            .boxed(),
        // ACK-only requests have no data response.
        Request::ResetClear(_)
        | Request::WriteRegistersNative { .. }
        | Request::WriteIndividual(_) => Just(Response::Ack {
            command: req.command(),
        })
        .boxed(),
    }
}

/// Any response consistent with `req`: its data reply (or ACK), or a NACK.
fn arb_response_for(req: &Request) -> BoxedStrategy<Response> {
    let command = req.command();
    prop_oneof![
        6 => data_response(req),
        1 => nack_code().prop_map(move |code| Response::Nack { command, code }),
    ]
    .boxed()
}

fn arb_exchange() -> impl Strategy<Value = (Request, Response)> {
    arb_request().prop_flat_map(|r| (Just(r.clone()), arb_response_for(&r)))
}

/// Requests whose replies are long enough to need several packets.
fn arb_multi_packet_exchange() -> impl Strategy<Value = (Request, Response)> {
    prop_oneof![
        (0u16..=0xFF00, 32usize..=cmd::MAX_READ_NATIVE)
            .prop_map(|(s, c)| Request::read_registers_native(s, c).unwrap()),
        prop::collection::vec(any::<u16>(), 16..=cmd::MAX_READ_INDIVIDUAL)
            .prop_map(|a| Request::read_individual(&a).unwrap()),
        Just(Request::ReadNewestEvents),
        Just(Request::ReadAllEvents),
    ]
    .prop_flat_map(|r| {
        let resp = match r {
            Request::ReadNewestEvents | Request::ReadAllEvents => {
                // 15 events (64 bytes) already need two packets; 49 is the whole
                // event log, 63 the most that fits MAX_PAYLOAD.
                prop_oneof![events(15..=MAX_EVENTS), events(49..=49), events(62..=63)].boxed()
            }
            _ => data_response(&r),
        };
        (Just(r), resp)
    })
}

/// Chunk sizes for feeding the decoder (cycled), sometimes byte by byte.
fn chunking() -> impl Strategy<Value = Vec<usize>> {
    prop_oneof![
        Just(vec![1usize]),
        prop::collection::vec(1usize..=8, 1..8),
        prop::collection::vec(1usize..=300, 1..12),
    ]
}

/// Bytes that never contain the preamble: ASCII broadcast lines of the kind
/// HARDWARE-NOTES describes, or random non-0xAA bytes.
fn noise() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        2 => Just(Vec::new()),
        2 => "[A-Z0-9:. -]{0,12}(\t[A-Z0-9:. -]{0,10}){0,6}"
            .prop_map(|s| format!("MST:\t{s}\r\n").into_bytes()),
        1 => Just(b"MST:\tEXT1:----\tEXT2:----\tOS:155\r\n".to_vec()),
        2 => prop::collection::vec(
            any::<u8>().prop_map(|b| if b == cmd::PREAMBLE { 0x55 } else { b }),
            1..24
        ),
    ]
}

/// A byte distribution that hits the framing rules often.
fn wire_byte() -> impl Strategy<Value = u8> {
    prop_oneof![
        4 => any::<u8>(),
        2 => Just(cmd::PREAMBLE),
        3 => select(vec![
            0x00u8, 0x01, 0x02, 0x03, 0x07, 0x09, 0x0B, 0x0D, 0x10, 0x11, 0x12, 0x14, 0x15, 0x16,
            0x18, 0x1A, 0x1B, 0x1C, 0x1D, 0x1E, 0x1F, 0x20, 0x3F, 0x40, 0x80, 0x81, 0x82, 0xBF,
            0xFF, 0x05, 0x06, 0x0A, 0x3E,
        ]),
    ]
}

// ---------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------

fn encode_frame(f: &Frame) -> Vec<u8> {
    let mut b = vec![0u8; 600];
    let n = f.encode(&mut b).unwrap();
    assert_eq!(f.encoded_len(), Ok(n));
    b.truncate(n);
    b
}

/// Wire packets of an encoded frame: 68-byte non-last packets, then the last.
fn packets(bytes: &[u8], f: &Frame) -> Vec<Vec<u8>> {
    let packetized = matches!(f, Frame::Data { command, .. } if is_packetized(*command));
    if !packetized {
        return vec![bytes.to_vec()];
    }
    let mut out = Vec::new();
    let mut rest = bytes;
    // A non-last packet has PL bit 7 set.
    while rest.len() > 2 && rest[2] & 0x80 != 0 {
        let (p, r) = rest.split_at(MAX_PACKET_PAYLOAD + 5);
        out.push(p.to_vec());
        rest = r;
    }
    out.push(rest.to_vec());
    out
}

/// `f` with `packets` set to the number of packets its encoding has, i.e. what
/// the decoder reports.
fn as_received(f: &Frame) -> Frame {
    match f {
        Frame::Data {
            command, payload, ..
        } => {
            let n = packets(&encode_frame(f), f).len();
            Frame::Data {
                command: *command,
                payload: payload.clone(),
                packets: n as u8,
            }
        }
        other => other.clone(),
    }
}

/// Feeds `bytes` in chunks of the (cycled) `sizes`, polling after every push, then
/// flushes. Fails instead of hanging if the decoder stops making progress. The
/// same bytes go through a copy of the decoder polled with `poll_ref`/`flush_ref`
/// (the link's way, frames lent from the buffer), and through a third copy
/// that receives straight into `spare` and `commit`s (the chip's way): every
/// answer, the counters and what stays buffered must be the same.
fn decode_chunked(
    dec: &mut Decoder,
    bytes: &[u8],
    sizes: &[usize],
) -> Vec<Result<Frame, DecodeError>> {
    let mut lending = dec.clone();
    let mut receiving = dec.clone();
    let out = decode_chunked_owned(dec, bytes, sizes);
    let lent = decode_chunked_lent(&mut lending, bytes, sizes, false);
    assert_eq!(lent, out, "poll_ref differs from poll");
    assert_eq!(lending.stats(), dec.stats(), "poll_ref counts differ");
    assert_eq!(lending.buffered(), dec.buffered());
    assert_eq!(lending.in_packets(), dec.in_packets());
    let received = decode_chunked_lent(&mut receiving, bytes, sizes, true);
    assert_eq!(received, out, "spare/commit differs from push");
    assert_eq!(receiving.stats(), dec.stats(), "spare/commit counts differ");
    assert_eq!(receiving.buffered(), dec.buffered());
    assert_eq!(receiving.in_packets(), dec.in_packets());
    out
}

fn owned(f: protocol_core::FrameRef<'_>) -> Frame {
    use protocol_core::FrameRef as R;
    match f {
        R::Ack { command } => Frame::Ack { command },
        R::Nack { command, code } => Frame::Nack { command, code },
        R::Data {
            command,
            payload,
            packets,
        } => Frame::Data {
            command,
            payload: protocol_core::frame::Payload::from_slice(payload).unwrap(),
            packets,
        },
    }
}

/// `bytes` in consecutive chunks of the (cycled) `sizes`, each at least 1 byte.
fn chunks<'a>(bytes: &'a [u8], sizes: &'a [usize]) -> impl Iterator<Item = &'a [u8]> {
    let mut rest = bytes;
    sizes.iter().cycle().map_while(move |&size| {
        if rest.is_empty() {
            return None;
        }
        let (chunk, r) = rest.split_at(size.clamp(1, rest.len()));
        rest = r;
        Some(chunk)
    })
}

/// Feeds as [`decode_chunked_owned`], polling with `poll_ref`/`flush_ref`. With
/// `in_place`, each chunk is written into `Decoder::spare` (as much as it holds)
/// and committed, the way the chip's UART driver hands bytes over; the spare
/// room must then never be empty after the polls (a reader given no room would
/// spin).
fn decode_chunked_lent(
    dec: &mut Decoder,
    bytes: &[u8],
    sizes: &[usize],
    in_place: bool,
) -> Vec<Result<Frame, DecodeError>> {
    let mut out = Vec::new();
    let mut spill = None;
    for mut chunk in chunks(bytes, sizes) {
        while !chunk.is_empty() {
            let n = if in_place {
                let spare = dec.spare();
                assert!(!spare.is_empty(), "no spare room after the polls");
                let n = spare.len().min(chunk.len());
                spare[..n].copy_from_slice(&chunk[..n]);
                assert_eq!(dec.commit(n), n);
                n
            } else {
                dec.push(chunk)
            };
            chunk = &chunk[n..];
            while let Some(r) = dec.poll_ref(&mut spill) {
                out.push(r.map(owned));
            }
        }
    }
    if in_place {
        assert!(!dec.spare().is_empty(), "no spare room after the polls");
    }
    let mut guard = 0;
    while let Some(r) = dec.flush_ref(&mut spill) {
        out.push(r.map(owned));
        guard += 1;
        assert!(guard < 10_000, "flush_ref never returned None");
    }
    out
}

fn decode_chunked_owned(
    dec: &mut Decoder,
    bytes: &[u8],
    sizes: &[usize],
) -> Vec<Result<Frame, DecodeError>> {
    let mut out = Vec::new();
    for mut chunk in chunks(bytes, sizes) {
        while !chunk.is_empty() {
            let n = dec.push(chunk);
            chunk = &chunk[n..];
            while let Some(r) = dec.poll() {
                out.push(r);
            }
            // Once the buffer is full, poll must have made room.
            assert!(
                n > 0 || dec.buffered() < protocol_core::frame::MAX_FRAME_LEN,
                "decoder stalled with a full buffer"
            );
        }
    }
    let mut guard = 0;
    while let Some(r) = dec.flush() {
        out.push(r);
        guard += 1;
        assert!(guard < 10_000, "flush never returned None");
    }
    out
}

/// Response equality with floats compared by bits (NaN payloads included).
fn same_response(a: &Response, b: &Response) -> bool {
    match (a, b) {
        (Response::PackVoltage(x), Response::PackVoltage(y))
        | (Response::PackCurrent(x), Response::PackCurrent(y)) => x.to_bits() == y.to_bits(),
        (
            Response::SpeedDistanceTime {
                speed_kmh: s1,
                distance_left_km: d1,
                time_left_s: t1,
            },
            Response::SpeedDistanceTime {
                speed_kmh: s2,
                distance_left_km: d2,
                time_left_s: t2,
            },
        ) => s1.to_bits() == s2.to_bits() && d1 == d2 && t1 == t2,
        _ => a == b,
    }
}

fn payload_of(f: &Frame) -> &[u8] {
    match f {
        Frame::Data { payload, .. } => payload,
        _ => &[],
    }
}

/// What validated constructors must answer for a block of `count` registers at
/// `start` (limits first, then the address span, then writability).
fn block_verdict(start: u16, count: usize, max: usize, writable: bool) -> Result<(), RequestError> {
    if count == 0 {
        return Err(RequestError::Empty);
    }
    if count > max {
        return Err(RequestError::TooMany { count, max });
    }
    if start as usize + count > 0x1_0000 {
        return Err(RequestError::AddressOverflow);
    }
    if writable {
        let last = (start as usize + count - 1) as u16;
        for a in [start, last] {
            if !cmd::WRITABLE.contains(&a) {
                return Err(RequestError::NotWritable { address: a });
            }
        }
    }
    Ok(())
}

/// The validated constructor's verdict for a request built directly.
fn request_verdict(r: &Request) -> Result<(), RequestError> {
    match r {
        Request::ReadRegisters { start, count } => {
            block_verdict(*start, *count as usize, cmd::MAX_READ_MODBUS, false)
        }
        Request::ReadRegistersNative { start, count } => {
            block_verdict(*start, *count as usize, cmd::MAX_READ_NATIVE, false)
        }
        Request::ReadIndividual(a) => block_verdict(0, a.len(), cmd::MAX_READ_INDIVIDUAL, false),
        Request::WriteRegistersNative { start, values } => {
            block_verdict(*start, values.len(), cmd::MAX_WRITE_NATIVE, true)
        }
        Request::WriteRegisters { start, values } => {
            block_verdict(*start, values.len(), cmd::MAX_WRITE_MODBUS, true)
        }
        Request::WriteIndividual(p) => {
            block_verdict(0, p.len(), cmd::MAX_WRITE_INDIVIDUAL, false)?;
            match p.iter().find(|(a, _)| !cmd::WRITABLE.contains(a)) {
                Some(&(address, _)) => Err(RequestError::NotWritable { address }),
                None => Ok(()),
            }
        }
        Request::ReadSettings { count, .. } => {
            block_verdict(0, *count as usize, cmd::MAX_READ_SETTINGS, false)
        }
        _ => Ok(()),
    }
}

/// Builds a stream of the given frames with noise at every frame boundary and
/// between the packets of multi-packet replies. Returns the bytes, the frames as
/// the decoder reports them, and the noise length.
fn noisy_stream(frames: &[Frame], noises: &[Vec<u8>]) -> (Vec<u8>, Vec<Frame>, usize) {
    let mut noises = noises.iter();
    let mut next_noise = |s: &mut Vec<u8>| -> usize {
        let n = noises.next().cloned().unwrap_or_default();
        s.extend_from_slice(&n);
        n.len()
    };
    let mut stream = Vec::new();
    let mut noise_len = 0;
    for f in frames {
        noise_len += next_noise(&mut stream);
        let bytes = encode_frame(f);
        let pk = packets(&bytes, f);
        for (i, p) in pk.iter().enumerate() {
            if i > 0 {
                noise_len += next_noise(&mut stream);
            }
            stream.extend_from_slice(p);
        }
    }
    noise_len += next_noise(&mut stream);
    let expected = frames.iter().map(as_received).collect();
    (stream, expected, noise_len)
}

#[derive(Debug, Clone)]
enum Corruption {
    FlipBit(Index, u8),
    Drop(Index),
    DropRun(Index, usize),
    Insert(Index, u8),
    InsertPreamble(Index),
}

fn corruption() -> impl Strategy<Value = Corruption> {
    prop_oneof![
        3 => (any::<Index>(), 0u8..8).prop_map(|(i, b)| Corruption::FlipBit(i, b)),
        2 => any::<Index>().prop_map(Corruption::Drop),
        1 => (any::<Index>(), 2usize..80).prop_map(|(i, n)| Corruption::DropRun(i, n)),
        2 => (any::<Index>(), wire_byte()).prop_map(|(i, b)| Corruption::Insert(i, b)),
        2 => any::<Index>().prop_map(Corruption::InsertPreamble),
    ]
}

fn corrupt(stream: &mut Vec<u8>, ops: &[Corruption]) {
    for op in ops {
        if stream.is_empty() {
            return;
        }
        match op {
            Corruption::FlipBit(i, bit) => {
                let i = i.index(stream.len());
                stream[i] ^= 1 << bit;
            }
            Corruption::Drop(i) => {
                stream.remove(i.index(stream.len()));
            }
            Corruption::DropRun(i, n) => {
                let i = i.index(stream.len());
                let end = (i + n).min(stream.len());
                stream.drain(i..end);
            }
            Corruption::Insert(i, b) => stream.insert(i.index(stream.len() + 1), *b),
            Corruption::InsertPreamble(i) => {
                stream.insert(i.index(stream.len() + 1), cmd::PREAMBLE)
            }
        }
    }
}

/// Decodes a corrupted stream and returns the Ok frames that were never sent.
fn invented_frames(
    originals: &[Frame],
    stream: &[u8],
    sizes: &[usize],
    expect: Option<&Request>,
) -> Vec<Frame> {
    let mut dec = Decoder::new();
    if let Some(r) = expect {
        dec.expect(r);
    }
    decode_chunked(&mut dec, stream, sizes)
        .into_iter()
        .filter_map(Result::ok)
        .filter(|f| !originals.contains(f))
        .filter(|f| !crc_collision(f, stream))
        .collect()
}

/// True when the corrupted stream itself carries `frame` byte for byte, CRC
/// included: random corruption (an inserted and a dropped byte in one frame, say)
/// produced a sequence whose CRC-16 happens to match — a 2^-16 event per corrupted
/// frame that no 16-bit checksum can exclude and larger `PROPTEST_CASES` runs do
/// hit. The decoder then rightly returns what is on the wire; anything else it
/// returns that was not sent is a decoder bug.
fn crc_collision(frame: &Frame, stream: &[u8]) -> bool {
    let bytes = encode_frame(frame);
    !bytes.is_empty() && stream.windows(bytes.len()).any(|w| w == bytes.as_slice())
}

// ---------------------------------------------------------------------------
// Requests
// ---------------------------------------------------------------------------

proptest! {
    #![proptest_config(config())]

    /// to_bytes -> parse is the identity; frame_len finds the length from any long
    /// enough prefix and never more; a shorter or longer slice does not parse.
    #[test]
    fn request_bytes_round_trip(req in arb_request()) {
        let bytes = req.to_bytes().unwrap();
        prop_assert_eq!(bytes.len(), req.encoded_len());
        prop_assert_eq!(Request::parse(&bytes), Ok(req.clone()));
        prop_assert_eq!(Request::frame_len(&bytes), Ok(Some(bytes.len())));
        for cut in 0..bytes.len() {
            let prefix = &bytes[..cut];
            let fl = Request::frame_len(prefix);
            prop_assert!(fl == Ok(None) || fl == Ok(Some(bytes.len())), "{:?} on {:02X?}", fl, prefix);
            prop_assert_eq!(Request::parse(prefix), Err(RequestError::Truncated));
        }
        let mut longer = bytes.to_vec();
        longer.push(0);
        prop_assert_eq!(Request::parse(&longer), Err(RequestError::TrailingBytes));
        // encode() into a slice writes the same bytes.
        let mut out = [0u8; 300];
        let n = req.encode(&mut out).unwrap();
        prop_assert_eq!(&out[..n], bytes.as_slice());
        // And the CRC is the MODBUS CRC, LSB first.
        let (body, crc) = bytes.split_at(bytes.len() - 2);
        prop_assert_eq!(crc16(body).to_le_bytes(), [crc[0], crc[1]]);
    }

    /// Validated constructors refuse too many registers, empty lists, address
    /// overflow and writes outside 300..=399, with the right error.
    #[test]
    fn request_constructors_refuse_invalid(
        start in address(),
        count in prop_oneof![0usize..=2, 0usize..=140, 95usize..=130],
        values in prop::collection::vec(any::<u16>(), 0..=130),
        pairs in prop::collection::vec((address(), any::<u16>()), 0..=20),
        option in settings_option(),
    ) {
        let check = |got: Result<Request, RequestError>, want: Result<(), RequestError>| {
            match (&got, want) {
                (Ok(r), Ok(())) => {
                    assert!(r.to_bytes().is_ok());
                }
                (Err(e), Err(w)) => assert_eq!(*e, w),
                _ => panic!("got {got:?}, want {want:?}"),
            }
        };
        check(Request::read_registers(start, count), block_verdict(start, count, 127, false));
        check(Request::read_registers_native(start, count), block_verdict(start, count, 127, false));
        check(Request::read_settings(option, count), block_verdict(0, count, 100, false));
        let addrs: Vec<u16> = values.iter().take(count.min(values.len())).copied().collect();
        check(Request::read_individual(&addrs), block_verdict(0, addrs.len(), 31, false));
        let v = &values[..count.min(values.len())];
        check(Request::write_registers(start, v), block_verdict(start, v.len(), 100, true));
        check(Request::write_registers_native(start, v), block_verdict(start, v.len(), 30, true));
        let want = block_verdict(0, pairs.len(), 15, false).and_then(|()| {
            match pairs.iter().find(|(a, _)| !cmd::WRITABLE.contains(a)) {
                Some(&(address, _)) => Err(RequestError::NotWritable { address }),
                None => Ok(()),
            }
        });
        check(Request::write_individual(&pairs), want);
    }

    /// A request built directly (bypassing the constructors) is encoded only if
    /// valid: otherwise to_bytes/encode fail with the constructor's error and not a
    /// byte is written.
    #[test]
    fn invalid_requests_produce_no_bytes(req in arb_raw_request()) {
        let verdict = request_verdict(&req);
        prop_assert_eq!(req.validate(), verdict);
        let mut out = [0x5Au8; 300];
        match verdict {
            Ok(()) => {
                let bytes = req.to_bytes().unwrap();
                prop_assert_eq!(Request::parse(&bytes), Ok(req.clone()));
                let n = req.encode(&mut out).unwrap();
                prop_assert_eq!(&out[..n], bytes.as_slice());
            }
            Err(e) => {
                prop_assert_eq!(req.to_bytes(), Err(e));
                prop_assert_eq!(req.encode(&mut out), Err(e));
                prop_assert!(out.iter().all(|&b| b == 0x5A));
            }
        }
    }

    /// Request::parse and frame_len never panic on arbitrary bytes; whatever parses
    /// encodes back to exactly the same bytes.
    #[test]
    fn request_parse_never_panics(
        raw in prop::collection::vec(wire_byte(), 0..=220),
        fix_crc in any::<bool>(),
        fix_len in any::<bool>(),
    ) {
        let mut bytes = raw;
        if fix_len && bytes.len() >= 2 {
            // Shape the slice to the length frame_len announces, so parsing gets
            // past the length checks.
            bytes[0] = cmd::PREAMBLE;
            if let Ok(Some(n)) = Request::frame_len(&bytes) {
                bytes.resize(n.max(2), 0);
            }
        }
        if fix_crc && bytes.len() >= 4 {
            let n = bytes.len();
            let c = crc16(&bytes[..n - 2]).to_le_bytes();
            bytes[n - 2] = c[0];
            bytes[n - 1] = c[1];
        }
        let _ = Request::frame_len(&bytes);
        if let Ok(req) = Request::parse(&bytes) {
            prop_assert_eq!(req.validate(), Ok(()));
            let again = req.to_bytes().unwrap();
            prop_assert_eq!(again.as_slice(), bytes.as_slice());
        }
    }
}

// ---------------------------------------------------------------------------
// Responses
// ---------------------------------------------------------------------------

fn check_response_round_trip(
    req: &Request,
    resp: &Response,
    sizes: &[usize],
) -> Result<(), TestCaseError> {
    let frame = resp.to_frame(req).unwrap();
    let bytes = encode_frame(&frame);
    let want = as_received(&frame);
    for expect in [false, true] {
        let mut dec = Decoder::new();
        if expect {
            dec.expect(req);
        }
        let got = decode_chunked(&mut dec, &bytes, sizes);
        prop_assert_eq!(&got, &vec![Ok(want.clone())]);
        let decoded = Response::decode(req, &want).unwrap();
        prop_assert!(same_response(&decoded, resp), "{:?} != {:?}", decoded, resp);
        let st = dec.stats();
        prop_assert_eq!(st.frames, 1);
        prop_assert_eq!(st.skipped_bytes, 0);
        prop_assert_eq!(st.bytes_in as usize, bytes.len());
    }
    Ok(())
}

proptest! {
    #![proptest_config(config())]

    /// Response -> to_frame -> encode -> Decoder (random chunks) -> decode is the
    /// identity, for every request and every response consistent with it.
    #[test]
    fn response_round_trip((req, resp) in arb_exchange(), sizes in chunking()) {
        check_response_round_trip(&req, &resp, &sizes)?;
    }

    /// The same for long native replies: 0x07 up to 127 registers, 0x09 up to 31
    /// addresses, 0x11/0x12 up to 63 events (49 = the whole log), reassembled from
    /// several 63-byte packets.
    #[test]
    fn multi_packet_response_round_trip(
        (req, resp) in arb_multi_packet_exchange(),
        sizes in chunking(),
    ) {
        let frame = resp.to_frame(&req).unwrap();
        prop_assert!(payload_of(&frame).len() > MAX_PACKET_PAYLOAD);
        let Frame::Data { packets, .. } = as_received(&frame) else { unreachable!() };
        prop_assert!(packets >= 2);
        check_response_round_trip(&req, &resp, &sizes)?;
    }

    /// Response::decode of an arbitrary frame against an arbitrary (even invalid)
    /// request never panics; what it accepts re-encodes to the same frame (0x1E/0x1F
    /// tolerate and drop trailing bytes).
    #[test]
    fn response_decode_never_panics(
        req in arb_raw_request(),
        kind in 0u8..4,
        same_command in any::<bool>(),
        other_command in any::<u8>(),
        arg in any::<u8>(),
        payload in prop_oneof![
            prop::collection::vec(any::<u8>(), 0..=16),
            prop::collection::vec(any::<u8>(), 0..=MAX_PAYLOAD),
        ],
        packets in any::<u8>(),
    ) {
        let command = if same_command { req.command() } else { other_command };
        let frame = match kind {
            0 => Frame::Ack { command },
            1 => Frame::Nack { command, code: NackCode::from_u8(arg) },
            _ => Frame::Data {
                command,
                payload: heapless::Vec::from_slice(&payload).unwrap(),
                packets,
            },
        };
        check_decoded_reencodes(&req, &frame)?;
    }

    /// Valid replies with a damaged payload (cut, extended, bytes changed) decoded
    /// against their request: no panic, and anything accepted re-encodes exactly.
    #[test]
    fn damaged_payload_never_panics(
        (req, resp) in arb_exchange(),
        cut in any::<Index>(),
        extra in prop::collection::vec(any::<u8>(), 0..8),
        flips in prop::collection::vec((any::<Index>(), 1u8..=255), 0..3),
    ) {
        let frame = resp.to_frame(&req).unwrap();
        if let Frame::Data { command, payload, packets } = frame {
            let mut p = payload.to_vec();
            p.truncate(cut.index(p.len() + 1));
            p.extend_from_slice(&extra);
            p.truncate(MAX_PAYLOAD);
            for (i, x) in &flips {
                if !p.is_empty() {
                    let i = i.index(p.len());
                    p[i] ^= x;
                }
            }
            let damaged = Frame::Data {
                command,
                payload: heapless::Vec::from_slice(&p).unwrap(),
                packets,
            };
            check_decoded_reencodes(&req, &damaged)?;
        }
    }
}

fn check_decoded_reencodes(req: &Request, frame: &Frame) -> Result<(), TestCaseError> {
    let Ok(resp) = Response::decode(req, frame) else {
        return Ok(());
    };
    let again = resp.to_frame(req).unwrap();
    prop_assert_eq!(again.command(), frame.command());
    match (frame, &again) {
        (Frame::Data { command, .. }, Frame::Data { .. })
            if *command == cmd::READ_VERSION || *command == cmd::READ_EXTENDED_VERSION =>
        {
            prop_assert!(payload_of(frame).starts_with(payload_of(&again)));
        }
        (Frame::Data { payload, .. }, Frame::Data { payload: p2, .. }) => {
            prop_assert_eq!(payload, p2)
        }
        _ => prop_assert_eq!(frame, &again),
    }
    Ok(())
}

// ---------------------------------------------------------------------------
// Streams: noise, chunking, corruption
// ---------------------------------------------------------------------------

proptest! {
    #![proptest_config(config())]

    /// Valid frames with ASCII broadcasts and random non-0xAA bytes between them
    /// (and between the packets of multi-packet replies), cut into random chunks,
    /// decode to exactly the frames sent, in order, with every noise byte counted
    /// as skipped and no error.
    #[test]
    fn stream_with_noise_decodes_exactly(
        exchanges in prop::collection::vec(
            prop_oneof![3 => arb_exchange(), 1 => arb_multi_packet_exchange()],
            1..8,
        ),
        noises in prop::collection::vec(noise(), 0..24),
        sizes in chunking(),
    ) {
        let frames: Vec<Frame> =
            exchanges.iter().map(|(q, r)| r.to_frame(q).unwrap()).collect();
        let (stream, expected, noise_len) = noisy_stream(&frames, &noises);
        let mut dec = Decoder::new();
        let got = decode_chunked(&mut dec, &stream, &sizes);
        let want: Vec<Result<Frame, DecodeError>> = expected.into_iter().map(Ok).collect();
        prop_assert_eq!(got, want);
        let st = dec.stats();
        prop_assert_eq!(st.skipped_bytes as usize, noise_len);
        prop_assert_eq!(st.frames as usize, frames.len());
        prop_assert_eq!(st.bytes_in as usize, stream.len());
        prop_assert_eq!(
            (st.crc_errors, st.length_errors, st.truncated, st.packet_errors),
            (0, 0, 0, 0)
        );
        // And each frame decodes as the answer to its request.
        for ((req, resp), f) in exchanges.iter().zip(&frames) {
            let decoded = Response::decode(req, &as_received(f)).unwrap();
            prop_assert!(same_response(&decoded, resp));
        }
    }

    /// Random corruption (bit flips, dropped bytes and runs, inserted bytes
    /// including 0xAA) of a stream of single-packet frames never yields a frame that
    /// was not sent, and never panics.
    #[test]
    fn corruption_never_invents_single_packet_frames(
        exchanges in prop::collection::vec(arb_exchange(), 1..8),
        noises in prop::collection::vec(noise(), 0..10),
        ops in prop::collection::vec(corruption(), 1..8),
        sizes in chunking(),
    ) {
        let frames: Vec<Frame> = exchanges
            .iter()
            .map(|(q, r)| r.to_frame(q).unwrap())
            .filter(|f| packets(&encode_frame(f), f).len() == 1)
            .collect();
        let (mut stream, originals, _) = noisy_stream(&frames, &noises);
        corrupt(&mut stream, &ops);
        let invented = invented_frames(&originals, &stream, &sizes, None);
        prop_assert!(invented.is_empty(), "invented {:?}", invented);
    }

    /// The same with multi-packet replies (0x07/0x09/0x11/0x12) in the stream:
    /// a frame that was not sent can only be a packetized reply, i.e. come from
    /// reassembly (without `Decoder::expect` a reply whose first packets were lost
    /// cannot be told from a shorter one); every other command is exact.
    #[test]
    fn corruption_never_invents_frames_outside_reassembly(
        exchanges in prop::collection::vec(
            prop_oneof![2 => arb_exchange(), 1 => arb_multi_packet_exchange()],
            1..6,
        ),
        noises in prop::collection::vec(noise(), 0..10),
        ops in prop::collection::vec(corruption(), 1..8),
        sizes in chunking(),
    ) {
        let frames: Vec<Frame> =
            exchanges.iter().map(|(q, r)| r.to_frame(q).unwrap()).collect();
        let (mut stream, originals, _) = noisy_stream(&frames, &noises);
        corrupt(&mut stream, &ops);
        let invented = invented_frames(&originals, &stream, &sizes, None);
        for f in &invented {
            prop_assert!(
                is_packetized(f.command()),
                "invented a non-packetized frame {:?}",
                f
            );
        }
    }
}

proptest! {
    #![proptest_config(config())]

    /// STRICT version of the corruption property with multi-packet replies, the way
    /// the firmware uses the decoder: one request outstanding at a time, announced
    /// with `Decoder::expect`. No frame that was not sent ever comes out — not even
    /// the tail of a reply whose first packets were lost.
    #[test]
    fn corruption_never_invents_frames_strict(
        exchanges in prop::collection::vec(
            prop_oneof![2 => arb_exchange(), 1 => arb_multi_packet_exchange()],
            1..6,
        ),
        noises in prop::collection::vec(noise(), 0..10),
        ops in prop::collection::vec(corruption(), 1..8),
        sizes in chunking(),
    ) {
        for (q, r) in &exchanges {
            let frames = vec![r.to_frame(q).unwrap()];
            let (mut stream, originals, _) = noisy_stream(&frames, &noises);
            corrupt(&mut stream, &ops);
            let invented = invented_frames(&originals, &stream, &sizes, Some(q));
            prop_assert!(invented.is_empty(), "invented {:?}", invented);
        }
    }
}

// ---------------------------------------------------------------------------
// No panic on arbitrary input; decoder invariants
// ---------------------------------------------------------------------------

proptest! {
    #![proptest_config(config())]

    /// Arbitrary bytes in random chunks: no panic, no stall, all input accounted
    /// for, and every frame returned is encodable and re-encodes to bytes that
    /// decode to the same command and payload.
    #[test]
    fn decoder_never_panics_on_arbitrary_bytes(
        bytes in prop_oneof![
            prop::collection::vec(wire_byte(), 0..=700),
            prop::collection::vec(any::<u8>(), 0..=700),
        ],
        sizes in chunking(),
        expect in prop::option::of(arb_raw_request()),
    ) {
        let mut dec = Decoder::new();
        if let Some(r) = &expect {
            dec.expect(r);
        }
        let got = decode_chunked(&mut dec, &bytes, &sizes);
        prop_assert_eq!(dec.buffered(), 0);
        prop_assert!(!dec.in_packets());
        let st = dec.stats();
        prop_assert_eq!(st.bytes_in as usize, bytes.len());
        prop_assert_eq!(st.frames as usize, got.iter().filter(|r| r.is_ok()).count());
        for f in got.into_iter().flatten() {
            check_frame_reencodes(&f)?;
            if let Some(r) = &expect {
                let _ = Response::decode(r, &f);
            }
        }
    }

    /// Arbitrary frames: encoding never panics, and a frame the encoder accepts
    /// and the decoder returns comes back with the same command and payload.
    #[test]
    fn frame_encode_never_panics(
        kind in 0u8..3,
        command in wire_byte(),
        arg in any::<u8>(),
        payload in prop::collection::vec(any::<u8>(), 0..=MAX_PAYLOAD),
        small in any::<bool>(),
    ) {
        let frame = match kind {
            0 => Frame::Ack { command },
            1 => Frame::Nack { command, code: NackCode::from_u8(arg) },
            _ => {
                let p = if small { &payload[..payload.len().min(16)] } else { &payload[..] };
                Frame::data(command, p).unwrap()
            }
        };
        let mut buf = [0u8; 400];
        let Ok(n) = frame.encode(&mut buf) else { return Ok(()) };
        prop_assert_eq!(frame.encoded_len(), Ok(n));
        let mut small_buf = vec![0u8; n.saturating_sub(1)];
        prop_assert!(frame.encode(&mut small_buf).is_err());
        let mut out = Vec::new();
        decode_all(&buf[..n], |r| out.push(r));
        // Packetized payloads of implausible length are refused by the decoder;
        // anything it does return must be the frame.
        for f in out.iter().flatten() {
            prop_assert_eq!(f.command(), frame.command());
            prop_assert_eq!(payload_of(f), payload_of(&frame));
        }
        if !is_packetized(command) || kind < 2 {
            prop_assert_eq!(out.len(), 1);
            prop_assert!(out[0].is_ok(), "{:?}", out);
        }
    }

    /// Register views over arbitrary blocks never panic and fail exactly when the
    /// block does not cover their registers.
    #[test]
    fn views_never_panic(
        start in prop_oneof![0u16..=60, 90u16..=120, 180u16..=210, 480u16..=510, any::<u16>()],
        values in prop::collection::vec(any::<u16>(), 0..=cmd::MAX_READ_MODBUS),
        cells in prop::array::uniform16(prop_oneof![Just(0u16), any::<u16>()]),
        cell_count in any::<u16>(),
    ) {
        let b = RegisterBlock { start, values: Words::from_slice(&values).unwrap() };
        let live = LiveSnapshot::from_registers(&b);
        prop_assert_eq!(live.is_ok(), b.covers(regs::LIVE_FIRST, regs::LIVE_LAST));
        if let Ok(s) = live {
            prop_assert_eq!(s.pack_voltage_v.to_bits(), b.get_u32(36).unwrap());
            prop_assert_eq!(s.cell_count, b.get(53).unwrap());
            let _ = (s.soc_percent(), s.soh_percent(), s.internal_c(), s.external1_c());
            let _ = (s.cells.min(), s.cells.max(), s.cells.volts(0));
        }
        prop_assert_eq!(
            Statistics::from_registers(&b).is_ok(),
            b.covers(regs::STATS_FIRST, regs::STATS_LAST)
        );
        prop_assert_eq!(
            views::event_log(&b).is_ok(),
            b.covers(regs::EVENTS_FIRST, regs::EVENTS_LAST)
        );
        prop_assert_eq!(
            VersionInfo::from_registers(&b).is_ok(),
            b.covers(regs::VERSION_FIRST, regs::VERSION_LAST)
        );
        for a in [start, start.wrapping_add(1), 0xFFFF, 36] {
            let _ = (b.get(a), b.get_u32(a), b.get_f32(a), regs::lookup(a));
        }
        let _ = b.iter().count();
        let c = Cells::select(&cells, cell_count);
        let n = (cell_count as usize).min(MAX_CELLS);
        prop_assert_eq!(c.raw.len(), n);
        prop_assert!(c.first_register as usize + n <= MAX_CELLS);
        prop_assert_eq!(c.raw.as_slice(), &cells[c.first_register as usize..][..n]);
    }

    /// Settings: any value is either refused or produces register words that read
    /// back as that value; lookups never panic.
    #[test]
    fn settings_never_panic(
        id in select(SettingId::ALL.to_vec()),
        value in prop_oneof![any::<i32>(), -100i32..=70_000],
        current in any::<u16>(),
        words in (any::<u16>(), prop::option::of(any::<u16>())),
        values in prop::collection::vec(any::<u16>(), 0..=60),
    ) {
        let _ = id.value_from_words(words.0, words.1);
        let b = RegisterBlock { start: 300, values: Words::from_slice(&values).unwrap() };
        let _ = (id.read(&b), id.limits(&b, &b), id.name());
        let raw = Setting { id, value };
        let _ = (raw.words(Some(current)), raw.words(None), raw.matches_readback(words.0, words.1));
        if let Ok(s) = Setting::new(id, value) {
            let w = s.words(Some(current)).unwrap();
            prop_assert_eq!(w.len(), id.register_count() as usize);
            prop_assert_eq!(w[0].0, id.address());
            for (a, _) in &w {
                prop_assert!(cmd::WRITABLE.contains(a));
            }
            prop_assert!(
                s.matches_readback(w[0].1, w.get(1).map(|p| p.1)),
                "{:?} wrote {:?}",
                s,
                w
            );
            // The other byte of a byte field is kept.
            if id.register_count() == 1 {
                let mask = match id.field() {
                    regs::Field::Whole => 0,
                    regs::Field::LowByte => 0xFF00,
                    regs::Field::HighByte => 0x00FF,
                };
                prop_assert_eq!(w[0].1 & mask, current & mask);
            }
        }
    }
}

fn check_frame_reencodes(f: &Frame) -> Result<(), TestCaseError> {
    let n = f.encoded_len();
    prop_assert!(n.is_ok(), "decoded frame not encodable: {:?} ({:?})", f, n);
    let bytes = encode_frame(f);
    let mut again = Vec::new();
    decode_all(&bytes, |r| again.push(r));
    prop_assert_eq!(again.len(), 1, "{:?} -> {:02X?} -> {:?}", f, bytes, again);
    let g = again[0].as_ref().unwrap();
    prop_assert_eq!(g.command(), f.command());
    prop_assert_eq!(payload_of(g), payload_of(f));
    prop_assert_eq!(std::mem::discriminant(g), std::mem::discriminant(f));
    Ok(())
}

// ---------------------------------------------------------------------------
// Regression test (found by the strict property above)
// ---------------------------------------------------------------------------

/// A 45-register 0x07 reply (63 + 27 bytes, as HARDWARE-NOTES saw) whose first
/// packet is damaged: the decoder drops that packet and then sees the 27-byte
/// last packet on its own. With the request announced through `Decoder::expect`
/// (which implies 90 bytes) the lone 27-byte tail must be an error, not a frame.
#[test]
fn lost_first_packet_never_yields_the_tail_as_a_frame() {
    let req = Request::read_registers_native(0, 45).unwrap();
    let values: Vec<u16> = (0..45).collect();
    let resp = Response::Registers(RegisterBlock {
        start: 0,
        values: Words::from_slice(&values).unwrap(),
    });
    let frame = resp.to_frame(&req).unwrap();
    let mut bytes = encode_frame(&frame);
    assert_eq!(bytes.len(), 68 + 32);
    bytes[10] ^= 0x01; // one bit of the first packet's payload
    let mut dec = Decoder::new();
    dec.expect(&req);
    let got = decode_chunked(&mut dec, &bytes, &[64]);
    let oks: Vec<&Frame> = got.iter().filter_map(|r| r.as_ref().ok()).collect();
    assert!(oks.is_empty(), "decoder returned {oks:?} (from {got:?})");
}

/// The typed layer does catch the case above for 0x07 (length checked against
/// the request) — this documents that the damage stops at `Response::decode`.
#[test]
fn lost_first_packet_is_caught_by_response_decode_for_0x07() {
    let req = Request::read_registers_native(0, 45).unwrap();
    let tail = Frame::data(cmd::READ_BLOCK, &[0u8; 27]).unwrap();
    assert!(Response::decode(&req, &tail).is_err());
}
