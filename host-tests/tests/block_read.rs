//! Block reads whose assembled block is lent in place and whose next pass
//! starts at the next request (the deferred restart): a new pass never keeps a
//! value of the previous one.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

use protocol_core::request::Request;
use protocol_core::response::{RegisterBlock, Words};
use tinybms_firmware::reader::{self, BlockRead, Mode, PIECE_REGISTERS};

/// Answers `request` (as the piece in flight of `read`) with `value(address)`;
/// returns the assembled block, if the read completed.
fn answer(
    read: &mut BlockRead,
    now: u64,
    request: &Request,
    value: impl Fn(u16) -> u16,
) -> Option<RegisterBlock> {
    match request {
        Request::ReadRegisters { start, count } => {
            let values: Words = (*start..*start + u16::from(*count)).map(&value).collect();
            let reply = RegisterBlock {
                start: *start,
                values,
            };
            read.on_block(now, &reply).map(|a| a.block.clone())
        }
        Request::ReadIndividual(addresses) => {
            let pairs: Vec<(u16, u16)> = addresses.iter().map(|&a| (a, value(a))).collect();
            read.on_pairs(now, &pairs, None).map(|a| a.block.clone())
        }
        other => panic!("unexpected request {other:?}"),
    }
}

/// One complete pass at `piece` registers per request: the requests sent and
/// the assembled block, if the read completed.
fn pass(
    read: &mut BlockRead,
    now: &mut u64,
    piece: u16,
    value: impl Fn(u16) -> u16,
) -> (Vec<Request>, Option<RegisterBlock>) {
    let mut sent = Vec::new();
    for _ in 0..64 {
        *now += 1_000;
        let req = read.next_request(*now, piece);
        sent.push(req.clone());
        let done = answer(read, *now, &req, &value);
        // The pass is over once its last piece is stored.
        let last = match &req {
            Request::ReadRegisters { start, count } => start + u16::from(*count) - 1,
            Request::ReadIndividual(a) => *a.last().unwrap(),
            _ => unreachable!(),
        };
        if done.is_some() || last == 343 || last == 55 {
            return (sent, done);
        }
    }
    panic!("the pass never ended: {sent:?}");
}

#[test]
fn a_confirmed_pass_is_read_afresh_and_never_mixed_with_the_previous_one() {
    let mut now = 0;
    let mut read = BlockRead::new(reader::SETTINGS_SEGMENTS, Mode::Confirmed, now);
    let piece = PIECE_REGISTERS[2];
    let a = |addr: u16| addr;
    let b = |addr: u16| addr + 1000;
    // Pass 1: nothing to compare with yet.
    let (sent, done) = pass(&mut read, &mut now, piece, a);
    assert!(done.is_none());
    assert!(sent.len() > 2, "read in pieces: {sent:?}");
    // Pass 2 starts again at the first register, not at the last piece.
    let (sent, done) = pass(&mut read, &mut now, piece, b);
    assert!(
        matches!(&sent[0], Request::ReadIndividual(a) if a[0] == 300),
        "{:?}",
        sent[0]
    );
    assert!(done.is_none(), "differs from pass 1: not confirmed");
    // Pass 3 agrees with pass 2: confirmed, every value from these two passes.
    let (_, done) = pass(&mut read, &mut now, piece, b);
    let block = done.expect("two identical passes");
    assert_eq!(block.start, 300);
    assert_eq!(block.values.len(), 44);
    for (addr, v) in block.iter() {
        assert_eq!(v, b(addr), "register {addr}");
    }
    assert_eq!(read.passes(), 3);
}

#[test]
fn a_pass_after_a_change_of_piece_size_keeps_nothing_of_the_previous_pass() {
    // A whole-span 0x03 pass holds whatever the BMS sends for the reserved
    // registers 16-31; a later pass in 0x09 pieces skips them, so they must
    // read 0 again, not the previous pass's values.
    let mut now = 0;
    let mut read = BlockRead::new(reader::LIVE_SEGMENTS, Mode::Window(10_000_000), now);
    let (sent, done) = pass(&mut read, &mut now, PIECE_REGISTERS[0], |a| 0x7700 + a);
    assert_eq!(sent.len(), 1);
    let whole = done.expect("one request, one block");
    assert_eq!(whole.get(20), Some(0x7700 + 20));
    let (sent, done) = pass(&mut read, &mut now, PIECE_REGISTERS[1], |a| 100 + a);
    assert!(sent.len() > 1);
    let block = done.expect("complete");
    for (addr, v) in block.iter() {
        let want = if (16..=31).contains(&addr) {
            0
        } else {
            100 + addr
        };
        assert_eq!(v, want, "register {addr}");
    }
}

#[test]
fn a_late_reply_after_a_complete_pass_is_not_stored() {
    // Between the end of a pass and the next request the block is lent out
    // unchanged: a reply arriving then (no piece in flight) changes nothing.
    let mut now = 0;
    let mut read = BlockRead::new(reader::LIVE_SEGMENTS, Mode::Window(10_000_000), now);
    let (_, done) = pass(&mut read, &mut now, PIECE_REGISTERS[0], |a| a);
    assert!(done.is_some());
    let stale = RegisterBlock {
        start: 0,
        values: (0..56u16).map(|a| a + 9).collect(),
    };
    assert!(read.on_block(now, &stale).is_none());
    assert!(read.on_pairs(now, &[(0, 1), (1, 2)], None).is_none());
    // The next pass is read afresh.
    let (_, done) = pass(&mut read, &mut now, PIECE_REGISTERS[0], |a| a + 3);
    let block = done.unwrap();
    assert!(block.iter().all(|(a, v)| v == a + 3));
}
