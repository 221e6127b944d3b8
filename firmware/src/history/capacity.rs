//! The pack's capacity, estimated by the bridge from its own charge count
//! between two points whose state of charge (SOC) is known — the TinyBMS's
//! SOC is a coulomb counter that trusts the capacity it was told (306), so
//! it cannot say what the cells really hold as they age.
//!
//! ## The two known points
//!
//! - **Full**: the BMS says so (status "fully charged", register 50 =
//!   0x92): the pack is at 100 %. Or the bridge's own charge control says
//!   so ([`charge_finished`]: absorption held until the current tapered,
//!   then the step into float) — behind the bridge a TinyBMS rarely says it
//!   itself: its "fully charged voltage" (300) is above the bridge's
//!   absorption target (315 − 100 mV by default), which the cells then
//!   never reach. The caller hands that snapshot in as "fully charged".
//! - **The knee**: the lowest cell crossing down through the knee voltage
//!   while the pack discharges at a modest current (at most
//!   [`KNEE_MAX_C_PERMILLE`] ‰ of the nominal capacity per hour, 0.2 C):
//!   below it the voltage of a nearly empty cell falls steeply, so the
//!   crossing happens at an SOC the chemistry fixes. A faster discharge
//!   crosses it earlier (the cell's I·R and polarisation), so it does not
//!   count.
//!
//! The chemistry is read from the BMS's "fully charged voltage" (300):
//! 3300-3700 mV is LiFePO4, whose knee is taken at [`LFP_KNEE_MV`] = 3000 mV,
//! at [`LFP_KNEE_SOC_PERMILLE`] = 3.5 % ± [`LFP_KNEE_SOC_UNCERTAINTY_PERMILLE`]
//! = 1.5 %. Where that comes from: the simulator's LiFePO4 curve
//! (`host-tests/src/year.rs`) puts 3000 mV at rest at 2.9 % (between 2.95 V
//! at 2 % and 3.12 V at 5 %); at 0.2 C its cells stand about 55 mV lower
//! (I·R and polarisation), so the crossing happens at 2.9-3.9 % for any
//! current this module accepts; 1.5 % also leaves room for real cells
//! whose curve differs. Any other chemistry (NMC and its sloped curve, LTO's
//! 2.7-2.85 V) has no knee here: no estimate (unknown rather than guessed).
//!
//! ## A run
//!
//! From one known point to the other, the bridge counts the net charge
//! (pack current × time, positive charging) over the snapshots:
//!
//! - full → knee (a discharge): capacity = net Ah out / (1 − SOC at the knee);
//! - knee → full (a charge): capacity = net Ah in / (1 − SOC at the knee)
//!   (no coulombic efficiency: a LiFePO4 cell's is above 99.5 %, inside the
//!   uncertainty).
//!
//! The count only goes on between good snapshots at most [`MAX_GAP_US`]
//! apart (10 s, the rule of [`crate::energy`]): a longer gap without a good
//! snapshot abandons the run (the charge that flowed then is unknown); so
//! does a run longer than [`MAX_RUN_US`] (4 days: the current sensor's
//! offset and the cells' self-discharge add up), and unknown settings. Each
//! known point starts a new run (the latest full, the latest crossing).
//!
//! Each qualifying run gives an [`Estimate`] with its uncertainty: the
//! knee's SOC uncertainty over (1 − SOC at the knee) plus half a step of the
//! current's resolution ([`CURRENT_RESOLUTION_MA`], assumed 0.1 A) held over
//! the run's length, over the charge counted. An estimate outside half to
//! one and a half times the nominal capacity is refused (a run that cannot
//! be one). What is reported ([`Capacity::estimate`]) is the median of the
//! last [`KEPT`] estimates; with none, nothing (`None`: unknown).
//!
//! All the counting is integer (mA × µs); the snapshot's current (f32 A) is
//! rounded to the mA.

use protocol_core::events::OnlineStatus;
use protocol_core::views::LiveSnapshot;

use crate::inverter::control::PackSettings;
use crate::{Instant, SECOND};

