//! Several packs, one battery: the summaries bridges exchange on the inverter's
//! bus, the battery they add up to, and which bridge speaks to the inverter.
//! Sans-IO like the rest of the inverter output.
//!
//! **Summaries.** A bridge with a node number (1..=[`MAX_NODES`]) sends its
//! pack's summary every second as [`SUMMARY_FRAMES`] classic frames with the
//! 11-bit identifiers `SUMMARY_BASE_ID + 4 × (node − 1) + k`, k = 0..=3
//! (0x6A0-0x6BF: outside every identifier the Victron and SMA protocols use).
//! The last byte of each frame carries a 4-bit sequence number; a summary is
//! taken only when all four frames with one sequence number have arrived, so a
//! lost or late frame never mixes two summaries. Every field is checked on
//! receipt (see [`SummaryError`]); a summary that fails is dropped whole.
//!
//! **The battery** ([`aggregate`]) is made of the packs that *take part*: a
//! summary heard within [`PACK_LOST_US`], data younger than the stale age, no
//! fault. A pack that stops taking part leaves the sums at once.
//!
//! * CVL: the lowest CVL of the packs taking part; discharge voltage the highest.
//! * CCL: packs in parallel share the current by their voltages and
//!   resistances, not evenly, and a pack may even take current from the others.
//!   When the total changes by ΔI, a pack's share changes by α·ΔI with
//!   0 ≤ α ≤ 1 (its conductance over the sum of all). So the battery's CCL is
//!   the present total plus the *smallest* headroom of any pack
//!   (`CCL_k − I_k`): whichever way the extra current splits, no pack gets more
//!   than its headroom. A pack already past its own CCL turns the headroom
//!   negative, scaled by the number of packs (its share of a cut is about
//!   1/N). Never above the sum of the packs' CCLs; never below 0. While the
//!   battery discharges (or rests), the CCL starts from 0 current: the
//!   smallest headroom, so a limit is never 0 for a current that is not there.
//!   DCL the same way with discharge currents. Each pack's limit counts 2 %
//!   (at least 0.5 A) less ([`usable`]): its current was measured a moment ago.
//! * **One pack may open its switch at any moment** (a fault, a cutoff): until
//!   the inverter hears new limits, the others carry its current. So the total
//!   is also kept where, without any one pack, each other pack's share
//!   (measured: its current over the total) would stay within its own limit:
//!   `total ≤ limit_k × (total − I_j) / I_k` for every pair. Four equal packs
//!   are asked for at most three packs' current; two, for one pack's — the
//!   price of never tripping the others in a cascade.
//! * Those limits then go through the single pack's hold and ramp
//!   ([`super::control`]): they fall at once; they rise at most
//!   `ramp_da_per_s`; when a pack leaves or comes (back), a rise waits
//!   `hold_us` first. They start once the bridge has listened for
//!   [`LISTEN_US`] (it knows every pack then).
//! * SOC and SOH weighted by capacity; capacity, current summed; voltage the
//!   mean; cell and temperature extremes across the packs; alarms and warnings
//!   of the packs taking part combined (the highest level of each field). A
//!   pack that left shows as a BMS internal *warning* — never as an alarm that
//!   would stop the whole battery, nor as "link lost", which a GX reads as the
//!   battery offline.
//!
//! **One speaker** ([`Election`]): a bridge that is not speaking starts only
//! when (a) it has listened for [`LISTEN_US`] since it started or recovered from
//! a bus-off, (b) no other node heard within [`SPEAKER_LOST_US`] says it is
//! speaking, and (c) no lower node number is heard. A speaker goes on until it
//! hears a *lower* node that says it is speaking. So node 1, the primary,
//! speaks after its first 3 s; when the speaker falls silent, the lowest node
//! still heard takes over once [`SPEAKER_LOST_US`] have passed since its last
//! summary: the inverter is without limits for at most 2.5 s (a Victron GX
//! waits 3 s); a node that comes back finds a speaker
//! and stays quiet (no handover, no gap). A bridge speaks only while it sends
//! its own summary (it has BMS data, and no other bridge has its number), so
//! the others always hear the speaker; "heard" counts any frame of a node, so
//! one refused or incomplete summary does not start a takeover. Two speakers
//! exist only while one of them hears nothing of the bus, and at most for one
//! period after a speaker's summaries went missing for 1.5 s; as soon as they
//! hear each other, the higher one stops.
//!
//! Every bridge with a node number computes the battery every second, speaker
//! or not, so a new speaker takes over with the hold and ramp state of the
//! battery as it was.

