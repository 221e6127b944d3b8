//! The host link's lines are one set of types (`host_link::schema`): what the
//! firmware writes from them, a host reads back into them with nothing lost and
//! nothing added. A member the firmware writes that the reading side does not
//! have (or names otherwise) fails here, as does a line type the host would
//! not recognise.

use serde_json::Value;

use host_tests::closed_loop::ClosedLoop;
use host_tests::multi_pack;
use host_tests::sim::PackModel;
use tinybms_desk::flash::RamFlash;
use tinybms_desk::ota::{chip_flash, ChipFlash};
use tinybms_desk::station::open_history;
use tinybms_firmware::host_link::encode;
use tinybms_firmware::host_link::schema::HostLine;
use tinybms_firmware::inverter::InverterConfig;

/// The line's members as the reading side holds them, written back.
fn written_back(line: &HostLine) -> Value {
    let v = match line {
        HostLine::Hello(l) => serde_json::to_value(l),
        HostLine::Telemetry(l) => serde_json::to_value(l),
        HostLine::Setting(l) => serde_json::to_value(l),
        HostLine::SettingsEnd(l) | HostLine::EventsEnd(l) => serde_json::to_value(l),
        HostLine::Can(l) => serde_json::to_value(l),
        HostLine::CanEnd(l) => serde_json::to_value(l),
        HostLine::HistoryEvent(l) => serde_json::to_value(l),
        HostLine::HistoryDay(l) => serde_json::to_value(l),
        HostLine::HistorySkipped(l) => serde_json::to_value(l),
        HostLine::HistoryEnd(l) => serde_json::to_value(l),
        HostLine::Statistics(l) => serde_json::to_value(l),
        HostLine::Version(l) => serde_json::to_value(l),
        HostLine::Event(l) => serde_json::to_value(l),
        HostLine::Log(l) => serde_json::to_value(l),
        HostLine::Link(l) => serde_json::to_value(l),
        HostLine::Accepted(l) => serde_json::to_value(l),
        HostLine::Outcome(l) => serde_json::to_value(l),
        HostLine::ResetDone(l) => serde_json::to_value(l),
        HostLine::Update(l) => serde_json::to_value(l),
        HostLine::Cleared(l) => serde_json::to_value(l),
        HostLine::Raw(l) => serde_json::to_value(l),
        HostLine::Error(l) => serde_json::to_value(l),
        HostLine::Config(l) => serde_json::to_value(l),
        HostLine::ConfigEnd(l) => serde_json::to_value(l),
        HostLine::ConfigOutcome(l) => serde_json::to_value(l),
        HostLine::ConfigDone(l) => serde_json::to_value(l),
        HostLine::Battery(l) => serde_json::to_value(l),
        HostLine::Pack(l) => serde_json::to_value(l),
        HostLine::Other => Ok(Value::Null),
    };
    v.expect("a line read back writes")
}

/// Reads `v` as a [`HostLine`] and checks that writing it back gives `v`
/// (its `type` aside, which the variant holds); returns the line's type.
fn round_trip(v: &Value) -> String {
    let ty = v["type"]
        .as_str()
        .expect("every line has a type")
        .to_string();
    let line: HostLine =
        serde_json::from_value(v.clone()).unwrap_or_else(|e| panic!("{ty}: {e}: {v}"));
    assert!(line != HostLine::Other, "{ty} is not a known line: {v}");
    let mut back = written_back(&line);
    let obj = back.as_object_mut().expect("an object");
    obj.insert("type".into(), Value::String(ty.clone()));
    // Members are compared as sets: serde_json's map keeps an order of its own.
    assert_eq!(&back, v, "{ty}: read and written back differs");
    ty
}

