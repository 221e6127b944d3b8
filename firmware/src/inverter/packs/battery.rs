//! The battery the packs add up to: who takes part, the sums, the reserve
//! for one pack dropping out, and the limits' hold and ramp.

use super::shares::share_with_margin;
use super::summary::{Summary, MAX_NODES};
use crate::freshness::Freshness;
use crate::inverter::control::{ChargeConfig, Conditions, Limits, PackState, Ramp};
use crate::Instant;

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
    /// Of those, the packs without fresh data whose switch is not known to be
    /// open: they may still conduct, so the limits stay safe for them.
    pub unknown: u8,
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
    /// Heard within [`PACK_LOST_US`](super::heard::PACK_LOST_US) (this bridge's own pack: always).
    pub alive: bool,
    /// How long ago the summary came (this bridge's own: 0), µs.
    pub heard_ago_us: Instant,
    /// CCL and DCL of its last summary without a fault, 0.1 A: what it may
    /// take when its BMS closes its switch again.
    pub closed_limits: Option<(u16, u16)>,
}

impl Member {
    /// This bridge's own pack, or a summary just heard.
    pub const fn now(summary: Summary) -> Self {
        Self {
            summary,
            alive: true,
            heard_ago_us: 0,
            closed_limits: None,
        }
    }

    /// The age of its data now: the age it was sent with plus the time since,
    /// µs; `None` when it was sent as 25.5 s or more (the field's top).
    pub fn data_age_us(&self) -> Option<Instant> {
        (self.summary.age_ds < u8::MAX).then(|| {
            (u64::from(self.summary.age_ds) * 100 * crate::MS).saturating_add(self.heard_ago_us)
        })
    }

    /// Takes part in the battery: alive, data fresh by the one rule
    /// (its age now, not when it was sent), no fault.
    pub fn takes_part(&self, freshness: Freshness) -> bool {
        let fresh = freshness.young(self.data_age_us());
        self.alive && fresh && !self.summary.fault
    }

    /// Known to be out of the current: alive with fresh data that says its
    /// BMS has a fault (its switch is open).
    pub fn known_open(&self, freshness: Freshness) -> bool {
        self.alive && freshness.young(self.data_age_us()) && self.summary.fault
    }

    /// May still conduct without telling what it does: no fresh data (its
    /// bridge lost, or its BMS link stale) and not known to be open. Such a
    /// pack stays in the safety sums with its last limits until it is back
    /// or known open.
    pub fn unknown(&self, freshness: Freshness) -> bool {
        !self.takes_part(freshness) && !self.known_open(freshness)
    }

    /// Counts in the battery's limits: taking part, or [`Member::unknown`].
    pub fn in_sums(&self, freshness: Freshness) -> bool {
        !self.known_open(freshness)
    }
}

/// What the battery may ask of a pack whose own limit is `limit_da`: 2 % (at
/// least 0.5 A) less, for the current measured a moment ago and its noise.
pub fn usable(limit_da: u16) -> i32 {
    let l = i32::from(limit_da);
    l - (l / 50).max(5).min(l)
}

/// The battery of `members` (each pack once, this bridge's own included);
/// `None` when no pack takes part. Nothing known of how the current splits:
/// see [`aggregate_with`].
pub fn aggregate(members: &[Member], freshness: Freshness) -> Option<Battery> {
    aggregate_with(members, freshness, &[])
}

/// The battery of `members` with `shares[i]`, the learnt share of a change
/// of the total of `members[i]` ([`super::Shares`]; `None`: not known).
pub fn aggregate_with(
    members: &[Member],
    freshness: Freshness,
    shares: &[Option<f32>],
) -> Option<Battery> {
    let part = || members.iter().filter(|m| m.takes_part(freshness));
    let n = part().count();
    if n == 0 {
        return None;
    }
    let mut cvl = u16::MAX;
    let mut discharge = 0u16;
    let mut i_sum = 0i32;
    let (mut cap, mut soc_w, mut soh_w, mut v_sum) = (0u64, 0u64, 0u64, 0u64);
    let (mut min_cell, mut max_cell) = (u16::MAX, 0u16);
    let (mut min_t, mut max_t) = (i16::MAX, i16::MIN);
    let mut cond = [0u8; 10];
    let (mut block_c, mut block_d) = (0u8, 0u8);
    for m in part() {
        let s = &m.summary;
        cvl = cvl.min(s.limits.cvl_dv);
        discharge = discharge.max(s.limits.discharge_dv);
        i_sum += i32::from(s.current_da);
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
    for _ in members.iter().filter(|m| !m.takes_part(freshness)) {
        offline = offline.saturating_add(1);
        // A BMS internal warning: never "link lost", which a Victron GX reads
        // as the whole battery offline.
        cond[8] = cond[8].max(1);
    }
    let clamp_da = |x: i32| x.clamp(0, i32::from(u16::MAX)) as u16;
    let ccl = clamp_da(limit_of(members, freshness, shares, 1, |s| s.limits.ccl_da));
    let dcl = clamp_da(limit_of(members, freshness, shares, -1, |s| {
        s.limits.dcl_da
    }));
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
            // The summaries carry no balancing bits: each pack's own charge
            // control holds its absorption for its balance.
            balancing: 0,
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
        unknown: members
            .iter()
            .filter(|m| m.unknown(freshness))
            .count()
            .min(usize::from(u8::MAX)) as u8,
        blocking_charge: block_c,
        blocking_discharge: block_d,
    })
}

