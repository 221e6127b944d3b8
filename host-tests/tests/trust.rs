//! Trust under noise: the bridge publishes only what the BMS sent, does not flap
//! offline on a noisy line, keeps telemetry flowing, loses no event and says what
//! it knows about each write. Every test runs the firmware's bridge against the
//! simulated TinyBMS with the ground-truth checks of `Harness::checked`.

use host_tests::sim::{CurrentSensor, FaultConfig, PackModel, SimBms, SimConfig};
use host_tests::virtual_time::Harness;
use protocol_core::events::EventId;
use protocol_core::registers;
use protocol_core::request::Request;
use protocol_core::response::{RegisterBlock, Response};
use protocol_core::settings::{Setting, SettingId};
use tinybms_firmware::bms::checks::Check;
use tinybms_firmware::bms::link::LinkStats;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::bridge::report::WriteOutcome;
use tinybms_firmware::{Command, Level, Report};

const S: u64 = 1_000_000;
const MIN: u64 = 60 * S;

fn checked(profile: PackModel, config: SimConfig, seed: u64) -> Harness {
    Harness::checked(SimBms::new(profile, config, seed), Timing::default())
}

fn genuine(h: &Harness) {
    let s = h.soak.as_ref().unwrap();
    assert_eq!(s.wrong, 0, "{:#?}", s.wrong_examples);
    assert_eq!(s.false_successes, 0, "{:#?}", s.wrong_examples);
}

fn count(h: &Harness, f: impl Fn(&Report) -> bool) -> usize {
    h.log.iter().filter(|l| f(&l.report)).count()
}

/// A CRC-valid 0x03 0-55 reply holding `regs` (what a collision looks like).
fn forged_live(mut edit: impl FnMut(&mut [u16; 56]), sim: &SimBms) -> Vec<u8> {
    let mut regs = [0u16; 56];
    for (i, r) in regs.iter_mut().enumerate() {
        *r = sim.register(i as u16);
    }
    edit(&mut regs);
    let req = Request::read_registers(0, 56).unwrap();
    let resp = Response::Registers(RegisterBlock {
        start: 0,
        values: heapless::Vec::from_slice(&regs).unwrap(),
    });
    let frame = resp.to_frame(&req).unwrap();
    let mut b = vec![0u8; frame.encoded_len().unwrap()];
    let n = frame.encode(&mut b).unwrap();
    b.truncate(n);
    b
}

fn set32(regs: &mut [u16; 56], a: usize, v: u32) {
    regs[a] = v as u16;
    regs[a + 1] = (v >> 16) as u16;
}

// ---------------------------------------------------------------------------
// 1. A published value is one the BMS sent.
// ---------------------------------------------------------------------------

#[test]
fn forged_live_blocks_with_a_valid_crc_are_never_published() {
    // Each forgery is a CRC-valid reply of the right length that the simulated
    // BMS never built: the kinds the soaks found (SOC 352 %, 18 cells on a 16S
    // pack, a pack of 806 669 647 872 V, a 76.1 °C jump).
    type Edit = Box<dyn Fn(&mut [u16; 56])>;
    let forgeries: Vec<(&str, Edit)> = vec![
        ("soc", Box::new(|r| set32(r, 46, 352_000_000))),
        ("cells", Box::new(|r| r[53] = 18)),
        (
            "pack",
            Box::new(|r| set32(r, 36, 806_669_647_872f32.to_bits())),
        ),
        ("jump", Box::new(|r| r[48] = 761)),
        ("shifted cell", Box::new(|r| r[5] = r[5].rotate_left(8))),
    ];
    for (name, edit) in forgeries {
        let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 21);
        h.run_until(3 * S);
        let before = h.published.len();
        assert!(before > 3, "{name}");
        let bytes = forged_live(&*edit, &h.sim);
        h.sim.forge_next_reply(bytes);
        h.run_until(6 * S);
        genuine(&h);
        assert!(h.published.len() > before + 5, "{name}: telemetry goes on");
        // Not flagged either: the second read disagreed with the forgery.
        assert_eq!(
            count(&h, |r| matches!(r, Report::Flagged(Some(_)))),
            0,
            "{name}"
        );
    }
}