/// A gap between two good snapshots longer than this abandons a run, µs.
pub const MAX_GAP_US: Instant = crate::energy::MAX_GAP_US;
/// A run longer than this is abandoned, µs (4 days).
pub const MAX_RUN_US: Instant = 4 * 24 * 3600 * SECOND;
/// The knee of a LiFePO4 cell, mV.
pub const LFP_KNEE_MV: u16 = 3000;
/// The SOC of a LiFePO4 cell at its knee, ‰.
pub const LFP_KNEE_SOC_PERMILLE: u32 = 35;
/// Its uncertainty, ‰ of SOC.
pub const LFP_KNEE_SOC_UNCERTAINTY_PERMILLE: u32 = 15;
/// "Fully charged voltage" (300) that marks LiFePO4, mV.
pub const LFP_FULL_MV: (u16, u16) = (3300, 3700);
/// The fastest discharge through the knee that counts, ‰ of the nominal
/// capacity per hour (0.2 C).
pub const KNEE_MAX_C_PERMILLE: u32 = 200;
/// The resolution of the pack current assumed, mA.
pub const CURRENT_RESOLUTION_MA: u64 = 100;
/// Estimates kept for the median.
pub const KEPT: usize = 5;

/// mA·µs in 0.01 Ah.
const MA_US_PER_CAH: i64 = 36_000_000_000;
/// A current beyond this is nonsense, mA (10 kA).
const MAX_MA: f32 = 10_000_000.0;

/// The bridge's charge control has just finished a charge: its stage went
/// from absorption (or the balance hold) to the step into float or float —
/// the highest cell at the absorption target and the current tapered below
/// the tail current: the pack is full (a known point, as the BMS's "fully
/// charged").
pub fn charge_finished(
    before: Option<&crate::inverter::finish::Stage>,
    now: Option<&crate::inverter::finish::Stage>,
) -> bool {
    use crate::inverter::finish::Stage;
    matches!(before, Some(Stage::Absorption | Stage::BalanceHeld { .. }))
        && matches!(now, Some(Stage::StepDown { .. } | Stage::Float))
}

/// One capacity estimate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Estimate {
    /// Capacity, 0.01 Ah.
    pub cah: u32,
    /// Its uncertainty, ‰ of it.
    pub uncertainty_permille: u16,
    /// Runs that qualified since start-up (this one included).
    pub runs: u16,
}

/// What a chemistry's knee is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Knee {
    mv: u16,
    soc_permille: u32,
    uncertainty_permille: u32,
}

/// The knee of the chemistry these settings say, `None` when unknown.
fn knee_of(s: &PackSettings) -> Option<Knee> {
    (LFP_FULL_MV.0..=LFP_FULL_MV.1)
        .contains(&s.fully_charged_mv)
        .then_some(Knee {
            mv: LFP_KNEE_MV,
            soc_permille: LFP_KNEE_SOC_PERMILLE,
            uncertainty_permille: LFP_KNEE_SOC_UNCERTAINTY_PERMILLE,
        })
}

/// Which known point a run started from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum From {
    Full,
    Knee,
}

/// The estimator. See the module documentation.
#[derive(Debug, Clone)]
pub struct Capacity {
    /// The run under way: where it started, when.
    run: Option<(From, Instant)>,
    /// Net charge into the pack since the run started, mA·µs.
    net: i64,
    /// The last good snapshot: time, current (mA), lowest cell (mV).
    last: Option<(Instant, i64, u16)>,
    /// The last estimates, oldest first overwritten.
    kept: [Option<Estimate>; KEPT],
    next: usize,
    latest: Option<Estimate>,
    runs: u16,
}

impl Default for Capacity {
    fn default() -> Self {
        Self::new()
    }
}

impl Capacity {
    /// No run, no estimate.
    pub const fn new() -> Self {
        Self {
            run: None,
            net: 0,
            last: None,
            kept: [None; KEPT],
            next: 0,
            latest: None,
            runs: 0,
        }
    }

    /// The last qualifying run's estimate.
    pub fn latest(&self) -> Option<Estimate> {
        self.latest
    }

    /// Runs that qualified since start-up.
    pub fn runs(&self) -> u16 {
        self.runs
    }

    /// Whether a run is under way (from full or from the knee).
    pub fn running(&self) -> bool {
        self.run.is_some()
    }

    /// The capacity: the median of the last [`KEPT`] estimates (of two
    /// middle ones, their mean), with the median of their uncertainties or
    /// half their spread, whichever is larger; `None` before any run
    /// qualified.
    pub fn estimate(&self) -> Option<Estimate> {
        let mut cah = [0u32; KEPT];
        let mut unc = [0u32; KEPT];
        let mut n = 0;
        for (e, (c, u)) in self.kept.iter().flatten().zip(cah.iter_mut().zip(&mut unc)) {
            *c = e.cah;
            *u = u32::from(e.uncertainty_permille);
            n += 1;
        }
        let (cah, unc) = (cah.get(..n)?, unc.get(..n)?);
        let mid = median(cah)?;
        let spread = cah.iter().max()?.saturating_sub(*cah.iter().min()?);
        let half_spread = u64::from(spread) * 500 / u64::from(mid.max(1));
        let unc_mid = median(unc)?;
        Some(Estimate {
            cah: mid,
            uncertainty_permille: u16::try_from(u64::from(unc_mid).max(half_spread))
                .unwrap_or(u16::MAX),
            runs: self.runs,
        })
    }

