//! Improv Wi-Fi on the host port: its packets, the WPA2 key derived on the
//! bridge, the port shared with the host link, and the whole exchange the
//! browser installer has with the station (provision, a wrong passphrase, a
//! network that is not there, malformed packets, an image without Wi-Fi).

use std::time::{Duration, Instant as Wall};

use host_tests::real_time::SimPort;
use host_tests::sim::{PackModel, SimBms, SimConfig};
use host_tests::sim_wifi::{SimNetwork, SimWifi};
use proptest::prelude::*;
use tinybms_desk::flash::{DeskFlash, RamFlash};
use tinybms_desk::{HostSide, Hosted};
use tinybms_firmware::host_link::assembler::{LineAssembler, Piece};
use tinybms_firmware::improv::psk::{PskDerivation, PskError, Start};
use tinybms_firmware::improv::wire::{self, checksum, ErrorState, PacketError, Rpc, State};

// ------------------------------------------------------------------ packets

/// A command packet as improv-wifi-serial-sdk writes it, without its `\n`.
fn rpc(cmd: u8, args: &[u8]) -> Vec<u8> {
    let mut p = b"IMPROV".to_vec();
    p.extend_from_slice(&[1, 3, (args.len() + 2) as u8, cmd, args.len() as u8]);
    p.extend_from_slice(args);
    p.push(checksum(&p));
    p
}

fn settings(ssid: &str, pass: &str) -> Vec<u8> {
    let mut a = vec![ssid.len() as u8];
    a.extend_from_slice(ssid.as_bytes());
    a.push(pass.len() as u8);
    a.extend_from_slice(pass.as_bytes());
    rpc(1, &a)
}

#[test]
fn the_sdks_request_for_the_state_is_read() {
    // IMPROV, version 1, type 3 (RPC), length 2, command 2, no arguments,
    // checksum: the bytes the installer sends first.
    let p = [
        b'I', b'M', b'P', b'R', b'O', b'V', 0x01, 0x03, 0x02, 0x02, 0x00, 0xE5,
    ];
    assert_eq!(wire::parse(&p), Ok(Rpc::CurrentState));
    assert_eq!(rpc(2, b""), p);
}

#[test]
fn wifi_settings_carry_the_network_and_passphrase() {
    assert_eq!(
        wire::parse(&settings("home", "secret-key")),
        Ok(Rpc::WifiSettings {
            ssid: b"home",
            passphrase: b"secret-key"
        })
    );
    assert_eq!(
        wire::parse(&settings("cafe", "")),
        Ok(Rpc::WifiSettings {
            ssid: b"cafe",
            passphrase: b""
        })
    );
}

#[test]
fn every_kind_of_bad_packet_is_named_never_a_command() {
    let good = rpc(2, b"");
    let n = good.len();
    let mut bad_sum = good.clone();
    bad_sum[n - 1] ^= 1;
    assert_eq!(wire::parse(&bad_sum), Err(PacketError::Checksum));
    assert_eq!(wire::parse(&good[..n - 1]), Err(PacketError::Length));
    assert_eq!(wire::parse(b"IMPRO"), Err(PacketError::Length));
    assert_eq!(
        wire::parse(b"IMPROX\x01\x03\x00\x00"),
        Err(PacketError::Header)
    );
    let fix = |mut p: Vec<u8>| {
        let n = p.len();
        p[n - 1] = checksum(&p[..n - 1]);
        p
    };
    let mut v2 = good.clone();
    v2[6] = 2;
    assert_eq!(wire::parse(&fix(v2)), Err(PacketError::Version));
    let mut state = good.clone();
    state[7] = 1;
    assert_eq!(wire::parse(&fix(state)), Err(PacketError::NotRpc));
    // The network's length runs past the command's data.
    assert_eq!(
        wire::parse(&rpc(1, b"\x09home\x00")),
        Err(PacketError::Arguments)
    );
    // Bytes after the passphrase.
    assert_eq!(
        wire::parse(&rpc(1, b"\x01a\x01bX")),
        Err(PacketError::Arguments)
    );
    // The command's own length beyond the packet.
    let mut over = rpc(2, b"");
    over[10] = 5;
    assert_eq!(wire::parse(&fix(over)), Err(PacketError::Arguments));
    assert_eq!(wire::parse(&rpc(9, b"")), Ok(Rpc::Other(9)));
}

