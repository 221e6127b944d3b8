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
//! The budget is spent at the worst draw the BMS allows: its discharge
//! over-current cutoff (317), or the current last measured if that was
//! higher — an inverter that ignores the discharge limit (an off-grid one that
//! obeys only the SOC, a Multi in island mode that ignores any limit but 0)
//! draws at most that without tripping the BMS. The discharge limit then
//! falls linearly from its last value to 0 over that time
//! ([`HoldBudget::spend_us`], at most the hold itself): an inverter that obeys
//! the falling limit, or overshoots it by 20 %, takes a fraction of the
//! budget, one that ignores every limit at most all of it, and the discharge
//! stop is `discharge_margin` above the cutoff besides. When the limit reaches
//! 0 the hold is over: the stop goes out with every signal.

use super::control::{ChargeConfig, PackSettings, PackState};
use crate::Instant;

/// The least share of its capacity a lithium cell gives per volt it falls,
/// anywhere between full and its cutoff (its empty knee is the steepest),
/// per mille per volt: 20 = 2 % of the capacity per volt.
pub const KNEE_CAPACITY_PERMILLE_PER_V: u64 = 20;

/// mA per A.
const MA_PER_A: u64 = 1000;

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
        let measured_ma = (state.current_a.min(0.0) * -1000.0).clamp(0.0, 1e9) as u64;
        let draw_ma = (u64::from(settings.discharge_cutoff_a) * MA_PER_A).max(measured_ma);
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

    /// A 280 Ah, 16-cell pack with a 2.5 V cutoff and a 60 A discharge
    /// over-current cutoff (the simulated pack's).
    fn settings() -> PackSettings {
        PackSettings {
            fully_charged_mv: 3550,
            capacity_cah: 28_000,
            cells: 16,
            allowed_disbalance_mv: 15,
            ov_cutoff_mv: 3650,
            uv_cutoff_mv: 2500,
            discharge_cutoff_a: 60,
            charge_cutoff_a: 60,
            discharge_cutoff_s: 5,
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
            balancing: 0,
        }
    }

    const HOLD: Instant = 120 * crate::SECOND;

    /// The case: a lowest cell of 2.80 V (200 mV above the discharge
    /// stop of 2.60 V), 280 Ah: 2 % × 0.2 × 280 Ah = 1.12 Ah, spent at the
    /// 60 A the BMS allows in 67.2 s — not the 120 s of the old hold.
    #[test]
    fn a_low_cell_affords_a_short_hold() {
        let b = HoldBudget::new(
            &state(2800, -40.0),
            &settings(),
            &ChargeConfig::default(),
            480,
            HOLD,
        );
        assert_eq!(b.budget_mah, 1120);
        assert_eq!(b.spend_us, 67_200_000);
        assert_eq!(b.dcl_at(0), 480);
        assert_eq!(b.dcl_at(33_600_000), 240);
        assert_eq!(b.dcl_at(67_200_000), 0);
        assert!(b.spent(70 * crate::SECOND));
        // Drawn at the falling limit with a 20 % overshoot, or at the BMS's
        // cutoff until the limit is 0 (an inverter that ignores it): at most
        // the budget.
        let (mut obeying, mut ignoring) = (0u64, 0u64);
        let step = 100_000;
        let mut t = 0;
        while t < HOLD {
            obeying += u64::from(b.dcl_at(t)) * 100 * 120 / 100 * step / crate::SECOND;
            if !b.spent(t) {
                ignoring += 60_000 * step / crate::SECOND;
            }
            t += step;
        }
        assert!(obeying / 3600 <= b.budget_mah, "{} mAh", obeying / 3600);
        assert!(ignoring / 3600 <= b.budget_mah, "{} mAh", ignoring / 3600);
    }

    /// On the plateau (3.25 V, 650 mV above the stop) the whole hold is
    /// afforded; at or below the stop nothing is.
    #[test]
    fn the_plateau_affords_the_hold_and_the_stop_none() {
        let b = HoldBudget::new(
            &state(3250, -20.0),
            &settings(),
            &ChargeConfig::default(),
            300,
            HOLD,
        );
        // 3.64 Ah at 60 A: 218 s, more than the hold.
        assert_eq!((b.budget_mah, b.spend_us), (3640, HOLD));
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

    /// A current measured above the BMS's cutoff (an inverter already past
    /// it) is the draw the budget is spent at.
    #[test]
    fn the_larger_of_the_cutoff_and_the_current_spends_it() {
        let s = settings();
        let c = ChargeConfig::default();
        let within = HoldBudget::new(&state(2800, -50.0), &s, &c, 480, HOLD);
        let past = HoldBudget::new(&state(2800, -120.0), &s, &c, 480, HOLD);
        assert_eq!(within.spend_us, 2 * past.spend_us);
    }
}