use super::control::{ChargeConfig, Conditions, Limits, PackState, Ramp};
use super::frames::CanFrame;
use crate::Instant;

/// Identifier of node 1's first summary frame.
pub const SUMMARY_BASE_ID: u16 = 0x6A0;
/// Highest node number.
pub const MAX_NODES: u8 = 8;
/// Frames per summary.
pub const SUMMARY_FRAMES: usize = 4;
/// Last identifier of the summary range.
pub const SUMMARY_LAST_ID: u16 = SUMMARY_BASE_ID + (MAX_NODES as u16) * 4 - 1;
/// A pack whose last complete summary is older than this is lost and leaves
/// the battery, µs (one summary may go missing).
pub const PACK_LOST_US: Instant = 2_500_000;
/// A speaker (or a lower node) counts as silent for the election after this
/// long without a summary, µs: short enough that a new speaker's first 0x351
/// comes within 2.5 s of the last one (a GX stops after 3 s without).
pub const SPEAKER_LOST_US: Instant = 1_500_000;
/// Below this total current (0.1 A) the shares of the packs are not known well
/// enough for the rule that one pack may drop out.
pub const REDUNDANCY_MIN_DA: i32 = 20;
/// After a start or a bus-off recovery, a node listens this long before it may
/// speak, µs.
pub const LISTEN_US: Instant = 3 * crate::SECOND;

/// One pack's summary, in the integer units of the frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Summary {
    /// Pack voltage, 0.01 V.
    pub voltage_cv: u16,
    /// Pack current, 0.1 A (positive = charging).
    pub current_da: i16,
    /// SOC, 0.01 % (0..=10000).
    pub soc_cpct: u16,
    /// SOH, % (0..=100).
    pub soh_pct: u8,
    /// Lowest cell, mV.
    pub min_cell_mv: u16,
    /// Highest cell, mV.
    pub max_cell_mv: u16,
    /// Lowest temperature, 0.1 °C.
    pub min_temp_dc: i16,
    /// Highest temperature, 0.1 °C.
    pub max_temp_dc: i16,
    /// Age of the pack's data when sent, 0.1 s (255 = 25.5 s or more).
    pub age_ds: u8,
    /// Capacity (BMS register 306), 0.1 Ah.
    pub capacity_dah: u16,
    /// The pack's own limits as its bridge computed them.
    pub limits: Limits,
    /// The pack's alarms and warnings (`link_lost` is not carried: see `age_ds`).
    pub conditions: Conditions,
    /// BMS status "fault" (its switch is open).
    pub fault: bool,
    /// A charge-side fault is latched (charge switch open).
    pub charge_blocked: bool,
    /// The sending bridge speaks to the inverter.
    pub speaking: bool,
}

/// Why a summary was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SummaryError {
    /// Not 8 data bytes.
    Length,
    /// SOC above 100 %, SOH above 100 %.
    Soc,
    /// Lowest cell above the highest, or temperatures the other way round.
    Order,
    /// A condition field holds 3 (only 0, 1, 2 exist) or a reserved bit is set.
    Reserved,
}

/// The 10 conditions carried (all of [`Conditions`] but `link_lost`), 2 bits each.
fn conditions_bits(c: &Conditions) -> u32 {
    let all = c.all();
    let mut bits = 0u32;
    for (i, v) in all.iter().take(10).enumerate() {
        bits |= u32::from((*v).min(2)) << (2 * i);
    }
    bits
}

fn conditions_from(bits: u32) -> Option<Conditions> {
    let f = |i: u32| -> Option<u8> {
        let v = ((bits >> (2 * i)) & 3) as u8;
        (v <= 2).then_some(v)
    };
    Some(Conditions {
        high_voltage: f(0)?,
        low_voltage: f(1)?,
        high_temperature: f(2)?,
        low_temperature: f(3)?,
        high_temperature_charge: f(4)?,
        low_temperature_charge: f(5)?,
        high_discharge_current: f(6)?,
        high_charge_current: f(7)?,
        bms_internal: f(8)?,
        cell_imbalance: f(9)?,
        link_lost: 0,
    })
}

const FLAG_SPEAKING: u8 = 1;
const FLAG_FAULT: u8 = 2;
const FLAG_CHARGE_BLOCKED: u8 = 4;