    /// A snapshot decoded at `at`; `valid` false for a flagged one (skipped:
    /// the gap since the last good one decides). Returns the estimate of a
    /// run that qualified with it.
    pub fn on_snapshot(
        &mut self,
        at: Instant,
        s: &LiveSnapshot,
        valid: bool,
        settings: Option<&PackSettings>,
    ) -> Option<Estimate> {
        let Some((settings, knee)) = settings.and_then(|st| Some((st, knee_of(st)?))) else {
            self.run = None;
            self.last = None;
            return None;
        };
        let amps = s.pack_current_a * 1000.0;
        if !valid || !amps.is_finite() || amps.abs() > MAX_MA {
            return None;
        }
        let ma = if amps < 0.0 { amps - 0.5 } else { amps + 0.5 } as i64;
        let mut found = None;
        // The lowest cell of the last good snapshot, when the interval since
        // counted (a crossing across a gap is no known point).
        let mut before_mv = None;
        match self.last {
            Some((t0, ma0, mv0)) if at > t0 && at - t0 <= MAX_GAP_US => {
                self.net = self
                    .net
                    .saturating_add(ma0.saturating_mul((at - t0) as i64));
                before_mv = Some(mv0);
            }
            // Time went back or stood still: nothing to count, nothing lost.
            Some((t0, _, _)) if at <= t0 => {}
            _ => self.run = None,
        }
        if self
            .run
            .is_some_and(|(_, since)| at.saturating_sub(since) > MAX_RUN_US)
        {
            self.run = None;
        }
        let nominal_cah = i64::from(settings.capacity_cah);
        if s.status == OnlineStatus::FullyCharged {
            if let Some((From::Knee, since)) = self.run {
                found = self.qualify(self.net, at - since.min(at), knee, nominal_cah);
            }
            self.start(From::Full, at);
        } else if let Some(mv0) = before_mv {
            // mA at 0.2 C = cAh × 10 × 0.2.
            let modest = nominal_cah * 10 * i64::from(KNEE_MAX_C_PERMILLE) / 1000;
            let crossed = mv0 >= knee.mv && s.min_cell_mv < knee.mv;
            if crossed && ma < 0 && -ma <= modest {
                if let Some((From::Full, since)) = self.run {
                    found = self.qualify(-self.net, at - since.min(at), knee, nominal_cah);
                }
                self.start(From::Knee, at);
            }
        }
        self.last = Some((at, ma, s.min_cell_mv));
        found
    }

    fn start(&mut self, from: From, at: Instant) {
        self.run = Some((from, at));
        self.net = 0;
    }

    /// The estimate of a run that counted `counted` mA·µs over `length` µs,
    /// kept when it qualifies.
    fn qualify(
        &mut self,
        counted: i64,
        length: Instant,
        knee: Knee,
        nominal_cah: i64,
    ) -> Option<Estimate> {
        let counted_cah = counted / MA_US_PER_CAH;
        let share = 1000 - i64::from(knee.soc_permille);
        let cah = counted_cah.checked_mul(1000)? / share;
        if cah * 2 < nominal_cah || cah * 2 > nominal_cah * 3 || counted <= 0 {
            return None;
        }
        // Half a step of the current's resolution held over the run, over
        // the charge counted: (mA·µs) / (mA·µs), ‰.
        let offset = (CURRENT_RESOLUTION_MA / 2).saturating_mul(length);
        let drift = offset.saturating_mul(1000) / counted.unsigned_abs().max(1);
        let knee_part = u64::from(knee.uncertainty_permille) * 1000 / share.unsigned_abs();
        self.runs = self.runs.saturating_add(1);
        let e = Estimate {
            cah: u32::try_from(cah).ok()?,
            uncertainty_permille: u16::try_from(drift.saturating_add(knee_part))
                .unwrap_or(u16::MAX),
            runs: self.runs,
        };
        if let Some(slot) = self.kept.get_mut(self.next) {
            *slot = Some(e);
        }
        self.next = (self.next + 1) % KEPT;
        self.latest = Some(e);
        Some(e)
    }
}

