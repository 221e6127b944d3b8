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
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]

use host_tests::mqtt::{self as hm, TcpNet};
use host_tests::mqtt_e2e;
use tinybms_firmware::mqtt::session::Target;
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
            Settings::from_config(&mqtt_e2e::config()),
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