fn put16(d: &mut [u8; 8], at: usize, v: u16) {
    let b = v.to_le_bytes();
    if let Some(s) = d.get_mut(at..at + 2) {
        s.copy_from_slice(&b);
    }
}

fn get16(d: &[u8; 8], at: usize) -> u16 {
    match d.get(at..at + 2) {
        Some(&[a, b]) => u16::from_le_bytes([a, b]),
        _ => 0,
    }
}

/// The identifier of frame `k` of `node`'s summary (`None` outside 1..=8, 0..=3).
pub const fn summary_id(node: u8, k: u8) -> Option<u16> {
    if node == 0 || node > MAX_NODES || k as usize >= SUMMARY_FRAMES {
        return None;
    }
    Some(SUMMARY_BASE_ID + (node as u16 - 1) * 4 + k as u16)
}

/// Node and frame index of a summary identifier.
pub const fn from_id(id: u16) -> Option<(u8, u8)> {
    if id < SUMMARY_BASE_ID || id > SUMMARY_LAST_ID {
        return None;
    }
    let off = id - SUMMARY_BASE_ID;
    Some(((off / 4) as u8 + 1, (off % 4) as u8))
}

impl Summary {
    /// The four frames of `node`'s summary with sequence number `seq` (0..=15);
    /// `None` for a node outside 1..=8.
    ///
    /// | frame | bytes 0-1 | 2-3 | 4-5 | 6 | 7 |
    /// |---|---|---|---|---|---|
    /// | 0 | voltage u16 0.01 V | current s16 0.1 A | SOC u16 0.01 % | SOH u8 % | seq (bits 0-3), flags (4-7) |
    /// | 1 | min cell u16 mV | max cell u16 mV | min temperature s16 0.1 °C | data age u8 0.1 s | seq |
    /// | 2 | max temperature s16 0.1 °C | capacity u16 0.1 Ah | discharge voltage u16 0.1 V | conditions bits 0-7 | seq |
    /// | 3 | CVL u16 0.1 V | CCL u16 0.1 A | DCL u16 0.1 A | conditions bits 8-15 | seq, conditions bits 16-19 (4-7) |
    pub fn frames(&self, node: u8, seq: u8) -> Option<[CanFrame; SUMMARY_FRAMES]> {
        let seq = seq & 0x0F;
        let mut out = [CanFrame {
            id: 0,
            len: 8,
            data: [0; 8],
        }; SUMMARY_FRAMES];
        let cond = conditions_bits(&self.conditions);
        let mut flags = 0;
        for (on, flag) in [
            (self.speaking, FLAG_SPEAKING),
            (self.fault, FLAG_FAULT),
            (self.charge_blocked, FLAG_CHARGE_BLOCKED),
        ] {
            if on {
                flags |= flag;
            }
        }
        for (k, f) in out.iter_mut().enumerate() {
            f.id = summary_id(node, k as u8)?;
            let d = &mut f.data;
            match k {
                0 => {
                    put16(d, 0, self.voltage_cv);
                    put16(d, 2, self.current_da as u16);
                    put16(d, 4, self.soc_cpct);
                    d[6] = self.soh_pct;
                    d[7] = seq | (flags << 4);
                }
                1 => {
                    put16(d, 0, self.min_cell_mv);
                    put16(d, 2, self.max_cell_mv);
                    put16(d, 4, self.min_temp_dc as u16);
                    d[6] = self.age_ds;
                    d[7] = seq;
                }
                2 => {
                    put16(d, 0, self.max_temp_dc as u16);
                    put16(d, 2, self.capacity_dah);
                    put16(d, 4, self.limits.discharge_dv);
                    d[6] = cond as u8;
                    d[7] = seq;
                }
                _ => {
                    put16(d, 0, self.limits.cvl_dv);
                    put16(d, 2, self.limits.ccl_da);
                    put16(d, 4, self.limits.dcl_da);
                    d[6] = (cond >> 8) as u8;
                    d[7] = seq | ((((cond >> 16) & 0x0F) as u8) << 4);
                }
            }
        }
        Some(out)
    }

