//! Output lines: one JSON object per line, written with `serde` + `serde-json-core`
//! into a caller's buffer. No allocation, no `core::fmt`.
//!
//! Numbers print as `replay` prints them (host-tests/src/replay.rs): fixed-point
//! register values as `raw / 10^k` rounded to k decimals ([`fixed`]), f32
//! quantities rounded to [`FLOAT_DECIMALS`] ([`rounded`]), serialized with the
//! shortest round-trip representation (`ryu`, as `serde_json` does; the values'
//! writers are in [`wire`](super::wire)).

use heapless::String;
use protocol_core::events::{Event, EventId, OnlineStatus, ResetReason, WakeupReason};
use protocol_core::settings::{Setting, SettingError, SettingId};
use protocol_core::views::{CurrentSensor, LiveSnapshot, Statistics, VersionInfo};
use serde::ser::Serialize;

use crate::bms::link::LinkStats;
use crate::bridge::report::WriteOutcome;
use crate::units::{fixed, physical, rounded};

use super::schema::{self, Wire};
use super::wire::{Cells, Hex, Name};

/// Decimals of f32 quantities (pack voltage, current, speed): replay's
/// `FLOAT_DECIMALS`.
pub const FLOAT_DECIMALS: u32 = 4;

fn status_name(st: OnlineStatus) -> Name {
    st.key().map_or(Name::Unknown(st.raw()), Name::Known)
}

fn event_name(id: EventId) -> Name {
    match id {
        EventId::Unknown(v) => Name::Unknown(u16::from(v)),
        id => Name::Known(id.name()),
    }
}

fn reset_name(r: ResetReason) -> Name {
    match r {
        ResetReason::Unknown(v) => Name::Unknown(u16::from(v)),
        r => Name::Snake(r.name()),
    }
}

fn wakeup_name(r: WakeupReason) -> Name {
    match r {
        WakeupReason::Unknown(v) => Name::Unknown(u16::from(v)),
        r => Name::Snake(r.name()),
    }
}

fn sensor_name(c: CurrentSensor) -> Name {
    match c {
        CurrentSensor::InternalResistor => Name::Known("internal_resistor"),
        CurrentSensor::InternalHall => Name::Known("internal_hall"),
        CurrentSensor::External => Name::Known("external"),
        CurrentSensor::Unknown(v) => Name::Unknown(u16::from(v)),
    }
}

/// Serializes `v` and a `\n` into `out`; `None` when it does not fit.
fn line<T: Serialize>(v: &T, out: &mut [u8]) -> Option<usize> {
    let n = serde_json_core::to_slice(v, out).ok()?;
    *out.get_mut(n)? = b'\n';
    Some(n + 1)
}

/// What a `hello` line says.
#[derive(Debug, Clone, Copy)]
pub struct HelloFields<'a> {
    /// This firmware's version.
    pub firmware: &'a str,
    /// The chip's name.
    pub chip: &'a str,
    /// The board's name.
    pub board: &'a str,
    /// What the image has built in.
    pub features: crate::identity::Features,
    /// Read-only.
    pub read_only: bool,
    /// The stream period, ms.
    pub stream_period_ms: u32,
    /// Lines the host did not get since start-up (a host that did not read,
    /// a full queue).
    pub dropped_lines: u32,
    /// Where the configuration store lives, when the shell said.
    pub store: Option<crate::config::store::StoreSite>,
    /// Where the MQTT connection stands, once its session said (images with
    /// Wi-Fi).
    pub mqtt: Option<&'static str>,
    /// The radio's start (`crate::wifi::Radio::key`; images with Wi-Fi,
    /// once the shell said).
    pub radio: Option<&'static str>,
    /// The Wi-Fi link (images with Wi-Fi).
    pub wifi: Option<crate::improv::WifiLink>,
    /// The updates' side: slot, trial, keys trusted, a rollback.
    pub update: &'a super::UpdateView,
    /// Why the bridge keeps no history (`None`: it does).
    pub history: Option<&'static str>,
}

/// Writes a `hello` line.
pub fn hello(out: &mut [u8], req: Option<u32>, f: &HelloFields<'_>) -> Option<usize> {
    let mut ip = crate::log_line::Line::new();
    if let Some(crate::improv::WifiLink::Up(a)) = f.wifi {
        crate::text::ipv4(a, &mut ip);
    }
    let u = f.update;
    line(
        &schema::Hello::<Wire> {
            ty: "hello",
            req,
            protocol: super::PROTOCOL_VERSION,
            firmware: f.firmware,
            build: crate::identity::BUILD,
            chip: f.chip,
            board: f.board,
            features: &f.features.names(),
            record_version: crate::config::VERSION,
            read_only: f.read_only,
            stream_period_ms: f.stream_period_ms,
            dropped_lines: f.dropped_lines,
            store: f.store.map(|s| schema::Store::<Wire> {
                flash_kib: s.flash_bytes / 1024,
                partition_offset: s.partition.map(|p| p.0),
                partition_bytes: s.partition.map(|p| p.1),
                needs_bytes: crate::config::store::STORE_MIN_BYTES,
                problem: s.problem().map(|p| p.reason()),
            }),
            mqtt: f.mqtt,
            radio: f.radio,
            wifi: f.wifi.map(|w| schema::Wifi::<Wire> {
                state: w.key(),
                ip: (!ip.as_str().is_empty()).then_some(ip.as_str()),
            }),
            rolled_back: u.rolled_back.as_deref(),
            update: Some(schema::UpdateHello::<Wire> {
                slot: u.slot.map(|s| if s == 0 { "ota_0" } else { "ota_1" }),
                trial: if u.on_trial { "on_trial" } else { "confirmed" },
                built_in_key: u.built_in_key.as_ref().map(|k| Hex(k, false)),
                owner_key: u.owner_key.as_ref().map(|k| Hex(k, false)),
            }),
            history: Some(f.history.unwrap_or("recording")),
        },
        out,
    )
}

