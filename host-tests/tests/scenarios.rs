//! The firmware's bridge logic against the simulated TinyBMS, in virtual time: the
//! scenarios of the firmware issue. Each runs the real `tinybms_firmware::Bridge`
//! through `host_tests::virtual_time::Harness` (the same loop as the chip shell).

use host_tests::sim::{CurrentSensor, FaultConfig, PackModel, SimBms, SimConfig};
use host_tests::virtual_time::Harness;
use protocol_core::events::{EventId, OnlineStatus};
use protocol_core::settings::{Setting, SettingError, SettingId};
use tinybms_firmware::bridge::report::WriteOutcome;
use tinybms_firmware::{Command, Level, Report};

const S: u64 = 1_000_000;

fn harness(profile: PackModel, config: SimConfig, seed: u64) -> Harness {
    let mut sim = SimBms::new(profile, config, seed);
    sim.record_frames(true);
    Harness::checked(sim, tinybms_firmware::bms::timing::Timing::default())
}

fn writes(h: &Harness) -> Vec<(SettingId, i32, WriteOutcome)> {
    h.log
        .iter()
        .filter_map(|l| match &l.report {
            Report::Write { setting, outcome } => Some((setting.id, setting.value, *outcome)),
            _ => None,
        })
        .collect()
}

fn count(h: &Harness, f: impl Fn(&Report) -> bool) -> usize {
    h.log.iter().filter(|l| f(&l.report)).count()
}

fn group(items: &[(SettingId, i32)]) -> Command {
    Command::ApplySettings(
        items
            .iter()
            .map(|&(id, value)| Setting { id, value })
            .collect(),
        protocol_core::settings::ChemistryCheck::Inferred,
    )
}

fn write_requests(h: &Harness) -> u64 {
    let by = &h.sim.stats().requests_by_command;
    [0x0B, 0x0D, 0x10]
        .iter()
        .map(|c| by.get(c).copied().unwrap_or(0))
        .sum()
}

/// Every published value must be one the simulated BMS really sent (each value
/// of each snapshot, settings, limits, statistics and version block found in its
/// clean, pre-fault answers), and every write success held by its registers.
fn assert_published_are_genuine(h: &Harness) {
    let soak = h.soak.as_ref().unwrap();
    assert_eq!(soak.wrong, 0, "{:#?}", soak.wrong_examples);
    assert_eq!(soak.false_successes, 0, "{:#?}", soak.wrong_examples);
    assert_eq!(soak.published as usize, h.published.len());
    assert!(soak.blocks_checked > soak.published);
}

#[test]
fn cold_start_with_a_sleeping_bms() {
    let mut h = harness(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_start_asleep(true),
        1,
    );
    h.run_until(5 * S);
    let s = h.bridge().link_stats();
    assert_eq!(s.wakeup_resends, 1, "{s:?}");
    assert_eq!(h.sim.stats().wakeups, 1);
    assert_eq!(
        count(&h, |r| matches!(r, Report::Ready { series_cells: 16 })),
        1
    );
    assert_eq!(count(&h, |r| matches!(r, Report::Version(_))), 1);
    assert!(h.published.len() >= 18, "{}", h.published.len());
    assert_eq!(
        count(&h, |r| matches!(
            r,
            Report::LinkError { .. } | Report::Offline { .. }
        )),
        0
    );
    // Only the first request was sent twice: every other one once.
    assert_eq!(
        h.sim.stats().requests,
        u64::from(s.requests + s.wakeup_resends)
    );
    assert_eq!(s.retries, 0);
    assert_eq!(s.requests, s.replies);
    // Register 114's high byte says the UART woke it.
    assert_eq!(h.sim.register(114) >> 8, 0x03);
    assert_published_are_genuine(&h);
}

