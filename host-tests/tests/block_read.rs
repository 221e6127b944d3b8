//! Block reads whose assembled block is lent in place and whose next pass
//! starts at the next request (the deferred restart): a new pass never keeps a
//! value of the previous one.

use protocol_core::request::Request;
use protocol_core::response::{RegisterBlock, Words};
use tinybms_firmware::bms::reader::{self, BlockRead, Mode, PIECE_REGISTERS};

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

/// As [`answer`], with the time the assembled block's first piece was asked
/// for.
fn answer_at(
    read: &mut BlockRead,
    now: u64,
    request: &Request,
    value: impl Fn(u16) -> u16,
) -> Option<(RegisterBlock, u64)> {
    match request {
        Request::ReadRegisters { start, count } => {
            let values: Words = (*start..*start + u16::from(*count)).map(&value).collect();
            let reply = RegisterBlock {
                start: *start,
                values,
            };
            read.on_block(now, &reply)
                .map(|a| (a.block.clone(), a.started_at))
        }
        Request::ReadIndividual(addresses) => {
            let pairs: Vec<(u16, u16)> = addresses.iter().map(|&a| (a, value(a))).collect();
            read.on_pairs(now, &pairs, None)
                .map(|a| (a.block.clone(), a.started_at))
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

/// One step of a random block read: the next request at a piece size, and what
/// happens to it.
#[derive(Debug, Clone)]
enum Op {
    /// Answered with the values of the pass (`stable`) or with fresh ones.
    Answer { level: usize, stable: bool },
    /// Lost: [`BlockRead::on_failure`].
    Fail { level: usize },
    /// Answered by a reply for another piece (refused).
    Stale { level: usize },
    /// Time passes (a window read may start over).
    Wait(u64),
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        6 => (0..4usize, any::<bool>()).prop_map(|(level, stable)| Op::Answer { level, stable }),
        1 => (0..4usize).prop_map(|level| Op::Fail { level }),
        1 => (0..4usize).prop_map(|level| Op::Stale { level }),
        1 => (0..3_000_000u64).prop_map(Op::Wait),
    ]
}

use proptest::prelude::*;

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, .. ProptestConfig::default() })]

    /// Whatever the order of piece sizes, failures, refused replies and
    /// restarts, an assembled block holds exactly the values stored in its own
    /// pass (reserved gaps 0): never a value of an earlier pass. A window read
    /// holds for each register the last value read for it, every one asked
    /// for within the window.
    #[test]
    fn an_assembled_block_holds_only_its_own_pass(
        which in 0..4usize,
        window in any::<bool>(),
        ops in prop::collection::vec(op(), 1..200),
    ) {
        let segments = [
            reader::LIVE_SEGMENTS,
            reader::SETTINGS_SEGMENTS,
            reader::STATS_SEGMENTS,
            reader::EVENTS_SEGMENTS,
        ][which];
        let mode = if window { Mode::Window(1_000_000) } else { Mode::Confirmed };
        let mut now = 0u64;
        let mut read = BlockRead::new(segments, mode, now);
        let first = segments[0].0;
        let last = segments[segments.len() - 1].1;
        let mut fresh = 1u16;
        // What this pass stored so far.
        let mut pass: std::collections::BTreeMap<u16, u16> = Default::default();
        // Window reads: the last value stored for each address, and when it
        // was asked for.
        let mut latest: std::collections::BTreeMap<u16, (u64, u16)> = Default::default();
        let mut previous_complete: Option<Vec<u16>> = None;
        for op in ops {
            now += 500;
            let level = match op {
                Op::Wait(t) => {
                    now += t;
                    continue;
                }
                Op::Answer { level, .. } | Op::Fail { level } | Op::Stale { level } => level,
            };
            let req = read.next_request(now, PIECE_REGISTERS[level]);
            let addresses: Vec<u16> = match &req {
                Request::ReadRegisters { start, count } => (*start..*start + u16::from(*count)).collect(),
                Request::ReadIndividual(a) => a.to_vec(),
                other => panic!("{other:?}"),
            };
            if addresses[0] == first {
                pass.clear(); // a pass starts (or its first piece is asked again)
            }
            match op {
                Op::Fail { .. } => read.on_failure(),
                Op::Stale { .. } => {
                    let shifted = RegisterBlock {
                        start: addresses[0].wrapping_add(1),
                        values: addresses.iter().map(|_| 0xDEAD).collect(),
                    };
                    prop_assert!(read.on_block(now, &shifted).is_none());
                }
                Op::Answer { stable, .. } => {
                    let value = |a: u16| if stable { a ^ 0x5A5A } else { fresh.wrapping_add(a) };
                    let done = answer_at(&mut read, now, &req, value);
                    for &a in &addresses {
                        pass.insert(a, value(a));
                        latest.insert(a, (now, value(a)));
                    }
                    fresh = fresh.wrapping_add(1000);
                    if window {
                        // Window: every register holds the last value read
                        // for it, all asked for within the window.
                        if let Some((block, started_at)) = done {
                            prop_assert_eq!(block.start, first);
                            for &(x, y) in segments {
                                for a in x..=y {
                                    let (t, v) = latest[&a];
                                    prop_assert_eq!(block.get(a), Some(v), "register {}", a);
                                    prop_assert!(t >= started_at && t - started_at <= 1_000_000,
                                        "register {} asked for at {} in a block from {}", a, t, started_at);
                                }
                            }
                        }
                        continue;
                    }
                    let done = done.map(|(b, _)| b);
                    if let Some(block) = done {
                        prop_assert_eq!(block.start, first);
                        prop_assert_eq!(usize::from(last - first) + 1, block.values.len());
                        for (a, v) in block.iter() {
                            prop_assert_eq!(v, pass.get(&a).copied().unwrap_or(0), "register {}", a);
                        }
                        if !window {
                            // Confirmed: two complete passes agreed.
                            prop_assert_eq!(previous_complete.as_deref(), Some(&block.values[..]));
                        }
                    }
                    if addresses.last() == Some(&last) {
                        // The pass is complete (confirmed or not).
                        let mut v = vec![0u16; usize::from(last - first) + 1];
                        for (a, x) in &pass {
                            v[usize::from(a - first)] = *x;
                        }
                        previous_complete = Some(v);
                    }
                }
                Op::Wait(_) => unreachable!(),
            }
        }
    }
}

