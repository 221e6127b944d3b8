//! Which BMS events have been reported, so that each is reported exactly once.
//!
//! Events are identified by (timestamp, id). A high-water mark (the newest
//! timestamp reported, with the ids already reported at that very second) tells
//! new from old. The bridge does not depend on how a unit's 0x11 ("newest
//! events") behaves: the simulator marks events as read when it answers, and a
//! real unit may do the same. So whenever a 0x11 reply may have been lost — the
//! transaction failed, or went out more than once — the tracker asks for an
//! idempotent read of the whole log (registers 200-297, confirmed by two identical
//! passes), and reports what is newer than the mark. The same full read gives the
//! start-up history: one INFO line, once.
//!
//! A full read is 98 registers: on a bad line that is dozens of requests. So a
//! gap is first filled by a scan: the slot that held the newest event is read
//! again (if it still holds it, the log has not shifted), then the slots after it,
//! one by one, until an empty slot or an older event (an append-ordered log or a
//! ring). Each slot is believed when two reads of it agree. A log that shifted or
//! was cleared falls back to the full read.

use heapless::Vec;
use protocol_core::events::{Event, EventId};

/// Event timestamps are 24 bits (Rev D §1.1.9) and wrap after 194 days: compare
/// them as serial numbers (RFC 1982 style), `a` newer than `b`.
pub fn ts_newer(a: u32, b: u32) -> bool {
    let d = a.wrapping_sub(b) & 0x00FF_FFFF;
    d != 0 && d < 0x0080_0000
}

/// Ids remembered at the high-water mark's second.
const SAME_SECOND: usize = 8;

/// How far the BMS clock in a 0x11 reply may be from the one the live block
/// implies, seconds. A damaged reply with a valid CRC has a random clock.
pub const CLOCK_TOLERANCE_S: u32 = 120;

/// What a batch of events means for the log.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Found {
    /// An event not reported before.
    New(Event),
    /// The start-up history: how many events the log held, and the newest.
    History {
        /// Events in the log at start-up.
        count: u8,
        /// The newest of them.
        newest: Option<Event>,
    },
}

/// Where a gap scan is.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
enum Scan {
    /// No scan: a full read (if a gap is open).
    #[default]
    Off,
    /// Reading this slot; the previous read of it, to compare with.
    Slot {
        slot: u8,
        first_read: Option<(u16, u16)>,
        /// The slot that held the mark: checking it still does.
        anchor: bool,
        /// Slots visited in this scan (bounds it to one turn of the log).
        visited: u8,
    },
}

/// The tracker. See the module documentation.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct EventTracker {
    history_done: bool,
    mark: Option<u32>,
    at_mark: Vec<u8, SAME_SECOND>,
    /// Slot of the newest event a full read or a scan saw there, and the event.
    anchor: Option<(u8, Event)>,
    gap: bool,
    scan: Scan,
    /// BMS clock of the last 0x11 reply believed.
    last_clock: Option<u32>,
}

impl EventTracker {
    /// A tracker that has seen nothing: the first full read is the history.
    pub const fn new() -> Self {
        Self {
            history_done: false,
            mark: None,
            at_mark: Vec::new(),
            anchor: None,
            gap: false,
            scan: Scan::Off,
            last_clock: None,
        }
    }

    /// A 0x11 reply's clock must be newer than the last one believed: an older
    /// or equal one is a stale copy (a repeated or duplicated earlier reply taken
    /// for this one), and then this request's real answer — whose events the BMS
    /// may have marked as read — was lost: treat it so.
    pub fn fresh_clock(&self, bms_clock_s: u32) -> bool {
        self.last_clock.is_none_or(|c| bms_clock_s > c)
    }

    /// Remembers the clock of a believed 0x11 reply.
    pub fn accept_clock(&mut self, bms_clock_s: u32) {
        self.last_clock = Some(bms_clock_s);
    }

    /// A gap or the start-up history is open: the next events read is a scan or
    /// a full read, not 0x11.
    pub fn needs_full_read(&self) -> bool {
        !self.history_done || self.gap
    }