#[test]
fn an_awake_bms_gets_every_request_exactly_once() {
    let mut h = harness(PackModel::LiIon_14S, SimConfig::default(), 2);
    h.run_until(60 * S);
    let s = h.bridge().link_stats();
    assert_eq!(u64::from(s.requests), h.sim.stats().requests);
    assert_eq!(s.wakeup_resends + s.retries + s.timeouts, 0, "{s:?}");
    assert!(h.published.len() >= 235);
    // One snapshot line per 10 s (the default log period), on the grid.
    let lines: Vec<u64> = h
        .reports(|r| matches!(r, Report::Snapshot(_)))
        .map(|l| l.at_us)
        .collect();
    assert_eq!(lines.len(), 6, "{lines:?}");
    assert!(
        lines.windows(2).all(|w| w[1] - w[0] < 10_100_000),
        "{lines:?}"
    );
    // 14S pack, cells in registers 2-15.
    let (_, last) = h.published.last().unwrap();
    assert_eq!((last.cells.first_register, last.cells.raw.len()), (2, 14));
    let sum: f32 = last.cells.raw.iter().map(|&c| f32::from(c) * 1e-4).sum();
    assert!(
        (sum - last.pack_voltage_v).abs() < 0.01,
        "{sum} vs {}",
        last.pack_voltage_v
    );
    assert_eq!(last.external2_dc, None);
    // Snapshot age is known to readers.
    let t = h.bridge().telemetry();
    assert!(t.ready && t.online);
    assert!(t.snapshot_age_us(h.now).unwrap() <= 250_000);
    assert_published_are_genuine(&h);
}

#[test]
fn hours_of_polling_with_1_percent_byte_corruption() {
    let faults = FaultConfig {
        drop_byte: 0.005,
        bit_flip: 0.005,
        ..FaultConfig::NONE
    };
    let mut h = harness(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(faults),
        3,
    );
    h.run_until(2 * 3600 * S);
    let s = h.bridge().link_stats();
    // The line really was bad, and the link recovered every time.
    assert!(h.sim.stats().faults.bit_flips > 10_000 && h.sim.stats().faults.dropped_bytes > 10_000);
    assert!(
        s.crc_errors > 5_000 && s.framing_errors > 5_000 && s.retries > 10_000,
        "{s:?}"
    );
    assert!(s.skipped_bytes > 100_000);
    // Corruption is not absence: never offline.
    assert_eq!(count(&h, |r| matches!(r, Report::Offline { .. })), 0);
    // Still a steady flow of snapshots (at least 1.5 per second of the 4 asked).
    assert!(
        h.published.len() > 2 * 3600 * 3 / 2,
        "{}",
        h.published.len()
    );
    // Link errors are logged, but rate-limited: the log stays readable.
    let errors = count(&h, |r| matches!(r, Report::LinkError { .. }));
    assert!(errors > 0 && errors <= 2 * 360 + 1, "{errors}");
    // And never a wrong value.
    assert_published_are_genuine(&h);
    // The statistics line went out periodically.
    assert!(count(&h, |r| matches!(r, Report::LinkStats(_))) >= 23);
}

#[test]
fn bms_silent_for_10_s_then_back() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 4);
    h.run_until(10 * S);
    let before = h.published.len();
    let version_reads = h
        .sim
        .stats()
        .requests_by_command
        .get(&0x03)
        .copied()
        .unwrap_or(0);
    h.sim.set_silent_until(20 * S);
    h.run_until(30 * S);
    let offline: Vec<_> = h
        .reports(|r| matches!(r, Report::Offline { .. }))
        .map(|l| l.at_us)
        .collect();
    let online: Vec<_> = h
        .reports(|r| matches!(r, Report::Online))
        .map(|l| l.at_us)
        .collect();
    assert_eq!(offline.len(), 1, "offline logged once");
    assert_eq!(online.len(), 1);
    // Three silent transactions (each: send, wake-up resend, 2 retries) in ~3 s.
    assert!(offline[0] > 10 * S && offline[0] < 15 * S, "{}", offline[0]);
    assert!(online[0] >= 20 * S && online[0] < 23 * S, "{}", online[0]);
    // Nothing published while silent.
    assert!(h
        .published
        .iter()
        .all(|(t, _)| *t < 10 * S || *t > online[0]));
    // On reconnection: version and settings re-read before trusting anything.
    let after: Vec<&Report> = h
        .log
        .iter()
        .filter(|l| l.at_us >= online[0])
        .map(|l| &l.report)
        .collect();
    let ready = after
        .iter()
        .position(|r| matches!(r, Report::Ready { .. }))
        .unwrap();
    let version = after
        .iter()
        .position(|r| matches!(r, Report::Version(_)))
        .unwrap();
    assert!(version < ready);
    let first_published_after = h.published.iter().find(|(t, _)| *t > online[0]).unwrap().0;
    let ready_at = h
        .log
        .iter()
        .filter(|l| l.at_us >= online[0])
        .nth(ready)
        .unwrap()
        .at_us;
    assert!(first_published_after >= ready_at);
    assert!(h.published.len() > before + 30);
    assert!(h.sim.stats().requests_by_command[&0x03] > version_reads);
    // While offline it probed slowly (every 2 s), not at the live rate.
    let probes_while_silent = h.bridge().link_stats().wakeup_resends;
    assert!(probes_while_silent < 20, "{probes_while_silent}");
    assert!(h.bridge().telemetry().online && h.bridge().telemetry().ready);
    assert_published_are_genuine(&h);
}