/// What the MQTT state says besides the host link's telemetry fields.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StateExtras<'a> {
    /// The status's key, or `other` for a value no table knows.
    pub status: &'static str,
    /// The status's name (Rev D's), or `Other` (Home Assistant's enum sensor
    /// needs a fixed list: `mqtt::discovery::STATUS_OPTIONS`).
    pub status_name: &'static str,
    /// Data age, ms.
    pub age_ms: u64,
    /// Requests answered, percent, 0.1 % steps (None: nothing asked yet).
    pub link_quality_permille: Option<u32>,
    /// The limits the inverter is sent: CVL 0.1 V, CCL 0.1 A, DCL 0.1 A.
    pub limits: Option<(u16, u16, u16)>,
    /// What is left in the pack, 0.01 Ah: the SOC of the capacity (306).
    pub remaining_cah: Option<u32>,
    /// Energy into and out of the pack since the bridge started, mWh.
    pub energy_mwh: (u64, u64),
    /// The bridge's uptime, s.
    pub uptime_s: u64,
    /// The bridge's firmware, build and board.
    pub bridge_firmware: &'a str,
    /// The CAN output's state, when built in.
    pub can_state: Option<&'static str>,
    /// The inverter is heard, when the CAN output is built in.
    pub inverter_heard: Option<bool>,
    /// What stops charging and discharging (`None`: the output off,
    /// published as null).
    pub stops: Option<(&'static str, &'static str)>,
    /// The SOC the frames tell the inverter, % (`None`: null).
    pub soc_told: Option<u8>,
    /// The last stop the inverter was seen ignoring, in words (`None`:
    /// null).
    pub ignored_stop: Option<&'a str>,
    /// Where the charge is and why, in words (`None`: null).
    pub charge_stage: Option<&'a str>,
    /// Why CVL, CCL and DCL are what they are, in words (`None`: null).
    pub why: [Option<&'a str>; 3],
    /// The doctor's verdicts of the last minute, their keys (`ok`: none;
    /// `None`: no CAN output, null).
    pub can_doctor: Option<&'a str>,
    /// The UART wire's verdict in words ([`crate::bms::wire`]).
    pub bms_wire: Option<&'a str>,
    /// The Wi-Fi signal, dBm (`None`: unknown, published as null).
    pub wifi_rssi_dbm: Option<i8>,
    /// "update to X rolled back: reason" (`None`: none, published as null).
    pub update_rolled_back: Option<&'a str>,
    /// The newest version known beyond the running one (`None`: none known,
    /// published as null: Home Assistant's update entity then says unknown).
    pub update_latest: Option<&'a str>,
    /// How the pack ages.
    pub aging: crate::history::Aging,
}

/// What a `telemetry` line says besides the snapshot.
#[derive(Debug, Clone, Copy)]
pub struct TelemetryHead {
    /// Echoed request id.
    pub req: Option<u32>,
    /// [`crate::Telemetry::snapshot_seq`].
    pub seq: u32,
    /// Snapshot age, ms.
    pub age_ms: Option<u64>,
    /// The freshness rule's limit the bridge runs with, ms (the host link's
    /// lines carry it, so a host shows "stale" by the bridge's rule).
    pub stale_after_ms: Option<u64>,
    /// Link up.
    pub online: bool,
    /// Settings and limits read.
    pub ready: bool,
    /// The inverter output (host link only; `None` without CAN output and in
    /// the MQTT state, which has members of its own).
    pub inverter: Option<InverterState>,
    /// Configuration fields changed that apply at the next restart (host
    /// link only: 0 is not written).
    pub restart_pending: u32,
}

/// The inverter output as a `telemetry` line's `inverter` member says it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InverterState {
    /// `victron` or `sma`.
    pub protocol: &'static str,
    /// [`crate::inverter::CanState::key`].
    pub can: &'static str,
    /// The inverter's keep-alive is heard.
    pub heard: bool,
    /// What it is told now: CVL 0.1 V, CCL 0.1 A, DCL 0.1 A (`None`: nothing
    /// sent, e.g. no fresh data).
    pub limits: Option<(u16, u16, u16)>,
    /// What stops charging and discharging
    /// ([`crate::inverter::dialect::shared::stop_key`]; `None` with the
    /// output off).
    pub stops: Option<(&'static str, &'static str)>,
    /// What the frames sent tell the inverter, read back from them.
    pub told: crate::inverter::dialect::Told,
    /// The last stop the inverter was seen ignoring.
    pub ignored: Option<crate::inverter::ignored::Ignored>,
    /// Where the charge is and why.
    pub stage: Option<crate::inverter::finish::Stage>,
    /// Why each limit is what it is.
    pub reasons: Option<crate::inverter::why::Reasons>,
    /// The inverter's heartbeat as heard.
    pub heartbeat: crate::inverter::doctor::Heartbeat,
    /// The doctor's verdicts of the last minute, in its order.
    pub verdicts: [Option<crate::inverter::doctor::Verdict>; crate::inverter::doctor::KINDS],
}