/// What the soaks found (docs/trust.md): on a bad line, a 0x09 piece whose
/// CRC matched by chance, carrying a cell a little off or a current of
/// -6.8e-21 A: values every consistency check lets through. Every live piece
/// that changed since the last snapshot is read twice
/// (`BlockRead::confirm_pieces`), so such a piece is never believed.
#[test]
fn a_crc_collision_in_a_piece_is_never_published() {
    type Edit = fn(u16) -> u16;
    let forgeries: [(&str, u16, Edit); 3] = [
        ("a cell 50 mV up", 5, |v| v + 500),
        ("a cell 50 mV down", 9, |v| v - 500),
        ("the current's low word", 38, |v| v ^ 0x1234),
    ];
    for (name, addr, edit) in forgeries {
        let mut h = checked(
            PackModel::LiFePO4_16S,
            SimConfig::default().with_faults(FaultConfig::all(0.05)),
            26,
        );
        h.run_until(60 * S);
        assert!(h.bridge().piece_registers() < 56, "{name}: read in pieces");
        // The line clears (the piece size grows back only after 12 clean reads):
        // the forged piece arrives intact.
        h.sim.config_mut().faults = FaultConfig::all(0.0);
        let before = h.soak.as_ref().unwrap().published;
        h.sim.forge_next_pair(addr, edit(h.sim.register(addr)));
        h.run_until(70 * S);
        assert!(
            !h.sim.pair_forgery_pending(),
            "{name}: the forgery went out"
        );
        genuine(&h);
        assert!(
            h.soak.as_ref().unwrap().published > before + 5,
            "{name}: telemetry goes on"
        );
    }
}

#[test]
fn a_real_broken_sense_wire_is_published_flagged_once_confirmed() {
    // Cell 6 reads 0 V on every read: real, unusual. Each block fails the cell
    // check, the second read agrees: published, flagged, and said once at WARN.
    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 22);
    h.run_until(3 * S);
    h.sim.pin_register(5, 0);
    h.run_until(20 * S);
    genuine(&h);
    let t = h.bridge().telemetry();
    assert_eq!(t.live.flagged, Some(Check::CellVoltage));
    assert_eq!(t.snapshot.as_ref().unwrap().cells.raw[5], 0);
    let flagged: Vec<_> = h
        .log
        .iter()
        .filter(|l| matches!(l.report, Report::Flagged(_)))
        .collect();
    assert_eq!(flagged.len(), 1, "said once, not per snapshot");
    assert_eq!(flagged[0].level, Level::Warn);
    assert!(h.soak.as_ref().unwrap().flagged > 20);
}

#[test]
fn consistency_checks_name_what_failed() {
    use tinybms_firmware::bms::checks::{check_jump, check_live, Context};
    let sim = SimBms::new(PackModel::LiIon_14S, SimConfig::default(), 23);
    let block = |edit: &dyn Fn(&mut [u16; 56])| {
        let mut regs = [0u16; 56];
        for (i, r) in regs.iter_mut().enumerate() {
            *r = sim.register(i as u16);
        }
        edit(&mut regs);
        RegisterBlock {
            start: 0,
            values: heapless::Vec::from_slice(&regs).unwrap(),
        }
    };
    let ctx = Context {
        series_cells: Some(14),
        assembled: false,
    };
    let verdict = |edit: &dyn Fn(&mut [u16; 56])| {
        let b = block(edit);
        let s = protocol_core::views::LiveSnapshot::from_registers(&b).unwrap();
        check_live(&b, &s, ctx)
    };
    assert_eq!(verdict(&|_| {}), Ok(()));
    assert_eq!(verdict(&|r| r[53] = 16), Err(Check::CellCount));
    assert_eq!(verdict(&|r| r[53] = 0), Err(Check::CellCount));
    assert_eq!(verdict(&|r| r[0] = 33_000), Err(Check::CellOutsideBlock));
    assert_eq!(verdict(&|r| r[7] = 51_000), Err(Check::CellVoltage));
    assert_eq!(verdict(&|r| r[40] += 50), Err(Check::MinMaxCell));
    assert_eq!(
        verdict(&|r| set32(r, 36, 70.0f32.to_bits())),
        Err(Check::PackVoltage)
    );
    assert_eq!(
        verdict(&|r| set32(r, 36, f32::NAN.to_bits())),
        Err(Check::PackVoltage)
    );
    assert_eq!(
        verdict(&|r| set32(r, 38, 9_999.0f32.to_bits())),
        Err(Check::Current)
    );
    assert_eq!(verdict(&|r| set32(r, 46, 100_000_001)), Err(Check::Soc));
    assert_eq!(verdict(&|r| r[45] = 50_001), Err(Check::Soh));
    assert_eq!(verdict(&|r| r[50] = 0x90), Err(Check::Status));
    assert_eq!(verdict(&|r| r[48] = 1300), Err(Check::Temperature));
    // Disconnected external sensor: the marker, not an impossible temperature.
    assert_eq!(verdict(&|r| r[43] = 0x8000), Ok(()));
    // Jumps.
    let b0 = block(&|_| {});
    let s0 = protocol_core::views::LiveSnapshot::from_registers(&b0).unwrap();
    let jump = |edit: &dyn Fn(&mut [u16; 56]), dt: u64| {
        let b = block(edit);
        let s = protocol_core::views::LiveSnapshot::from_registers(&b).unwrap();
        check_jump(&s0, 0, &s, dt)
    };
    let soc = s0.soc_raw;
    assert_eq!(jump(&|r| set32(r, 46, soc + 2_500_000), S), Ok(()));
    assert_eq!(
        jump(&|r| set32(r, 46, soc + 5_000_000), S),
        Err(Check::SocJump)
    );
    assert_eq!(jump(&|r| set32(r, 46, soc + 5_000_000), 10 * S), Ok(()));
    assert_eq!(
        jump(&|r| r[48] = r[48].wrapping_add(200), S),
        Err(Check::TemperatureJump)
    );
    assert_eq!(
        jump(&|r| r[5] = r[5].wrapping_sub(15_000), S),
        Err(Check::CellJump)
    );
    let life = s0.lifetime_s;
    assert_eq!(
        jump(&|r| set32(r, 32, life - 1), S),
        Err(Check::LifetimeJump)
    );
    assert_eq!(
        jump(&|r| set32(r, 32, life + 3600), S),
        Err(Check::LifetimeJump)
    );
}

