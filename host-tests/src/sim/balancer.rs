//! The TinyBMS's balancer as the simulator models it: dissipative, up to
//! 150 mA a cell (Energus's datasheet, "dissipative balancing up to
//! 150 mA"), only while the pack charges or rests after a charge (the unit's
//! "charging" and "fully charged" states: never while discharging), only
//! above the early-balancing threshold (303), and only the cells above the
//! lowest by more than half the allowed disbalance (308). Registers 51 (decision: would balance) and 52 (real:
//! balancing now) are reported as the unit does: bit 0 = the first cell.
//!
//! Rev D and the manual do not say how far above the lowest cell a cell must
//! be to be bled; half of 308 is this model's choice (a balancer that stops
//! at 308 itself would leave every charge's end at the allowed disbalance).

/// What one balancing cell bleeds, A.
pub const BALANCE_CURRENT_A: f64 = 0.150;

/// The pack counts as discharging below this current, A (the simulator's
/// idle band): no balancing then.
pub const DISCHARGING_BELOW_A: f64 = -0.5;

/// Registers 51 and 52 for cells at `cells_mv`: (decision, real).
pub fn bits(cells_mv: &[u16], early_mv: u16, allowed_mv: u16, current_a: f64) -> (u16, u16) {
    let Some(&lowest) = cells_mv.iter().min() else {
        return (0, 0);
    };
    let band = allowed_mv / 2;
    let mut decision = 0u16;
    for (i, &mv) in cells_mv.iter().enumerate().take(16) {
        if mv > early_mv && mv > lowest.saturating_add(band) {
            decision |= 1 << i;
        }
    }
    let real = if current_a > DISCHARGING_BELOW_A {
        decision
    } else {
        0
    };
    (decision, real)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_above_the_threshold_and_the_band_and_never_while_discharging() {
        let cells = [3380, 3420, 3431, 3500];
        // 303 = 3400, 308 = 15: band 7 mV above the lowest (3380).
        assert_eq!(bits(&cells, 3400, 15, 10.0), (0b1110, 0b1110));
        assert_eq!(bits(&cells, 3400, 15, 0.2), (0b1110, 0b1110), "resting");
        assert_eq!(bits(&cells, 3400, 15, -5.0), (0b1110, 0), "discharging");
        assert_eq!(bits(&cells, 3450, 15, 10.0), (0b1000, 0b1000));
        // A balanced pack above the threshold: nothing to bleed.
        assert_eq!(bits(&[3500, 3504, 3502], 3400, 15, 10.0), (0, 0));
        assert_eq!(bits(&[], 3400, 15, 10.0), (0, 0));
    }
}
