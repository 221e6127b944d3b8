//! The inverter output in a closed loop, on the desk: the firmware's bridge
//! reads the simulated TinyBMS, the firmware's [`Inverter`] turns its telemetry
//! into CAN frames, and an inverter/charger model obeys those frames the way a
//! Victron system does and drives the simulated pack's current. Everything in
//! virtual time.
//!
//! The inverter model: it charges at min(CCL, charger maximum) until the pack
//! reaches CVL, then holds CVL with a tapering current (a constant-voltage
//! stage); a load discharges within DCL; without a 0x351 for 3 s it stops
//! charging and discharging (what a GX does on a lost battery).

use std::collections::BTreeMap;
use std::io::Write;

use protocol_core::views::cell_mv;

use embassy_futures::block_on;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::store::{Loaded, Source};
use tinybms_firmware::config::Config;
use tinybms_firmware::identity::{Features, Identity};
use tinybms_firmware::inverter::frames::{self, CanFrame};
use tinybms_firmware::inverter::{Inverter, InverterConfig, InverterReport};
use tinybms_firmware::station::{Logged, Setup, Station};

use crate::sim::{PackModel, SimBms, SimConfig};
use crate::virtual_time::Harness;
use tinybms_desk::flash::RamFlash;

/// How often the loop advances, µs (the inverter model's control step).
pub const STEP_US: u64 = 100_000;

/// A Victron-like inverter/charger.
#[derive(Debug, Clone)]
pub struct InverterModel {
    /// Largest charge current the charger can deliver, A.
    pub charger_max_a: f64,
    /// Discharge demand of the loads, A.
    pub load_a: f64,
    /// Pack resistance it assumes for its constant-voltage stage, Ω.
    pub r_pack: f64,
    /// Last 0x351: (CVL V, CCL A, DCL A) and when it came.
    pub last_limits: Option<(f64, f64, f64, u64)>,
    /// The current it draws now, A (positive = charging the pack).
    pub current_a: f64,
}

/// Gain of the model's constant-voltage regulator, A per volt of error per
/// second.
pub const CV_GAIN_A_PER_V_S: f64 = 40.0;

/// A GX stops charging and discharging when 0x351 is missing this long, µs.
pub const GX_LIMITS_TIMEOUT_US: u64 = 3_000_000;

impl InverterModel {
    /// A charger of `charger_max_a` with no load.
    pub fn new(charger_max_a: f64, r_pack: f64) -> Self {
        Self {
            charger_max_a,
            load_a: 0.0,
            r_pack,
            last_limits: None,
            current_a: 0.0,
        }
    }

    /// A frame the bridge sent.
    pub fn on_frame(&mut self, now: u64, f: &CanFrame) {
        if f.id == frames::ID_LIMITS && f.len >= 6 {
            let d = f.data;
            let cvl = f64::from(u16::from_le_bytes([d[0], d[1]])) * 0.1;
            let ccl = f64::from(i16::from_le_bytes([d[2], d[3]])) * 0.1;
            let dcl = f64::from(i16::from_le_bytes([d[4], d[5]])) * 0.1;
            self.last_limits = Some((cvl, ccl.max(0.0), dcl.max(0.0), now));
        }
    }

    /// The current for the next step, given the pack voltage the inverter
    /// measures (it uses its own readings, like a real one).
    pub fn step(&mut self, now: u64, pack_v: f64) -> f64 {
        let Some((cvl, ccl, dcl, at)) = self.last_limits else {
            self.current_a = 0.0;
            return 0.0;
        };
        if now.saturating_sub(at) > GX_LIMITS_TIMEOUT_US {
            self.current_a = 0.0;
            return 0.0;
        }
        let i = if self.load_a > 0.0 {
            -self.load_a.min(dcl)
        } else {
            // Constant current up to CVL, then constant voltage: an integrating
            // voltage regulator (as a charger's CV stage), bounded by CCL and the
            // charger's maximum.
            let dt_s = STEP_US as f64 / 1e6;
            let next = self.current_a.max(0.0) + CV_GAIN_A_PER_V_S * (cvl - pack_v) * dt_s;
            next.clamp(0.0, self.charger_max_a.min(ccl))
        };
        self.current_a = i;
        i
    }
}