/// The words of the limits' reasons, and the doctor's keys, of an
/// [`InverterState`] (built once per line, lent to the schema).
struct InverterWords {
    why: Option<[crate::log_line::Line; 3]>,
    doctor: heapless::String<160>,
}

impl InverterWords {
    fn of(s: &InverterState) -> Self {
        let why = s
            .reasons
            .map(|r| [r.cvl.text(), r.ccl.text(), r.dcl.text()]);
        let mut doctor = heapless::String::new();
        for (k, v) in s.verdicts.iter().flatten().enumerate() {
            if k > 0 {
                let _ = doctor.push(',');
            }
            let _ = doctor.push_str(v.key()); // 9 keys < 160 bytes
        }
        Self { why, doctor }
    }
}

/// The `inverter` member of a `telemetry` line (`name`: 0x35E's, `ignored`:
/// the last ignored stop, in words; `reason`: the stage's).
fn inverter_member<'a>(
    s: &InverterState,
    name: Option<&'a str>,
    ignored: Option<&'a str>,
    reason: Option<&'a str>,
    words: &'a InverterWords,
) -> schema::Inverter<Wire<'a>> {
    let why = |k: usize| {
        words
            .why
            .as_ref()
            .and_then(|w| w.get(k))
            .map(|l| l.as_str())
    };
    let heard = s.heartbeat.count > 0;
    let l =
        |f: fn(&(u16, u16, u16)) -> u16| s.limits.as_ref().and_then(|x| fixed(i64::from(f(x)), 1));
    schema::Inverter {
        protocol: s.protocol,
        can: s.can,
        heard: s.heard,
        cvl_v: l(|x| x.0),
        ccl_a: l(|x| x.1),
        dcl_a: l(|x| x.2),
        charge_stop: s.stops.map(|x| x.0),
        discharge_stop: s.stops.map(|x| x.1),
        soc_told: s.told.soc_pct,
        charge_enabled: s.told.charge_enabled,
        discharge_enabled: s.told.discharge_enabled,
        name,
        ignored,
        stage: s.stage.map(|x| x.key()),
        stage_reason: reason,
        cvl_why: why(0),
        ccl_why: why(1),
        dcl_why: why(2),
        heartbeat_ms: heard.then_some(s.heartbeat.mean_ms),
        heartbeat_longest_ms: heard.then_some(s.heartbeat.longest_ms),
        heartbeat_late: heard.then_some(s.heartbeat.late),
        doctor: (!words.doctor.is_empty()).then_some(words.doctor.as_str()),
    }
}

/// 0x35E's name as text (trailing spaces dropped; `None` when not ASCII).
fn name_text(bytes: &[u8; 8]) -> Option<&str> {
    core::str::from_utf8(bytes)
        .ok()
        .map(|t| t.trim_end_matches(' '))
}

/// Writes a `telemetry` line: the head, and the snapshot's fields when there is
/// one.
pub fn telemetry(
    out: &mut [u8],
    head: TelemetryHead,
    snapshot: Option<&LiveSnapshot>,
    flagged: Option<&'static str>,
    extras: Option<&StateExtras>,
) -> Option<usize> {
    // Only the MQTT state says which cells balance (in words).
    let balancing = snapshot
        .filter(|_| extras.is_some())
        .map(|s| balancing_cells(s.real_balancing_bits, s.cell_count));
    let name = head.inverter.as_ref().and_then(|i| i.told.name);
    let ignored = head
        .inverter
        .as_ref()
        .and_then(|i| i.ignored)
        .map(|e| e.text());
    let reason = head
        .inverter
        .as_ref()
        .and_then(|i| i.stage)
        .map(|s| s.text());
    let words = head.inverter.as_ref().map(InverterWords::of);
    line(
        &schema::Telemetry::<Wire> {
            head: schema::Head {
                ty: "telemetry",
                req: head.req,
                seq: head.seq,
                age_ms: head.age_ms,
                stale_after_ms: head.stale_after_ms,
                online: head.online,
                ready: head.ready,
                restart_pending: (head.restart_pending > 0).then_some(head.restart_pending),
            },
            snapshot: snapshot.map(|s| snapshot_members(s, flagged)),
            told: schema::Told {
                inverter: head.inverter.as_ref().zip(words.as_ref()).map(|(i, w)| {
                    inverter_member(
                        i,
                        name.as_ref().and_then(name_text),
                        ignored.as_deref(),
                        reason.as_ref().map(|r| r.as_str()),
                        w,
                    )
                }),
            },
            extras: match (snapshot, extras, &balancing) {
                (Some(s), Some(e), Some(b)) => Some(extras_members(s, e, b)),
                _ => None,
            },
        },
        out,
    )
}