// ---------------------------------------------------------------------------
// 2. The simulator's new faults, and the sim command checking itself.
// ---------------------------------------------------------------------------

#[test]
fn new_fault_kinds_are_injected_and_counted() {
    let faults = FaultConfig {
        insert_byte: 0.01,
        noise_burst: 0.05,
        repeat_fragment: 0.05,
        ..FaultConfig::NONE
    };
    let mut h = checked(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(faults),
        24,
    );
    h.run_until(5 * MIN);
    let f = h.sim.stats().faults;
    let replies = h.sim.stats().replies as f64;
    assert!(f.inserted_bytes > 100, "{f:?}");
    let near = |n: u64, p: f64| (n as f64 - p * replies).abs() < 0.3 * p * replies;
    assert!(near(f.noise_bursts, 0.05), "{f:?} of {replies}");
    assert!(near(f.repeated_fragments, 0.05), "{f:?} of {replies}");
    assert_eq!(
        f.total(),
        f.inserted_bytes + f.noise_bursts + f.repeated_fragments
    );
    genuine(&h);
}

// ---------------------------------------------------------------------------
// 3. Offline means silence.
// ---------------------------------------------------------------------------

#[test]
fn a_noisy_line_never_goes_offline() {
    // 1 h at 5 % of every fault kind: the BMS is awake and wired, so the link
    // must never call it offline (today: 14-31 times per 6 h).
    let mut h = checked(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(FaultConfig::all(0.05)),
        25,
    );
    h.retain = false;
    h.run_until(60 * MIN);
    let s = h.soak.as_ref().unwrap();
    assert_eq!(s.offline_transitions, 0);
    assert!(h.bridge().link_stats().failures > 100, "the line was bad");
    genuine(&h);
}

#[test]
fn a_late_answer_between_silent_transactions_resets_the_offline_count() {
    use tinybms_firmware::bms::link::{Link, LinkStep, Silence};
    let mut link = Link::new(Timing::default());
    let mut now = 0u64;
    let req = Request::read_registers(0, 2).unwrap();
    let silent = |link: &mut Link, now: &mut u64| {
        link.start(*now, req.clone(), Silence::Failure);
        loop {
            match link.step(*now) {
                LinkStep::Send(_) => {}
                LinkStep::WaitUntil(t) => *now = t,
                LinkStep::Done(c) => break c,
                LinkStep::Idle => panic!("idle"),
            }
        }
    };
    for _ in 0..2 {
        let _ = silent(&mut link, &mut now);
    }
    assert_eq!(link.consecutive_failures(), 2);
    // A reply delayed past the timeout arrives between transactions.
    now += 50_000;
    link.on_bytes(now, &[0xAA, 0x03, 0x04, 1, 2]);
    assert_eq!(link.consecutive_failures(), 0);
    for _ in 0..2 {
        let _ = silent(&mut link, &mut now);
    }
    assert!(link.is_online(), "2 silent since the late bytes, not 4");
    let _ = silent(&mut link, &mut now);
    assert!(!link.is_online(), "3 silent in a row: offline");
}

