//! `sim --mqtt` as an owner tries Home Assistant without hardware (issue 29,
//! item 2; issue 26, item 14): against Debian's `mosquitto` on loopback, the
//! simulated bridge publishes what a wired chip would — the limits its
//! inverter output sends, its CAN state, the inverter heard —, its
//! `--config` options apply from the start, every simulated bridge has its own
//! serial and client id, and `--packs N --mqtt` publishes every pack and the
//! battery's device. (The real Home Assistant reads all of it in
//! `host-tests/home-assistant/check.py`, run by `.ci/run`.)

use std::process::{Child, Command, Stdio};
use std::time::Instant;

use host_tests::mqtt_e2e::{Broker, Msg, Sub};

mod common;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A `sim` process, killed on drop.
struct SimProc(Child);

impl SimProc {
    fn start(args: &[&str]) -> SimProc {
        SimProc(
            Command::new(env!("CARGO_BIN_EXE_sim"))
                .args(args)
                .args(["--duration", "60s", "--quiet"])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .unwrap(),
        )
    }
}

impl Drop for SimProc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn json(m: &Msg) -> serde_json::Value {
    serde_json::from_str(&m.payload).unwrap_or_else(|e| panic!("{e}: {}", m.payload))
}

fn state_topics(msgs: &[Msg], prefix: &str) -> Vec<String> {
    let mut t: Vec<String> = msgs
        .iter()
        .filter(|m| m.topic.starts_with(prefix) && m.topic.ends_with("/state"))
        .map(|m| m.topic.clone())
        .collect();
    t.sort();
    t.dedup();
    t
}

#[test]
fn the_try_out_publishes_what_a_wired_bridge_would_with_its_own_options() {
    let port = free_port();
    let broker = Broker::start("127.0.0.1", port).unwrap();
    let sub = Sub::start(&broker).unwrap();
    let mqtt = format!("127.0.0.1:{port}");
    let from = Instant::now();
    let _a = SimProc::start(&[
        "--mqtt",
        &mqtt,
        "--config",
        "topic_prefix=trial",
        "--config",
        "publish_period=7",
    ]);
    // The state under the prefix given, with what the inverter output sends.
    let msgs = sub
        .wait(from, "a state with limits under trial/", |m| {
            m.iter().any(|m| {
                m.topic.starts_with("trial/")
                    && m.topic.ends_with("/state")
                    && json(m)["cvl_v"].is_number()
            })
        })
        .unwrap();
    let state = msgs
        .iter()
        .rev()
        .find(|m| m.topic.starts_with("trial/") && m.topic.ends_with("/state"))
        .map(json)
        .unwrap();
    assert!(state["ccl_a"].as_f64().unwrap() > 0.0, "{state}");
    assert!(state["dcl_a"].as_f64().unwrap() > 0.0, "{state}");
    assert_eq!(state["can_state"], "running", "{state}");
    assert_eq!(state["inverter_heard"], true, "{state}");
    // A simulated Wi-Fi signal, as a chip's would be: a plausible RSSI.
    let rssi = state["wifi_rssi_dbm"].as_i64().unwrap_or(0);
    assert!((-90..=-30).contains(&rssi), "{state}");
    // The configs say where the state is and when it expires: 3 x 7 s.
    let configs = sub
        .wait(from, "the configs", |m| {
            m.iter().any(|m| m.topic.ends_with("/pack_voltage/config"))
        })
        .unwrap();
    let cfg = configs
        .iter()
        .find(|m| m.topic.ends_with("/pack_voltage/config"))
        .map(json)
        .unwrap();
    assert!(
        cfg["state_topic"].as_str().unwrap().starts_with("trial/"),
        "{cfg}"
    );
    assert_eq!(cfg["expire_after"], 21, "{cfg}");
    // A second try-out of another seed: its own device, and neither throws
    // the other off (client ids after the serials).
    let from2 = Instant::now();
    // A seed no default try-out is handed (those take the lowest free one
    // from 1, and the other tests of this file run theirs beside this one).
    let _b = SimProc::start(&["--mqtt", &mqtt, "--seed", "1000"]);
    sub.wait(from2, "the second bridge's state", |m| {
        state_topics(m, "tinybms/").len() == 1
    })
    .unwrap();
    std::thread::sleep(std::time::Duration::from_secs(8));
    let since = sub.wait(from2, "", |_| true).unwrap();
    let trial = since
        .iter()
        .filter(|m| m.topic.starts_with("trial/") && m.topic.ends_with("/state"))
        .count();
    assert!(trial >= 1, "the first bridge stopped publishing");
    // Offline after having been online (a bridge starts `offline` until its
    // first data).
    let mut online = std::collections::HashSet::new();
    let mut dropped = Vec::new();
    for m in since.iter().filter(|m| m.topic.ends_with("/availability")) {
        match m.payload.as_str() {
            "online" => {
                online.insert(m.topic.clone());
            }
            _ if online.contains(&m.topic) => dropped.push(m.topic.clone()),
            _ => {}
        }
    }
    assert!(dropped.is_empty(), "offline beside the other: {dropped:?}");
    let serial = |t: &str| t.split('/').nth(1).unwrap_or("").to_string();
    let a = state_topics(&since, "trial/");
    let b = state_topics(&since, "tinybms/");
    assert_ne!(serial(&a[0]), serial(&b[0]), "two seeds, one serial");
    drop(broker);
}

