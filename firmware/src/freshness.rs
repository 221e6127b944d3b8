//! The one freshness rule: when the bridge's data counts as current.
//!
//! Data is **fresh** while the BMS link is up and synced and the newest
//! snapshot is at most [`Freshness::limit_us`] old (the configuration's
//! `stale_after`, 5 s by default: 20 live periods). Past that it is
//! **stale**: never sent or shown as current. Every consumer asks this rule
//! — the inverter output (its stale policy), the packs of a battery (a pack
//! with stale data leaves the sums), MQTT (availability and the state), the
//! host link (each `telemetry` line carries the age and this limit) and the
//! desktop tool (which shows what the line says, not a constant of its own).

use crate::Instant;

/// The stale age the configuration's `stale_after` gives by default, µs.
pub const DEFAULT_STALE_AFTER_US: Instant = 5 * crate::SECOND;

/// How current the data is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DataState {
    /// No snapshot yet.
    NoData,
    /// The BMS link is down (or not synced): the last snapshot is not current.
    Offline,
    /// Older than the limit.
    Stale,
    /// Current.
    Fresh,
}

impl DataState {
    /// As the host link and the desktop tool write it.
    pub const fn name(self) -> &'static str {
        match self {
            Self::NoData => "no_data",
            Self::Offline => "offline",
            Self::Stale => "stale",
            Self::Fresh => "fresh",
        }
    }
}

/// What the inverter output does while the data is stale: the one type of
/// the choice (the record's `stale_policy` field and the output's setting).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StaleMode {
    /// Stop sending at once: the inverter sees the battery as lost and stops.
    Stop,
    /// Send CCL 0 (discharge allowed) for at most the hold time, then stop.
    Hold,
}

/// The rule with its limit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Freshness {
    /// Data older than this is stale, µs.
    pub limit_us: Instant,
}

impl Default for Freshness {
    fn default() -> Self {
        Self::new(DEFAULT_STALE_AFTER_US)
    }
}

impl Freshness {
    /// The rule with `limit_us`.
    pub const fn new(limit_us: Instant) -> Self {
        Self { limit_us }
    }

    /// Data of this age (`None`: none, or too old to say) counts as current.
    pub fn young(&self, age_us: Option<Instant>) -> bool {
        age_us.is_some_and(|a| a <= self.limit_us)
    }

    /// Data of this age, with the BMS link up and synced (`online`) or not.
    pub fn state(&self, online: bool, age_us: Option<Instant>) -> DataState {
        match age_us {
            None => DataState::NoData,
            Some(_) if !online => DataState::Offline,
            a if self.young(a) => DataState::Fresh,
            _ => DataState::Stale,
        }
    }

    /// Data of this age with the link as given may be used as current.
    pub fn fresh(&self, online: bool, age_us: Option<Instant>) -> bool {
        self.state(online, age_us) == DataState::Fresh
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_limit_is_inclusive_and_offline_wins() {
        let f = Freshness::new(5 * crate::SECOND);
        assert_eq!(f.state(true, None), DataState::NoData);
        assert_eq!(f.state(true, Some(5 * crate::SECOND)), DataState::Fresh);
        assert_eq!(f.state(true, Some(5 * crate::SECOND + 1)), DataState::Stale);
        assert_eq!(f.state(false, Some(0)), DataState::Offline);
        assert!(!f.fresh(false, Some(0)));
    }
}
