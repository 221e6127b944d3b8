//! Each command's answer, and the writes with their side effects.

use super::*;

impl SimBms {
    pub(super) fn execute(&mut self, t: u64, req: &Request) {
        let command = req.command();
        let nack = Frame::Nack {
            command,
            code: NackCode::CommandError,
        };
        let ack = Frame::Ack { command };
        let response = match req {
            Request::ResetClear(ResetOption::ClearEvents) => {
                self.clear_events();
                self.send_frame(t, &ack);
                return;
            }
            Request::ResetClear(ResetOption::ClearStatistics) => {
                self.clear_statistics();
                self.send_frame(t, &ack);
                return;
            }
            Request::ResetClear(ResetOption::ResetBms) => {
                // HARDWARE-NOTES: the ACK never comes.
                let latency = self.draw_latency();
                self.pending_reboot = Some(t.saturating_add(latency));
                return;
            }
            Request::ReadRegisters { start, count }
            | Request::ReadRegistersNative { start, count } => self
                .block(*start, usize::from(*count))
                .map(Response::Registers),
            Request::ReadIndividual(addresses) => self.individual(addresses),
            Request::WriteRegistersNative { start, values } => {
                let writes = consecutive(*start, values);
                return self.write(t, &writes, ack, nack);
            }
            Request::WriteIndividual(pairs) => {
                return self.write(t, pairs, ack, nack);
            }
            Request::WriteRegisters { start, values } => {
                let writes = consecutive(*start, values);
                let echo = Response::WriteEcho {
                    start: *start,
                    count: values.len() as u8,
                }
                .to_frame(req);
                match echo {
                    Ok(echo) => return self.write(t, &writes, echo, nack),
                    Err(_) => None,
                }
            }
            Request::ReadNewestEvents => Some(Response::Events(self.event_list(true))),
            Request::ReadAllEvents => Some(Response::Events(self.event_list(false))),
            Request::ReadPackVoltage => Some(Response::PackVoltage(self.f32_at(36))),
            Request::ReadPackCurrent => Some(Response::PackCurrent(self.f32_at(38))),
            Request::ReadMaxCellVoltage => Some(Response::MaxCellVoltage(self.register(41))),
            Request::ReadMinCellVoltage => Some(Response::MinCellVoltage(self.register(40))),
            Request::ReadOnlineStatus => Some(Response::OnlineStatus(OnlineStatus::from_raw(
                self.register(50),
            ))),
            Request::ReadLifetime => Some(Response::Lifetime(self.u32_at(32))),
            Request::ReadSoc => Some(Response::Soc(self.u32_at(46))),
            Request::ReadTemperatures => Some(Response::Temperatures(Temperatures {
                internal_dc: self.register(48) as i16,
                external1_dc: sensor(self.register(42) as i16),
                external2_dc: sensor(self.register(43) as i16),
            })),
            Request::ReadCellVoltages => Some(Response::CellVoltages(self.cells())),
            Request::ReadSettings { option, count } => {
                let table = self.settings_values(*option);
                let mut values = Words::new();
                let mut ok = true;
                for &v in table.iter().take(usize::from(*count)) {
                    ok &= values.push(v).is_ok();
                }
                ok.then_some(Response::Settings {
                    option: *option,
                    values: RegisterBlock {
                        start: cmd::SETTINGS_FIRST_REGISTER,
                        values,
                    },
                })
            }
            Request::ReadVersion => Some(Response::Version(self.version())),
            Request::ReadExtendedVersion => {
                let [bootloader, register_map] = self.register(503).to_le_bytes();
                Some(Response::ExtendedVersion(ExtendedVersion {
                    version: self.version(),
                    bootloader,
                    register_map,
                }))
            }
            Request::ReadSpeedDistanceTime => Some(Response::SpeedDistanceTime {
                speed_kmh: self.f32_at(54),
                distance_left_km: u32::from(self.register(44)),
                time_left_s: self.u32_at(34),
            }),
        };
        if let (Some(window), Some(r)) = (self.record_reads, &response) {
            self.record_true_reads(t, window, r);
        }
        if let (Some(pair), Some(Response::Individual(pairs))) = (self.forged_pair, &response) {
            self.forge_pair(req, pair, pairs);
        }
        let frame = match response.map(|r| r.to_frame(req)) {
            Some(Ok(f)) => f,
            Some(Err(_)) => {
                self.stats.encode_errors += 1;
                return;
            }
            None => nack,
        };
        self.send_frame(t, &frame);
    }

    /// 0x09: each address asked with its value (`None`: one is no register).
    pub(super) fn individual(&self, addresses: &[u16]) -> Option<Response> {
        let mut pairs = heapless::Vec::new();
        let mut ok = true;
        for &a in addresses {
            match self.regs.get(usize::from(a)) {
                Some(&v) if pairs.push((a, v)).is_ok() => {}
                _ => ok = false,
            }
        }
        ok.then_some(Response::Individual(pairs))
    }