/// A snapshot's live values as a `telemetry` line says them.
fn snapshot_members<'a>(
    s: &'a LiveSnapshot,
    flagged: Option<&'static str>,
) -> schema::Snapshot<Wire<'a>> {
    let f32v = |x: f32| rounded(f64::from(x), FLOAT_DECIMALS);
    let ext = |t: Option<i16>| t.and_then(|t| fixed(i64::from(t), 1));
    schema::Snapshot {
        pack_voltage_v: f32v(s.pack_voltage_v),
        pack_current_a: f32v(s.pack_current_a),
        min_cell_voltage_v: fixed(i64::from(s.min_cell_mv), 3),
        max_cell_voltage_v: fixed(i64::from(s.max_cell_mv), 3),
        cell_voltages_v: Cells(&s.cells.raw),
        cell_first_register: s.cells.first_register,
        cell_count: s.cell_count,
        soc_percent: fixed(i64::from(s.soc_raw), 6),
        // 0.002 %: replay's rounded(raw / 500, 3), exactly.
        soh_percent: fixed(2 * i64::from(s.soh_raw), 3),
        lifetime_s: s.lifetime_s,
        estimated_time_left_s: s.estimated_time_left_s,
        internal_temperature_c: fixed(i64::from(s.internal_dc), 1),
        external_temperature_1_c: ext(s.external1_dc),
        external_temperature_2_c: ext(s.external2_dc),
        online_status: status_name(s.status),
        balancing_decision_bits: s.balancing_decision_bits,
        real_balancing_bits: s.real_balancing_bits,
        speed_kmh: f32v(s.speed_kmh),
        distance_left_km: s.distance_left_km,
        flagged,
    }
}

/// The MQTT state's members beyond the host link's.
fn extras_members<'a>(
    s: &LiveSnapshot,
    e: &StateExtras<'a>,
    balancing: &'a str,
) -> schema::Extras<Wire<'a>> {
    schema::Extras {
        status: e.status,
        pack_power_w: rounded(f64::from(s.pack_voltage_v) * f64::from(s.pack_current_a), 1),
        cell_spread_v: fixed(i64::from(s.max_cell_mv.saturating_sub(s.min_cell_mv)), 3),
        data_age_s: fixed(e.age_ms.min(1 << 40) as i64, 3),
        link_quality_percent: e.link_quality_permille.and_then(|p| fixed(i64::from(p), 1)),
        cvl_v: e.limits.and_then(|l| fixed(i64::from(l.0), 1)),
        ccl_a: e.limits.and_then(|l| fixed(i64::from(l.1), 1)),
        dcl_a: e.limits.and_then(|l| fixed(i64::from(l.2), 1)),
        status_name: e.status_name,
        balancing_cells: balancing,
        remaining_capacity_ah: e.remaining_cah.and_then(|c| fixed(i64::from(c), 2)),
        energy_charged_kwh: fixed(e.energy_mwh.0.min(1 << 50) as i64, 6),
        energy_discharged_kwh: fixed(e.energy_mwh.1.min(1 << 50) as i64, 6),
        uptime_s: e.uptime_s,
        bridge_firmware: e.bridge_firmware,
        can_state: e.can_state,
        inverter_heard: e.inverter_heard,
        charge_stop: e.stops.map(|x| x.0),
        discharge_stop: e.stops.map(|x| x.1),
        soc_told: e.soc_told,
        ignored_stop: e.ignored_stop,
        charge_stage: e.charge_stage,
        cvl_why: e.why[0],
        ccl_why: e.why[1],
        dcl_why: e.why[2],
        can_doctor: e.can_doctor,
        bms_wire: e.bms_wire,
        wifi_rssi_dbm: e.wifi_rssi_dbm,
        update_rolled_back: e.update_rolled_back,
        update_latest: e.update_latest,
        capacity_measured_ah: e.aging.capacity.and_then(|c| fixed(i64::from(c.0), 2)),
        capacity_uncertainty_percent: e.aging.capacity.and_then(|c| fixed(i64::from(c.1), 1)),
        charge_cycles: e.aging.cycles,
        top_spread_mv: e.aging.top_spread_mv,
        history: if e.aging.recording {
            "recording"
        } else {
            "off"
        },
    }
}

/// The cells balancing now (bit 0 of the real balancing bits is cell 1), as
/// `3, 7`, or `none`.
pub fn balancing_cells(bits: u16, cells: u16) -> String<64> {
    let mut out = String::new();
    for c in 0..cells.min(16) {
        if bits & (1 << c) != 0 {
            if !out.is_empty() {
                let _ = out.push_str(", ");
            }
            let n = c + 1;
            if n >= 10 {
                let _ = out.push('1');
            }
            let _ = out.push(char::from(b'0' + (n % 10) as u8));
        }
    }
    if out.is_empty() {
        let _ = out.push_str("none");
    }
    out
}

/// The MQTT state: a `telemetry` line's object with the [`StateExtras`], without
/// the line's `\n`.
pub fn state(
    out: &mut [u8],
    head: TelemetryHead,
    snapshot: Option<&LiveSnapshot>,
    flagged: Option<&'static str>,
    extras: Option<&StateExtras>,
) -> Option<usize> {
    telemetry(out, head, snapshot, flagged, extras).map(|n| n.saturating_sub(1))
}

