//! What the inverter is told: the one decision, made once per period for
//! every dialect, from the limits computed (charge control's, or the hold's),
//! what must stop and why, and which signals say a stop ([`Signals`]). Each
//! dialect only puts the [`Say`] into its own frames.
//!
//! A stop is said with every signal the dialect's inverters are known to
//! obey, fresh or stale:
//!
//! * the limit of the stopping side at 0, always;
//! * the enable bit clear, where the dialect has one, always;
//! * the charge voltage at most the pack's last voltage less
//!   [`BELOW_PACK_DV`] for a charge stop, where the inverters regulate on it
//!   ([`Signals::voltage`]) — and, while the data is stale, never above the
//!   pack's last voltage whatever the dialect (a gap never resumes a charge);
//! * the SOC at 100 % (charge) or 0 % (discharge) where they obey the SOC
//!   ([`Signals::soc`]; both stop: see [`Stops::soc_pct`]);
//! * the protection bits of the stop's cause ([`Signals::alarms`]) when the
//!   inverter was seen ignoring a stop, or a stop is decided blind.

use super::control::{Conditions, Limits, PackState};
use super::dialect::{Dialect, Protected, Say, StopWhy, Stops};

/// While charging must stop, the charge voltage told is this far below the
/// pack's last voltage, 0.1 V (an inverter's constant-voltage stage then has
/// nothing left to charge at once, not after its regulator has wound down).
pub const BELOW_PACK_DV: u16 = 5;

/// Which signals say a stop, beyond the limits and the enable bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Signals {
    /// The SOC told 100 % / 0 %.
    pub soc: bool,
    /// The charge voltage lowered below the pack's.
    pub voltage: bool,
    /// The protection bits of the stop's cause.
    pub alarms: bool,
}

impl Signals {
    /// Every signal the dialect has: for an inverter seen ignoring a stop, and
    /// for a stop decided blind.
    pub const ALL: Self = Self {
        soc: true,
        voltage: true,
        alarms: true,
    };

    /// What an ordinary stop says in `d`: the SOC (with `stop_by_soc`) and
    /// the charge voltage where its inverters are known to ignore a limit of
    /// 0 A; nothing more for a GX or a Sunny Island, which obey the limits
    /// (and for which a charge voltage far below the pack's makes the system
    /// discharge the battery).
    pub fn ordinary(d: &Dialect, stop_by_soc: bool) -> Self {
        Self {
            soc: d.ignores_zero && stop_by_soc,
            voltage: d.ignores_zero,
            alarms: false,
        }
    }
}

/// What goes into one decision.
#[derive(Debug, Clone, Copy)]
pub struct Inputs<'a> {
    /// The limits computed (charge control's, or the hold's).
    pub limits: Limits,
    /// The pack as last known (of now when `fresh`).
    pub state: &'a PackState,
    /// Its alarms and warnings.
    pub conditions: &'a Conditions,
    /// What must stop, and why.
    pub stops: Stops,
    /// The data is current.
    pub fresh: bool,
    /// The signals a stop goes out with.
    pub signals: Signals,
    /// What the BMS itself tripped on.
    pub bms_protected: Protected,
    /// The lowest charge voltage ever told: cells × the under-voltage
    /// cutoff (316), 0.1 V.
    pub floor_dv: u16,
    /// 0x35E's name.
    pub name: [u8; 8],
    /// The full-charge request (the Pylontech family's 0x35C bit 3).
    pub full_charge: bool,
}

/// The pack's temperature is below its charge cutoff (a charge would harm
/// at once): a warning of the low temperature, or of a charge while cold.
pub fn cold(c: &Conditions) -> bool {
    c.low_temperature >= 1 || c.low_temperature_charge >= 2
}

/// When both sides must stop and an inverter obeys nothing but the SOC,
/// which stop the SOC says: the charge's (100 %) when a charge would harm at
/// once — a cell at its ceiling, a temperature outside the charge window —
/// and the discharge stop is not for a harm of its own the data showed or
/// kept (only the same temperature, the BMS's data lost, or the inverter's
/// request); otherwise the discharge's (0 %): the SOC is the one signal such
/// inverters obey for a discharge, while a charge is also stopped by its
/// limit, its enable bit and the charge voltage below the pack's.
pub fn charge_first(stops: Stops) -> bool {
    let charge_harms = matches!(stops.charge, Some(StopWhy::CellHigh | StopWhy::Temperature));
    let discharge_blind = matches!(
        stops.discharge,
        Some(StopWhy::Temperature | StopWhy::LinkLost | StopWhy::InverterAsked)
    );
    charge_harms && discharge_blind
}

