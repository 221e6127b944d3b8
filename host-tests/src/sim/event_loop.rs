//! The simulated BMS's time: what happens at each instant (the clock, the pack, the replies that fall due).

use super::*;

impl SimBms {
    pub(super) fn sleep_at(&self) -> Option<u64> {
        if self.asleep || self.boot_until.is_some() {
            return None;
        }
        self.config
            .sleep_after_us
            .map(|d| self.last_traffic.saturating_add(d))
    }

    pub(super) fn next_internal(&self) -> Option<(u64, Ev)> {
        let candidates = [
            (self.boot_until, Ev::BootDone),
            (self.pending_reboot, Ev::Reboot),
            (self.input.front().map(|&(t, _)| t), Ev::Input),
            (self.sleep_at(), Ev::Sleep),
            (self.config.live.then_some(self.next_step), Ev::Live),
            (self.next_broadcast, Ev::Broadcast),
        ];
        candidates
            .iter()
            .filter_map(|&(t, e)| t.map(|t| (t, e)))
            .min()
    }

    pub(super) fn handle(&mut self, ev: Ev, t: u64) {
        match ev {
            Ev::BootDone => self.finish_boot(t),
            Ev::Reboot => self.begin_reboot(t),
            Ev::Input => {
                if let Some((_, b)) = self.input.pop_front() {
                    self.on_byte(t, b);
                }
            }
            Ev::Sleep => {
                self.asleep = true;
                self.stats.sleeps += 1;
                self.rx.clear();
            }
            Ev::Live => self.live_step(),
            Ev::Broadcast => self.broadcast(t),
        }
    }

    pub(super) fn silent_at(&self, t: u64) -> bool {
        matches!(self.silent, Some((from, until)) if from <= t && t < until)
    }

    pub(super) fn live_step(&mut self) {
        self.next_step = self.next_step.saturating_add(live::STEP_US);
        let params = Params::from_registers(&self.regs, self.fault.is_some());
        let mut events = Vec::new();
        self.live.step(&params, &mut events);
        self.live.publish(&mut self.regs, &params);
        for &(a, v) in &self.pinned {
            if let Some(r) = self.regs.get_mut(usize::from(a)) {
                *r = v;
            }
        }
        for id in events {
            match id {
                EventId::ChargingStarted => self.set_reg(111, self.register(111).saturating_add(1)),
                EventId::ChargingDone => self.set_reg(112, self.register(112).saturating_add(1)),
                _ => {}
            }
            self.log_event(id);
        }
    }

    pub(super) fn begin_reboot(&mut self, t: u64) {
        self.pending_reboot = None;
        self.boot_until = Some(t.saturating_add(self.config.boot_time_us));
        self.stats.reboots += 1;
        self.rx.clear();
        self.swallow_next = false;
        self.asleep = false;
        self.next_broadcast = None;
        // The UART stops mid-byte: what was still to be sent is lost.
        self.out.retain(|&(ts, _)| ts <= t);
        self.out_free = self.out_free.min(t);
        let r = self.register(REG_RESET_WAKE);
        self.set_reg(REG_RESET_WAKE, (r & 0xFF00) | RESET_SOFTWARE);
    }

    pub(super) fn finish_boot(&mut self, t: u64) {
        self.boot_until = None;
        self.last_traffic = t;
        self.log_event(EventId::SystemStarted);
        self.reconfigure_broadcast(t);
    }

    pub(super) fn reconfigure_broadcast(&mut self, t: u64) {
        self.next_broadcast = if self.boot_until.is_some() {
            None
        } else {
            ascii::active_interval(&self.regs).map(|iv| t.saturating_add(iv))
        };
    }

    pub(super) fn can_transmit(&self, t: u64) -> bool {
        !self.asleep && self.boot_until.is_none() && !self.silent_at(t)
    }

    pub(super) fn broadcast(&mut self, t: u64) {
        let Some(iv) = ascii::active_interval(&self.regs) else {
            self.next_broadcast = None;
            return;
        };
        self.next_broadcast = Some(t.saturating_add(iv));
        if self.can_transmit(t) {
            let line = ascii::line(&self.regs);
            let start = t.max(self.out_free);
            self.transmit(start, &line);
            self.stats.broadcasts += 1;
        }
    }
}