proptest! {
    #[test]
    fn any_bytes_parse_without_panic_and_a_command_only_with_its_checksum(
        bytes in proptest::collection::vec(any::<u8>(), 0..300)
    ) {
        let mut p = b"IMPROV".to_vec();
        p.extend_from_slice(&bytes);
        if wire::parse(&p).is_ok() {
            let n = p.len();
            prop_assert_eq!(p[n - 1], checksum(&p[..n - 1]));
            prop_assert_eq!(usize::from(p[8]) + 10, n);
        }
    }
}

#[test]
fn packets_for_the_host_have_their_checksum_and_newline() {
    assert_eq!(
        &wire::current_state(State::Provisioned)[..],
        b"IMPROV\x01\x01\x01\x04\xe4\n"
    );
    let e = wire::error_state(ErrorState::UnableToConnect);
    assert_eq!(e[9], 3);
    assert_eq!(e[10], checksum(&e[..10]));
    let r = wire::result(3, &[b"TinyBMS bridge", b"0.1.0", b"ESP32-C3", b"tinybms-1"]);
    assert_eq!(r[9], 3, "the command answered");
    assert_eq!(usize::from(r[10]), 15 + 6 + 9 + 10);
    assert_eq!(&r[11..26], b"\x0eTinyBMS bridge");
    assert_eq!(r[r.len() - 2], checksum(&r[..r.len() - 2]));
    // Too much for one packet: whole strings are left out, never cut.
    let long = [b'x'; 200];
    let r = wire::result(4, &[&long, &long]);
    assert_eq!(usize::from(r[8]), 2 + 201);
}

// ------------------------------------------------------------------ the key

fn psk_of(ssid: &str, pass: &str) -> String {
    match PskDerivation::start(ssid.as_bytes(), pass.as_bytes()).unwrap() {
        Start::Derive(mut d) => {
            let mut steps = 0;
            loop {
                steps += 1;
                if let Some(k) = d.step() {
                    assert!(steps > 100, "the work is spread over many steps");
                    return k.to_string();
                }
            }
        }
        other => panic!("{other:?}"),
    }
}

fn reference(ssid: &str, pass: &str) -> String {
    SimNetwork {
        ssid: ssid.into(),
        passphrase: Some(pass.into()),
        rssi: -50,
    }
    .psk()
}

