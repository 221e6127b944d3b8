//! The inverter output's scheduler through its sans-IO interface: what goes on
//! the bus, when, and what is logged.

use host_tests::sim::{PackModel, SimBms, SimConfig};
use protocol_core::response::RegisterBlock;
use protocol_core::views::LiveSnapshot;
use tinybms_firmware::inverter::control::PackSettings;
use tinybms_firmware::inverter::dialect::victron as frames;
use tinybms_firmware::inverter::{
    Inverter, InverterAction, InverterConfig, InverterReport, Protocol, TxResult,
};

const S: u64 = 1_000_000;

fn inputs() -> (LiveSnapshot, PackSettings) {
    let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 1);
    let block = |first: u16, n: u16| RegisterBlock {
        start: first,
        values: (first..first + n).map(|a| sim.register(a)).collect(),
    };
    let snap = LiveSnapshot::from_registers(&block(0, 56)).unwrap();
    let settings = PackSettings::from_registers(&block(300, 44)).unwrap();
    (snap, settings)
}

/// Runs the output for `secs`, feeding a fresh snapshot each second and
/// acknowledging every frame with `tx`; returns the frames sent and the reports.
fn run(
    config: InverterConfig,
    secs: u64,
    mut tx: impl FnMut(u64) -> TxResult,
    keepalive: impl Fn(u64) -> bool,
) -> (Vec<(u64, u16)>, Vec<InverterReport>) {
    let (snap, settings) = inputs();
    let mut inv = Inverter::new(config, 0);
    let mut sent = Vec::new();
    let mut reports = Vec::new();
    let mut now = 0u64;
    while now < secs * S {
        if now.is_multiple_of(S) {
            inv.on_snapshot(now, &snap, Some(settings), None);
            if keepalive(now) {
                inv.on_received(now, frames::ID_GX_KEEPALIVE_2, b"\x12\x34\x56\x78VIC\x00");
            }
        }
        match inv.poll(now) {
            InverterAction::Send(f) => {
                let r = tx(now);
                if r == TxResult::Sent {
                    sent.push((now, f.id));
                }
                inv.on_tx(now, r);
            }
            InverterAction::Recover => {}
            InverterAction::WaitUntil(t) => now = t.min((now / S + 1) * S),
        }
        while let Some(r) = inv.next_report() {
            reports.push(r);
        }
    }
    (sent, reports)
}

#[test]
fn victron_frames_go_out_at_their_periods() {
    let (sent, _) = run(InverterConfig::default(), 20, |_| TxResult::Sent, |_| true);
    let count = |id: u16| sent.iter().filter(|s| s.1 == id).count();
    for id in [0x351, 0x355, 0x356, 0x35A] {
        assert!((19..=21).contains(&count(id)), "{id:03X}: {}", count(id));
    }
    for id in [0x35E, 0x35F, 0x372, 0x373, 0x379] {
        assert!((4..=5).contains(&count(id)), "{id:03X}: {}", count(id));
    }
}

#[test]
fn sma_gets_only_its_frames() {
    let config = InverterConfig {
        protocol: Protocol::SmaSunnyIsland,
        ..InverterConfig::default()
    };
    let (sent, _) = run(config, 10, |_| TxResult::Sent, |_| false);
    let ids: std::collections::BTreeSet<u16> = sent.iter().map(|s| s.1).collect();
    assert_eq!(
        ids.into_iter().collect::<Vec<_>>(),
        vec![0x351, 0x355, 0x356, 0x35A, 0x35E, 0x35F]
    );
}

#[test]
fn can_output_switched_off_sends_nothing() {
    let config = InverterConfig {
        enabled: false,
        ..InverterConfig::default()
    };
    let (sent, reports) = run(config, 10, |_| TxResult::Sent, |_| true);
    assert!(sent.is_empty());
    assert!(reports.is_empty());
}

#[test]
fn the_gx_keepalive_is_seen_and_its_loss_logged_once() {
    let (_, reports) = run(
        InverterConfig::default(),
        30,
        |_| TxResult::Sent,
        |t| t < 10 * S,
    );
    let seen = reports
        .iter()
        .filter(|r| **r == InverterReport::InverterSeen)
        .count();
    let lost = reports
        .iter()
        .filter(|r| **r == InverterReport::InverterLost)
        .count();
    assert_eq!((seen, lost), (1, 1));
}

