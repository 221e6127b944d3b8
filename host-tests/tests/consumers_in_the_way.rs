//! Nothing that listens holds the bridge back: a USB host that opened the port
//! and never reads, a CAN bus nobody acknowledges, a controller that stays
//! bus-off. The station the chip runs, in virtual time against a faulted
//! simulated BMS, once with well-behaved consumers and once with each of
//! those: every request sent to the BMS (its time and bytes), every byte
//! received and every snapshot published (with its time) are identical. What the consumers lost
//! is counted (the host link's `dropped_lines`, the inverter output's failed
//! frames), not hidden. (The broker: `tests/mqtt_in_the_way.rs`.)

use host_tests::sim::{FaultConfig, PackModel, SimBms, SimConfig};
use host_tests::trace::{calls, Call, MAGIC};
use host_tests::virtual_time::Harness;
use protocol_core::views::LiveSnapshot;
use tinybms_firmware::bridge::Action;
use tinybms_firmware::config::Config;
use tinybms_firmware::station::Logged;
use tinybms_firmware::SECOND;

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
        PackModel::LiFePO4_16S,
        SimConfig::default().with_faults(FaultConfig::all(faults)),
        seed,
    );
    let mut station = host_tests::fixtures::station(
        tinybms_firmware::identity::Identity::desktop(
            "sim",
            tinybms_firmware::identity::Features {
                can: true,
                host_link: true,
                ..Default::default()
            },
        ),
        Config::default(),
    );
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
/// back: the same rate of requests within 2 %, and not 2 % fewer snapshots.
/// (More is not held back: since a late live read reads its oldest pieces
/// again instead of starting over, issue 54, two such runs differ by a few %
/// in snapshots either way — 1280 against 1252 here — as two seeds do.)
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
        assert!((p - q) / p < 0.02, "{what}: {q} snapshots against {p}");
    }
}

// ------------------------------------------------- the closed-loop scenarios

use host_tests::closed_loop::{run_scenario_on, ClosedLoop};
use host_tests::virtual_host_port::{Drain, HostPort};
use tinybms_firmware::inverter::InverterConfig;

/// How the loop's consumers misbehave.
#[derive(Clone, Copy, Debug)]
struct Trouble {
    drain: Drain,
    /// The bus never acknowledges: every frame fails (error passive); with
    /// `bus_off`, the controller is also off the bus from the start, for good.
    deaf_bus: bool,
    bus_off: bool,
}

/// What a loop did at the BMS, on the bus and at the host.
struct LoopRun {
    tx: Vec<(u64, Vec<u8>)>,
    rx: Vec<u8>,
    snapshots: Vec<u64>,
    snapshot_values: Vec<LiveSnapshot>,
    frames: Vec<(u64, u16)>,
    limits: Vec<(u64, u16, u16, u16)>,
    port: HostPort,
    deaf_bus: bool,
    bus_off: bool,
}

fn run_loop(name: &str, t: Trouble, charger_a: f64) -> LoopRun {
    run_loop_with(name, t, charger_a, |_| {})
}

fn run_loop_with(
    name: &str,
    t: Trouble,
    charger_a: f64,
    port: impl FnOnce(&mut HostPort),
) -> LoopRun {
    let mut l = ClosedLoop::new_with(
        PackModel::LiFePO4_16S,
        1,
        InverterConfig::default(),
        charger_a,
        true,
    );
    l.h.trace = Some(Vec::new());
    let mut p = HostPort::new(t.drain, 5);
    port(&mut p);
    l.h.host_port = Some(p);
    let (mut l, _) = run_scenario_on(name, l, |l| {
        if t.deaf_bus {
            l.h.can.attached = false;
        }
        if t.bus_off {
            l.h.station.can_bus_off(0);
            l.h.can.bus_off_until = Some(u64::MAX);
        }
    })
    .unwrap();
    let mut trace = MAGIC.to_vec();
    trace.push(0);
    trace.extend(l.h.trace.take().unwrap());
    trace.push(b'E');
    let mut tx = Vec::new();
    let mut rx = Vec::new();
    for call in calls(&trace).unwrap() {
        match call {
            Call::Poll { now, action } => {
                if let Action::Transmit(b) = *action {
                    tx.push((now, b.to_vec()));
                }
            }
            Call::Rx { bytes, .. } => rx.extend(bytes),
        }
    }
    LoopRun {
        tx,
        rx,
        snapshots: l.h.published.iter().map(|(at, _)| *at).collect(),
        snapshot_values: l.h.published.iter().map(|(_, s)| s.clone()).collect(),
        frames: l.sent_ids.clone(),
        limits: l.sent_limits.clone(),
        port: l.h.host_port.take().unwrap(),
        deaf_bus: t.deaf_bus,
        bus_off: t.bus_off,
    }
}

