//! The host link (JSON Lines over USB, firmware/src/host_link/PROTOCOL.md) on the
//! real bridge against the simulated TinyBMS, in virtual time: every command,
//! every error code, outcome correlation, read-only, a slow host, telemetry equal
//! to replay's output for the same registers, and property tests of the line
//! assembler and the whole input path.

use std::collections::BTreeMap;

use host_tests::replay::{event_json, register_values};
use host_tests::virtual_host_link::{check_line, config, fuzz_one, Rig};
use proptest::prelude::*;
use protocol_core::events::{Event, EventId};
use protocol_core::response::RegisterBlock;
use protocol_core::settings::SettingId;
use serde_json::{json, Value};
use tinybms_firmware::bridge::report::WriteOutcome;
use tinybms_firmware::host_link::assembler::{LineAssembler, Piece, LINE_MAX};
use tinybms_firmware::host_link::encode;
use tinybms_firmware::host_link::{HostLink, OUT_LINE_MAX};
use tinybms_firmware::units;
use tinybms_firmware::{Report, MS, SECOND};

fn ready() -> Rig {
    let mut r = Rig::ready(config(false, 0));
    r.drain();
    r
}

fn of_type<'a>(lines: &'a [Value], ty: &str) -> Vec<&'a Value> {
    lines.iter().filter(|l| l["type"] == ty).collect()
}

fn only(lines: &[Value]) -> &Value {
    assert_eq!(lines.len(), 1, "{lines:#?}");
    &lines[0]
}

/// The error line for `line`, checking that nothing reached the bridge.
fn error_for(r: &mut Rig, line: &str) -> Value {
    r.line(line);
    assert!(!r.h.bridge().busy(), "{line}: a command reached the bridge");
    let out = r.drain();
    let e = only(&out).clone();
    assert_eq!(e["type"], "error", "{line}: {e}");
    e
}

fn assert_error(r: &mut Rig, line: &str, code: &str) -> Value {
    let e = error_for(r, line);
    assert_eq!(e["error"], code, "{line}: {e}");
    assert!(e["detail"].as_str().is_some_and(|d| !d.is_empty()), "{e}");
    e
}

// ---------------------------------------------------------------- line assembler

fn assemble(chunks: &[&[u8]]) -> Vec<Option<Vec<u8>>> {
    let mut a = LineAssembler::new();
    let mut out = Vec::new();
    for chunk in chunks {
        let mut rest: &[u8] = chunk;
        while !rest.is_empty() {
            let (n, p) = a.push(rest);
            assert!(n >= 1 && n <= rest.len());
            match p {
                Some(Piece::Line(l)) => out.push(Some(l.to_vec())),
                Some(Piece::TooLong) => out.push(None),
                Some(Piece::Improv(p)) => out.push(Some([&b"<improv>"[..], p].concat())),
                None => {}
            }
            rest = &rest[n..];
        }
    }
    out
}

#[test]
fn lines_crlf_split_and_empty() {
    assert_eq!(
        assemble(&[b"ab\r", b"\ncd\n\n"]),
        vec![Some(b"ab".to_vec()), Some(b"cd".to_vec()), Some(vec![])]
    );
}

#[test]
fn longest_line_fits_with_and_without_cr() {
    let max = vec![b'x'; LINE_MAX];
    let mut crlf = max.clone();
    crlf.extend_from_slice(b"\r\n");
    let mut lf = max.clone();
    lf.push(b'\n');
    assert_eq!(assemble(&[&crlf]), vec![Some(max.clone())]);
    assert_eq!(assemble(&[&lf]), vec![Some(max)]);
    let mut one_more = vec![b'x'; LINE_MAX + 1];
    one_more.push(b'\n');
    assert_eq!(assemble(&[&one_more]), vec![None]);
}

#[test]
fn too_long_resyncs_at_the_newline() {
    let mut very = vec![b'x'; 3 * LINE_MAX];
    very.extend_from_slice(b"\nok\n");
    assert_eq!(assemble(&[&very]), vec![None, Some(b"ok".to_vec())]);
}

// ---------------------------------------------------------------- numbers

#[test]
fn fixed_point_prints_like_replay() {
    let text = |v: Option<units::Dec>| {
        serde_json_core::to_string::<_, 64>(&v)
            .unwrap()
            .as_str()
            .to_owned()
    };
    assert_eq!(text(units::fixed(33125, 4)), "3.3125");
    assert_eq!(text(units::fixed(3650, 3)), "3.65");
    assert_eq!(text(units::fixed(-105, 1)), "-10.5");
    assert_eq!(text(units::fixed(0, 1)), "0.0");
    assert_eq!(text(units::fixed(50_000_000, 6)), "50.0");
    assert_eq!(text(units::rounded(f64::NAN, 4)), "null");
    assert_eq!(text(units::rounded(-0.00001, 4)), "0.0");
    // Against replay's own serde_json output, over many raw values and decimals.
    for decimals in 0..=6u32 {
        let special = [
            1,
            5,
            10,
            99,
            100_000,
            1_000_000,
            123_456_789_012,
            -3,
            i64::from(u32::MAX),
        ];
        for raw in (-70_000i64..70_000)
            .step_by(7)
            .chain(special)
            .chain((0..16).map(|e| 10i64.pow(e)))
        {
            let ours = text(units::fixed(raw, decimals));
            let p = 10f64.powi(decimals as i32);
            let x = raw as f64 / p;
            let r = (x * p).round() / p;
            let theirs = serde_json::to_string(&json!(if r == 0.0 { 0.0 } else { r })).unwrap();
            assert_eq!(ours, theirs, "raw {raw} decimals {decimals}");
        }
    }
    for x in [
        3.3125f32, 52.81, -12.34567, 0.00005, 0.00015, 1234.5678, 1e-7, -0.00004, 51.7, -23.4,
        6.5e8,
    ] {
        let ours = text(units::rounded(f64::from(x), 4));
        let theirs = serde_json::to_string(&host_tests::replay::rounded(f64::from(x), 4)).unwrap();
        assert_eq!(ours, theirs, "{x}");
    }
}

#[test]
fn physical_and_raw_conversions() {
    use SettingId::*;
    assert_eq!(
        units::physical(OverVoltageCutoff, 3650).map(units::Dec::as_f64),
        Some(3.65)
    );
    assert_eq!(
        units::raw_from_physical(OverVoltageCutoff, 3.65),
        Some(3650)
    );
    assert_eq!(
        units::raw_from_physical(OverVoltageCutoff, 3.6504),
        Some(3650)
    );
    assert_eq!(
        units::physical(StateOfHealth, 50_000).map(units::Dec::as_f64),
        Some(100.0)
    );
    assert_eq!(
        units::raw_from_physical(StateOfHealth, 99.998),
        Some(49_999)
    );
    assert_eq!(
        units::physical(BatteryCapacity, 10_000).map(units::Dec::as_f64),
        Some(100.0)
    );
    assert_eq!(units::raw_from_physical(OverHeatCutoff, -5.0), Some(-5));
    assert_eq!(units::raw_from_physical(OverVoltageCutoff, 1e300), None);
    for &id in SettingId::ALL {
        let (lo, hi) = id.register().unwrap().range.unwrap_or((0, 100));
        for raw in [lo, (lo + hi) / 2, hi] {
            let v = units::physical(id, raw).unwrap().as_f64();
            assert_eq!(units::raw_from_physical(id, v), Some(raw), "{id:?} {raw}");
        }
    }
}

// ---------------------------------------------------------------- errors