#[test]
fn no_other_node_is_logged_once_and_the_recovery_too() {
    // Nothing acknowledges for 20 s (no other node: error-passive), then it does.
    let (sent, reports) = run(
        InverterConfig::default(),
        40,
        |t| {
            if t < 20 * S {
                TxResult::Failed
            } else {
                TxResult::Sent
            }
        },
        |_| true,
    );
    let no_ack = reports
        .iter()
        .filter(|r| matches!(r, InverterReport::NoAck { .. }))
        .count();
    let ok = reports
        .iter()
        .filter(|r| **r == InverterReport::BusOk)
        .count();
    assert_eq!((no_ack, ok), (1, 1), "{reports:?}");
    // Failed frames are not retried late: fresh ones go out at the next period.
    assert!(sent.iter().all(|s| s.0 >= 20 * S));
    assert!(sent.len() > 50);
}

#[test]
fn nothing_is_sent_before_the_bms_said_anything() {
    let mut inv = Inverter::new(InverterConfig::default(), 0);
    for t in 0..10 {
        assert!(matches!(inv.poll(t * S), InverterAction::WaitUntil(_)));
    }
}

#[test]
fn repeated_bus_offs_back_off_longer() {
    let mut inv = Inverter::new(InverterConfig::default(), 0);
    let mut backoffs = Vec::new();
    for k in 0..6 {
        inv.on_bus_off(k * 100 * S);
        while let Some(r) = inv.next_report() {
            if let InverterReport::BusOff { backoff_ms, .. } = r {
                backoffs.push(backoff_ms);
            }
        }
    }
    assert_eq!(backoffs, vec![1000, 2000, 4000, 8000, 16000, 16000]);
    // During the backoff nothing is sent; then the controller is recovered.
    let t = 500 * S;
    assert!(matches!(inv.poll(t), InverterAction::WaitUntil(w) if w == t + 16 * S));
    assert_eq!(inv.poll(t + 16 * S), InverterAction::Recover);
}

#[test]
fn a_charge_side_fault_event_blocks_charging_until_its_own_recovery() {
    use protocol_core::events::{Event, EventId};
    let (snap, settings) = inputs();
    let mut inv = Inverter::new(InverterConfig::default(), 0);
    let ccl_at = |inv: &mut Inverter, t: u64| {
        inv.on_snapshot(t, &snap, Some(settings), None);
        while !matches!(inv.poll(t), InverterAction::WaitUntil(_)) {}
        inv.limits().unwrap().ccl_da
    };
    assert!(ccl_at(&mut inv, 0) > 0);
    let ev = |id| Event { timestamp_s: 1, id };
    // The status is not "fault" (the BMS already recovered its switches), yet
    // the over-voltage event blocks charging.
    inv.on_event(&ev(EventId::OverVoltageCutoff));
    assert_eq!(ccl_at(&mut inv, 2 * S), 0);
    // Another fault's recovery does not lift it...
    inv.on_event(&ev(EventId::RecoveredLowTemperatureFault));
    assert_eq!(ccl_at(&mut inv, 4 * S), 0);
    // ...its own does (then the hold and the ramp).
    inv.on_event(&ev(EventId::RecoveredOverVoltage));
    assert_eq!(ccl_at(&mut inv, 6 * S), 0, "held after the cut");
    assert!(ccl_at(&mut inv, 40 * S) > 0);
}

/// A configuration change while running: the protocol and on/off stay as the
/// output was started (they apply at the next restart); a new stale policy
/// given during stale data waits for the next stale episode — switching from
/// "stop" to "hold" mid-episode must not re-allow a discharge.
#[test]
fn reconfigure_keeps_the_protocol_and_defers_a_stale_policy_change() {
    use tinybms_firmware::inverter::StaleMode;
    let (snap, settings) = inputs();
    let stop = InverterConfig {
        protocol: Protocol::SmaSunnyIsland,
        stale_policy: StaleMode::Stop,
        ..InverterConfig::default()
    };
    let mut inv = Inverter::new(stop, 0);
    let frames_at = |inv: &mut Inverter, from: u64, to: u64, fresh: bool| {
        let mut out = Vec::new();
        let mut now = from;
        while now < to {
            if fresh && now.is_multiple_of(S) {
                inv.on_snapshot(now, &snap, Some(settings), None);
            }
            match inv.poll(now) {
                InverterAction::Send(f) => {
                    out.push(f);
                    inv.on_tx(now, TxResult::Sent);
                }
                InverterAction::Recover => {}
                InverterAction::WaitUntil(t) => now = t.min((now / S + 1) * S).max(now + 1),
            }
        }
        out
    };
    frames_at(&mut inv, 0, 10 * S, true);
    // Stale from 10 s on (no snapshot); at 20 s the owner switches to hold.
    frames_at(&mut inv, 10 * S, 20 * S, false);
    let hold = InverterConfig {
        protocol: Protocol::Victron,
        enabled: false,
        stale_policy: StaleMode::Hold,
        stale_hold_us: 600 * S,
        ..InverterConfig::default()
    };
    inv.reconfigure(hold);
    assert_eq!(inv.config().protocol, Protocol::SmaSunnyIsland);
    assert!(inv.config().enabled);
    assert_eq!(inv.config().stale_policy, StaleMode::Stop);
    // Still stale: SMA "stop" sends CCL 0 and DCL 0 — never the held DCL.
    for f in frames_at(&mut inv, 20 * S, 30 * S, false) {
        if f.id == frames::ID_LIMITS {
            assert_eq!(&f.data[2..6], &[0, 0, 0, 0], "{f:?}");
        }
    }
    // Fresh again: the new policy is in force for the next episode.
    frames_at(&mut inv, 30 * S, 40 * S, true);
    assert_eq!(inv.config().stale_policy, StaleMode::Hold);
    assert_eq!(inv.config().stale_hold_us, 600 * S);
    // A charge cap applies at once.
    let mut capped = *inv.config();
    capped.charge.charge_current_cap_da = Some(55);
    inv.reconfigure(capped);
    let after = frames_at(&mut inv, 40 * S, 45 * S, true);
    let ccl: Vec<u16> = after
        .iter()
        .filter(|f| f.id == frames::ID_LIMITS)
        .map(|f| u16::from_le_bytes([f.data[2], f.data[3]]))
        .collect();
    assert!(!ccl.is_empty() && ccl.iter().all(|&c| c <= 55), "{ccl:?}");
}