#[test]
fn packs_on_mqtt_publish_every_pack_and_the_battery() {
    let port = free_port();
    let broker = Broker::start("127.0.0.1", port).unwrap();
    let sub = Sub::start(&broker).unwrap();
    let mqtt = format!("127.0.0.1:{port}");
    let from = Instant::now();
    let _p = SimProc::start(&["--packs", "3", "--mqtt", &mqtt]);
    let msgs = sub
        .wait(from, "three packs and the battery", |m| {
            state_topics(m, "tinybms/").len() == 4
                && m.iter()
                    .any(|m| m.topic == "tinybms/battery/state" && json(m)["packs_online"] == 3)
        })
        .unwrap();
    let battery = msgs
        .iter()
        .rev()
        .find(|m| m.topic == "tinybms/battery/state")
        .map(json)
        .unwrap();
    assert!(battery["cvl_v"].is_number(), "{battery}");
    // The battery's device: every one of its configs, under one device id.
    let mut configs: Vec<&str> = msgs
        .iter()
        .filter(|m| m.topic.contains("/tinybms_battery_tinybms/") && !m.payload.is_empty())
        .map(|m| m.topic.as_str())
        .collect();
    configs.sort();
    configs.dedup();
    assert_eq!(
        configs.len(),
        tinybms_firmware::mqtt::battery::ENTITIES.len(),
        "{configs:?}"
    );
    drop(broker);
}