/// Figures of one closed-loop run.
#[derive(Debug, Clone, Default)]
pub struct LoopFigures {
    /// Highest cell seen in any snapshot, mV.
    pub max_cell_mv: u16,
    /// Highest cell allowed (315 − margin), mV.
    pub max_allowed_mv: u16,
    /// Lowest CVL sent, 0.1 V.
    pub min_cvl_dv: Option<u16>,
    /// Highest CVL sent, 0.1 V.
    pub max_cvl_dv: Option<u16>,
    /// CVL changes sent.
    pub cvl_changes: u32,
    /// Time of the switch to float, µs.
    pub float_at_us: Option<u64>,
    /// Frames on the bus.
    pub frames: u64,
    /// Bits on the bus (frames with stuffing estimated at 20 %).
    pub bits: u64,
    /// 0x351 frames sent while the telemetry was stale.
    pub stale_frames: u64,
    /// Reports of the inverter output.
    pub reports: Vec<(u64, InverterReport)>,
}

impl LoopFigures {
    /// Bus load at 500 kbit/s over `duration_us`, percent.
    pub fn bus_load_percent(&self, duration_us: u64) -> f64 {
        if duration_us == 0 {
            return 0.0;
        }
        self.bits as f64 / (duration_us as f64 / 1e6 * 500_000.0) * 100.0
    }
    /// CVL changes per hour over `duration_us`.
    pub fn cvl_changes_per_hour(&self, duration_us: u64) -> f64 {
        self.cvl_changes as f64 / (duration_us as f64 / 3.6e9).max(1e-9)
    }
}

/// Bits of a classic base-format CAN frame with `len` data bytes: 47 + 8·len,
/// plus about 20 % bit stuffing.
pub fn frame_bits(len: u8) -> u64 {
    let raw = 47 + 8 * u64::from(len);
    raw + raw / 5
}

/// The station (bridge and inverter output), the simulated BMS and the
/// inverter model.
pub struct ClosedLoop {
    /// The station and simulated BMS (its CAN controller on the loop's bus).
    pub h: Harness,
    /// The inverter/charger.
    pub model: InverterModel,
    /// Figures so far.
    pub figures: LoopFigures,
    /// Every limits frame (time, CVL dV, CCL dA, DCL dA) as sent.
    pub sent_limits: Vec<(u64, u16, u16, u16)>,
    /// Every frame's (time, id) as sent.
    pub sent_ids: Vec<(u64, u16)>,
    /// A candump log being written (`--can-log`).
    pub can_log: Option<Box<dyn Write>>,
    /// A JSON Lines log being written (`--json`).
    pub json_log: Option<Box<dyn Write>>,
    /// The host side, when the loop runs with a host link and the record in
    /// flash ([`ClosedLoop::from_flash`]).
    pub host: Option<LoopHost>,
    seen_seq: u32,
    last_cvl: Option<u16>,
}

/// The host side of a [`ClosedLoop`] made by [`ClosedLoop::from_flash`].
pub struct LoopHost {
    /// The flash the record is on (shared with the store).
    pub flash: RamFlash,
    /// Every line the host link wrote, parsed.
    pub lines: Vec<serde_json::Value>,
}

/// Epoch of the candump timestamps (virtual time 0), s.
pub const CANDUMP_EPOCH_S: u64 = 1_700_000_000;

impl ClosedLoop {
    /// A loop with a simulated 16S LiFePO4 pack (or `profile`) and a charger;
    /// the inverter output runs with `inverter` (not the record's settings).
    pub fn new(
        profile: PackModel,
        seed: u64,
        inverter: InverterConfig,
        charger_max_a: f64,
    ) -> Self {
        Self::new_with(profile, seed, inverter, charger_max_a, false)
    }

    /// As [`ClosedLoop::new`], with the station's host link built in or not
    /// (its port: [`Harness::host_port`] or [`Harness::host_lines`]).
    pub fn new_with(
        profile: PackModel,
        seed: u64,
        inverter: InverterConfig,
        charger_max_a: f64,
        host_link: bool,
    ) -> Self {
        let setup = Setup {
            timing: Timing::default(),
            identity: Identity::desktop(
                "sim",
                Features {
                    can: true,
                    host_link,
                    ..Features::default()
                },
            ),
            inverter: Some(inverter),
        };
        let loaded = Loaded {
            config: Config::default(),
            source: Source::Empty,
        };
        Self::with_station(profile, seed, Station::new(setup, loaded, 0), charger_max_a)
    }