/// A request for the live block (0x03 from register 0, or 0x09 pieces of
/// registers 0-55).
fn is_live_read(b: &[u8]) -> bool {
    match b.get(1) {
        Some(0x03) => b.get(2..4) == Some(&[0, 0]),
        Some(0x09) => b
            .get(3..5)
            .is_some_and(|a| u16::from_le_bytes([a[0], a[1]]) < 56),
        _ => false,
    }
}

/// How far a request or a snapshot may move: four UART chunks (16 bytes
/// each, the RX FIFO's timeout/threshold model), µs.
const SHIFT_US: i64 = 4 * host_tests::virtual_time::RX_CHUNK_US as i64;

/// `Err` (what differs) when `r`'s bridge was held back against
/// `reference`'s: every request the same, in the same order, at the same time
/// within [`SHIFT_US`] (a reply's last bytes are handed in at the station's
/// next wake, which a consumer's timer — the host link's, after a host came
/// back — can bring forward, as on the chip, where every timer wake drains the
/// UART's FIFO); every byte from the BMS the same; every snapshot, within
/// [`SHIFT_US`]; the CAN frames and limits the same where the bus takes them.
fn held_back(reference: &LoopRun, r: &LoopRun) -> Result<String, String> {
    let (ref_tx, r_tx) = (&reference.tx, &r.tx);
    if ref_tx.len() != r_tx.len() {
        return Err(format!("{} requests against {}", r_tx.len(), ref_tx.len()));
    }
    // The live poll: the same requests at the same times. The other reads
    // (events, statistics) all there too; two of them due at nearly the same
    // time may swap when a wake moves a request by a UART chunk.
    let live = |tx: &[(u64, Vec<u8>)]| -> Vec<(u64, Vec<u8>)> {
        tx.iter()
            .filter(|(_, b)| is_live_read(b))
            .cloned()
            .collect()
    };
    let (ref_live, r_live) = (live(ref_tx), live(r_tx));
    if ref_live.len() != r_live.len() {
        return Err(format!(
            "{} live reads against {}",
            r_live.len(),
            ref_live.len()
        ));
    }
    let mut late_us = 0i64;
    let mut early_us = 0i64;
    for (i, ((ta, a), (tb, b))) in ref_live.iter().zip(&r_live).enumerate() {
        if a != b {
            return Err(format!("live read {i}: {b:02x?} against {a:02x?}"));
        }
        late_us = late_us.max(*tb as i64 - *ta as i64);
        early_us = early_us.max(*ta as i64 - *tb as i64);
    }
    if late_us > SHIFT_US || early_us > SHIFT_US {
        return Err(format!(
            "live reads up to {late_us} µs later, {early_us} µs earlier"
        ));
    }
    let others = |tx: &[(u64, Vec<u8>)]| -> Vec<Vec<u8>> {
        let mut v: Vec<Vec<u8>> = tx
            .iter()
            .filter(|(_, b)| !is_live_read(b))
            .map(|(_, b)| b.clone())
            .collect();
        v.sort();
        v
    };
    if others(ref_tx) != others(r_tx) {
        return Err("other reads or writes differ".into());
    }
    // What the BMS said: the same snapshots (the raw bytes may come in
    // another order when two reads swapped).
    if reference.snapshot_values != r.snapshot_values {
        return Err("other snapshot values".into());
    }
    if ref_tx == r_tx && reference.rx != r.rx {
        return Err("other bytes from the BMS".into());
    }
    if reference.snapshots.len() != r.snapshots.len() {
        return Err(format!(
            "{} snapshots against {}",
            r.snapshots.len(),
            reference.snapshots.len()
        ));
    }
    let shift = reference
        .snapshots
        .iter()
        .zip(&r.snapshots)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap_or(0);
    if shift > SHIFT_US as u64 {
        return Err(format!("a snapshot {shift} µs off"));
    }
    if !r.deaf_bus && !r.bus_off && (reference.frames != r.frames || reference.limits != r.limits) {
        return Err("other CAN frames".into());
    }
    Ok(format!(
        "requests up to {late_us} µs later, {early_us} µs earlier, snapshots {shift} µs"
    ))
}