/// A 25 s loss of the BMS's data, then fresh data from a healthy battery
/// (issue 42: `sim --bridge-pty --bms-silent 8s+25s` kept DCL at 0 for 30 s
/// after the data was back, an island inverter off three times as long as the
/// glitch). Now, whatever the stale policy: DCL is back at once when the data
/// is, CCL ramps from 0 without the 30 s hold, and the ramp is logged a few
/// times rather than once a second. With the default policy (hold) DCL never
/// reaches 0 at all.
#[test]
fn after_a_loss_of_data_the_discharge_limit_is_back_at_once() {
    use tinybms_firmware::inverter::StaleMode;
    let (snap, settings) = inputs();
    for policy in [StaleMode::Hold, StaleMode::Stop] {
        let config = InverterConfig {
            stale_policy: policy,
            ..InverterConfig::default()
        };
        let mut inv = Inverter::new(config, 0);
        let mut limits = Vec::new();
        let mut logged = Vec::new();
        let mut now = 0u64;
        let (lost, back, end) = (8 * S, 33 * S, 120 * S);
        while now < end {
            if now.is_multiple_of(S) && (now < lost || now >= back) {
                inv.on_snapshot(now, &snap, Some(settings), None);
            }
            match inv.poll(now) {
                InverterAction::Send(f) => {
                    if f.id == frames::ID_LIMITS {
                        let dcl = u16::from_le_bytes([f.data[4], f.data[5]]);
                        let ccl = u16::from_le_bytes([f.data[2], f.data[3]]);
                        limits.push((now, ccl, dcl));
                    }
                    inv.on_tx(now, TxResult::Sent);
                }
                InverterAction::Recover => {}
                InverterAction::WaitUntil(t) => now = t.min((now / S + 1) * S).max(now + 1),
            }
            while let Some(r) = inv.next_report() {
                if let InverterReport::Limits(l) = r {
                    logged.push((now, l));
                }
            }
        }
        let before = limits.iter().rev().find(|(t, _, _)| *t < lost).unwrap();
        let (full_ccl, full_dcl) = (before.1, before.2);
        assert!(full_dcl > 0 && full_ccl > 0, "{policy:?}: {before:?}");
        // From one second after the data is back, DCL is the battery's.
        for (t, _, dcl) in limits.iter().filter(|(t, _, _)| *t >= back + S) {
            assert_eq!(*dcl, full_dcl, "{policy:?}: DCL at {} s", t / S);
        }
        if policy == StaleMode::Hold {
            assert!(
                limits.iter().all(|(_, _, dcl)| *dcl > 0),
                "hold: DCL never 0: {limits:?}"
            );
        }
        // CCL ramps from 0 at once (2 A/s), without waiting the 30 s hold.
        let ccl_at = |s: u64| {
            limits
                .iter()
                .rev()
                .find(|(t, _, _)| *t <= s * S)
                .map(|l| l.1)
                .unwrap()
        };
        assert!(ccl_at(35) > 0, "{policy:?}: CCL at 35 s: {}", ccl_at(35));
        assert_eq!(ccl_at(115), full_ccl, "{policy:?}: the ramp ends");
        // The recovery is logged a few times, not once a second.
        let recovery = logged.iter().filter(|(t, _)| *t >= back).count();
        assert!(
            (1..=6).contains(&recovery),
            "{policy:?}: {recovery} limits lines after the data came back: {logged:?}"
        );
    }
}