#[test]
fn the_key_is_ieee_802_11i_s() {
    // IEEE 802.11i-2004, annex H.4.
    assert_eq!(
        psk_of("IEEE", "password"),
        "f42c6fc52df0ebef9ebb4b90b38a5f902e83fe1b135a70e23aed762e9710a12e"
    );
    assert_eq!(
        psk_of("ThisIsASSID", "ThisIsAPassword"),
        "0dc0d6eb90555ed6419756b9a15ec3e3209b63df707dd508d14581f8982721af"
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    #[test]
    fn the_key_is_the_pbkdf2_crates(
        ssid in "[ -~]{1,32}",
        pass in "[ -~]{8,63}",
    ) {
        prop_assert_eq!(psk_of(&ssid, &pass), reference(&ssid, &pass));
    }
}

#[test]
fn a_passphrase_that_cannot_be_wpa2_is_refused_and_a_hex_key_is_the_key() {
    let err = |s: &str, p: &[u8]| match PskDerivation::start(s.as_bytes(), p) {
        Err(e) => e,
        Ok(s) => panic!("{s:?}"),
    };
    assert_eq!(err("home", b"short"), PskError::Passphrase);
    assert_eq!(err("home", &[b'z'; 64]), PskError::Passphrase);
    assert_eq!(err("home", "pässwörd".as_bytes()), PskError::Passphrase);
    assert_eq!(err("", b"password"), PskError::SsidLength);
    assert_eq!(err(&"s".repeat(33), b"password"), PskError::SsidLength);
    let hex = "F42C6FC52DF0EBEF9EBB4B90B38A5F902E83FE1B135A70E23AED762E9710A12E";
    match PskDerivation::start(b"IEEE", hex.as_bytes()).unwrap() {
        Start::Key(k) => assert_eq!(k.as_str(), hex.to_lowercase()),
        other => panic!("{other:?}"),
    }
    assert!(matches!(
        PskDerivation::start(b"cafe", b"").unwrap(),
        Start::Open
    ));
    // Nothing of the passphrase in its debug form.
    let Start::Derive(d) = PskDerivation::start(b"home", b"hunter22-secret").unwrap() else {
        panic!()
    };
    assert!(!format!("{d:?}").contains("hunter22"));
}

// ---------------------------------------------------- the port, shared

fn pieces(chunks: &[&[u8]]) -> Vec<(String, Vec<u8>)> {
    let mut a = LineAssembler::new();
    let mut out = Vec::new();
    for chunk in chunks {
        let mut rest: &[u8] = chunk;
        while !rest.is_empty() {
            let (n, p) = a.push(rest);
            match p {
                Some(Piece::Line(l)) => out.push(("line".into(), l.to_vec())),
                Some(Piece::TooLong) => out.push(("too_long".into(), vec![])),
                Some(Piece::Improv(p)) => out.push(("improv".into(), p.to_vec())),
                None => {}
            }
            rest = &rest[n..];
        }
    }
    out
}

#[test]
fn a_newline_inside_an_improv_packet_does_not_end_it() {
    // The SSID's length is 10 (`\n`), and the passphrase holds a `\n` too.
    let p = settings("ten-bytes!", "line\nbreak-1");
    assert_eq!(p[11], b'\n');
    let mut bytes = b"{\"cmd\":\"hello\"}\n".to_vec();
    bytes.extend_from_slice(&p);
    bytes.push(b'\n');
    bytes.extend_from_slice(b"{\"cmd\":\"get\",\"what\":\"link\"}\n");
    let whole = pieces(&[&bytes]);
    assert_eq!(
        whole,
        vec![
            ("line".into(), b"{\"cmd\":\"hello\"}".to_vec()),
            ("improv".into(), p.clone()),
            ("line".into(), vec![]),
            (
                "line".into(),
                b"{\"cmd\":\"get\",\"what\":\"link\"}".to_vec()
            ),
        ]
    );
    // The same whatever the chunks.
    for size in 1..bytes.len() {
        let chunks: Vec<&[u8]> = bytes.chunks(size).collect();
        assert_eq!(pieces(&chunks), whole, "chunks of {size}");
    }
}

#[test]
fn a_line_that_only_starts_like_improv_is_a_line() {
    assert_eq!(
        pieces(&[b"IMPRO\n", b"IMP{x}\n"]),
        vec![
            ("line".into(), b"IMPRO".to_vec()),
            ("line".into(), b"IMP{x}".to_vec())
        ]
    );
}

// ------------------------------------------- the exchange with a station

/// The host side: every byte the bridge writes, kept whole.
#[derive(Default)]
struct Port {
    out: Vec<u8>,
    to_bridge: Vec<u8>,
}

impl HostSide for Port {
    fn read(&mut self, into: &mut Vec<u8>) -> std::io::Result<()> {
        into.append(&mut self.to_bridge);
        Ok(())
    }
    fn can_take(&mut self) -> bool {
        true
    }
    fn write_line(&mut self, line: &[u8]) -> std::io::Result<()> {
        self.out.extend_from_slice(line);
        Ok(())
    }
}

/// What the bridge sent, split as the installer's reader splits it: Improv
/// packets (type, data) and the other lines.
fn split(bytes: &[u8]) -> (Vec<(u8, Vec<u8>)>, Vec<String>) {
    let mut packets = Vec::new();
    let mut lines = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i..].starts_with(b"IMPROV") {
            let len = usize::from(bytes[i + 8]);
            let p = &bytes[i..i + 10 + len];
            assert_eq!(p[9 + len], checksum(&p[..9 + len]), "checksum");
            assert_eq!(bytes[i + 10 + len], b'\n', "a packet ends its line");
            packets.push((p[7], p[9..9 + len].to_vec()));
            i += 11 + len;
        } else {
            let end = bytes[i..].iter().position(|&b| b == b'\n').unwrap() + i;
            lines.push(String::from_utf8(bytes[i..end].to_vec()).unwrap());
            i = end + 1;
        }
    }
    (packets, lines)
}

/// The strings of an RPC result's data.
fn strings(data: &[u8]) -> Vec<String> {
    let mut out = Vec::new();
    let mut i = 2;
    while i < 2 + usize::from(data[1]) {
        let n = usize::from(data[i]);
        out.push(String::from_utf8(data[i + 1..i + 1 + n].to_vec()).unwrap());
        i += 1 + n;
    }
    out
}

struct Bridge {
    h: Hosted<SimPort>,
    port: Port,
}