    /// The slot a gap scan wants to read next (two registers from
    /// `200 + 2 * slot`), or `None` when a full read is due instead.
    pub fn scan_slot(&self) -> Option<u8> {
        match self.scan {
            Scan::Slot { slot, .. } if self.needs_full_read() => Some(slot),
            _ => None,
        }
    }

    /// A 0x11 transaction went out and its reply may be lost (failed, or sent
    /// more than once).
    pub fn reply_may_be_lost(&mut self) {
        if !self.gap {
            self.gap = true;
            self.scan = match (self.history_done, self.anchor) {
                (true, Some((slot, _))) => Scan::Slot {
                    slot,
                    first_read: None,
                    anchor: true,
                    visited: 0,
                },
                _ => Scan::Off,
            };
        }
    }

    /// A read of the scanned slot: its two registers. Calls `found` for a new
    /// event once two reads of the slot agree.
    pub fn on_slot(&mut self, first: u16, second: u16, mut found: impl FnMut(Found)) {
        let Scan::Slot {
            slot,
            first_read,
            anchor,
            visited,
        } = self.scan
        else {
            return;
        };
        if first_read != Some((first, second)) {
            // Believed only when two reads agree.
            self.scan = Scan::Slot {
                slot,
                first_read: Some((first, second)),
                anchor,
                visited,
            };
            return;
        }
        let both = protocol_core::registers::u32_from_words(first, second);
        let empty = both == 0 || both == u32::MAX;
        let e = Event::from_registers(first, second);
        let next = |s: u8| {
            if usize::from(s) + 1 >= protocol_core::registers::EVENT_SLOTS {
                0
            } else {
                s + 1
            }
        };
        let Some((_, anchor_event)) = self.anchor else {
            self.scan = Scan::Off;
            return;
        };
        if anchor {
            self.scan = if !empty && e == anchor_event {
                Scan::Slot {
                    slot: next(slot),
                    first_read: None,
                    anchor: false,
                    visited: 0,
                }
            } else {
                // Shifted or cleared: only a full read can tell what is new.
                Scan::Off
            };
            return;
        }
        if empty || ts_newer(anchor_event.timestamp_s, e.timestamp_s) {
            // The end of what was appended after the anchor (an empty slot, or
            // the oldest event of a ring): the gap is filled.
            self.gap = false;
            self.scan = Scan::Off;
            return;
        }
        if !EventId::KNOWN.contains(&e.id) {
            self.scan = Scan::Off; // not believable: full read
            return;
        }
        if self.is_new(&e) {
            self.take(&e);
            found(Found::New(e));
        }
        self.anchor = Some((slot, e));
        let visited = visited.saturating_add(1);
        self.scan = if usize::from(visited) >= protocol_core::registers::EVENT_SLOTS {
            Scan::Off
        } else {
            Scan::Slot {
                slot: next(slot),
                first_read: None,
                anchor: false,
                visited,
            }
        };
    }

    /// True when the high-water mark has not seen this event.
    fn is_new(&self, e: &Event) -> bool {
        match self.mark {
            None => true,
            Some(m) if ts_newer(e.timestamp_s, m) => true,
            Some(m) if e.timestamp_s == m => !self.at_mark.contains(&e.id.raw()),
            Some(_) => false,
        }
    }

    fn take(&mut self, e: &Event) {
        match self.mark {
            Some(m) if m == e.timestamp_s => {
                if self.at_mark.is_full() {
                    let _ = self.at_mark.remove(0);
                }
                let _fits = self.at_mark.push(e.id.raw());
            }
            _ => {
                self.mark = Some(e.timestamp_s);
                self.at_mark.clear();
                let _fits = self.at_mark.push(e.id.raw());
            }
        }
    }