#[test]
fn ascii_broadcasts_on() {
    let mut h = harness(PackModel::LiIon_14S, SimConfig::default(), 5);
    h.sim.set_register(342, 0x01); // every 0.1 s
    h.sim.set_register(343, 0x01); // ASCII
    h.run_until(60 * S);
    assert!(
        h.sim.stats().broadcasts > 500,
        "{}",
        h.sim.stats().broadcasts
    );
    let s = h.bridge().link_stats();
    assert!(s.skipped_bytes > 20_000, "{s:?}");
    assert_eq!(s.crc_errors + s.framing_errors + s.failures, 0, "{s:?}");
    assert!(h.published.len() >= 235);
    assert_eq!(count(&h, r_level_warn), 0, "{}", h.log_text());
    assert_published_are_genuine(&h);
}

fn r_level_warn(r: &Report) -> bool {
    r.level() == Level::Warn
}

#[test]
fn a_settings_profile_is_applied_and_verified() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 6);
    // 330: charger type (low byte) and over-current timeout (high byte) share a register.
    h.sim.set_register(330, 0x0A01);
    let profile = [
        (SettingId::OverVoltageCutoff, 3700),
        (SettingId::UnderVoltageCutoff, 2600),
        (SettingId::ChargerType, 0),
        (SettingId::BroadcastTime, 0x04),
        (SettingId::StateOfCharge, 40_000), // 80 %: reads back 0xFFFF when accepted
        (SettingId::PulsesPerUnit, 70_000), // 32 bits over 312-313
        (SettingId::FullyChargedVoltage, h.sim.register(300) as i32), // already equal
    ];
    h.bridge_mut().submit_profile(&profile).unwrap();
    h.run_until(20 * S);
    let w = writes(&h);
    assert_eq!(w.len(), profile.len(), "{}", h.log_text());
    for (id, value, outcome) in &w {
        let expected = if *id == SettingId::FullyChargedVoltage {
            WriteOutcome::Unchanged
        } else {
            WriteOutcome::Verified
        };
        assert_eq!(*outcome, expected, "{id:?} = {value}");
    }
    assert_eq!(h.sim.register(315), 3700);
    assert_eq!(h.sim.register(316), 2600);
    assert_eq!(h.sim.register(330), 0x0A00, "high byte (timeout) kept");
    assert_eq!(h.sim.register(342) & 0xFF, 0x04);
    assert_eq!(h.sim.register(328), 0xFFFF);
    assert_eq!(
        (h.sim.register(312), h.sim.register(313)),
        ((70_000 & 0xFFFF) as u16, 1)
    );
    // Settings re-read after the writes, and they show the new values; the
    // live data kept flowing meanwhile (no second sync, no second "ready").
    let settings = h.bridge().telemetry().settings.clone().unwrap();
    assert_eq!(settings.get(315), Some(3700));
    assert_eq!(count(&h, |r| matches!(r, Report::Ready { .. })), 1);
    // Five registers written: five writes, no more (the unchanged one was skipped).
    assert_eq!(write_requests(&h), 6);
}

