//! The inverter frames byte by byte, the DBC files against the encoder, and the
//! properties of charge control.

use std::collections::BTreeMap;

use proptest::prelude::*;
use tinybms_firmware::inverter::control::{
    ChargeConfig, ChargeControl, Conditions, Limits, PackSettings, PackState,
};
use tinybms_firmware::inverter::dialect::{sma, victron, CanFrame, Period, Protected, Say};
use tinybms_firmware::inverter::Protocol;

const S: u64 = 1_000_000;

fn lfp_settings() -> PackSettings {
    PackSettings {
        fully_charged_mv: 3650,
        capacity_cah: 28000,
        cells: 16,
        allowed_disbalance_mv: 15,
        ov_cutoff_mv: 3650,
        uv_cutoff_mv: 2500,
        discharge_cutoff_a: 150,
        charge_cutoff_a: 90,
        discharge_cutoff_s: 5,
        overheat_c: 60,
        low_temp_charge_c: 0,
    }
}

fn state() -> PackState {
    PackState {
        min_cell_mv: 3301,
        max_cell_mv: 3312,
        pack_v: 52.91,
        current_a: -25.5,
        soc_pct: 65.4,
        soh_pct: 97.0,
        min_temp_c: 24.5,
        max_temp_c: 27.0,
        fault: false,
        charge_blocked: false,
        balancing: 0,
    }
}

// ---------------------------------------------------------------------------
// Byte-exact vectors (little-endian; worked by hand).
// ---------------------------------------------------------------------------

#[test]
fn frame_0x351_limits() {
    // CVL 56.8 V = 568 = 0x0238; CCL 60.0 A = 600 = 0x0258; DCL 150.0 A =
    // 1500 = 0x05DC; discharge voltage 41.6 V = 416 = 0x01A0.
    let f = victron::limits(&Limits {
        cvl_dv: 568,
        ccl_da: 600,
        dcl_da: 1500,
        discharge_dv: 416,
    });
    assert_eq!((f.id, f.len), (0x351, 8));
    assert_eq!(f.bytes(), &[0x38, 0x02, 0x58, 0x02, 0xDC, 0x05, 0xA0, 0x01]);
}

#[test]
fn frame_0x355_soc() {
    // SOC 65 % (65.4 rounded down), SOH 97 %, SOC 65.40 % = 6540 = 0x198C.
    let f = victron::soc(state().soc_pct, state().soh_pct);
    assert_eq!((f.id, f.len), (0x355, 6));
    assert_eq!(f.bytes(), &[0x41, 0x00, 0x61, 0x00, 0x8C, 0x19]);
}

#[test]
fn frame_0x356_measurements() {
    // 52.91 V = 5291 = 0x14AB; -25.5 A = -255 = 0xFF01; 27.0 °C = 270 = 0x010E.
    let f = victron::measurements(&state(), 1.0);
    assert_eq!((f.id, f.len), (0x356, 6));
    assert_eq!(f.bytes(), &[0xAB, 0x14, 0x01, 0xFF, 0x0E, 0x01]);
}

#[test]
fn frame_0x35a_victron_all_ok() {
    // Every supported field OK (0b10); contactor and short circuit not
    // supported (0b00); system status OK: byte 0 = 10 10 10 10 = 0xAA, byte 1 =
    // 0xAA, byte 2 = 10 00 00 10 = 0x82, byte 3 = 0x02; warnings the same, and
    // byte 7 also has the system-status OK (bits 2-3 = 10): 0x0A.
    let f = victron::alarms(&Conditions::default(), &Protected::default(), false);
    assert_eq!((f.id, f.len), (0x35A, 8));
    assert_eq!(f.bytes(), &[0xAA, 0xAA, 0x82, 0x02, 0xAA, 0xAA, 0x82, 0x0A]);
}

#[test]
fn frame_0x35a_victron_high_voltage_alarm_and_imbalance_warning() {
    let c = Conditions {
        high_voltage: 2,
        cell_imbalance: 1,
        ..Conditions::default()
    };
    let f = victron::alarms(&c, &Protected::default(), true);
    // Byte 0: general active (01), high voltage active (01 << 2), low voltage
    // OK (10 << 4), high temperature OK (10 << 6) = 0b10_10_01_01 = 0xA5.
    // Byte 3: imbalance alarm OK = 0x02; byte 7: imbalance warning active (01),
    // system status offline active (01 << 2) = 0x05. Byte 4: general warning
    // active, high voltage warning active = 0xA5.
    assert_eq!(f.bytes(), &[0xA5, 0xAA, 0x82, 0x02, 0xA5, 0xAA, 0x82, 0x05]);
}

#[test]
fn frame_0x35a_sma_flags_only_real_faults_as_alarms() {
    // Over-heat alarm (a real fault): alarm flag bit 6 of byte 0 + general
    // (bit 0); warning flags the same. A charge over-current alarm is a warning
    // only for the Sunny Island (any alarm stops it until a manual restart).
    let c = Conditions {
        high_temperature: 2,
        high_charge_current: 2,
        ..Conditions::default()
    };
    let f = sma::alarms(&c, &Protected::default());
    assert_eq!((f.id, f.len), (0x35A, 8));
    assert_eq!(f.bytes(), &[0x41, 0x00, 0x00, 0x00, 0x41, 0x00, 0x01, 0x00]);
    let ok = sma::alarms(&Conditions::default(), &Protected::default());
    assert_eq!(ok.bytes(), &[0; 8]);
}

