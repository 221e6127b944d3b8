//! The MQTT end-to-end scenario, shared by the loopback test
//! (tests/mqtt_broker.rs: the session over a TCP socket) and the network
//! namespace test (`mqtt-tap`: the session over embassy-net on a TAP device):
//! Debian's `mosquitto`, the firmware's bridge against the simulated BMS in
//! real time, and `mosquitto_sub` to see what the broker delivers.
//!
//! Checked, each bounded by [`WAIT`]: retained discovery configs and
//! availability; state values equal to what the simulated BMS sent; the
//! configs again when Home Assistant says `online`; the will on a dropped
//! connection and the reconnect; availability `offline` and no state while the
//! BMS link is lost; the reconnect after the broker restarts. Every child
//! process is killed when its guard drops.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::Value;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::mqtt::session::Note;

use crate::mqtt::{Kill, Notes, Shared};
use crate::real_time::SimPort;
use crate::replay::register_values;
use crate::sim::{PackModel, SimBms, SimConfig};
use tinybms_desk::flash::{DeskFlash, RamFlash};
use tinybms_desk::{Hosted, NoHost};

/// The longest any one expectation may take (a bound, not a timing check).
pub const WAIT: Duration = Duration::from_secs(30);

type Check = Result<(), String>;

/// The bridge's record for the scenario: the defaults with a state every
/// second (the scenario takes less time; the schedule itself is unit-tested).
pub fn config() -> tinybms_firmware::config::Config {
    tinybms_firmware::config::Config {
        publish_period_s: 1,
        ..Default::default()
    }
}

fn ensure(ok: bool, what: impl FnOnce() -> String) -> Check {
    if ok {
        Ok(())
    } else {
        Err(what())
    }
}

/// `mosquitto` listening on `ip:port`, killed on drop.
pub struct Broker {
    child: Child,
    /// Its address.
    pub ip: String,
    /// Its port.
    pub port: u16,
    /// The login it needs (`None`: anonymous clients are welcome).
    pub login: Option<(String, String)>,
    conf: std::path::PathBuf,
    passwords: Option<std::path::PathBuf>,
}

impl Broker {
    /// Starts it and waits until it accepts connections.
    pub fn start(ip: &str, port: u16) -> Result<Broker, String> {
        Self::start_with(ip, port, None)
    }

    /// Starts one that takes only `user` with `password` (a password file
    /// made by `mosquitto_passwd`, `allow_anonymous false`: Home Assistant's
    /// Mosquitto add-on's way).
    pub fn start_with_login(
        ip: &str,
        port: u16,
        user: &str,
        password: &str,
    ) -> Result<Broker, String> {
        Self::start_with(ip, port, Some((user.to_string(), password.to_string())))
    }