#[test]
fn out_of_range_settings_are_rejected_before_any_byte() {
    let config = SimConfig::default().with_current_sensor(CurrentSensor::InternalResistor);
    let mut h = harness(PackModel::LiFePO4_16S, config, 7);
    h.run_until(S);
    let before = h.sim.stats().requests;
    let tx_before = h.tx_bytes;
    h.bridge_mut()
        .submit(group(&[
            (SettingId::OverVoltageCutoff, 4600),      // Rev D: 1200..=4500
            (SettingId::PrechargePin, 0x01),           // not an option of Rev D
            (SettingId::ChargeOverCurrentCutoff, 200), // Rev D allows, this BMS's max is 60 A
        ]))
        .unwrap();
    // Run just long enough for the bridge to take the command, not for a live poll.
    h.run_until(S + 1);
    let w = writes(&h);
    assert_eq!(w.len(), 3);
    assert!(matches!(
        w[0].2,
        WriteOutcome::Rejected(SettingError::OutOfRange {
            min: 1200,
            max: 4500,
            ..
        })
    ));
    assert!(matches!(
        w[1].2,
        WriteOutcome::Rejected(SettingError::NotAnOption { .. })
    ));
    assert!(matches!(
        w[2].2,
        WriteOutcome::Rejected(SettingError::OutsideBmsLimits { max: 60, .. })
    ));
    assert_eq!(h.sim.stats().requests, before);
    assert_eq!(h.tx_bytes, tx_before);
    h.run_until(5 * S);
    assert_eq!(write_requests(&h), 0);
    assert_eq!(
        count(
            &h,
            |r| matches!(r, Report::Write { .. } if r.level() == Level::Warn)
        ),
        3
    );
}

#[test]
fn a_read_back_mismatch_is_reported_as_such() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 8);
    h.sim.ignore_writes_to(308);
    let old = h.sim.register(308);
    h.bridge_mut()
        .submit(group(&[(SettingId::AllowedDisbalance, 30)]))
        .unwrap();
    h.run_until(5 * S);
    assert_eq!(
        writes(&h),
        vec![(
            SettingId::AllowedDisbalance,
            30,
            WriteOutcome::Mismatch { read_back: old }
        )]
    );
    assert_eq!(
        write_requests(&h),
        1,
        "written once, never re-sent after the echo"
    );
}

#[test]
fn a_nacked_write_is_reported_with_its_code() {
    // The bridge read the limits with an external sensor (max 750 A); the sensor
    // then changes and the BMS now refuses 200 A itself.
    let config = SimConfig::default().with_current_sensor(CurrentSensor::External);
    let mut h = harness(PackModel::LiFePO4_16S, config, 9);
    h.run_until(S);
    h.sim.config_mut().current_sensor = CurrentSensor::InternalResistor;
    let old = h.sim.register(318);
    h.bridge_mut()
        .submit(group(&[(SettingId::ChargeOverCurrentCutoff, 200)]))
        .unwrap();
    h.run_until(3 * S);
    assert_eq!(
        writes(&h),
        vec![(
            SettingId::ChargeOverCurrentCutoff,
            200,
            WriteOutcome::Nacked(protocol_core::frame::NackCode::CommandError)
        )]
    );
    assert_eq!(write_requests(&h), 1, "never re-sent after a NACK");
    assert_eq!(h.sim.register(318), old);
    // The limits were re-read after the attempt: the bridge now knows 60 A.
    let max = h.bridge().telemetry().limits_max.clone().unwrap();
    assert_eq!(SettingId::ChargeOverCurrentCutoff.read(&max), Some(60));
}

#[test]
fn a_write_to_340_waits_for_the_reboot_and_confirms() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 10);
    h.run_until(2 * S);
    let old = h.sim.register(340) & 0xFF;
    let new = if old == 0 { 1 } else { 0 };
    h.bridge_mut()
        .submit(group(&[(SettingId::OperationMode, i32::from(new))]))
        .unwrap();
    h.run_until(12 * S);
    assert_eq!(
        writes(&h),
        vec![(
            SettingId::OperationMode,
            i32::from(new),
            WriteOutcome::Verified
        )]
    );
    assert_eq!(h.sim.stats().reboots, 1);
    assert_eq!(h.sim.register(340) & 0xFF, new);
    // The restart is visible: "System Started" logged as a new event, version re-read.
    assert!(
        count(
            &h,
            |r| matches!(r, Report::NewEvent(e) if e.id == EventId::SystemStarted && e.timestamp_s > 0)
        ) >= 1
    );
    assert_eq!(count(&h, |r| matches!(r, Report::Version(_))), 2);
    assert_eq!(count(&h, |r| matches!(r, Report::Offline { .. })), 0);
    assert_published_are_genuine(&h);
}