/// The decision. See the module documentation.
pub fn decide(i: &Inputs<'_>) -> Say {
    let stops = i.stops;
    let mut l = i.limits;
    if stops.charge.is_some() {
        l.ccl_da = 0;
    }
    if stops.discharge.is_some() {
        l.dcl_da = 0;
    }
    let pack_dv = (i.state.pack_v * 10.0).clamp(0.0, f32::from(u16::MAX)) as u16;
    if !i.fresh && pack_dv > 0 {
        l.cvl_dv = l.cvl_dv.min(pack_dv);
    }
    if stops.charge.is_some() && i.signals.voltage && pack_dv > BELOW_PACK_DV {
        l.cvl_dv = l.cvl_dv.min(pack_dv - BELOW_PACK_DV);
    }
    l.cvl_dv = l.cvl_dv.max(i.floor_dv).max(1);
    let cold = cold(i.conditions);
    let charge_first = charge_first(stops);
    let soc_pct = if i.signals.soc {
        stops.soc_pct(i.state.soc_pct, charge_first)
    } else {
        i.state.soc_pct
    };
    let mut protected = i.bms_protected;
    if i.signals.alarms {
        if let Some(w) = stops.charge {
            protected = protected.or(Protected::of_stop(w, true, cold));
        }
        if let Some(w) = stops.discharge {
            protected = protected.or(Protected::of_stop(w, false, cold));
        }
    }
    Say {
        limits: l,
        soc_pct,
        stops,
        fresh: i.fresh,
        link_lost: !i.fresh,
        protected,
        name: i.name,
        full_charge: i.full_charge,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inverter::dialect::pylon::tests::state;
    use crate::inverter::dialect::{pylon, victron};

    fn inputs<'a>(s: &'a PackState, c: &'a Conditions, stops: Stops, sig: Signals) -> Inputs<'a> {
        Inputs {
            limits: Limits {
                cvl_dv: 568,
                ccl_da: 1000,
                dcl_da: 1500,
                discharge_dv: 416,
            },
            state: s,
            conditions: c,
            stops,
            fresh: true,
            signals: sig,
            bms_protected: Protected::default(),
            floor_dv: 400,
            name: pylon::DEFAULT_NAME,
            full_charge: false,
        }
    }

    const CHARGE: Stops = Stops {
        charge: Some(StopWhy::Temperature),
        discharge: None,
    };

    /// A charge stop behind a Deye-like dialect: CCL 0, CVL 0.5 V below the
    /// pack, SOC 100 % with stop_by_soc; behind a GX: CCL 0 alone.
    #[test]
    fn a_charge_stop_is_said_as_the_dialect_s_inverters_obey() {
        let (s, c) = (state(), Conditions::default());
        let deye = decide(&inputs(
            &s,
            &c,
            CHARGE,
            Signals::ordinary(&pylon::PYLON, true),
        ));
        assert_eq!((deye.limits.ccl_da, deye.limits.cvl_dv), (0, 527));
        assert_eq!(deye.soc_pct, 100.0);
        assert!(!deye.protected.any());
        let gx = decide(&inputs(
            &s,
            &c,
            CHARGE,
            Signals::ordinary(&victron::DIALECT, true),
        ));
        assert_eq!((gx.limits.ccl_da, gx.limits.cvl_dv), (0, 568));
        assert_eq!(gx.soc_pct, 65.4);
        // Every signal: the GX too, with the protection of the cause.
        let all = decide(&inputs(&s, &c, CHARGE, Signals::ALL));
        assert_eq!((all.limits.cvl_dv, all.soc_pct), (527, 100.0));
        assert!(all.protected.over_temperature);
    }

    /// Without fresh data the charge voltage is never above the pack's last,
    /// nor below the cells' under-voltage sum.
    #[test]
    fn a_gap_never_raises_the_charge_voltage() {
        let (s, c) = (state(), Conditions::default());
        let mut i = inputs(&s, &c, Stops::default(), Signals::default());
        i.fresh = false;
        let say = decide(&i);
        assert_eq!(say.limits.cvl_dv, 532);
        assert!(say.link_lost && !say.fresh);
        let low = PackState {
            pack_v: 30.0,
            ..state()
        };
        let i = Inputs { state: &low, ..i };
        assert_eq!(decide(&i).limits.cvl_dv, 400);
    }

    /// Both stop: SOC 0 % unless the charge stop harms at once (a cell at
    /// its ceiling, a temperature outside the charge window) and the
    /// discharge stop was decided blind or for the same temperature.
    #[test]
    fn both_stopped_the_soc_says_the_nearer_harm() {
        let s = state();
        let warm = Conditions::default();
        let cold = Conditions {
            low_temperature: 1,
            ..Conditions::default()
        };
        let both = Stops {
            charge: Some(StopWhy::Temperature),
            discharge: Some(StopWhy::LinkLost),
        };
        assert_eq!(
            decide(&inputs(&s, &cold, both, Signals::ALL)).soc_pct,
            100.0
        );
        // A charge held at 0 after a cut harms nothing at once: SOC 0 %.
        let held = Stops {
            charge: Some(StopWhy::Limit),
            discharge: Some(StopWhy::LinkLost),
        };
        assert_eq!(decide(&inputs(&s, &warm, held, Signals::ALL)).soc_pct, 0.0);
        // A cold pack whose discharge is held at 0 after a cut: the
        // discharge is the stop the SOC says.
        let held_cold = Stops {
            charge: Some(StopWhy::Temperature),
            discharge: Some(StopWhy::Limit),
        };
        assert_eq!(
            decide(&inputs(&s, &cold, held_cold, Signals::ALL)).soc_pct,
            0.0
        );
        // A cold pack at its discharge stop: the discharge is the stop the
        // SOC says (the charge is stopped by its voltage, bit and limit).
        let empty_and_cold = Stops {
            charge: Some(StopWhy::Temperature),
            discharge: Some(StopWhy::CellLow),
        };
        assert_eq!(
            decide(&inputs(&s, &cold, empty_and_cold, Signals::ALL)).soc_pct,
            0.0
        );
        let lost = Stops {
            charge: Some(StopWhy::LinkLost),
            discharge: Some(StopWhy::LinkLost),
        };
        let say = decide(&inputs(&s, &cold, lost, Signals::ALL));
        assert_eq!(
            (say.soc_pct, say.limits.ccl_da, say.limits.dcl_da),
            (0.0, 0, 0)
        );
        assert!(say.protected.system);
    }
}