impl Bridge {
    fn new(wifi: bool) -> Self {
        let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 5);
        let mut h = Hosted::with_wifi(
            SimPort::new(sim),
            tinybms_firmware::bms::timing::Timing::default(),
            DeskFlash::Ram(RamFlash::new()),
            "esp32c3",
            wifi,
        );
        if wifi {
            let mut w = SimWifi::new(vec![
                SimNetwork::parse("home:correct horse:-48").unwrap(),
                SimNetwork::parse("cafe").unwrap(),
                SimNetwork::parse("neighbour:whatever1:-80").unwrap(),
            ]);
            w.delay = Duration::from_millis(200);
            h.driver.wifi = Some(Box::new(w));
        }
        h.network_name = Some("tinybms-test".into());
        h.boot_wifi();
        h.connected();
        Self {
            h,
            port: Port::default(),
        }
    }

    fn send(&mut self, bytes: &[u8]) {
        self.port.to_bridge.extend_from_slice(bytes);
    }

    /// Steps until `done` holds for what was sent (bounded).
    fn until(&mut self, what: &str, done: impl Fn(&[(u8, Vec<u8>)], &[String]) -> bool) {
        let end = Wall::now() + Duration::from_secs(15);
        loop {
            self.h.step(&mut self.port).unwrap();
            let (p, l) = split(&self.port.out);
            if done(&p, &l) {
                return;
            }
            assert!(Wall::now() < end, "{what}: {p:?}\n{l:#?}");
        }
    }

    fn take(&mut self) -> (Vec<(u8, Vec<u8>)>, Vec<String>) {
        let r = split(&self.port.out);
        self.port.out.clear();
        r
    }
}

const STATE: u8 = 1;
const ERROR: u8 = 2;
const RESULT: u8 = 4;

#[test]
fn the_installer_provisions_the_bridge_and_the_key_is_stored_never_the_passphrase() {
    let mut b = Bridge::new(true);
    // Who are you, what state?
    let mut req = rpc(2, b"");
    req.push(b'\n');
    req.extend_from_slice(&rpc(3, b""));
    req.push(b'\n');
    b.send(&req);
    b.until("state and device info", |p, _| {
        p.iter().any(|(t, d)| *t == RESULT && d[0] == 3)
    });
    let (p, _) = b.take();
    assert!(p.contains(&(STATE, vec![0x02])), "ready: {p:?}");
    let info = p.iter().find(|(t, d)| *t == RESULT && d[0] == 3).unwrap();
    assert_eq!(
        strings(&info.1),
        vec![
            "TinyBMS bridge".to_string(),
            // An image with Wi-Fi, as its manifest names it (semver build
            // metadata), so the installer offers the other image as an update.
            format!("{}+wifi", tinybms_firmware::identity::FIRMWARE),
            "ESP32-C3".to_string(),
            "tinybms-test".to_string()
        ]
    );
    // The networks in range, strongest first, then an empty result.
    let mut scan = rpc(4, b"");
    scan.push(b'\n');
    b.send(&scan);
    b.until("scan", |p, _| {
        p.iter()
            .any(|(t, d)| *t == RESULT && d[0] == 4 && d[1] == 0)
    });
    let (p, _) = b.take();
    let nets: Vec<Vec<String>> = p
        .iter()
        .filter(|(t, d)| *t == RESULT && d[0] == 4 && d[1] > 0)
        .map(|(_, d)| strings(d))
        .collect();
    assert_eq!(
        nets,
        vec![
            vec!["home".to_string(), "-48".into(), "YES".into()],
            vec!["cafe".to_string(), "-55".into(), "NO".into()],
            vec!["neighbour".to_string(), "-80".into(), "YES".into()],
        ]
    );
    // Provision.
    let mut s = settings("home", "correct horse");
    s.push(b'\n');
    b.send(&s);
    b.until("provisioned", |p, _| {
        p.iter().any(|(t, d)| *t == RESULT && d[0] == 1)
    });
    let all = b.port.out.clone();
    let (p, lines) = b.take();
    assert!(p.contains(&(STATE, vec![0x03])), "provisioning: {p:?}");
    let provisioned = p.iter().position(|x| *x == (STATE, vec![0x04])).unwrap();
    let result = p
        .iter()
        .position(|(t, d)| *t == RESULT && d[0] == 1)
        .unwrap();
    assert!(provisioned < result, "{p:?}");
    // The record holds the network and its key, in use now.
    let rec = b.h.station().config().stored().clone();
    assert_eq!(rec.wifi_ssid.as_str(), "home");
    assert_eq!(rec.wifi_key.as_str(), reference("home", "correct horse"));
    assert!(!b
        .h
        .station()
        .config()
        .restart_pending(tinybms_firmware::config::FieldId::WifiSsid));
    let text = String::from_utf8_lossy(&all);
    assert!(
        !text.contains("correct horse"),
        "the passphrase is never echoed"
    );
    assert!(
        lines
            .iter()
            .any(|l| l.contains("Improv Wi-Fi: joined home, IP 192.0.2.10")),
        "{lines:#?}"
    );
    // hello says where the bridge is.
    b.send(b"{\"cmd\":\"hello\"}\n");
    b.until("hello", |_, l| {
        l.iter().any(|l| l.contains("\"type\":\"hello\""))
    });
    let (_, lines) = b.take();
    let hello = lines
        .iter()
        .find(|l| l.contains("\"type\":\"hello\""))
        .unwrap();
    assert!(
        hello.contains("\"wifi\":{\"state\":\"connected\",\"ip\":\"192.0.2.10\"}"),
        "{hello}"
    );
    assert!(hello.contains("\"radio\":\"up\""), "{hello}");
    // Asked again, the state is provisioned, with its (empty) URL list.
    let mut req = rpc(2, b"");
    req.push(b'\n');
    b.send(&req);
    b.until("state", |p, _| {
        p.iter().any(|(t, d)| *t == RESULT && d[0] == 2)
    });
    let (p, _) = b.take();
    assert!(p.contains(&(STATE, vec![0x04])), "{p:?}");
    // The saved record comes back at a restart, and the bridge rejoins.
    b.h.restart();
    b.port.out.clear();
    assert_eq!(b.h.station().config().running().wifi_ssid.as_str(), "home");
    let t = Wall::now();
    while t.elapsed() < Duration::from_millis(400) {
        b.h.step(&mut b.port).unwrap();
    }
    b.send(b"{\"cmd\":\"hello\"}\n");
    b.until("hello after the restart", |_, l| {
        l.iter()
            .any(|l| l.contains("\"type\":\"hello\"") && l.contains("\"state\":\"connected\""))
    });
}