#[test]
fn a_corrupt_reply_then_silence_does_not_count_towards_offline() {
    use protocol_core::frame::Frame;
    use tinybms_firmware::bms::link::{Link, LinkStep, Silence};
    let config = Timing::default();
    let mut link = Link::new(config);
    let mut now = 0u64;
    let req = Request::read_registers(0, 2).unwrap();
    let mut garbage = vec![0u8; 9];
    Frame::Ack { command: 0x03 }.encode(&mut garbage).unwrap();
    garbage[3] ^= 0x55; // a damaged answer
    for _ in 0..5 {
        link.start(now, req.clone(), Silence::Failure);
        let mut sends = 0;
        loop {
            match link.step(now) {
                LinkStep::Send(_) => {
                    sends += 1;
                    if sends == 1 {
                        now += 2_000;
                        link.on_bytes(now, &garbage); // heard, but nothing valid
                    }
                }
                LinkStep::WaitUntil(t) => now = t,
                LinkStep::Done(c) => {
                    assert!(c.result.is_err());
                    break;
                }
                LinkStep::Idle => panic!("idle"),
            }
        }
    }
    assert!(link.is_online());
    assert_eq!(link.consecutive_failures(), 0);
}

// ---------------------------------------------------------------------------
// 4. Telemetry keeps flowing on a bad line.
// ---------------------------------------------------------------------------

fn longest_gap(rate: f64, minutes: u64, seed: u64) -> (Harness, u64) {
    let mut h = checked(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(FaultConfig::all(rate)),
        seed,
    );
    h.retain = false;
    h.run_until(minutes * MIN);
    let gap = h.longest_gap_us();
    (h, gap)
}

/// At 5 % the live block is read in pieces, and every piece that changed since
/// the last snapshot is read twice (`BlockRead::confirm_pieces`): the longest gap
/// was 2.9 s over 20 × 6 h before that, 3.5 s since (docs/trust.md).
#[test]
fn at_5_percent_snapshots_keep_coming_within_4_s() {
    let (h, gap) = longest_gap(0.05, 30, 26);
    genuine(&h);
    assert!(gap <= 4 * S, "longest gap {gap} µs");
    // Read in pieces, each snapshot says how it was made.
    assert!(h.bridge().piece_registers() < 56);
    assert!(h.bridge().telemetry().live.pieces > 1);
    assert!(h.soak.as_ref().unwrap().published > 30 * 60 / 2);
}

#[test]
fn at_10_percent_the_sync_completes_and_gaps_stay_under_30_s() {
    let (h, gap) = longest_gap(0.10, 30, 27);
    genuine(&h);
    assert!(h.soak.as_ref().unwrap().ready_at.is_some());
    assert!(gap <= 30 * S, "longest gap {gap} µs");
}

#[test]
fn at_20_percent_the_line_quality_is_stated_not_flooded() {
    let mut h = checked(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(FaultConfig::all(0.20)),
        28,
    );
    h.run_until(10 * MIN);
    genuine(&h);
    let quality = count(&h, |r| matches!(r, Report::LineQuality { .. }));
    assert!((9..=11).contains(&quality), "{quality}");
    let warnings = h.log.iter().filter(|l| l.level == Level::Warn).count();
    // About one line a minute, plus rate-limited link errors: not a flood.
    assert!(warnings < 10 * 8, "{warnings}\n{}", h.log_text());
}

#[test]
fn a_clean_line_reads_the_live_block_in_one_request() {
    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 29);
    h.run_until(10 * S);
    genuine(&h);
    assert_eq!(h.bridge().telemetry().live.pieces, 1);
    let s = h.bridge().link_stats();
    assert_eq!(s.retries, 0);
    assert_eq!(count(&h, |r| matches!(r, Report::LineQuality { .. })), 0);
}

