//! What this bridge hears of the other packs: summaries reassembled from
//! their frames, and who was heard when.

use super::battery::Member;
use super::summary::{from_id, Summary, SummaryError, MAX_NODES, SEQ_MASK, SUMMARY_FRAMES};
use crate::Instant;

/// A pack whose last complete summary is older than this is lost and leaves
/// the battery, µs (one summary may go missing).
pub const PACK_LOST_US: Instant = 2_500_000;

/// Frames of one node being collected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Partial {
    seq: u8,
    have: u8,
    started: Instant,
    data: [[u8; 8]; SUMMARY_FRAMES],
}

/// The frames of one summary go out back to back: a summary still incomplete
/// this long after its first frame is dropped, µs.
pub const PARTIAL_MAX_US: Instant = 200 * crate::MS;

/// What is known of one node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Heard {
    /// Its last complete summary.
    pub summary: Summary,
    /// When its last frame arrived.
    pub at: Instant,
    /// CCL and DCL of its last summary without a fault, 0.1 A.
    pub closed: Option<(u16, u16)>,
}

/// What a received frame was.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Received {
    /// Not a summary frame.
    NotSummary,
    /// A frame of a summary still incomplete.
    Partial,
    /// The last frame of a summary: taken.
    Complete(u8),
    /// The last frame of a summary: taken, and one of its current limits is
    /// 0 where the node's last summary had it above 0 (a stop the speaker
    /// passes on at once, not a period later).
    Stops(u8),
    /// A summary from this bridge's own node number: another bridge is
    /// configured with the same number.
    DuplicateNode,
    /// Refused.
    Refused(u8, SummaryError),
}

/// The summaries heard from the other nodes.
#[derive(Debug, Clone)]
pub struct Packs {
    node: u8,
    partial: [Option<Partial>; MAX_NODES as usize],
    heard: [Option<Heard>; MAX_NODES as usize],
    /// When any 8-byte frame of each node last arrived (the election's
    /// "heard": one refused or incomplete summary does not silence a node).
    frame_at: [Option<Instant>; MAX_NODES as usize],
    refused: u32,
    duplicates: u32,
    limits_at: Option<Instant>,
}

impl Packs {
    /// The table of bridge `node` (1..=8; 0 = alone, hears nobody).
    pub const fn new(node: u8) -> Self {
        Self {
            node,
            partial: [None; MAX_NODES as usize],
            heard: [None; MAX_NODES as usize],
            frame_at: [None; MAX_NODES as usize],
            refused: 0,
            duplicates: 0,
            limits_at: None,
        }
    }

    /// This bridge's node number.
    pub fn node(&self) -> u8 {
        self.node
    }

    /// Summaries refused so far (bad length or content).
    pub fn refused(&self) -> u32 {
        self.refused
    }

    /// Summaries heard with this bridge's own node number.
    pub fn duplicates(&self) -> u32 {
        self.duplicates
    }

    /// A frame from the bus.
    pub fn on_frame(&mut self, now: Instant, id: u16, data: &[u8]) -> Received {
        {
            use crate::inverter::dialect::victron::{
                ID_ALARMS, ID_LIMITS, ID_MEASUREMENTS, ID_SOC,
            };
            use crate::inverter::dialect::{growatt, pylon};
            const SPEAKERS: [u16; 7] = [
                ID_LIMITS,
                ID_SOC,
                ID_MEASUREMENTS,
                ID_ALARMS,
                pylon::ID_ALARMS,
                growatt::ID_LIMITS,
                growatt::ID_MEASUREMENTS,
            ];
            if SPEAKERS.contains(&id) && self.node != 0 {
                // A frame only a speaker sends, from another bridge:
                // somebody speaks.
                self.limits_at = Some(now);
            }
        }
        let Some((node, k)) = from_id(id) else {
            return Received::NotSummary;
        };
        if self.node == 0 {
            return Received::NotSummary;
        }
        // Frames on this bridge's own identifiers: assembled like the others,
        // and only a whole, valid summary says another bridge has this number
        // (one stray frame neither silences this bridge nor counts as heard).
        let own = node == self.node;
        let i = usize::from(node - 1);
        let Ok(d) = <[u8; 8]>::try_from(data) else {
            self.refused = self.refused.saturating_add(1);
            if let Some(p) = self.partial.get_mut(i) {
                *p = None;
            }
            return Received::Refused(node, SummaryError::Length);
        };
        if !own {
            if let Some(t) = self.frame_at.get_mut(i) {
                *t = Some(now);
            }
        }
        let seq = d[7] & SEQ_MASK;
        let Some(slot) = self.partial.get_mut(i) else {
            return Received::NotSummary;
        };
        // A frame of the same sequence only continues a summary that is young
        // and lacks that frame: never a mixture of two sends (a bridge that
        // restarted, one frame of a burst lost).
        let mut p = match *slot {
            Some(p)
                if p.seq == seq
                    && p.have & (1 << k) == 0
                    && now.saturating_sub(p.started) <= PARTIAL_MAX_US =>
            {
                p
            }
            _ => Partial {
                seq,
                have: 0,
                started: now,
                data: [[0; 8]; SUMMARY_FRAMES],
            },
        };
        if let Some(dst) = p.data.get_mut(usize::from(k)) {
            *dst = d;
        }
        p.have |= 1 << k;
        if p.have != (1 << SUMMARY_FRAMES) - 1 {
            *slot = Some(p);
            return Received::Partial;
        }
        *slot = None;
        match Summary::from_frames(&p.data) {
            Ok(_) if own => {
                self.duplicates = self.duplicates.saturating_add(1);
                Received::DuplicateNode
            }
            Ok(summary) => {
                let mut stops = false;
                if let Some(h) = self.heard.get_mut(i) {
                    if let Some(last) = h.as_ref().map(|h| h.summary.limits) {
                        let fell = |was: u16, is: u16| was > 0 && is == 0;
                        stops = fell(last.ccl_da, summary.limits.ccl_da)
                            || fell(last.dcl_da, summary.limits.dcl_da);
                    }
                    let before = h.as_ref().and_then(|h| h.closed);
                    let closed = if summary.fault {
                        before
                    } else {
                        Some((summary.limits.ccl_da, summary.limits.dcl_da))
                    };
                    *h = Some(Heard {
                        summary,
                        at: now,
                        closed,
                    });
                }
                if stops {
                    Received::Stops(node)
                } else {
                    Received::Complete(node)
                }
            }
            Err(e) => {
                self.refused = self.refused.saturating_add(1);
                Received::Refused(node, e)
            }
        }
    }