#[test]
fn frame_0x35a_sma_bms_fault_status_is_a_warning_not_an_alarm() {
    // The TinyBMS clears its own fault status after an over-current trip or a
    // cold-morning cutoff; a Sunny Island alarm would need a manual restart.
    let f = sma::alarms(
        &Conditions {
            bms_internal: 2,
            ..Conditions::default()
        },
        &Protected {
            system: true,
            ..Protected::default()
        },
    );
    assert_eq!(&f.bytes()[..4], &[0, 0, 0, 0], "no alarm flag");
    assert_eq!(&f.bytes()[4..], &[0x01, 0x00, 0x40, 0x00], "warnings");
}

#[test]
fn frame_0x356_sma_current_is_positive_when_discharging() {
    // -25.5 A (discharging) is sent as +255 = 0x00FF to the Sunny Island.
    let f = victron::measurements(&state(), sma::CURRENT_SIGN);
    assert_eq!(f.bytes(), &[0xAB, 0x14, 0xFF, 0x00, 0x0E, 0x01]);
}

#[test]
fn settings_with_zero_current_cutoffs_are_refused() {
    let regs = |coc: u16| {
        let mut v = [0u16; 44];
        for (a, x) in [
            (300, 3650),
            (306, 28000),
            (307, 16),
            (315, 3650),
            (316, 2500),
            (317, 150),
            (318, coc),
            (319, 60),
        ] {
            v[a - 300] = x;
        }
        protocol_core::response::RegisterBlock {
            start: 300,
            values: heapless::Vec::from_slice(&v).unwrap(),
        }
    };
    assert!(PackSettings::from_registers(&regs(90)).is_some());
    assert!(PackSettings::from_registers(&regs(0)).is_none());
}

#[test]
fn a_cut_on_the_first_update_is_held_too() {
    let s = lfp_settings();
    let mut c = ChargeControl::new(ChargeConfig::default());
    let faulty = PackState {
        fault: true,
        ..state()
    };
    assert_eq!(c.update(0, &s, &faulty).0.ccl_da, 0);
    // The fault clears at once: still held for 30 s, then ramping.
    assert_eq!(c.update(S, &s, &state()).0.ccl_da, 0);
    assert_eq!(c.update(20 * S, &s, &state()).0.ccl_da, 0);
    let after = c.update(32 * S, &s, &state()).0.ccl_da;
    assert!(after > 0 && after <= 20 * 12, "{after}");
}

/// A current past its cutoff: a discharge past 317 stops once it lasted
/// 1 s (half the BMS's timeout when that is shorter; a shorter surge
/// passes), a charge past 318 at once; a timeout of 0 leaves no patience;
/// the limit comes back after the hold.
#[test]
fn a_current_past_its_cutoff_stops_that_direction_before_the_bms_trips() {
    let s = lfp_settings(); // 317 = 150 A for 5 s, 318 = 90 A
    let at = |a: f32| PackState {
        current_a: a,
        ..state()
    };
    let run = |s: &PackSettings, currents: &[(u64, f32)]| {
        let mut c = ChargeControl::new(ChargeConfig::default());
        let mut out = Vec::new();
        for &(t, a) in currents {
            let begins = c.watch_current(t, s, &at(a));
            let (l, _) = c.update(t, s, &at(a));
            out.push((begins, l.ccl_da, l.dcl_da));
        }
        out
    };
    // A 0.8 s surge to 160 A: nothing stops.
    let surge: Vec<_> = (0..=4)
        .map(|k| (k * S / 5, -160.0))
        .chain([(S, -40.0)])
        .collect();
    assert!(run(&s, &surge).iter().all(|&(b, _, dcl)| !b && dcl > 0));
    // 160 A on: DCL 0 from 1 s on, said once; CCL stays.
    let on: Vec<_> = (0..=6).map(|k| (k * S / 2, -160.0)).collect();
    let r = run(&s, &on);
    let first = r.iter().position(|&(_, _, dcl)| dcl == 0).unwrap();
    assert_eq!(first, 2, "{r:?}");
    assert_eq!(r.iter().filter(|(b, ..)| *b).count(), 1);
    assert!(r[first].0 && r[first].1 > 0);
    // The load gone: still 0 for the hold, then back.
    let mut c = ChargeControl::new(ChargeConfig::default());
    for &(t, a) in &on {
        c.watch_current(t, &s, &at(a));
        c.update(t, &s, &at(a));
    }
    c.watch_current(4 * S, &s, &at(0.0));
    assert_eq!(c.update(4 * S, &s, &at(0.0)).0.dcl_da, 0);
    assert_eq!(c.update(30 * S, &s, &at(0.0)).0.dcl_da, 0);
    assert!(c.update(40 * S, &s, &at(0.0)).0.dcl_da > 0);
    // A stop seen by a snapshot is kept for the next update even when a
    // later snapshot no longer shows the current.
    let mut c = ChargeControl::new(ChargeConfig::default());
    assert!(c.watch_current(0, &s, &at(95.0)));
    c.watch_current(S / 10, &s, &at(10.0));
    assert_eq!(c.update(S / 5, &s, &at(10.0)).0.ccl_da, 0);
    // Timeout 1 s: the stop at 0.5 s (half of it); 0 s: at once.
    for (timeout, when) in [(1u8, 1usize), (0, 0)] {
        let t = PackSettings {
            discharge_cutoff_s: timeout,
            ..s
        };
        let r = run(&t, &on);
        let first = r.iter().position(|&(_, _, dcl)| dcl == 0);
        assert_eq!(first, Some(when), "timeout {timeout}: {r:?}");
    }
}

