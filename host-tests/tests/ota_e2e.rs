//! End to end: updates through `sim --bridge-pty` (the firmware's station,
//! host link and update side on the desktop's chip flash with the real
//! partition table), with the built `tinybms` (`keygen`, `sign`, `update`)
//! and with a host of the test's own that loses, repeats and reorders
//! chunks and goes away in the middle. An image that panics before it
//! confirms itself is rolled back by the bridge, which says so in `hello`.

mod common;
use common::*;

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use base64::Engine as _;
use serde_json::{json, Value};

/// An app image as the bridge checks its start: magic, ESP32-C3's chip id,
/// the app descriptor with `version` and `project`.
fn image(len: usize, version: &str, project: &str) -> Vec<u8> {
    let mut v: Vec<u8> = (0..len).map(|i| (i * 13 + i / 253) as u8).collect();
    v[0] = 0xE9;
    v[12..14].copy_from_slice(&5u16.to_le_bytes());
    v[32..36].copy_from_slice(&0xABCD_5432u32.to_le_bytes());
    v[48..112].fill(0);
    v[48..48 + version.len()].copy_from_slice(version.as_bytes());
    v[80..80 + project.len()].copy_from_slice(project.as_bytes());
    v
}

struct Keys {
    key: std::path::PathBuf,
    public: String,
}

fn keygen(name: &str) -> Keys {
    let key = tmp(name);
    let _ = std::fs::remove_file(&key);
    let _ = std::fs::remove_file(key.with_extension("pub"));
    let out = tinybms(&["keygen", key.to_str().unwrap()]);
    assert_eq!(out.code, 0, "{out}");
    let public = std::fs::read_to_string(format!("{}.pub", key.display()))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .collect::<String>()
        .trim()
        .to_string();
    assert_eq!(public.len(), 64);
    assert!(out.stdout.contains(&public), "{out}");
    Keys { key, public }
}

/// What the simulated bridge runs (its `hello`'s features): an update file
/// names the same, or the bridge refuses it unless told to drop some.
const FEATURES: &str = "can,host-link,wifi,store";

/// `tinybms sign` of `img` for `board` and `version`: the file's path.
fn sign(k: &Keys, img: &[u8], board: &str, version: &str, name: &str) -> std::path::PathBuf {
    let bin = tmp(&format!("{name}.bin"));
    std::fs::write(&bin, img).unwrap();
    let out_path = tmp(&format!("{name}.tbu"));
    let out = tinybms(&[
        "sign",
        "--key",
        k.key.to_str().unwrap(),
        "--chip",
        "esp32c3",
        "--board",
        board,
        "--version",
        version,
        "--features",
        FEATURES,
        bin.to_str().unwrap(),
        "-o",
        out_path.to_str().unwrap(),
    ]);
    assert_eq!(out.code, 0, "{out}");
    out_path
}

/// `sim --bridge-pty` standing for a SuperMini's image that trusts `k`
/// (registered as the owner's `update_key`), with `extra` arguments.
fn bridge_trusting(k: &Keys, extra: &[&str]) -> Sim {
    let key = format!("update_key={}", k.public);
    let mut args = vec!["--bridge-pty", "--board", "c3-supermini", "--config", &key];
    args.extend_from_slice(extra);
    Sim::start(&args)
}

/// The host link of the pty, line by line.
struct Host {
    port: Box<dyn serialport::SerialPort>,
    buf: Vec<u8>,
    req: u32,
}

impl Host {
    fn open(path: &str) -> Self {
        let port = serialport::new(path, 115_200)
            .timeout(Duration::from_millis(20))
            .open()
            .expect("the pty");
        let mut h = Self {
            port,
            buf: Vec::new(),
            req: 1000,
        };
        h.port.write_all(b"\n").unwrap();
        h
    }

    fn send(&mut self, mut cmd: Value) -> u32 {
        self.req += 1;
        cmd["req"] = json!(self.req);
        let mut line = cmd.to_string().into_bytes();
        line.push(b'\n');
        self.port.write_all(&line).unwrap();
        self.req
    }

