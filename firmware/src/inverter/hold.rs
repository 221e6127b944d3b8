//! The hold the pack can afford: how much an inverter may still discharge
//! while the BMS's data is stale (`stale_policy = hold`), decided once from
//! the last fresh data, and how the discharge limit decays to 0 where that
//! budget could be spent.
//!
//! **The physics.** Nothing is measured during a gap, so the bridge may
//! allow only the charge the last fresh data *proves* the pack still holds
//! above its discharge stop (316 + `discharge_margin`). What proves it is the
//! lowest cell's voltage: a lithium cell's voltage falls fastest with the
//! charge taken in its empty knee, and even there (LiFePO4 from about
//! 2.9 V down to its cutoff, NMC below about 3.3 V) each volt it stands
//! above a lower voltage is at least [`KNEE_CAPACITY_PERMILLE_PER_V`] (2 %)
//! of its capacity. So a cell `Δ` volts above the discharge stop holds at
//! least 2 % × `Δ` × capacity (306, times SOH) before it reaches the stop —
//! a lower bound wherever the cell is on its curve (on the plateau it holds
//! far more), and one that needs no SOC, which drifts.
//!
//! The budget is spent at the worst draw the inverter could make: the
//! larger of the discharge limit at the start and the current last measured,
//! plus [`OVERSHOOT_PERCENT`] for an inverter that overshoots a limit (real
//! ones overshoot by up to 20 %). The discharge limit then falls linearly
//! from its last value to 0 over that time ([`HoldBudget::spend_us`], at most
//! the hold itself): an inverter that obeys the falling limit takes half the
//! budget, one that ignores every limit but 0 (a Multi in island mode) at
//! most all of it, and 20 % more still stops short of the BMS's cutoff (the
//! discharge stop is `discharge_margin` above it). When the limit reaches
//! 0 the hold is over: the stop goes out with every signal.

use super::control::{ChargeConfig, PackSettings, PackState};
use crate::Instant;

/// The least share of its capacity a lithium cell gives per volt it falls,
/// anywhere between full and its cutoff (its empty knee is the steepest),
/// per mille per volt: 20 = 2 % of the capacity per volt.
pub const KNEE_CAPACITY_PERMILLE_PER_V: u64 = 20;

/// The draw the budget is spent at: this share of the larger of the
/// discharge limit and the current last measured, percent.
pub const OVERSHOOT_PERCENT: u64 = 120;

/// mA per 0.1 A.
const MA_PER_DA: u64 = 100;

/// The hold's discharge: its limit at the start, and how long until it is
/// spent. See the module documentation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct HoldBudget {
    /// The discharge limit when the data went stale, 0.1 A.
    pub dcl_da: u16,
    /// The charge the pack can afford, mAh.
    pub budget_mah: u64,
    /// How long the limit falls to 0, µs (at most the hold).
    pub spend_us: Instant,
}

impl HoldBudget {
    /// The budget of a hold of at most `hold_us` from the pack's last fresh
    /// `state`, its `settings`, and the discharge limit last sent (`dcl_da`).
    pub fn new(
        state: &PackState,
        settings: &PackSettings,
        charge: &ChargeConfig,
        dcl_da: u16,
        hold_us: Instant,
    ) -> Self {
        let stop_mv = u64::from(settings.uv_cutoff_mv) + u64::from(charge.discharge_margin_mv);
        let above_mv = u64::from(state.min_cell_mv).saturating_sub(stop_mv);
        let soh = (state.soh_pct.clamp(0.0, 100.0) * 10.0) as u64;
        // 0.01 Ah → mAh, times SOH (per mille).
        let capacity_mah = u64::from(settings.capacity_cah) * 10 * soh / 1000;
        // mAh × mV × ‰/V: /1000 for the volts, /1000 for the per mille.
        let budget_mah = capacity_mah * above_mv * KNEE_CAPACITY_PERMILLE_PER_V / 1_000_000;
        let measured_da = (state.current_a.min(0.0) * -10.0).clamp(0.0, 65_535.0) as u64;
        let draw_ma = u64::from(dcl_da).max(measured_da) * MA_PER_DA * OVERSHOOT_PERCENT / 100;
        let spend_us = if dcl_da == 0 || draw_ma == 0 {
            0
        } else {
            // mAh × 3600 s/h / mA = s; in µs.
            (budget_mah * 3600 * crate::SECOND / draw_ma).min(hold_us)
        };
        Self {
            dcl_da,
            budget_mah,
            spend_us,
        }
    }