/// Answers the piece in flight of `read` (0x09) with `value`, against the
/// published `reference`; returns the assembled block, if the read completed.
fn answer_pairs(
    read: &mut BlockRead,
    now: u64,
    request: &Request,
    value: impl Fn(u16) -> u16,
    reference: Option<&RegisterBlock>,
) -> Option<RegisterBlock> {
    let Request::ReadIndividual(addresses) = request else {
        panic!("a confirmed read asks 0x09 pieces on a bad line: {request:?}");
    };
    let pairs: Vec<(u16, u16)> = addresses.iter().map(|&a| (a, value(a))).collect();
    read.on_pairs(now, &pairs, reference)
        .map(|a| a.block.clone())
}

#[test]
fn a_confirmed_live_piece_that_changed_is_believed_only_when_read_twice_alike() {
    // A CRC collision on a bad line: one reply of a piece carries a cell slightly
    // off, which no consistency check can tell. With `confirm_pieces` the piece
    // is asked again and the pass completes with the values read twice alike.
    let genuine = |a: u16| 33_000 + a;
    let published = RegisterBlock {
        start: 0,
        values: (0..56u16).map(|a| genuine(a) - 7).collect(), // every value changed since
    };
    let mut now = 0;
    let mut read = confirming_live_read(now);
    let piece = PIECE_REGISTERS[3];
    let mut corrupted = false;
    let mut block = None;
    for _ in 0..200 {
        now += 1_000;
        let req = read.next_request(now, piece);
        let Request::ReadIndividual(a) = &req else {
            panic!("{req:?}");
        };
        // The first answer for register 5 is the collision.
        let collide = a.contains(&5) && !corrupted;
        corrupted |= collide;
        let value = |x: u16| {
            if collide && x == 5 {
                genuine(5) + 40
            } else {
                genuine(x)
            }
        };
        if let Some(b) = answer_pairs(&mut read, now, &req, value, Some(&published)) {
            block = Some(b);
            break;
        }
    }
    let block = block.expect("the pass completes");
    assert!(corrupted);
    for (a, v) in block.iter() {
        let want = if (16..=31).contains(&a) {
            0
        } else {
            genuine(a)
        };
        assert_eq!(v, want, "register {a}");
    }
    // 20 pieces, each read twice (every value changed since the last snapshot),
    // and the collided one once more.
    assert_eq!(read.second_reads(), 21);
}