/// Writes a `setting` line: the current raw value (when read), its physical
/// value, Rev D's range and the BMS's own limits, all in the setting's unit.
pub fn setting(
    out: &mut [u8],
    req: Option<u32>,
    id: SettingId,
    raw: Option<i32>,
    bms_limits: Option<(i32, i32)>,
) -> Option<usize> {
    let r = id.register();
    let range = r.and_then(|r| r.range);
    line(
        &schema::SettingLine::<Wire> {
            ty: "setting",
            req,
            name: crate::bms::profile::setting_key(id),
            address: id.address(),
            raw,
            value: raw.and_then(|v| physical(id, v)),
            unit: r.map(|r| r.unit).unwrap_or(""),
            min: range.and_then(|(lo, _)| physical(id, lo)),
            max: range.and_then(|(_, hi)| physical(id, hi)),
            bms_min: bms_limits.and_then(|(lo, _)| physical(id, lo)),
            bms_max: bms_limits.and_then(|(_, hi)| physical(id, hi)),
        },
        out,
    )
}

/// Writes the line that closes a listing (`settings_end`, `events_end`).
pub fn end(out: &mut [u8], ty: &'static str, req: Option<u32>, count: u32) -> Option<usize> {
    line(&schema::End::<Wire> { ty, req, count }, out)
}

/// Writes a `can` line: one entry of the CAN capture as a candump line.
pub fn can(out: &mut [u8], req: Option<u32>, candump: &str) -> Option<usize> {
    line(
        &schema::CanLine::<Wire> {
            ty: "can",
            req,
            line: candump,
        },
        out,
    )
}

/// Writes a `can_end` line: `count` `can` lines of a capture of `protocol`.
pub fn can_end(out: &mut [u8], req: Option<u32>, count: u32, protocol: &str) -> Option<usize> {
    line(
        &schema::CanEnd::<Wire> {
            ty: "can_end",
            req,
            count,
            protocol,
        },
        out,
    )
}

/// Writes one line of a `get history` listing (`history_event`,
/// `history_day`, `history_skipped`).
pub fn history(
    out: &mut [u8],
    req: Option<u32>,
    item: &crate::history::log::Listed,
) -> Option<usize> {
    use crate::history::log::Listed;
    use crate::history::ring::{Kind, DAY_PAYLOAD_BYTES};
    match item {
        Listed::Event(id, e) => line(
            &schema::HistoryEvent::<Wire> {
                ty: "history_event",
                req,
                id: *id,
                code: e.code.key(),
                boot: u32::from(e.boot),
                uptime_ms: e.uptime_ms,
                date: (e.unix_s != 0).then_some(u64::from(e.unix_s)),
                a: e.a,
                b: e.b,
                text: e.text(),
            },
            out,
        ),
        Listed::Day(id, p) => line(
            &schema::HistoryDay::<Wire> {
                ty: "history_day",
                req,
                id: *id,
                record: Hex(p.get(..DAY_PAYLOAD_BYTES).unwrap_or(p), false),
            },
            out,
        ),
        Listed::Skipped(kind, at, reason) => line(
            &schema::HistorySkipped::<Wire> {
                ty: "history_skipped",
                req,
                ring: if *kind == Kind::Event {
                    "events"
                } else {
                    "days"
                },
                at: *at,
                reason,
            },
            out,
        ),
    }
}

/// Writes a `history_end` line.
pub fn history_end(out: &mut [u8], req: Option<u32>, counts: [u32; 3]) -> Option<usize> {
    line(
        &schema::HistoryEnd::<Wire> {
            ty: "history_end",
            req,
            events: counts[0],
            days: counts[1],
            skipped: counts[2],
        },
        out,
    )
}

/// Writes a `statistics` line (replay's statistics fields).
pub fn statistics(out: &mut [u8], req: Option<u32>, s: &Statistics) -> Option<usize> {
    line(
        &schema::StatisticsLine::<Wire> {
            ty: "statistics",
            req,
            total_distance_km: fixed(i64::from(s.total_distance_raw), 2),
            max_discharge_current_a: fixed(i64::from(s.max_discharge_current_da), 1),
            max_charge_current_a: fixed(i64::from(s.max_charge_current_da), 1),
            max_cell_voltage_difference_v: fixed(i64::from(s.max_cell_difference_raw), 4),
            under_voltage_count: s.under_voltage_count,
            over_voltage_count: s.over_voltage_count,
            discharge_over_current_count: s.discharge_over_current_count,
            charge_over_current_count: s.charge_over_current_count,
            over_heat_count: s.over_heat_count,
            charging_count: s.charging_count,
            full_charge_count: s.full_charge_count,
            min_pack_temperature_c: s.min_pack_temperature_c,
            max_pack_temperature_c: s.max_pack_temperature_c,
            last_reset: reset_name(s.last_reset),
            last_wakeup: wakeup_name(s.last_wakeup),
            stats_cleared_at_s: s.stats_cleared_at_s,
        },
        out,
    )
}

/// Writes a `version` line (replay's version fields).
pub fn version(out: &mut [u8], req: Option<u32>, v: &VersionInfo) -> Option<usize> {
    line(
        &schema::Version::<Wire> {
            ty: "version",
            req,
            hardware_version: v.hardware,
            hardware_changes_version: v.hardware_changes,
            firmware_public_version: v.firmware_public,
            high_power: v.high_power,
            current_sensor: sensor_name(v.current_sensor),
            firmware_internal_version: v.firmware_internal,
            bootloader_version: v.bootloader,
            profile_version: v.profile,
            serial_number: Hex(&v.serial, false),
        },
        out,
    )
}

