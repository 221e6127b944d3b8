//! Nothing that listens holds the bridge back: a USB host that opened the port
//! and never reads, a CAN bus nobody acknowledges, a controller that stays
//! bus-off. The station the chip runs, in virtual time against a faulted
//! simulated BMS, once with well-behaved consumers and once with each of
//! those: every request sent to the BMS (its time and bytes), every byte
//! received and every snapshot published (with its time) are identical. What the consumers lost
//! is counted (the host link's `dropped_lines`, the inverter output's failed
//! frames), not hidden. (The broker: `tests/mqtt_in_the_way.rs`.)
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::indexing_slicing)]

use host_tests::harness::Harness;
use host_tests::sim::{FaultConfig, PackProfile, SimBms, SimConfig};
use host_tests::trace::{calls, Call, MAGIC};
use protocol_core::views::LiveSnapshot;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::store::{Loaded, Source};
use tinybms_firmware::config::Config;
use tinybms_firmware::station::{Logged, Setup, Station};
use tinybms_firmware::{Action, SECOND};

/// How each consumer behaves.
#[derive(Clone, Copy)]
struct Consumers {
    host_reads: bool,
    can_acks: bool,
    bus_off: bool,
}

const GOOD: Consumers = Consumers {
    host_reads: true,
    can_acks: true,
    bus_off: false,
};

/// What the BMS saw and what was published.
struct Run {
    /// (time, bytes) of every transmit and every receive, in order.
    wire: Vec<(u64, bool, Vec<u8>)>,
    /// (time, snapshot) of every snapshot published.
    published: Vec<(u64, LiveSnapshot)>,
    dropped_lines: u32,
    host_lines: usize,
    can_frames: usize,
    can_failures: usize,
}

fn run(c: Consumers, faults: f64, seed: u64, duration_us: u64) -> Run {
    let sim = SimBms::new(
        PackProfile::LiFePO4_16S,
        SimConfig::default().with_faults(FaultConfig::all(faults)),
        seed,
    );
    let setup = Setup {
        timing: Timing::default(),
        chip: "sim",
        host_link: true,
        can: true,
        inverter: None,
    };
    let loaded = Loaded {
        config: Config::default(),
        source: Source::Empty,
    };
    let mut station = Station::new(setup, loaded, 0);
    // A host opened the port (so `hello` and the telemetry stream are due).
    station.host_connected(0);
    let mut h = Harness::with_station(sim, station);
    h.trace = Some(Vec::new());
    h.host_lines = c.host_reads.then(Vec::new);
    h.can.attached = c.can_acks;
    if c.bus_off {
        h.station.can_bus_off(0);
        h.can.bus_off_until = Some(u64::MAX);
    }
    h.run_until(duration_us);
    let mut trace = MAGIC.to_vec();
    trace.push(0);
    trace.extend(h.trace.take().unwrap());
    trace.push(b'E');
    let wire = calls(&trace)
        .expect("a well-formed trace")
        .into_iter()
        .filter_map(|call| match call {
            Call::Poll { now, action } => match *action {
                Action::Transmit(t) => Some((now, true, t.to_vec())),
                Action::WaitUntil(_) => None,
            },
            Call::Rx { now, bytes } => Some((now, false, bytes)),
        })
        .collect();
    let can_failures = h
        .other_log
        .iter()
        .filter(|(_, l)| {
            matches!(
                l,
                Logged::Inverter(
                    tinybms_firmware::inverter::InverterReport::NoAck { .. }
                        | tinybms_firmware::inverter::InverterReport::BusOff { .. }
                )
            )
        })
        .count();
    Run {
        wire,
        published: std::mem::take(&mut h.published),
        dropped_lines: h.station.host_link().map_or(0, |l| l.stats().dropped_lines),
        host_lines: h.host_lines.as_ref().map_or(0, Vec::len),
        can_frames: h.can.outbox.len(),
        can_failures,
    }
}