    /// Checks a 0x11 reply before anything in it is believed: known ids, no event
    /// after the reply's own clock, and that clock near `expected_clock_s` (the
    /// lifetime counter of the live block, moved on by the time since). A reply
    /// that fails is treated as lost: a full read follows.
    pub fn plausible(events: &[Event], bms_clock_s: u32, expected_clock_s: Option<u32>) -> bool {
        if let Some(expected) = expected_clock_s {
            if bms_clock_s.abs_diff(expected & Event::MAX_TIMESTAMP) > CLOCK_TOLERANCE_S
                && bms_clock_s.abs_diff(expected) > CLOCK_TOLERANCE_S
            {
                return false;
            }
        }
        events.iter().all(|e| {
            EventId::KNOWN.contains(&e.id)
                && !ts_newer(e.timestamp_s, bms_clock_s & Event::MAX_TIMESTAMP)
        })
    }

    /// Events from a 0x11 reply (already checked with [`EventTracker::plausible`]).
    /// Calls `found` for each event not reported before, oldest first.
    pub fn on_newest(&mut self, events: &[Event], found: impl FnMut(Found)) {
        if !self.history_done {
            // The history comes from a full read; until then, hold nothing back:
            // a full read will follow and settle it.
            self.gap = true;
            return;
        }
        self.report_new(events, found);
    }

    fn report_new(&mut self, events: &[Event], mut found: impl FnMut(Found)) {
        self.take_new(events, |e| found(Found::New(e)));
    }

    /// Raises the mark over every event not seen before, oldest first whatever
    /// order `events` has, calling `taken` for each.
    fn take_new(&mut self, events: &[Event], mut taken: impl FnMut(Event)) {
        let mut sorted: Vec<Event, { protocol_core::response::MAX_EVENTS }> = Vec::new();
        for e in events {
            let _fits = sorted.push(*e);
        }
        sort_by_time(&mut sorted);
        for e in &sorted {
            if self.is_new(e) {
                self.take(e);
                taken(*e);
            }
        }
    }

    /// The whole log, from a confirmed read of registers 200-297, as (slot,
    /// event). The first one is the start-up history (one [`Found::History`]);
    /// later ones fill gaps.
    pub fn on_full_slots(&mut self, slots: &[(u8, Event)], found: impl FnMut(Found)) {
        let mut events: Vec<Event, { protocol_core::registers::EVENT_SLOTS }> = Vec::new();
        for (_, e) in slots {
            let _fits = events.push(*e);
        }
        self.on_full(&events, found);
        // Where the newest event sits, for the next gap scan.
        let mut anchor: Option<(u8, Event)> = None;
        for &(slot, e) in slots {
            if anchor.is_none_or(|(_, a)| !ts_newer(a.timestamp_s, e.timestamp_s)) {
                anchor = Some((slot, e));
            }
        }
        self.anchor = anchor;
        self.scan = Scan::Off;
    }

    /// The whole log (see [`EventTracker::on_full_slots`]), without slot numbers.
    pub fn on_full(&mut self, events: &[Event], mut found: impl FnMut(Found)) {
        if self.history_done {
            self.report_new(events, found);
        } else {
            let mut newest: Option<Event> = None;
            for e in events {
                if newest.is_none_or(|n| ts_newer(e.timestamp_s, n.timestamp_s)) {
                    newest = Some(*e);
                }
            }
            // Everything in the log now is history: raise the mark over all of it.
            self.take_new(events, |_| {});
            self.history_done = true;
            found(Found::History {
                count: events.len().min(usize::from(u8::MAX)) as u8,
                newest,
            });
        }
        self.gap = false;
    }
}

/// Insertion sort by timestamp (serial-number order), stable; at most 63 items.
pub(crate) fn sort_by_time(v: &mut [Event]) {
    for i in 1..v.len() {
        let mut j = i;
        while j > 0 {
            let (Some(a), Some(b)) = (v.get(j - 1), v.get(j)) else {
                break;
            };
            if ts_newer(a.timestamp_s, b.timestamp_s) {
                v.swap(j - 1, j);
                j -= 1;
            } else {
                break;
            }
        }
    }
}