#[test]
fn a_wrong_passphrase_or_an_absent_network_is_unable_to_connect_and_changes_nothing() {
    let mut b = Bridge::new(true);
    for (ssid, pass, why) in [
        ("home", "wrong horse", "the passphrase was not accepted"),
        ("elsewhere", "whatever1", "network not found"),
        ("home", "short", "8 to 63 printable ASCII"),
    ] {
        let mut s = settings(ssid, pass);
        s.push(b'\n');
        b.send(&s);
        b.until(why, |p, _| p.iter().any(|(t, d)| *t == ERROR && d == &[3]));
        b.until("back to ready", |p, _| {
            let e = p
                .iter()
                .position(|(t, d)| *t == ERROR && d == &[3])
                .unwrap();
            p[e..].contains(&(STATE, vec![0x02]))
        });
        let all = String::from_utf8_lossy(&b.port.out).to_string();
        let (p, lines) = b.take();
        assert!(
            !p.iter().any(|(t, d)| *t == STATE && d == &[4]),
            "{ssid}: never provisioned: {p:?}"
        );
        assert!(
            lines.iter().any(|l| l.contains(why)),
            "{ssid}: the log says why: {lines:#?}"
        );
        assert!(
            !all.contains(pass),
            "{ssid}: the passphrase is never echoed"
        );
        let rec = b.h.station().config().stored().clone();
        assert!(
            rec.wifi_ssid.is_empty() && rec.wifi_key.is_empty(),
            "{ssid}"
        );
    }
}