    fn with_station(profile: PackModel, seed: u64, station: Station, charger_max_a: f64) -> Self {
        let mut sim = SimBms::new(profile, SimConfig::default(), seed);
        sim.set_external_current(Some(0.0));
        let cells = profile.cell_count() as f64;
        let r_cell = match profile {
            PackModel::LiFePO4_16S => 0.0003,
            PackModel::LiIon_14S => 0.0015,
        };
        let mut h = Harness::with_station(sim, station);
        h.retain = true;
        h.can.attached = true;
        h.finish_at_end = true;
        Self {
            h,
            model: InverterModel::new(charger_max_a, (cells * r_cell).max(0.001)),
            figures: LoopFigures::default(),
            sent_limits: Vec::new(),
            sent_ids: Vec::new(),
            can_log: None,
            json_log: None,
            host: None,
            seen_seq: 0,
            last_cvl: None,
        }
    }

    /// A loop as a bridge with its configuration record in `flash` starts it:
    /// the station runs with the record (the defaults when the flash holds
    /// none), and a host link takes configuration changes
    /// ([`ClosedLoop::host_line`]) that apply at once where they may and are
    /// saved to `flash` when the BMS link is quiet.
    pub fn from_flash(profile: PackModel, seed: u64, flash: RamFlash, charger_max_a: f64) -> Self {
        let loaded = block_on(tinybms_desk::flash::store(flash.clone()).load());
        let setup = Setup {
            timing: Timing::default(),
            identity: Identity::desktop(
                "sim",
                Features {
                    can: true,
                    host_link: true,
                    ..Features::default()
                },
            ),
            inverter: None,
        };
        let station = Station::new(setup, loaded, 0);
        let mut l = Self::with_station(profile, seed, station, charger_max_a);
        l.h.saver = Some(crate::virtual_host_link::ram_saver(
            &flash,
            std::rc::Rc::new(std::cell::Cell::new(0)),
        ));
        l.h.host_lines = Some(Vec::new());
        l.host = Some(LoopHost {
            flash,
            lines: Vec::new(),
        });
        l
    }

    /// The inverter output.
    pub fn inverter(&self) -> &Inverter {
        self.h
            .station
            .inverter()
            .expect("a loop's station is built with its CAN output")
    }

    /// One line from the host (needs [`ClosedLoop::from_flash`]).
    pub fn host_line(&mut self, line: &str) {
        let mut b = line.as_bytes().to_vec();
        b.push(b'\n');
        let now = self.h.now;
        self.h.station.host_rx(now, &b);
        self.h.run_until(now);
        self.after_step(now);
    }

    /// Runs until virtual time `end_us`.
    pub fn run_until(&mut self, end_us: u64) {
        while self.h.now < end_us {
            let t = (self.h.now + STEP_US).min(end_us);
            self.h.run_until(t);
            self.after_step(t);
            let pack_v = f64::from(
                self.h
                    .bridge()
                    .telemetry()
                    .snapshot
                    .as_ref()
                    .map_or(0.0, |s| s.pack_voltage_v),
            );
            let i = self.model.step(t, pack_v);
            self.h.sim.set_external_current(Some(i));
        }
    }

    /// What the station did up to `now`: its frames onto the bus (and to the
    /// model), its reports and host lines into the figures.
    fn after_step(&mut self, now: u64) {
        self.watch_snapshots();
        for (at, f) in std::mem::take(&mut self.h.can.outbox) {
            self.on_frame(at, &f);
        }
        for (at, item) in std::mem::take(&mut self.h.other_log) {
            if let Logged::Inverter(r) = item {
                self.figures.reports.push((at, r));
            }
        }
        if let (Some(host), Some(lines)) = (self.host.as_mut(), self.h.host_lines.as_mut()) {
            for l in lines.drain(..) {
                if let Ok(v) = serde_json::from_str(&l) {
                    host.lines.push(v);
                }
            }
        }
        if self.figures.float_at_us.is_none()
            && self.inverter().phase() == tinybms_firmware::inverter::control::Phase::Float
        {
            self.figures.float_at_us = Some(now);
        }
    }