#[test]
fn packs_on_mqtt_refuse_a_scenario() {
    let out = Command::new(env!("CARGO_BIN_EXE_sim"))
        .args([
            "--packs",
            "2",
            "--mqtt",
            "127.0.0.1:1",
            "--scenario",
            "full-charge",
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--scenario goes without them"), "{err}");
}

/// Two bridges with one client id (here two try-outs of one `--seed`): each
/// says so in `hello`, and `tinybms version` puts it in words, instead of
/// both flapping in silence.
#[test]
fn a_taken_client_id_is_in_hello_and_tinybms_version() {
    let port = free_port();
    let _broker = Broker::start("127.0.0.1", port).unwrap();
    let mqtt = format!("127.0.0.1:{port}");
    let a = common::Sim::start(&["--bridge-pty", "--mqtt", &mqtt, "--quiet", "--seed", "1"]);
    let _b = common::Sim::start(&["--bridge-pty", "--mqtt", &mqtt, "--quiet", "--seed", "1"]);
    let end = Instant::now() + std::time::Duration::from_secs(60);
    let mut last = None;
    while Instant::now() < end {
        let v = common::tinybms(&["version", &a.path, "--json"]);
        if v.code == 0 {
            let line: serde_json::Value = serde_json::from_str(v.stdout.trim()).unwrap();
            if line["bridge"]["mqtt"] == "client_id_taken" {
                let text = common::tinybms(&["version", &a.path]);
                assert!(
                    text.stdout
                        .contains("another client uses this bridge's client id"),
                    "{text}"
                );
                return;
            }
            last = Some(line);
        }
        std::thread::sleep(std::time::Duration::from_secs(1));
    }
    panic!("never said: {last:?}");
}

/// A `sim` whose stderr is kept (its seed line, its log), and the pty path
/// when it has one; killed on drop.
struct Logged {
    child: Child,
    stderr: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    path: Option<String>,
}

impl Logged {
    fn start(args: &[&str]) -> Logged {
        use std::io::{BufRead, BufReader};
        let mut child = Command::new(env!("CARGO_BIN_EXE_sim"))
            .args(args)
            .args(["--duration", "120s"])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let stderr: std::sync::Arc<std::sync::Mutex<Vec<String>>> = Default::default();
        let (err, lines) = (child.stderr.take().unwrap(), stderr.clone());
        std::thread::spawn(move || {
            for l in BufReader::new(err).lines().map_while(Result::ok) {
                lines.lock().unwrap().push(l);
            }
        });
        let out = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut r = BufReader::new(out);
            let mut first = String::new();
            let _ = r.read_line(&mut first);
            let _ = tx.send(first);
            let mut sink = Vec::new();
            let _ = std::io::Read::read_to_end(&mut r, &mut sink);
        });
        let path = args.contains(&"--bridge-pty").then(|| {
            let line = rx
                .recv_timeout(std::time::Duration::from_secs(60))
                .expect("sim printed its pty path");
            line.trim().to_string()
        });
        Logged {
            child,
            stderr,
            path,
        }
    }

    fn lines(&self) -> Vec<String> {
        self.stderr.lock().unwrap().clone()
    }

    /// Waits (bounded) for a stderr line that contains `what`.
    fn wait_for(&self, what: &str) -> String {
        let end = Instant::now() + std::time::Duration::from_secs(40);
        loop {
            if let Some(l) = self.lines().into_iter().find(|l| l.contains(what)) {
                return l;
            }
            assert!(Instant::now() < end, "no `{what}` in {:#?}", self.lines());
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    }

    /// The seed it said it drew.
    fn seed(&self) -> String {
        let l = self.wait_for("pass --seed ");
        let n = l
            .split("pass --seed ")
            .nth(1)
            .and_then(|t| t.split_whitespace().next())
            .unwrap()
            .to_string();
        assert!(l.contains(&format!("seed {n}:")), "{l}");
        n
    }
}

impl Drop for Logged {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The BMS serial and the MQTT state of a bridge, by `tinybms version`.
fn serial_and_mqtt(path: &str) -> Option<(String, String)> {
    let v = common::tinybms(&["version", path, "--json"]);
    if v.code != 0 {
        return None;
    }
    let line: serde_json::Value = serde_json::from_str(v.stdout.trim()).ok()?;
    Some((
        line["serial_number"].as_str()?.to_string(),
        line["bridge"]["mqtt"].as_str().unwrap_or("").to_string(),
    ))
}

/// Issue 26, item 14 and issue 29, item 2: two try-outs started without
/// `--seed` had one serial and one client id, so on one broker they threw
/// each other off (`client_id_taken`). Each now has its own seed (the lowest
/// free one, issue 42), says it, and has its own serial and client id;
/// `--seed N` repeats one.
#[test]
fn two_default_try_outs_have_their_own_serial_and_client_id() {
    let port = free_port();
    let broker = Broker::start("127.0.0.1", port).unwrap();
    let sub = Sub::start(&broker).unwrap();
    let mqtt = format!("127.0.0.1:{port}");
    let from = Instant::now();
    let a = Logged::start(&["--bridge-pty", "--mqtt", &mqtt, "--quiet"]);
    let b = Logged::start(&["--bridge-pty", "--mqtt", &mqtt, "--quiet"]);
    let (seed_a, seed_b) = (a.seed(), b.seed());
    assert_ne!(seed_a, seed_b);
    sub.wait(from, "two devices", |m| {
        state_topics(m, "tinybms/").len() == 2
    })
    .unwrap();
    // Both stay connected, neither says its id is taken (a taken id shows
    // within seconds: the broker drops one connection for the other).
    let (pa, pb) = (a.path.clone().unwrap(), b.path.clone().unwrap());
    let end = Instant::now() + std::time::Duration::from_secs(15);
    let mut serials = (String::new(), String::new());
    let mut states = (String::new(), String::new());
    while Instant::now() < end {
        if let (Some(x), Some(y)) = (serial_and_mqtt(&pa), serial_and_mqtt(&pb)) {
            assert_ne!(x.1, "client_id_taken", "{x:?} {y:?}");
            assert_ne!(y.1, "client_id_taken", "{x:?} {y:?}");
            serials = (x.0, y.0);
            states = (x.1, y.1);
        }
        std::thread::sleep(std::time::Duration::from_millis(500));
    }
    assert_eq!(states, ("connected".into(), "connected".into()));
    // The client id is `tinybms-sim-` and the serial's last six digits.
    let tail = |s: &str| s[s.len() - 6..].to_string();
    assert_ne!(tail(&serials.0), tail(&serials.1), "{serials:?}");
    // Both devices published, each under its own serial.
    let topics = state_topics(&sub.wait(from, "", |_| true).unwrap(), "tinybms/");
    for s in [&serials.0, &serials.1] {
        assert!(
            topics.iter().any(|t| t.contains(s.as_str())),
            "{s}: {topics:?}"
        );
    }
    // The seed it printed repeats the same BMS.
    let again = common::Sim::start(&["--bridge-pty", "--quiet", "--seed", &seed_a]);
    let end = Instant::now() + std::time::Duration::from_secs(30);
    loop {
        if let Some((serial, _)) = serial_and_mqtt(&again.path) {
            assert_eq!(serial, serials.0);
            break;
        }
        assert!(Instant::now() < end, "no version from the repeat");
    }
    drop(broker);
}

/// Issue 42, item 6: every try-out drew a new seed, so every `sim --mqtt`
/// left another device in Home Assistant. A try-out now takes the lowest seed
/// no running simulator holds: run again, it is the same BMS (serial, client
/// id, device); two at once are still two; a killed one gives its seed back.
#[test]
fn a_try_out_run_again_is_the_same_device() {
    use std::io::{BufRead, BufReader};
    let locks = std::env::temp_dir().join(format!("tinybms-seeds-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&locks);
    let start = || {
        let mut child = Command::new(env!("CARGO_BIN_EXE_sim"))
            .args(["--bridge-pty", "--quiet", "--duration", "60s"])
            .env("TINYBMS_SIM_LOCKS", &locks)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let err = child.stderr.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for l in BufReader::new(err).lines().map_while(Result::ok) {
                if let Some(n) = l.strip_prefix("sim: seed ") {
                    let _ = tx.send(n.split(':').next().unwrap_or("").to_string());
                }
            }
        });
        let seed = rx
            .recv_timeout(std::time::Duration::from_secs(30))
            .expect("sim said its seed");
        (child, seed)
    };
    let (mut a, seed_a) = start();
    let (mut b, seed_b) = start();
    assert_eq!((seed_a.as_str(), seed_b.as_str()), ("1", "2"));
    // The first one ends as a killed process does: its seed is free again.
    a.kill().unwrap();
    a.wait().unwrap();
    let (mut c, seed_c) = start();
    assert_eq!(seed_c, "1", "a try-out run again is the same BMS");
    for p in [&mut b, &mut c] {
        let _ = p.kill();
        let _ = p.wait();
    }
    let _ = std::fs::remove_dir_all(&locks);
}

/// Issue 26, item 14: a broker that needs a login (Home Assistant's
/// Mosquitto add-on: a password file, no anonymous clients). `--config
/// mqtt_user=… --config mqtt_password=…` connects and publishes; a wrong
/// password is named in the log (it said only "the broker refused the
/// login"), and the password is never printed.
#[test]
fn a_broker_that_needs_a_login() {
    let port = free_port();
    let broker = Broker::start_with_login("127.0.0.1", port, "tbuser", "s3cret pass").unwrap();
    let sub = Sub::start(&broker).unwrap();
    let mqtt = format!("127.0.0.1:{port}");
    let from = Instant::now();
    let good = Logged::start(&[
        "--mqtt",
        &mqtt,
        "--seed",
        "3",
        "--config",
        "mqtt_user=tbuser",
        "--config",
        "mqtt_password=s3cret pass",
    ]);
    let msgs = sub
        .wait(from, "the state of the bridge that logged in", |m| {
            state_topics(m, "tinybms/").len() == 1
        })
        .unwrap();
    assert!(msgs
        .iter()
        .any(|m| m.topic.ends_with("/pack_voltage/config")));
    good.wait_for("MQTT: connected to the broker");
    let bad = Logged::start(&[
        "--mqtt",
        &mqtt,
        "--seed",
        "4",
        "--config",
        "mqtt_user=tbuser",
        "--config",
        "mqtt_password=hunter2-not-it",
    ]);
    let l = bad.wait_for("MQTT: cannot connect (");
    assert!(
        l.contains("the broker refused the login: wrong or missing mqtt_user / mqtt_password"),
        "{l}"
    );
    // No login at all: the same words.
    let none = Logged::start(&["--mqtt", &mqtt, "--seed", "5"]);
    let l = none.wait_for("MQTT: cannot connect (");
    assert!(
        l.contains("wrong or missing mqtt_user / mqtt_password"),
        "{l}"
    );
    for line in bad.lines().iter().chain(good.lines().iter()) {
        assert!(
            !line.contains("hunter2") && !line.contains("s3cret"),
            "a password in the log: {line}"
        );
    }
    // Only the one that logged in published.
    let all = sub.wait(from, "", |_| true).unwrap();
    assert_eq!(state_topics(&all, "tinybms/").len(), 1, "{all:?}");
    drop(broker);
}
