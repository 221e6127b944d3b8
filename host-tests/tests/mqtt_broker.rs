//! The firmware's MQTT output against a real broker: Debian's `mosquitto` on
//! loopback (no root needed), fed by the firmware's bridge running against the
//! simulated BMS in real time — the library's publisher and session, the code
//! the chip runs.
//!
//! What the broker delivers is checked with `mosquitto_sub`: the retained
//! discovery configs and availability, state values equal to what the simulated
//! BMS sent, the will on a dropped connection, re-announcement on Home
//! Assistant's `online`, reconnection after the broker restarts, and
//! availability `offline` while the BMS link is lost. Every wait is bounded;
//! every child process is killed when its guard drops.
//!
//! Needs `mosquitto` and `mosquitto_sub`/`mosquitto_pub` (Debian: `apt-get install
//! mosquitto mosquitto-clients`; `.ci/run` installs them).
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use host_tests::flash::{RamFlash, SimFlash};
use host_tests::hosted::{Hosted, NoHost};
use host_tests::mqtt::{self as hm, Shared, TcpNet};
use host_tests::realtime::SimPort;
use host_tests::replay::register_values;
use host_tests::sim::{PackProfile, SimBms, SimConfig};
use serde_json::Value;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::Config;
use tinybms_firmware::mqtt::session::{Note, Target};
use tinybms_firmware::mqtt::Settings;

/// The longest any one expectation may take (a bound, not a timing check).
const WAIT: Duration = Duration::from_secs(30);

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// `mosquitto` on 127.0.0.1:port, killed on drop.
struct Broker {
    child: Child,
    port: u16,
    _conf: std::path::PathBuf,
}

