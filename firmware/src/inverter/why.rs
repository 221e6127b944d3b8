//! Why each limit is what it is: for CVL, CCL and DCL the rule that set the
//! value the inverter is told, with its numbers. Charge control names the rule
//! of each limit it computes ([`super::control::ChargeControl::reasons`]); the
//! output then names what it changed on the way out — a stop, the data gap,
//! the battery of several packs. The log, the host link, `tinybms monitor`
//! and Home Assistant say it in the words of [`Why::write`].

use super::dialect::StopWhy;
use crate::log_line::Line;

/// The rule that set one limit, with its numbers (each variant's text says
/// what its fields are).
#[allow(missing_docs)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Why {
    /// Nothing computed yet.
    Unknown,
    /// CVL: the absorption target, mV a cell × cells.
    Absorption { cell_mv: u16, cells: u8 },
    /// CVL: held at absorption while cells balance (the balance hold).
    BalanceHold { spread_mv: u16 },
    /// CVL: the float target, mV a cell × cells.
    Float { cell_mv: u16, cells: u8 },
    /// CVL: stepping down into float, to `float_dv` (0.1 V).
    StepDown { float_dv: u16 },
    /// CVL: lowered by `offset_mv` (pack) for the highest cell at `cell_mv`,
    /// running ahead of the others.
    Runner { cell_mv: u16, offset_mv: u32 },
    /// CVL: at the cells' over-voltage cutoff (315) × cells.
    CutoffCeiling { cutoff_mv: u16 },
    /// CVL: at the cells' under-voltage cutoff (316) × cells.
    CutoffFloor { cutoff_mv: u16 },
    /// CVL: a rise waits (raised at most once per `cvl_raise_interval`).
    RaiseWait,
    /// CCL/DCL: the BMS's own cutoff (318/317) less the current margin.
    Cutoff { cutoff_a: u16, margin_pct: u8 },
    /// CCL/DCL: the owner's cap in the configuration, 0.1 A.
    OwnerCap { cap_da: u16 },
    /// CCL: tapered by the highest cell at `cell_mv`, 0 at `stop_mv`.
    CellHigh { cell_mv: u16, stop_mv: u16 },
    /// DCL: tapered by the lowest cell at `cell_mv`, 0 at `stop_mv`.
    CellLow { cell_mv: u16, stop_mv: u16 },
    /// CCL: tapered by the coldest sensor (0.1 °C), 0 at the cutoff (°C).
    Cold { temp_dc: i16, cutoff_c: i16 },
    /// CCL/DCL: tapered by the hottest sensor (0.1 °C), 0 at the cutoff (°C).
    Hot { temp_dc: i16, cutoff_c: i16 },
    /// CCL/DCL: 0 on a BMS fault.
    BmsFault,
    /// CCL: 0 while a charge-side cutoff event of the BMS is latched.
    ChargeBlocked,
    /// CCL: 0 at the SOC ceiling (`soc_ceiling`), %.
    SocCeiling { pct: u8 },
    /// CCL/DCL: 0 after a current past the BMS's cutoff (A).
    OverCurrent { cutoff_a: u16 },
    /// CCL/DCL: ramping back after a cut, towards `target_da` (0.1 A).
    Ramp { target_da: u16 },
    /// A stop said for this reason.
    Stop(StopWhy),
    /// CVL: no higher than the pack's last voltage while the BMS's data is
    /// stale; DCL: what the hold's budget allows.
    DataGap,
    /// The battery of several packs: this limit is the battery's.
    Battery { packs: u8 },
}