/// Writes an `event` line (replay's event fields; `history` on `get events`).
pub fn event(out: &mut [u8], req: Option<u32>, e: &Event, history: bool) -> Option<usize> {
    line(
        &schema::EventLine::<Wire> {
            ty: "event",
            req,
            timestamp_s: e.timestamp_s,
            id: e.id.raw(),
            name: event_name(e.id),
            severity: e.id.severity().name(),
            history,
        },
        out,
    )
}

/// A `log` line: one of the bridge's own log lines, as its log has it.
pub fn log(out: &mut [u8], level: crate::Level, text: &str) -> Option<usize> {
    log_line(out, level, text, false)
}

/// A `log` line of one of the lines the bridge wrote at boot, replayed after
/// a `hello` (`"boot":true`).
pub fn boot_log(out: &mut [u8], level: crate::Level, text: &str) -> Option<usize> {
    log_line(out, level, text, true)
}

fn log_line(out: &mut [u8], level: crate::Level, text: &str, boot: bool) -> Option<usize> {
    line(
        &schema::Log::<Wire> {
            ty: "log",
            level: match level {
                crate::Level::Info => "info",
                crate::Level::Warn => "warn",
            },
            text,
            boot: boot.then_some(true),
        },
        out,
    )
}

/// Writes a `link` line: the UART link's counters and the host link's own.
pub fn link(
    out: &mut [u8],
    req: Option<u32>,
    s: &LinkStats,
    online: bool,
    piece_registers: u16,
    host: &super::HostLinkStats,
    wire: (crate::bms::wire::WireFigures, crate::bms::wire::WireVerdict),
) -> Option<usize> {
    let mut verdict = crate::log_line::Line::new();
    wire.1.text(&mut verdict);
    line(
        &schema::Link::<Wire> {
            ty: "link",
            req,
            requests: s.requests,
            replies: s.replies,
            timeouts: s.timeouts,
            wakeup_resends: s.wakeup_resends,
            retries: s.retries,
            crc_errors: s.crc_errors,
            framing_errors: s.framing_errors,
            invalid_replies: s.invalid_replies,
            nacks_command: s.nacks_command,
            nacks_crc: s.nacks_crc,
            nacks_other: s.nacks_other,
            skipped_bytes: s.skipped_bytes,
            unsolicited: s.unsolicited,
            failures: s.failures,
            latency_min_us: s.latency_min_us,
            latency_mean_us: s.latency_mean_us(),
            latency_max_us: s.latency_max_us,
            online,
            piece_registers,
            lines_in: host.lines_in,
            errors: host.errors,
            dropped_lines: host.dropped_lines,
            corrupted_permille: wire.0.corrupted_permille,
            lost_permille: wire.0.lost_permille,
            resent_permille: wire.0.resent_permille,
            wire: wire.1.key(),
            wire_verdict: verdict.as_str(),
        },
        out,
    )
}

/// Writes an `accepted` line.
pub fn accepted(out: &mut [u8], req: Option<u32>, cmd: &'static str) -> Option<usize> {
    line(
        &schema::Accepted::<Wire> {
            ty: "accepted",
            req,
            cmd,
        },
        out,
    )
}

/// Writes an `outcome` line for one setting through write/verify.
pub fn outcome(
    out: &mut [u8],
    req: Option<u32>,
    setting: &Setting,
    outcome: &WriteOutcome,
    follow_up: bool,
) -> Option<usize> {
    let (detail, read_back, nack_code) = match outcome {
        WriteOutcome::Verified | WriteOutcome::Unchanged => (None, None, None),
        WriteOutcome::Rejected(e) => (Some(e.reason()), None, None),
        WriteOutcome::Mismatch { read_back } => (Some("read_back_differs"), Some(*read_back), None),
        WriteOutcome::Nacked(c) => (Some(c.name()), None, Some(c.to_u8())),
        WriteOutcome::NotWritten(f) | WriteOutcome::Failed(f) | WriteOutcome::Unconfirmed(f) => {
            (Some(f.name()), None, None)
        }
    };
    line(
        &schema::Outcome::<Wire> {
            ty: "outcome",
            req,
            name: crate::bms::profile::setting_key(setting.id),
            raw: setting.value,
            value: physical(setting.id, setting.value),
            outcome: outcome.name(),
            detail,
            read_back,
            nack_code,
            chemistry: match outcome {
                WriteOutcome::Rejected(SettingError::OutsideChemistry { chemistry, .. }) => {
                    Some(chemistry.key())
                }
                _ => None,
            },
            follow_up,
        },
        out,
    )
}

/// Writes an `update` line.
pub fn update(out: &mut [u8], l: &schema::Update<Wire<'_>>) -> Option<usize> {
    line(l, out)
}

/// Writes a `reset_done` line.
pub fn reset_done(out: &mut [u8], req: Option<u32>, confirmed: bool) -> Option<usize> {
    line(
        &schema::ResetDone::<Wire> {
            ty: "reset_done",
            req,
            confirmed,
        },
        out,
    )
}

/// Writes a `cleared` line.
pub fn cleared(out: &mut [u8], req: Option<u32>, what: &'static str, ok: bool) -> Option<usize> {
    line(
        &schema::Cleared::<Wire> {
            ty: "cleared",
            req,
            what,
            ok,
        },
        out,
    )
}

