//! The link engine's rules, against a scripted responder (no simulator): what is
//! sent, when, and how many times.

use protocol_core::frame::{Frame, NackCode};
use protocol_core::request::Request;
use protocol_core::response::Response;
use tinybms_firmware::bms::link::{Completion, Failure, Link, LinkStep, Silence};
use tinybms_firmware::bms::timing::Timing;

fn encode(f: &Frame) -> Vec<u8> {
    let mut b = [0u8; 600];
    let n = f.encode(&mut b).unwrap();
    b[..n].to_vec()
}

/// Runs one transaction. `answer(attempt)` gives the bytes the BMS sends back to
/// the n-th transmission (None = silence). Returns the completion and how many
/// times the request went out.
fn run(
    req: Request,
    silence: Silence,
    answer: impl FnMut(usize) -> Option<Vec<u8>>,
) -> (Result<Response, Failure>, usize, Link) {
    let mut link = Link::new(Timing::default());
    let (c, sends) = transact(&mut link, &mut 0, req, silence, answer);
    (c.result, sends, link)
}

/// [`run`] on a given link from `now` (advanced to the completion): the completion
/// and how many times the request went out.
fn transact(
    link: &mut Link,
    now: &mut u64,
    req: Request,
    silence: Silence,
    mut answer: impl FnMut(usize) -> Option<Vec<u8>>,
) -> (Completion, usize) {
    link.start(*now, req, silence);
    let mut sends = 0;
    for _ in 0..50 {
        match link.step(*now) {
            LinkStep::Send(_) => {
                sends += 1;
                if let Some(bytes) = answer(sends) {
                    *now += 2_000;
                    link.on_bytes(*now, &bytes);
                }
            }
            LinkStep::WaitUntil(t) => *now = t,
            LinkStep::Done(c) => return (c, sends),
            LinkStep::Idle => panic!("idle before done"),
        }
    }
    panic!("no completion");
}

fn live_reply() -> Vec<u8> {
    let req = Request::read_registers(0, 2).unwrap();
    let resp = Response::Registers(protocol_core::response::RegisterBlock {
        start: 0,
        values: heapless::Vec::from_slice(&[33000, 33010]).unwrap(),
    });
    encode(&resp.to_frame(&req).unwrap())
}

#[test]
fn awake_bms_gets_each_request_once() {
    let (r, sends, link) = run(
        Request::read_registers(0, 2).unwrap(),
        Silence::Failure,
        |_| Some(live_reply()),
    );
    assert!(matches!(r, Ok(Response::Registers(_))));
    assert_eq!(sends, 1);
    assert_eq!(link.stats().wakeup_resends, 0);
}

#[test]
fn sleeping_bms_gets_one_wakeup_resend() {
    let (r, sends, link) = run(
        Request::read_registers(0, 2).unwrap(),
        Silence::Failure,
        |n| (n >= 2).then(live_reply),
    );
    assert!(r.is_ok());
    assert_eq!(sends, 2);
    assert_eq!(link.stats().wakeup_resends, 1);
    assert_eq!(link.stats().timeouts, 1);
}

#[test]
fn silent_bms_fails_after_wakeup_and_retries() {
    let (r, sends, link) = run(
        Request::read_registers(0, 2).unwrap(),
        Silence::Failure,
        |_| None,
    );
    assert_eq!(r, Err(Failure::Timeout));
    // 1 + wake-up resend + MAX_RETRIES.
    assert_eq!(
        sends,
        2 + usize::from(tinybms_firmware::bms::timing::MAX_RETRIES)
    );
    assert_eq!(link.consecutive_failures(), 1);
}

#[test]
fn corrupt_read_reply_is_retried_not_woken() {
    let mut bad = live_reply();
    let last = bad.len() - 1;
    bad[last] ^= 0x55;
    let (r, sends, link) = run(
        Request::read_registers(0, 2).unwrap(),
        Silence::Failure,
        |n| Some(if n == 1 { bad.clone() } else { live_reply() }),
    );
    assert!(r.is_ok());
    assert_eq!(sends, 2);
    assert_eq!(link.stats().crc_errors, 1);
    assert_eq!(link.stats().retries, 1);
    assert_eq!(link.stats().wakeup_resends, 0);
}