/// The wire in figures and words (issue 54): a bad line is a bad wire, a
/// clean one healthy (and says nothing), a BMS that never answers silent.
#[test]
fn the_wire_is_judged_from_the_link_counters() {
    use tinybms_firmware::bms::wire::WireVerdict;
    let bad = SimConfig::default().with_faults(FaultConfig::all(0.10));
    let mut h = checked(PackModel::LiFePO4_16S, bad, 30);
    h.run_until(3 * MIN);
    let (f, v) = h.bridge().wire();
    assert!(matches!(v, WireVerdict::BadWire { .. }), "{v:?} {f:?}");
    assert!(f.replies > 0 && f.corrupted_permille >= 100, "{f:?}");
    let said = count(&h, |r| matches!(r, Report::Wire { .. }));
    assert!((2..=3).contains(&said), "{said}");

    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 31);
    h.run_until(3 * MIN);
    assert_eq!(h.bridge().wire().1, WireVerdict::Healthy);
    assert!(h.bridge().wire().0.replies > 0);
    assert_eq!(count(&h, |r| matches!(r, Report::Wire { .. })), 0);

    let deaf = FaultConfig {
        no_reply: 1.0,
        ..FaultConfig::NONE
    };
    let mut h = checked(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(deaf),
        32,
    );
    h.run_until(3 * MIN);
    assert_eq!(h.bridge().wire().1, WireVerdict::Silent);
    assert!(
        count(&h, |r| matches!(
            r,
            Report::Wire {
                verdict: WireVerdict::Silent,
                ..
            }
        )) >= 2
    );
}

// ---------------------------------------------------------------------------
// 5. No event is lost.
// ---------------------------------------------------------------------------

fn events_soak(rate: f64, seed: u64) {
    let mut h = checked(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(FaultConfig::all(rate)),
        seed,
    );
    h.retain = false;
    let ids = [
        EventId::ChargingStarted,
        EventId::ChargingDone,
        EventId::UnderVoltageCutoff,
        EventId::ChargerDisconnected,
    ];
    for k in 0..40u64 {
        h.run_until((k + 1) * 37 * S);
        let id = ids[(k % 4) as usize];
        h.sim.inject_fault_event(id);
        if id.severity() == protocol_core::events::Severity::Fault {
            h.sim.clear_fault();
        }
    }
    h.run_until(41 * 37 * S);
    let e = h.event_check();
    assert!(e.logged >= 40, "{e:?}");
    assert_eq!(e.reported_once, e.logged, "{e:?}");
    assert_eq!((e.missing, e.duplicated, e.invented), (0, 0, 0), "{e:?}");
    genuine(&h);
}

#[test]
fn every_event_is_reported_exactly_once_at_1_percent() {
    events_soak(0.01, 30);
}

#[test]
fn every_event_is_reported_exactly_once_at_5_percent() {
    events_soak(0.05, 31);
}

#[test]
fn an_empty_log_at_start_up_is_history_once_and_later_faults_warn() {
    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 32);
    h.sim.clear_event_log();
    h.run_until(20 * S);
    assert_eq!(
        count(&h, |r| matches!(r, Report::EventHistory { count: 0, .. })),
        1
    );
    h.sim.inject_fault_event(EventId::OverVoltageCutoff);
    h.run_until(40 * S);
    assert_eq!(count(&h, |r| matches!(r, Report::EventHistory { .. })), 1);
    let new: Vec<_> = h
        .log
        .iter()
        .filter(|l| matches!(l.report, Report::NewEvent(_)))
        .collect();
    assert_eq!(new.len(), 1);
    assert_eq!(new[0].level, Level::Warn);
}

// ---------------------------------------------------------------------------
// 6. Write outcomes say what is known.
// ---------------------------------------------------------------------------

fn group(id: SettingId, value: i32) -> Command {
    let mut items = heapless::Vec::new();
    items.push(Setting { id, value }).unwrap();
    Command::ApplySettings(items, protocol_core::settings::ChemistryCheck::Inferred)
}

fn outcomes(h: &Harness) -> Vec<(bool, WriteOutcome)> {
    h.log
        .iter()
        .filter_map(|l| match &l.report {
            Report::Write { outcome, .. } => Some((false, *outcome)),
            Report::WriteFollowUp { outcome, .. } => Some((true, *outcome)),
            _ => None,
        })
        .collect()
}

#[test]
fn an_applied_write_whose_replies_were_lost_is_unconfirmed_then_verified() {
    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 33);
    h.run_until(2 * S);
    // The write is applied but every echo is lost (so it is re-sent only while
    // nothing came back); every read-back is lost too.
    h.sim.drop_next_replies(0x10, 3);
    h.bridge_mut()
        .submit(group(SettingId::OverVoltageCutoff, 3720))
        .unwrap();
    h.run_until(2 * S + 150_000);
    h.sim.drop_next_replies(0x09, 12);
    h.run_until(8 * S);
    let o = outcomes(&h);
    assert!(
        matches!(
            o.as_slice(),
            [
                (false, WriteOutcome::Unconfirmed(_)),
                (true, WriteOutcome::Verified)
            ]
        ),
        "{o:?}"
    );
    assert_eq!(h.sim.register(315), 3720);
    genuine(&h);
}