/// The requests (time and bytes), every byte received (in order: how the
/// bytes are cut into chunks follows the station's wake times, which the
/// consumers change) and every snapshot (with its time).
fn assert_same_bridge(good: &Run, other: &Run, what: &str) {
    let tx = |r: &Run| -> Vec<(u64, Vec<u8>)> {
        r.wire
            .iter()
            .filter(|(_, t, _)| *t)
            .map(|(at, _, b)| (*at, b.clone()))
            .collect()
    };
    let rx = |r: &Run| -> Vec<u8> {
        r.wire
            .iter()
            .filter(|(_, t, _)| !*t)
            .flat_map(|(_, _, b)| b.clone())
            .collect()
    };
    let (a, b) = (tx(good), tx(other));
    assert!(a.len() > 1000, "{}", a.len());
    assert_eq!(a.len(), b.len(), "{what}: requests");
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        assert_eq!(x, y, "{what}: request {i} differs");
    }
    assert_eq!(rx(good), rx(other), "{what}: bytes received");
    assert_eq!(good.published, other.published, "{what}: snapshots");
}

#[test]
fn a_host_that_never_reads_and_a_bus_that_never_acks_change_nothing_at_the_bms() {
    let duration = 600 * SECOND;
    let good = run(GOOD, 0.03, 41, duration);
    assert!(good.published.len() > 800, "{}", good.published.len());
    assert!(good.host_lines > 500, "{}", good.host_lines);
    assert!(good.can_frames > 1000, "{}", good.can_frames);
    assert_eq!(good.can_failures, 0);

    let deaf_host = run(
        Consumers {
            host_reads: false,
            ..GOOD
        },
        0.03,
        41,
        duration,
    );
    assert_same_bridge(&good, &deaf_host, "a host that never reads");
    // Its lines were dropped whole and counted.
    assert!(deaf_host.dropped_lines > 500, "{}", deaf_host.dropped_lines);

    let no_ack = run(
        Consumers {
            can_acks: false,
            ..GOOD
        },
        0.03,
        41,
        duration,
    );
    assert_same_bridge(&good, &no_ack, "a bus nobody acknowledges");
    assert_eq!(no_ack.can_frames, 0);
    assert!(no_ack.can_failures > 0, "the failures are logged");

    println!(
        "600 s faulted: {} wire entries, {} snapshots; host never reading: {} lines dropped; \
         CAN unacknowledged: {} failures logged",
        good.wire.len(),
        good.published.len(),
        deaf_host.dropped_lines,
        no_ack.can_failures
    );
}

/// A controller that stays bus-off makes the inverter output wake at other
/// times (its recovery backoff), so the station wakes at other times and a
/// reply can be handed in cut at another byte (on the chip too: every timer
/// wake drains the UART's FIFO). On a clean line that changes nothing; on a
/// faulted one the bridge decides a few edge cases differently (a reply that
/// trickles in around a timeout), so there the measure is that it is not held
/// back: the same rate of requests and snapshots within 2 %.
#[test]
fn a_controller_that_stays_bus_off_does_not_hold_the_bridge_back() {
    let duration = 600 * SECOND;
    let all_bad = Consumers {
        host_reads: false,
        can_acks: false,
        bus_off: true,
    };
    let bus_off = Consumers {
        bus_off: true,
        ..GOOD
    };
    // A clean line: identical.
    let good = run(GOOD, 0.0, 7, duration);
    assert!(good.published.len() > 2300, "{}", good.published.len());
    for (c, what) in [(bus_off, "bus-off"), (all_bad, "all three")] {
        let r = run(c, 0.0, 7, duration);
        assert_same_bridge(&good, &r, what);
        assert_eq!(r.can_frames, 0);
    }
    // A faulted line: not held back.
    let good = run(GOOD, 0.03, 41, duration);
    for (c, what) in [(bus_off, "bus-off"), (all_bad, "all three")] {
        let r = run(c, 0.03, 41, duration);
        let requests = |r: &Run| r.wire.iter().filter(|(_, t, _)| *t).count() as f64;
        let (a, b) = (requests(&good), requests(&r));
        let (p, q) = (good.published.len() as f64, r.published.len() as f64);
        println!("{what}, faulted: {b} requests against {a}, {q} snapshots against {p}");
        assert!((a - b).abs() / a < 0.02, "{what}: {b} requests against {a}");
        assert!(
            (p - q).abs() / p < 0.02,
            "{what}: {q} snapshots against {p}"
        );
    }
}