#[test]
fn a_reset_gets_no_ack_and_is_confirmed() {
    let mut h = harness(PackModel::LiIon_14S, SimConfig::default(), 11);
    h.run_until(2 * S);
    h.bridge_mut().submit(Command::ResetBms).unwrap();
    h.run_until(12 * S);
    assert_eq!(h.sim.stats().reboots, 1);
    assert_eq!(
        h.sim.stats().requests_by_command.get(&0x02),
        Some(&1),
        "reset sent once"
    );
    assert_eq!(
        count(&h, |r| matches!(r, Report::ResetDone { confirmed: true })),
        1
    );
    // Silence after a reset is normal: no link error, no offline.
    assert_eq!(
        count(&h, |r| r.level() == Level::Warn),
        0,
        "{}",
        h.log_text()
    );
    assert_eq!(count(&h, |r| matches!(r, Report::Ready { .. })), 2);
    assert!(h.published.iter().any(|(t, _)| *t > 8 * S));
}

#[test]
fn clear_events_and_statistics() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 12);
    h.run_until(2 * S);
    h.bridge_mut().submit(Command::ClearEvents).unwrap();
    h.bridge_mut().submit(Command::ClearStatistics).unwrap();
    h.run_until(4 * S);
    assert_eq!(
        count(&h, |r| matches!(r, Report::Cleared { ok: true, .. })),
        2
    );
    assert!(h.sim.events().is_empty());
}

#[test]
fn faults_are_warnings_and_events_are_logged_once() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 13);
    h.run_until(10 * S);
    // The log's history at start-up is one info line, not a burst of old events.
    assert!(matches!(
        h.log
            .iter()
            .find(|l| matches!(l.report, Report::EventHistory { .. }))
            .map(|l| (&l.report, l.level)),
        Some((
            Report::EventHistory {
                count: 1..,
                newest: Some(_)
            },
            Level::Info
        ))
    ));
    assert_eq!(count(&h, |r| matches!(r, Report::EventHistory { .. })), 1);
    let events_before = count(&h, |r| matches!(r, Report::NewEvent(_)));
    assert_eq!(events_before, 0);
    h.sim.inject_fault_event(EventId::OverTemperatureCutoff);
    h.run_until(20 * S);
    h.sim.clear_fault();
    h.run_until(40 * S);
    let lines: Vec<_> = h.log.iter().filter(|l| l.at_us > 10 * S).collect();
    let fault_status = lines
        .iter()
        .find(|l| {
            matches!(
                l.report,
                Report::StatusChanged {
                    to: OnlineStatus::Fault,
                    ..
                }
            )
        })
        .unwrap();
    assert_eq!(fault_status.level, Level::Warn);
    let fault_event = lines
        .iter()
        .filter(
            |l| matches!(l.report, Report::NewEvent(e) if e.id == EventId::OverTemperatureCutoff),
        )
        .collect::<Vec<_>>();
    assert_eq!(fault_event.len(), 1, "logged once");
    assert_eq!(fault_event[0].level, Level::Warn);
    assert!(lines.iter().any(
        |l| matches!(l.report, Report::NewEvent(e) if e.id == EventId::RecoveredOverTemperature)
    ));
    assert!(lines.iter().any(|l| matches!(
        l.report,
        Report::StatusChanged {
            from: Some(OnlineStatus::Fault),
            ..
        }
    )));
    // Polling events every 5 s for 30 s did not log old events again.
    let total = count(&h, |r| matches!(r, Report::NewEvent(_)));
    assert_eq!(total, events_before + 2, "{}", h.log_text());
}