    /// A summary from its four frames' data, in frame order.
    pub fn from_frames(d: &[[u8; 8]; SUMMARY_FRAMES]) -> Result<Self, SummaryError> {
        let [a, b, c, e] = d;
        let flags = a[7] >> 4;
        if flags & !(FLAG_SPEAKING | FLAG_FAULT | FLAG_CHARGE_BLOCKED) != 0
            || b[7] >> 4 != 0
            || c[7] >> 4 != 0
        {
            return Err(SummaryError::Reserved);
        }
        let cond = u32::from(c[6]) | u32::from(e[6]) << 8 | u32::from(e[7] >> 4) << 16;
        let conditions = conditions_from(cond).ok_or(SummaryError::Reserved)?;
        let s = Self {
            voltage_cv: get16(a, 0),
            current_da: get16(a, 2) as i16,
            soc_cpct: get16(a, 4),
            soh_pct: a[6],
            min_cell_mv: get16(b, 0),
            max_cell_mv: get16(b, 2),
            min_temp_dc: get16(b, 4) as i16,
            age_ds: b[6],
            max_temp_dc: get16(c, 0) as i16,
            capacity_dah: get16(c, 2),
            limits: Limits {
                cvl_dv: get16(e, 0),
                ccl_da: get16(e, 2),
                dcl_da: get16(e, 4),
                discharge_dv: get16(c, 4),
            },
            conditions,
            fault: flags & FLAG_FAULT != 0,
            charge_blocked: flags & FLAG_CHARGE_BLOCKED != 0,
            speaking: flags & FLAG_SPEAKING != 0,
        };
        if s.soc_cpct > 10_000 || s.soh_pct > 100 {
            return Err(SummaryError::Soc);
        }
        if s.min_cell_mv > s.max_cell_mv || s.min_temp_dc > s.max_temp_dc {
            return Err(SummaryError::Order);
        }
        Ok(s)
    }

    /// This bridge's own summary: its pack's state (taken `age_us` ago), its
    /// limits and conditions, its capacity (register 306, 0.01 Ah).
    pub fn own(
        p: &PackState,
        age_us: Instant,
        limits: &Limits,
        conditions: &Conditions,
        capacity_cah: u16,
        speaking: bool,
    ) -> Self {
        let round = |x: f32, k: f32| -> f32 {
            let v = x * k;
            if v >= 0.0 {
                v + 0.5
            } else {
                v - 0.5
            }
        };
        let i16_of = |x: f32, k: f32| round(x, k).clamp(-32768.0, 32767.0) as i16;
        let (lo_t, hi_t) = (i16_of(p.min_temp_c, 10.0), i16_of(p.max_temp_c, 10.0));
        let mut c = *conditions;
        c.link_lost = 0;
        Self {
            voltage_cv: round(p.pack_v.max(0.0), 100.0).min(65535.0) as u16,
            current_da: i16_of(p.current_a, 10.0),
            soc_cpct: round(p.soc_pct.clamp(0.0, 100.0), 100.0).min(10_000.0) as u16,
            soh_pct: round(p.soh_pct.clamp(0.0, 100.0), 1.0).min(100.0) as u8,
            min_cell_mv: p.min_cell_mv.min(p.max_cell_mv),
            max_cell_mv: p.max_cell_mv.max(p.min_cell_mv),
            min_temp_dc: lo_t.min(hi_t),
            max_temp_dc: hi_t.max(lo_t),
            age_ds: (age_us / (100 * crate::MS)).min(255) as u8,
            capacity_dah: capacity_cah / 10,
            limits: *limits,
            conditions: c,
            fault: p.fault,
            charge_blocked: p.charge_blocked,
            speaking,
        }
    }
}

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
        let Some((node, k)) = from_id(id) else {
            return Received::NotSummary;
        };
        if self.node == 0 {
            return Received::NotSummary;
        }
        if node == self.node {
            self.duplicates = self.duplicates.saturating_add(1);
            return Received::DuplicateNode;
        }
        let i = usize::from(node - 1);
        let Ok(d) = <[u8; 8]>::try_from(data) else {
            self.refused = self.refused.saturating_add(1);
            if let Some(p) = self.partial.get_mut(i) {
                *p = None;
            }
            return Received::Refused(node, SummaryError::Length);
        };
        if let Some(t) = self.frame_at.get_mut(i) {
            *t = Some(now);
        }
        let seq = d[7] & 0x0F;
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
            Ok(summary) => {
                if let Some(h) = self.heard.get_mut(i) {
                    *h = Some(Heard { summary, at: now });
                }
                Received::Complete(node)
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
    /// summary, whether it is alive, and how long ago it came.
    pub fn known(&self, now: Instant) -> impl Iterator<Item = (u8, Member)> + '_ {
        self.heard.iter().enumerate().filter_map(move |(i, h)| {
            let h = h.as_ref()?;
            let ago = now.saturating_sub(h.at);
            Some((
                i as u8 + 1,
                Member {
                    summary: h.summary,
                    alive: ago <= PACK_LOST_US,
                    heard_ago_us: ago,
                },
            ))
        })
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
            listened && !(1..=MAX_NODES).any(speaks) && !(1..me).any(|n| heard(n).is_some())
        };
        self.speaking
    }
}

