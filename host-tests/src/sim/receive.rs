//! Bytes from the host: framing a request, its CRC, the wake-up and what a half request costs.

use super::*;

impl SimBms {
    pub(super) fn on_byte(&mut self, t: u64, b: u8) {
        self.stats.bytes_received += 1;
        if self.silent_at(t) || self.boot_until.is_some() {
            self.stats.bytes_ignored += 1;
            return;
        }
        self.last_traffic = t;
        if self.asleep {
            self.asleep = false;
            self.stats.wakeups += 1;
            let r = self.register(REG_RESET_WAKE);
            self.set_reg(REG_RESET_WAKE, (r & 0x00FF) | (WAKE_UART << 8));
            self.swallow_next = true;
            self.rx.clear();
        }
        if !self.rx.is_empty() && t.saturating_sub(self.rx_last) > self.config.idle_gap_us {
            self.stats.partial_requests_dropped += 1;
            self.rx.clear();
        }
        self.rx_last = t;
        self.rx.push(b);
        self.scan(t);
    }

    /// Frames the receive buffer: resynchronises on the preamble one byte at a
    /// time, hands complete frames on.
    pub(super) fn scan(&mut self, t: u64) {
        loop {
            let Some(&first) = self.rx.first() else {
                return;
            };
            if first != PREAMBLE {
                self.rx.remove(0);
                self.stats.garbage_bytes += 1;
                continue;
            }
            match Request::frame_len(&self.rx) {
                Ok(None) => return,
                Ok(Some(n)) => {
                    if self.rx.len() < n {
                        return;
                    }
                    let frame: Vec<u8> = self.rx.drain(..n).collect();
                    let command = frame.get(1).copied().unwrap_or(0);
                    let parsed = Request::parse(&frame).map_err(|e| match e {
                        RequestError::Crc { .. } => NackCode::CrcError,
                        _ => NackCode::CommandError,
                    });
                    self.on_request(t, command, parsed);
                }
                Err(RequestError::UnknownCommand(c)) => {
                    self.rx.drain(..2.min(self.rx.len()));
                    self.on_request(t, c, Err(NackCode::CommandError));
                }
                Err(_) => {
                    self.rx.remove(0);
                    self.stats.garbage_bytes += 1;
                }
            }
        }
    }

    pub(super) fn on_request(&mut self, t: u64, command: u8, parsed: Result<Request, NackCode>) {
        self.stats.requests += 1;
        *self.stats.requests_by_command.entry(command).or_insert(0) += 1;
        if self.swallow_next {
            self.swallow_next = false;
            self.stats.wake_requests += 1;
            return;
        }
        if t < self.busy_until {
            self.stats.busy_ignored += 1;
            return;
        }
        if self.ignored_commands.contains(&command) {
            return;
        }
        if let Some(n) = self.drop_next.get_mut(&command) {
            if *n > 0 {
                *n -= 1;
                return;
            }
        }
        if self.rng_faults.chance(self.config.faults.no_reply) {
            self.stats.faults.no_reply += 1;
            return;
        }
        match parsed {
            Err(code) => {
                self.send_frame(t, &Frame::Nack { command, code });
            }
            Ok(req) => self.execute(t, &req),
        }
    }
}
