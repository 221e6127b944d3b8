//! The battery of several packs, as one bridge with a node number takes part
//! in it (see [`super::packs`] for the wire and the rules): the summaries
//! heard, the election of the one speaker, the battery's limits, how its
//! current splits, and what is logged when they change. [`Membership`]
//! keeps that state; the inverter output's `fill_member` is the period of a member:
//! its own pack's summary out, the battery computed, and — when it speaks —
//! the inverter frames for the battery.

use heapless::Deque;

use super::control::{Conditions, Limits, PackSettings, PackState};
use super::dialect::{CanFrame, OnSilence, StopWhy, Stops};
use super::packs::{
    self, Battery, BatteryLimits, BatteryView, Election, Member, PackPart, PackView, Packs,
    Received, Shares, Summary,
};
use super::say::Signals;
use super::{Freshness, Inverter, InverterReport, Made, Reports, QUEUE};
use crate::Instant;

/// 0.1 Ah per Ah (the battery's capacity is summed in 0.1 Ah, sent in Ah).
const DAH_PER_AH: u32 = 10;

/// One bridge's part in a battery of several packs. See the module
/// documentation.
#[derive(Debug, Clone)]
pub struct Membership {
    packs: Packs,
    election: Election,
    battery_limits: BatteryLimits,
    shares: Shares,
    battery: Option<(Battery, Limits)>,
    logged_battery: Option<Limits>,
    logged_packs: Option<(u8, u8)>,
    battery_lost: bool,
    /// The battery last spoken for, with its limits (for the stop said
    /// when the battery is lost).
    sent_battery: Option<(Battery, Limits)>,
    /// Periods of that stop said so far.
    lost_periods: u8,
    duplicate_reported: bool,
    /// Nodes whose refused summary was reported (bit `node - 1`).
    refused_reported: u8,
    seq: u8,
    own_summary: Option<Summary>,
    own_closed: Option<(u16, u16)>,
}

impl Membership {
    /// Node `node` (0, or one out of range: a bridge alone) at `now`.
    pub fn new(node: u8, now: Instant) -> Self {
        Self {
            packs: Packs::new(if node <= packs::MAX_NODES { node } else { 0 }),
            election: Election::new(now),
            battery_limits: BatteryLimits::new(),
            shares: Shares::new(),
            battery: None,
            logged_battery: None,
            logged_packs: None,
            // No battery yet is no battery lost: a bridge that just started
            // (its own data not read yet) says nothing until it had one.
            battery_lost: true,
            sent_battery: None,
            lost_periods: 0,
            duplicate_reported: false,
            refused_reported: 0,
            seq: 0,
            own_summary: None,
            own_closed: None,
        }
    }

    /// The node number (0 = alone).
    pub fn node(&self) -> u8 {
        self.packs.node()
    }

    /// The battery last computed and the limits for it.
    pub fn battery(&self) -> Option<&(Battery, Limits)> {
        self.battery.as_ref()
    }

    /// This bridge speaks to the inverter.
    pub fn speaking(&self) -> bool {
        self.election.speaking()
    }

    /// What was heard of the other nodes.
    pub fn packs(&self) -> &Packs {
        &self.packs
    }

    /// What was learnt of how the battery's current splits.
    pub fn shares(&self) -> &Shares {
        &self.shares
    }

    /// This bridge's own summary as it last sent it.
    pub fn own_summary(&self) -> Option<Summary> {
        self.own_summary
    }

    /// The battery and every pack as this bridge sees them at `now`; `None`
    /// for a bridge alone.
    pub fn view(&self, now: Instant, freshness: Freshness) -> Option<BatteryView> {
        let node = self.packs.node();
        if node == 0 {
            return None;
        }
        let mut packs: heapless::Vec<PackView, { packs::MAX_NODES as usize }> =
            heapless::Vec::new();
        // By node number: the others come in order; this one goes between.
        // The data's age now (sent age plus the time since), as the line shows it.
        let view = |n: u8, m: Member| PackView {
            node: n,
            summary: Summary {
                age_ds: m
                    .data_age_us()
                    .map_or(u8::MAX, |a| (a / (100 * crate::MS)).min(255) as u8),
                ..m.summary
            },
            part: PackPart::of(&m, freshness),
        };
        let mut own = self.own_summary.map(|s| view(node, Member::now(s)));
        for (n, m) in self.packs.known(now) {
            if n > node {
                if let Some(o) = own.take() {
                    let _ = packs.push(o);
                }
            }
            let _ = packs.push(view(n, m));
        }
        if let Some(o) = own {
            let _ = packs.push(o);
        }
        Some(BatteryView {
            node,
            speaking: self.election.speaking(),
            battery: self.battery,
            packs,
        })
    }