#[test]
fn every_line_of_a_host_session_reads_back_whole() {
    let mut l = ClosedLoop::from_flash(PackModel::LiFePO4_16S, 3, RamFlash::new(), 100.0);
    l.h.sim.set_soc_percent(40.0);
    // A history in the chip's flash with a day, events and one damaged
    // record (`history_skipped`).
    let mut chip = ChipFlash(chip_flash());
    {
        use tinybms_firmware::history::event::Code;
        use tinybms_firmware::history::ring::Kind;
        let mut h = open_history(&mut chip);
        let day = tinybms_firmware::history::day::DayRecord {
            day: 3,
            covered_s: 86_400,
            lowest_cell_mv: 3100,
            highest_cell_mv: 3500,
            ..Default::default()
        };
        h.record(Kind::Day, &day.encode());
        h.event(0, Code::Started, 1, 0, "0.9.0");
        h.event(0, Code::Bms, 1, 0, "x");
        while let Some(op) = h.next_op() {
            let ok = tinybms_firmware::history::log::run(&mut chip, op);
            h.done(ok);
        }
        // The second event's slot (the event ring's first sector, slot 2).
        chip.0.lock()[0x380000 + 2 * 64 + 20] ^= 0x40;
    }
    let h = open_history(&mut chip);
    l.h.station.set_history(l.h.now, h, Some(1));
    l.h.ota = Some(chip);
    let script: [(u64, &str); 22] = [
        (1, r#"{"cmd":"hello","req":1}"#),
        (5, r#"{"cmd":"stream","period_ms":500,"req":2}"#),
        (30, r#"{"cmd":"get","what":"settings","req":3}"#),
        (31, r#"{"cmd":"get","what":"statistics","req":4}"#),
        (32, r#"{"cmd":"get","what":"version","req":5}"#),
        (33, r#"{"cmd":"get","what":"events","req":6}"#),
        (34, r#"{"cmd":"get","what":"link","req":7}"#),
        (35, r#"{"cmd":"get","what":"config","req":8}"#),
        (36, r#"{"cmd":"get","what":"can","req":20}"#),
        (37, r#"{"cmd":"set_time","at":1765000000,"req":21}"#),
        (38, r#"{"cmd":"get","what":"history","req":22}"#),
        (
            60,
            r#"{"cmd":"set_config","fields":{"charge_current_cap":"40 A","nonsense":"1"},"req":9}"#,
        ),
        (
            61,
            r#"{"cmd":"set_config","fields":{"charge_current_cap":"40 A"},"req":10}"#,
        ),
        (
            120,
            r#"{"cmd":"set","raw":{"over_voltage_cutoff":3640},"req":11}"#,
        ),
        (
            121,
            r#"{"cmd":"set","raw":{"over_voltage_cutoff":2400},"req":12}"#,
        ),
        (200, r#"{"cmd":"clear","what":"statistics","req":13}"#),
        (250, r#"{"cmd":"no_such_command","req":14}"#),
        (300, r#"{"cmd":"capture","on":true,"req":15}"#),
        (302, r#"{"cmd":"capture","on":false,"req":16}"#),
        (310, r#"{"cmd":"reset","req":17}"#),
        (320, r#"{"cmd":"update_status","req":18}"#),
        (321, r#"{"cmd":"update_begin","size":100,"req":19}"#),
    ];
    for (at_s, line) in script {
        l.run_until(at_s * 1_000_000);
        l.host_line(line);
    }
    l.run_until(400 * 1_000_000);
    let lines = &l.host.as_ref().unwrap().lines;
    let mut seen = std::collections::BTreeSet::new();
    for v in lines {
        seen.insert(round_trip(v));
    }
    let want = [
        "hello",
        "telemetry",
        "setting",
        "settings_end",
        "statistics",
        "version",
        "event",
        "events_end",
        "link",
        "config",
        "config_end",
        "can",
        "can_end",
        "history_event",
        "history_day",
        "history_skipped",
        "history_end",
        "config_outcome",
        "config_done",
        "accepted",
        "outcome",
        "cleared",
        "error",
        "raw",
        "log",
        "reset_done",
        "update",
    ];
    let missing: Vec<_> = want.iter().filter(|t| !seen.contains(**t)).collect();
    assert!(
        missing.is_empty(),
        "the session wrote no {missing:?} line (seen: {seen:?})"
    );
    // A telemetry line with its inverter member and its snapshot read back.
    let t = lines
        .iter()
        .rev()
        .find(|v| v["type"] == "telemetry" && v["pack_voltage_v"].is_number())
        .expect("a telemetry line with a snapshot");
    let HostLine::Telemetry(t) = serde_json::from_value(t.clone()).unwrap() else {
        panic!("not telemetry")
    };
    let s = t.snapshot.expect("the snapshot read");
    assert_eq!(s.cell_voltages_v.len(), 16);
    assert!(t.told.inverter.is_some(), "the inverter member read");
}

#[test]
fn battery_and_pack_lines_read_back_whole() {
    let (l, _) = multi_pack::run_scenario("joined", 3, InverterConfig::default(), |_| {}).unwrap();
    let mut n = 0;
    for p in &l.nodes {
        let Some(view) = p.h.station.battery_view() else {
            continue;
        };
        let mut buf = [0u8; 1024];
        let k = encode::battery(&mut buf, view).unwrap();
        let v: Value = serde_json::from_slice(&buf[..k]).unwrap();
        assert_eq!(round_trip(&v), "battery");
        for pack in &view.packs {
            let k = encode::pack(&mut buf, pack).unwrap();
            let v: Value = serde_json::from_slice(&buf[..k]).unwrap();
            assert_eq!(round_trip(&v), "pack");
            n += 1;
        }
    }
    assert!(n >= 3, "{n} pack lines");
}

#[test]
fn a_member_the_reading_side_lacks_is_caught() {
    // The check above can fail: a member the types do not have is dropped on
    // the way in, so the line written back differs.
    let v: Value =
        serde_json::from_str(r#"{"type":"accepted","req":3,"cmd":"set","surprise":1}"#).unwrap();
    let line: HostLine = serde_json::from_value(v.clone()).unwrap();
    let mut back = written_back(&line);
    back.as_object_mut()
        .unwrap()
        .insert("type".into(), "accepted".into());
    assert_ne!(back, v);
    // And a type no host knows is Other, not an error.
    let other: HostLine = serde_json::from_str(r#"{"type":"from_the_future","x":1}"#).unwrap();
    assert_eq!(other, HostLine::Other);
}

/// The members of a line as written, without the line's own (`type`, `req`
/// and the telemetry head's).
fn members(encode: impl FnOnce(&mut [u8]) -> Option<usize>, head: &[&str]) -> Vec<String> {
    let mut buf = [0u8; 4096];
    let n = encode(&mut buf).unwrap();
    let v: serde_json::Map<String, Value> = serde_json::from_slice(&buf[..n]).unwrap();
    v.keys()
        .filter(|k| !head.contains(&k.as_str()))
        .cloned()
        .collect()
}

fn table(t: &[(&str, &[(u16, u16)])]) -> Vec<String> {
    t.iter().map(|(m, _)| (*m).to_string()).collect()
}

#[test]
fn the_register_tables_name_exactly_the_members_a_line_writes() {
    use protocol_core::response::{RegisterBlock, Words};
    use protocol_core::views::{LiveSnapshot, Statistics, VersionInfo};
    use tinybms_firmware::host_link::schema;
    let block = |start: u16, n: u16| {
        let mut values = Words::new();
        for i in 0..n {
            // Register 53: 16 cells; everything else a small plausible word.
            let _ = values.push(if start + i == 53 { 16 } else { 1 });
        }
        RegisterBlock { start, values }
    };
    let live = LiveSnapshot::from_registers(&block(0, 56)).unwrap();
    let head = encode::TelemetryHead {
        req: None,
        seq: 1,
        age_ms: Some(0),
        stale_after_ms: None,
        online: true,
        ready: true,
        inverter: None,
        restart_pending: 0,
    };
    let telemetry_head = ["type", "seq", "age_ms", "online", "ready", "flagged"];
    assert_eq!(
        members(
            |o| encode::telemetry(o, head, Some(&live), None, None),
            &telemetry_head
        ),
        table(schema::SNAPSHOT_REGISTERS)
    );
    let stats = Statistics::from_registers(&block(100, 18)).unwrap();
    assert_eq!(
        members(|o| encode::statistics(o, None, &stats), &["type"]),
        table(schema::STATISTICS_REGISTERS)
    );
    let version = VersionInfo::from_registers(&block(500, 10)).unwrap();
    assert_eq!(
        members(|o| encode::version(o, None, &version), &["type"]),
        table(schema::VERSION_REGISTERS)
    );
}