impl Why {
    /// A short key (the host link's and Home Assistant's attribute).
    pub const fn key(self) -> &'static str {
        match self {
            Self::Unknown => "unknown",
            Self::Absorption { .. } => "absorption",
            Self::BalanceHold { .. } => "balance_hold",
            Self::Float { .. } => "float",
            Self::StepDown { .. } => "step_down",
            Self::Runner { .. } => "runner",
            Self::CutoffCeiling { .. } => "cutoff_ceiling",
            Self::CutoffFloor { .. } => "cutoff_floor",
            Self::RaiseWait => "raise_wait",
            Self::Cutoff { .. } => "bms_cutoff",
            Self::OwnerCap { .. } => "owner_cap",
            Self::CellHigh { .. } => "cell_high",
            Self::CellLow { .. } => "cell_low",
            Self::Cold { .. } => "cold",
            Self::Hot { .. } => "hot",
            Self::BmsFault => "bms_fault",
            Self::ChargeBlocked => "charge_blocked",
            Self::SocCeiling { .. } => "soc_ceiling",
            Self::OverCurrent { .. } => "over_current",
            Self::Ramp { .. } => "ramp",
            Self::Stop(_) => "stop",
            Self::DataGap => "data_gap",
            Self::Battery { .. } => "battery",
        }
    }

    /// In words, with the numbers.
    pub fn write(self, out: &mut Line) {
        match self {
            Self::Unknown => {
                out.push("not computed yet");
            }
            Self::Absorption { cell_mv, cells } => {
                out.push("absorption ");
                mv_times(out, cell_mv, cells);
            }
            Self::BalanceHold { spread_mv } => {
                out.push("absorption held while cells balance (spread ")
                    .uint(u64::from(spread_mv))
                    .push(" mV)");
            }
            Self::Float { cell_mv, cells } => {
                out.push("float ");
                mv_times(out, cell_mv, cells);
            }
            Self::StepDown { float_dv } => {
                out.push("stepping down to float ")
                    .fixed(i64::from(float_dv), 1)
                    .push(" V");
            }
            Self::Runner { cell_mv, offset_mv } => {
                out.push("highest cell ")
                    .uint(u64::from(cell_mv))
                    .push(" mV runs ahead: lowered ")
                    .fixed(i64::from(offset_mv / 100), 1)
                    .push(" V");
            }
            Self::CutoffCeiling { cutoff_mv } => {
                out.push("the BMS's over-voltage cutoff ")
                    .uint(u64::from(cutoff_mv))
                    .push(" mV a cell");
            }
            Self::CutoffFloor { cutoff_mv } => {
                out.push("the BMS's under-voltage cutoff ")
                    .uint(u64::from(cutoff_mv))
                    .push(" mV a cell");
            }
            Self::RaiseWait => {
                out.push("a rise waits (at most one a cvl_raise_interval)");
            }
            Self::Cutoff {
                cutoff_a,
                margin_pct,
            } => {
                out.push("the BMS's cutoff ")
                    .uint(u64::from(cutoff_a))
                    .push(" A less ")
                    .uint(u64::from(margin_pct))
                    .push(" %");
            }
            Self::OwnerCap { cap_da } => {
                out.push("the configured cap ")
                    .fixed(i64::from(cap_da), 1)
                    .push(" A");
            }
            Self::CellHigh { cell_mv, stop_mv } => {
                out.push("highest cell ")
                    .uint(u64::from(cell_mv))
                    .push(" mV, 0 A at ")
                    .uint(u64::from(stop_mv))
                    .push(" mV");
            }
            Self::CellLow { cell_mv, stop_mv } => {
                out.push("lowest cell ")
                    .uint(u64::from(cell_mv))
                    .push(" mV, 0 A at ")
                    .uint(u64::from(stop_mv))
                    .push(" mV");
            }
            Self::Cold { temp_dc, cutoff_c } => {
                out.push("cold: ")
                    .fixed(i64::from(temp_dc), 1)
                    .push(" °C, 0 A at ")
                    .int(i64::from(cutoff_c))
                    .push(" °C");
            }
            Self::Hot { temp_dc, cutoff_c } => {
                out.push("hot: ")
                    .fixed(i64::from(temp_dc), 1)
                    .push(" °C, 0 A at ")
                    .int(i64::from(cutoff_c))
                    .push(" °C");
            }
            Self::BmsFault => {
                out.push("the BMS reports a fault");
            }
            Self::ChargeBlocked => {
                out.push("a charge cutoff of the BMS is latched");
            }
            Self::SocCeiling { pct } => {
                out.push("the SOC ceiling ").uint(u64::from(pct)).push(" %");
            }
            Self::OverCurrent { cutoff_a } => {
                out.push("a current past the BMS's cutoff ")
                    .uint(u64::from(cutoff_a))
                    .push(" A: held, then ramping");
            }
            Self::Ramp { target_da } => {
                out.push("ramping back to ")
                    .fixed(i64::from(target_da), 1)
                    .push(" A");
            }
            Self::Stop(why) => {
                out.push("stop: ").push(why.text());
            }
            Self::DataGap => {
                out.push("the BMS's data is stale: the hold");
            }
            Self::Battery { packs } => {
                out.push("the battery of ")
                    .uint(u64::from(packs))
                    .push(" packs");
            }
        }
    }

    /// [`Why::write`] as a line of its own.
    pub fn text(self) -> Line {
        let mut out = Line::new();
        self.write(&mut out);
        out
    }
}

