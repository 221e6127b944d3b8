//! Throughput benchmarks: the CRC against the `crc` crate, and the streaming
//! decoder on a realistic poll stream (chunked as a UART DMA would hand it over,
//! and byte by byte as an interrupt handler would).
//!
//! `cargo bench -p protocol-core --bench throughput -- --warm-up-time 1 --measurement-time 3`
//!
//! First, the fair comparison: the decoder and the CRC alone on the same bytes,
//! chunked the same way, timed alternately in one run, and the ratio of their
//! throughputs printed (`cargo bench -p protocol-core --bench throughput -- ratio`
//! prints only that: the filter matches no criterion benchmark).
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput};
use protocol_core::crc::{crc16, Crc16};
use protocol_core::events::{Event, EventId, OnlineStatus};
use protocol_core::request::Request;
use protocol_core::response::{EventList, RegisterBlock, Response, Temperatures, Words};
use protocol_core::{Decoder, Frame};

const CRC_SIZES: [usize; 4] = [8, 64, 256, 4096];
/// Poll exchanges in the decoder stream.
const EXCHANGES: usize = 1000;
/// One ASCII broadcast line (HARDWARE-NOTES), 34 bytes.
const BROADCAST: &[u8] = b"MST:\tEXT1:----\tEXT2:----\tOS:155\r\n";

fn crc_benches(c: &mut Criterion) {
    let table1 = crc::Crc::<u16>::new(&crc::CRC_16_MODBUS);
    let slice16 = crc::Crc::<u16, crc::Table<16>>::new(&crc::CRC_16_MODBUS);
    let mut g = c.benchmark_group("crc16_modbus");
    for size in CRC_SIZES {
        let data: Vec<u8> = (0..size).map(|i| (i * 31 + 7) as u8).collect();
        // Same value from all three, checked once, outside the timing.
        assert_eq!(crc16(&data), table1.checksum(&data));
        assert_eq!(crc16(&data), slice16.checksum(&data));
        g.throughput(Throughput::Bytes(size as u64));
        g.bench_with_input(BenchmarkId::new("protocol_core", size), &data, |b, d| {
            b.iter(|| crc16(black_box(d)))
        });
        g.bench_with_input(BenchmarkId::new("crc_crate_table", size), &data, |b, d| {
            b.iter(|| table1.checksum(black_box(d)))
        });
        g.bench_with_input(
            BenchmarkId::new("crc_crate_slice16", size),
            &data,
            |b, d| b.iter(|| slice16.checksum(black_box(d))),
        );
    }
    g.finish();
}

fn encode(f: &Frame) -> Vec<u8> {
    let mut b = [0u8; 600];
    let n = f.encode(&mut b).unwrap();
    b[..n].to_vec()
}

/// One live poll exchange as the bridge sees it: a 0x03 reply of registers 0-55
/// (117 bytes), a 0x11 reply with 5 events, a 0x1B reply, and two ACKs.
fn poll_exchange(i: usize) -> Vec<u8> {
    let live = Request::read_registers(0, 56).unwrap();
    let values: Vec<u16> = (0..56u16)
        .map(|r| match r {
            0..=15 => 33_000 + r * 7 + (i as u16 % 13),
            50 => OnlineStatus::Discharging.raw(),
            53 => 16,
            _ => r.wrapping_mul(0x9E37).wrapping_add(i as u16),
        })
        .collect();
    let block = Response::Registers(RegisterBlock {
        start: 0,
        values: Words::from_slice(&values).unwrap(),
    });
    let events = Response::Events(EventList {
        bms_timestamp_s: 0x003B_2A00 + i as u32,
        events: (0..5u32)
            .map(|k| Event {
                timestamp_s: 0x3B_2800 + k,
                id: EventId::from_raw(0x61 + k as u8),
            })
            .collect(),
    });
    let temps = Response::Temperatures(Temperatures {
        internal_dc: 278,
        external1_dc: Some(276),
        external2_dc: None,
    });
    let mut s = encode(&block.to_frame(&live).unwrap());
    assert_eq!(s.len(), 117);
    s.extend(encode(
        &events.to_frame(&Request::ReadNewestEvents).unwrap(),
    ));
    s.extend(encode(&temps.to_frame(&Request::ReadTemperatures).unwrap()));
    s.extend(encode(&Frame::Ack { command: 0x0D }));
    s.extend(encode(&Frame::Ack { command: 0x02 }));
    s
}