    /// A frame from the bus: another node's summary (a duplicate of this
    /// node and a refused summary reported once). True when, as the speaker,
    /// a summary stops a side its node's last did not.
    pub fn on_frame(&mut self, now: Instant, id: u16, data: &[u8], reports: &mut Reports) -> bool {
        let received = self.packs.on_frame(now, id, data);
        match received {
            Received::DuplicateNode if !self.duplicate_reported => {
                self.duplicate_reported = true;
                reports.push(InverterReport::DuplicateNode(self.packs.node()));
            }
            Received::Refused(node, e) => {
                let bit = 1u8 << (node.saturating_sub(1) & 7);
                if self.refused_reported & bit == 0 {
                    self.refused_reported |= bit;
                    reports.push(InverterReport::SummaryRefused(node, e));
                }
            }
            Received::Complete(node) | Received::Stops(node) => {
                self.refused_reported &= !(1u8 << (node.saturating_sub(1) & 7));
            }
            _ => {}
        }
        matches!(received, Received::Stops(_)) && self.election.speaking()
    }

    /// The controller went bus-off: not the speaker while off the bus, and no
    /// battery shown as current meanwhile.
    pub fn on_bus_off(&mut self, now: Instant, reports: &mut Reports) {
        if self.election.speaking() {
            reports.push(InverterReport::Speaker(false));
        }
        self.election.restart(now);
        self.battery = None;
    }

    /// Back on the bus: listen again before speaking; the battery's limits
    /// come back after the hold.
    pub fn on_recovery(&mut self, now: Instant) {
        self.election.restart(now);
        self.battery_limits.cut(now);
    }

    /// Who speaks (reported when it changes). A bridge that sends no summary
    /// (no BMS data yet; another bridge has its number) must not speak: the
    /// others would not know.
    fn elect(&mut self, now: Instant, has_own: bool, reports: &mut Reports) -> bool {
        let able = has_own && !self.duplicate_reported;
        let was = self.election.speaking();
        let speaking = self.election.update(now, &self.packs, able);
        if speaking != was {
            reports.push(InverterReport::Speaker(speaking));
        }
        speaking
    }

    /// This pack's summary (saying whether it speaks) onto the bus, and this
    /// pack as a member of the battery. Another bridge with this node number:
    /// this one falls silent (the same identifiers with other data would
    /// collide on the bus) until it restarts; the log says why. The sequence
    /// number advances either way.
    fn send_own_summary(
        &mut self,
        own: OwnPack,
        speaking: bool,
        queue: &mut Deque<CanFrame, QUEUE>,
    ) -> Member {
        let summary = Summary::own(
            &own.state,
            own.age,
            &own.limits,
            &own.conditions,
            own.capacity_cah,
            speaking,
        );
        if !self.duplicate_reported {
            if let Some(fs) = summary.frames(self.packs.node(), self.seq) {
                for f in fs {
                    let _ = queue.push_back(f);
                }
            }
        }
        self.seq = (self.seq + 1) & packs::SEQ_MASK;
        self.own_summary = Some(summary);
        // What the pack may take when its BMS closes its switch again.
        if !summary.fault {
            self.own_closed = Some((summary.limits.ccl_da, summary.limits.dcl_da));
        }
        Member {
            closed_limits: self.own_closed,
            ..Member::now(summary)
        }
    }

    /// Every pack once (this one first, then the others heard), and the packs
    /// in the battery's sums as bits.
    fn gather(&self, now: Instant, own: Option<Member>, freshness: Freshness) -> Gathered {
        let mut g = Gathered::new();
        if let Some(m) = own {
            g.add(self.packs.node(), m, freshness);
        }
        for (n, m) in self.packs.known(now) {
            g.add(n, m, freshness);
        }
        g
    }