#[test]
fn a_confirmed_live_piece_equal_to_the_published_one_is_believed_at_once() {
    let genuine = |a: u16| 33_000 + a;
    let published = RegisterBlock {
        start: 0,
        values: (0..56u16)
            .map(|a| {
                if (16..=31).contains(&a) {
                    0
                } else {
                    genuine(a)
                }
            })
            .collect(),
    };
    let mut now = 0;
    let mut read = confirming_live_read(now);
    let mut requests = 0;
    let block = loop {
        now += 1_000;
        requests += 1;
        assert!(requests < 100, "the pass never ended");
        let req = read.next_request(now, PIECE_REGISTERS[1]);
        if let Some(b) = answer_pairs(&mut read, now, &req, genuine, Some(&published)) {
            break b;
        }
    };
    assert_eq!(read.second_reads(), 0);
    assert_eq!(block, published);
    // 15-register pieces: 0-14, 15, 32-46, 47-55 (no piece splits a 32-bit value).
    assert!(requests <= 5, "{requests}");
}

/// A live read (60 s window) whose pieces are confirmed, as the bridge makes it.
fn confirming_live_read(now: u64) -> BlockRead {
    let mut read = BlockRead::new(reader::LIVE_SEGMENTS, Mode::Window(60_000_000), now);
    read.confirm_pieces();
    read
}

/// `read` reset in place to the live read with confirmed pieces (a new snapshot).
fn restart_confirming(read: &mut BlockRead, now: u64) {
    read.reset(reader::LIVE_SEGMENTS, Mode::Window(60_000_000), now);
    read.confirm_pieces();
}

/// One pass of a confirmed live read in 2-register pieces against no published
/// block, each piece answered with `value`; returns the assembled block.
fn confirmed_pass(
    read: &mut BlockRead,
    now: &mut u64,
    value: impl Fn(u16) -> u16,
) -> RegisterBlock {
    for _ in 0..200 {
        *now += 1_000;
        let req = read.next_request(*now, PIECE_REGISTERS[3]);
        if let Some(b) = answer_pairs(read, *now, &req, &value, None) {
            return b;
        }
    }
    panic!("the pass never ended");
}

