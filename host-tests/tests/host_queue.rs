//! The queue between the station and the host port's writer, as the chip has
//! it: embassy-sync's `Pipe` (a ring buffer whose `try_write` stops at its wrap
//! point) of the chip's size, fed through `host_link::queue::hand_off`. Every
//! line must come out whole and in order, whatever the ring's position, and a
//! line that does not fit must leave nothing behind.

use embassy_sync::blocking_mutex::raw::NoopRawMutex;
use embassy_sync::pipe::Pipe;
use tinybms_firmware::host_link::queue::{hand_off, ByteQueue, HandOff};
use tinybms_firmware::host_link::OUT_LINE_MAX;

/// The chip's queue (`chip/wires.rs`: `HOST_TX`).
const CHIP_QUEUE: usize = 2 * OUT_LINE_MAX;

/// A line of `len` bytes (newline included) that says which one it is.
fn line(n: usize, len: usize) -> Vec<u8> {
    let head = format!("{{\"n\":{n},\"pad\":\"");
    let mut l = head.into_bytes();
    while l.len() < len.saturating_sub(3) {
        l.push(b'a' + (l.len() % 26) as u8);
    }
    l.extend_from_slice(b"\"}\n");
    l.truncate(len.max(1) - 1);
    l.push(b'\n');
    l
}

/// Everything in the pipe now.
fn drain<const N: usize>(p: &Pipe<NoopRawMutex, N>) -> Vec<u8> {
    let mut out = Vec::new();
    let mut buf = [0u8; 64];
    while let Ok(n) = p.try_read(&mut buf) {
        out.extend_from_slice(&buf[..n]);
    }
    out
}

/// Moves the ring's read and write position to `k` (an empty pipe).
fn turn<const N: usize>(p: &Pipe<NoopRawMutex, N>, k: usize) {
    let mut left = k;
    while left > 0 {
        let chunk = vec![b'x'; left.min(N)];
        let mut q = p;
        let mut rest = &chunk[..];
        while !rest.is_empty() {
            let n = q.offer(rest);
            assert!(n > 0, "an empty pipe takes bytes");
            rest = &rest[n..];
        }
        left -= chunk.len();
        drain(p);
    }
}

#[test]
fn a_line_comes_out_whole_at_every_wrap_offset_of_the_chips_queue() {
    let p: Pipe<NoopRawMutex, CHIP_QUEUE> = Pipe::new();
    for k in 0..CHIP_QUEUE {
        turn(&p, k);
        // The longest line the station hands out, and a short one after it.
        let long = line(k, OUT_LINE_MAX);
        let short = line(k + 1, 40);
        assert_eq!(hand_off(&mut &p, &long), HandOff::Whole, "offset {k}");
        assert_eq!(hand_off(&mut &p, &short), HandOff::Whole, "offset {k}");
        let out = drain(&p);
        assert_eq!(out.len(), long.len() + short.len(), "offset {k}");
        assert_eq!(&out[..long.len()], &long[..], "offset {k}: the long line");
        assert_eq!(&out[long.len()..], &short[..], "offset {k}: the short line");
    }
}

#[test]
fn lines_of_every_length_interleaved_with_a_slow_reader_stay_whole_and_in_order() {
    let p: Pipe<NoopRawMutex, 97> = Pipe::new();
    let mut sent = Vec::new();
    let mut got = Vec::new();
    let mut buf = [0u8; 13];
    let mut n = 0;
    for len in (2..=97).chain((2..=97).rev()).cycle().take(3000) {
        let l = line(n, len);
        loop {
            match hand_off(&mut &p, &l) {
                HandOff::Whole => break,
                HandOff::NoRoom => {
                    // The reader takes a little; nothing of the line went in.
                    let k = p.try_read(&mut buf).unwrap_or(0);
                    assert!(k > 0, "a pipe without room has bytes to read");
                    got.extend_from_slice(&buf[..k]);
                }
                HandOff::Cut { taken } => panic!("line {n} cut after {taken} bytes"),
            }
        }
        sent.extend_from_slice(&l);
        n += 1;
        if n % 3 == 0 {
            if let Ok(k) = p.try_read(&mut buf) {
                got.extend_from_slice(&buf[..k]);
            }
        }
    }
    got.extend(drain(&p));
    assert_eq!(got, sent);
    let lines = got.split(|&b| b == b'\n').filter(|l| !l.is_empty()).count();
    assert_eq!(lines, n);
}