impl Broker {
    fn start(port: u16) -> Broker {
        let conf = std::env::temp_dir().join(format!(
            "tinybms-mosquitto-{}-{port}.conf",
            std::process::id()
        ));
        std::fs::write(
            &conf,
            format!("listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"),
        )
        .unwrap();
        let child = Command::new("mosquitto")
            .args(["-c", conf.to_str().unwrap()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto (apt-get install mosquitto mosquitto-clients)");
        let end = Instant::now() + WAIT;
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < end, "mosquitto did not listen on {port}");
            std::thread::sleep(Duration::from_millis(50));
        }
        Broker {
            child,
            port,
            _conf: conf,
        }
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One message as `mosquitto_sub` printed it.
#[derive(Debug, Clone)]
struct Msg {
    retained: bool,
    topic: String,
    payload: String,
    at: Instant,
}

/// `mosquitto_sub -t '#'`, collecting every message; killed on drop.
struct Sub {
    child: Child,
    msgs: Arc<Mutex<Vec<Msg>>>,
}

impl Sub {
    fn start(port: u16) -> Sub {
        let mut child = Command::new("mosquitto_sub")
            .args([
                "-h",
                "127.0.0.1",
                "-p",
                &port.to_string(),
                "-t",
                "#",
                "-F",
                "%r\t%t\t%p",
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto_sub");
        let out = child.stdout.take().unwrap();
        let msgs: Arc<Mutex<Vec<Msg>>> = Arc::default();
        let m = msgs.clone();
        std::thread::spawn(move || {
            // One message a line: no payload of the bridge holds a newline.
            for line in BufReader::new(out).split(b'\n').map_while(Result::ok) {
                let text = String::from_utf8_lossy(&line).into_owned();
                let mut parts = text.splitn(3, '\t');
                let (Some(r), Some(t)) = (parts.next(), parts.next()) else {
                    continue;
                };
                m.lock().unwrap().push(Msg {
                    retained: r == "1",
                    topic: t.to_string(),
                    payload: parts.next().unwrap_or("").to_string(),
                    at: Instant::now(),
                });
            }
        });
        Sub { child, msgs }
    }

    fn all(&self) -> Vec<Msg> {
        self.msgs.lock().unwrap().clone()
    }

    /// Waits until `pred` holds for the messages since `from`; returns them.
    fn wait(&self, from: Instant, what: &str, pred: impl Fn(&[Msg]) -> bool) -> Vec<Msg> {
        let end = Instant::now() + WAIT;
        loop {
            let since: Vec<Msg> = self.all().into_iter().filter(|m| m.at >= from).collect();
            if pred(&since) {
                return since;
            }
            assert!(
                Instant::now() < end,
                "{what}: not seen within {WAIT:?}; got {:#?}",
                tail(&since)
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

fn tail(m: &[Msg]) -> Vec<String> {
    m.iter()
        .rev()
        .take(8)
        .map(|m| format!("{} {}", m.topic, &m.payload[..m.payload.len().min(80)]))
        .collect()
}

impl Drop for Sub {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn publish(port: u16, topic: &str, payload: &str) {
    let ok = Command::new("mosquitto_pub")
        .args([
            "-h",
            "127.0.0.1",
            "-p",
            &port.to_string(),
            "-t",
            topic,
            "-m",
            payload,
        ])
        .status()
        .expect("mosquitto_pub")
        .success();
    assert!(ok);
}

/// The bridge against the simulated BMS in real time on a thread, feeding
/// `shared`; `silent_until_s` makes the BMS silent (virtual seconds of the sim).
struct Bridge {
    stop: Arc<AtomicBool>,
    silent_until_us: Arc<AtomicU64>,
    /// seq -> the live registers the bridge published with that snapshot.
    published: Arc<Mutex<BTreeMap<u32, BTreeMap<u16, u16>>>>,
    join: Option<std::thread::JoinHandle<()>>,
    clock: host_tests::realtime::Clock,
}

impl Bridge {
    fn start(shared: Shared) -> Bridge {
        let stop = Arc::new(AtomicBool::new(false));
        let silent = Arc::new(AtomicU64::new(0));
        let published: Arc<Mutex<BTreeMap<u32, BTreeMap<u16, u16>>>> = Arc::default();
        let (s, q, p) = (stop.clone(), silent.clone(), published.clone());
        let (tx, rx) = std::sync::mpsc::channel();
        let join = std::thread::spawn(move || {
            let sim = SimBms::new(PackProfile::LiFePO4_16S, SimConfig::default(), 5);
            let mut h = Hosted::new(
                SimPort::new(sim),
                Timing::default(),
                SimFlash::Ram(RamFlash::new()),
                "sim",
            );
            h.mqtt = Some(shared);
            tx.send(h.driver.clock()).unwrap();
            let mut seen = 0;
            while !s.load(Ordering::Relaxed) {
                let until = q.load(Ordering::Relaxed);
                if until > 0 {
                    h.driver.port.sim.set_silent_until(until);
                    q.store(0, Ordering::Relaxed);
                }
                h.step(&mut NoHost).unwrap();
                let t = h.driver.bridge.telemetry();
                if t.snapshot_seq != seen {
                    seen = t.snapshot_seq;
                    if let Some(b) = &t.live_registers {
                        p.lock().unwrap().insert(seen, b.iter().collect());
                    }
                }
            }
        });
        let clock = rx.recv_timeout(WAIT).unwrap();
        Bridge {
            stop,
            silent_until_us: silent,
            published,
            join: Some(join),
            clock,
        }
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(j) = self.join.take() {
            let _ = j.join();
        }
    }
}

fn target(port: u16) -> Target {
    let mut t = Target::from_config(&Config::default(), "tinybms-test");
    t.host.push_str("127.0.0.1").unwrap();
    t.port = port;
    t
}

fn json(s: &str) -> Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("{e}: {s}"))
}

#[test]
fn the_broker_gets_what_home_assistant_needs_and_the_session_survives_its_trouble() {
    let port = free_port();
    let broker = Broker::start(port);
    let shared = Shared::default();
    let bridge = Bridge::start(shared.clone());
    let net = TcpNet::default();
    let notes = hm::spawn(
        target(port),
        Settings::from_config(&Config::default()),
        shared.clone(),
        bridge.clock,
        net.clone(),
        false,
    );
    let start = Instant::now();

    // Retained configs, availability online, and states.
    let sub = Sub::start(port);
    let got = sub.wait(start, "configs, availability and 3 states", |m| {
        m.iter().filter(|x| x.topic.ends_with("/config")).count() >= 34
            && m.iter()
                .any(|x| x.topic.ends_with("/availability") && x.payload == "online")
            && m.iter().filter(|x| x.topic.ends_with("/state")).count() >= 3
    });
    let configs: Vec<&Msg> = got
        .iter()
        .filter(|x| x.topic.ends_with("/config"))
        .collect();
    // A 16-cell pack: every config announces, none removes.
    assert!(
        configs.iter().all(|c| !c.payload.is_empty()),
        "a config removed"
    );
    for c in &configs {
        let v = json(&c.payload);
        assert!(
            v["unique_id"].as_str().unwrap().starts_with("tinybms_"),
            "{}",
            c.payload
        );
    }
    let serial = configs[0]
        .topic
        .split('/')
        .nth(2)
        .unwrap()
        .trim_start_matches("tinybms_")
        .to_string();
    let avail = format!("tinybms/{serial}/availability");
    // The state's values are what the simulated BMS sent: each state is the
    // snapshot of its `seq`, decoded independently here (replay's decoder) from
    // the registers the bridge published.
    let states: Vec<Value> = got
        .iter()
        .filter(|x| x.topic.ends_with("/state"))
        .map(|x| json(&x.payload))
        .collect();
    let published = bridge.published.lock().unwrap().clone();
    for s in &states {
        assert!(!s["retained"].as_bool().unwrap_or(false));
        let seq = s["seq"].as_u64().unwrap() as u32;
        let regs = published
            .get(&seq)
            .unwrap_or_else(|| panic!("state of seq {seq} that was never published"));
        let truth = register_values(regs);
        for k in [
            "pack_voltage_v",
            "pack_current_a",
            "min_cell_voltage_v",
            "max_cell_voltage_v",
            "cell_voltages_v",
            "soc_percent",
            "soh_percent",
            "internal_temperature_c",
            "external_temperature_1_c",
            "external_temperature_2_c",
            "online_status",
        ] {
            assert_eq!(s[k], truth[k], "seq {seq}: {k}");
        }
    }
    // Retained messages seen by a late subscriber: configs and availability.
    let late = Sub::start(port);
    let retained = late.wait(Instant::now() - Duration::from_secs(1), "retained", |m| {
        m.iter()
            .filter(|x| x.retained && x.topic.ends_with("/config"))
            .count()
            >= 34
            && m.iter()
                .any(|x| x.retained && x.topic == avail && x.payload == "online")
    });
    assert!(!retained
        .iter()
        .any(|x| x.retained && x.topic.ends_with("/state")));
    drop(late);

    // Home Assistant says it is back: the configs again.
    let t = Instant::now();
    publish(port, "homeassistant/status", "online");
    sub.wait(t, "re-announced configs", |m| {
        m.iter().filter(|x| x.topic.ends_with("/config")).count() >= 34
    });

    // The connection drops without a DISCONNECT: the broker publishes the will;
    // the session reconnects and says online again.
    let t = Instant::now();
    net.kill();
    sub.wait(t, "the will, then online again", |m| {
        let off = m
            .iter()
            .position(|x| x.topic == avail && x.payload == "offline");
        off.is_some_and(|i| {
            m[i..]
                .iter()
                .any(|x| x.topic == avail && x.payload == "online")
        })
    });

    // The BMS link is lost: availability offline (published, not the will),
    // no state while the data is stale; back online after.
    let t = Instant::now();
    let now_sim = bridge.clock.now();
    bridge
        .silent_until_us
        .store(now_sim + 20_000_000, Ordering::Relaxed);
    let m = sub.wait(t, "offline while the BMS is silent", |m| {
        m.iter().any(|x| x.topic == avail && x.payload == "offline")
    });
    let off_at = m
        .iter()
        .find(|x| x.topic == avail && x.payload == "offline")
        .unwrap()
        .at;
    let m = sub.wait(t, "online again after the BMS is back", |m| {
        m.iter()
            .any(|x| x.topic == avail && x.payload == "online" && x.at > off_at)
    });
    let on_at = m
        .iter()
        .filter(|x| x.topic == avail && x.payload == "online")
        .last()
        .unwrap()
        .at;
    let stale_states = m
        .iter()
        .filter(|x| {
            x.topic.ends_with("/state")
                && x.at > off_at + Duration::from_millis(200)
                && x.at < on_at
        })
        .count();
    assert_eq!(
        stale_states, 0,
        "a state was published while the BMS data was stale"
    );

    // The broker restarts: the session reconnects and announces again.
    drop(sub);
    drop(broker);
    std::thread::sleep(Duration::from_millis(500));
    let broker = Broker::start(port);
    let t = Instant::now();
    let sub = Sub::start(broker.port);
    sub.wait(t, "configs after the broker's restart", |m| {
        m.iter().filter(|x| x.topic.ends_with("/config")).count() >= 34
            && m.iter().any(|x| x.topic == avail && x.payload == "online")
    });
    // And the new broker holds them retained.
    let late = Sub::start(broker.port);
    late.wait(
        Instant::now() - Duration::from_secs(1),
        "retained after the restart",
        |m| {
            m.iter()
                .filter(|x| x.retained && x.topic.ends_with("/config"))
                .count()
                >= 34
        },
    );
    let notes = notes.lock().unwrap().clone();
    let connects = notes
        .iter()
        .filter(|n| matches!(n, Note::Connected))
        .count();
    assert!(connects >= 3, "{notes:?}");
    let _ = std::io::stderr().flush();
    println!("session notes: {notes:?}");
}