/// The battery's limit in one direction before its hold and ramp, 0.1 A:
/// `sign` +1 for charge (each pack's CCL), −1 for discharge (its DCL).
/// Currents below are in that direction; T is the packs' total that the
/// bridges measure, I_k and L_k a pack's current and usable limit, α_k its
/// share of a change of the total.
///
/// * Now: T' ≤ T + (L_k − I_k)/α_k for every pack, so that no pack passes
///   its own limit at the new total T'.
/// * One pack j opens: its current and any change move to the others by
///   conductance, α_k/(1 − α_j) to pack k: T' ≤ T − I_j + (L_k − I_k)·(1 − α_j)/α_k.
/// * A pack that may conduct without data (u) takes at most what the
///   inverter delivers beyond the packs that report, with the largest of
///   those open too: T' ≤ T − max I_j + L_u.
/// * A pack whose switch is open may close it at any moment and take up to
///   all of the total before the bridges hear it: T' ≤ its last limit with
///   the switch closed.
/// * Never above the sum of the limits.
///
/// With the shares learnt, α with its margins ([`super::share_with_margin`]).
/// Without (or while a pack has no data), the bound that needs no knowledge,
/// α = 1, counted from 0 while the battery goes the other way or rests — so
/// a limit is never 0 for a current that is not there (a DCL of 0 while
/// charging would switch a Victron inverter off); a pack already past its
/// own limit counts its excess `n` times (its share of a cut is about 1/n).
fn limit_of(
    members: &[Member],
    freshness: Freshness,
    shares: &[Option<f32>],
    sign: i32,
    limit: fn(&Summary) -> u16,
) -> i32 {
    let part = || {
        members
            .iter()
            .enumerate()
            .filter(|(_, m)| m.takes_part(freshness))
    };
    let unknown = || members.iter().filter(|m| m.unknown(freshness));
    let n = part().count() as i32;
    let x = |m: &Member| sign * i32::from(m.summary.current_da);
    let l = |m: &Member| usable(limit(&m.summary));
    // A pack without data whose last data said its switch was open (a
    // fault: limits 0) may have closed it meanwhile: it counts with what it
    // takes closed, as a pack known open does — never with the 0 of its
    // fault, which would stop the battery for a pack that is not there.
    let lu = |m: &Member| match m.closed_limits {
        Some((ccl, dcl)) if m.summary.fault => usable(if sign > 0 { ccl } else { dcl }),
        _ => l(m),
    };
    let total: i32 = part().map(|(_, m)| x(m)).sum();
    let pos = |v: i32| v.max(0);
    let alpha = |i: usize| shares.get(i).copied().flatten();
    let learnt = n >= 2 && unknown().next().is_none() && part().all(|(i, _)| alpha(i).is_some());
    let mut most: i32 = part()
        .map(|(_, m)| l(m))
        .chain(unknown().map(lu))
        .fold(0i32, i32::saturating_add);
    let over = |t: f32| t.clamp(i32::MIN as f32, i32::MAX as f32) as i32;
    for (k, mk) in part() {
        let room = l(mk) - x(mk);
        match alpha(k) {
            Some(ak) if learnt => {
                most = most.min(total.saturating_add(over(room as f32 / share_with_margin(ak))));
                for (j, mj) in part().filter(|(j, _)| *j != k) {
                    let aj = alpha(j).unwrap_or(1.0);
                    let akj = if aj < 0.95 {
                        share_with_margin(ak / (1.0 - aj))
                    } else {
                        1.0
                    };
                    let t = (total - x(mj)).saturating_add(over(room as f32 / akj));
                    most = most.min(t);
                }
            }
            _ => {
                let room = l(mk) - pos(x(mk));
                let now = if room >= 0 {
                    room
                } else {
                    room.saturating_mul(n)
                };
                most = most.min(pos(total).saturating_add(now));
                if n >= 2 {
                    let largest_other = part()
                        .filter(|(j, _)| *j != k)
                        .map(|(_, m)| pos(x(m)))
                        .max()
                        .unwrap_or(0);
                    most = most.min((pos(total) - largest_other).saturating_add(room));
                }
            }
        }
    }
    let largest = part().map(|(_, m)| pos(x(m))).max().unwrap_or(0);
    for mu in unknown() {
        most = most.min((pos(total) - largest).saturating_add(lu(mu)));
    }
    // A pack whose BMS opened its switch closes it again by itself (a
    // TinyBMS recovers from a cutoff) and takes its share of the total at
    // once, before any bridge hears it: at most all of it.
    for mo in members.iter().filter(|m| m.known_open(freshness)) {
        if let Some((ccl, dcl)) = mo.closed_limits {
            most = most.min(usable(if sign > 0 { ccl } else { dcl }));
        }
    }
    most.max(0)
}

/// The battery's limits after the single pack's hold and ramp: they fall at
/// once, rise at most `ramp_rate_da_per_s`, and after a pack left (or a cut) a rise
/// waits `limit_hold_us`.
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
    /// Before any limits were computed there is nothing to cut: the first
    /// ones still apply at once (a cold start never tells a healthy battery
    /// CCL 0 / DCL 0).
    pub fn cut(&mut self, now: Instant) {
        if self.last.is_none() {
            return;
        }
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
    /// Not heard within [`PACK_LOST_US`](super::heard::PACK_LOST_US).
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
    pub fn of(m: &Member, freshness: Freshness) -> Self {
        if !m.alive {
            Self::Lost
        } else if m.summary.fault {
            Self::Fault
        } else if m.takes_part(freshness) {
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