#[test]
fn a_line_that_does_not_fit_leaves_nothing_in_a_full_pipe() {
    let p: Pipe<NoopRawMutex, CHIP_QUEUE> = Pipe::new();
    for k in [0, 1, 100, CHIP_QUEUE - 1] {
        turn(&p, k);
        let first = line(1, OUT_LINE_MAX);
        assert_eq!(hand_off(&mut &p, &first), HandOff::Whole);
        // Room for less than a line: refused, nothing written.
        let filler = line(2, CHIP_QUEUE - OUT_LINE_MAX - 10);
        assert_eq!(hand_off(&mut &p, &filler), HandOff::Whole);
        assert_eq!(p.free_capacity(), 10);
        assert_eq!(hand_off(&mut &p, &line(3, 11)), HandOff::NoRoom);
        assert_eq!(p.free_capacity(), 10, "a refused line took no room");
        assert_eq!(hand_off(&mut &p, &line(4, 10)), HandOff::Whole);
        assert_eq!(hand_off(&mut &p, &line(5, 1)), HandOff::NoRoom);
        let out = drain(&p);
        let mut want = first.clone();
        want.extend(line(2, CHIP_QUEUE - OUT_LINE_MAX - 10));
        want.extend(line(4, 10));
        assert_eq!(out, want, "offset {k}");
    }
}

/// A queue whose room is taken by someone else between the check and the
/// write: the line is reported cut, never as whole.
#[test]
fn a_queue_that_takes_less_than_it_promised_is_reported_cut() {
    struct Liar(usize);
    impl ByteQueue for Liar {
        fn free(&self) -> usize {
            1000
        }
        fn offer(&mut self, bytes: &[u8]) -> usize {
            let n = bytes.len().min(self.0);
            self.0 -= n;
            n
        }
    }
    assert_eq!(
        hand_off(&mut Liar(7), &line(0, 20)),
        HandOff::Cut { taken: 7 }
    );
    assert_eq!(hand_off(&mut Liar(20), &line(0, 20)), HandOff::Whole);
}

/// The station's own pump (`Station::hand_out_host_lines`, what the chip's
/// station task calls) into the chip's queue, read by a writer that takes a
/// few bytes at a time: every line that comes out is one whole JSON line, and
/// they are the lines a direct reader gets, in the same order.
#[test]
fn the_stations_pump_into_the_chips_queue_gives_only_whole_lines() {
    use host_tests::virtual_host_link::{check_line, config, Rig};

    let mut direct = Rig::ready(config(false, 200));
    let mut pumped = Rig::ready(config(false, 200));
    let mut want = direct.drain_text();
    let pipe: Pipe<NoopRawMutex, CHIP_QUEUE> = Pipe::new();
    let mut buf = [0u8; OUT_LINE_MAX];
    let mut stream = Vec::new();
    let mut chunk = [0u8; 23];
    let mut handed = 0;
    // What the first pump hands out is what the direct reader drained.
    let now = pumped.h.now;
    handed += pumped
        .h
        .station
        .hand_out_host_lines(now, &mut &pipe, &mut buf);
    for round in 0..400 {
        // The settings listing and the configuration: many lines at once.
        if round % 50 == 0 {
            direct.line(r#"{"cmd":"get","what":"settings","req":1}"#);
            pumped.line(r#"{"cmd":"get","what":"settings","req":1}"#);
            direct.line(r#"{"cmd":"get","what":"config","req":2}"#);
            pumped.line(r#"{"cmd":"get","what":"config","req":2}"#);
        }
        direct.run(20 * tinybms_firmware::MS);
        pumped.run(20 * tinybms_firmware::MS);
        want.extend(direct.drain_text());
        // The writer reads a little, then the station pumps.
        for _ in 0..8 {
            if let Ok(k) = pipe.try_read(&mut chunk) {
                stream.extend_from_slice(&chunk[..k]);
            }
        }
        let now = pumped.h.now;
        handed += pumped
            .h
            .station
            .hand_out_host_lines(now, &mut &pipe, &mut buf);
    }
    // The rest, until the station has nothing more.
    for _ in 0..10_000 {
        stream.extend(drain(&pipe));
        let now = pumped.h.now;
        let n = pumped
            .h
            .station
            .hand_out_host_lines(now, &mut &pipe, &mut buf);
        handed += n;
        if n == 0 {
            break;
        }
    }
    stream.extend(drain(&pipe));
    let got: Vec<String> = stream
        .split_inclusive(|&b| b == b'\n')
        .map(check_line)
        .collect();
    assert!(got.len() > 200, "{} lines", got.len());
    assert_eq!(got.len() as u32, handed);
    // A slow writer costs streamed telemetry (dropped whole, counted), never
    // an answer: the answers' types come out in the order a direct reader
    // gets them.
    let answers = |ls: &[String]| -> Vec<String> {
        ls.iter()
            .map(|l| {
                let v: serde_json::Value = serde_json::from_str(l).unwrap();
                v["type"].as_str().unwrap_or("").to_string()
            })
            .filter(|t| t != "telemetry" && t != "log")
            .collect()
    };
    let (g, w) = (answers(&got), answers(&want));
    assert!(g.len() > 100, "{} answer lines", g.len());
    assert_eq!(g, w);
}