#[test]
fn write_is_never_resent_after_ack_or_nack() {
    let w = Request::write_individual(&[(315, 3650)]).unwrap();
    let (r, sends, _) = run(w.clone(), Silence::Failure, |_| {
        Some(encode(&Frame::Ack { command: 0x0D }))
    });
    assert_eq!(r, Ok(Response::Ack { command: 0x0D }));
    assert_eq!(sends, 1);
    for code in [NackCode::CommandError, NackCode::CrcError] {
        let (r, sends, _) = run(w.clone(), Silence::Failure, |_| {
            Some(encode(&Frame::Nack {
                command: 0x0D,
                code,
            }))
        });
        assert_eq!(r, Err(Failure::Nack(code)));
        assert_eq!(sends, 1, "{code:?}");
    }
}

#[test]
fn crc_nack_on_a_read_is_retried() {
    let (r, sends, link) = run(
        Request::read_registers(0, 2).unwrap(),
        Silence::Failure,
        |n| {
            Some(if n == 1 {
                encode(&Frame::Nack {
                    command: 0x03,
                    code: NackCode::CrcError,
                })
            } else {
                live_reply()
            })
        },
    );
    assert!(r.is_ok());
    assert_eq!(sends, 2);
    assert_eq!(link.stats().nacks_crc, 1);
}

#[test]
fn reset_silence_is_expected_and_not_resent() {
    let (r, sends, link) = run(
        Request::ResetClear(protocol_core::request::ResetOption::ResetBms),
        Silence::Expected,
        |_| None,
    );
    assert_eq!(r, Err(Failure::Silent));
    assert_eq!(sends, 1);
    assert_eq!(link.consecutive_failures(), 0);
}

#[test]
fn other_frames_are_unsolicited_and_ignored() {
    let (r, sends, link) = run(
        Request::read_registers(0, 2).unwrap(),
        Silence::Failure,
        |_| {
            let mut b = encode(&Frame::data(0x1B, &[1, 0, 2, 0, 3, 0]).unwrap());
            b.extend_from_slice(b"MST:\tEXT1:----\r\n");
            b.extend(live_reply());
            Some(b)
        },
    );
    assert!(r.is_ok());
    assert_eq!(sends, 1);
    assert_eq!(link.stats().unsolicited, 1);
    assert_eq!(link.stats().skipped_bytes, 16);
}

#[test]
fn offline_after_consecutive_failures_and_back() {
    let mut link = Link::new(Timing::default());
    let mut now = 0;
    for i in 0..3 {
        assert!(link.is_online(), "online before failure {i}");
        link.start(now, Request::ReadSoc, Silence::Failure);
        loop {
            match link.step(now) {
                LinkStep::WaitUntil(t) => now = t,
                LinkStep::Send(_) => {}
                LinkStep::Done(c) => {
                    assert_eq!(c.result, Err(Failure::Timeout));
                    break;
                }
                LinkStep::Idle => panic!(),
            }
        }
    }
    assert!(!link.is_online());
    link.start(now, Request::ReadSoc, Silence::Failure);
    assert!(matches!(link.step(now), LinkStep::Send(_)));
    link.on_bytes(
        now + 1000,
        &encode(&Frame::data(0x1A, &[0, 0x7D, 0xF4, 1]).unwrap()),
    );
    assert!(
        matches!(link.step(now + 1000), LinkStep::Done(c) if c.result == Ok(Response::Soc(32_800_000)))
    );
    assert!(link.is_online());
}

#[test]
fn a_late_answer_is_never_taken_for_the_next_request() {
    let mut link = Link::new(Timing::default());
    let reply = |v: u16| {
        let req = Request::read_registers(300, 1).unwrap();
        let resp = Response::Registers(protocol_core::response::RegisterBlock {
            start: 300,
            values: heapless::Vec::from_slice(&[v]).unwrap(),
        });
        encode(&resp.to_frame(&req).unwrap())
    };
    // First copy unanswered in time: wake-up resend, answered at once.
    link.start(
        0,
        Request::read_registers(315, 1).unwrap(),
        Silence::Failure,
    );
    assert!(matches!(link.step(0), LinkStep::Send(_)));
    let LinkStep::WaitUntil(deadline) = link.step(0) else {
        panic!()
    };
    assert!(matches!(link.step(deadline), LinkStep::Send(_)));
    link.on_bytes(deadline + 2_000, &reply(3600));
    assert!(matches!(link.step(deadline + 2_000), LinkStep::Done(c) if c.sends == 2));
    // Next request (same shape: 0x03, one register): it waits until the answer to
    // the first copy would have come...
    let t = deadline + 3_000;
    link.start(
        t,
        Request::read_registers(330, 1).unwrap(),
        Silence::Failure,
    );
    let LinkStep::WaitUntil(quiet) = link.step(t) else {
        panic!("sent during the quiet period")
    };
    assert!(quiet > t);
    // ... which it does, late; it is counted, not used.
    link.on_bytes(t + 10_000, &reply(3600));
    assert_eq!(link.stats().unsolicited, 1);
    assert!(matches!(link.step(quiet), LinkStep::Send(_)));
    link.on_bytes(quiet + 2_000, &reply(0x0A01));
    let LinkStep::Done(c) = link.step(quiet + 2_000) else {
        panic!()
    };
    assert!(matches!(c.result, Ok(Response::Registers(b)) if b.values[0] == 0x0A01));
}