    /// What the bridge read (`r`, at `t`) as the ground truth keeps it for
    /// `window` µs: each block, and each run of consecutive addresses of a
    /// 0x09 reply as one block.
    pub(super) fn record_true_reads(&mut self, t: u64, window: u64, r: &Response) {
        let mut reads: Vec<(Option<SettingsOption>, RegisterBlock)> = Vec::new();
        match r {
            Response::Registers(b) => reads.push((None, b.clone())),
            Response::Settings { option, values } => reads.push((Some(*option), values.clone())),
            // 0x09: each run of consecutive addresses is one block.
            Response::Individual(pairs) => {
                for &(a, v) in pairs {
                    match reads.last_mut() {
                        Some((None, b))
                            if usize::from(b.start) + b.values.len() == usize::from(a) =>
                        {
                            let _ = b.values.push(v);
                        }
                        _ => {
                            let mut values = Words::new();
                            let _ = values.push(v);
                            reads.push((None, RegisterBlock { start: a, values }));
                        }
                    }
                }
            }
            _ => {}
        }
        for (option, block) in reads {
            self.recent_reads.push_back(TrueRead {
                at_us: t,
                option,
                block,
            });
        }
        while self
            .recent_reads
            .front()
            .is_some_and(|r| r.at_us.saturating_add(window) < t)
        {
            self.recent_reads.pop_front();
        }
    }

    /// The one forged pair asked for (`pair`: address, value) put into the
    /// answer to `req` instead of the truth, once.
    pub(super) fn forge_pair(
        &mut self,
        req: &Request,
        (addr, value): (u16, u16),
        pairs: &heapless::Vec<(u16, u16), { cmd::MAX_READ_INDIVIDUAL }>,
    ) {
        if pairs.iter().any(|p| p.0 == addr) {
            self.forged_pair = None;
            let mut forged = pairs.clone();
            for p in forged.iter_mut().filter(|p| p.0 == addr) {
                p.1 = value;
            }
            if let Ok(f) = Response::Individual(forged).to_frame(req) {
                let mut bytes = vec![0u8; f.encoded_len().unwrap_or(0)];
                if let Ok(n) = f.encode(&mut bytes) {
                    bytes.truncate(n);
                    self.forged = Some(bytes);
                }
            }
        }
    }

    /// Applies a write request all-or-nothing, answers `ok` or `refused`, and
    /// runs the side effects (323/328 markers, broadcast settings, 340 reboot).
    pub(super) fn write(&mut self, t: u64, writes: &[(u16, u16)], ok: Frame, refused: Frame) {
        let sensor = self.config.current_sensor;
        let mut candidate = self.regs;
        for &(a, v) in writes {
            match candidate.get_mut(usize::from(a)) {
                Some(r) if cmd::WRITABLE.contains(&a) => *r = v,
                _ => {
                    self.send_frame(t, &refused);
                    return;
                }
            }
        }
        let refused_value = |a: u16, v: u16| match self.limit(a) {
            Some((lo, hi)) => !(lo..=hi).contains(&v),
            None => settings::check(a, &candidate, sensor).is_err(),
        };
        if writes.iter().any(|&(a, v)| refused_value(a, v)) {
            self.send_frame(t, &refused);
            return;
        }
        let mut reboot = false;
        let mut broadcast = false;
        for &(a, v) in writes {
            match a {
                323 => {
                    if v != ACCEPTED_MARKER {
                        self.set_reg(45, v);
                    }
                    self.set_reg(323, ACCEPTED_MARKER);
                }
                328 => {
                    if v != ACCEPTED_MARKER {
                        // 0.002 % -> 0.000001 %.
                        let soc = u32::from(v) * 2000;
                        self.set_reg(46, soc as u16);
                        self.set_reg(47, (soc >> 16) as u16);
                        self.live.set_soc(f64::from(v) * 0.002);
                    }
                    self.set_reg(328, ACCEPTED_MARKER);
                }
                _ if self.ignored_writes.contains(&a) => {}
                _ => self.set_reg(a, v),
            }
            reboot |= a == REG_OPERATION_MODE;
            broadcast |= a == 342 || a == 343;
        }
        if broadcast {
            self.reconfigure_broadcast(t);
        }
        self.busy_until = t.saturating_add(self.config.settle_after_write_us);
        let end = self.send_frame(t, &ok);
        if reboot {
            self.pending_reboot = Some(end.unwrap_or(t));
        }
    }

    pub(super) fn block(&self, start: u16, count: usize) -> Option<RegisterBlock> {
        let first = usize::from(start);
        let regs = self.regs.get(first..first.checked_add(count)?)?;
        if regs.is_empty() {
            return None;
        }
        let values = Words::from_slice(regs).ok()?;
        Some(RegisterBlock { start, values })
    }

    pub(super) fn cells(&self) -> heapless::Vec<u16, { protocol_core::registers::MAX_CELLS }> {
        let max = protocol_core::registers::MAX_CELLS;
        let n = usize::from(self.register(53)).min(max);
        let first = usize::from(self.model.first_cell_register()).min(max - n);
        let mut cells = heapless::Vec::new();
        for &c in self.regs.iter().skip(first).take(n) {
            if cells.push(c).is_err() {
                break; // n <= MAX_CELLS: cannot happen
            }
        }
        cells
    }

    pub(super) fn version(&self) -> Version {
        let [hardware, hardware_changes] = self.register(500).to_le_bytes();
        Version {
            hardware,
            hardware_changes,
            firmware_public: self.register(501) as u8,
            firmware_internal: self.register(502),
        }
    }

    pub(super) fn u32_at(&self, a: u16) -> u32 {
        u32::from(self.register(a)) | (u32::from(self.register(a + 1)) << 16)
    }

    pub(super) fn f32_at(&self, a: u16) -> f32 {
        f32::from_bits(self.u32_at(a))
    }

    pub(super) fn set_reg(&mut self, a: u16, v: u16) {
        if let Some(r) = self.regs.get_mut(usize::from(a)) {
            *r = v;
        }
    }

    pub(super) fn draw_latency(&mut self) -> u64 {
        let (lo, hi) = self.config.reply_latency_us;
        self.rng_latency.range_u64(lo, hi)
    }
}