    /// What is learnt of how the current splits (see `packs::shares`), from
    /// the packs taking part; returns the learnt share of each member, in the
    /// members' order.
    fn learn_shares(
        &mut self,
        g: &Gathered,
        freshness: Freshness,
    ) -> [Option<f32>; packs::MAX_NODES as usize] {
        let mut part: heapless::Vec<(u8, i16), { packs::MAX_NODES as usize }> =
            heapless::Vec::new();
        for (n, m) in g.nodes.iter().zip(&g.members) {
            if m.takes_part(freshness) {
                let _ = part.push((*n, m.summary.current_da));
            }
        }
        let unknown = g.members.iter().any(|m| m.unknown(freshness));
        self.shares.update(&part, unknown);
        let mut shares = [None; packs::MAX_NODES as usize];
        for (s, n) in shares.iter_mut().zip(&g.nodes) {
            *s = self.shares.of(*n);
        }
        shares
    }

    /// The battery the members add up to (`None`: no pack takes part); the
    /// packs online and offline reported when they change.
    fn aggregate(
        &mut self,
        g: &Gathered,
        shares: &[Option<f32>],
        freshness: Freshness,
        reports: &mut Reports,
    ) -> Option<Battery> {
        let battery = packs::aggregate_with(&g.members, freshness, shares);
        let counts = battery.map_or((0, g.members.len() as u8), |b| (b.online, b.offline));
        if self.logged_packs != Some(counts) {
            self.logged_packs = Some(counts);
            reports.push(InverterReport::Packs {
                online: counts.0,
                offline: counts.1,
            });
        }
        battery
    }

    /// No pack takes part: no battery, its limits cut (they come back after
    /// the hold), reported once. Returns the battery last spoken for while a
    /// speaker is to say the stop this period (every period towards an
    /// inverter that may run on, a few towards one that stops on silence).
    fn lose_battery(
        &mut self,
        now: Instant,
        speaking: bool,
        on_silence: OnSilence,
        reports: &mut Reports,
    ) -> Option<(Battery, Limits)> {
        self.battery = None;
        self.battery_limits.cut(now);
        if !self.battery_lost {
            self.battery_lost = true;
            reports.push(InverterReport::BatteryLost);
        }
        let n = self.lost_periods;
        self.lost_periods = n.saturating_add(1);
        let quiet = on_silence == OnSilence::Stops && n >= super::dialect::STOP_BEFORE_QUIET;
        if speaking && !quiet {
            self.sent_battery
        } else {
            None
        }
    }

    /// The battery of `g`'s packs at `now`, with its limits, once every pack
    /// has been listened for (`None` before: no battery limits, nor speaking).
    fn limits_for(
        &mut self,
        now: Instant,
        battery: Battery,
        g: &Gathered,
        charge: &super::control::ChargeConfig,
    ) -> Option<Limits> {
        self.battery_lost = false;
        self.lost_periods = 0;
        if !self.election.listened(now) {
            self.battery = None;
            return None;
        }
        let limits = self.battery_limits.step(now, &battery, g.mask, charge);
        self.battery = Some((battery, limits));
        Some(limits)
    }

    /// As the speaker: the battery's limits, logged when they change and kept
    /// for the stop said when the battery is lost.
    fn speaks(&mut self, battery: &Battery, limits: Limits, reports: &mut Reports) {
        if self.logged_battery != Some(limits) {
            self.logged_battery = Some(limits);
            reports.push(InverterReport::BatteryLimits(limits));
        }
        self.sent_battery = Some((*battery, limits));
    }
}

impl Inverter {
    /// With a node number: this pack's limits and summary, the battery of all
    /// packs heard, and — when this bridge is the speaker — the inverter
    /// frames for the battery.
    pub(super) fn fill_member(&mut self, now: Instant, slow: bool) {
        let freshness = self.config.freshness;
        let own = self.own_pack(now);
        let speaking = self.membership.elect(now, own.is_some(), &mut self.reports);
        let own = own.map(|o| {
            self.membership
                .send_own_summary(o, speaking, &mut self.queue)
        });
        let gathered = self.membership.gather(now, own, freshness);
        let shares = self.membership.learn_shares(&gathered, freshness);
        let Some(battery) =
            self.membership
                .aggregate(&gathered, &shares, freshness, &mut self.reports)
        else {
            self.forget_answer();
            let on_silence = self.config.protocol.on_silence();
            if let Some((b, limits)) =
                self.membership
                    .lose_battery(now, speaking, on_silence, &mut self.reports)
            {
                self.tell_battery_lost(now, &b, limits);
            }
            return;
        };
        let charge = self.config.charge;
        let Some(limits) = self.membership.limits_for(now, battery, &gathered, &charge) else {
            return;
        };
        if speaking {
            self.speak_for_battery(now, &battery, limits, slow);
        } else {
            self.membership.logged_battery = None;
            // Not the speaker: no answer to Growatt's query either.
            self.forget_answer();
        }
    }