    /// The discharge limit `elapsed_us` into the hold, 0.1 A: falling
    /// linearly from the start's to 0 at [`HoldBudget::spend_us`].
    pub fn dcl_at(&self, elapsed_us: Instant) -> u16 {
        if elapsed_us >= self.spend_us || self.spend_us == 0 {
            return 0;
        }
        let left = self.spend_us - elapsed_us;
        (u64::from(self.dcl_da) * left / self.spend_us) as u16
    }

    /// The budget is spent `elapsed_us` into the hold.
    pub fn spent(&self, elapsed_us: Instant) -> bool {
        self.dcl_at(elapsed_us) == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> PackSettings {
        PackSettings {
            fully_charged_mv: 3550,
            capacity_cah: 28_000,
            cells: 16,
            allowed_disbalance_mv: 15,
            ov_cutoff_mv: 3650,
            uv_cutoff_mv: 2500,
            discharge_cutoff_a: 150,
            charge_cutoff_a: 100,
            overheat_c: 60,
            low_temp_charge_c: 0,
        }
    }

    fn state(min_cell_mv: u16, current_a: f32) -> PackState {
        PackState {
            min_cell_mv,
            max_cell_mv: min_cell_mv + 20,
            pack_v: f32::from(min_cell_mv) * 16.0 / 1000.0,
            current_a,
            soc_pct: 20.0,
            soh_pct: 100.0,
            min_temp_c: 20.0,
            max_temp_c: 22.0,
            fault: false,
            charge_blocked: false,
        }
    }

    const HOLD: Instant = 120 * crate::SECOND;

    /// The case: a 100 A load from a lowest cell of 2.80 V (200 mV
    /// above the discharge stop of 2.60 V), 280 Ah: 2 % × 0.2 × 280 Ah =
    /// 1.12 Ah, spent at 120 A in 33.6 s — not the 120 s of the old hold.
    #[test]
    fn a_low_cell_affords_a_short_hold() {
        let b = HoldBudget::new(
            &state(2800, -100.0),
            &settings(),
            &ChargeConfig::default(),
            1000,
            HOLD,
        );
        assert_eq!(b.budget_mah, 1120);
        assert_eq!(b.spend_us, 33_600_000);
        assert_eq!(b.dcl_at(0), 1000);
        assert_eq!(b.dcl_at(16_800_000), 500);
        assert_eq!(b.dcl_at(33_600_000), 0);
        assert!(b.spent(40 * crate::SECOND));
        // The charge drawn at the falling limit, with a 20 % overshoot, is at
        // most the budget.
        let mut mas = 0u64;
        let step = 100_000;
        let mut t = 0;
        while t < HOLD {
            mas += u64::from(b.dcl_at(t)) * 100 * 120 / 100 * step / crate::SECOND;
            t += step;
        }
        assert!(mas / 3600 <= b.budget_mah, "{} mAh", mas / 3600);
    }

    /// On the plateau (3.25 V, 650 mV above the stop) the whole hold is
    /// afforded at a modest load; at or below the stop nothing is.
    #[test]
    fn the_plateau_affords_the_hold_and_the_stop_none() {
        let b = HoldBudget::new(
            &state(3250, -20.0),
            &settings(),
            &ChargeConfig::default(),
            300,
            HOLD,
        );
        assert_eq!(b.spend_us, HOLD);
        assert!(b.dcl_at(60 * crate::SECOND) > 100);
        for mv in [2600, 2550, 0] {
            let b = HoldBudget::new(
                &state(mv, -20.0),
                &settings(),
                &ChargeConfig::default(),
                300,
                HOLD,
            );
            assert_eq!((b.spend_us, b.dcl_at(0)), (0, 0), "{mv}");
        }
        // A discharge already stopped stays stopped.
        let b = HoldBudget::new(
            &state(3300, 0.0),
            &settings(),
            &ChargeConfig::default(),
            0,
            HOLD,
        );
        assert_eq!(b.dcl_at(0), 0);
    }

    /// A current measured above the limit (an inverter overshooting it) is
    /// the draw the budget is spent at.
    #[test]
    fn the_larger_of_the_limit_and_the_current_spends_it() {
        let s = settings();
        let c = ChargeConfig::default();
        let at_limit = HoldBudget::new(&state(2800, -50.0), &s, &c, 500, HOLD);
        let over = HoldBudget::new(&state(2800, -100.0), &s, &c, 500, HOLD);
        assert_eq!(at_limit.spend_us, 2 * over.spend_us);
    }
}