#[test]
fn faults_of_every_kind_never_publish_a_wrong_value() {
    let faults = FaultConfig {
        drop_byte: 0.002,
        bit_flip: 0.002,
        truncate: 0.02,
        no_reply: 0.02,
        duplicate: 0.02,
        delay: 0.02,
        delay_us: 150_000,
        ..FaultConfig::NONE
    };
    let config = SimConfig::default()
        .with_faults(faults)
        .with_sleep_after_us(Some(20 * S));
    let mut h = harness(PackModel::LiIon_14S, config, 14);
    h.sim.set_register(342, 0x03);
    h.sim.set_register(343, 0x01);
    h.bridge_mut()
        .submit(group(&[
            (SettingId::OverVoltageCutoff, 4150),
            (SettingId::ChargerType, 1),
        ]))
        .unwrap();
    h.run_until(20 * 60 * S);
    let f = h.sim.stats().faults;
    assert!(
        f.duplicated > 0 && f.delayed > 0 && f.truncated > 0 && f.no_reply > 0,
        "{f:?}"
    );
    assert!(h.bridge().link_stats().unsolicited > 0);
    for (id, _, outcome) in writes(&h) {
        // Success only with a matching read-back; the sim holds what was reported.
        if outcome == WriteOutcome::Verified {
            let r = h.sim.register(id.address());
            assert!(Setting {
                id,
                value: if id == SettingId::ChargerType {
                    1
                } else {
                    4150
                }
            }
            .matches_readback(r, None));
        }
    }
    assert!(h.published.len() > 20 * 60 * 3);
    assert_published_are_genuine(&h);
}

#[test]
fn a_lost_write_to_328_is_not_verified_by_its_marker() {
    // 328 already reads 0xFFFF before the write; the write (0x10) is lost on every
    // attempt, so the 0xFFFF read back afterwards proves nothing.
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 15);
    h.run_until(S);
    assert_eq!(h.sim.register(328), 0xFFFF);
    h.sim.drop_next_requests(0x10, 10);
    h.bridge_mut()
        .submit(group(&[(SettingId::StateOfCharge, 40_000)]))
        .unwrap();
    h.run_until(4 * S);
    // Neither verified nor "failed": the read-back shows 0xFFFF, which is what
    // 328 reads before and after an accepted write. The settings read after the
    // group cannot tell either: the follow-up stays unconfirmed.
    let unconfirmed = WriteOutcome::Unconfirmed(tinybms_firmware::bms::link::Failure::Timeout);
    assert_eq!(
        writes(&h),
        vec![(SettingId::StateOfCharge, 40_000, unconfirmed)]
    );
    let follow: Vec<_> = h
        .log
        .iter()
        .filter_map(|l| match &l.report {
            Report::WriteFollowUp { setting, outcome } => Some((setting.id, *outcome)),
            _ => None,
        })
        .collect();
    assert_eq!(follow, vec![(SettingId::StateOfCharge, unconfirmed)]);
    // Sent, unanswered, re-sent only while nothing at all came back.
    assert_eq!(h.sim.stats().requests_by_command[&0x10], 3);
}

#[test]
fn a_write_whose_echo_was_lost_is_decided_by_the_read_back() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 16);
    h.run_until(S);
    // The first write request is lost: the retry is applied and echoed.
    h.sim.drop_next_requests(0x10, 1);
    h.bridge_mut()
        .submit(group(&[(SettingId::OverVoltageCutoff, 3720)]))
        .unwrap();
    h.run_until(3 * S);
    assert_eq!(
        writes(&h),
        vec![(SettingId::OverVoltageCutoff, 3720, WriteOutcome::Verified)]
    );
    assert_eq!(h.sim.stats().requests_by_command[&0x10], 2);
    assert_eq!(h.sim.register(315), 3720);
}

#[test]
fn a_lost_reset_is_not_confirmed() {
    let mut h = harness(PackModel::LiIon_14S, SimConfig::default(), 17);
    h.run_until(2 * S);
    // Register 114 already says "software reset" from an earlier restart.
    h.sim
        .set_register(114, (h.sim.register(114) & 0xFF00) | 0x04);
    h.sim.drop_next_requests(0x02, 1);
    h.bridge_mut().submit(Command::ResetBms).unwrap();
    h.run_until(15 * S);
    assert_eq!(h.sim.stats().reboots, 0);
    assert_eq!(
        h.sim.stats().requests_by_command.get(&0x02),
        Some(&1),
        "never re-sent"
    );
    assert_eq!(
        count(&h, |r| matches!(r, Report::ResetDone { confirmed: false })),
        1
    );
    assert_eq!(
        count(&h, |r| matches!(r, Report::ResetDone { confirmed: true })),
        0
    );
}