    /// This pack as it goes into the battery, once the BMS has said anything:
    /// its limits are computed while its data is fresh (see
    /// [`Inverter::refresh_own`]). The summary carries the pack's limits before
    /// its own hold and ramp: the battery holds and ramps as a whole, so a pack
    /// that comes back after a cut adds its share at once instead of holding
    /// the whole battery at 0.
    fn own_pack(&mut self, now: Instant) -> Option<OwnPack> {
        let (Some(settings), Some((state, taken_at))) = (self.settings, self.state) else {
            return None;
        };
        let age = now.saturating_sub(taken_at);
        self.refresh_own(now, age, &settings, &state);
        let (ccl_da, dcl_da) = self.control.targets();
        self.limits.map(|l| OwnPack {
            state,
            age,
            limits: Limits {
                ccl_da,
                dcl_da,
                ..l
            },
            conditions: self.conditions,
            capacity_cah: settings.capacity_cah,
        })
    }

    /// This pack's data `age` old: stale once (reported when it becomes so),
    /// or fresh — reported when it was stale, and its limits computed. A pack
    /// that was stale left the battery meanwhile; the battery's hold and ramp
    /// rule its return (see `packs`), not this pack's.
    fn refresh_own(
        &mut self,
        now: Instant,
        age: Instant,
        settings: &PackSettings,
        state: &PackState,
    ) {
        if !self.config.freshness.young(Some(age)) {
            if self.stale.starts(now) {
                self.report_stale(age, None);
            }
        } else {
            if self.stale.ends() {
                self.reports.push(InverterReport::Fresh);
            }
            self.update_own(now, settings, state);
        }
    }

    /// As the speaker: the battery's limits (logged when they change, kept for
    /// the stop said when the battery is lost) and its inverter frames.
    fn speak_for_battery(&mut self, now: Instant, battery: &Battery, limits: Limits, slow: bool) {
        self.membership.speaks(battery, limits, &mut self.reports);
        self.watch_ignored(now, battery.state.current_a);
        let made = Made {
            state: &battery.state,
            conditions: &battery.conditions,
            capacity_ah: capacity_ah(battery),
            modules: modules(battery),
            slow,
        };
        self.tell_fresh(now, &limits, &made);
    }

    /// As the speaker, no pack takes part: both sides stop, said with every
    /// signal, from the battery last spoken for.
    fn tell_battery_lost(&mut self, now: Instant, battery: &Battery, limits: Limits) {
        let made = Made {
            state: &battery.state,
            conditions: &battery.conditions,
            capacity_ah: capacity_ah(battery),
            modules: (0, 0, 0, u16::from(battery.online)),
            slow: false,
        };
        let stops = Stops {
            charge: Some(StopWhy::LinkLost),
            discharge: Some(StopWhy::LinkLost),
        };
        self.tell(now, limits, stops, Signals::ALL, false, false, &made);
    }
}

/// The battery's capacity, Ah.
fn capacity_ah(battery: &Battery) -> u16 {
    (battery.capacity_dah / DAH_PER_AH).min(u32::from(u16::MAX)) as u16
}

/// The battery's modules: online, blocking charge, blocking discharge,
/// offline.
fn modules(battery: &Battery) -> (u16, u16, u16, u16) {
    (
        u16::from(battery.online),
        u16::from(battery.blocking_charge),
        u16::from(battery.blocking_discharge),
        u16::from(battery.offline),
    )
}

/// This pack as it goes into the battery (with a node number).
#[derive(Debug, Clone, Copy)]
struct OwnPack {
    /// Its state, as last decoded.
    state: PackState,
    /// The age of that state, µs.
    age: Instant,
    /// Its limits, CCL and DCL before its own hold and ramp.
    limits: Limits,
    /// Its alarms and warnings.
    conditions: Conditions,
    /// Its capacity (306), 0.01 Ah.
    capacity_cah: u16,
}

