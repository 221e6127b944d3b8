//! The BMS event log as the bridge reads it: the replies to 0x11 (newest
//! events), to the one-slot 0x09 reads of a scan and to the full read of the log
//! go to the [`EventTracker`], and every event it finds is reported once
//! ([`Report::NewEvent`], or [`Report::EventHistory`] for the backlog at start).
//!
//! When to read (the event log period, a gap to fill at once) is the schedule's
//! business ([`super::schedule`]); which of the three reads is the tracker's.
//!
//! What was found is also kept in [`KnownEvents`]: the log as far as the bridge
//! knows it, for consumers that list it (the host link's `get events`).

use heapless::{Deque, Vec};
use protocol_core::events::Event;
use protocol_core::request::{AddressList, Request};
use protocol_core::response::{RegisterBlock, Response};
use protocol_core::views::event_log;

use super::Reports;
use crate::bms::event_log::{sort_by_time, EventTracker, Found};
use crate::bms::link::{CompletionRef, Failure};
use crate::bridge::report::Report;

/// The BMS event log as far as the bridge knows it: the start-up history (the
/// confirmed full read of registers 200-297) and every event found since,
/// oldest first, the newest [`EVENT_SLOTS`](protocol_core::registers::EVENT_SLOTS)
/// kept (as many as the BMS's log holds). Emptied when a clear of the BMS's log
/// is ACKed.
#[derive(Debug, Clone, Default)]
pub struct KnownEvents {
    list: Deque<Event, { protocol_core::registers::EVENT_SLOTS }>,
    total: u32,
}

impl KnownEvents {
    /// Events kept, oldest first.
    pub fn iter(&self) -> impl Iterator<Item = &Event> {
        self.list.iter()
    }
    /// The `i`-th kept event, oldest first.
    pub fn get(&self, i: usize) -> Option<&Event> {
        self.list.get(i)
    }
    /// Events kept.
    pub fn len(&self) -> usize {
        self.list.len()
    }
    /// No event kept.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }
    /// Events recorded since start (wrapping): the sequence number the next one
    /// gets. The kept ones are `total - len .. total`.
    pub fn total(&self) -> u32 {
        self.total
    }

    fn push(&mut self, e: Event) {
        if self.list.is_full() {
            let _oldest = self.list.pop_front();
        }
        let _fits = self.list.push_back(e);
        self.total = self.total.wrapping_add(1);
    }

    /// The BMS's log was cleared.
    pub(super) fn clear(&mut self) {
        self.list.clear();
    }
}

/// A reply to 0x11 (the newest events). `expected_clock` is the BMS clock now
/// from the last snapshot, if any (see [`EventTracker::plausible`]).
pub(super) fn on_newest(
    tracker: &mut EventTracker,
    known: &mut KnownEvents,
    c: &CompletionRef<'_>,
    expected_clock: impl FnOnce() -> Option<u32>,
    out: &mut Reports,
) {
    // The BMS may mark events as read when it answers: a reply that was
    // lost, or a request that went out twice, may have hidden some.
    if c.sends > 1 || c.result.is_err() {
        tracker.reply_may_be_lost();
    }
    if let Ok(Response::Events(list)) = &c.result {
        let expected = expected_clock();
        let fresh = tracker.fresh_clock(list.bms_timestamp_s);
        if fresh && EventTracker::plausible(&list.events, list.bms_timestamp_s, expected) {
            tracker.accept_clock(list.bms_timestamp_s);
            let mut found: Vec<Found, { protocol_core::response::MAX_EVENTS }> = Vec::new();
            tracker.on_newest(&list.events, |f| {
                let _fits = found.push(f);
            });
            for f in found {
                report(f, known, out);
            }
        } else {
            tracker.reply_may_be_lost();
        }
    }
}

/// A reply to the 0x09 read of one event slot (two registers).
pub(super) fn on_slot(
    tracker: &mut EventTracker,
    known: &mut KnownEvents,
    result: &Result<Response, Failure>,
    out: &mut Reports,
) {
    if let Ok(Response::Individual(pairs)) = result {
        if let [(_, first), (_, second)] = pairs.as_slice() {
            let mut found: Vec<Found, 1> = Vec::new();
            tracker.on_slot(*first, *second, |f| {
                let _fits = found.push(f);
            });
            for f in found {
                report(f, known, out);
            }
        }
    }
}

/// The whole event log, read and confirmed as a register block.
pub(super) fn on_full(
    tracker: &mut EventTracker,
    known: &mut KnownEvents,
    b: &RegisterBlock,
    out: &mut Reports,
) {
    if let Ok(slots) = event_log(b) {
        let mut events: Vec<(u8, Event), { protocol_core::registers::EVENT_SLOTS }> = Vec::new();
        for s in &slots {
            let _fits = events.push((s.slot, s.event));
        }
        let mut found: Vec<Found, { protocol_core::response::MAX_EVENTS }> = Vec::new();
        tracker.on_full_slots(&events, |f| {
            let _fits = found.push(f);
        });
        for f in found {
            if let Found::History { .. } = f {
                // The whole log is the history: keep it, oldest first.
                let mut history: Vec<Event, { protocol_core::registers::EVENT_SLOTS }> =
                    events.iter().map(|(_, e)| *e).collect();
                sort_by_time(&mut history);
                for e in history {
                    known.push(e);
                }
            }
            report(f, known, out);
        }
    }
}

fn report(f: Found, known: &mut KnownEvents, out: &mut Reports) {
    match f {
        Found::New(e) => {
            known.push(e);
            out.push(Report::NewEvent(e));
        }
        Found::History { count, newest } => out.push(Report::EventHistory { count, newest }),
    }
}

/// A 0x09 read of one event slot (two registers).
pub(super) fn slot_request(slot: u8) -> Request {
    let a = protocol_core::registers::EVENTS_FIRST + 2 * u16::from(slot);
    let mut addresses = AddressList::new();
    let _ = addresses.push(a);
    let _ = addresses.push(a + 1);
    Request::ReadIndividual(addresses)
}