/// The battery the packs add up to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Battery {
    /// The state to report (sums, means and extremes).
    pub state: PackState,
    /// The limits before the battery's hold and ramp.
    pub limits: Limits,
    /// Combined alarms and warnings.
    pub conditions: Conditions,
    /// Capacity of the packs taking part, 0.1 Ah.
    pub capacity_dah: u32,
    /// Packs taking part.
    pub online: u8,
    /// Packs known but not taking part (lost, stale, faulted).
    pub offline: u8,
    /// Packs taking part with CCL 0.
    pub blocking_charge: u8,
    /// Packs taking part with DCL 0.
    pub blocking_discharge: u8,
}

/// One pack as the aggregation sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Member {
    /// Its summary.
    pub summary: Summary,
    /// Heard within [`PACK_LOST_US`] (this bridge's own pack: always).
    pub alive: bool,
    /// How long ago the summary came (this bridge's own: 0), µs.
    pub heard_ago_us: Instant,
}

impl Member {
    /// This bridge's own pack, or a summary just heard.
    pub const fn now(summary: Summary) -> Self {
        Self {
            summary,
            alive: true,
            heard_ago_us: 0,
        }
    }

    /// The age of its data now: the age it was sent with plus the time since,
    /// µs; `None` when it was sent as 25.5 s or more (the field's top).
    pub fn data_age_us(&self) -> Option<Instant> {
        (self.summary.age_ds < u8::MAX).then(|| {
            (u64::from(self.summary.age_ds) * 100 * crate::MS).saturating_add(self.heard_ago_us)
        })
    }

    /// Takes part in the battery: alive, data younger than `stale_after_us`
    /// (its age now, not when it was sent), no fault.
    pub fn takes_part(&self, stale_after_us: Instant) -> bool {
        let fresh = self.data_age_us().is_some_and(|a| a <= stale_after_us);
        self.alive && fresh && !self.summary.fault
    }
}

/// What the battery may ask of a pack whose own limit is `limit_da`: 2 % (at
/// least 0.5 A) less, for the current measured a moment ago and its noise.
pub fn usable(limit_da: u16) -> i32 {
    let l = i32::from(limit_da);
    l - (l / 50).max(5).min(l)
}