/// Every pack of the battery once: their node numbers and members in the same
/// order, and the packs in the battery's sums as bits (node n: bit n − 1).
struct Gathered {
    nodes: heapless::Vec<u8, { packs::MAX_NODES as usize }>,
    members: heapless::Vec<Member, { packs::MAX_NODES as usize }>,
    mask: u16,
}

impl Gathered {
    fn new() -> Self {
        Self {
            nodes: heapless::Vec::new(),
            members: heapless::Vec::new(),
            mask: 0,
        }
    }

    /// Node `n` as `m`. The packs in the battery's sums: a pack without fresh
    /// data that may still conduct stays (no hold restarts when a lossy bus
    /// makes packs come and go); one known open leaves.
    fn add(&mut self, n: u8, m: Member, freshness: Freshness) {
        let _ = self.nodes.push(n);
        if m.in_sums(freshness) {
            self.mask |= node_bit(n);
        }
        let _ = self.members.push(m);
    }
}

/// Node `n`'s bit in a mask of nodes (bit `n − 1`; the index wrapped to the
/// mask's 16 bits).
const fn node_bit(n: u8) -> u16 {
    1 << (n.saturating_sub(1) & (u16::BITS as u8 - 1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_bits_are_one_below_the_node_and_wrap_to_sixteen() {
        assert_eq!(node_bit(1), 1);
        assert_eq!(node_bit(8), 0x80);
        assert_eq!(node_bit(0), 1, "saturates at bit 0");
        assert_eq!(node_bit(17), 1, "wrapped to the mask's 16 bits");
    }

    #[test]
    fn a_duplicate_of_this_node_is_reported_once_and_silences_it() {
        let mut s = Membership::new(3, 0);
        let mut r = Reports::default();
        // A bridge alone has no view; a member has one with itself unknown yet.
        assert!(Membership::new(0, 0)
            .view(0, Freshness::default())
            .is_none());
        assert!(s.view(0, Freshness::default()).is_some());
        assert!(
            !s.elect(0, false, &mut r),
            "no summary of its own: never speaks"
        );
        s.duplicate_reported = true;
        assert!(!s.elect(10 * crate::SECOND, true, &mut r));
        assert_eq!(r.pop(), None);
    }

    #[test]
    fn the_battery_lost_is_reported_once_and_its_stop_said_as_the_inverter_needs() {
        let mut s = Membership::new(1, 0);
        let mut r = Reports::default();
        assert_eq!(s.lose_battery(0, true, OnSilence::RunsOn, &mut r), None);
        assert_eq!(r.pop(), None, "no battery yet is no battery lost");
        s.battery_lost = false;
        let sent = Limits {
            ccl_da: 500,
            dcl_da: 600,
            cvl_dv: 560,
            discharge_dv: 480,
        };
        let state = PackState {
            min_cell_mv: 3300,
            max_cell_mv: 3310,
            pack_v: 52.9,
            current_a: -10.0,
            soc_pct: 50.0,
            soh_pct: 100.0,
            min_temp_c: 20.0,
            max_temp_c: 21.0,
            fault: false,
            charge_blocked: false,
            balancing: 0,
        };
        let battery = Battery {
            state,
            limits: sent,
            conditions: Conditions::default(),
            capacity_dah: 2800,
            online: 1,
            offline: 0,
            unknown: 0,
            blocking_charge: 0,
            blocking_discharge: 0,
        };
        s.speaks(&battery, sent, &mut r);
        assert_eq!(r.pop(), Some(InverterReport::BatteryLimits(sent)));
        // An inverter that may run on: the stop every period.
        for t in 1..20 {
            let got = s.lose_battery(t, true, OnSilence::RunsOn, &mut r);
            assert_eq!(got.map(|(_, l)| l), Some(sent), "{t}");
        }
        assert_eq!(r.pop(), Some(InverterReport::BatteryLost));
        assert_eq!(r.pop(), None, "reported once");
        // Not the speaker: nothing to say.
        assert_eq!(s.lose_battery(21, false, OnSilence::RunsOn, &mut r), None);
        // One that stops on silence: the stop a few periods, then quiet.
        let mut s = Membership::new(1, 0);
        s.speaks(&battery, sent, &mut r);
        let said = (0..20)
            .filter(|t| s.lose_battery(*t, true, OnSilence::Stops, &mut r).is_some())
            .count();
        assert_eq!(
            said,
            usize::from(crate::inverter::dialect::STOP_BEFORE_QUIET)
        );
    }
}