#[test]
fn frame_0x35e_name_is_not_pylon() {
    let f = victron::name();
    assert_eq!((f.id, f.len), (0x35E, 8));
    assert_eq!(f.bytes(), b"TINYBMS ");
}

#[test]
fn frame_0x35f_victron_and_sma() {
    // Victron: model 0, firmware 20 = 0x0014, capacity 280 Ah = 0x0118.
    let v = victron::info(20, 280);
    assert_eq!((v.id, v.len), (0x35F, 6));
    assert_eq!(v.bytes(), &[0x00, 0x00, 0x14, 0x00, 0x18, 0x01]);
    // SMA: "Li", hardware 1.0 = 0x0001, 280 Ah, software 20.
    let s = sma::info(0x0001, 280, 20);
    assert_eq!((s.id, s.len), (0x35F, 8));
    assert_eq!(s.bytes(), &[b'L', b'i', 0x01, 0x00, 0x18, 0x01, 0x14, 0x00]);
}

#[test]
fn frames_0x372_0x373_0x379() {
    // One module online, blocking charge (CCL 0), not discharge, none offline.
    let m = victron::module_counts((1, 1, 0, 0));
    assert_eq!((m.id, m.len), (0x372, 8));
    assert_eq!(m.bytes(), &[1, 0, 1, 0, 0, 0, 0, 0]);
    // 3301 mV = 0x0CE5, 3312 mV = 0x0CF0, 24.5 °C = 297.65 K -> 298 = 0x012A,
    // 27.0 °C = 300.15 K -> 300 = 0x012C.
    let c = victron::cell_extremes(&state());
    assert_eq!((c.id, c.len), (0x373, 8));
    assert_eq!(c.bytes(), &[0xE5, 0x0C, 0xF0, 0x0C, 0x2A, 0x01, 0x2C, 0x01]);
    let k = victron::capacity(280);
    assert_eq!((k.id, k.len), (0x379, 2));
    assert_eq!(k.bytes(), &[0x18, 0x01]);
}

#[test]
fn candump_lines_are_what_can_utils_write() {
    let f = victron::limits(&Limits {
        cvl_dv: 568,
        ccl_da: 600,
        dcl_da: 1500,
        discharge_dv: 416,
    });
    assert_eq!(
        host_tests::closed_loop::candump_line(1_250_000, &f),
        "(1700000001.250000) can0 351#38025802DC05A001"
    );
}

// ---------------------------------------------------------------------------
// The DBC files describe exactly what the encoder sends.
// ---------------------------------------------------------------------------

#[derive(Debug)]
struct Signal {
    name: String,
    start: u32,
    len: u32,
    /// Motorola (big-endian, `@0`): `start` is the most significant bit, in
    /// the DBC's numbering (byte × 8 + bit, bit 7 the byte's highest).
    big_endian: bool,
    signed: bool,
    factor: f64,
    offset: f64,
}

impl Signal {
    /// The bits of the signal, most significant first, as indexes into the
    /// little-endian 64-bit word of the data (byte × 8 + bit).
    fn bits(&self) -> Vec<u32> {
        if !self.big_endian {
            return (0..self.len).rev().map(|i| self.start + i).collect();
        }
        let mut out = Vec::new();
        let mut at = self.start;
        for _ in 0..self.len {
            out.push(at);
            // Down the byte, then to the next byte's highest bit.
            at = if at.is_multiple_of(8) {
                at + 15
            } else {
                at - 1
            };
        }
        out
    }
}

/// A DBC's messages: id → (length, sender, signals).
type Dbc = BTreeMap<u16, (u8, String, Vec<Signal>)>;

fn parse_dbc(text: &str) -> Dbc {
    let mut out = BTreeMap::new();
    let mut current: Option<u16> = None;
    for line in text.lines() {
        let t = line.trim();
        if let Some(rest) = t.strip_prefix("BO_ ") {
            let mut it = rest.split_whitespace();
            let id: u16 = it.next().unwrap().parse().unwrap();
            let dlc: u8 = it.nth(1).unwrap().parse().unwrap();
            let sender = it.next().unwrap_or("").to_string();
            out.insert(id, (dlc, sender, Vec::new()));
            current = Some(id);
        } else if let Some(rest) = t.strip_prefix("SG_ ") {
            let (name, def) = rest.split_once(" : ").unwrap();
            let (pos, rest) = def.split_once('@').unwrap();
            let (start, len) = pos.split_once('|').unwrap();
            let big_endian = rest.starts_with('0');
            assert!(big_endian || rest.starts_with('1'), "byte order: {t}");
            let signed = rest[1..].starts_with('-');
            let scale = &rest[rest.find('(').unwrap() + 1..rest.find(')').unwrap()];
            let (factor, offset) = scale.split_once(',').unwrap();
            out.get_mut(&current.unwrap()).unwrap().2.push(Signal {
                name: name.trim().to_string(),
                start: start.parse().unwrap(),
                len: len.parse().unwrap(),
                big_endian,
                signed,
                factor: factor.parse().unwrap(),
                offset: offset.parse().unwrap(),
            });
        } else if t.is_empty() {
            current = None;
        }
    }
    out
}