fn mv_times(out: &mut Line, cell_mv: u16, cells: u8) {
    out.uint(u64::from(cell_mv))
        .push(" mV × ")
        .uint(u64::from(cells));
}

/// Why CVL, CCL and DCL are what they are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Reasons {
    /// Charge voltage limit.
    pub cvl: Why,
    /// Charge current limit.
    pub ccl: Why,
    /// Discharge current limit.
    pub dcl: Why,
}

impl Default for Reasons {
    fn default() -> Self {
        Self {
            cvl: Why::Unknown,
            ccl: Why::Unknown,
            dcl: Why::Unknown,
        }
    }
}

impl Reasons {
    /// The same rules (numbers aside): a change of rule is logged, a change
    /// of a number is not.
    pub fn same_rules(&self, other: &Self) -> bool {
        self.cvl.key() == other.cvl.key()
            && self.ccl.key() == other.ccl.key()
            && self.dcl.key() == other.dcl.key()
    }

    /// The output's last word on the limits charge control computed
    /// (`computed`) and told (`told`): a limit the stops or the gap changed
    /// is theirs.
    pub fn after_say(
        mut self,
        computed: &super::control::Limits,
        told: &super::control::Limits,
        stops: super::dialect::Stops,
        fresh: bool,
    ) -> Self {
        if let Some(why) = stops.charge {
            if told.ccl_da == 0 && !matches!(why, StopWhy::Limit) {
                self.ccl = Why::Stop(why);
            }
        }
        if let Some(why) = stops.discharge {
            if told.dcl_da == 0 && !matches!(why, StopWhy::Limit) {
                self.dcl = Why::Stop(why);
            }
        }
        if told.cvl_dv < computed.cvl_dv {
            self.cvl = if fresh {
                Why::Stop(stops.charge.unwrap_or(StopWhy::Limit))
            } else {
                Why::DataGap
            };
        }
        if !fresh && told.dcl_da > 0 {
            self.dcl = Why::DataGap;
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inverter::control::Limits;
    use crate::inverter::dialect::Stops;

    fn limits(cvl_dv: u16, ccl_da: u16, dcl_da: u16) -> Limits {
        Limits {
            cvl_dv,
            ccl_da,
            dcl_da,
            discharge_dv: 480,
        }
    }

    #[test]
    fn every_reason_has_words_with_its_numbers() {
        let w = Why::CellHigh {
            cell_mv: 3521,
            stop_mv: 3600,
        };
        assert_eq!(w.text().as_str(), "highest cell 3521 mV, 0 A at 3600 mV");
        let w = Why::Cold {
            temp_dc: 23,
            cutoff_c: 0,
        };
        assert_eq!(w.text().as_str(), "cold: 2.3 °C, 0 A at 0 °C");
        assert_eq!(
            Why::Absorption {
                cell_mv: 3450,
                cells: 16
            }
            .text()
            .as_str(),
            "absorption 3450 mV × 16"
        );
    }

    #[test]
    fn a_stop_names_the_limits_it_set() {
        let r = Reasons {
            cvl: Why::Absorption {
                cell_mv: 3450,
                cells: 16,
            },
            ccl: Why::Cutoff {
                cutoff_a: 100,
                margin_pct: 10,
            },
            dcl: Why::Cutoff {
                cutoff_a: 100,
                margin_pct: 10,
            },
        };
        let stops = Stops {
            charge: Some(StopWhy::CellHigh),
            discharge: None,
        };
        let after = r.after_say(&limits(552, 900, 900), &limits(530, 0, 900), stops, true);
        assert_eq!(after.ccl, Why::Stop(StopWhy::CellHigh));
        assert_eq!(after.cvl, Why::Stop(StopWhy::CellHigh));
        assert_eq!(after.dcl, r.dcl);
        // Stale: CVL at the pack's last, DCL the hold's.
        let stale = r.after_say(&limits(552, 900, 900), &limits(530, 0, 400), stops, false);
        assert_eq!(stale.cvl, Why::DataGap);
        assert_eq!(stale.dcl, Why::DataGap);
        // Nothing changed: charge control's reasons stay.
        let same = r.after_say(
            &limits(552, 900, 900),
            &limits(552, 900, 900),
            Stops::default(),
            true,
        );
        assert_eq!(same, r);
    }
}