/// The battery of `members` (each pack once, this bridge's own included);
/// `None` when no pack takes part.
pub fn aggregate(members: &[Member], stale_after_us: Instant) -> Option<Battery> {
    let part = || members.iter().filter(|m| m.takes_part(stale_after_us));
    let n = part().count();
    if n == 0 {
        return None;
    }
    let n_i = n as i32;
    let mut cvl = u16::MAX;
    let mut discharge = 0u16;
    let (mut i_sum, mut ccl_sum, mut dcl_sum) = (0i32, 0i32, 0i32);
    let (mut ch_room, mut dis_room) = (i32::MAX, i32::MAX);
    let (mut cap, mut soc_w, mut soh_w, mut v_sum) = (0u64, 0u64, 0u64, 0u64);
    let (mut min_cell, mut max_cell) = (u16::MAX, 0u16);
    let (mut min_t, mut max_t) = (i16::MAX, i16::MIN);
    let mut cond = [0u8; 11];
    let (mut block_c, mut block_d) = (0u8, 0u8);
    for m in part() {
        let s = &m.summary;
        cvl = cvl.min(s.limits.cvl_dv);
        discharge = discharge.max(s.limits.discharge_dv);
        let i = i32::from(s.current_da);
        let (ccl, dcl) = (usable(s.limits.ccl_da), usable(s.limits.dcl_da));
        i_sum += i;
        ccl_sum += ccl;
        dcl_sum += dcl;
        let room = |r: i32| if r >= 0 { r } else { r.saturating_mul(n_i) };
        // Headroom in each direction from the pack's current in that
        // direction (a pack going the other way counts as 0: it has at least
        // its whole limit).
        ch_room = ch_room.min(room(ccl - i.max(0)));
        dis_room = dis_room.min(room(dcl - (-i).max(0)));
        let c = u64::from(s.capacity_dah);
        cap += c;
        soc_w += c * u64::from(s.soc_cpct);
        soh_w += c * u64::from(s.soh_pct);
        v_sum += u64::from(s.voltage_cv);
        min_cell = min_cell.min(s.min_cell_mv);
        max_cell = max_cell.max(s.max_cell_mv);
        min_t = min_t.min(s.min_temp_dc);
        max_t = max_t.max(s.max_temp_dc);
        for (acc, v) in cond.iter_mut().zip(s.conditions.all()) {
            *acc = (*acc).max(v);
        }
        block_c += u8::from(s.limits.ccl_da == 0);
        block_d += u8::from(s.limits.dcl_da == 0);
    }
    let mut offline = 0u8;
    for _ in members.iter().filter(|m| !m.takes_part(stale_after_us)) {
        offline = offline.saturating_add(1);
        // A BMS internal warning: never "link lost", which a Victron GX reads
        // as the whole battery offline.
        cond[8] = cond[8].max(1);
    }
    let clamp_da = |x: i32| x.clamp(0, i32::from(u16::MAX)) as u16;
    // From the battery's present current in that direction; while it goes
    // the other way (or rests), from 0: the smallest pack's headroom, never a
    // 0 computed from a current that is not there (a DCL of 0 while charging
    // would switch a Victron inverter off).
    let ccl = i_sum.max(0).saturating_add(ch_room).min(ccl_sum);
    let dcl = (-i_sum).max(0).saturating_add(dis_room).min(dcl_sum);
    // One pack may open its switch at any moment: the others then share its
    // current until the inverter hears the new limits. Keep the total low
    // enough that they stay within their own limits then.
    let spare = |sign: i32, limit: fn(&Summary) -> u16| -> i32 {
        let share = |m: &Member| (sign * i32::from(m.summary.current_da)).max(0);
        let total: i32 = part().map(share).sum();
        if n < 2 || total < REDUNDANCY_MIN_DA {
            return i32::MAX; // no current to share out (yet): the ramp rules
        }
        let mut most = i32::MAX;
        for (k, mk) in part().enumerate() {
            let own = share(mk);
            if own == 0 {
                continue;
            }
            let largest_other = part()
                .enumerate()
                .filter(|(j, _)| *j != k)
                .map(|(_, m)| share(m))
                .max()
                .unwrap_or(0);
            // Pack k carries own/total of the battery's current; without
            // pack j, own/(total − d_j). So the total may be at most
            // limit_k × (total − d_j) / own.
            let t = i64::from(usable(limit(&mk.summary))) * i64::from(total - largest_other)
                / i64::from(own);
            most = most.min(t.clamp(0, i64::from(i32::MAX)) as i32);
        }
        most
    };
    let ccl = clamp_da(ccl.min(spare(1, |s| s.limits.ccl_da)));
    let dcl = clamp_da(dcl.min(spare(-1, |s| s.limits.dcl_da)));
    let (soc, soh) = match (soc_w.checked_div(cap), soh_w.checked_div(cap)) {
        (Some(soc), Some(soh)) => (soc, soh),
        _ => {
            // No capacity known: plain means (n ≥ 1 here).
            let (s1, s2) = part().fold((0u64, 0u64), |(a, b), m| {
                (
                    a + u64::from(m.summary.soc_cpct),
                    b + u64::from(m.summary.soh_pct),
                )
            });
            let n = n.max(1) as u64;
            (s1 / n, s2 / n)
        }
    };
    let conditions = Conditions {
        high_voltage: cond[0],
        low_voltage: cond[1],
        high_temperature: cond[2],
        low_temperature: cond[3],
        high_temperature_charge: cond[4],
        low_temperature_charge: cond[5],
        high_discharge_current: cond[6],
        high_charge_current: cond[7],
        bms_internal: cond[8],
        cell_imbalance: cond[9],
        link_lost: cond[10],
    };
    let charge_blocked = part().all(|m| m.summary.charge_blocked);
    Some(Battery {
        state: PackState {
            min_cell_mv: min_cell,
            max_cell_mv: max_cell,
            pack_v: (v_sum / n as u64) as f32 / 100.0,
            current_a: i_sum as f32 / 10.0,
            soc_pct: soc as f32 / 100.0,
            soh_pct: soh as f32,
            min_temp_c: f32::from(min_t) / 10.0,
            max_temp_c: f32::from(max_t) / 10.0,
            fault: false,
            charge_blocked,
        },
        limits: Limits {
            cvl_dv: cvl,
            ccl_da: ccl,
            dcl_da: dcl,
            discharge_dv: discharge,
        },
        conditions,
        capacity_dah: cap as u32,
        online: n as u8,
        offline,
        blocking_charge: block_c,
        blocking_discharge: block_d,
    })
}