/// 1000 exchanges (5 frames each) with a broadcast line before every 4th one:
/// about 5 % of the bytes are ASCII noise.
fn poll_stream() -> (Vec<u8>, usize) {
    let mut s = Vec::new();
    let mut noise = 0;
    for i in 0..EXCHANGES {
        if i % 4 == 0 {
            s.extend_from_slice(BROADCAST);
            noise += BROADCAST.len();
        }
        s.extend(poll_exchange(i));
    }
    eprintln!(
        "poll stream: {} bytes, {} frames, {:.1} % noise",
        s.len(),
        5 * EXCHANGES,
        100.0 * noise as f64 / s.len() as f64
    );
    (s, 5 * EXCHANGES)
}

/// 200 native 0x07 reads of 127 registers (5 packets each, reassembled).
fn native_stream() -> (Vec<u8>, usize) {
    let req = Request::read_registers_native(0, 127).unwrap();
    let mut s = Vec::new();
    for i in 0..200u16 {
        let values: Vec<u16> = (0..127u16).map(|r| r.wrapping_mul(i | 1)).collect();
        let resp = Response::Registers(RegisterBlock {
            start: 0,
            values: Words::from_slice(&values).unwrap(),
        });
        s.extend(encode(&resp.to_frame(&req).unwrap()));
    }
    (s, 200)
}

/// Feeds `stream` in `chunk`-byte pieces as the firmware's link does (push, then
/// `Decoder::poll_ref` until it answers `None`, until every byte is taken: a
/// single-frame reply is lent where it lies in the buffer) and counts the frames.
fn decode_chunked(stream: &[u8], chunk: usize) -> usize {
    let mut dec = Decoder::new();
    let mut frames = 0usize;
    let mut spill = None;
    for piece in stream.chunks(chunk) {
        let mut input = piece;
        loop {
            let n = dec.push(input);
            input = input.get(n..).unwrap_or(&[]);
            while let Some(r) = dec.poll_ref(&mut spill) {
                if let Ok(f) = r {
                    black_box(&f);
                    frames += 1;
                }
            }
            if input.is_empty() {
                break;
            }
        }
    }
    frames
}

/// As [`decode_chunked`], through `Decoder::feed` (every frame handed over
/// owned, its payload copied out of the buffer).
fn feed_chunked(stream: &[u8], chunk: usize) -> usize {
    let mut dec = Decoder::new();
    let mut frames = 0usize;
    for piece in stream.chunks(chunk) {
        dec.feed(piece, |r| {
            if let Ok(f) = r {
                black_box(&f);
                frames += 1;
            }
        });
    }
    frames
}

fn decode_bytewise(stream: &[u8]) -> usize {
    decode_chunked(stream, 1)
}

fn decoder_benches(c: &mut Criterion) {
    let (poll, poll_frames) = poll_stream();
    let (native, native_frames) = native_stream();
    // Correct before fast: every frame found, in both feeding modes.
    assert_eq!(decode_chunked(&poll, 64), poll_frames);
    assert_eq!(feed_chunked(&poll, 64), poll_frames);
    assert_eq!(decode_bytewise(&poll), poll_frames);
    assert_eq!(decode_chunked(&native, 64), native_frames);

    let mut g = c.benchmark_group("decoder");
    g.throughput(Throughput::Bytes(poll.len() as u64));
    g.bench_function("poll_stream_64B_chunks", |b| {
        b.iter(|| decode_chunked(black_box(&poll), 64))
    });
    g.bench_function("poll_stream_bytewise", |b| {
        b.iter(|| decode_bytewise(black_box(&poll)))
    });
    g.throughput(Throughput::Bytes(native.len() as u64));
    g.bench_function("native_0x07_127reg_64B_chunks", |b| {
        b.iter(|| decode_chunked(black_box(&native), 64))
    });
    g.finish();
}

