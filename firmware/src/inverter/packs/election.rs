//! Who of the bridges speaks to the inverter.

use super::heard::Packs;
use super::summary::MAX_NODES;
use crate::Instant;

/// A speaker (or a lower node) counts as silent for the election after this
/// long without a summary, µs: short enough that a new speaker's first 0x351
/// comes within 2.5 s of the last one (a GX stops after 3 s without).
pub const SPEAKER_LOST_US: Instant = 1_500_000;
/// After a start or a bus-off recovery, a node listens this long before it may
/// speak, µs.
pub const LISTEN_US: Instant = 3 * crate::SECOND;
/// A node that heard two or more other nodes and now hears none at all
/// (the whole bus fell silent at once) more likely has a deaf receiver of
/// its own (an overrun, a stalled driver) than lost every other bridge at
/// the same moment: it waits this long after the last frame it heard before
/// it takes over, µs. A real takeover after one bridge is lost is not
/// delayed: the others are still heard.
pub const DEAF_GUARD_US: Instant = 20 * crate::SECOND;

/// Who speaks to the inverter (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Election {
    listening_since: Instant,
    speaking: bool,
}

impl Election {
    /// Started (or recovered) at `now`: listening.
    pub const fn new(now: Instant) -> Self {
        Self {
            listening_since: now,
            speaking: false,
        }
    }

    /// Listen again from `now` (a bus-off recovery): not speaking.
    pub fn restart(&mut self, now: Instant) {
        self.listening_since = now;
        self.speaking = false;
    }

    /// Whether this bridge speaks now.
    pub fn speaking(&self) -> bool {
        self.speaking
    }

    /// It has listened for [`LISTEN_US`] since it started or recovered: it
    /// knows the other packs.
    pub fn listened(&self, now: Instant) -> bool {
        now.saturating_sub(self.listening_since) >= LISTEN_US
    }

    /// Decides at `now` from what has been heard. `able`: this bridge sends
    /// its own summary this period (it has BMS data and no other bridge has
    /// its number) — one that the others cannot hear must not speak.
    pub fn update(&mut self, now: Instant, packs: &Packs, able: bool) -> bool {
        let me = packs.node();
        let heard = |n: u8| packs.heard_speaking(now, n, SPEAKER_LOST_US);
        let speaks = |n: u8| n != me && heard(n) == Some(true);
        self.speaking = if me == 0 || !able {
            false
        } else if self.speaking {
            !(1..me).any(speaks)
        } else {
            let listened = now.saturating_sub(self.listening_since) >= LISTEN_US;
            let deaf = packs.others_heard_within(now, SPEAKER_LOST_US) == 0
                && packs.others_heard_within(now, DEAF_GUARD_US) >= 2;
            // Somebody's inverter frames heard: a speaker is there, even if
            // its summaries were lost (a bus that loses frames).
            let spoken = packs.limits_heard_within(now, SPEAKER_LOST_US);
            listened
                && !deaf
                && !spoken
                && !(1..=MAX_NODES).any(speaks)
                && !(1..me).any(|n| heard(n).is_some())
        };
        self.speaking
    }
}
