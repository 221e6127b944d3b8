//! Energy in and out of the pack, counted by the bridge: the TinyBMS keeps no
//! energy counter (Rev D has none), so the bridge integrates the power of the
//! snapshots it decoded, pack voltage × pack current over the time between
//! two of them (positive current charges, as the BMS reports it).
//!
//! Only what the BMS sent is counted: only intervals between two good
//! snapshots count (a flagged one counts nothing on either side), and a
//! gap longer than [`MAX_GAP_US`] (link lost, BMS asleep) counts nothing —
//! the energy that flowed then is unknown, and the counters never guess it.
//! Both counters only grow (Home Assistant's `total_increasing`); they start
//! at 0 with the bridge, which Home Assistant's statistics take as a new meter
//! cycle (the dashboard's sums go on without a jump).
//!
//! Tested in host-tests (`tests/energy.rs`): the counters against the
//! integral of what the simulated BMS sent, with a silent link in between.

use crate::{Instant, SECOND};

/// A gap between two snapshots longer than this counts no energy, µs.
pub const MAX_GAP_US: Instant = 10 * SECOND;

/// mW·µs in one mWh.
const MW_US_PER_MWH: u64 = 3_600_000_000;

/// The counters. See the module documentation.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Energy {
    charged_mwh: u64,
    discharged_mwh: u64,
    /// What did not make a whole mWh yet, mW·µs.
    charged_rest: u64,
    discharged_rest: u64,
    /// The previous snapshot: its time and power, mW (signed).
    last: Option<(Instant, i64)>,
}

impl Energy {
    /// Counters at 0.
    pub const fn new() -> Self {
        Self {
            charged_mwh: 0,
            discharged_mwh: 0,
            charged_rest: 0,
            discharged_rest: 0,
            last: None,
        }
    }

    /// Energy into the pack since start-up, mWh.
    pub fn charged_mwh(&self) -> u64 {
        self.charged_mwh
    }

    /// Energy out of the pack since start-up, mWh.
    pub fn discharged_mwh(&self) -> u64 {
        self.discharged_mwh
    }

    /// A snapshot decoded at `at` with this pack voltage and current; `valid`
    /// false for a flagged one. Only an interval between two good snapshots
    /// counts (at the power measured at its start): a flagged or nonsense one
    /// counts nothing on either side of it.
    pub fn on_snapshot(&mut self, at: Instant, voltage_v: f32, current_a: f32, valid: bool) {
        let power_mw = f64::from(voltage_v) * f64::from(current_a) * 1000.0;
        // Nonsense (NaN, infinite, beyond 10 MW) is not a power.
        if !(valid && power_mw.is_finite() && power_mw.abs() < 1e10) {
            self.last = None;
            return;
        }
        if let Some((t0, p0)) = self.last {
            let dt = at.saturating_sub(t0);
            if dt > 0 && dt <= MAX_GAP_US {
                let amount = p0.unsigned_abs().saturating_mul(dt);
                let (total, rest) = if p0 >= 0 {
                    (&mut self.charged_mwh, &mut self.charged_rest)
                } else {
                    (&mut self.discharged_mwh, &mut self.discharged_rest)
                };
                let sum = rest.saturating_add(amount);
                *total = total.saturating_add(sum / MW_US_PER_MWH);
                *rest = sum % MW_US_PER_MWH;
            }
        }
        self.last = Some((at, power_mw as i64));
    }
}
