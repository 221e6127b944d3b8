//! The firmware's MQTT output against a real broker: Debian's `mosquitto` on
//! loopback (no root needed), fed by the firmware's bridge running against the
//! simulated BMS in real time — the library's publisher and session, the code
//! the chip runs, here over a host TCP socket. The scenario itself (what the
//! broker must deliver, every wait bounded) is `host_tests::mqtt_e2e`, shared
//! with the network-namespace test (`tests/mqtt_tap.rs`) where the session runs
//! over embassy-net, the chip's network stack.
//!
//! Needs `mosquitto` and `mosquitto_sub`/`mosquitto_pub` (Debian: `apt-get install
//! mosquitto mosquitto-clients`; `.ci/run` installs them).

use host_tests::mqtt::{self as hm, TcpNet};
use host_tests::mqtt_e2e;
use tinybms_firmware::identity::Identity;
use tinybms_firmware::mqtt::session::{Failure, Note, Target};
use tinybms_firmware::mqtt::Settings;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

#[test]
fn the_broker_gets_what_home_assistant_needs_and_the_session_survives_its_trouble() {
    let port = free_port();
    let summary = mqtt_e2e::scenario("127.0.0.1", port, |b| {
        let mut t = Target::from_config(&mqtt_e2e::config(), "tinybms-test");
        t.host.push_str("127.0.0.1").unwrap();
        t.port = port;
        let net = TcpNet::default();
        let kill = net.kill.clone();
        let notes = hm::spawn(
            t,
            (Settings::from_config(&mqtt_e2e::config()), bridge()),
            b.shared.clone(),
            b.clock,
            net,
            false,
        );
        Ok((kill, notes))
    })
    .unwrap_or_else(|e| panic!("{e}"));
    println!("{summary}");
}

fn bridge() -> Identity {
    Identity::desktop("sim", Default::default())
}

/// Two bridges with one client id (two bridges given one `hostname`, a
/// try-out beside a bridge): mosquitto drops each as the other connects, with
/// no reason this session reads (mosquitto 2.0.11 closes the old
/// connection). Each says so in its log within a few reconnects instead
/// of flapping in silence; bridges with their own ids connect once and stay.
#[test]
fn a_client_id_taken_by_another_bridge_is_named_in_the_log() {
    let port = free_port();
    let broker = mqtt_e2e::Broker::start("127.0.0.1", port).unwrap();
    let bridge_thread = mqtt_e2e::BridgeThread::start().unwrap();
    let start = |id: &str| {
        let mut t = Target::from_config(&mqtt_e2e::config(), id);
        t.host.push_str("127.0.0.1").unwrap();
        t.port = port;
        hm::spawn(
            t,
            (Settings::from_config(&mqtt_e2e::config()), bridge()),
            bridge_thread.shared.clone(),
            bridge_thread.clock,
            TcpNet::default(),
            false,
        )
    };
    let a = start("tinybms-same");
    let b = start("tinybms-same");
    let c = start("tinybms-other");
    let taken = |n: &hm::Notes| {
        n.lock()
            .unwrap()
            .iter()
            .any(|n| matches!(n, Note::Disconnected(Failure::TakenOver, _)))
    };
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(40);
    while !(taken(&a) && taken(&b)) && std::time::Instant::now() < deadline {
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
    println!("a: {:?}\nb: {:?}", a.lock().unwrap(), b.lock().unwrap());
    assert!(
        taken(&a) && taken(&b),
        "the taken client id was never named"
    );
    let c = c.lock().unwrap();
    assert!(c.contains(&Note::Connected), "{c:?}");
    assert!(
        !c.iter()
            .any(|n| matches!(n, Note::Disconnected(..) | Note::Failed(..))),
        "the bridge with its own id was disturbed: {c:?}"
    );
    drop(broker);
}