fn decode(f: &CanFrame, s: &Signal) -> f64 {
    let raw = u64::from_le_bytes(f.data);
    let v = s
        .bits()
        .iter()
        .fold(0u64, |acc, &b| (acc << 1) | ((raw >> b) & 1));
    let v = if s.signed && v >> (s.len - 1) & 1 == 1 {
        v as i64 - (1i64 << s.len)
    } else {
        v as i64
    };
    v as f64 * s.factor + s.offset
}

/// The DBC's Motorola walk, checked on Growatt's own layout: 0x311's charge
/// voltage (start bit 7, 16 bits) is bytes 0-1, high byte first.
#[test]
fn a_big_endian_signal_reads_high_byte_first() {
    let s = Signal {
        name: "ChargeVoltageLimit".into(),
        start: 7,
        len: 16,
        big_endian: true,
        signed: false,
        factor: 0.1,
        offset: 0.0,
    };
    let f = CanFrame {
        id: 0x311,
        len: 8,
        data: [0x02, 0x28, 0, 0, 0, 0, 0, 0],
    };
    assert!((decode(&f, &s) - 55.2).abs() < 1e-9);
    assert_eq!(s.bits()[..3], [7, 6, 5]);
    assert_eq!(s.bits()[8], 15);
}

fn check_dbc(path: &str, sent: &[CanFrame], expect: &[(&str, f64)]) {
    let text = std::fs::read_to_string(path).unwrap();
    let dbc = parse_dbc(&text);
    let mut seen = Vec::new();
    for f in sent {
        let (dlc, _, signals) = dbc
            .get(&f.id)
            .unwrap_or_else(|| panic!("{:03X} not in {path}", f.id));
        assert_eq!(*dlc, f.len, "{:03X} length in {path}", f.id);
        // Every bit the encoder may set is described by some signal.
        let mut covered = 0u64;
        for s in signals {
            for b in s.bits() {
                covered |= 1 << b;
            }
        }
        let used = u64::from_le_bytes(f.data);
        assert_eq!(
            used & !covered,
            0,
            "{:03X}: undocumented bits in {path}",
            f.id
        );
        for s in signals {
            seen.push((s.name.clone(), decode(f, s)));
        }
    }
    for (name, want) in expect {
        let got = seen
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("{name} not in {path}"))
            .1;
        assert!(
            (got - want).abs() < 1e-6,
            "{name}: {got} != {want} ({path})"
        );
    }
    // No message of the DBC that the encoder never sends (the inverter's
    // own are the inverter's).
    for (id, (_, sender, _)) in &dbc {
        assert!(
            sender == "INVERTER" || sent.iter().any(|f| f.id == *id),
            "{id:03X} unused in {path}"
        );
    }
}

/// The frames of one slow period of `p`, as the dialect builds them for
/// the output: a cell at its ceiling the BMS tripped on (an alarm and a
/// protection), an imbalance warning, a full-charge request, two packs, 16
/// cells each.
fn period_frames(p: Protocol) -> Vec<CanFrame> {
    let l = Limits {
        cvl_dv: 568,
        ccl_da: 600,
        dcl_da: 1500,
        discharge_dv: 416,
    };
    let c = Conditions {
        high_voltage: 2,
        cell_imbalance: 1,
        ..Conditions::default()
    };
    let s = state();
    let settings = PackSettings {
        fully_charged_mv: 3650,
        capacity_cah: 28_000,
        cells: 16,
        allowed_disbalance_mv: 15,
        ov_cutoff_mv: 3650,
        uv_cutoff_mv: 2800,
        discharge_cutoff_a: 200,
        charge_cutoff_a: 150,
        discharge_cutoff_s: 5,
        overheat_c: 60,
        low_temp_charge_c: 0,
    };
    let say = Say {
        protected: Protected {
            over_voltage: true,
            ..Protected::default()
        },
        full_charge: true,
        ..Say::plain(l, s.soc_pct)
    };
    let period = Period {
        say: &say,
        state: &s,
        conditions: &c,
        capacity_ah: 280,
        modules: (2, 0, 0, 0),
        firmware: 20,
        hardware: 1,
        slow: true,
        settings: Some(&settings),
    };
    p.frames(&period).to_vec()
}

fn lv_frames(p: Protocol) -> Vec<CanFrame> {
    period_frames(p)
}

fn frames_for(protocol: &str) -> Vec<CanFrame> {
    period_frames(Protocol::from_key(protocol).unwrap())
}