/// The battery's limits after the single pack's hold and ramp: they fall at
/// once, rise at most `ramp_da_per_s`, and after a pack left (or a cut) a rise
/// waits `hold_us`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatteryLimits {
    ccl: Ramp,
    dcl: Ramp,
    members: u16,
    last: Option<Instant>,
}

impl Default for BatteryLimits {
    fn default() -> Self {
        Self::new()
    }
}

impl BatteryLimits {
    /// Nothing sent yet: the first limits apply at once.
    pub const fn new() -> Self {
        Self {
            ccl: Ramp::new(),
            dcl: Ramp::new(),
            members: 0,
            last: None,
        }
    }

    /// The inverter was without the battery's limits (this bridge's bus-off,
    /// the battery lost): both limits start from 0 and come back after the
    /// hold. (A takeover keeps the state: every node steps the battery.)
    pub fn cut(&mut self, now: Instant) {
        for r in [&mut self.ccl, &mut self.dcl] {
            *r = Ramp::new();
            let _ = r.step(now, 0, 0, &ChargeConfig::default());
        }
    }

    /// The limits to send at `now` for `battery`, whose packs taking part are
    /// the bits of `members` (bit n − 1 for node n, bit 15 for a lone bridge).
    pub fn step(
        &mut self,
        now: Instant,
        battery: &Battery,
        members: u16,
        c: &ChargeConfig,
    ) -> Limits {
        if self.last.is_some() && self.members != members {
            // A pack left: its share is gone at once (the target falls). A
            // pack came (back): what it adds waits the hold, then ramps — the
            // single pack's rule after a cut.
            self.ccl.hold_from(now);
            self.dcl.hold_from(now);
        }
        self.members = members;
        let dt = self
            .last
            .map_or(crate::SECOND, |t| now.saturating_sub(t))
            .min(60 * crate::SECOND);
        self.last = Some(now);
        Limits {
            ccl_da: self.ccl.step(now, battery.limits.ccl_da, dt, c),
            dcl_da: self.dcl.step(now, battery.limits.dcl_da, dt, c),
            ..battery.limits
        }
    }
}

/// Where a pack stands in the battery.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PackPart {
    /// Taking part.
    Part,
    /// Not heard within [`PACK_LOST_US`].
    Lost,
    /// Heard, but its data is older than the stale age.
    Stale,
    /// Its BMS reports a fault (its switch is open).
    Fault,
}

impl PackPart {
    /// As the host link and MQTT write it.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Part => "part",
            Self::Lost => "lost",
            Self::Stale => "stale",
            Self::Fault => "fault",
        }
    }

    /// Of a member, with the stale age.
    pub fn of(m: &Member, stale_after_us: Instant) -> Self {
        if !m.alive {
            Self::Lost
        } else if m.summary.fault {
            Self::Fault
        } else if m.takes_part(stale_after_us) {
            Self::Part
        } else {
            Self::Stale
        }
    }
}

/// One pack as a bridge sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PackView {
    /// Node number.
    pub node: u8,
    /// Its last summary (this bridge's own: as it sent it).
    pub summary: Summary,
    /// Where it stands.
    pub part: PackPart,
}

/// What a bridge with a node number knows of the battery: for the host link
/// and MQTT.
#[derive(Debug, Clone, PartialEq)]
pub struct BatteryView {
    /// This bridge's node number.
    pub node: u8,
    /// This bridge speaks to the inverter.
    pub speaking: bool,
    /// The battery and the limits for it (sent when speaking); `None` while
    /// no pack takes part or before the bridge has listened.
    pub battery: Option<(Battery, Limits)>,
    /// Every pack known, by node number.
    pub packs: heapless::Vec<PackView, { MAX_NODES as usize }>,
}