#[test]
fn malformed_packets_are_refused_and_the_host_link_goes_on() {
    let mut b = Bridge::new(true);
    let mut bad = rpc(2, b"");
    let n = bad.len();
    bad[n - 1] ^= 0x55;
    bad.push(b'\n');
    // A packet cut short, then a pause, then a JSON command: the command is
    // answered, not swallowed as the packet's bytes.
    bad.extend_from_slice(b"IMPROV\x01\x03\x20\x01");
    b.send(&bad);
    b.until("invalid", |p, _| {
        p.iter().any(|(t, d)| *t == ERROR && d == &[1])
    });
    let t = Wall::now();
    while t.elapsed() < Duration::from_millis(700) {
        b.h.step(&mut b.port).unwrap();
    }
    b.send(b"{\"cmd\":\"get\",\"what\":\"link\",\"req\":7}\n");
    let mut unknown = rpc(0x42, b"");
    unknown.push(b'\n');
    b.send(&unknown);
    b.until("link and unknown", |p, l| {
        l.iter().any(|l| l.contains("\"req\":7")) && p.iter().any(|(t, d)| *t == ERROR && d == &[2])
    });
    let (p, lines) = b.take();
    assert_eq!(
        p.iter().filter(|(t, d)| *t == ERROR && d == &[1]).count(),
        2,
        "the bad checksum and the cut packet: {p:?}"
    );
    assert!(
        lines.iter().any(|l| l.contains("wrong checksum")),
        "{lines:#?}"
    );
    assert!(
        lines.iter().any(|l| l.contains("\"type\":\"link\"")),
        "{lines:#?}"
    );
}

/// A radio that never finishes starting (the chip's would hang in its RF
/// calibration): the bridge polls the BMS and answers the host all the same,
/// and `hello` says where the radio stands, `starting`, then `late`.
#[test]
fn a_radio_that_never_comes_up_holds_nothing_back() {
    let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 5);
    let mut h = Hosted::with_wifi(
        SimPort::new(sim),
        tinybms_firmware::bms::timing::Timing::default(),
        DeskFlash::Ram(RamFlash::new()),
        "esp32c3",
        true,
    );
    let mut w = SimWifi::new(vec![SimNetwork::parse("home:correct horse:-48").unwrap()]);
    w.radio_hangs = true;
    w.late_after = 1_500 * tinybms_firmware::MS;
    h.driver.wifi = Some(Box::new(w));
    h.boot_wifi();
    h.connected();
    let mut b = Bridge {
        h,
        port: Port::default(),
    };
    let hello_with = |b: &mut Bridge, what: &str| {
        b.take();
        b.send(b"{\"cmd\":\"hello\"}\n");
        b.until("hello", |_, l| {
            l.iter().any(|l| l.contains("\"type\":\"hello\""))
        });
        let (_, lines) = b.take();
        let hello = lines
            .iter()
            .find(|l| l.contains("\"type\":\"hello\""))
            .unwrap()
            .clone();
        assert!(hello.contains(what), "{what}: {hello}");
    };
    hello_with(&mut b, "\"radio\":\"starting\"");
    // The BMS is read meanwhile: the bridge gets ready.
    let end = Wall::now() + Duration::from_secs(10);
    while !b.h.station().bridge().telemetry().ready {
        b.h.step(&mut b.port).unwrap();
        assert!(
            Wall::now() < end,
            "the BMS was not read while the radio hung"
        );
    }
    let end = Wall::now() + Duration::from_secs(5);
    loop {
        b.h.step(&mut b.port).unwrap();
        let (_, l) = split(&b.port.out);
        if l.iter().any(|l| l.contains("radio: not up after 20 s")) {
            break;
        }
        assert!(Wall::now() < end, "no `late` line: {l:#?}");
    }
    hello_with(&mut b, "\"radio\":\"late\"");
}

#[test]
fn an_image_without_wifi_is_recognised_but_has_wifi_stopped() {
    let mut b = Bridge::new(false);
    let mut req = rpc(2, b"");
    req.push(b'\n');
    req.extend_from_slice(&rpc(3, b""));
    req.push(b'\n');
    req.extend_from_slice(&settings("home", "correct horse"));
    req.push(b'\n');
    b.send(&req);
    b.until("answers", |p, _| {
        p.iter().any(|(t, d)| *t == ERROR && d == &[2])
    });
    let (p, _) = b.take();
    assert!(p.contains(&(STATE, vec![0x00])), "stopped: {p:?}");
    let info = p.iter().find(|(t, d)| *t == RESULT && d[0] == 3).unwrap();
    assert_eq!(strings(&info.1)[0], "TinyBMS bridge");
    // The version as the image without Wi-Fi's manifest has it: no `+wifi`.
    assert_eq!(strings(&info.1)[1], tinybms_firmware::identity::FIRMWARE);
    assert!(b.h.station().config().stored().wifi_ssid.is_empty());
}