#[test]
fn a_lost_write_with_lost_read_backs_is_unconfirmed_then_failed() {
    // Nothing reaches the BMS and no read-back answers: "unconfirmed"; the
    // settings read after the group shows the old value: the follow-up says
    // "failed" (not applied) — never "verified".
    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 41);
    h.run_until(2 * S);
    let old = h.sim.register(315);
    h.sim.drop_next_requests(0x10, 10);
    h.bridge_mut()
        .submit(group(SettingId::OverVoltageCutoff, 3720))
        .unwrap();
    h.run_until(2 * S + 150_000);
    h.sim.drop_next_replies(0x09, 12);
    h.run_until(8 * S);
    let o = outcomes(&h);
    assert!(
        matches!(
            o.as_slice(),
            [
                (false, WriteOutcome::Unconfirmed(_)),
                (true, WriteOutcome::Failed(_))
            ]
        ),
        "{o:?}"
    );
    assert_eq!(h.sim.register(315), old);
    genuine(&h);
}

#[test]
fn a_lost_write_whose_read_back_shows_the_old_value_is_failed() {
    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 34);
    h.run_until(2 * S);
    let old = h.sim.register(315);
    h.sim.drop_next_requests(0x10, 10);
    h.bridge_mut()
        .submit(group(SettingId::OverVoltageCutoff, 3720))
        .unwrap();
    h.run_until(6 * S);
    let o = outcomes(&h);
    assert!(
        matches!(o.as_slice(), [(false, WriteOutcome::Failed(_))]),
        "{o:?}"
    );
    assert_eq!(h.sim.register(315), old);
}

#[test]
fn at_5_percent_no_write_is_reported_failed_that_was_applied() {
    let mut h = checked(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(FaultConfig::all(0.05)),
        35,
    );
    h.retain = false;
    let values = [3700, 3710]; // above fully_charged (3.65 V)
    for k in 0..60u64 {
        h.run_until((k + 1) * 20 * S);
        let _ = h.bridge_mut().submit(group(
            SettingId::OverVoltageCutoff,
            values[(k % 2) as usize],
        ));
    }
    h.run_until(61 * 20 * S);
    let s = h.soak.as_ref().unwrap();
    assert_eq!(s.false_failures, 0, "{:?}", s.outcomes);
    assert_eq!(s.false_successes, 0);
    assert!(
        s.outcomes.get("verified").copied().unwrap_or(0) > 30,
        "{:?}",
        s.outcomes
    );
    genuine(&h);
}

// ---------------------------------------------------------------------------
// 7. Counters wrap; 8. every-snapshot logging.
// ---------------------------------------------------------------------------

#[test]
fn counters_near_the_wrap_point_do_not_panic() {
    let mut h = checked(
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(FaultConfig::all(0.05)),
        36,
    );
    let max = u32::MAX - 3;
    h.bridge_mut().preset_link_stats(LinkStats {
        requests: max,
        replies: max,
        timeouts: max,
        wakeup_resends: max,
        retries: max,
        crc_errors: max,
        framing_errors: max,
        invalid_replies: max,
        nacks_command: max,
        nacks_crc: max,
        nacks_other: max,
        skipped_bytes: max,
        unsolicited: max,
        failures: max,
        latency_min_us: 0,
        latency_max_us: u32::MAX,
        latency_sum_us: u64::MAX - 10,
    });
    h.run_until(2 * MIN);
    let s = h.bridge().link_stats();
    assert!(s.requests < 10_000 && s.replies < 10_000, "wrapped: {s:?}");
    genuine(&h);
}

#[test]
fn snapshot_log_period_0_logs_every_snapshot_without_catching_up() {
    let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 37);
    let config = Timing {
        snapshot_log_period_us: 0,
        ..Timing::default()
    };
    let mut h = Harness::checked(sim, config);
    h.run_until(30 * S);
    // One hour of silence, then back.
    h.sim.set_silent_until(h.now + 3600 * S);
    h.run_until(3600 * S + 60 * S);
    let lines = count(&h, |r| matches!(r, Report::Snapshot(_)));
    assert_eq!(lines, h.published.len());
    assert!(lines > 100);
}