#[test]
fn every_error_code() {
    let mut r = Rig::new(config(false, 0));
    // Before the bridge is ready.
    let e = assert_error(
        &mut r,
        r#"{"cmd":"set","req":3,"values":{"over_voltage_cutoff":3.6}}"#,
        "not_ready",
    );
    assert_eq!(e["req"], 3);
    assert_error(&mut r, r#"{"cmd":"get","what":"settings"}"#, "not_ready");
    // The BMS's own limit for 315 is below Rev D's maximum.
    r.h.sim.override_limits(315, 3000, 3700);
    r.run(6 * SECOND);
    r.drain();

    for bad in [
        "{",
        "[1]",
        "hello",
        r#"{"cmd":"hello"} x"#,
        r#"{"cmd":"hello",}"#,
        r#"{"cmd":"hello","cmd":"get"}"#,
        r#"{"a":[[[[[1]]]]]}"#,
        "{\"cmd\":\"he\u{1}llo\"\u{ff}",
    ] {
        let e = assert_error(&mut r, bad, "malformed_json");
        assert_eq!(e["req"], Value::Null, "{bad}");
    }
    let e = assert_error(&mut r, r#"{"req":9,"cmd":"fly"}"#, "unknown_command");
    assert_eq!(e["req"], 9);
    assert!(e["detail"].as_str().unwrap().contains("fly"));
    let e = assert_error(
        &mut r,
        r#"{"cmd":"hello","req":4,"colour":"red"}"#,
        "unknown_field",
    );
    assert!(e["detail"].as_str().unwrap().contains("colour"), "{e}");
    assert_error(&mut r, r#"{"cmd":"hello","what":"link"}"#, "unknown_field");
    assert_error(&mut r, r#"{"req":1}"#, "missing_field");
    assert_error(&mut r, r#"{"cmd":"get"}"#, "missing_field");
    assert_error(&mut r, r#"{"cmd":"set"}"#, "missing_field");
    assert_error(&mut r, r#"{"cmd":"stream"}"#, "missing_field");
    assert_error(&mut r, r#"{"cmd":"capture"}"#, "missing_field");
    assert_error(&mut r, r#"{"cmd":"clear"}"#, "missing_field");
    for bad in [
        r#"{"cmd":"get","what":"everything"}"#,
        r#"{"cmd":"clear","what":"settings"}"#,
        r#"{"cmd":"hello","req":-1}"#,
        r#"{"cmd":"hello","req":"x"}"#,
        r#"{"cmd":"stream","period_ms":1.5}"#,
        r#"{"cmd":"capture","on":1}"#,
        r#"{"cmd":"set","values":{}}"#,
        r#"{"cmd":"set","values":{"over_voltage_cutoff":"3.6"}}"#,
        r#"{"cmd":"set","values":{"a":1,"b":2,"c":3,"d":4,"e":5,"f":6,"g":7,"h":8,"i":9}}"#,
        r#"{"cmd":"set","values":{"over_voltage_cutoff":3.6},"raw":{"over_voltage_cutoff":3600}}"#,
    ] {
        assert_error(&mut r, bad, "invalid_value");
    }
    let e = assert_error(
        &mut r,
        r#"{"cmd":"set","req":5,"values":{"over_voltage_cutoff":3.6,"warp_drive":1}}"#,
        "unknown_setting",
    );
    assert_eq!(e["req"], 5);
    assert!(e["detail"].as_str().unwrap().contains("warp_drive"));
    for bad in [
        r#"{"cmd":"set","values":{"over_voltage_cutoff":9.9}}"#,
        r#"{"cmd":"set","values":{"over_voltage_cutoff":1e300}}"#,
        r#"{"cmd":"set","raw":{"over_voltage_cutoff":9900}}"#,
        r#"{"cmd":"set","raw":{"over_voltage_cutoff":3600.5}}"#,
        r#"{"cmd":"set","raw":{"charger_type":7}}"#,
        r#"{"cmd":"set","raw":{"under_voltage_cutoff":2800,"over_voltage_cutoff":9900}}"#,
        r#"{"cmd":"stream","period_ms":50}"#,
        r#"{"cmd":"stream","period_ms":60001}"#,
    ] {
        assert_error(&mut r, bad, "out_of_range");
    }
    // Outside the BMS's own 0x1D limits, inside Rev D's range.
    let e = assert_error(
        &mut r,
        r#"{"cmd":"set","values":{"over_voltage_cutoff":3.9}}"#,
        "out_of_range",
    );
    assert!(
        e["detail"].as_str().unwrap().contains("outside_bms_limits"),
        "{e}"
    );

    let mut long = vec![b' '; 300];
    long.push(b'\n');
    r.send(&long);
    let e = only(&r.drain()).clone();
    assert_eq!(e["error"], "line_too_long");
    assert_eq!(e["req"], Value::Null);

    // busy: the bridge's command queue is full (nothing polls it meanwhile).
    let mut busy = None;
    for i in 0..8 {
        r.line(&format!(
            r#"{{"cmd":"clear","what":"statistics","req":{i}}}"#
        ));
        let out = r.drain();
        if out[0]["type"] == "error" {
            busy = Some(out[0].clone());
            break;
        }
        assert_eq!(out[0]["type"], "accepted");
    }
    assert_eq!(busy.expect("queue never full")["error"], "busy");

    let mut ro = Rig::ready(config(true, 0));
    ro.drain();
    assert_error(&mut ro, r#"{"cmd":"reset"}"#, "read_only");

    let stats = r.link().stats();
    assert!(
        stats.errors >= 30 && stats.lines_in >= stats.errors,
        "{stats:?}"
    );
}

#[test]
fn over_long_line_then_resync() {
    let mut r = ready();
    // A valid command that is too long (padding) must not run, even in part.
    let mut long = br#"{"cmd":"reset","req":1}"#.to_vec();
    long.extend(std::iter::repeat_n(b' ', 400));
    long.extend_from_slice(b"\r\n");
    long.extend_from_slice(b"{\"cmd\":\"hello\",\"req\":2}\r\n");
    for chunk in long.chunks(7) {
        r.send(chunk);
    }
    assert!(!r.h.bridge().busy());
    let out = r.drain();
    assert_eq!(out.len(), 2, "{out:#?}");
    assert_eq!(out[0]["error"], "line_too_long");
    assert_eq!(out[1]["type"], "hello");
    assert_eq!(out[1]["req"], 2);
}

// ---------------------------------------------------------------- commands

#[test]
fn hello_on_connect_and_on_request() {
    let mut r = Rig::new(config(false, 1000));
    r.h.station.host_connected(0);
    let h = only(&r.drain()).clone();
    assert_eq!(
        h,
        json!({"type":"hello","protocol":1,"firmware":env!("CARGO_PKG_VERSION"),
            "build":tinybms_firmware::identity::BUILD,"chip":"sim","board":"simulated",
            "features":["host-link"],"record_version":tinybms_firmware::config::VERSION,
            "read_only":false,"stream_period_ms":1000,"dropped_lines":0,
            "update":{"slot":null,"trial":"confirmed","built_in_key":null,"owner_key":null},
            "history":"this runner keeps no history"})
    );
    r.line(r#"{"cmd":"hello","req":77}"#);
    assert_eq!(only(&r.drain())["req"], 77);
}

/// Issue 29: a client id another client takes is in `hello` — and stays
/// there while the two fight (each new connection is dropped again at once),
/// until a connection holds.
#[test]
fn hello_says_where_mqtt_stands_and_a_taken_id_stays_until_a_connection_holds() {
    use tinybms_firmware::mqtt::MqttState as S;
    let mut r = Rig::new(config(false, 1000));
    let hello = |r: &mut Rig| {
        r.line(r#"{"cmd":"hello"}"#);
        only(&r.drain()).get("mqtt").cloned()
    };
    // Nothing said yet (an image without Wi-Fi says nothing at all).
    assert_eq!(hello(&mut r), None);
    r.h.station.mqtt_state(S::Connected);
    assert_eq!(hello(&mut r), Some(json!("connected")));
    r.h.station.mqtt_state(S::ClientIdTaken);
    assert_eq!(hello(&mut r), Some(json!("client_id_taken")));
    // Reconnected, and dropped again a moment later: still taken.
    r.h.station.mqtt_state(S::Connected);
    assert_eq!(hello(&mut r), Some(json!("client_id_taken")));
    r.h.station.mqtt_state(S::Held);
    assert_eq!(hello(&mut r), Some(json!("connected")));
    r.h.station.mqtt_state(S::Reconnecting);
    assert_eq!(hello(&mut r), Some(json!("reconnecting")));
}

#[test]
fn hello_names_the_store_and_the_lines_a_host_missed() {
    use tinybms_firmware::config::store::StoreSite;
    let mut r = Rig::new(config(false, 1000));
    r.h.station.set_store_site(StoreSite {
        flash_bytes: 0,
        partition: Some((0x9000, 0x6000)),
        lookup: None,
    });
    // A host that did not read: the port dropped 12 lines.
    r.h.station.host_lines_dropped(12);
    r.h.station.host_connected(0);
    let h = only(&r.drain()).clone();
    assert_eq!(h["dropped_lines"], 12, "{h}");
    assert_eq!(
        h["store"],
        json!({"flash_kib":0,"partition_offset":0x9000,"partition_bytes":0x6000,"needs_bytes":8192,
               "problem":"the `nvs` partition ends past the flash the chip reports"})
    );
    r.line(r#"{"cmd":"get","what":"link","req":3}"#);
    let link = r.drain().into_iter().find(|l| l["type"] == "link").unwrap();
    assert_eq!(link["dropped_lines"], 12, "{link}");
    // And the log says it once the host is back (here and in the chip's log).
    let logs: Vec<Value> = r
        .run_reading(SECOND)
        .into_iter()
        .filter(|l| l["type"] == "log")
        .collect();
    assert!(
        logs.iter().any(|l| l["level"] == "warn"
            && l["text"] == "host link: 12 lines dropped while no host read the port"),
        "{logs:?}"
    );
    assert!(r
        .h
        .other_log
        .iter()
        .any(|(_, l)| *l == tinybms_firmware::station::Logged::HostMissed(12)));
}

#[test]
fn get_everything() {
    let mut r = ready();
    for (what, ty) in [
        ("snapshot", "telemetry"),
        ("statistics", "statistics"),
        ("version", "version"),
        ("link", "link"),
    ] {
        r.line(&format!(r#"{{"cmd":"get","what":"{what}","req":11}}"#));
        let l = only(&r.drain()).clone();
        assert_eq!(l["type"], ty, "{l}");
        assert_eq!(l["req"], 11);
    }
    r.line(r#"{"cmd":"get","what":"settings","req":12}"#);
    let out = r.drain();
    let settings = of_type(&out, "setting");
    assert_eq!(settings.len(), SettingId::ALL.len());
    let end = out.last().unwrap();
    assert_eq!(
        *end,
        json!({"type":"settings_end","req":12,"count":SettingId::ALL.len()})
    );
    let t = r.h.bridge().telemetry();
    for (s, &id) in settings.iter().zip(SettingId::ALL) {
        assert_eq!(s["name"], tinybms_firmware::bms::profile::setting_key(id));
        assert_eq!(s["address"], id.address());
        let raw = id.read(t.settings.as_ref().unwrap()).unwrap();
        assert_eq!(s["raw"], raw);
        assert_eq!(
            s["value"],
            json!(units::physical(id, raw).unwrap().as_f64())
        );
        assert_eq!(s["unit"], id.register().unwrap().unit);
        let (lo, hi) = id
            .limits(
                t.limits_min.as_ref().unwrap(),
                t.limits_max.as_ref().unwrap(),
            )
            .unwrap();
        assert_eq!(
            s["bms_min"],
            json!(units::physical(id, lo).unwrap().as_f64()),
            "{s}"
        );
        assert_eq!(
            s["bms_max"],
            json!(units::physical(id, hi).unwrap().as_f64()),
            "{s}"
        );
    }
    let ovc = settings
        .iter()
        .find(|s| s["name"] == "over_voltage_cutoff")
        .unwrap();
    assert_eq!(ovc["unit"], "V");
    assert_eq!(ovc["min"], 1.2);
    assert_eq!(ovc["max"], 4.5);

    // Events: the history's newest and every new one, oldest first.
    r.h.sim.inject_fault_event(EventId::OverVoltageCutoff);
    r.run(8 * SECOND);
    let pushed = r.drain();
    let ev = of_type(&pushed, "event");
    assert!(!ev.is_empty(), "{pushed:#?}");
    assert_eq!(ev[0]["name"], EventId::OverVoltageCutoff.name());
    assert!(ev[0].get("history").is_none());
    r.line(r#"{"cmd":"get","what":"events","req":13}"#);
    let out = r.drain();
    let listed = of_type(&out, "event");
    assert!(listed.len() > ev.len(), "{out:#?}");
    assert!(listed
        .iter()
        .all(|e| e["history"] == true && e["req"] == 13));
    assert_eq!(
        *out.last().unwrap(),
        json!({"type":"events_end","req":13,"count":listed.len()})
    );
    let last = listed.last().unwrap();
    assert_eq!(last["name"], ev.last().unwrap()["name"]);
}

#[test]
fn event_lines_are_replays_events() {
    let mut link = HostLink::new(config(false, 0), 0);
    let bridge = tinybms_firmware::Bridge::new(tinybms_firmware::bms::timing::Timing::default(), 0);
    let events = [
        Event {
            timestamp_s: 12345,
            id: EventId::SystemStarted,
        },
        Event {
            timestamp_s: 0xFF_FFFF,
            id: EventId::Unknown(0x7E),
        },
    ];
    for e in events {
        link.on_report(&Report::NewEvent(e));
    }
    let mut buf = [0u8; OUT_LINE_MAX];
    let cfg = defaults();
    for e in events {
        let n = link.next_line(0, &bridge, &cfg, &mut buf).unwrap();
        let mut v: serde_json::Map<String, Value> =
            serde_json::from_str(&check_line(&buf[..n])).unwrap();
        assert_eq!(v.remove("type").unwrap(), "event");
        assert_eq!(v, event_json(&e));
    }
}

#[test]
fn set_reset_clear_and_outcome_correlation() {
    let mut r = ready();
    let ovc = r.h.sim.register(315);
    // Above the fully-charged voltage (3.65 V): a lower cutoff contradicts it.
    let target = if ovc == 3700 { 3750 } else { 3700 };
    r.line(&format!(
        r#"{{"cmd":"set","req":7,"values":{{"over_voltage_cutoff":{},"under_voltage_cutoff":2.8}}}}"#,
        f64::from(target) / 1000.0
    ));
    r.line(r#"{"cmd":"set","req":8,"raw":{"Charge Restart Level":80}}"#);
    let acc = r.drain();
    assert_eq!(
        acc,
        vec![
            json!({"type":"accepted","req":7,"cmd":"set"}),
            json!({"type":"accepted","req":8,"cmd":"set"})
        ]
    );
    r.run(10 * SECOND);
    let out = r.drain();
    let outcomes = of_type(&out, "outcome");
    assert_eq!(outcomes.len(), 3, "{out:#?}");
    assert_eq!(outcomes[0]["req"], 7);
    assert_eq!(outcomes[0]["name"], "over_voltage_cutoff");
    assert_eq!(outcomes[0]["raw"], target);
    assert_eq!(outcomes[0]["outcome"], "verified");
    assert_eq!(outcomes[1]["req"], 7);
    assert_eq!(outcomes[1]["name"], "under_voltage_cutoff");
    assert_eq!(outcomes[1]["raw"], 2800);
    assert_eq!(outcomes[2]["req"], 8);
    assert_eq!(outcomes[2]["name"], "charge_restart_level");
    assert_eq!(r.h.sim.register(315), target);

    r.line(r#"{"cmd":"clear","what":"events","req":20}"#);
    r.line(r#"{"cmd":"clear","what":"statistics","req":21}"#);
    r.line(r#"{"cmd":"reset","req":22}"#);
    r.run(30 * SECOND);
    let out = r.drain();
    assert_eq!(of_type(&out, "accepted").len(), 3);
    let cleared = of_type(&out, "cleared");
    assert_eq!(
        *cleared[0],
        json!({"type":"cleared","req":20,"what":"events","ok":true})
    );
    assert_eq!(
        *cleared[1],
        json!({"type":"cleared","req":21,"what":"statistics","ok":true})
    );
    let done = only(
        &of_type(&out, "reset_done")
            .into_iter()
            .cloned()
            .collect::<Vec<_>>(),
    )
    .clone();
    assert_eq!(done["req"], 22);

    // Outcomes of writes the host did not ask for carry no req.
    let mut link = HostLink::new(config(false, 0), 0);
    let setting = protocol_core::settings::Setting {
        id: SettingId::OverVoltageCutoff,
        value: 3650,
    };
    link.on_report(&Report::Write {
        setting,
        outcome: WriteOutcome::Unconfirmed(tinybms_firmware::bms::link::Failure::Timeout),
    });
    link.on_report(&Report::WriteFollowUp {
        setting,
        outcome: WriteOutcome::Verified,
    });
    let mut buf = [0u8; OUT_LINE_MAX];
    let bridge = tinybms_firmware::Bridge::new(tinybms_firmware::bms::timing::Timing::default(), 0);
    let cfg = defaults();
    let mut next = || {
        let n = link.next_line(0, &bridge, &cfg, &mut buf).unwrap();
        serde_json::from_str::<Value>(&check_line(&buf[..n])).unwrap()
    };
    let a = next();
    let b = next();
    assert_eq!(
        a,
        json!({"type":"outcome","name":"over_voltage_cutoff","raw":3650,"value":3.65,"outcome":"unconfirmed","detail":"timeout"})
    );
    assert_eq!(b["follow_up"], true);
    assert!(b.get("req").is_none());
}

#[test]
fn follow_up_outcome_keeps_the_req() {
    let mut r = ready();
    // Above the fully-charged voltage (3.65 V): a lower cutoff contradicts it.
    let target = if r.h.sim.register(315) == 3700 {
        3750
    } else {
        3700
    };
    // The read-back after the write is lost: unconfirmed, then settled by the
    // settings read that follows.
    r.line(&format!(
        r#"{{"cmd":"set","req":31,"raw":{{"315":{target}}}}}"#
    ));
    let mut seen = Vec::new();
    let mut dropped = false;
    for _ in 0..400 {
        r.run(25 * MS);
        if !dropped
            && r.h
                .sim
                .stats()
                .requests_by_command
                .get(&0x10)
                .copied()
                .unwrap_or(0)
                > 0
        {
            r.h.sim.drop_next_replies(0x09, 50);
            dropped = true;
        }
        seen.extend(r.drain());
    }
    let outcomes = of_type(&seen, "outcome");
    assert!(outcomes.iter().all(|o| o["req"] == 31), "{outcomes:#?}");
    assert_eq!(outcomes.len(), 2, "{outcomes:#?}");
    assert_eq!(outcomes[0]["outcome"], "unconfirmed", "{outcomes:#?}");
    assert_eq!(outcomes[1]["follow_up"], true, "{outcomes:#?}");
}

#[test]
fn read_only_refuses_writes() {
    let mut r = Rig::ready(config(true, 0));
    r.line(r#"{"cmd":"hello"}"#);
    assert_eq!(only(&r.drain())["read_only"], true);
    for cmd in [
        r#"{"cmd":"set","req":1,"values":{"over_voltage_cutoff":3.6}}"#,
        r#"{"cmd":"set","raw":{"over_voltage_cutoff":3600}}"#,
        r#"{"cmd":"reset"}"#,
        r#"{"cmd":"clear","what":"events"}"#,
        r#"{"cmd":"clear","what":"statistics"}"#,
    ] {
        assert_error(&mut r, cmd, "read_only");
    }
    let before = r.h.sim.stats().requests_by_command.clone();
    r.run(5 * SECOND);
    for c in [0x02u8, 0x0B, 0x0D, 0x10] {
        assert_eq!(
            r.h.sim.stats().requests_by_command.get(&c),
            before.get(&c),
            "command 0x{c:02X}"
        );
    }
    // Reading still works.
    r.line(r#"{"cmd":"get","what":"snapshot"}"#);
    assert_eq!(only(&r.drain())["type"], "telemetry");
}

#[test]
fn stream_and_capture() {
    let mut r = Rig::new(config(false, 1000));
    // Before the first snapshot: the head only.
    r.line(r#"{"cmd":"get","what":"snapshot"}"#);
    let t = only(&r.drain()).clone();
    assert_eq!(
        t,
        json!({"type":"telemetry","seq":0,"age_ms":null,"stale_after_ms":5000,"online":true,"ready":false})
    );
    let out = r.run_reading(9 * SECOND);
    let tel = of_type(&out, "telemetry");
    assert!((8..=10).contains(&tel.len()), "{}", tel.len());
    assert!(tel
        .iter()
        .all(|t| t["ready"] == true && t.get("pack_voltage_v").is_some()));
    r.line(r#"{"cmd":"stream","period_ms":200,"req":1}"#);
    let out = r.run_reading(2 * SECOND);
    assert_eq!(out[0], json!({"type":"accepted","req":1,"cmd":"stream"}));
    assert!((9..=11).contains(&of_type(&out, "telemetry").len()));
    r.line(r#"{"cmd":"stream","period_ms":0}"#);
    assert_eq!(of_type(&r.run_reading(3 * SECOND), "telemetry").len(), 0);

    // Capture: the station hands every UART byte to the host link, both ways.
    r.line(r#"{"cmd":"capture","on":true}"#);
    let out = r.run_reading(600 * MS);
    assert_eq!(out[0]["type"], "accepted");
    let raw = of_type(&out, "raw");
    assert!(
        raw.iter()
            .any(|l| l["dir"] == "tx" && l["hex"] == "AA 03 00 00 00 38 5D C3"),
        "the live read goes out as a raw tx line: {:#?}",
        raw.iter().filter(|l| l["dir"] == "tx").collect::<Vec<_>>()
    );
    let rx: Vec<_> = raw.iter().filter(|l| l["dir"] == "rx").collect();
    assert!(!rx.is_empty());
    assert!(rx.iter().all(|l| l["hex"].as_str().unwrap().len() < 32 * 3));
    assert!(rx[0]["hex"].as_str().unwrap().starts_with("AA 03 70"));
    r.line(r#"{"cmd":"capture","on":false}"#);
    r.drain();
    assert_eq!(of_type(&r.run_reading(SECOND), "raw").len(), 0);
}

#[test]
fn slow_host_loses_telemetry_not_outcomes() {
    let mut r = Rig::ready(config(false, 100));
    r.drain();
    // Above the fully-charged voltage (3.65 V): a lower cutoff contradicts it.
    let target = if r.h.sim.register(315) == 3700 {
        3750
    } else {
        3700
    };
    r.line(&format!(
        r#"{{"cmd":"set","req":5,"raw":{{"over_voltage_cutoff":{target}}}}}"#
    ));
    // Also fill the output with errors while nobody reads.
    for _ in 0..40 {
        r.line("nonsense");
    }
    r.run(20 * SECOND);
    let stats = r.link().stats();
    assert!(stats.dropped_lines >= 150, "{stats:?}");
    let out = r.drain();
    assert_eq!(out[0], json!({"type":"accepted","req":5,"cmd":"set"}));
    let outcome = of_type(&out, "outcome");
    assert_eq!(outcome.len(), 1, "{out:#?}");
    assert_eq!(outcome[0]["req"], 5);
    assert_eq!(outcome[0]["outcome"], "verified");
    assert!(of_type(&out, "telemetry").len() <= 1);
    // The host reads again: the stream resumes.
    assert!(of_type(&r.run_reading(SECOND), "telemetry").len() >= 9);
}

// ---------------------------------------------------------------- replay's names and values

fn regs(block: &RegisterBlock) -> BTreeMap<u16, u16> {
    block
        .values
        .iter()
        .enumerate()
        .map(|(i, &v)| (block.start + i as u16, v))
        .collect()
}

fn assert_fields_equal(line: &Value, replay: &serde_json::Map<String, Value>, skip: &[&str]) {
    let obj = line.as_object().unwrap();
    for (k, v) in replay {
        assert_eq!(obj.get(k), Some(v), "field {k}: {line}");
    }
    for k in obj.keys() {
        assert!(
            replay.contains_key(k) || skip.contains(&k.as_str()),
            "field {k} is not replay's"
        );
    }
}

#[test]
fn telemetry_statistics_and_version_are_replays_values() {
    let mut r = ready();
    // Several snapshots, currents of both signs, a disconnected sensor.
    for step in 0..6 {
        r.h.sim
            .set_external_current(Some(if step % 2 == 0 { -23.4 } else { 51.7 }));
        if step == 3 {
            r.h.sim.force_temperature(None);
        }
        r.run(2 * SECOND);
        r.line(r#"{"cmd":"get","what":"snapshot"}"#);
        let line = only(&r.drain()).clone();
        let t = r.h.bridge().telemetry();
        let replay = register_values(&regs(t.live_registers.as_ref().unwrap()));
        assert!(replay.len() >= 18, "{replay:?}");
        assert_fields_equal(
            &line,
            &replay,
            &[
                "type",
                "seq",
                "age_ms",
                "stale_after_ms",
                "online",
                "ready",
                "flagged",
            ],
        );
        assert_eq!(line["seq"], t.snapshot_seq);
        // The freshness limit the bridge runs with (the record's 5 s).
        assert_eq!(line["stale_after_ms"], 5000);
        assert_eq!(line["flagged"], Value::Null);
    }

    r.run(40 * SECOND);
    r.drain();
    r.line(r#"{"cmd":"get","what":"statistics"}"#);
    let line = only(&r.drain()).clone();
    let t = r.h.bridge().telemetry();
    let replay = register_values(&regs(t.statistics_registers.as_ref().unwrap()));
    assert_fields_equal(&line, &replay, &["type"]);

    r.line(r#"{"cmd":"get","what":"version"}"#);
    let line = only(&r.drain()).clone();
    let version: BTreeMap<u16, u16> = (500..=509).map(|a| (a, r.h.sim.register(a))).collect();
    let replay = register_values(&version);
    assert_fields_equal(&line, &replay, &["type"]);
}

#[test]
fn link_line_counts() {
    let mut r = ready();
    r.line("oops");
    r.line(r#"{"cmd":"get","what":"link","req":2}"#);
    let out = r.drain();
    let l = out[1].clone();
    assert_eq!(l["type"], "link");
    let s = r.h.bridge().link_stats();
    assert_eq!(l["requests"], s.requests);
    assert_eq!(l["online"], true);
    assert_eq!(l["piece_registers"], r.h.bridge().piece_registers());
    assert_eq!(l["lines_in"], 2);
    assert_eq!(l["errors"], 1);
    assert_eq!(l["dropped_lines"], 0);
}

#[test]
fn longest_telemetry_line_fits() {
    let snapshot = host_tests::fixtures::widest_snapshot();
    let mut buf = [0u8; OUT_LINE_MAX];
    let head = encode::TelemetryHead {
        req: Some(u32::MAX),
        seq: u32::MAX,
        age_ms: Some(u64::MAX),
        // The field's top: 60 s.
        stale_after_ms: Some(60_000),
        online: true,
        ready: true,
        // The longest inverter member.
        inverter: Some(encode::InverterState {
            protocol: "luxpower",
            can: "waiting",
            heard: false,
            limits: Some((u16::MAX, u16::MAX, u16::MAX)),
            stops: Some(("inverter_asked", "inverter_asked")),
            told: tinybms_firmware::inverter::dialect::Told {
                soc_pct: Some(100),
                charge_enabled: Some(false),
                discharge_enabled: Some(false),
                name: Some(*b"ABCDEFGH"),
                ..Default::default()
            },
            ignored: Some(tinybms_firmware::inverter::ignored::Ignored {
                side: tinybms_firmware::inverter::ignored::Side::Discharge,
                current_da: u16::MAX,
                for_s: u16::MAX,
            }),
            stage: Some(tinybms_firmware::inverter::finish::Stage::BalanceHeld {
                balancing: 0xF000,
                spread_mv: u16::MAX,
                left_s: u32::MAX,
            }),
            reasons: Some({
                use tinybms_firmware::inverter::why::{Reasons, Why};
                let longest = Why::OverCurrent { cutoff_a: u16::MAX };
                Reasons {
                    cvl: longest,
                    ccl: longest,
                    dcl: longest,
                }
            }),
            heartbeat: tinybms_firmware::inverter::doctor::Heartbeat {
                count: u32::MAX,
                mean_ms: u32::MAX,
                longest_ms: u32::MAX,
                late: u32::MAX,
            },
            verdicts: every_verdict(),
        }),
        restart_pending: u32::MAX,
    };
    let n = encode::telemetry(
        &mut buf,
        head,
        Some(&snapshot),
        Some("cell_count_mismatch"),
        None,
    )
    .unwrap();
    // A margin of a fifth of the buffer (the freshness limit, 25 bytes, took
    // the line from 764 to 789 bytes: past the three quarters it kept before;
    // the inverter member, 107 bytes, to 896, and the buffer from 1024 to
    // 1280 bytes; what the inverter is told — the SOC, the enable bits, the
    // name, an ignored stop — and the changes waiting for a restart, 221
    // bytes, to 1117, and the buffer to 1408 bytes; the charge's stage and
    // its reason, 136 bytes, to 1253, and the buffer to 1600 bytes; why each
    // limit is what it is, the heartbeat and the doctor's verdicts, 431
    // bytes, to 1684, and the buffer to 2112 bytes).
    assert!(n < OUT_LINE_MAX * 4 / 5, "{n}");
    check_line(&buf[..n]);
}

// ---------------------------------------------------------------- properties

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, .. ProptestConfig::default() })]

    #[test]
    fn lines_do_not_depend_on_chunking(
        input in proptest::collection::vec(prop_oneof![Just(b'\n'), Just(b'\r'), Just(b'{'), any::<u8>()], 0..1200),
        cuts in proptest::collection::vec(1usize..64, 1..40),
    ) {
        let whole = assemble(&[&input]);
        let mut chunks: Vec<&[u8]> = Vec::new();
        let mut rest: &[u8] = &input;
        for c in cuts.iter().cycle() {
            if rest.is_empty() { break; }
            let n = (*c).min(rest.len());
            chunks.push(&rest[..n]);
            rest = &rest[n..];
        }
        prop_assert_eq!(assemble(&chunks), whole.clone());
        // Every line handed out is a real line of the input, at most LINE_MAX.
        for l in whole.iter().flatten() {
            prop_assert!(l.len() <= LINE_MAX);
            prop_assert!(!l.contains(&b'\n'));
        }
    }

    #[test]
    fn over_long_lines_never_yield_commands(
        pad in LINE_MAX..(3 * LINE_MAX),
        cut in 1usize..50,
        cmd in prop::sample::select(vec![
            r#"{"cmd":"reset"}"#,
            r#"{"cmd":"clear","what":"events"}"#,
            r#"{"cmd":"set","raw":{"over_voltage_cutoff":3600}}"#,
        ]),
    ) {
        let mut input = cmd.as_bytes().to_vec();
        input.extend(std::iter::repeat_n(b' ', pad));
        input.push(b'\n');
        // Also the command after the padding, on the same line.
        let mut tail = vec![b' '; pad];
        tail.extend_from_slice(cmd.as_bytes());
        tail.push(b'\n');
        for bytes in [input, tail] {
            let mut data = vec![cut as u8, 0];
            data.extend_from_slice(&bytes);
            fuzz_one(&data);
            let pieces = assemble(&[&bytes]);
            prop_assert_eq!(pieces, vec![None]);
        }
    }

    #[test]
    fn arbitrary_bytes_never_panic(
        chunk in any::<u8>(),
        flags in 0u8..4,
        input in proptest::collection::vec(
            prop_oneof![
                4 => any::<u8>(),
                1 => Just(b'\n'),
                1 => prop::sample::select(b"{}[]\":,0123456789.-eE ".to_vec()),
            ],
            0..2000,
        ),
    ) {
        let mut data = vec![chunk, flags];
        data.extend_from_slice(&input);
        fuzz_one(&data);
    }

    #[test]
    fn command_shaped_lines_never_panic(
        chunk in any::<u8>(),
        flags in 0u8..4,
        lines in proptest::collection::vec(
            (
                prop::sample::select(vec!["hello", "get", "set", "reset", "clear", "stream", "capture",
                    "set_config", "reset_config", "x"]),
                prop::sample::select(vec!["what", "values", "raw", "period_ms", "on", "req", "fields", "zz"]),
                prop::sample::select(vec![
                    "\"snapshot\"", "\"settings\"", "\"events\"", "\"statistics\"", "\"version\"", "\"link\"",
                    "\"config\"",
                    "{\"over_voltage_cutoff\":3.6}", "{\"315\":3600,\"charger_type\":1}", "{}", "true", "0",
                    "150", "-1", "1e9", "null", "[1,2]", "\"\\u0041\"",
                    "{\"charge_current_cap\":\"50 A\"}", "{\"read_only\":\"on\"}",
                    "{\"wifi_ssid\":\"a\\\"b\",\"wifi_key\":\"00\"}", "{\"stale_after\":5}",
                    "{\"inverter_protocol\":\"sma\",\"float_voltage\":\"9 V\"}",
                ]),
            ),
            1..12,
        ),
    ) {
        let mut data = vec![chunk, flags];
        for (cmd, key, value) in lines {
            data.extend_from_slice(format!("{{\"cmd\":\"{cmd}\",\"req\":1,\"{key}\":{value}}}\n").as_bytes());
        }
        fuzz_one(&data);
    }
}

#[test]
fn fuzz_seeds_pass() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/fuzz/seeds/host_link");
    let mut n = 0;
    for entry in std::fs::read_dir(dir).unwrap() {
        fuzz_one(&std::fs::read(entry.unwrap().path()).unwrap());
        n += 1;
    }
    assert!(n >= 4);
}

/// The BMS's event log (registers 200-297 of the simulated BMS), oldest first.
fn sim_log(r: &Rig) -> Vec<Event> {
    let mut values = protocol_core::response::Words::new();
    for a in 200..=297u16 {
        values.push(r.h.sim.register(a)).unwrap();
    }
    let block = RegisterBlock { start: 200, values };
    let mut events: Vec<Event> = protocol_core::views::event_log(&block)
        .unwrap()
        .iter()
        .map(|s| s.event)
        .collect();
    events.sort_by_key(|e| e.timestamp_s);
    events
}

fn listed_events(r: &mut Rig, req: u32) -> Vec<Value> {
    r.line(&format!(r#"{{"cmd":"get","what":"events","req":{req}}}"#));
    let lines = r.drain();
    let end = lines.last().unwrap();
    assert_eq!(end["type"], "events_end", "{lines:?}");
    assert_eq!(end["req"], req);
    let events: Vec<Value> = lines[..lines.len() - 1].to_vec();
    assert_eq!(end["count"], events.len());
    for e in &events {
        assert_eq!(e["type"], "event");
        assert_eq!(e["history"], true);
        assert_eq!(e["req"], req);
    }
    events
}

#[test]
fn get_events_lists_the_whole_log_then_nothing_after_a_clear() {
    let mut r = Rig::ready(config(false, 0));
    // The first event-log turn reads the whole log (the start-up history).
    r.run(12 * SECOND);
    let truth = sim_log(&r);
    assert!(truth.len() >= 3, "the simulated BMS starts with a history");
    let listed = listed_events(&mut r, 1);
    let expected: Vec<Value> = truth
        .iter()
        .map(|e| {
            let mut m = event_json(e);
            m.insert("type".into(), json!("event"));
            m.insert("req".into(), json!(1));
            m.insert("history".into(), json!(true));
            Value::Object(m)
        })
        .collect();
    let strip = |v: &Value| {
        let mut m = v.as_object().unwrap().clone();
        m.retain(|k, _| ["timestamp_s", "id", "name", "severity"].contains(&k.as_str()));
        m
    };
    assert_eq!(
        listed.iter().map(strip).collect::<Vec<_>>(),
        expected.iter().map(strip).collect::<Vec<_>>(),
        "the whole log, oldest first"
    );
    assert_eq!(r.h.bridge().events().len(), truth.len());

    // A clear that the BMS ACKs empties what the bridge knows.
    r.line(r#"{"cmd":"clear","what":"events","req":2}"#);
    r.run(3 * SECOND);
    let out = r.drain();
    assert!(
        out.iter()
            .any(|l| l["type"] == "cleared" && l["ok"] == true && l["req"] == 2),
        "{out:?}"
    );
    let after = listed_events(&mut r, 3);
    let now_in_log = sim_log(&r);
    assert!(
        after.len() <= now_in_log.len(),
        "{after:?} vs {now_in_log:?}"
    );
}

#[test]
fn link_statistics_are_pushed_while_streaming_only() {
    let count_links = |stream_ms: u32| {
        let mut r = Rig::new(config(false, stream_ms));
        let out = r.run_reading(11 * 60 * SECOND);
        let links: Vec<Value> = out.into_iter().filter(|l| l["type"] == "link").collect();
        for l in &links {
            assert!(l.get("req").is_none(), "{l}");
            assert!(l["requests"].as_u64().unwrap() > 0, "{l}");
        }
        links.len()
    };
    // The bridge's link statistics come every 5 minutes.
    assert!((2..=3).contains(&count_links(1000)));
    assert_eq!(count_links(0), 0);
}

// ---------------------------------------------------------------- review

/// A physical value exactly on a half step rounds away from zero (PROTOCOL.md),
/// also where the decimal's f64 lies an ulp below the tie (4.0005 * 1000 is
/// 4000.4999999999995 in f64).
#[test]
fn half_step_physical_values_round_away_from_zero() {
    use SettingId::*;
    for (id, v, raw) in [
        (OverVoltageCutoff, 4.0005, 4001),
        (UnderVoltageCutoff, 2.0035, 2004),
        (BatteryCapacity, 1.005, 101),
        (BatteryCapacity, 0.145, 15),
        (StateOfHealth, 1.001, 501),
        (OverVoltageCutoff, 3.6005, 3601),
        (OverHeatCutoff, -20.5, -21),
        (OverHeatCutoff, -0.0, 0),
        // Either side of a tie.
        (OverVoltageCutoff, 4.00049, 4000),
        (OverVoltageCutoff, 4.00051, 4001),
        (BatteryCapacity, 1.00499, 100),
        (LowTemperatureChargerCutoff, -20.49, -20),
    ] {
        assert_eq!(units::raw_from_physical(id, v), Some(raw), "{id:?} {v}");
    }
}

/// `null` where a number belongs is a value of the wrong type (`invalid_value`),
/// not a number out of range (serde-json-core reads `null` as NaN).
#[test]
fn null_setting_value_is_invalid_value() {
    let mut r = ready();
    for bad in [
        r#"{"cmd":"set","values":{"over_voltage_cutoff":null}}"#,
        r#"{"cmd":"set","raw":{"over_voltage_cutoff":null}}"#,
        r#"{"cmd":"hello","req":null}"#,
        r#"{"cmd":"stream","period_ms":null}"#,
    ] {
        assert_error(&mut r, bad, "invalid_value");
    }
}

/// One setting twice in a `set` (by the same name, or by two of its names) is
/// refused whole: writing both values in turn would write one the host may not
/// mean, and which one it means is not clear (JSON leaves duplicate members
/// undefined; the command object's own are refused too).
#[test]
fn set_naming_one_setting_twice_is_refused() {
    let mut r = ready();
    for bad in [
        r#"{"cmd":"set","raw":{"over_voltage_cutoff":3600,"over_voltage_cutoff":3650}}"#,
        r#"{"cmd":"set","raw":{"over_voltage_cutoff":3600,"315":3650}}"#,
        r#"{"cmd":"set","values":{"Over-Voltage Cutoff":3.6,"over_voltage_cutoff":3.6}}"#,
    ] {
        let e = assert_error(&mut r, bad, "invalid_value");
        assert!(
            e["detail"]
                .as_str()
                .unwrap()
                .contains("over_voltage_cutoff")
                || e["detail"].as_str().unwrap().contains("315"),
            "{e}"
        );
    }
}

/// The error's detail is the reason, `: ` and the offending name, also with the
/// longest reason and a long name (up to the 32 characters kept).
#[test]
fn error_detail_keeps_the_subject_after_a_long_reason() {
    let mut r = ready();
    let name = "a_choice_that_is_32_chars_long__";
    assert_eq!(name.len(), 32);
    let e = assert_error(
        &mut r,
        &format!(r#"{{"cmd":"get","what":"{name}"}}"#),
        "invalid_value",
    );
    assert!(
        e["detail"]
            .as_str()
            .unwrap()
            .ends_with(&format!(": {name}")),
        "{e}"
    );
}

proptest! {
    /// Any registers 0-55 (unknown status codes, negative and absurd values,
    /// disconnected sensors, NaN floats): the telemetry fields are replay's,
    /// except f32 values too large to print exactly (null here, by design).
    #[test]
    fn telemetry_of_any_live_registers_is_replays(values in proptest::collection::vec(any::<u16>(), 56)) {
        let regs: BTreeMap<u16, u16> = (0..56u16).zip(values).collect();
        let replay = register_values(&regs);
        let block = RegisterBlock { start: 0, values: regs.values().copied().collect() };
        let s = protocol_core::views::LiveSnapshot::from_registers(&block).unwrap();
        let head = encode::TelemetryHead { req: None, seq: 1, age_ms: Some(0), stale_after_ms: None, online: true, ready: true, inverter: None, restart_pending: 0 };
        let mut out = [0u8; OUT_LINE_MAX];
        let n = encode::telemetry(&mut out, head, Some(&s), None, None).unwrap();
        let line: Value = serde_json::from_str(&check_line(&out[..n])).unwrap();
        for (k, v) in &replay {
            let huge = v.as_f64().is_some_and(|x| x.abs() >= 2f64.powi(53) / 1e4);
            if huge && line[k].is_null() {
                continue;
            }
            prop_assert_eq!(line.get(k), Some(v), "field {}: {}", k, line);
        }
    }
}

/// What a host leaves behind (a capture left on, its own stream period) ends
/// when the next one connects or says hello: a killed or unplugged tool leaves
/// no trace in the next session.
#[test]
fn hello_and_connect_start_a_clean_session() {
    for reconnect in ["hello", "connect"] {
        let mut r = Rig::ready(config(false, 1000));
        r.line(r#"{"cmd":"stream","period_ms":200}"#);
        r.line(r#"{"cmd":"capture","on":true}"#);
        let out = r.run_reading(2 * SECOND);
        assert!((8..=11).contains(&of_type(&out, "telemetry").len()));
        assert!(!of_type(&out, "raw").is_empty());
        assert!(r.link().capturing());
        // The tool is killed here; the next one comes.
        match reconnect {
            "hello" => r.line(r#"{"cmd":"hello","req":1}"#),
            _ => {
                let now = r.h.now;
                r.h.station.host_connected(now)
            }
        }
        let hello = r.drain();
        let hello = of_type(&hello, "hello");
        assert_eq!(hello.len(), 1);
        assert_eq!(hello[0]["stream_period_ms"], 1000);
        let out = r.run_reading(5 * SECOND);
        assert!(
            of_type(&out, "raw").is_empty(),
            "{reconnect}: capture still on"
        );
        let tel = of_type(&out, "telemetry").len();
        assert!(
            (4..=6).contains(&tel),
            "{reconnect}: {tel} telemetry lines in 5 s"
        );
        assert_eq!(r.link().stream_period_ms(), 1000);
        assert!(!r.link().capturing());
    }
}

/// The default configuration record, as a state.
fn defaults() -> tinybms_firmware::config::state::ConfigState {
    tinybms_firmware::config::state::ConfigState::new(
        tinybms_firmware::config::Config::default(),
        tinybms_firmware::config::store::Source::Empty,
    )
}

// ---------------------------------------------------------------- log lines

#[test]
fn log_lines_carry_the_bridges_log_latest_four_after_answers_before_telemetry() {
    let mut r = ready();
    for i in 0..6 {
        let text = format!("line {i}: 3.304 V, 24.5 °C, \"quoted\" \\ back");
        r.h.station
            .foreign_log(tinybms_firmware::Level::Warn, &text);
    }
    r.line(r#"{"cmd":"get","what":"link","req":7}"#);
    let out = r.drain_all();
    // The answer first, then the newest four log lines, oldest of them first.
    assert_eq!(out[0]["type"], "link", "{out:#?}");
    let logs = of_type(&out, "log");
    assert_eq!(logs.len(), 4, "{out:#?}");
    for (k, l) in logs.iter().enumerate() {
        assert_eq!(l["level"], "warn");
        assert_eq!(
            l["text"],
            format!("line {}: 3.304 V, 24.5 °C, \"quoted\" \\ back", k + 2)
        );
    }
    let first_log = out.iter().position(|l| l["type"] == "log").unwrap();
    if let Some(t) = out.iter().position(|l| l["type"] == "telemetry") {
        assert!(t > first_log, "telemetry before the log lines: {out:#?}");
    }
    // The two dropped are counted.
    r.line(r#"{"cmd":"get","what":"link"}"#);
    let link = r.drain();
    assert!(of_type(&link, "link")[0]["dropped_lines"].as_u64().unwrap() >= 2);
}

/// Every line the simulated bridge writes to its host.
struct Capture(Vec<Value>);

impl tinybms_desk::HostSide for Capture {
    fn read(&mut self, _: &mut Vec<u8>) -> std::io::Result<()> {
        Ok(())
    }
    fn can_take(&mut self) -> bool {
        true
    }
    fn write_line(&mut self, line: &[u8]) -> std::io::Result<()> {
        self.0.push(serde_json::from_slice(line).unwrap());
        Ok(())
    }
}

#[test]
fn the_bridges_reports_reach_the_host_as_log_lines_in_the_simulated_bridge() {
    // `sim --bridge-pty` hands every report's log line to the host link, as the
    // chip's log does: the start of a session has the sync and snapshot lines.
    use host_tests::real_time::SimPort;
    use host_tests::sim::{PackModel, SimBms, SimConfig};
    use tinybms_desk::flash::{DeskFlash, RamFlash};
    use tinybms_desk::Hosted;
    let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 3);
    let mut h = Hosted::new(
        SimPort::new(sim),
        tinybms_firmware::bms::timing::Timing::default(),
        DeskFlash::Ram(RamFlash::new()),
        "sim",
    );
    let mut side = Capture(Vec::new());
    let end = std::time::Instant::now() + std::time::Duration::from_secs(20);
    let texts = |c: &Capture| -> Vec<String> {
        c.0.iter()
            .filter(|l| l["type"] == "log")
            .map(|l| l["text"].as_str().unwrap().to_string())
            .collect()
    };
    while !texts(&side).iter().any(|t| t.starts_with("pack ")) {
        assert!(
            std::time::Instant::now() < end,
            "no snapshot line: {:#?}",
            texts(&side)
        );
        h.step(&mut side).unwrap();
    }
    let logs: Vec<&Value> = side.0.iter().filter(|l| l["type"] == "log").collect();
    assert!(logs
        .iter()
        .all(|l| l["level"] == "info" || l["level"] == "warn"));
    assert!(logs.len() >= 2, "{logs:#?}");
}

/// Right after a `set` is verified, `get settings` shows the value the BMS read
/// back — not the old one until the next settings read (a second `apply` then
/// showed the same difference again).
#[test]
fn get_settings_right_after_a_verified_write_shows_the_read_back_value() {
    let mut r = ready();
    let old = r.h.sim.register(310);
    let target = if old == 21 { 22 } else { 21 };
    r.line(&format!(
        r#"{{"cmd":"set","req":3,"raw":{{"charger_startup_delay":{target}}}}}"#
    ));
    // Step until the outcome line is out, then ask at once.
    let mut outcome = None;
    for _ in 0..400 {
        r.run(10 * MS);
        if let Some(o) = r.drain().into_iter().find(|l| l["type"] == "outcome") {
            outcome = Some(o);
            break;
        }
    }
    let outcome = outcome.expect("no outcome within 4 s");
    assert_eq!(outcome["outcome"], "verified", "{outcome}");
    r.line(r#"{"cmd":"get","what":"settings","req":4}"#);
    let lines = r.drain();
    let line = lines
        .iter()
        .find(|l| l["type"] == "setting" && l["name"] == "charger_startup_delay")
        .unwrap_or_else(|| panic!("{lines:#?}"));
    assert_eq!(line["raw"], target, "{line}");
    assert_eq!(r.h.sim.register(310), target);
}

/// Packs in parallel: after each streamed telemetry line, the battery and one
/// line per pack, as the inverter output sees them.
#[test]
fn a_bridge_with_a_node_number_streams_the_battery_and_its_packs() {
    use host_tests::fixtures::{self, pack_summary};
    use tinybms_firmware::inverter::control::Limits;
    use tinybms_firmware::inverter::packs::{BatteryView, PackPart, Summary};
    let s = pack_summary();
    let me = Summary {
        speaking: true,
        ..s
    };
    let lost = Summary { age_ds: 2, ..s };
    let packs = [
        (1, me, PackPart::Part),
        (2, s, PackPart::Part),
        (3, lost, PackPart::Lost),
    ];
    let view = fixtures::battery_view(true, &packs, true, |l| Limits { ccl_da: 1000, ..l });
    let battery = view.battery.expect("a battery").0;
    let mut r = Rig::ready(config(false, 1000));
    r.drain();
    r.link_mut().on_battery(Some(view.clone()));
    let out = r.run_reading(3 * SECOND + 500 * MS);
    let types: Vec<&str> = out.iter().filter_map(|l| l["type"].as_str()).collect();
    let period = ["telemetry", "battery", "pack", "pack", "pack"];
    assert!(types.len() >= 15, "{types:?}");
    for chunk in types.chunks(5).take(3) {
        assert_eq!(chunk, period);
    }
    let b = of_type(&out, "battery")[0];
    assert_eq!(
        *b,
        json!({"type":"battery","node":1,"speaking":true,"packs_online":2,"packs_offline":1,
               "capacity_ah":560.0,"soc_percent":65.43,"soh_percent":97.0,"voltage_v":53.21,
               "current_a":-8.2,"min_cell_v":3.301,"max_cell_v":3.345,"min_temperature_c":21.5,
               "max_temperature_c":24.8,"cvl_v":55.2,"ccl_a":100.0,"dcl_a":battery.limits.dcl_da as f64 / 10.0})
    );
    let p = of_type(&out, "pack");
    assert_eq!(
        *p[0],
        json!({"type":"pack","node":1,"state":"part","speaking":true,"voltage_v":53.21,
               "current_a":-4.1,"soc_percent":65.43,"soh_percent":97,"min_cell_v":3.301,
               "max_cell_v":3.345,"min_temperature_c":21.5,"max_temperature_c":24.8,
               "capacity_ah":280.0,"data_age_s":0.7,"cvl_v":55.2,"ccl_a":58.8,"dcl_a":117.6})
    );
    assert_eq!(p[2]["state"], "lost");
    assert_eq!(p[2]["data_age_s"], 0.2);
    // No pack takes part: the counts, everything else null.
    let none = BatteryView {
        battery: None,
        ..view
    };
    r.link_mut().on_battery(Some(none));
    let out = r.run_reading(1100 * MS);
    let b = of_type(&out, "battery")[0];
    assert_eq!(b["packs_online"], 0);
    assert_eq!(b["packs_offline"], 3);
    assert_eq!(b["ccl_a"], Value::Null);
    assert_eq!(b["soc_percent"], Value::Null);
    // A bridge alone streams neither.
    r.link_mut().on_battery(None);
    let out = r.run_reading(2 * SECOND);
    assert!(of_type(&out, "battery").is_empty() && of_type(&out, "pack").is_empty());
    assert!(!of_type(&out, "telemetry").is_empty());
}

// ---------------------------------------------------------------- boot lines

/// The chip's boot lines, as its shell hands them in.
fn chip_boot_lines() -> Vec<tinybms_firmware::text::Boot> {
    use tinybms_firmware::boards::{HostWire, LogPath};
    use tinybms_firmware::inverter::Protocol;
    use tinybms_firmware::text::Boot;
    vec![
        Boot::Image {
            log: Some(LogPath::Rtt),
        },
        Boot::Can {
            protocol: Protocol::Victron,
            pins: Some((4, 5)),
            node: 0,
        },
        Boot::HostLink {
            wire: Some(HostWire::UsbSerialJtag),
            read_only: false,
            stream_period_ms: 1000,
        },
        Boot::Uart {
            baud: 115_200,
            pins: Some((7, 6, 64)),
        },
        Boot::Profile {
            settings: 0,
            queued: true,
        },
    ]
}

/// Issue 26, item 8: the boot lines (image, board, pins, log path, CAN, the
/// host link's wire) reached only defmt, and the host link keeps the latest
/// 4 log lines: a host that came later never saw them. The host link keeps
/// them from boot and sends them right after every `hello` (the connection's
/// and a `hello` command's), marked `boot`, and never in the log stream.
#[test]
fn a_host_that_connects_late_gets_the_boot_lines_right_after_hello() {
    use tinybms_firmware::identity::{BUILD, FIRMWARE};
    let mut r = Rig::new(config(false, 0));
    for b in chip_boot_lines() {
        let (level, _) = r.h.station.boot_line(&b);
        assert_eq!(level, tinybms_firmware::Level::Info);
    }
    // Ten seconds of reports nobody reads: many more than four log lines.
    r.run(10 * SECOND);
    let now = r.h.now;
    r.h.station.host_connected(now);
    let want = [
        format!("tinybms-firmware {FIRMWARE} (build {BUILD}) on simulated (sim), logs over RTT"),
        "CAN to the inverter: Victron, 500 kbit/s, TX=GPIO4 RX=GPIO5".to_string(),
        "host link on USB-Serial-JTAG: read-write, telemetry every 1000 ms".to_string(),
        "UART1 115200 8N1 to the BMS: TX=GPIO7 RX=GPIO6 (rx fifo threshold 64)".to_string(),
        "settings profile empty: nothing written".to_string(),
    ];
    let check = |out: &[Value]| {
        assert_eq!(out[0]["type"], "hello", "{out:#?}");
        for (k, w) in want.iter().enumerate() {
            let l = &out[k + 1];
            assert_eq!(l["type"], "log", "{out:#?}");
            assert_eq!(l["boot"], true, "{l}");
            assert_eq!(l["level"], "info", "{l}");
            assert_eq!(l["text"], w.as_str(), "{l}");
        }
        // Then the latest log lines of the running bridge, not marked.
        let after: Vec<&Value> = out[want.len() + 1..]
            .iter()
            .filter(|l| l["type"] == "log")
            .collect();
        assert!(!after.is_empty(), "{out:#?}");
        assert!(after.iter().all(|l| l.get("boot").is_none()), "{out:#?}");
    };
    check(&r.drain_all());
    // A `hello` command starts a session too: the boot lines again.
    r.run(3 * SECOND);
    r.line(r#"{"cmd":"hello","req":4}"#);
    let out = r.drain_all();
    let hello = out.iter().position(|l| l["type"] == "hello").unwrap();
    check(&out[hello..]);
    // Between sessions they are not sent again.
    let more = r.run_reading(3 * SECOND);
    assert!(more.iter().all(|l| l.get("boot").is_none()), "{more:#?}");
}

/// The longest boot lines an image can write all fit what the host link
/// keeps (the longest board name, the CAN output of a pack node with SMA,
/// the host link on UART0, a profile too long for the queue).
#[test]
fn the_longest_boot_lines_all_fit() {
    use tinybms_firmware::boards::{HostWire, LogPath, BOARDS};

    use tinybms_firmware::identity::{Features, Identity};
    use tinybms_firmware::inverter::Protocol;

    use tinybms_firmware::text::Boot;
    let board = BOARDS
        .iter()
        .map(|b| b.name)
        .max_by_key(|n| n.len())
        .unwrap();
    let mut station = host_tests::fixtures::station(
        Identity {
            chip: "esp32c6",
            board,
            firmware: tinybms_firmware::identity::FIRMWARE,
            features: Features {
                can: true,
                host_link: true,
                wifi: true,
                store: true,
            },
        },
        tinybms_firmware::config::Config::default(),
    );
    let lines = [
        Boot::Image {
            log: Some(LogPath::Uart0),
        },
        Boot::CanOff,
        Boot::Can {
            protocol: Protocol::SmaSunnyIsland,
            pins: Some((21, 22)),
            node: 8,
        },
        Boot::HostLink {
            wire: Some(HostWire::Uart0),
            read_only: true,
            stream_period_ms: 60_000,
        },
        Boot::Uart {
            baud: 115_200,
            pins: Some((23, 22, 64)),
        },
        Boot::Profile {
            settings: 99,
            queued: false,
        },
    ];
    for b in &lines {
        station.boot_line(b);
    }
    station.host_connected(0);
    let mut out = Vec::new();
    let mut buf = [0u8; OUT_LINE_MAX];
    while let Some(n) = station.next_host_line(0, &mut buf) {
        out.push(serde_json::from_slice::<Value>(&buf[..n]).unwrap());
    }
    let boot: Vec<&Value> = out.iter().filter(|l| l["boot"] == true).collect();
    assert!(
        boot[0]["text"].as_str().unwrap().contains(board),
        "{out:#?}"
    );
    assert_eq!(boot.len(), lines.len(), "{out:#?}");
    assert_eq!(boot[5]["level"], "warn");
    assert!(boot[5]["text"]
        .as_str()
        .unwrap()
        .contains("too many for the command queue"));
}

// ---------------------------------------------------------------- chemistry

/// Issue 26, item 2: the bridge checks cell voltages against the pack's
/// chemistry before it writes — the one the BMS's own cutoffs name
/// (LiFePO4 here: 3.65 V), or the one the host gives (`chemistry`); `force`
/// passes that check, never the relations between settings.
#[test]
fn the_bridge_checks_cell_voltages_against_the_chemistry() {
    let mut r = ready();
    let set = |r: &mut Rig, line: &str| {
        r.line(line);
        r.run(10 * SECOND);
        r.drain()
    };
    // 4.25 V / 4.2 V: consistent with each other, plainly wrong for LiFePO4.
    let out = set(
        &mut r,
        r#"{"cmd":"set","req":1,"values":{"over_voltage_cutoff":4.25,"fully_charged_voltage":4.2}}"#,
    );
    let o = of_type(&out, "outcome");
    assert_eq!(o.len(), 2, "{out:#?}");
    for x in &o {
        assert_eq!(x["outcome"], "rejected", "{x}");
        assert_eq!(x["detail"], "outside_chemistry_range", "{x}");
        assert_eq!(x["chemistry"], "lifepo4", "{x}");
    }
    assert_eq!(r.h.sim.register(315), 3650, "nothing written");
    // The host says the pack is Li-ion: checked against that, written.
    let out = set(
        &mut r,
        r#"{"cmd":"set","req":2,"chemistry":"li-ion","values":{"over_voltage_cutoff":4.25,"fully_charged_voltage":4.2}}"#,
    );
    let o = of_type(&out, "outcome");
    assert!(o.iter().all(|x| x["outcome"] == "verified"), "{out:#?}");
    assert_eq!(r.h.sim.register(315), 4250);
    // Now the BMS's cutoff names Li-ion: 3.65 V is what is plainly wrong.
    let out = set(
        &mut r,
        r#"{"cmd":"set","req":3,"raw":{"fully_charged_voltage":3650}}"#,
    );
    assert_eq!(
        of_type(&out, "outcome")[0]["chemistry"],
        "li-ion",
        "{out:#?}"
    );
    // Forced: the chemistry is not checked ...
    let out = set(
        &mut r,
        r#"{"cmd":"set","req":4,"force":true,"values":{"fully_charged_voltage":3.65,"over_voltage_cutoff":3.65}}"#,
    );
    let o = of_type(&out, "outcome");
    assert!(o.iter().all(|x| x["outcome"] == "verified"), "{out:#?}");
    // ... the relations are: an over-voltage cutoff below the under-voltage one.
    let out = set(
        &mut r,
        r#"{"cmd":"set","req":5,"force":true,"values":{"over_voltage_cutoff":2.4}}"#,
    );
    let o = of_type(&out, "outcome");
    assert_eq!(o[0]["outcome"], "rejected", "{out:#?}");
    assert_eq!(o[0]["detail"], "contradicts_another_setting", "{out:#?}");
    // An unknown chemistry is an error, nothing queued.
    r.line(r#"{"cmd":"set","req":6,"chemistry":"lead-acid","values":{"over_voltage_cutoff":3.6}}"#);
    let e = only(&r.drain()).clone();
    assert_eq!(e["error"], "invalid_value", "{e}");
}

/// One verdict of each kind, with the widest numbers.
fn every_verdict() -> [Option<tinybms_firmware::inverter::doctor::Verdict>; 9] {
    use tinybms_firmware::inverter::doctor::Verdict;
    use tinybms_firmware::inverter::Protocol;
    let m = u16::MAX;
    [
        Verdict::NoAck { frames: m },
        Verdict::BusOff,
        Verdict::NoInverter { for_s: u32::MAX },
        Verdict::HeartbeatLate {
            late: m,
            longest_ms: u32::MAX,
        },
        Verdict::OtherDialect {
            id: 0x7FF,
            heard: Protocol::SmaSunnyIsland,
        },
        Verdict::OverLimit {
            charge: true,
            current_da: m,
            limit_da: m,
            for_s: u32::MAX,
        },
        Verdict::VoltageDisagrees {
            inverter_dv: m,
            bms_dv: m,
        },
        Verdict::UnknownName { name: *b"ABCDEFGH" },
        Verdict::ExportAfterStep {
            from_dv: m,
            to_dv: m,
            current_da: m,
        },
    ]
    .map(Some)
}