#[test]
fn a_bms_that_never_answers_0x1d_is_still_polled() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 18);
    h.sim.ignore_command(0x1D);
    h.run_until(30 * S);
    assert_eq!(count(&h, |r| matches!(r, Report::Ready { .. })), 1);
    assert!(h.published.len() > 100);
    assert_eq!(
        count(&h, |r| matches!(r, Report::Offline { .. })),
        0,
        "{}",
        h.log_text()
    );
    assert!(h.bridge().telemetry().limits_max.is_none());
    // Writes still validate against Rev D and go through write/verify.
    h.bridge_mut()
        .submit(group(&[(SettingId::OverVoltageCutoff, 3710)]))
        .unwrap();
    h.run_until(33 * S);
    assert_eq!(
        writes(&h),
        vec![(SettingId::OverVoltageCutoff, 3710, WriteOutcome::Verified)]
    );
}

#[test]
fn a_long_group_does_not_stop_the_live_polling() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 19);
    h.run_until(S);
    let items: Vec<(SettingId, i32)> = (0..16)
        .map(|i| (SettingId::ChargerStartupDelay, 10 + i))
        .collect();
    h.bridge_mut().submit(group(&items)).unwrap();
    h.run_until(8 * S);
    assert_eq!(writes(&h).len(), 16);
    assert!(writes(&h).iter().all(|w| w.2 == WriteOutcome::Verified));
    let mut last = S;
    for (t, _) in h.published.iter().filter(|(t, _)| *t > S) {
        assert!(t - last < 700_000, "no snapshot between {last} and {t}");
        last = *t;
    }
}

#[test]
fn event_timestamps_wrap_after_24_bits() {
    use tinybms_firmware::bms::event_log::ts_newer;
    assert!(ts_newer(5, 0x00FF_FFF0));
    assert!(!ts_newer(0x00FF_FFF0, 5));
    assert!(ts_newer(0x10, 0x0F));
    assert!(!ts_newer(7, 7));
}

/// A setting that contradicts another is never written (issue 26): an
/// over-voltage cutoff below the under-voltage cutoff, a fully-charged voltage
/// above the over-voltage cutoff (4.2 V on a LiFePO4 pack). Checked against
/// the values the BMS holds and those written with it; nothing reaches the
/// BMS, and the outcome names both settings.
#[test]
fn a_setting_that_contradicts_another_is_never_written() {
    let mut h = harness(PackModel::LiFePO4_16S, SimConfig::default(), 3);
    h.run_until(5 * S);
    let uv = h.sim.register(316);
    let ov = h.sim.register(315);
    assert!(uv > 2000 && ov > uv, "uv {uv} ov {ov}");
    let before = write_requests(&h);
    h.bridge_mut()
        .submit(group(&[(
            SettingId::OverVoltageCutoff,
            i32::from(uv) - 100,
        )]))
        .unwrap();
    h.bridge_mut()
        .submit(group(&[(SettingId::FullyChargedVoltage, 4200)]))
        .unwrap();
    h.run_until(15 * S);
    assert_eq!(write_requests(&h), before, "nothing was sent to the BMS");
    assert_eq!(h.sim.register(315), ov);
    let w = writes(&h);
    assert_eq!(w.len(), 2, "{w:?}");
    for (id, _, outcome) in &w {
        assert!(
            matches!(
                outcome,
                WriteOutcome::Rejected(SettingError::Contradicts { .. })
            ),
            "{id:?}: {outcome:?}"
        );
    }
    let said: Vec<String> = h
        .log
        .iter()
        .filter(|l| matches!(l.report, Report::Write { .. }))
        .map(|l| l.report.to_string())
        .collect();
    assert!(
        said[0].contains("Under-Voltage Cutoff must stay below Over-Voltage Cutoff, Under-Voltage Cutoff is 2500"),
        "{said:?}"
    );
    assert!(
        said[1].contains(
            "Fully Charged Voltage may not exceed Over-Voltage Cutoff, Over-Voltage Cutoff is 3650"
        ),
        "{said:?}"
    );
    // Both moved together, consistently: written.
    h.bridge_mut()
        .submit(group(&[
            (SettingId::UnderVoltageCutoff, 2600),
            (SettingId::FullyDischargedVoltage, 2900),
        ]))
        .unwrap();
    h.run_until(30 * S);
    assert_eq!(h.sim.register(316), 2600);
    assert_eq!(h.sim.register(301), 2900);
    assert_published_are_genuine(&h);
}