#[test]
fn the_snapshot_log_grid_is_computed_not_walked() {
    use tinybms_firmware::bridge::snapshot_log_due;
    // Ten years late with a 1 µs period: a loop stepping the grid would take
    // 3e14 iterations; the computation answers at once.
    let ten_years = 10 * 365 * 24 * 3600 * S;
    assert_eq!(snapshot_log_due(0, ten_years, 1), Some(ten_years + 1));
    assert_eq!(snapshot_log_due(0, ten_years, 0), Some(ten_years));
    // On the grid: due at 10 s, next at 20 s; 25 s late -> next at 40 s.
    assert_eq!(snapshot_log_due(10 * S, 9 * S, 10 * S), None);
    assert_eq!(snapshot_log_due(10 * S, 10 * S, 10 * S), Some(20 * S));
    assert_eq!(snapshot_log_due(10 * S, 35 * S, 10 * S), Some(40 * S));
    assert_eq!(snapshot_log_due(u64::MAX - 5, u64::MAX, 10), Some(u64::MAX));
}

#[test]
fn snapshot_lines_keep_their_grid_after_a_long_silence() {
    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 38);
    h.run_until(30 * S);
    h.sim.set_silent_until(h.now + 3600 * S);
    h.run_until(3600 * S + 120 * S);
    let times: Vec<u64> = h
        .log
        .iter()
        .filter(|l| matches!(l.report, Report::Snapshot(_)))
        .map(|l| l.at_us)
        .collect();
    let last = times.windows(2).last().unwrap();
    // Every 10 s, as before the silence.
    assert!((9 * S..=11 * S).contains(&(last[1] - last[0])), "{times:?}");
}

// ---------------------------------------------------------------------------
// 9. The audit's protocol fixes, through the bridge.
// ---------------------------------------------------------------------------

#[test]
fn a_sensor_dependent_setting_follows_the_bms_limits() {
    // An external sensor that allows 900 A on 317: Rev D's 750 A cap must not
    // refuse it when the BMS says so; above the BMS's own max is refused.
    let config = SimConfig::default().with_current_sensor(CurrentSensor::External);
    let mut h = checked(PackModel::LiFePO4_16S, config, 39);
    h.sim.override_limits(317, 1, 1000);
    h.run_until(3 * S);
    h.bridge_mut()
        .submit(group(SettingId::DischargeOverCurrentCutoff, 900))
        .unwrap();
    h.bridge_mut()
        .submit(group(SettingId::DischargeOverCurrentCutoff, 1001))
        .unwrap();
    h.run_until(10 * S);
    let o = outcomes(&h);
    assert_eq!(o[0], (false, WriteOutcome::Verified), "{o:?}");
    assert!(matches!(o[1], (false, WriteOutcome::Rejected(_))), "{o:?}");
    assert_eq!(h.sim.register(317), 900);
    let _ = registers::lookup(317);
}

#[test]
fn register_337_accepts_0x0a() {
    let mut h = checked(PackModel::LiFePO4_16S, SimConfig::default(), 40);
    h.run_until(3 * S);
    h.bridge_mut()
        .submit(group(SettingId::PrechargePin, 0x0A))
        .unwrap();
    h.run_until(6 * S);
    let o = outcomes(&h);
    assert!(!matches!(o[0].1, WriteOutcome::Rejected(_)), "{o:?}");
}

#[test]
fn unknown_values_print_as_unknown_0x_everywhere() {
    use protocol_core::events::{Event, OnlineStatus};
    let status = Report::StatusChanged {
        from: Some(OnlineStatus::Idle),
        to: OnlineStatus::from_raw(0x9C),
    };
    assert_eq!(status.to_string(), "status Idle -> unknown_0x9C");
    let e = Report::NewEvent(Event {
        timestamp_s: 5,
        id: EventId::from_raw(0x99),
    });
    assert!(e.to_string().ends_with("0x99 unknown_0x99"), "{e}");
}