fn check_host_lines(port: &HostPort, what: &str) -> usize {
    let mut pieces = 0;
    for line in port.lines() {
        if line.is_empty() {
            continue;
        }
        let ok = serde_json::from_slice::<serde_json::Value>(line)
            .map(|v| v["type"].is_string())
            .unwrap_or(false);
        if !ok {
            pieces += 1;
        }
    }
    assert!(
        pieces as u64 <= port.dropped,
        "{what}: {pieces} broken lines, {} dropped or cut",
        port.dropped
    );
    pieces
}

#[test]
fn no_consumer_holds_the_closed_loops_back() {
    let good = Trouble {
        drain: Drain::All,
        deaf_bus: false,
        bus_off: false,
    };
    let troubles = [
        Trouble {
            drain: Drain::Never,
            deaf_bus: false,
            bus_off: false,
        },
        Trouble {
            drain: Drain::BytesPerSecond(1),
            deaf_bus: false,
            bus_off: false,
        },
        Trouble {
            drain: Drain::Fits(0.3),
            deaf_bus: false,
            bus_off: false,
        },
        Trouble {
            drain: Drain::All,
            deaf_bus: true,
            bus_off: false,
        },
        Trouble {
            drain: Drain::Never,
            deaf_bus: true,
            bus_off: false,
        },
        Trouble {
            drain: Drain::All,
            deaf_bus: true,
            bus_off: true,
        },
        // All at once.
        Trouble {
            drain: Drain::BytesPerSecond(1),
            deaf_bus: true,
            bus_off: true,
        },
    ];
    for name in host_tests::closed_loop::SCENARIOS {
        let reference = run_loop(name, good, 100.0);
        // Without limits on the bus the charger would run otherwise, and the
        // pack with it (other values, other reads): the deaf bus is compared
        // with a charger that does nothing either way.
        let idle_reference = run_loop(name, good, 0.0);
        assert!(reference.tx.len() > 1000, "{name}");
        assert!(reference.port.lines().len() > 100, "{name}");
        assert_eq!(check_host_lines(&reference.port, name), 0, "{name}");
        assert_eq!(reference.port.dropped, 0, "{name}");
        for t in troubles {
            let what = format!("{name}, {t:?}");
            let (reference, r) = if t.deaf_bus || t.bus_off {
                (&idle_reference, run_loop(name, t, 0.0))
            } else {
                (&reference, run_loop(name, t, 100.0))
            };
            let shifts = held_back(reference, &r).unwrap_or_else(|e| panic!("{what}: {e}"));
            let pieces = check_host_lines(&r.port, &what);
            println!(
                "{what}: {} requests, {} snapshots as without trouble ({shifts}); host got {} lines \
                 ({pieces} pieces), {} dropped",
                r.tx.len(),
                r.snapshots.len(),
                r.port.lines().len(),
                r.port.dropped
            );
        }
    }
}

/// The comparison above can fail: a writer that waits by spinning (the CPU is
/// its while the host does not read, as the old driver loop's), with the
/// library's bounds or without them, holds the bridge back, and the same
/// measure says so.
#[test]
fn a_writer_that_spins_or_waits_unbounded_is_caught() {
    let good = Trouble {
        drain: Drain::All,
        deaf_bus: false,
        bus_off: false,
    };
    let deaf = Trouble {
        drain: Drain::Never,
        deaf_bus: false,
        bus_off: false,
    };
    let reference = run_loop("bms-fault", good, 100.0);
    let bounded_spin = run_loop_with("bms-fault", deaf, 100.0, |p| p.spins = true);
    let e = held_back(&reference, &bounded_spin).expect_err("a spinning writer must be seen");
    println!("spinning writer, bounded waits: {e}");
    let unbounded = run_loop_with("bms-fault", deaf, 100.0, |p| {
        p.spins = true;
        p.unbounded = true;
    });
    let e = held_back(&reference, &unbounded).expect_err("an unbounded writer must be seen");
    println!("spinning writer, no bound: {e}");
    // The same host, the writer waiting as the chip's does: not held back.
    held_back(&reference, &run_loop("bms-fault", deaf, 100.0)).unwrap();
}