    fn start_with(ip: &str, port: u16, login: Option<(String, String)>) -> Result<Broker, String> {
        let base =
            std::env::temp_dir().join(format!("tinybms-mosquitto-{}-{port}", std::process::id()));
        let conf = base.with_extension("conf");
        let mut text = format!("listener {port} {ip}\npersistence false\n");
        let passwords = match &login {
            None => {
                text.push_str("allow_anonymous true\n");
                None
            }
            Some((user, password)) => {
                let file = base.with_extension("passwd");
                let _ = std::fs::remove_file(&file);
                let ok = Command::new("mosquitto_passwd")
                    .args(["-c", "-b", &file.to_string_lossy(), user, password])
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .status()
                    .map_err(|e| format!("mosquitto_passwd: {e}"))?;
                if !ok.success() {
                    return Err(format!("mosquitto_passwd: {ok}"));
                }
                text.push_str(&format!(
                    "allow_anonymous false\npassword_file {}\n",
                    file.display()
                ));
                Some(file)
            }
        };
        std::fs::write(&conf, text).map_err(|e| format!("mosquitto config: {e}"))?;
        let child = Command::new("mosquitto")
            .args(["-c", &conf.to_string_lossy()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("mosquitto (apt-get install mosquitto mosquitto-clients): {e}"))?;
        let b = Broker {
            child,
            ip: ip.to_string(),
            port,
            login,
            conf,
            passwords,
        };
        let end = Instant::now() + WAIT;
        while std::net::TcpStream::connect((ip, port)).is_err() {
            if Instant::now() > end {
                return Err(format!("mosquitto did not listen on {ip}:{port}"));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        Ok(b)
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_file(&self.conf);
        if let Some(p) = &self.passwords {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// One message as `mosquitto_sub` printed it.
#[derive(Debug, Clone)]
pub struct Msg {
    /// Delivered as a retained message.
    pub retained: bool,
    /// Topic.
    pub topic: String,
    /// Payload (the bridge's have no newline).
    pub payload: String,
    /// When it arrived.
    pub at: Instant,
}

/// `mosquitto_sub -t '#'`, collecting every message; killed on drop.
pub struct Sub {
    child: Child,
    msgs: Arc<Mutex<Vec<Msg>>>,
}

impl Sub {
    /// Subscribes to everything on the broker.
    /// (With the broker's login, when it needs one.)
    pub fn start(b: &Broker) -> Result<Sub, String> {
        let mut cmd = Command::new("mosquitto_sub");
        cmd.args([
            "-h",
            &b.ip,
            "-p",
            &b.port.to_string(),
            "-t",
            "#",
            "-F",
            "%r\t%t\t%p",
        ]);
        if let Some((user, password)) = &b.login {
            cmd.args(["-u", user, "-P", password]);
        }
        let mut child = cmd
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("mosquitto_sub: {e}"))?;
        let out = child.stdout.take().ok_or("mosquitto_sub: no stdout")?;
        let msgs: Arc<Mutex<Vec<Msg>>> = Arc::default();
        let m = msgs.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(out).split(b'\n').map_while(Result::ok) {
                let text = String::from_utf8_lossy(&line).into_owned();
                let mut parts = text.splitn(3, '\t');
                let (Some(r), Some(t)) = (parts.next(), parts.next()) else {
                    continue;
                };
                m.lock().unwrap_or_else(|e| e.into_inner()).push(Msg {
                    retained: r == "1",
                    topic: t.to_string(),
                    payload: parts.next().unwrap_or("").to_string(),
                    at: Instant::now(),
                });
            }
        });
        Ok(Sub { child, msgs })
    }

    fn all(&self) -> Vec<Msg> {
        self.msgs.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Waits until `pred` holds for the messages since `from`; returns them.
    pub fn wait(
        &self,
        from: Instant,
        what: &str,
        pred: impl Fn(&[Msg]) -> bool,
    ) -> Result<Vec<Msg>, String> {
        let end = Instant::now() + WAIT;
        loop {
            let since: Vec<Msg> = self.all().into_iter().filter(|m| m.at >= from).collect();
            if pred(&since) {
                return Ok(since);
            }
            if Instant::now() > end {
                let tail: Vec<String> = since
                    .iter()
                    .rev()
                    .take(8)
                    .map(|m| format!("{} {}", m.topic, &m.payload[..m.payload.len().min(80)]))
                    .collect();
                return Err(format!(
                    "{what}: not seen within {WAIT:?}; the last: {tail:#?}"
                ));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Sub {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `mosquitto_pub` one message.
pub fn publish(b: &Broker, topic: &str, payload: &str) -> Check {
    let ok = Command::new("mosquitto_pub")
        .args([
            "-h",
            &b.ip,
            "-p",
            &b.port.to_string(),
            "-t",
            topic,
            "-m",
            payload,
        ])
        .status()
        .map_err(|e| format!("mosquitto_pub: {e}"))?
        .success();
    ensure(ok, || "mosquitto_pub failed".into())
}

/// The bridge against the simulated BMS in real time on a thread, feeding a
/// [`Shared`]; stopped on drop.
pub struct BridgeThread {
    stop: Arc<AtomicBool>,
    silent_until_us: Arc<AtomicU64>,
    /// seq -> the live registers the bridge published with that snapshot.
    pub published: Arc<Mutex<BTreeMap<u32, BTreeMap<u16, u16>>>>,
    join: Option<std::thread::JoinHandle<()>>,
    /// The bridge's clock.
    pub clock: tinybms_desk::Clock,
    /// What the session reads.
    pub shared: Shared,
}

impl BridgeThread {
    /// Starts it.
    pub fn start() -> Result<BridgeThread, String> {
        let shared = Shared::default();
        let stop = Arc::new(AtomicBool::new(false));
        let silent = Arc::new(AtomicU64::new(0));
        let published: Arc<Mutex<BTreeMap<u32, BTreeMap<u16, u16>>>> = Arc::default();
        let (s, q, p, sh) = (
            stop.clone(),
            silent.clone(),
            published.clone(),
            shared.clone(),
        );
        let (tx, rx) = std::sync::mpsc::channel();
        let join = std::thread::spawn(move || {
            let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 5);
            let mut h = Hosted::new(
                SimPort::new(sim),
                Timing::default(),
                DeskFlash::Ram(RamFlash::new()),
                "sim",
            );
            h.beside = Some(Box::new(crate::real_time_station::MqttBeside::new(
                sh, None,
            )));
            let _ = tx.send(h.driver.clock());
            let mut seen = 0;
            while !s.load(Ordering::Relaxed) {
                let until = q.swap(0, Ordering::Relaxed);
                if until > 0 {
                    h.driver.port.sim.set_silent_until(until);
                }
                if h.step(&mut NoHost).is_err() {
                    break;
                }
                let t = h.driver.station.bridge().telemetry();
                if t.snapshot_seq != seen {
                    seen = t.snapshot_seq;
                    if let Some(b) = &t.live_registers {
                        p.lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .insert(seen, b.iter().collect());
                    }
                }
            }
        });
        let clock = rx
            .recv_timeout(WAIT)
            .map_err(|_| "the bridge did not start")?;
        Ok(BridgeThread {
            stop,
            silent_until_us: silent,
            published,
            join: Some(join),
            clock,
            shared,
        })
    }

    /// The simulated BMS goes silent for `secs` (the BMS link is lost).
    pub fn silence(&self, secs: u64) {
        let now = self.clock.now();
        self.silent_until_us
            .store(now + secs * 1_000_000, Ordering::Relaxed);
    }
}

impl Drop for BridgeThread {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(j) = self.join.take() {
            let _ = j.join();
        }
    }
}

fn json(s: &str) -> Result<Value, String> {
    serde_json::from_str(s).map_err(|e| format!("{e}: {s}"))
}

/// Every state in `got` against the registers the bridge published with its
/// `seq`, decoded here (replay's decoder): how many were checked.
fn check_states(bridge: &BridgeThread, got: &[Msg]) -> Result<usize, String> {
    let published = bridge
        .published
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .clone();
    let mut states = 0;
    for m in got.iter().filter(|x| x.topic.ends_with("/state")) {
        let s = json(&m.payload)?;
        let seq = s["seq"].as_u64().unwrap_or(0) as u32;
        let regs = published
            .get(&seq)
            .ok_or_else(|| format!("a state of seq {seq}, which was never published"))?;
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
            ensure(s[k] == truth[k], || {
                format!(
                    "seq {seq}: {k} is {} in the state, {} in the registers",
                    s[k], truth[k]
                )
            })?;
        }
        states += 1;
    }
    Ok(states)
}

/// The BMS link lost: offline (published, not the will), no state while
/// stale, then online again.
fn bms_silent(bridge: &BridgeThread, sub: &Sub, avail: &str) -> Result<(), String> {
    let t = Instant::now();
    bridge.silence(10);
    let m = sub.wait(t, "offline while the BMS is silent", |m| {
        m.iter().any(|x| x.topic == avail && x.payload == "offline")
    })?;
    let off_at = m
        .iter()
        .find(|x| x.topic == avail && x.payload == "offline")
        .map(|x| x.at)
        .unwrap_or(t);
    let m = sub.wait(t, "online again after the BMS is back", |m| {
        m.iter()
            .any(|x| x.topic == avail && x.payload == "online" && x.at > off_at)
    })?;
    let on_at = m
        .iter()
        .rfind(|x| x.topic == avail && x.payload == "online")
        .map(|x| x.at)
        .unwrap_or(t);
    let stale = m
        .iter()
        .filter(|x| {
            x.topic.ends_with("/state")
                && x.at > off_at + Duration::from_millis(200)
                && x.at < on_at
        })
        .count();
    ensure(stale == 0, || {
        format!("{stale} states published while the BMS data was stale")
    })?;
    Ok(())
}

/// Runs the scenario on a broker at `ip:port`. `start_session` starts the
/// firmware's MQTT session (fed by the bridge's [`Shared`], connecting to
/// `ip:port`) and returns its kill switch and notes (or why it cannot). On success, a summary.
pub fn scenario(
    ip: &str,
    port: u16,
    start_session: impl FnOnce(&BridgeThread) -> Result<(Kill, Notes), String>,
) -> Result<String, String> {
    let broker = Broker::start(ip, port)?;
    let bridge = BridgeThread::start()?;
    let (kill, notes) = start_session(&bridge)?;
    let start = Instant::now();

    // Retained configs, availability online, and states.
    let sub = Sub::start(&broker)?;
    let got = sub.wait(start, "configs, availability and 3 states", |m| {
        m.iter().filter(|x| x.topic.ends_with("/config")).count() >= 34
            && m.iter()
                .any(|x| x.topic.ends_with("/availability") && x.payload == "online")
            && m.iter().filter(|x| x.topic.ends_with("/state")).count() >= 3
    })?;
    let configs: Vec<&Msg> = got
        .iter()
        .filter(|x| x.topic.ends_with("/config"))
        .collect();
    // A 16-cell pack: every config announces, none removes.
    ensure(configs.iter().all(|c| !c.payload.is_empty()), || {
        "a config removed".into()
    })?;
    for c in &configs {
        let v = json(&c.payload)?;
        let uid = v["unique_id"].as_str().unwrap_or("");
        ensure(uid.starts_with("tinybms_"), || format!("unique_id {uid}"))?;
    }
    let node = configs[0].topic.split('/').nth(2).unwrap_or("");
    let serial = node.trim_start_matches("tinybms_").to_string();
    let avail = format!("tinybms/{serial}/availability");
    // State values are what the simulated BMS sent: each state is the snapshot
    // of its `seq`, decoded independently here (replay's decoder) from the
    // registers the bridge published with it.
    let states = check_states(&bridge, &got)?;
    // A late subscriber gets the configs and the availability, retained.
    {
        let late = Sub::start(&broker)?;
        let r = late.wait(Instant::now() - Duration::from_secs(1), "retained", |m| {
            m.iter()
                .filter(|x| x.retained && x.topic.ends_with("/config"))
                .count()
                >= 34
                && m.iter()
                    .any(|x| x.retained && x.topic == avail && x.payload == "online")
        })?;
        ensure(
            !r.iter().any(|x| x.retained && x.topic.ends_with("/state")),
            || "a retained state".into(),
        )?;
    }
    // Home Assistant is back: the configs again.
    let t = Instant::now();
    publish(&broker, "homeassistant/status", "online")?;
    sub.wait(
        t,
        "configs re-announced on homeassistant/status online",
        |m| m.iter().filter(|x| x.topic.ends_with("/config")).count() >= 34,
    )?;
    // A connection dropped without DISCONNECT: the will, then online again.
    let t = Instant::now();
    kill.kill();
    sub.wait(t, "the will, then online again", |m| {
        let off = m
            .iter()
            .position(|x| x.topic == avail && x.payload == "offline");
        off.is_some_and(|i| {
            m[i..]
                .iter()
                .any(|x| x.topic == avail && x.payload == "online")
        })
    })?;
    bms_silent(&bridge, &sub, &avail)?;
    // The broker restarts: the session reconnects and announces again.
    drop(sub);
    drop(broker);
    std::thread::sleep(Duration::from_millis(500));
    let broker = Broker::start(ip, port)?;
    let t = Instant::now();
    let sub = Sub::start(&broker)?;
    sub.wait(t, "configs after the broker's restart", |m| {
        m.iter().filter(|x| x.topic.ends_with("/config")).count() >= 34
            && m.iter().any(|x| x.topic == avail && x.payload == "online")
    })?;
    let late = Sub::start(&broker)?;
    late.wait(
        Instant::now() - Duration::from_secs(1),
        "retained after the restart",
        |m| {
            m.iter()
                .filter(|x| x.retained && x.topic.ends_with("/config"))
                .count()
                >= 34
        },
    )?;
    let notes = notes.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let connects = notes
        .iter()
        .filter(|n| matches!(n, Note::Connected))
        .count();
    ensure(connects >= 3, || format!("connections: {notes:?}"))?;
    Ok(format!(
        "{} configs, {states} states checked against the registers, {connects} connections ({} notes: {:?})",
        configs.len(),
        notes.len(),
        notes
    ))
}