/// The cell part of `check_live` as it was first written (a pass per rule,
/// registers read one by one): the fused single pass must agree with it.
fn cell_checks_reference(
    block: &RegisterBlock,
    s: &protocol_core::views::LiveSnapshot,
    ctx: tinybms_firmware::bms::checks::Context,
) -> Option<Check> {
    use tinybms_firmware::bms::checks::*;
    if s.cell_count == 0 || usize::from(s.cell_count) > 16 {
        return Some(Check::CellCount);
    }
    if ctx.series_cells.is_some_and(|n| n != s.cell_count) {
        return Some(Check::CellCount);
    }
    let first = u16::from(s.cells.first_register);
    let last = first + s.cell_count.min(16);
    for a in 0..16u16 {
        if !(first..last).contains(&a) && block.get(a).unwrap_or(0) != 0 {
            return Some(Check::CellOutsideBlock);
        }
    }
    if s.cells
        .raw
        .iter()
        .any(|&c| !(CELL_MIN_RAW..=CELL_MAX_RAW).contains(&c))
    {
        return Some(Check::CellVoltage);
    }
    let tol = if ctx.assembled {
        MIN_MAX_TOLERANCE_ASSEMBLED_MV
    } else {
        MIN_MAX_TOLERANCE_MV
    };
    let lo = s.cells.min()?.1;
    let hi = s.cells.max()?.1;
    let mv = protocol_core::views::cell_mv;
    if mv(lo).abs_diff(s.min_cell_mv) > tol || mv(hi).abs_diff(s.max_cell_mv) > tol {
        return Some(Check::MinMaxCell);
    }
    None
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(2000))]

    /// Random cell registers (zeros, plausible and impossible voltages), cell
    /// counts and min/max registers: `check_live` names the same cell failure
    /// as the reference, and none when the reference finds none.
    #[test]
    fn fused_cell_checks_agree_with_the_reference(
        values in proptest::collection::vec(
            proptest::prop_oneof![
                8 => 25_000u16..42_000,
                1 => proptest::prelude::Just(0u16),
                1 => proptest::prelude::any::<u16>(),
                // The range's edges (CELL_MIN_RAW, CELL_MAX_RAW).
                1 => proptest::sample::select(vec![9_999u16, 10_000, 50_000, 50_001]),
            ],
            16,
        ),
        count in proptest::prop_oneof![8 => 1u16..=16, 1 => 0u16..18],
        start in 0usize..16,
        stray in proptest::option::of((0usize..16, 1u16..60_000)),
        min_mv in 0u16..6_000,
        max_mv in 0u16..6_000,
        from_cells in proptest::prop_oneof![3 => proptest::prelude::Just(true), 1 => proptest::prelude::Just(false)],
        deltas in (-160i32..160, -160i32..160),
        series in proptest::prop_oneof![
            proptest::prelude::Just(None),
            proptest::prelude::Just(Some(u16::MAX)),
            proptest::option::of(0u16..18),
        ],
        assembled in proptest::prelude::any::<bool>(),
    ) {
        use tinybms_firmware::bms::checks::{check_live, Context};
        let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 5);
        let mut regs = [0u16; 56];
        for (i, r) in regs.iter_mut().enumerate() {
            *r = sim.register(i as u16);
        }
        // `count` cells from `start` (moved back to fit), zeros around them,
        // perhaps a stray reading elsewhere.
        let n = usize::from(count).min(16);
        let start = start.min(16 - n);
        regs[..16].fill(0);
        regs[start..start + n].copy_from_slice(&values[..n]);
        if let Some((at, v)) = stray {
            regs[at] = v;
        }
        regs[53] = count;
        regs[40] = min_mv;
        regs[41] = max_mv;
        let series = series.map(|n| if n == u16::MAX { count } else { n });
        if from_cells {
            // Registers 40/41 near the true lowest/highest of the selected cells
            // (within, at and beyond both tolerances).
            let probe = RegisterBlock { start: 0, values: heapless::Vec::from_slice(&regs).unwrap() };
            let cells = protocol_core::views::LiveSnapshot::from_registers(&probe).unwrap().cells;
            let mv = |c: Option<(usize, u16)>, d: i32| {
                (i32::from(protocol_core::views::cell_mv(c.map_or(0, |c| c.1))) + d).clamp(0, 65_535) as u16
            };
            regs[40] = mv(cells.min(), deltas.0 / 16);
            regs[41] = mv(cells.max(), if assembled { deltas.1 } else { deltas.1 / 16 });
        }
        let b = RegisterBlock { start: 0, values: heapless::Vec::from_slice(&regs).unwrap() };
        let s = protocol_core::views::LiveSnapshot::from_registers(&b).unwrap();
        let ctx = Context { series_cells: series, assembled };
        let cell_failures = [
            Check::CellCount,
            Check::CellOutsideBlock,
            Check::CellVoltage,
            Check::MinMaxCell,
        ];
        match cell_checks_reference(&b, &s, ctx) {
            Some(e) => proptest::prop_assert_eq!(check_live(&b, &s, ctx), Err(e)),
            None => proptest::prop_assert!(
                !matches!(check_live(&b, &s, ctx), Err(e) if cell_failures.contains(&e))
            ),
        }
    }
}