    /// Node `node`'s last summary if heard within [`PACK_LOST_US`].
    pub fn alive(&self, now: Instant, node: u8) -> Option<&Summary> {
        self.heard_within(now, node, PACK_LOST_US)
    }

    /// Node `node`'s last summary if heard within `us`.
    pub fn heard_within(&self, now: Instant, node: u8, us: Instant) -> Option<&Summary> {
        let h = self
            .heard
            .get(usize::from(node.checked_sub(1)?))?
            .as_ref()?;
        (now.saturating_sub(h.at) <= us).then_some(&h.summary)
    }

    /// Every node ever heard (1..=8) as a [`Member`] of the battery: its
    /// last summary, whether it is alive (any frame of it heard within
    /// [`PACK_LOST_US`]: on a bus that loses frames a bridge still sending is
    /// there, its last whole summary counting as long as its data is fresh),
    /// and how long ago that summary came.
    pub fn known(&self, now: Instant) -> impl Iterator<Item = (u8, Member)> + '_ {
        self.heard.iter().enumerate().filter_map(move |(i, h)| {
            let h = h.as_ref()?;
            let ago = now.saturating_sub(h.at);
            let frame_ago = self
                .frame_at
                .get(i)
                .copied()
                .flatten()
                .map_or(ago, |t| now.saturating_sub(t).min(ago));
            Some((
                i as u8 + 1,
                Member {
                    summary: h.summary,
                    alive: frame_ago <= PACK_LOST_US,
                    heard_ago_us: ago,
                    closed_limits: h.closed,
                },
            ))
        })
    }

    /// Another bridge's inverter frame (0x351, 0x355, 0x356, 0x35A; the
    /// Pylontech family's 0x359; Growatt's 0x311, 0x313: only a speaker
    /// sends them) was heard within `us`: a speaker is there, whichever node
    /// it is.
    pub fn limits_heard_within(&self, now: Instant, us: Instant) -> bool {
        self.limits_at.is_some_and(|t| now.saturating_sub(t) <= us)
    }

    /// How many other nodes were heard (any frame) within `us`.
    pub fn others_heard_within(&self, now: Instant, us: Instant) -> usize {
        self.frame_at
            .iter()
            .enumerate()
            .filter(|(i, t)| {
                *i + 1 != usize::from(self.node) && t.is_some_and(|t| now.saturating_sub(t) <= us)
            })
            .count()
    }

    /// For the election: whether node `node` was heard (any frame) within
    /// `us`, and whether its last summary says it speaks.
    pub fn heard_speaking(&self, now: Instant, node: u8, us: Instant) -> Option<bool> {
        let i = usize::from(node.checked_sub(1)?);
        let at = (*self.frame_at.get(i)?)?;
        if now.saturating_sub(at) > us {
            return None;
        }
        Some(
            self.heard
                .get(i)
                .and_then(|h| h.as_ref())
                .is_some_and(|h| h.summary.speaking),
        )
    }
}