/// The values every Pylontech-family DBC decodes from [`lv_frames`].
const PYLON_FAMILY: [(&str, f64); 12] = [
    ("ChargeVoltageLimit", 56.8),
    ("ChargeCurrentLimit", 60.0),
    ("DischargeCurrentLimit", 150.0),
    ("StateOfCharge", 65.0),
    ("StateOfHealth", 97.0),
    ("BatteryCurrent", -25.5),
    ("ProtectionOverVoltage", 1.0),
    ("AlarmHighVoltage", 1.0),
    ("ModuleCount", 2.0),
    ("FullChargeRequest", 1.0),
    ("ChargeEnable", 1.0),
    ("DischargeEnable", 1.0),
];

#[test]
fn the_pylon_dbc_and_the_encoder_agree() {
    let mut want = PYLON_FAMILY.to_vec();
    // 52.91 V in 0.01 V; the mean of 24.5 and 27.0 °C; the discharge voltage
    // in bytes 6-7 of 0x351, as real Pylontech packs send it.
    want.extend([
        ("BatteryVoltage", 52.91),
        ("BatteryTemperature", 25.8),
        ("DischargeVoltage", 41.6),
    ]);
    check_dbc(
        concat!(env!("CARGO_MANIFEST_DIR"), "/can/tinybms-pylon.dbc"),
        &lv_frames(Protocol::Pylon),
        &want,
    );
}

#[test]
fn the_solark_dbc_and_the_encoder_agree() {
    let mut want = PYLON_FAMILY.to_vec();
    // The voltage in 0.1 V; the discharge voltage in 0x351; the bank.
    want.extend([
        ("BatteryVoltage", 52.9),
        ("DischargeVoltage", 41.6),
        ("BankCapacity", 280.0),
    ]);
    check_dbc(
        concat!(env!("CARGO_MANIFEST_DIR"), "/can/tinybms-solark.dbc"),
        &lv_frames(Protocol::SolArk),
        &want,
    );
}

#[test]
fn the_luxpower_dbc_and_the_encoder_agree() {
    let mut want = PYLON_FAMILY.to_vec();
    want.extend([
        ("BatteryVoltage", 52.91),
        ("DischargeVoltage", 41.6),
        ("MaxCellVoltage", 3312.0),
        ("MinCellVoltage", 3301.0),
        ("MaxCellTemperature", 27.0),
        ("MinCellTemperature", 24.5),
        ("Capacity", 280.0),
        ("CycleCount", 0.0),
    ]);
    check_dbc(
        concat!(env!("CARGO_MANIFEST_DIR"), "/can/tinybms-luxpower.dbc"),
        &lv_frames(Protocol::Luxpower),
        &want,
    );
}

#[test]
fn the_growatt_dbc_and_the_encoder_agree() {
    check_dbc(
        concat!(env!("CARGO_MANIFEST_DIR"), "/can/tinybms-growatt.dbc"),
        &lv_frames(Protocol::Growatt),
        &[
            ("ChargeVoltageLimit", 56.8),
            ("ChargeCurrentLimit", 60.0),
            ("DischargeCurrentLimit", 150.0),
            ("State", 3.0),
            ("ErrorBytesValid", 1.0),
            // An imbalance warning: "unbalance" (table 1: 1 balance).
            ("CellBalance", 0.0),
            ("ChargeEnabled", 1.0),
            ("DischargeEnabled", 1.0),
            ("BoxMode", 1.0),
            ("ProtectionCellOverVoltage", 1.0),
            ("AlarmCellOverVoltage", 1.0),
            ("AlarmCellImbalance", 1.0),
            ("PackCount", 2.0),
            ("TotalCellCount", 32.0),
            ("BatteryVoltage", 52.91),
            ("BatteryCurrent", -25.5),
            ("MaxCellTemperature", 27.0),
            ("StateOfCharge", 65.0),
            ("StateOfHealth", 97.0),
            ("FullChargeCapacity", 280.0),
            ("RemainingCapacity", 183.12),
            ("CellVoltageDelta", 11.0),
            ("MaxCellVoltage", 3312.0),
            ("MinCellVoltage", 3301.0),
            ("ChargeEnable", 1.0),
            ("BatteryType", 0.0),
            ("HardwareVersion", 1.0),
            ("DateTime", f64::from(0x6842_0000u32)),
            ("UpdateStatus", 0.0),
        ],
    );
}

#[test]
fn the_victron_dbc_and_the_encoder_agree() {
    check_dbc(
        concat!(env!("CARGO_MANIFEST_DIR"), "/can/tinybms-victron.dbc"),
        &frames_for("victron"),
        &[
            ("ChargeVoltageLimit", 56.8),
            ("ChargeCurrentLimit", 60.0),
            ("DischargeCurrentLimit", 150.0),
            ("DischargeVoltage", 41.6),
            ("StateOfCharge", 65.0),
            ("StateOfHealth", 97.0),
            ("StateOfChargeHighRes", 65.4),
            ("BatteryVoltage", 52.91),
            ("BatteryCurrent", -25.5),
            ("BatteryTemperature", 27.0),
            ("AlarmHighVoltage", 1.0),
            ("AlarmLowVoltage", 2.0),
            ("AlarmContactor", 0.0),
            ("WarningCellImbalance", 1.0),
            ("AlarmCellImbalance", 2.0),
            ("SystemOffline", 2.0),
            ("FirmwareVersion", 20.0),
            ("OnlineCapacity", 280.0),
            ("ModulesOnline", 2.0),
            ("MinCellVoltage", 3.301),
            ("MaxCellVoltage", 3.312),
            ("MaxCellTemperature", 300.0 - 273.15),
            ("InstalledCapacity", 280.0),
        ],
    );
}