/// The median of `v` (of two middle values, their mean); `None` when empty.
fn median(v: &[u32]) -> Option<u32> {
    let mut all = [0u32; KEPT];
    for (d, x) in all.iter_mut().zip(v) {
        *d = *x;
    }
    let s = all.get_mut(..v.len().min(KEPT))?;
    s.sort_unstable();
    let n = s.len();
    let hi = *s.get(n / 2)?;
    if n % 2 == 1 {
        return Some(hi);
    }
    let lo = *s.get(n.checked_sub(1)? / 2)?;
    Some(((u64::from(lo) + u64::from(hi)) / 2) as u32)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use protocol_core::views::Cells;

    /// The simulator's pack: 16 LiFePO4 cells of 280 Ah, 300 = 3650 mV.
    pub(crate) fn settings() -> PackSettings {
        PackSettings {
            fully_charged_mv: 3650,
            capacity_cah: 28000,
            cells: 16,
            allowed_disbalance_mv: 15,
            ov_cutoff_mv: 3650,
            uv_cutoff_mv: 2500,
            discharge_cutoff_a: 150,
            charge_cutoff_a: 150,
            discharge_cutoff_s: 5,
            overheat_c: 60,
            low_temp_charge_c: 0,
        }
    }

    /// A snapshot of 16 cells between `min` and `max` mV at `current` A.
    pub(crate) fn snap(min: u16, max: u16, current: f32, status: OnlineStatus) -> LiveSnapshot {
        let mut raw = heapless::Vec::new();
        for i in 0..16u16 {
            let mv = if i == 5 {
                max
            } else if i == 9 {
                min
            } else {
                (min + max) / 2
            };
            raw.push(mv * 10).unwrap();
        }
        LiveSnapshot {
            cells: Cells {
                first_register: 0,
                raw,
            },
            cell_count: 16,
            lifetime_s: 0,
            estimated_time_left_s: 0,
            pack_voltage_v: f32::from(min + max) * 8.0 / 1000.0,
            pack_current_a: current,
            min_cell_mv: min,
            max_cell_mv: max,
            external1_dc: None,
            external2_dc: None,
            distance_left_km: 0,
            soh_raw: 50000,
            soc_raw: 50_000_000,
            internal_dc: 250,
            status,
            balancing_decision_bits: 0,
            real_balancing_bits: 0,
            speed_kmh: 0.0,
        }
    }

    const FULL: OnlineStatus = OnlineStatus::FullyCharged;
    const DIS: OnlineStatus = OnlineStatus::Discharging;

    /// Full at t = 0, then `amps` A out for `secs` s (a snapshot a second)
    /// with the lowest cell above the knee, then one below it.
    fn full_then_discharge(
        c: &mut Capacity,
        amps: f32,
        secs: u64,
        gap_at: Option<u64>,
    ) -> Option<Estimate> {
        let st = settings();
        c.on_snapshot(0, &snap(3400, 3410, 0.0, FULL), true, Some(&st));
        let mut t = 0;
        for k in 1..=secs {
            if gap_at == Some(k) {
                t += 11 * SECOND;
            } else {
                t += SECOND;
            }
            let r = c.on_snapshot(t, &snap(3100, 3120, -amps, DIS), true, Some(&st));
            assert_eq!(r, None);
        }
        c.on_snapshot(t + SECOND, &snap(2990, 3100, -amps, DIS), true, Some(&st))
    }

    #[test]
    fn an_exact_full_to_knee_run_gives_the_capacity() {
        let mut c = Capacity::new();
        assert_eq!(c.estimate(), None);
        // 27 A for 10 h = 270 Ah out (the snapshot at full counts 0 A for
        // its first second): 270 / 0.965 = 279.79 Ah.
        let e = full_then_discharge(&mut c, 27.0, 36_000, None).unwrap();
        assert_eq!(e.cah, 27_000 * 1000 / 965);
        assert_eq!(e.runs, 1);
        // Knee: 15 / 965 = 15 ‰; the current: 50 mA × 36 001 s over
        // 270 Ah = 1.85 ‰ → 15 + 1 (floors).
        assert_eq!(e.uncertainty_permille, 15 + 1);
        assert_eq!(c.latest(), Some(e));
        assert_eq!(c.estimate(), Some(e));
    }

    #[test]
    fn a_knee_to_full_run_gives_the_capacity_too() {
        let st = settings();
        let mut c = Capacity::new();
        c.on_snapshot(0, &snap(3100, 3120, -20.0, DIS), true, Some(&st));
        assert!(!c.running());
        c.on_snapshot(SECOND, &snap(2995, 3050, -20.0, DIS), true, Some(&st));
        assert!(c.running());
        // 2 s at −20 A then 50 A for 5.4 h + 2 s (≈ 270 Ah net).
        let mut t = SECOND;
        let mut e = None;
        for k in 0..19_500u64 {
            t += SECOND;
            e = c.on_snapshot(
                t,
                &snap(3300, 3320, 50.0, OnlineStatus::Charging),
                true,
                Some(&st),
            );
            assert_eq!(e, None, "{k}");
        }
        e = e.or(c.on_snapshot(t + SECOND, &snap(3500, 3550, 0.0, FULL), true, Some(&st)));
        // −20 A × 1 s + 50 A × 19 500 s = 270.8278 Ah → 280.64 Ah.
        let net_cah = (50_000i64 * 19_500 - 20_000) * 1_000_000 / MA_US_PER_CAH;
        assert_eq!(e.unwrap().cah as i64, net_cah * 1000 / 965);
    }

    #[test]
    fn a_gap_abandons_the_run() {
        let mut c = Capacity::new();
        assert_eq!(
            full_then_discharge(&mut c, 27.0, 36_000, Some(20_000)),
            None
        );
        assert_eq!(c.estimate(), None);
        // 10 s is no gap yet.
        let st = settings();
        let mut c = Capacity::new();
        c.on_snapshot(0, &snap(3400, 3410, 0.0, FULL), true, Some(&st));
        c.on_snapshot(10 * SECOND, &snap(3100, 3120, -27.0, DIS), true, Some(&st));
        assert!(c.running());
        // Flagged snapshots are skipped: the next good one 11 s later is a gap.
        c.on_snapshot(15 * SECOND, &snap(3100, 3120, -27.0, DIS), false, Some(&st));
        c.on_snapshot(21 * SECOND, &snap(3100, 3120, -27.0, DIS), true, Some(&st));
        assert!(!c.running());
    }

    #[test]
    fn a_fast_discharge_through_the_knee_does_not_qualify() {
        // 0.25 C = 70 A: the crossing is no known point.
        let mut c = Capacity::new();
        assert_eq!(full_then_discharge(&mut c, 70.0, 13_900, None), None);
        assert_eq!(c.estimate(), None);
        // 56 A (0.2 C) does.
        let mut c = Capacity::new();
        assert!(full_then_discharge(&mut c, 56.0, 17_400, None).is_some());
    }

    #[test]
    fn unknown_settings_a_run_too_long_or_another_chemistry_give_nothing() {
        let mut c = Capacity::new();
        c.on_snapshot(0, &snap(3400, 3410, 0.0, FULL), true, None);
        assert!(!c.running());
        // NMC (4150 mV fully charged): no knee.
        let nmc = PackSettings {
            fully_charged_mv: 4150,
            ..settings()
        };
        c.on_snapshot(0, &snap(3400, 3410, 0.0, FULL), true, Some(&nmc));
        assert!(!c.running());
        // 270 Ah in 4 days and 10 s: past MAX_RUN_US; 20 s sooner, a run.
        let mut c = Capacity::new();
        assert_eq!(
            full_then_discharge(&mut c, 2.8125, 4 * 86_400 + 10, None),
            None
        );
        let mut c = Capacity::new();
        assert!(full_then_discharge(&mut c, 2.8125, 4 * 86_400 - 10, None).is_some());
        // A run that cannot be one (10 Ah from full to the knee) is refused.
        let mut c = Capacity::new();
        assert_eq!(full_then_discharge(&mut c, 10.0, 3600, None), None);
        assert_eq!(c.runs(), 0);
    }

    #[test]
    fn the_estimate_is_the_median_of_the_last_five() {
        let mut c = Capacity::new();
        for (i, amps) in [27.0, 26.0, 27.5, 20.0, 27.2, 27.1, 26.9]
            .iter()
            .enumerate()
        {
            assert!(
                full_then_discharge(&mut c, *amps, 36_000, None).is_some(),
                "{i}"
            );
        }
        // Kept: 27.5, 20.0, 27.2, 27.1, 26.9 A × 10 h; the median 27.1 A.
        let e = c.estimate().unwrap();
        assert_eq!(e.cah, 27_100 * 1000 / 965);
        assert_eq!(e.runs, 7);
        assert_eq!(c.latest().unwrap().cah, 26_900 * 1000 / 965);
        // Half the spread (75 Ah over 280.8) dominates the uncertainty.
        assert_eq!(
            e.uncertainty_permille,
            (7_500 * 1000 / 965 * 500 / e.cah) as u16
        );
        assert_eq!(median(&[3, 1]), Some(2));
        assert_eq!(median(&[]), None);
    }
}