/// Writes a `raw` line (UART bytes while capture is on).
pub fn raw(out: &mut [u8], dir: &'static str, bytes: &[u8]) -> Option<usize> {
    line(
        &schema::Raw::<Wire> {
            ty: "raw",
            dir,
            hex: Hex(bytes, true),
        },
        out,
    )
}

/// Writes an `error` line; `detail` is the reason, followed by `: subject` (the
/// offending name) when there is one.
pub fn error(
    out: &mut [u8],
    req: Option<u32>,
    code: &'static str,
    detail: &'static str,
    subject: &str,
) -> Option<usize> {
    // The longest reason is 70 bytes (`what: snapshot, ...`); a reason and a
    // subject that do not fit would lose the subject.
    let mut d: String<{ 96 + 2 + super::SUBJECT_MAX }> = String::new();
    let _ = d.push_str(detail);
    if !subject.is_empty() {
        let _ = d.push_str(": ");
        let _ = d.push_str(subject);
    }
    line(
        &schema::Error::<Wire> {
            ty: "error",
            req,
            error: code,
            detail: &d,
        },
        out,
    )
}

/// Writes a `config` line: one field of the bridge's configuration, its value
/// in the stored record as text (`set`/`unset` for a secret), its default,
/// range and when a change applies.
#[inline(never)]
pub fn config_field(
    out: &mut [u8],
    req: Option<u32>,
    f: &crate::config::Field,
    config: &crate::config::state::ConfigState,
    bms: Option<&crate::config::PackSettings>,
) -> Option<usize> {
    use crate::config::value;
    use crate::text::Line;
    let mut e = Line::new();
    let effective =
        bms.and_then(|b| effective(f.id, config.stored(), b, &mut e).then(|| e.as_str()));
    let mut v = Line::new();
    value::write(f, &config.stored().get(f.id), false, &mut v);
    let defaults = crate::config::Config::default();
    let mut d = Line::new();
    value::write(f, &defaults.get(f.id), false, &mut d);
    let mut r = Line::new();
    value::write_range(f, &mut r);
    line(
        &schema::ConfigField::<Wire> {
            ty: "config",
            req,
            name: f.name,
            group: f.group.name(),
            value: v.as_str(),
            unit: f.unit,
            default: d.as_str(),
            range: r.as_str(),
            applies: f.applies.name(),
            restart_pending: config.restart_pending(f.id),
            secret: f.is_secret(),
            help: f.help,
            effective,
        },
        out,
    )
}

/// What a field that leaves its value to the BMS (`absorption_voltage bms`,
/// `float_voltage auto`, a cap `none`) comes to with the BMS's settings `b`,
/// as charge control computes it: written to `out` (true), or nothing to say.
/// Not inlined: one copy for every field of a listing (flash is tight).
#[inline(never)]
fn effective(
    id: crate::config::FieldId,
    c: &crate::config::Config,
    b: &crate::config::PackSettings,
    out: &mut crate::text::Line,
) -> bool {
    use crate::config::FieldId;
    let (absorption, float) =
        crate::inverter::control::ChargeControl::new(c.charge()).targets_mv(b);
    match id {
        FieldId::AbsorptionVoltage if c.absorption_voltage_mv == 0 => {
            out.uint(u64::from(absorption)).push(" mV");
        }
        FieldId::FloatVoltage if c.float_voltage_mv == 0 => {
            out.uint(u64::from(float)).push(" mV");
        }
        FieldId::ChargeCurrentCap if c.charge_current_cap_da == 0 => {
            out.uint(u64::from(b.charge_cutoff_a)).push(".0 A");
        }
        FieldId::DischargeCurrentCap if c.discharge_current_cap_da == 0 => {
            out.uint(u64::from(b.discharge_cutoff_a)).push(".0 A");
        }
        _ => return false,
    }
    true
}

/// Writes a `config_end` line: how many fields, the record's layout version,
/// where the record the bridge started with came from, and how many fields
/// wait for a restart.
pub fn config_end(
    out: &mut [u8],
    req: Option<u32>,
    config: &crate::config::state::ConfigState,
) -> Option<usize> {
    line(
        &schema::ConfigEnd::<Wire> {
            ty: "config_end",
            req,
            count: crate::config::FIELDS.len() as u32,
            version: crate::config::VERSION,
            source: config.source().name(),
            restart_pending: config.restarts_pending() as u32,
        },
        out,
    )
}

/// Writes a `config_outcome` line for a field of a `set_config`: the outcome,
/// the field's value in the stored record afterwards (`set`/`unset` for a
/// secret), and for a refusal the error code, the reason and the field's range.
pub fn config_outcome(
    out: &mut [u8],
    req: Option<u32>,
    name: &str,
    id: Option<crate::config::FieldId>,
    outcome: crate::config::state::Outcome,
    config: &crate::config::state::ConfigState,
) -> Option<usize> {
    use crate::config::state::Outcome;
    use crate::config::value;
    use crate::text::Line;
    let mut v = Line::new();
    let mut r = Line::new();
    if let Some(id) = id {
        value::write(id.field(), &config.stored().get(id), true, &mut v);
        match outcome {
            // What the BMS's settings allow, not the field's whole range.
            Outcome::RuleBroken(_, Some((lo, hi))) => {
                value::write_bounds(id.field(), lo, hi, &mut r)
            }
            _ => value::write_range(id.field(), &mut r),
        }
    }
    let (error, detail) = match outcome {
        Outcome::Refused(e) => (
            Some(if e.out_of_range {
                "out_of_range"
            } else {
                "invalid_value"
            }),
            Some(e.detail),
        ),
        Outcome::RuleBroken(d, _) => (Some("out_of_range"), Some(d)),
        Outcome::NotApplied => (None, Some("another field was refused: nothing changed")),
        _ => (None, None),
    };
    let refused = error.is_some();
    line(
        &schema::ConfigOutcome::<Wire> {
            ty: "config_outcome",
            req,
            name,
            outcome: outcome.name(),
            value: id.map(|_| v.as_str()),
            error,
            detail,
            range: (refused && id.is_some()).then_some(r.as_str()),
        },
        out,
    )
}