#[test]
fn the_sma_dbc_and_the_encoder_agree() {
    check_dbc(
        concat!(env!("CARGO_MANIFEST_DIR"), "/can/tinybms-sma.dbc"),
        &frames_for("sma"),
        &[
            ("ChargeVoltageLimit", 56.8),
            ("ChargeCurrentLimit", 60.0),
            ("DischargeCurrentLimit", 150.0),
            // Discharging 25.5 A: positive to the Sunny Island.
            ("BatteryCurrent", 25.5),
            ("AlarmHighVoltage", 1.0),
            ("AlarmGeneral", 1.0),
            ("WarningCellImbalance", 1.0),
            ("AlarmCellImbalance", 0.0),
            ("Chemistry", f64::from(u16::from_le_bytes(*b"Li"))),
            ("Capacity", 280.0),
            ("SoftwareVersion", 20.0),
        ],
    );
}

// ---------------------------------------------------------------------------
// Properties of charge control.
// ---------------------------------------------------------------------------

fn arb_settings() -> impl Strategy<Value = PackSettings> {
    (
        1u16..=16,
        2000u16..3200,
        300u16..1500,
        1u16..750,
        1u16..750,
        40i16..90,
        -40i16..10,
    )
        .prop_map(|(cells, uv, span, doc, coc, hot, cold)| {
            let ov = (uv + span).min(4500);
            PackSettings {
                fully_charged_mv: ov,
                capacity_cah: 10000,
                cells,
                allowed_disbalance_mv: 20,
                ov_cutoff_mv: ov,
                uv_cutoff_mv: uv,
                discharge_cutoff_a: doc,
                charge_cutoff_a: coc,
                discharge_cutoff_s: 5,
                overheat_c: hot,
                low_temp_charge_c: cold,
            }
        })
}

fn arb_state(s: PackSettings) -> impl Strategy<Value = PackState> {
    let (lo, hi) = (
        i32::from(s.uv_cutoff_mv) - 300,
        i32::from(s.ov_cutoff_mv) + 300,
    );
    (
        lo..hi,
        0i32..200,
        -200.0f32..200.0,
        0.0f32..100.0,
        -30.0f32..80.0,
        any::<bool>(),
    )
        .prop_map(move |(min, spread, i, soc, t, fault)| {
            let min = min.max(0) as u16;
            let max = min.saturating_add(spread as u16);
            PackState {
                min_cell_mv: min,
                max_cell_mv: max,
                pack_v: f32::from(min) * f32::from(s.cells) / 1000.0,
                current_a: i,
                soc_pct: soc,
                soh_pct: 100.0,
                min_temp_c: t,
                max_temp_c: t + 2.0,
                fault,
                charge_blocked: false,
                balancing: 0,
            }
        })
}

