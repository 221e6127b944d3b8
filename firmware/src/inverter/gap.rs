//! The inverter output of a bridge alone while its BMS's data is stale: the
//! hold the pack can afford ([`super::hold`]), then the stop said blind, once
//! or every period as the dialect's inverter needs ([`super::dialect::OnSilence`]).

use super::control::{Limits, PackSettings, PackState};
use super::dialect::{self, OnSilence, StopWhy, Stops};
use super::hold::HoldBudget;
use super::say::Signals;
use super::{Inverter, InverterReport, Made, StaleMode};
use crate::Instant;

impl Inverter {
    /// A bridge alone whose newest data is `age` old, stale: the hold the
    /// pack can afford, then the stop said blind (see the module
    /// documentation).
    pub(super) fn fill_stale(
        &mut self,
        now: Instant,
        age: Instant,
        settings: &PackSettings,
        state: &PackState,
    ) {
        let since = self.stale.stale_at(now);
        let hold_us = match self.config.stale_policy {
            StaleMode::Hold => self.config.stale_hold_us,
            StaleMode::Stop => 0,
        };
        let last = self.limits.unwrap_or(Limits {
            cvl_dv: 0,
            ccl_da: 0,
            dcl_da: 0,
            discharge_dv: 0,
        });
        let charge = self.config.charge;
        let budget = self
            .stale
            .budget(|| HoldBudget::new(state, settings, &charge, last.dcl_da, hold_us));
        if since == now {
            self.report_stale(age, Some(budget));
        }
        let elapsed = now.saturating_sub(since);
        let conditions = self.conditions;
        let made = Made {
            state,
            conditions: &conditions,
            capacity_ah: settings.capacity_cah / 100,
            modules: (1, 1, u16::from(budget.spent(elapsed)), 0),
            slow: false,
        };
        let charge_why = self.fresh_stops.charge.unwrap_or(StopWhy::LinkLost);
        if !budget.spent(elapsed) {
            let limits = Limits {
                ccl_da: 0,
                dcl_da: budget.dcl_at(elapsed),
                ..last
            };
            let stops = Stops {
                charge: Some(charge_why),
                discharge: None,
            };
            let signals = self.signals();
            self.tell(now, limits, stops, signals, false, false, &made);
            return;
        }
        let on_silence = self.config.protocol.on_silence();
        if self.stale.hold_ends() {
            self.reports
                .push(InverterReport::StaleHoldEnded(on_silence));
        }
        if on_silence == OnSilence::Stops && self.stale.stop_period() >= dialect::STOP_BEFORE_QUIET
        {
            return; // the stop was said: the inverter stops on silence
        }
        let stops = Stops {
            charge: Some(charge_why),
            discharge: Some(self.fresh_stops.discharge.unwrap_or(StopWhy::LinkLost)),
        };
        self.tell(now, last, stops, Signals::ALL, false, false, &made);
    }

    /// Stale telemetry, `age` old: what the configured policy does about it,
    /// with the hold the pack can afford (a bridge alone).
    pub(super) fn report_stale(&mut self, age: Instant, hold: Option<HoldBudget>) {
        self.reports.push(InverterReport::Stale {
            age_ms: (age / crate::MS).min(u64::from(u32::MAX)) as u32,
            policy: self.config.stale_policy,
            hold,
        });
    }
}