/// CRC-only baseline: one running CRC over the stream, fed the same chunks, the
/// least any decoder must do with the same bytes handed over the same way. (A
/// fresh CRC per chunk would be an unfair baseline: independent short CRCs
/// overlap in an out-of-order CPU, a frame's CRC cannot.)
fn crc_chunked(stream: &[u8], chunk: usize) -> u16 {
    let mut crc = Crc16::new();
    for piece in stream.chunks(chunk) {
        crc.update(black_box(piece));
    }
    crc.value()
}

/// Best time of `rounds` runs of `f`, in seconds, with the runs of `g` interleaved
/// (so both see the same machine state).
fn best_of_alternating(rounds: usize, mut f: impl FnMut(), mut g: impl FnMut()) -> (f64, f64) {
    let (mut bf, mut bg) = (f64::MAX, f64::MAX);
    for _ in 0..rounds {
        let t = std::time::Instant::now();
        f();
        bf = bf.min(t.elapsed().as_secs_f64());
        let t = std::time::Instant::now();
        g();
        bg = bg.min(t.elapsed().as_secs_f64());
    }
    (bf, bg)
}

/// Decoder throughput as a fraction of the CRC-only throughput on the same bytes.
fn ratio_report() {
    let (poll, poll_frames) = poll_stream();
    let live: Vec<u8> = (0..EXCHANGES)
        .flat_map(|i| poll_exchange(i)[..117].to_vec())
        .collect();
    println!("decoder vs CRC alone, same bytes, same chunks (best of 30 alternating runs):");
    println!(
        "  {:<22} {:>6} {:>12} {:>12} {:>8}",
        "stream", "chunk", "decoder MB/s", "CRC MB/s", "ratio"
    );
    let streams = [
        ("poll stream (5 % noise)", poll.as_slice(), poll_frames),
        ("0x03 live replies", live.as_slice(), EXCHANGES),
    ];
    ratio_table(&streams, &[1, 16, 64, 256], decode_chunked);
    println!("  (ratio = decoder throughput / CRC-only throughput; goal >= 0.80x at 16-byte chunks and above)");
    println!("through Decoder::feed instead (frames handed over owned, payload copied out):");
    ratio_table(&streams, &[16, 64], feed_chunked);
}

/// One table: for each stream and chunk size, `decode` against the CRC alone on
/// the same bytes (the frame count checked first).
fn ratio_table(
    streams: &[(&str, &[u8], usize)],
    chunks: &[usize],
    decode: fn(&[u8], usize) -> usize,
) {
    for &(name, stream, frames) in streams {
        for &chunk in chunks {
            assert_eq!(decode(stream, chunk), frames);
            let (dec, crc) = best_of_alternating(
                30,
                || {
                    black_box(decode(black_box(stream), chunk));
                },
                || {
                    black_box(crc_chunked(black_box(stream), chunk));
                },
            );
            let mbs = |t: f64| stream.len() as f64 / t / 1e6;
            println!(
                "  {:<22} {:>6} {:>12.1} {:>12.1} {:>7.2}x",
                name,
                chunk,
                mbs(dec),
                mbs(crc),
                crc / dec
            );
        }
    }
}

fn main() {
    ratio_report();
    let mut c = Criterion::default().without_plots().configure_from_args();
    crc_benches(&mut c);
    decoder_benches(&mut c);
    c.final_summary();
}