    fn watch_snapshots(&mut self) {
        let t = self.h.bridge().telemetry();
        if t.snapshot_seq == self.seen_seq {
            return;
        }
        self.seen_seq = t.snapshot_seq;
        let (Some(s), Some(at)) = (&t.snapshot, t.snapshot_at) else {
            return;
        };
        if let Some((_, raw)) = s.cells.max() {
            self.figures.max_cell_mv = self.figures.max_cell_mv.max(cell_mv(raw));
        }
        if let Some(w) = self.json_log.as_mut() {
            if let Some(b) = &t.live_registers {
                let regs: BTreeMap<u16, u16> = b.iter().collect();
                let mut v = crate::replay::register_values(&regs);
                v.insert("t_s".into(), serde_json::json!(at as f64 / 1e6));
                if let Some(l) = self.h.station.inverter().and_then(|i| i.limits()) {
                    v.insert(
                        "cvl_v".into(),
                        serde_json::json!(f64::from(l.cvl_dv) / 10.0),
                    );
                    v.insert(
                        "ccl_a".into(),
                        serde_json::json!(f64::from(l.ccl_da) / 10.0),
                    );
                    v.insert(
                        "dcl_a".into(),
                        serde_json::json!(f64::from(l.dcl_da) / 10.0),
                    );
                }
                let _ = writeln!(w, "{}", serde_json::Value::Object(v));
            }
        }
    }

    fn on_frame(&mut self, now: u64, f: &CanFrame) {
        self.figures.frames += 1;
        self.figures.bits += frame_bits(f.len);
        self.sent_ids.push((now, f.id));
        self.model.on_frame(now, f);
        if let Some(l) = frames::limits_of(f) {
            let (cvl, ccl, dcl) = (l.cvl_dv, l.ccl_da, l.dcl_da);
            self.sent_limits.push((now, cvl, ccl, dcl));
            self.figures.min_cvl_dv = Some(self.figures.min_cvl_dv.map_or(cvl, |m| m.min(cvl)));
            self.figures.max_cvl_dv = Some(self.figures.max_cvl_dv.map_or(cvl, |m| m.max(cvl)));
            if self.last_cvl.is_some_and(|c| c != cvl) {
                self.figures.cvl_changes += 1;
            }
            self.last_cvl = Some(cvl);
            let stale = self
                .h
                .bridge()
                .telemetry()
                .snapshot_age_us(now)
                .is_none_or(|a| a > 5_000_000);
            if stale {
                self.figures.stale_frames += 1;
            }
        }
        if let Some(w) = self.can_log.as_mut() {
            let _ = writeln!(w, "{}", candump_line(now, f));
        }
    }

    /// The ids of the frames sent from `since_us` on.
    pub fn ids_since(&self, since_us: u64) -> std::collections::BTreeSet<u16> {
        self.sent_ids
            .iter()
            .filter(|(t, _)| *t >= since_us)
            .map(|(_, id)| *id)
            .collect()
    }

    /// The CAN controller goes bus-off now for `duration_us`: the station is
    /// told, and a recovery before the end fails.
    pub fn bus_off(&mut self, duration_us: u64) {
        let now = self.h.now;
        self.h.station.can_bus_off(now);
        self.h.can.bus_off_until = Some(now + duration_us);
    }
}

/// One line of a candump log file (`candump -l` format), readable by can-utils'
/// `canplayer`/`log2asc`, python-can and cantools.
pub fn candump_line(now_us: u64, f: &CanFrame) -> String {
    let secs = CANDUMP_EPOCH_S + now_us / 1_000_000;
    let micros = now_us % 1_000_000;
    let data: String = f.bytes().iter().map(|b| format!("{b:02X}")).collect();
    format!("({secs}.{micros:06}) can0 {:03X}#{data}", f.id)
}

/// The head of `sim --scenario`'s table (docs/simulator.md shows it).
pub const SCENARIO_HEADER: &str =
    "scenario       max cell  ceiling   min CVL   max CVL   CVL ch/h time to full  bus load     ok";