proptest! {
    #[test]
    fn cvl_is_never_0_always_cell_count_scaled_and_limits_within_caps(
        (s, states) in arb_settings().prop_flat_map(|s| (Just(s), proptest::collection::vec(arb_state(s), 1..40))),
        cap in proptest::option::of(1u16..5000),
        (ccl_taper, dcl_taper, temp_margin, ov_margin) in (0u16..300, 0u16..300, -10i16..15, 0u16..200),
    ) {
        // Any configuration, zero and negative widths included: the safety rules
        // hold whatever the user typed.
        let config = ChargeConfig {
            charge_current_cap_da: cap,
            discharge_current_cap_da: cap,
            charge_taper_mv: ccl_taper,
            discharge_taper_mv: dcl_taper,
            temperature_margin_c: temp_margin,
            ceiling_margin_mv: ov_margin,
            ..ChargeConfig::default()
        };
        let mut c = ChargeControl::new(config);
        let n = u32::from(s.cells);
        for (k, p) in states.iter().enumerate() {
            let (l, _) = c.update(k as u64 * S, &s, p);
            prop_assert!(l.cvl_dv > 0);
            let cvl_mv = u32::from(l.cvl_dv) * 100;
            // Within cells × [316, 315] (0.1 V resolution).
            prop_assert!(cvl_mv + 100 > n * u32::from(s.uv_cutoff_mv), "{:?}", l);
            prop_assert!(cvl_mv <= n * u32::from(s.ov_cutoff_mv), "{:?}", l);
            let ccl_max = (u32::from(s.charge_cutoff_a) * 10).min(u32::from(cap.unwrap_or(u16::MAX)));
            let dcl_max = (u32::from(s.discharge_cutoff_a) * 10).min(u32::from(cap.unwrap_or(u16::MAX)));
            prop_assert!(u32::from(l.ccl_da) <= ccl_max);
            prop_assert!(u32::from(l.dcl_da) <= dcl_max);
            if p.fault {
                prop_assert_eq!((l.ccl_da, l.dcl_da), (0, 0));
            }
            // The ceiling: a cell at or above 315 - margin gets no charge current.
            if p.max_cell_mv + config.ceiling_margin_mv >= s.ov_cutoff_mv {
                prop_assert_eq!(l.ccl_da, 0);
            }
            if p.min_temp_c <= f32::from(s.low_temp_charge_c) || p.max_temp_c >= f32::from(s.overheat_c) {
                prop_assert_eq!(l.ccl_da, 0);
            }
            if p.max_temp_c >= f32::from(s.overheat_c) {
                prop_assert_eq!(l.dcl_da, 0);
            }
            // Discharge stops at or below 316 + margin.
            if p.min_cell_mv <= s.uv_cutoff_mv + config.discharge_margin_mv {
                prop_assert_eq!(l.dcl_da, 0);
            }
        }
    }

    #[test]
    fn tapers_are_monotonic(s in arb_settings(), a in 0u16..5000, b in 0u16..5000, t in -20.0f32..70.0) {
        // Fresh controllers (no ramp history): CCL never rises when the highest
        // cell is higher; DCL never falls when the lowest cell is higher.
        let (lo, hi) = (a.min(b), a.max(b));
        let p = |min: u16, max: u16| PackState {
            min_cell_mv: min, max_cell_mv: max,
            pack_v: f32::from(min) * f32::from(s.cells) / 1000.0,
            current_a: 0.0, soc_pct: 50.0, soh_pct: 100.0,
            min_temp_c: t, max_temp_c: t, fault: false, charge_blocked: false, balancing: 0,
        };
        let ccl = |max: u16| ChargeControl::new(ChargeConfig::default()).update(0, &s, &p(max, max)).0.ccl_da;
        let dcl = |min: u16| ChargeControl::new(ChargeConfig::default()).update(0, &s, &p(min, min)).0.dcl_da;
        prop_assert!(ccl(hi) <= ccl(lo));
        prop_assert!(dcl(hi) >= dcl(lo));
        // Temperature: warmer never means less charge below 25 °C, never more above.
        let at = |temp: f32| {
            let q = PackState { min_temp_c: temp, max_temp_c: temp, ..p(3300, 3300) };
            ChargeControl::new(ChargeConfig::default()).update(0, &s, &q).0.ccl_da
        };
        prop_assert!(at(t.min(25.0)) <= at(t.min(25.0) + 1.0) || t.min(25.0) + 1.0 > 25.0);
        prop_assert!(at(t.max(25.0)) >= at(t.max(25.0) + 1.0));
    }

    #[test]
    fn cvl_rises_at_most_once_per_20_s(steps in proptest::collection::vec((3000u16..3700, 0u64..5), 2..80)) {
        let s = lfp_settings();
        let mut c = ChargeControl::new(ChargeConfig::default());
        let mut now = 0u64;
        let mut last: Option<(u16, u64)> = None;
        let mut last_rise: Option<u64> = None;
        for (max, dt) in steps {
            now += dt * S;
            let st = PackState { max_cell_mv: max, min_cell_mv: 3300, pack_v: 52.8, ..state() };
            let (l, _) = c.update(now, &s, &st);
            if let Some((prev, _)) = last {
                if l.cvl_dv > prev {
                    if let Some(r) = last_rise {
                        prop_assert!(now - r >= 20 * S, "rise at {} after {}", now, r);
                    }
                    last_rise = Some(now);
                }
            }
            last = Some((l.cvl_dv, now));
        }
    }
}

/// The pack summaries' DBC (`host-tests/can/tinybms-packs.dbc`) describes
/// exactly what the encoder sends: every id of the 8 nodes, every bit, every
/// value.
#[test]
fn the_pack_summary_dbc_describes_the_encoder() {
    use tinybms_firmware::inverter::packs::Summary;
    let s = Summary {
        current_da: -1234,
        min_temp_dc: -52,
        max_temp_dc: 318,
        conditions: Conditions {
            high_voltage: 1,
            low_temperature: 2,
            high_charge_current: 1,
            bms_internal: 2,
            cell_imbalance: 1,
            ..Conditions::default()
        },
        fault: true,
        speaking: true,
        ..host_tests::fixtures::pack_summary()
    };
    let expect = [
        ("Voltage", 53.21),
        ("Current", -123.4),
        ("StateOfCharge", 65.43),
        ("StateOfHealth", 97.0),
        ("Sequence", 9.0),
        ("Speaking", 1.0),
        ("Fault", 1.0),
        ("ChargeBlocked", 0.0),
        ("MinCellVoltage", 3301.0),
        ("MaxCellVoltage", 3345.0),
        ("MinTemperature", -5.2),
        ("DataAge", 0.7),
        ("MaxTemperature", 31.8),
        ("Capacity", 280.0),
        ("DischargeVoltage", 48.0),
        ("HighVoltage", 1.0),
        ("LowVoltage", 0.0),
        ("HighTemperature", 0.0),
        ("LowTemperature", 2.0),
        ("ChargeVoltageLimit", 55.2),
        ("ChargeCurrentLimit", 58.8),
        ("DischargeCurrentLimit", 117.6),
        ("HighTemperatureCharge", 0.0),
        ("LowTemperatureCharge", 0.0),
        ("HighDischargeCurrent", 0.0),
        ("HighChargeCurrent", 1.0),
        ("BmsInternal", 2.0),
        ("CellImbalance", 1.0),
    ];
    let sent: Vec<CanFrame> = (1..=8).flat_map(|n| s.frames(n, 9).unwrap()).collect();
    check_dbc(
        concat!(env!("CARGO_MANIFEST_DIR"), "/can/tinybms-packs.dbc"),
        &sent,
        &expect,
    );
}

