//! The event log and the statistics the BMS keeps.

use super::*;

impl SimBms {
    pub(super) fn lifetime(&self) -> u32 {
        self.u32_at(32)
    }

    pub(super) fn push_event(&mut self, e: Event) {
        self.logged.push((self.now, e));
        self.event_seq += 1;
        self.events.push_back((self.event_seq, e));
        while self.events.len() > EVENT_SLOTS {
            self.events.pop_front();
        }
    }

    pub(super) fn log_event(&mut self, id: EventId) {
        let timestamp_s = self.lifetime() & Event::MAX_TIMESTAMP;
        self.push_event(Event { timestamp_s, id });
        self.stats.events_logged += 1;
        self.write_event_registers();
    }

    /// Mirrors the log into registers 200-297 (Rev D §3.3): first register =
    /// timestamp bits 0-15, second = bits 16-23 (low byte) and the ID (high byte).
    pub(super) fn write_event_registers(&mut self) {
        for slot in 0..EVENT_SLOTS {
            let (first, second) = match self.events.get(slot) {
                Some(&(_, e)) => {
                    let [t0, t1, t2, id] = e.to_bytes();
                    (u16::from_le_bytes([t0, t1]), u16::from_le_bytes([t2, id]))
                }
                None => (EMPTY_SLOT, EMPTY_SLOT),
            };
            let a = EVENTS_FIRST + 2 * slot as u16;
            self.set_reg(a, first);
            self.set_reg(a + 1, second);
        }
    }

    pub(super) fn clear_events(&mut self) {
        self.events.clear();
        self.newest_read_seq = self.event_seq;
        self.write_event_registers();
    }

    pub(super) fn clear_statistics(&mut self) {
        for a in 100..=112 {
            self.set_reg(a, 0);
        }
        let t = self.live.pack_temp_c() as u8;
        self.set_reg(113, u16::from_le_bytes([t, t]));
        let now = self.lifetime();
        self.set_reg(116, now as u16);
        self.set_reg(117, (now >> 16) as u16);
    }

    pub(super) fn event_list(&mut self, newest_only: bool) -> EventList {
        let mut chosen: Vec<Event> = self
            .events
            .iter()
            .filter(|&&(seq, _)| !newest_only || seq > self.newest_read_seq)
            .map(|&(_, e)| e)
            .collect();
        if newest_only {
            let keep = self.config.newest_events_max.min(MAX_EVENTS);
            let skip = chosen.len().saturating_sub(keep);
            chosen.drain(..skip);
            self.newest_read_seq = self.event_seq;
        }
        let mut events = heapless::Vec::new();
        for e in chosen {
            // At most EVENT_SLOTS (49) <= MAX_EVENTS (63) events: always fits.
            if events.push(e).is_err() {
                break;
            }
        }
        EventList {
            bms_timestamp_s: self.lifetime(),
            events,
        }
    }
}