/// Writes the `config_outcome` line of a name no field has.
pub fn config_unknown(out: &mut [u8], req: Option<u32>, name: &str) -> Option<usize> {
    line(
        &schema::ConfigOutcome::<Wire> {
            ty: "config_outcome",
            req,
            name,
            outcome: "refused",
            value: None,
            error: Some("unknown_setting"),
            detail: Some("no such field (`tinybms config PORT` lists them)"),
            range: None,
        },
        out,
    )
}

/// Writes a `config_done` line: the end of a `set_config` or `reset_config`.
pub fn config_done(out: &mut [u8], done: &super::ConfigDone) -> Option<usize> {
    use crate::config::store::Saved;
    let (saved, detail) = match done.saved {
        None => (None, None),
        Some(Ok(Saved::Written | Saved::Unchanged)) => (Some(true), None),
        Some(Err(e)) => (Some(false), Some(e.reason())),
    };
    line(
        &schema::ConfigDone::<Wire> {
            ty: "config_done",
            req: done.req,
            changed: done.changed,
            saved,
            restart_needed: done.restart_needed,
            detail,
        },
        out,
    )
}

/// A `battery` line: the battery of packs in parallel as this bridge sees it
/// (all `null` but the counts while no pack takes part).
pub fn battery(out: &mut [u8], v: &crate::inverter::packs::BatteryView) -> Option<usize> {
    let b = v.battery.as_ref();
    let offline = v
        .packs
        .len()
        .saturating_sub(b.map_or(0, |(b, _)| usize::from(b.online)));
    line(
        &schema::Battery::<Wire> {
            ty: "battery",
            node: v.node,
            speaking: v.speaking,
            packs_online: b.map_or(0, |(b, _)| b.online),
            packs_offline: offline.min(usize::from(u8::MAX)) as u8,
            capacity_ah: b.and_then(|(b, _)| fixed(i64::from(b.capacity_dah), 1)),
            soc_percent: b.and_then(|(b, _)| rounded(f64::from(b.state.soc_pct), 2)),
            soh_percent: b.and_then(|(b, _)| rounded(f64::from(b.state.soh_pct), 0)),
            voltage_v: b.and_then(|(b, _)| rounded(f64::from(b.state.pack_v), 2)),
            current_a: b.and_then(|(b, _)| rounded(f64::from(b.state.current_a), 1)),
            min_cell_v: b.and_then(|(b, _)| fixed(i64::from(b.state.min_cell_mv), 3)),
            max_cell_v: b.and_then(|(b, _)| fixed(i64::from(b.state.max_cell_mv), 3)),
            min_temperature_c: b.and_then(|(b, _)| rounded(f64::from(b.state.min_temp_c), 1)),
            max_temperature_c: b.and_then(|(b, _)| rounded(f64::from(b.state.max_temp_c), 1)),
            cvl_v: b.and_then(|(_, l)| fixed(i64::from(l.cvl_dv), 1)),
            ccl_a: b.and_then(|(_, l)| fixed(i64::from(l.ccl_da), 1)),
            dcl_a: b.and_then(|(_, l)| fixed(i64::from(l.dcl_da), 1)),
        },
        out,
    )
}

/// A `pack` line: one pack of the battery, from its summary.
pub fn pack(out: &mut [u8], p: &crate::inverter::packs::PackView) -> Option<usize> {
    let s = &p.summary;
    line(
        &schema::Pack::<Wire> {
            ty: "pack",
            node: p.node,
            state: p.part.name(),
            speaking: s.speaking,
            voltage_v: fixed(i64::from(s.voltage_cv), 2),
            current_a: fixed(i64::from(s.current_da), 1),
            soc_percent: fixed(i64::from(s.soc_cpct), 2),
            soh_percent: s.soh_pct,
            min_cell_v: fixed(i64::from(s.min_cell_mv), 3),
            max_cell_v: fixed(i64::from(s.max_cell_mv), 3),
            min_temperature_c: fixed(i64::from(s.min_temp_dc), 1),
            max_temperature_c: fixed(i64::from(s.max_temp_dc), 1),
            capacity_ah: fixed(i64::from(s.capacity_dah), 1),
            data_age_s: fixed(i64::from(s.age_ds), 1),
            cvl_v: fixed(i64::from(s.limits.cvl_dv), 1),
            ccl_a: fixed(i64::from(s.limits.ccl_da), 1),
            dcl_a: fixed(i64::from(s.limits.dcl_da), 1),
        },
        out,
    )
}