// ---------------------------------------------------------------------------
// Why each limit is what it is.
// ---------------------------------------------------------------------------

/// The rule charge control names for each limit is the one that set it, with
/// the numbers that set it: the base (the BMS's cutoff less the margin, or
/// the owner's cap), the taper that cuts deepest, a fault, a latched cutoff,
/// the ramp back; CVL's target, a runner, the cutoff bounds.
#[test]
fn the_reason_of_each_limit_is_the_rule_that_set_it() {
    use tinybms_firmware::inverter::why::Why;
    let s = lfp_settings();
    let first = |config: ChargeConfig, p: PackState| {
        let mut c = ChargeControl::new(config);
        let (l, _) = c.update(0, &s, &p);
        (l, c.reasons())
    };
    // At rest in the middle: the BMS's cutoffs less 20 %, absorption's CVL.
    let (l, r) = first(ChargeConfig::default(), state());
    let margin = ChargeConfig::default().current_margin_pct;
    assert_eq!(
        r.ccl,
        Why::Cutoff {
            cutoff_a: 90,
            margin_pct: margin
        }
    );
    assert_eq!(u32::from(l.ccl_da), 900 * (100 - u32::from(margin)) / 100);
    assert_eq!(
        r.dcl,
        Why::Cutoff {
            cutoff_a: 150,
            margin_pct: margin
        }
    );
    assert!(matches!(r.cvl, Why::Absorption { cells: 16, .. }), "{r:?}");
    // The owner's cap below the cutoff's.
    let capped = ChargeConfig {
        charge_current_cap_da: Some(400),
        ..ChargeConfig::default()
    };
    let (l, r) = first(capped, state());
    assert_eq!((r.ccl, l.ccl_da), (Why::OwnerCap { cap_da: 400 }, 400));
    // A cell near the top tapers the charge, a cold pack too: the deeper
    // taper is the reason.
    let high = PackState {
        max_cell_mv: 3590,
        ..state()
    };
    let (_, r) = first(ChargeConfig::default(), high);
    assert!(
        matches!(r.ccl, Why::CellHigh { cell_mv: 3590, .. }),
        "{r:?}"
    );
    // (The cell 40 mV below the stop: 40 % of the charge; 0.5 °C above the
    // cold cutoff: 10 %.)
    let cold_and_high = PackState {
        min_temp_c: 0.5,
        max_cell_mv: 3560,
        ..state()
    };
    let (_, r) = first(ChargeConfig::default(), cold_and_high);
    assert!(
        matches!(
            r.ccl,
            Why::Cold {
                temp_dc: 5,
                cutoff_c: 0
            }
        ),
        "{r:?}"
    );
    // A cell near the bottom tapers the discharge.
    let low = PackState {
        min_cell_mv: 2600,
        ..state()
    };
    let (_, r) = first(ChargeConfig::default(), low);
    assert!(matches!(r.dcl, Why::CellLow { cell_mv: 2600, .. }), "{r:?}");
    // A fault: both 0 for it; a latched charge cutoff: the charge.
    let (l, r) = first(
        ChargeConfig::default(),
        PackState {
            fault: true,
            ..state()
        },
    );
    assert_eq!((l.ccl_da, l.dcl_da), (0, 0));
    assert_eq!((r.ccl, r.dcl), (Why::BmsFault, Why::BmsFault));
    let (_, r) = first(
        ChargeConfig::default(),
        PackState {
            charge_blocked: true,
            ..state()
        },
    );
    assert_eq!(r.ccl, Why::ChargeBlocked);
    // After the fault clears: held, then ramping back to the target.
    let mut c = ChargeControl::new(ChargeConfig::default());
    c.update(
        0,
        &s,
        &PackState {
            fault: true,
            ..state()
        },
    );
    let (l, _) = c.update(32 * S, &s, &state());
    assert!(l.ccl_da > 0, "{l:?}");
    assert!(
        matches!(c.reasons().ccl, Why::Ramp { target_da } if target_da > l.ccl_da),
        "{:?}",
        c.reasons()
    );
    // A runner: CVL lowered, named with the runner's voltage.
    let mut c = ChargeControl::new(ChargeConfig::default());
    let target = c.targets_mv(&s).0;
    let runner = PackState {
        max_cell_mv: target + 40,
        pack_v: 16.0 * f32::from(target - 30) / 1000.0,
        current_a: 20.0,
        ..state()
    };
    c.update(0, &s, &runner);
    assert!(
        matches!(c.reasons().cvl, Why::Runner { cell_mv, offset_mv } if cell_mv == target + 40 && offset_mv > 0),
        "{:?}",
        c.reasons()
    );
}