/// One row of `sim --scenario`'s table for the loop `l` run until `end`, µs,
/// and whether it kept its promises: the highest cell at most the ceiling
/// (over-voltage cutoff less the margin), every CVL sent above the cells'
/// under-voltage cutoff sum and at most their over-voltage cutoff sum.
pub fn scenario_row(
    name: &str,
    l: &ClosedLoop,
    end: u64,
    config: InverterConfig,
) -> (String, bool) {
    use protocol_core::settings::SettingId::{
        NumberOfSeriesCells, OverVoltageCutoff, UnderVoltageCutoff,
    };
    let ceiling =
        l.h.bridge()
            .telemetry()
            .settings
            .as_ref()
            .and_then(|b| b.get(OverVoltageCutoff.address()))
            .map_or(0, |ov| ov.saturating_sub(config.charge.ceiling_margin_mv));
    let cells = l.h.sim.register(NumberOfSeriesCells.address()).max(1);
    let f = &l.figures;
    let cvl_ok = l.sent_limits.iter().all(|&(_, cvl, _, _)| {
        let mv = u32::from(cvl) * 100;
        cvl > 0
            && mv + 100
                > u32::from(cells) * u32::from(l.h.sim.register(UnderVoltageCutoff.address()))
            && mv <= u32::from(cells) * u32::from(l.h.sim.register(OverVoltageCutoff.address()))
    });
    let ok = f.max_cell_mv <= ceiling && cvl_ok && !l.sent_limits.is_empty();
    let v =
        |dv: Option<u16>| dv.map_or("-".to_string(), |d| format!("{:.1} V", f64::from(d) / 10.0));
    let row = format!(
        "{:<13} {:>6} mV {:>5} mV {:>9} {:>9} {:>10.1} {:>12} {:>7.2} % {:>6}",
        name,
        f.max_cell_mv,
        ceiling,
        v(f.min_cvl_dv),
        v(f.max_cvl_dv),
        f.cvl_changes_per_hour(end),
        f.float_at_us
            .map_or("-".to_string(), |t| format!("{:.2} h", t as f64 / 3.6e9)),
        f.bus_load_percent(end),
        if ok { "yes" } else { "NO" }
    );
    (row, ok)
}

/// The closed-loop scenarios of the `sim` command (and of the tests).
pub const SCENARIOS: [&str; 7] = [
    "full-charge",
    "runner",
    "cold-morning",
    "hot-pack",
    "bms-fault",
    "uart-lost",
    "bus-off",
];

/// Runs one named scenario (see [`SCENARIOS`]) to its end and returns the loop
/// and its duration, µs. `None` for an unknown name.
pub fn run_scenario(
    name: &str,
    inverter: InverterConfig,
    on_start: impl FnMut(&mut ClosedLoop),
) -> Option<(ClosedLoop, u64)> {
    let l = ClosedLoop::new(PackModel::LiFePO4_16S, 1, inverter, 100.0);
    run_scenario_on(name, l, on_start)
}

/// [`run_scenario`] on a loop built by the caller (seed 1, a 100 A charger,
/// as `run_scenario`'s).
pub fn run_scenario_on(
    name: &str,
    mut l: ClosedLoop,
    mut on_start: impl FnMut(&mut ClosedLoop),
) -> Option<(ClosedLoop, u64)> {
    const S: u64 = 1_000_000;
    const MIN: u64 = 60 * S;
    const H: u64 = 3600 * S;
    on_start(&mut l);
    let end = match name {
        "full-charge" => {
            l.h.sim.set_soc_percent(20.0);
            l.run_until(6 * H);
            6 * H
        }
        "runner" => {
            l.h.sim.set_soc_percent(60.0);
            l.h.sim.set_cell_offset_mv(7, 30.0);
            l.run_until(5 * H);
            5 * H
        }
        "cold-morning" => {
            l.h.sim.set_soc_percent(40.0);
            l.h.sim.force_temperature(Some(-5.0));
            l.run_until(10 * MIN);
            for k in 0..20 {
                l.h.sim.force_temperature(Some(f64::from(k)));
                let t = l.h.now + 3 * MIN;
                l.run_until(t);
            }
            l.h.now
        }
        "hot-pack" => {
            l.h.sim.set_soc_percent(40.0);
            for (k, t) in [30.0, 45.0, 55.0, 57.5, 61.0, 50.0].into_iter().enumerate() {
                l.h.sim.force_temperature(Some(t));
                l.run_until((k as u64 + 1) * 5 * MIN);
            }
            30 * MIN
        }
        "bms-fault" => {
            l.h.sim.set_soc_percent(40.0);
            l.run_until(5 * MIN);
            l.h.sim
                .inject_fault_event(protocol_core::events::EventId::DischargingOverCurrentCutoff);
            l.run_until(7 * MIN);
            l.h.sim.clear_fault();
            l.run_until(15 * MIN);
            15 * MIN
        }
        "uart-lost" => {
            l.h.sim.set_soc_percent(40.0);
            l.run_until(5 * MIN);
            l.h.sim.set_silent_until(5 * MIN + 30 * S);
            l.run_until(10 * MIN);
            10 * MIN
        }
        "bus-off" => {
            l.h.sim.set_soc_percent(40.0);
            l.run_until(5 * MIN);
            l.bus_off(10 * S);
            l.run_until(10 * MIN);
            10 * MIN
        }
        _ => return None,
    };
    Some((l, end))
}
