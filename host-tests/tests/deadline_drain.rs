//! The deadline-drain rule of the chip shell (issue 11), through the sans-IO
//! interface: when the deadline timer wins the race against the UART read, the
//! bytes already in the RX FIFO are handed to [`Bridge::handle_rx`] *before*
//! [`Bridge::poll`] handles the deadline.
//!
//! Each case runs twice on the same bytes and the same times: once in the order
//! `bridge_task` uses (drain, then poll), once in the order it used before (poll,
//! and the bytes only later). The first must complete the transaction the bytes
//! belong to; the second shows what the rule prevents (a resend the awake BMS
//! answers twice, or a retry after a cut-off reply), so the tests fail if the
//! order stops mattering or the drained bytes stop completing the transaction.

use host_tests::sim::{PackModel, SimBms, SimConfig};
use tinybms_firmware::bms::timing::{Timing, BYTE_TIME_US};
use tinybms_firmware::bridge::Action;
use tinybms_firmware::{Bridge, Report};

/// The bridge's first request, sent at time 0; returns (request bytes, time its
/// last byte left, deadline the bridge then waits for).
fn first_request(bridge: &mut Bridge) -> (Vec<u8>, u64, u64) {
    let Action::Transmit(req) = bridge.poll(0) else {
        panic!("the bridge starts by sending a request");
    };
    let req = req.to_vec();
    let sent = BYTE_TIME_US * req.len() as u64;
    let Action::WaitUntil(deadline) = bridge.poll(sent) else {
        panic!("after a request the bridge waits");
    };
    assert!(deadline > sent);
    (req, sent, deadline)
}

/// What the simulated BMS answers to `req` (the whole reply, however long it takes).
fn reply_to(req: &[u8]) -> Vec<u8> {
    let mut sim = SimBms::new(PackModel::LiIon_14S, SimConfig::default(), 11);
    let end = sim.host_send(0, req);
    let mut out = Vec::new();
    sim.take_output(end + 1_000_000, &mut out);
    assert!(out.len() >= 5, "the simulated BMS answers the request");
    out
}

/// The version reply was taken as the answer to the request (the bridge
/// believes the version block once a second read agrees, so the first accepted
/// reply shows as a reply in the link counters and as no link error).
fn accepted(bridge: &mut Bridge) -> bool {
    let errors = std::iter::from_fn(|| bridge.next_report())
        .filter(|r| matches!(r, Report::LinkError { .. }))
        .count();
    bridge.link_stats().replies >= 1 && errors == 0
}

/// The reply was fully received just before the response deadline, but below the
/// FIFO threshold and within the RX timeout, so `read_async` had not returned it
/// when the timer fired.
#[test]
fn a_whole_reply_in_the_fifo_at_the_response_deadline_completes_its_request() {
    let mut bridge = Bridge::new(Timing::default(), 0);
    let (req, _, deadline) = first_request(&mut bridge);
    let reply = reply_to(&req);

    // Drain, then poll (bridge_task now).
    bridge.handle_rx(deadline, &reply);
    // The next request may be the same read again: the bridge believes the
    // version block once a second read agrees. It is a new transaction, not a
    // resend: no timeout, no wake-up resend, no retry.
    let _next = bridge.poll(deadline);
    let s = bridge.link_stats();
    assert_eq!(
        (
            s.requests,
            s.replies,
            s.timeouts,
            s.wakeup_resends,
            s.retries
        ),
        (2, 1, 0, 0, 0)
    );
    let _ = &req;
    assert!(accepted(&mut bridge));
}

#[test]
fn the_same_reply_handed_in_after_the_deadline_costs_a_resend_answered_twice() {
    let mut bridge = Bridge::new(Timing::default(), 0);
    let (req, _, deadline) = first_request(&mut bridge);
    let reply = reply_to(&req);

    // Poll first (bridge_task before issue 11): the deadline sees silence.
    let Action::Transmit(again) = bridge.poll(deadline) else {
        panic!("silence at the deadline: the wake-up resend goes out");
    };
    assert_eq!(again.as_slice(), req.as_slice());
    let resent_at = deadline + BYTE_TIME_US * again.len() as u64;
    // The FIFO's bytes are only read after the resend: they answer the first copy
    // but are taken for the answer to the second...
    bridge.handle_rx(resent_at, &reply);
    let _ = bridge.poll(resent_at);
    let s = bridge.link_stats();
    assert_eq!((s.timeouts, s.wakeup_resends), (1, 1));
    assert!(accepted(&mut bridge));
    // ...and the awake BMS answers the second copy as well: a stray reply on the
    // line (what HARDWARE-NOTES "Sleep" warns about).
    let unsolicited_before = s.unsolicited;
    bridge.handle_rx(resent_at + 2_000, &reply);
    assert_eq!(bridge.link_stats().unsolicited, unsolicited_before + 1);
}

/// Splits a reply so that its first part arrives well before the deadline and
/// the rest sits in the FIFO when the reply-idle-gap deadline fires.
fn split_reply(bridge: &mut Bridge) -> (Vec<u8>, Vec<u8>, Vec<u8>, u64) {
    let (req, sent, _) = first_request(bridge);
    let reply = reply_to(&req);
    let (head, tail) = reply.split_at(3);
    let t1 = sent + 2_000;
    bridge.handle_rx(t1, head);
    let Action::WaitUntil(gap_deadline) = bridge.poll(t1) else {
        panic!("a partial reply: the bridge waits for the rest");
    };
    assert!(gap_deadline > t1);
    (req, head.to_vec(), tail.to_vec(), gap_deadline)
}

#[test]
fn the_rest_of_a_reply_in_the_fifo_at_the_idle_gap_deadline_completes_it() {
    let mut bridge = Bridge::new(Timing::default(), 0);
    let (req, _, tail, gap_deadline) = split_reply(&mut bridge);

    bridge.handle_rx(gap_deadline, &tail);
    let _next = bridge.poll(gap_deadline);
    let s = bridge.link_stats();
    assert_eq!(
        (
            s.replies,
            s.retries,
            s.timeouts,
            s.crc_errors,
            s.framing_errors
        ),
        (1, 0, 0, 0, 0)
    );
    let _ = &req;
    assert!(accepted(&mut bridge));
}

#[test]
fn the_rest_handed_in_after_the_idle_gap_deadline_is_lost_and_the_read_retried() {
    let mut bridge = Bridge::new(Timing::default(), 0);
    let (req, _, tail, gap_deadline) = split_reply(&mut bridge);

    let Action::Transmit(again) = bridge.poll(gap_deadline) else {
        panic!("a cut-off reply at the deadline: the read is retried");
    };
    assert_eq!(again.as_slice(), req.as_slice());
    let resent_at = gap_deadline + BYTE_TIME_US * again.len() as u64;
    bridge.handle_rx(resent_at, &tail);
    let s = bridge.link_stats();
    assert_eq!(s.retries, 1);
    assert_eq!(s.replies, 0, "the tail alone answers nothing");
    assert!(
        s.crc_errors + s.framing_errors + s.skipped_bytes > 0,
        "the cut-off head and the orphan tail show up as line errors"
    );
    assert!(!accepted(&mut bridge));
}