#[test]
fn a_write_is_not_resent_once_anything_came_back() {
    // A damaged echo: the write is not re-sent (the read-back will decide).
    let w = Request::write_registers(315, &[3650]).unwrap();
    let resp = Response::WriteEcho {
        start: 315,
        count: 1,
    };
    let mut echo = encode(&resp.to_frame(&w).unwrap());
    let n = echo.len();
    echo[n - 1] ^= 0x10;
    let (r, sends, _) = run(w.clone(), Silence::Failure, |_| Some(echo.clone()));
    assert!(matches!(r, Err(Failure::Corrupt(_))), "{r:?}");
    assert_eq!(sends, 1);
    // Total silence: no wake-up resend for a write, only the bounded retries.
    let (r, sends, _) = run(w, Silence::Failure, |_| None);
    assert_eq!(r, Err(Failure::Timeout));
    assert_eq!(
        sends,
        1 + usize::from(tinybms_firmware::bms::timing::MAX_RETRIES)
    );
}

#[test]
fn a_frame_for_another_command_does_not_count_as_an_answer() {
    // An unrelated frame during a reset's silence: still silence, no resend.
    let (r, sends, link) = run(
        Request::ResetClear(protocol_core::request::ResetOption::ResetBms),
        Silence::Expected,
        |_| Some(encode(&Frame::data(0x1B, &[1, 0, 2, 0, 3, 0]).unwrap())),
    );
    assert_eq!(r, Err(Failure::Silent));
    assert_eq!(sends, 1);
    assert_eq!(link.stats().unsolicited, 1);
}

#[test]
fn a_wrong_length_answer_waits_for_the_deadline_before_retrying() {
    let req = Request::read_registers(0, 2).unwrap();
    let short = encode(&Frame::data(0x03, &[0, 1]).unwrap());
    let mut link = Link::new(Timing::default());
    link.start(0, req, Silence::Failure);
    assert!(matches!(link.step(0), LinkStep::Send(_)));
    link.on_bytes(2_000, &short);
    // Not re-sent at once: the real answer may still be coming.
    assert!(matches!(link.step(2_000), LinkStep::WaitUntil(_)));
    link.on_bytes(3_000, &live_reply());
    assert!(matches!(link.step(3_000), LinkStep::Done(c) if c.result.is_ok() && c.sends == 1));
    assert_eq!(link.stats().invalid_replies, 1);
}

#[test]
fn a_reply_found_at_the_deadline_is_not_seen_again_by_the_next_request() {
    // The reply hides behind a header that claims a longer frame: it is found
    // only when the deadline cuts that candidate off, and then lent from the
    // decoder's buffer. The next transaction (same request) must not take it
    // again for its own answer.
    let req = Request::read_registers(0, 2).unwrap();
    let mut hidden = vec![0xAA, 0x03, 0x0A];
    hidden.extend(live_reply());
    let mut link = Link::new(Timing::default());
    let mut now = 0u64;
    let (first, _) = transact(&mut link, &mut now, req.clone(), Silence::Failure, |_| {
        Some(hidden.clone())
    });
    assert!(
        matches!(&first.result, Ok(Response::Registers(b)) if b.values[..] == [33000, 33010]),
        "{first:?}"
    );
    assert_eq!(first.sends, 1);
    // Second transaction: the BMS answers other values.
    let fresh = {
        let resp = Response::Registers(protocol_core::response::RegisterBlock {
            start: 0,
            values: heapless::Vec::from_slice(&[1, 2]).unwrap(),
        });
        encode(&resp.to_frame(&req).unwrap())
    };
    let (c, _) = transact(&mut link, &mut now, req, Silence::Failure, |_| {
        Some(fresh.clone())
    });
    assert!(
        matches!(&c.result, Ok(Response::Registers(b)) if b.values[..] == [1, 2]),
        "{c:?}"
    );
}