    fn next_line(&mut self, until: Instant) -> Option<Value> {
        loop {
            if let Some(i) = self.buf.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.buf.drain(..=i).collect();
                if let Ok(v) = serde_json::from_slice::<Value>(&line) {
                    return Some(v);
                }
                continue;
            }
            if Instant::now() >= until {
                return None;
            }
            let mut b = [0u8; 4096];
            match self.port.read(&mut b) {
                Ok(n) => self.buf.extend_from_slice(&b[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(e) => panic!("reading the pty: {e}"),
            }
        }
    }

    /// The answer to `req` within 5 s (other lines are skipped; telemetry
    /// lines are counted).
    fn answer(&mut self, req: u32, telemetry: &mut u32) -> Value {
        let until = Instant::now() + Duration::from_secs(5);
        while let Some(v) = self.next_line(until) {
            if v["type"] == "telemetry" {
                *telemetry += 1;
            }
            if v["req"] == json!(req) {
                return v;
            }
        }
        panic!("no answer to request {req}");
    }

    fn ask(&mut self, cmd: Value) -> Value {
        let req = self.send(cmd);
        self.answer(req, &mut 0)
    }
}

fn chunk(file: &[u8], at: usize) -> Value {
    let end = (at + 128).min(file.len());
    json!({"cmd": "update_chunk", "at": at, "data": base64::engine::general_purpose::STANDARD.encode(&file[at..end])})
}

/// Waits for the bridge to come back after its restart and for its hello to
/// say `firmware` (and the rest of it).
fn hello_until(h: &mut Host, firmware: &str) -> Value {
    let until = Instant::now() + Duration::from_secs(20);
    while Instant::now() < until {
        let v = h.ask(json!({"cmd": "hello"}));
        if v["firmware"] == firmware {
            return v;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    panic!("the bridge never said firmware {firmware}");
}

#[test]
fn lost_repeated_and_reordered_chunks_then_a_rollback() {
    let k = keygen("e2e-key");
    let good = std::fs::read(sign(
        &k,
        &image(40_000, "0.9.0", "tinybms-firmware"),
        "c3-supermini",
        "0.9.0",
        "good",
    ))
    .unwrap();
    let sim = bridge_trusting(&k, &["--stream-period", "500ms"]);
    let mut h = Host::open(&sim.path);
    let v = h.ask(json!({"cmd": "hello"}));
    assert_eq!(v["board"], "ESP32-C3 SuperMini", "{v}");
    let first = v["firmware"].as_str().unwrap().to_string();
    assert!(v.get("rolled_back").is_none(), "{v}");

    // Chunks lost (every 7th never sent), repeated (every 5th twice), one
    // sent ahead of its turn; the bridge's answers say where to go on. The
    // BMS keeps being polled: telemetry lines keep coming.
    let a = h.ask(json!({"cmd": "update_begin", "size": good.len()}));
    assert_eq!(
        (a["state"].as_str(), a["at"].as_u64()),
        (Some("next"), Some(0)),
        "{a}"
    );
    let mut at = 0usize;
    let (mut sent, mut lost, mut repeated, mut busy, mut telemetry) =
        (0u32, 0u32, 0u32, 0u32, 0u32);
    let started = Instant::now();
    while at < good.len() {
        sent += 1;
        if sent % 7 == 0 {
            lost += 1;
            // Lost on the way: the next one arrives after a gap.
            let ahead = (at + 128).min(good.len().saturating_sub(1));
            let req = h.send(chunk(&good, ahead));
            let r = h.answer(req, &mut telemetry);
            assert_eq!(
                r["at"].as_u64(),
                Some(at as u64),
                "a gap changes nothing: {r}"
            );
            continue;
        }
        let req = h.send(chunk(&good, at));
        let r = h.answer(req, &mut telemetry);
        // Not the last chunk: once the image is whole the bridge installs it
        // and restarts, and a repeat would meet the new boot's empty session.
        let whole = r["at"].as_u64() == Some(good.len() as u64);
        if sent % 5 == 0 && r["state"] == "next" && !whole {
            repeated += 1;
            let req = h.send(chunk(&good, at));
            let d = h.answer(req, &mut telemetry);
            assert_eq!(d["at"], r["at"], "a repeat changes nothing: {d}");
        }
        match r["state"].as_str() {
            Some("next") => at = r["at"].as_u64().unwrap() as usize,
            Some("busy") => {
                busy += 1;
                std::thread::sleep(Duration::from_millis(5));
            }
            _ => panic!("{r}"),
        }
    }
    let took = started.elapsed();
    eprintln!(
        "{} bytes in {:.1} s: {sent} chunks, {lost} lost, {repeated} repeated, {busy} busy, {telemetry} telemetry lines meanwhile",
        good.len(),
        took.as_secs_f64()
    );
    assert!(lost > 10 && repeated > 10);
    assert!(
        u64::from(telemetry) * 500 >= took.as_millis() as u64 / 2,
        "the telemetry stream (every 500 ms) went on: {telemetry} lines in {took:?}"
    );
    // Installed, then the restart into it on trial, then confirmed.
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        let s = h.ask(json!({"cmd": "update_status"}));
        if s["phase"] == "installed" || s["phase"] == "idle" && s["trial"] == "on_trial" {
            break;
        }
        assert!(Instant::now() < until, "never installed: {s}");
        std::thread::sleep(Duration::from_millis(50));
    }
    let v = hello_until(&mut h, "0.9.0");
    assert!(v.get("rolled_back").is_none(), "{v}");
    let until = Instant::now() + Duration::from_secs(20);
    while h.ask(json!({"cmd": "update_status"}))["trial"] != "confirmed" {
        assert!(
            Instant::now() < until,
            "the new image never confirmed itself"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    // `hello` says so too, at once (it said "on_trial" until a restart).
    let v = h.ask(json!({"cmd": "hello"}));
    assert_eq!(v["update"]["trial"], "confirmed", "{v}");

    // An image that panics before it confirms itself: back to 0.9.0, said.
    let bad = sign(
        &k,
        &image(20_000, "0.9.1", "tinybms-panics"),
        "c3-supermini",
        "0.9.1",
        "panics",
    );
    // The port is the tool's while it runs (serial ports are opened alone).
    drop(h);
    let out = tinybms(&["update", &sim.path, bad.to_str().unwrap(), "-y"]);
    assert_eq!(out.code, 0, "{out}");
    assert!(out.stdout.contains("installed 0.9.1"), "{out}");
    let mut h = Host::open(&sim.path);
    let until = Instant::now() + Duration::from_secs(20);
    let v = loop {
        let v = h.ask(json!({"cmd": "hello"}));
        if v.get("rolled_back").is_some() {
            break v;
        }
        assert!(Instant::now() < until, "no rollback said: {v}");
        std::thread::sleep(Duration::from_millis(200));
    };
    assert_eq!(v["firmware"], "0.9.0", "{v}");
    assert_eq!(
        v["rolled_back"], "update to 0.9.1 rolled back: it panicked before confirming itself",
        "{v}"
    );
    let s = h.ask(json!({"cmd": "update_status"}));
    assert_eq!(s["trial"], "confirmed", "{s}");
    assert_ne!(first, "0.9.0");
}

#[test]
fn every_refused_file_is_refused_with_its_reason_by_the_tool() {
    let k = keygen("e2e-key-2");
    let stranger = keygen("e2e-stranger");
    let img = image(9_000, "0.9.0", "tinybms-firmware");
    let good = sign(&k, &img, "c3-supermini", "0.9.0", "r-good");
    let sim = bridge_trusting(&k, &[]);
    let bytes = std::fs::read(&good).unwrap();
    let truncated = tmp("r-truncated.tbu");
    std::fs::write(&truncated, &bytes[..bytes.len() - 1]).unwrap();
    let padded = tmp("r-padded.tbu");
    std::fs::write(&padded, [&bytes[..], &[0u8; 16]].concat()).unwrap();
    let cases = [
        (
            sign(&k, &img, "c3-devkitm-1", "0.9.0", "r-board"),
            "for another board",
        ),
        (
            sign(&stranger, &img, "c3-supermini", "0.9.0", "r-stranger"),
            "not from a key this bridge trusts",
        ),
        (
            sign(
                &k,
                &image(9_000, "0.0.1", "x"),
                "c3-supermini",
                "0.0.1",
                "r-older",
            ),
            "older than the running firmware",
        ),
        (truncated, "shorter than its header says"),
        (padded, "longer than its header says"),
    ];
    for (file, why) in &cases {
        for check in [true, false] {
            let mut args = vec!["update", &sim.path, file.to_str().unwrap(), "-y"];
            if check {
                args.push("--check");
            }
            let out = tinybms(&args);
            assert_eq!(out.code, 1, "{why}: {out}");
            assert!(out.stderr.contains(why), "{why}: {out}");
        }
    }
    // The older one with --downgrade, checked only: acceptable.
    let older = &cases[2].0;
    let out = tinybms(&[
        "update",
        &sim.path,
        older.to_str().unwrap(),
        "--check",
        "--downgrade",
    ]);
    assert_eq!(out.code, 0, "{out}");
    assert!(out.stdout.contains("would take it"), "{out}");
    // Nothing changed: the same firmware, no transfer, no rollback.
    let mut h = Host::open(&sim.path);
    let v = h.ask(json!({"cmd": "hello"}));
    assert!(v.get("rolled_back").is_none(), "{v}");
    let s = h.ask(json!({"cmd": "update_status"}));
    assert_eq!(
        (s["phase"].as_str(), s["trial"].as_str()),
        (Some("idle"), Some("confirmed")),
        "{s}"
    );
    // A file that is no update at all is refused by the tool itself.
    let out = tinybms(&[
        "update",
        &sim.path,
        tmp("r-board.bin").to_str().unwrap(),
        "-y",
    ]);
    assert_eq!(out.code, 1, "{out}");
    assert!(out.stderr.contains("not an update file"), "{out}");
    assert!(!out.stderr.contains("--help"), "not a usage error: {out}");
}

#[test]
fn a_host_that_goes_away_mid_transfer_is_given_up_after_30_s() {
    let k = keygen("e2e-key-3");
    let good = std::fs::read(sign(
        &k,
        &image(30_000, "0.9.0", "tinybms-firmware"),
        "c3-supermini",
        "0.9.0",
        "stall",
    ))
    .unwrap();
    let sim = bridge_trusting(&k, &["--stream-period", "1s"]);
    let mut h = Host::open(&sim.path);
    h.ask(json!({"cmd": "update_begin", "size": good.len()}));
    let mut at = 0;
    while at < 8_000 {
        let r = h.ask(chunk(&good, at));
        at = r["at"].as_u64().unwrap() as usize;
    }
    // The host stops sending; the bridge keeps working and gives up.
    let started = Instant::now();
    let mut telemetry = 0;
    let s = loop {
        let req = h.send(json!({"cmd": "update_status"}));
        let s = h.answer(req, &mut telemetry);
        if s["phase"] == "idle" {
            break s;
        }
        assert!(
            started.elapsed() < Duration::from_secs(45),
            "never given up: {s}"
        );
        std::thread::sleep(Duration::from_secs(1));
    };
    assert_eq!(s["ended"], "stalled", "{s}");
    assert!(
        started.elapsed() >= Duration::from_secs(25),
        "{:?}",
        started.elapsed()
    );
    assert!(
        telemetry >= 20,
        "the bridge went on meanwhile: {telemetry} telemetry lines"
    );
    // Nothing boots differently, and a new transfer goes through.
    drop(h);
    let out = tinybms(&[
        "update",
        &sim.path,
        tmp("stall.tbu").to_str().unwrap(),
        "-y",
    ]);
    assert_eq!(out.code, 0, "{out}");
    let mut h = Host::open(&sim.path);
    hello_until(&mut h, "0.9.0");
}

/// The update port on the network (loopback): the same update with
/// `tinybms update HOST:PORT FILE`, and nothing but `hello` and the
/// `update_…` commands taken there.
#[test]
fn over_tcp_on_the_update_port() {
    let k = keygen("e2e-key-4");
    let file = sign(
        &k,
        &image(25_000, "0.9.0", "tinybms-firmware"),
        "c3-supermini",
        "0.9.0",
        "tcp",
    );
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let addr = format!("127.0.0.1:{port}");
    let sim = bridge_trusting(&k, &["--update-port", &addr]);
    // Only hello and the update commands.
    let mut s = std::net::TcpStream::connect(&addr).unwrap();
    s.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    s.write_all(b"{\"cmd\":\"get\",\"what\":\"settings\",\"req\":1}\n{\"cmd\":\"update_status\",\"req\":2}\n")
        .unwrap();
    let mut got = String::new();
    let until = Instant::now() + Duration::from_secs(5);
    while Instant::now() < until && !got.contains("\"req\":2") {
        let mut b = [0u8; 4096];
        if let Ok(n) = s.read(&mut b) {
            got.push_str(&String::from_utf8_lossy(&b[..n]));
        }
    }
    let lines = json_lines(&got);
    assert_eq!(lines[0]["type"], "hello", "{got}");
    let refused = lines
        .iter()
        .find(|v| v["req"] == 1)
        .expect("an answer to get");
    assert_eq!(refused["error"], "unknown_command", "{refused}");
    let status = lines
        .iter()
        .find(|v| v["req"] == 2)
        .expect("an answer to update_status");
    assert_eq!(status["phase"], "idle", "{status}");
    assert!(
        !lines.iter().any(|v| v["type"] == "telemetry"),
        "the update port streams nothing: {got}"
    );
    drop(s);
    let out = tinybms(&["update", &addr, file.to_str().unwrap(), "-y"]);
    assert_eq!(out.code, 0, "{out}");
    assert!(
        out.stdout
            .contains("bridge: esp32c3 ESP32-C3 SuperMini on 127.0.0.1"),
        "{out}"
    );
    assert!(out.stdout.contains("installed 0.9.0"), "{out}");
    let mut h = Host::open(&sim.path);
    hello_until(&mut h, "0.9.0");
}

/// Issue 51, item 1: the halves of a key pair cannot be swapped. Each file
/// says what it is; `public-key` refuses a public key, `sign` refuses one;
/// the bridge refuses a private key as `update_key` and it appears nowhere
/// (the tool's words, `hello`, the configuration listing, the bridge's log).
#[test]
fn the_halves_of_a_key_cannot_be_swapped_and_a_private_key_is_never_taken() {
    let k = keygen("e2e-key-5");
    let private = std::fs::read_to_string(&k.key).unwrap();
    assert!(
        private.starts_with("# tinybms update signing key: PRIVATE"),
        "{private}"
    );
    let private_hex: String = private.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(private_hex.len(), 128);
    assert!(
        private_hex.ends_with(&k.public),
        "the public half follows the seed"
    );
    let seed = &private_hex[..64];
    let pubfile = format!("{}.pub", k.key.display());
    assert!(std::fs::read_to_string(&pubfile)
        .unwrap()
        .starts_with("# tinybms update public key"));

    // public-key: the private key's public key; a public key is refused.
    let out = tinybms(&["public-key", k.key.to_str().unwrap()]);
    assert_eq!(
        (out.code, out.stdout.trim()),
        (0, k.public.as_str()),
        "{out}"
    );
    let out = tinybms(&["public-key", &pubfile]);
    assert_eq!(out.code, 1, "{out}");
    assert!(!out.stderr.contains("--help"), "not a usage error: {out}");
    assert!(out.stderr.contains("already is a public key"), "{out}");
    // sign: a public key is refused, with which is which.
    let bin = tmp("k5.bin");
    std::fs::write(&bin, image(9_000, "0.9.0", "tinybms-firmware")).unwrap();
    let out = tinybms(&[
        "sign",
        "--key",
        &pubfile,
        "--chip",
        "esp32c3",
        "--board",
        "c3-supermini",
        "--features",
        FEATURES,
        bin.to_str().unwrap(),
        "-o",
        tmp("k5.tbu").to_str().unwrap(),
    ]);
    assert_eq!(out.code, 1, "{out}");
    assert!(out.stderr.contains("PUBLIC key"), "{out}");
    // A damaged private key file (its halves disagree) is refused.
    let bad = tmp("k5-bad");
    std::fs::write(&bad, format!("{seed}\n{}\n", "0".repeat(64))).unwrap();
    let out = tinybms(&["public-key", bad.to_str().unwrap()]);
    assert_eq!(out.code, 1, "{out}");
    assert!(out.stderr.contains("damaged"), "{out}");

    // The bridge: a private key as update_key is refused, nothing stored.
    let sim = bridge_trusting(&k, &[]);
    let set = format!("update_key={private_hex}");
    let out = tinybms_with_input(&["config", &sim.path, &set], "y\n");
    assert_ne!(out.code, 0, "{out}");
    assert!(
        out.stderr.contains("PRIVATE key") || out.stdout.contains("PRIVATE key"),
        "{out}"
    );
    let listing = tinybms(&["config", &sim.path]);
    assert_eq!(listing.code, 0, "{listing}");
    let mut h = Host::open(&sim.path);
    let hello = h.ask(json!({"cmd": "hello"}));
    // What it trusts: its owner key, the public one, said in hello.
    assert_eq!(
        hello["update"]["owner_key"].as_str().map(str::to_lowercase),
        Some(k.public.clone()),
        "{hello}"
    );
    assert_eq!(hello["update"]["trial"], "confirmed", "{hello}");
    assert_eq!(hello["update"]["slot"], "ota_0", "{hello}");
    // Straight to the bridge, without the tool's own check: refused too,
    // and the answer does not repeat it.
    let req = h.send(json!({"cmd": "set_config", "fields": {"update_key": private_hex}}));
    let until = Instant::now() + Duration::from_secs(2);
    let mut answer = String::new();
    while let Some(v) = h.next_line(until) {
        if v["req"] == req {
            answer.push_str(&v.to_string());
        }
    }
    assert!(answer.contains("PRIVATE key"), "{answer}");
    drop(h);
    // The .pub file whole, as `update_key="$(cat mykey.pub)"` gives it (its
    // `#` lines, then the key): taken as the key.
    let k2 = keygen("e2e-key-5b");
    let whole = std::fs::read_to_string(format!("{}.pub", k2.key.display())).unwrap();
    assert!(whole.lines().count() > 1, "{whole}");
    let set = format!("update_key={whole}");
    let taken = tinybms_with_input(&["config", &sim.path, &set], "y\n");
    assert_eq!(taken.code, 0, "{taken}");
    let mut h = Host::open(&sim.path);
    let hello2 = h.ask(json!({"cmd": "hello"}));
    assert_eq!(
        hello2["update"]["owner_key"]
            .as_str()
            .map(str::to_lowercase),
        Some(k2.public.clone()),
        "{hello2}"
    );
    drop(h);
    let log = tinybms_limited(&["log", &sim.path], "", Duration::from_secs(3));
    let everything = format!(
        "{out}{listing}{hello}{answer}{}",
        log.map(|l| l.to_string()).unwrap_or_default()
    )
    .to_lowercase();
    assert!(
        !everything.contains(seed),
        "the private key was said somewhere"
    );
}

/// Issue 51, items 2-4: the whole file is checked before a byte is sent —
/// one flipped byte of the image fails `--check` as it fails the update; a
/// file without a feature the bridge runs is refused unless dropped on
/// purpose; swapped arguments are said at once.
#[test]
fn a_damaged_or_lesser_file_is_refused_before_a_byte_is_sent() {
    let k = keygen("e2e-key-6");
    let img = image(20_000, "0.9.0", "tinybms-firmware");
    let good = sign(&k, &img, "c3-supermini", "0.9.0", "w-good");
    let sim = bridge_trusting(&k, &[]);
    let mut bytes = std::fs::read(&good).unwrap();
    bytes[256 + 12_345] ^= 0x10;
    let damaged = tmp("w-damaged.tbu");
    std::fs::write(&damaged, &bytes).unwrap();
    for extra in [&["--check"][..], &["-y"][..]] {
        let mut args = vec!["update", &sim.path, damaged.to_str().unwrap()];
        args.extend_from_slice(extra);
        let out = tinybms(&args);
        assert_eq!(out.code, 1, "{out}");
        assert!(
            out.stderr.contains("damaged") && out.stderr.contains("nothing was sent"),
            "{out}"
        );
    }
    // A byte of the signature changed: it fails,
    // and the words say the file may have been changed, not only "a stranger".
    let mut header_changed = std::fs::read(&good).unwrap();
    header_changed[200] ^= 0x01;
    let changed = tmp("w-header.tbu");
    std::fs::write(&changed, &header_changed).unwrap();
    let out = tinybms(&["update", &sim.path, changed.to_str().unwrap(), "--check"]);
    assert_eq!(out.code, 1, "{out}");
    assert!(
        out.stderr.contains("not from a key this bridge trusts")
            && out.stderr.contains("changed after it was signed"),
        "{out}"
    );
    // Nothing reached the bridge.
    let mut h = Host::open(&sim.path);
    let s = h.ask(json!({"cmd": "update_status"}));
    assert_eq!(s["phase"], "idle", "{s}");
    assert!(s["ended"].is_null(), "{s}");
    drop(h);

    // Signed without Wi-Fi and the store: refused by the tool, and by the
    // bridge itself when asked without the tool's check.
    let bin = tmp("w-lesser.bin");
    std::fs::write(&bin, &img).unwrap();
    let lesser = tmp("w-lesser.tbu");
    let out = tinybms(&[
        "sign",
        "--key",
        k.key.to_str().unwrap(),
        "--chip",
        "esp32c3",
        "--board",
        "c3-supermini",
        "--features",
        "can,host-link",
        bin.to_str().unwrap(),
        "-o",
        lesser.to_str().unwrap(),
    ]);
    assert_eq!(out.code, 0, "{out}");
    let update_lesser = |extra: &[&str]| {
        let mut args = vec!["update", &sim.path, lesser.to_str().unwrap()];
        args.extend_from_slice(extra);
        tinybms(&args)
    };
    let out = update_lesser(&["--check"]);
    assert_eq!(out.code, 1, "{out}");
    assert!(out.stderr.contains("has no wifi, store"), "{out}");
    assert!(out.stderr.contains("--drop wifi,store"), "{out}");
    let out = update_lesser(&["--check", "--drop", "wifi"]);
    assert_eq!(out.code, 1, "store still missing: {out}");
    let out = update_lesser(&["--check", "--drop", "wifi,store"]);
    assert_eq!(out.code, 0, "{out}");
    let out = update_lesser(&["--drop", "radio"]);
    assert_eq!(out.code, 2, "{out}");
    let mut h = Host::open(&sim.path);
    let file = std::fs::read(&lesser).unwrap();
    // The bridge's own answer to the whole file, checked (nothing written).
    let mut checked = |begin: Value| {
        let a = h.ask(begin);
        assert_eq!(a["state"], "next", "{a}");
        let mut at = 0;
        loop {
            let a = h.ask(chunk(&file, at));
            if a["state"] != "next" {
                break a;
            }
            at = a["at"].as_u64().unwrap() as usize;
        }
    };
    let a = checked(json!({"cmd": "update_begin", "size": file.len(), "check": true}));
    assert_eq!(a["ended"], "drops_features", "{a}");
    let a = checked(
        json!({"cmd": "update_begin", "size": file.len(), "check": true,
                           "drop_features": "wifi,store"}),
    );
    assert_eq!(a["state"], "acceptable", "{a}");
    drop(h);

    // Swapped: the file first, the port second, said at once.
    let started = Instant::now();
    let out = tinybms(&["update", good.to_str().unwrap(), &sim.path, "-y"]);
    assert_eq!(out.code, 2, "{out}");
    assert!(out.stderr.contains("the bridge comes first"), "{out}");
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "{:?}",
        started.elapsed()
    );
}

/// Issue 51, item 10: a file signed as 0.3.0 reported 0.2.0 once installed
/// (the header said what the command line said). `sign` reads the version,
/// the build and the features from the image, and refuses others.
#[test]
fn sign_takes_the_image_s_own_version_build_and_features() {
    let k = keygen("e2e-key-7");
    let mut img = image(9_000, "0.2.0", "src-0123abcd");
    let tag = b"tinybms-features=can,host-link,store\0";
    img[5_000..5_000 + tag.len()].copy_from_slice(tag);
    let bin = tmp("own.bin");
    std::fs::write(&bin, &img).unwrap();
    let out_path = tmp("own.tbu");
    let sign_with = |extra: &[&str]| {
        let mut args = vec![
            "sign",
            "--key",
            k.key.to_str().unwrap(),
            "--chip",
            "esp32c3",
            "--board",
            "c3-supermini",
        ];
        args.extend_from_slice(extra);
        args.extend_from_slice(&[bin.to_str().unwrap(), "-o", out_path.to_str().unwrap()]);
        tinybms(&args)
    };
    let out = sign_with(&[]);
    assert_eq!(out.code, 0, "{out}");
    let file = std::fs::read(&out_path).unwrap();
    let field = |from: usize, to: usize| {
        String::from_utf8(
            file[from..to]
                .iter()
                .copied()
                .take_while(|&b| b != 0)
                .collect(),
        )
        .unwrap()
    };
    assert_eq!(field(124, 148), "0.2.0");
    assert_eq!(field(148, 180), "src-0123abcd");
    assert_eq!(field(84, 124), "can,host-link,store");
    for (flag, value, says) in [
        ("--version", "0.3.0", "version is `0.2.0`"),
        ("--build", "v9", "build is `src-0123abcd`"),
        (
            "--features",
            "can,host-link,wifi,store",
            "features is `can,host-link,store`",
        ),
    ] {
        let out = sign_with(&[flag, value]);
        assert_eq!(out.code, 1, "{flag}: {out}");
        assert!(out.stderr.contains(says), "{flag}: {out}");
    }
    // The same values given agree: taken.
    let out = sign_with(&["--version", "0.2.0", "--build", "src-0123abcd"]);
    assert_eq!(out.code, 0, "{out}");
}