#[test]
fn a_confirmed_piece_equal_to_an_earlier_confirmed_read_is_believed_at_once() {
    // Two reads agree when the second comes a pass later: a value confirmed in an
    // earlier pass (even one that never completed, or was never published)
    // confirms an equal read now. Nothing else does: not the block's initial
    // zeros, not a value from before a reset to another read.
    let mut now = 0;
    let mut read = confirming_live_read(now);
    let a = |x: u16| 33_000 + x;
    confirmed_pass(&mut read, &mut now, a);
    assert_eq!(
        read.second_reads(),
        20,
        "first pass: every piece read twice"
    );
    // The same values again (a new snapshot, the read reset in place).
    restart_confirming(&mut read, now);
    let block = confirmed_pass(&mut read, &mut now, a);
    assert_eq!(read.second_reads(), 0, "equal to the confirmed values");
    assert_eq!(block.get(5), Some(a(5)));
    // One value changed: only its piece is read twice.
    restart_confirming(&mut read, now);
    let b = |x: u16| if x == 9 { 33_333 } else { a(x) };
    let block = confirmed_pass(&mut read, &mut now, b);
    assert_eq!(read.second_reads(), 1);
    assert_eq!(block.get(9), Some(33_333));
    // Zeros are not "confirmed" by the block's initial zeros, and a reset to
    // another read forgets what was confirmed.
    read.reset(reader::STATS_SEGMENTS, Mode::Window(60_000_000), now);
    restart_confirming(&mut read, now);
    confirmed_pass(&mut read, &mut now, |_| 0);
    assert_eq!(read.second_reads(), 20);
}

#[test]
fn values_stored_without_confirmation_never_confirm_a_later_piece() {
    // Only a confirmed 0x09 piece stores values that confirm later reads. A
    // reply stored by copy (a 0x03 piece; the bridge sends none while pieces are
    // confirmed, the read accepts one) makes those registers unconfirmed again.
    let mut now = 0;
    let mut read = confirming_live_read(now);
    let a = |x: u16| 33_000 + x;
    confirmed_pass(&mut read, &mut now, a);
    restart_confirming(&mut read, now);
    // First piece (registers 0-1) answered as a 0x03 block of other values.
    now += 1_000;
    let req = read.next_request(now, PIECE_REGISTERS[3]);
    assert!(matches!(&req, Request::ReadIndividual(x) if x.as_slice() == [0, 1]));
    let copied = RegisterBlock {
        start: 0,
        values: [30_500u16, 30_501].into_iter().collect(),
    };
    assert!(read.on_block(now, &copied).is_none());
    // Next pass: registers 0-1 read with those values must be read twice.
    restart_confirming(&mut read, now);
    confirmed_pass(&mut read, &mut now, |x| match x {
        0 => 30_500,
        1 => 30_501,
        _ => a(x),
    });
    assert_eq!(read.second_reads(), 1);
}

/// The live read on a bad line, one piece per request; `stall_after`: a
/// pause longer than the window before that request. The addresses asked for
/// (first of each piece), the assembled block's start time and the end.
fn window_read(window: u64, stall_after: Option<usize>) -> (Vec<u16>, u64, u64) {
    let mut now = 0;
    let mut read = BlockRead::new(reader::LIVE_SEGMENTS, Mode::Window(window), now);
    let mut asked = Vec::new();
    for i in 0..500 {
        now += if Some(i) == stall_after {
            window + 10_000
        } else {
            1_000
        };
        let req = read.next_request(now, PIECE_REGISTERS[3]);
        let Request::ReadIndividual(a) = &req else {
            panic!("{req:?}");
        };
        asked.push(a[0]);
        if let Some((_, started_at)) = answer_at(&mut read, now, &req, |a| a ^ 0x1234) {
            return (asked, started_at, now);
        }
    }
    panic!("the read never completes");
}

/// Issue 54: a window read that runs late reads its oldest pieces again
/// instead of starting over: on a bad line, where a read takes about as long
/// as the window, starting over threw the good pieces away and snapshots came
/// 30 s apart. The block still lies within the window.
#[test]
fn a_window_read_that_runs_late_reads_its_oldest_pieces_again() {
    let w = 50_000;
    let (clean, _, _) = window_read(w, None);
    let (asked, started_at, end) = window_read(w, Some(3));
    // Three pieces, then the stall: the read goes on where it was...
    assert_eq!(asked[..3], clean[..3]);
    assert_eq!(asked[3], clean[3], "the read started over after the stall");
    // ...and reads only the three stale pieces again, at the end.
    assert_eq!(asked.len(), clean.len() + 3);
    assert_eq!(asked[clean.len()..], clean[..3]);
    assert!(end - started_at <= w);
}
