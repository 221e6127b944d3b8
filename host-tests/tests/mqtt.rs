//! What the bridge publishes for Home Assistant (`tinybms_firmware::mqtt`):
//! the discovery configs (valid JSON, ids Home Assistant accepts, units that
//! fit their device class, templates that read members the state really has)
//! and the schedule (availability, discovery and its removal, the state every
//! period and at once on a status change, stale data never published, events).

use heapless::String;
use host_tests::sim::{PackModel, SimBms, SimConfig};
use proptest::prelude::*;
use protocol_core::events::{Event, EventId, OnlineStatus};
use protocol_core::response::RegisterBlock;
use protocol_core::views::{LiveSnapshot, VersionInfo};
use serde_json::Value;
use tinybms_firmware::config::Config;
use tinybms_firmware::mqtt::discovery::{self, Component, Read, ENTITIES, STATUS_OPTIONS};
use tinybms_firmware::mqtt::publisher::{Kind, Publisher, View};
use tinybms_firmware::mqtt::{Identity, Settings, PAYLOAD_MAX, TOPIC_MAX};
use tinybms_firmware::SECOND;

fn inputs() -> (LiveSnapshot, VersionInfo) {
    let sim = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 1);
    let block = |first: u16, n: u16| RegisterBlock {
        start: first,
        values: (first..first + n).map(|a| sim.register(a)).collect(),
    };
    let snap = LiveSnapshot::from_registers(&block(0, 56)).unwrap();
    let version = VersionInfo::from_registers(&block(500, 10)).unwrap();
    (snap, version)
}

fn settings() -> Settings {
    Settings::from_config(&Config::default())
}

fn id() -> Identity {
    Identity::from_version(&inputs().1)
}

fn view<'a>(snap: &'a LiveSnapshot, age_s: u64) -> View<'a> {
    View {
        snapshot: Some(snap),
        seq: 1,
        age_us: Some(age_s * SECOND),
        online: true,
        flagged: None,
        identity: Some(id()),
        limits: Some((568, 600, 1000)),
        link: (100, 99),
        wire: Default::default(),
        battery: None,
        freshness: tinybms_firmware::freshness::Freshness::new(5 * SECOND),
        energy_mwh: (12_345, 6_789),
        capacity_cah: Some(28_000),
        inverter: Some(tinybms_firmware::station::InverterStatus {
            protocol: "victron",
            can: tinybms_firmware::inverter::CanState::Running,
            heard: true,
            stops: None,
            told: Default::default(),
            ignored: None,
            stage: None,
            reasons: None,
            verdicts: [None; 9],
        }),
        wifi_rssi_dbm: Some(-61),
        update_rolled_back: None,
        update_latest: None,
        aging: tinybms_firmware::history::Aging {
            capacity: Some((27_512, 19)),
            cycles: Some(412),
            top_spread_mv: Some(12),
            recording: true,
        },
    }
}

/// Everything the publisher hands out at `now` (topic, payload, kind, retain).
fn drain(
    p: &mut Publisher,
    now: u64,
    v: &View<'_>,
) -> Vec<(std::string::String, Vec<u8>, Kind, bool)> {
    let mut out = Vec::new();
    let mut topic = String::<TOPIC_MAX>::new();
    let mut payload = vec![0u8; PAYLOAD_MAX];
    for _ in 0..200 {
        let Some(m) = p.next(now, v, &mut topic, &mut payload) else {
            break;
        };
        out.push((
            topic.to_string(),
            payload[..m.len].to_vec(),
            m.kind,
            m.retain,
        ));
    }
    out
}

fn json(b: &[u8]) -> Value {
    serde_json::from_slice(b)
        .unwrap_or_else(|e| panic!("{e}: {}", std::string::String::from_utf8_lossy(b)))
}

/// Units Home Assistant accepts for each device class used (its sensor
/// documentation, "Device class").
fn units_for(class: &str) -> &'static [&'static str] {
    match class {
        "voltage" => &["V", "mV", "µV", "kV", "MV"],
        "current" => &["A", "mA"],
        "power" => &["W", "kW", "MW", "mW"],
        "battery" => &["%"],
        "temperature" => &["°C", "°F", "K"],
        "duration" => &["d", "h", "min", "s", "ms"],
        "energy" => &["Wh", "kWh", "MWh"],
        "signal_strength" => &["dB", "dBm"],
        "enum" | "connectivity" | "firmware" => &[],
        other => panic!("device class {other} not in the test's table"),
    }
}

fn is_id(s: &str) -> bool {
    !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

#[test]
fn discovery_configs_are_what_home_assistant_accepts() {
    let (snap, _) = inputs();
    let mut p = Publisher::new(settings(), &bridge());
    p.connected(0, id());
    let v = view(&snap, 0);
    let out = drain(&mut p, 0, &v);
    let configs: Vec<_> = out.iter().filter(|m| m.2 == Kind::Discovery).collect();
    assert_eq!(
        configs.len(),
        ENTITIES.len() + 16,
        "16 cells and the fixed entities"
    );
    let mut ids = std::collections::HashSet::new();
    for (topic, payload, _, retain) in &configs {
        assert!(retain, "{topic}: discovery configs are retained");
        let parts: Vec<&str> = topic.split('/').collect();
        assert_eq!(parts.len(), 5, "{topic}");
        assert_eq!(parts[0], "homeassistant");
        assert!(
            ["sensor", "binary_sensor", "event", "update"].contains(&parts[1]),
            "{topic}"
        );
        assert!(is_id(parts[2]) && is_id(parts[3]), "{topic}");
        assert_eq!(parts[4], "config");
        let c = json(payload);
        let uid = c["unique_id"].as_str().unwrap();
        assert!(is_id(uid), "{uid}");
        assert!(ids.insert(uid.to_string()), "unique_id {uid} twice");
        assert!(uid.starts_with(&id().device_id().to_string()), "{uid}");
        // The device is the BMS, by its serial number.
        assert_eq!(c["device"]["identifiers"][0], id().device_id().as_str());
        assert_eq!(c["device"]["serial_number"], id().serial_hex().as_str());
        assert_eq!(c["device"]["manufacturer"], "Energus");
        // The BMS's versions, and the bridge that publishes it (issue 26,
        // item 8: its firmware, build, board and chip were in no device info).
        let (fw, build) = (
            tinybms_firmware::identity::FIRMWARE,
            tinybms_firmware::identity::BUILD,
        );
        let bms = id();
        assert_eq!(
            c["device"]["sw_version"],
            format!(
                "BMS {} ({}), bridge: tinybms-esp32 {fw} (build {build})",
                bms.firmware.0, bms.firmware.1
            )
        );
        assert_eq!(
            c["device"]["hw_version"],
            format!(
                "BMS {}.{}, bridge: simulated (test)",
                bms.hardware.0, bms.hardware.1
            )
        );
        assert_eq!(c["origin"]["name"], "tinybms-esp32");
        assert_eq!(c["origin"]["sw_version"], format!("{fw} (build {build})"));
        let leaf = if parts[1] == "event" {
            "/event"
        } else {
            "/state"
        };
        assert!(c["state_topic"].as_str().unwrap().ends_with(leaf));
        assert_eq!(
            c["availability"][0]["topic"],
            format!("tinybms/{}/availability", id().serial_hex())
        );
        if let Some(class) = c["device_class"].as_str() {
            let unit = c["unit_of_measurement"].as_str();
            match units_for(class) {
                [] => assert!(unit.is_none(), "{uid}: {class} has no unit"),
                units => assert!(
                    unit.is_some_and(|u| units.contains(&u)),
                    "{uid}: {class} in {unit:?}"
                ),
            }
        }
        if c["device_class"] == "enum" {
            let opts: Vec<&str> = c["options"]
                .as_array()
                .unwrap()
                .iter()
                .map(|o| o.as_str().unwrap())
                .collect();
            let want = if uid.ends_with("_status") {
                STATUS_OPTIONS
            } else if uid.ends_with("_stop") {
                discovery::STOP_CAUSES
            } else {
                discovery::CAN_STATES
            };
            assert_eq!(opts, want, "{uid}");
            assert!(c.get("state_class").is_none());
        }
        assert!(
            payload.len() < PAYLOAD_MAX,
            "{uid}: {} bytes",
            payload.len()
        );
    }
    println!(
        "{} discovery configs, the longest {} bytes",
        configs.len(),
        configs.iter().map(|c| c.1.len()).max().unwrap()
    );
}

#[test]
fn every_template_reads_a_member_the_state_has() {
    let (snap, _) = inputs();
    let mut p = Publisher::new(settings(), &bridge());
    p.connected(0, id());
    let v = view(&snap, 1);
    let out = drain(&mut p, 0, &v);
    let state = out
        .iter()
        .find(|m| m.2 == Kind::State)
        .expect("a state after connect");
    let s = json(&state.1);
    for e in ENTITIES
        .iter()
        .copied()
        .filter(|e| e.component != Component::Event)
        .chain((1..=16).map(discovery::cell))
    {
        let member = e.read.member();
        // Whole: a template cut at its buffer's end would be refused.
        let template = discovery::value_template(e.read);
        assert!(template.ends_with("}}"), "{}: {template}", e.object);
        assert!(
            s.get(member).is_some(),
            "{}: the state has no `{member}`: {s}",
            e.object
        );
        match e.read {
            Read::Member(_) => assert!(!s[member].is_null(), "{}: {member} is null", e.object),
            Read::Cell(i) => assert!(s[member][usize::from(i)].is_number(), "cell {i}"),
            Read::Nullable(_) => {}
            Read::NonZero(_) => assert!(s[member].is_number()),
            Read::Flag(_) => assert!(s[member].is_boolean(), "{}: {member}", e.object),
            Read::Event => unreachable!("the event entity reads the event topic"),
            Read::Update => {
                assert!(s[member].is_string(), "{}: {member}", e.object);
                assert!(
                    s.get("update_rolled_back").is_some_and(|v| v.is_null()),
                    "{s}"
                );
                // No newer version known: null, never the installed one
                // (Home Assistant then says unknown, not "up to date").
                assert!(s.get("update_latest").is_some_and(|v| v.is_null()), "{s}");
            }
        }
        if e.component == Component::BinarySensor {
            assert!(matches!(e.read, Read::NonZero(_) | Read::Flag(_)));
        }
    }
    // The state's own members: the host link's telemetry names and the extras.
    assert_eq!(s["type"], "telemetry");
    assert!(STATUS_OPTIONS.contains(&s["status_name"].as_str().unwrap()));
    assert_eq!(s["status"], snap.status.key().unwrap_or("other"));
    assert_eq!(s["energy_charged_kwh"], 0.012345);
    assert_eq!(s["energy_discharged_kwh"], 0.006789);
    // 280 Ah at the snapshot's SOC.
    let soc = s["soc_percent"].as_f64().unwrap();
    let left = s["remaining_capacity_ah"].as_f64().unwrap();
    assert!(
        (left - 280.0 * soc / 100.0).abs() < 0.01,
        "{left} at {soc} %"
    );
    assert_eq!(s["can_state"], "running");
    assert_eq!(s["inverter_heard"], true);
    assert_eq!(s["uptime_s"], 0);
    let firmware = format!(
        "{} ({}) on simulated",
        tinybms_firmware::identity::FIRMWARE,
        tinybms_firmware::identity::BUILD
    );
    assert_eq!(s["bridge_firmware"], firmware.as_str());
    let power = s["pack_power_w"].as_f64().unwrap();
    let expect = s["pack_voltage_v"].as_f64().unwrap() * s["pack_current_a"].as_f64().unwrap();
    assert!((power - expect).abs() < 0.1, "{power} vs {expect}");
    assert_eq!(s["cvl_v"], 56.8);
    assert_eq!(s["ccl_a"], 60.0);
    assert_eq!(s["data_age_s"], 1.0);
}

#[test]
fn a_sensor_that_is_not_connected_is_unavailable_not_zero() {
    let (mut snap, _) = inputs();
    snap.external2_dc = None;
    let mut p = Publisher::new(settings(), &bridge());
    p.connected(0, id());
    let out = drain(&mut p, 0, &view(&snap, 0));
    let cfg = out
        .iter()
        .find(|m| m.0.contains("/temperature_external_2/"))
        .map(|m| json(&m.1))
        .unwrap();
    let avail = cfg["availability"].as_array().unwrap();
    assert_eq!(avail.len(), 2, "{cfg}");
    assert_eq!(cfg["availability_mode"], "all");
    assert!(avail[1]["value_template"]
        .as_str()
        .unwrap()
        .contains("external_temperature_2_c is none"));
    let state = out
        .iter()
        .find(|m| m.2 == Kind::State)
        .map(|m| json(&m.1))
        .unwrap();
    assert!(state["external_temperature_2_c"].is_null());
}

#[test]
fn the_schedule() {
    let (snap, _) = inputs();
    let mut p = Publisher::new(settings(), &bridge());
    // Nothing before a connection.
    assert!(drain(&mut p, 0, &view(&snap, 0)).is_empty());
    p.connected(0, id());
    let out = drain(&mut p, 0, &view(&snap, 0));
    let kinds: Vec<Kind> = out.iter().map(|m| m.2).collect();
    assert_eq!(kinds[0], Kind::Availability);
    assert_eq!(out[0].1, b"online");
    assert!(out[0].3, "availability is retained");
    assert_eq!(kinds.iter().filter(|k| **k == Kind::State).count(), 1);
    assert!(
        kinds.iter().position(|k| *k == Kind::State)
            > kinds.iter().rposition(|k| *k == Kind::Discovery)
    );
    // Nothing more until the period is over (5 s)...
    assert!(drain(&mut p, 4 * SECOND, &view(&snap, 0)).is_empty());
    let at5 = drain(&mut p, 5 * SECOND, &view(&snap, 0));
    assert_eq!(at5.len(), 1);
    assert_eq!(at5[0].2, Kind::State);
    assert!(!at5[0].3, "the state is not retained");
    // ... except at once on a status change.
    let mut fault = snap.clone();
    fault.status = OnlineStatus::Fault;
    let now = drain(&mut p, 6 * SECOND, &view(&fault, 0));
    assert_eq!(now.len(), 1);
    assert_eq!(json(&now[0].1)["status"], "fault");
    // Events as they arrive, not retained.
    p.on_event(Event {
        timestamp_s: 77,
        id: EventId::SystemStarted,
    });
    let ev = drain(&mut p, 6 * SECOND, &view(&fault, 0));
    assert_eq!(ev.len(), 1);
    assert_eq!(ev[0].2, Kind::Event);
    assert!(ev[0].0.ends_with("/event"));
    assert_eq!(json(&ev[0].1)["timestamp_s"], 77);
    // Stale data: availability offline, no state.
    let stale = drain(&mut p, 20 * SECOND, &view(&fault, 6));
    assert_eq!(stale.len(), 1, "{stale:?}");
    assert_eq!(stale[0].2, Kind::Availability);
    assert_eq!(stale[0].1, b"offline");
    assert!(drain(&mut p, 30 * SECOND, &view(&fault, 16)).is_empty());
    // The BMS link down: the same.
    let mut down = view(&fault, 0);
    down.online = false;
    assert!(drain(&mut p, 31 * SECOND, &down).is_empty());
    // Fresh again: online, and a state at once.
    let back = drain(&mut p, 32 * SECOND, &view(&fault, 0));
    assert_eq!(back[0].1, b"online");
    assert_eq!(back[1].2, Kind::State);
    // Home Assistant restarted: discovery again.
    p.on_ha_status(b"offline");
    assert!(drain(&mut p, 33 * SECOND, &view(&fault, 0)).is_empty());
    p.on_ha_status(b"online");
    let again = drain(&mut p, 33 * SECOND, &view(&fault, 0));
    assert_eq!(
        again.iter().filter(|m| m.2 == Kind::Discovery).count(),
        ENTITIES.len() + 16
    );
    // Disconnected: nothing, and events wait (the newest EVENT_QUEUE).
    p.disconnected();
    for t in 0..20 {
        p.on_event(Event {
            timestamp_s: 100 + t,
            id: EventId::ChargingStarted,
        });
    }
    assert!(drain(&mut p, 40 * SECOND, &view(&fault, 0)).is_empty());
    assert_eq!(p.stats().events_dropped, 12);
    p.connected(41 * SECOND, id());
    let events: Vec<u64> = drain(&mut p, 41 * SECOND, &view(&fault, 0))
        .iter()
        .filter(|m| m.2 == Kind::Event)
        .map(|m| json(&m.1)["timestamp_s"].as_u64().unwrap())
        .collect();
    assert_eq!(events, (112..120).collect::<Vec<_>>());
}

/// A connect before the bridge's first telemetry says nothing of the
/// availability until the data comes (`online` alone: the broker already holds
/// the will's `offline`), or says `offline` once the grace is over.
#[test]
fn a_connect_before_the_first_data_says_online_once_and_never_offline_first() {
    use tinybms_firmware::mqtt::publisher::FIRST_DATA_GRACE_US;
    let (snap, _) = inputs();
    let mut nothing = view(&snap, 0);
    nothing.snapshot = None;
    nothing.age_us = None;
    let mut p = Publisher::new(settings(), &bridge());
    p.connected(SECOND, id());
    assert!(drain(&mut p, SECOND, &nothing).is_empty());
    assert!(drain(&mut p, 2 * SECOND, &nothing).is_empty());
    // The chip wakes by the end of the grace at the latest, to say `offline`.
    assert!(
        p.next_due() <= SECOND + FIRST_DATA_GRACE_US,
        "{}",
        p.next_due()
    );
    let first = drain(&mut p, 3 * SECOND, &view(&snap, 0));
    let avail: Vec<_> = first
        .iter()
        .filter(|m| m.2 == Kind::Availability)
        .map(|m| m.1.clone())
        .collect();
    assert_eq!(avail, [b"online".to_vec()]);
    // The data never comes: `offline` at the end of the grace, once.
    let mut p = Publisher::new(settings(), &bridge());
    p.connected(SECOND, id());
    assert!(drain(&mut p, SECOND + FIRST_DATA_GRACE_US - 1, &nothing).is_empty());
    let late = drain(&mut p, SECOND + FIRST_DATA_GRACE_US, &nothing);
    assert_eq!(late.len(), 1, "{late:?}");
    assert_eq!(
        (late[0].2, late[0].1.as_slice()),
        (Kind::Availability, &b"offline"[..])
    );
    assert!(drain(&mut p, 60 * SECOND, &nothing).is_empty());
    // Data that is there but stale at the connect: `offline` at once.
    let mut p = Publisher::new(settings(), &bridge());
    p.connected(SECOND, id());
    let stale = drain(&mut p, SECOND, &view(&snap, 30));
    assert_eq!(stale[0].1, b"offline");
}

#[test]
fn discovery_off_removes_the_configs() {
    let (snap, _) = inputs();
    let mut s = settings();
    s.discovery = false;
    let mut p = Publisher::new(s, &bridge());
    p.connected(0, id());
    let out = drain(&mut p, 0, &view(&snap, 0));
    let removals: Vec<_> = out.iter().filter(|m| m.2 == Kind::Removal).collect();
    assert_eq!(removals.len(), ENTITIES.len() + 16);
    assert!(removals
        .iter()
        .all(|m| m.1.is_empty() && m.3 && m.0.ends_with("/config")));
    assert!(!out.iter().any(|m| m.2 == Kind::Discovery));
    // The state is still published.
    assert!(out.iter().any(|m| m.2 == Kind::State));
}

#[test]
fn a_smaller_pack_removes_the_cells_it_does_not_have() {
    let (mut snap, _) = inputs();
    snap.cell_count = 14;
    let mut p = Publisher::new(settings(), &bridge());
    p.connected(0, id());
    let out = drain(&mut p, 0, &view(&snap, 0));
    let cells: Vec<&str> = out
        .iter()
        .filter(|m| {
            let object = m.0.split('/').nth(3).unwrap_or("");
            m.2 == Kind::Discovery
                && object.starts_with("cell_")
                && object[5..].bytes().all(|b| b.is_ascii_digit())
        })
        .map(|m| m.0.as_str())
        .collect();
    assert_eq!(cells.len(), 14, "{cells:#?}");
    let removed: Vec<&str> = out
        .iter()
        .filter(|m| m.2 == Kind::Removal)
        .map(|m| m.0.as_str())
        .collect();
    assert_eq!(removed.len(), 2, "{removed:?}");
    assert!(removed[0].contains("/cell_15/") && removed[1].contains("/cell_16/"));
}

proptest! {
    /// Any sequence of what can happen: never a panic, every topic valid,
    /// every payload empty or JSON, never a state while stale.
    #[test]
    fn any_sequence_publishes_only_valid_messages(
        steps in proptest::collection::vec((0u8..8, 0u64..30, any::<u8>()), 1..80),
    ) {
        let (snap, _) = inputs();
        let mut s = settings();
        let mut p = Publisher::new(s.clone(), &bridge());
        let mut now = 0u64;
        let mut age = 0u64;
        let mut online = true;
        for (what, dt, x) in steps {
            now += dt * SECOND / 2;
            match what {
                0 => p.connected(now, id()),
                1 => p.disconnected(),
                2 => p.on_ha_status(if x % 2 == 0 { b"online" } else { b"offline" }),
                3 => p.on_event(Event { timestamp_s: u32::from(x), id: EventId::from_raw(x) }),
                4 => age = u64::from(x % 12),
                5 => online = !online,
                6 => { s.discovery = !s.discovery; p = Publisher::new(s.clone(), &bridge()); }
                _ => {}
            }
            let mut v = view(&snap, age);
            v.online = online;
            let fresh = v.fresh();
            for (topic, payload, kind, _) in drain(&mut p, now, &v) {
                prop_assert!(topic.len() <= TOPIC_MAX && !topic.contains('#') && !topic.contains('+'));
                prop_assert!(!topic.starts_with('/') && !topic.ends_with('/'));
                if !payload.is_empty() && kind != Kind::Availability {
                    prop_assert!(serde_json::from_slice::<Value>(&payload).is_ok());
                }
                if kind == Kind::State {
                    prop_assert!(fresh, "a state while stale");
                }
            }
        }
    }
}

/// One entity as the Home Assistant guide lists it.
fn guide_row(e: &discovery::Entity) -> std::string::String {
    let read = match e.read {
        Read::Member(m) => format!("`{m}`"),
        Read::Nullable(m) => format!("`{m}` (unavailable while null)"),
        Read::Cell(i) => format!("`cell_voltages_v[{i}]`"),
        Read::NonZero(m) => format!("`{m}` > 0"),
        Read::Flag(m) => format!("`{m}` (unavailable while null)"),
        Read::Event => "the event topic: each event's `severity`".to_string(),
        Read::Update => "`bridge_firmware` as the installed version, `update_latest` as the latest (a newer version the bridge has seen: a file checked with `tinybms update --check`, an update rolled back; else unknown — the bridge does not look for releases; install is not offered, updates come from `tinybms update`), `update_rolled_back` as the release summary after a rollback".to_string(),
    };
    format!(
        "| `{}` | {} | {} | {} | {} | {} | {}{} |",
        e.object,
        e.name,
        e.component.name(),
        e.device_class.unwrap_or("—"),
        e.state_class.unwrap_or("—"),
        e.unit.unwrap_or("—"),
        read,
        if e.category.is_some() {
            ", diagnostic"
        } else {
            ""
        }
    )
}

#[test]
fn the_home_assistant_guide_lists_every_entity_as_the_firmware_announces_it() {
    let guide = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../docs/home-assistant.md"
    ))
    .unwrap();
    let rows: Vec<_> = ENTITIES
        .iter()
        .chain([discovery::cell(1), discovery::cell(16)].iter())
        .chain(tinybms_firmware::mqtt::battery::ENTITIES.iter())
        .map(guide_row)
        .collect();
    if std::env::var("PRINT_GUIDE_ROWS").is_ok() {
        println!("{}", rows.join("\n"));
    }
    for row in &rows {
        assert!(guide.contains(row), "docs/home-assistant.md lacks:\n{row}");
    }
    let listed = guide
        .lines()
        .filter(|l| {
            l.starts_with("| `")
                && (l.contains(" | sensor | ")
                    || l.contains(" | binary_sensor | ")
                    || l.contains(" | event | ")
                    || l.contains(" | update | "))
        })
        .count();
    assert_eq!(
        listed,
        rows.len(),
        "an entity in the guide that the firmware has not"
    );
    for s in STATUS_OPTIONS {
        assert!(
            guide.contains(&format!("`{s}`")),
            "status {s} not in the guide"
        );
    }
}

mod the_battery_of_packs_in_parallel {
    use super::*;
    use host_tests::fixtures::{self, pack_summary};
    use tinybms_firmware::inverter::packs::{BatteryView, PackPart, Summary};
    use tinybms_firmware::mqtt::battery;

    fn battery_view(speaking: bool, with_battery: bool) -> BatteryView {
        let s = Summary {
            speaking,
            ..pack_summary()
        };
        let other = Summary {
            speaking: false,
            ..s
        };
        fixtures::battery_view(
            speaking,
            &[(1, s, PackPart::Part), (2, other, PackPart::Part)],
            with_battery,
            |l| l,
        )
    }

    fn with<'a>(snap: &'a LiveSnapshot, b: &'a BatteryView) -> View<'a> {
        View {
            battery: Some(b),
            ..view(snap, 0)
        }
    }

    #[test]
    fn the_speaker_announces_one_battery_device_and_publishes_its_state() {
        let (snap, _) = inputs();
        let b = battery_view(true, true);
        let mut p = Publisher::new(settings(), &bridge());
        p.connected(0, id());
        let out = drain(&mut p, 0, &with(&snap, &b));
        let configs: Vec<_> = out
            .iter()
            .filter(|m| m.2 == Kind::BatteryDiscovery)
            .collect();
        assert_eq!(configs.len(), battery::ENTITIES.len());
        // After the pack's own configs and state.
        let first = out
            .iter()
            .position(|m| m.2 == Kind::BatteryDiscovery)
            .unwrap();
        assert!(out[..first].iter().any(|m| m.2 == Kind::State));
        let mut ids = std::collections::HashSet::new();
        for (topic, payload, _, retain) in &configs {
            assert!(retain);
            let parts: Vec<&str> = topic.split('/').collect();
            assert_eq!(parts.len(), 5, "{topic}");
            assert_eq!(parts[0], "homeassistant");
            assert_eq!(parts[2], "tinybms_battery_tinybms");
            assert!(is_id(parts[2]) && is_id(parts[3]), "{topic}");
            let c = json(payload);
            let uid = c["unique_id"].as_str().unwrap();
            assert!(is_id(uid) && ids.insert(uid.to_string()), "{uid}");
            assert_eq!(c["device"]["identifiers"][0], "tinybms_battery_tinybms");
            // The battery is the bridges' own device: the bridge's versions.
            let fw = tinybms_firmware::identity::FIRMWARE;
            let build = tinybms_firmware::identity::BUILD;
            assert_eq!(
                c["device"]["sw_version"],
                format!("bridge: tinybms-esp32 {fw} (build {build})")
            );
            assert_eq!(c["device"]["hw_version"], "bridge: simulated (test)");
            assert_eq!(c["state_topic"], "tinybms/battery/state");
            // Unavailable when the speaker falls silent, whichever it was.
            assert_eq!(c["expire_after"], 15, "3 publish periods of 5 s");
            if let Some(class) = c["device_class"].as_str() {
                let unit = c["unit_of_measurement"].as_str();
                assert!(
                    unit.is_some_and(|u| units_for(class).contains(&u)),
                    "{uid}: {class} in {unit:?}"
                );
            }
            assert!(payload.len() < PAYLOAD_MAX);
        }
        // The state: the battery line, every member an entity reads present.
        let state = out.iter().find(|m| m.2 == Kind::BatteryState).unwrap();
        assert_eq!(state.0, "tinybms/battery/state");
        assert!(!state.3, "the state is not retained");
        let s = json(&state.1);
        assert_eq!(s["packs_online"], 2);
        assert_eq!(s["capacity_ah"], 560.0);
        for e in battery::ENTITIES {
            let m = e.read.member();
            assert!(s.get(m).is_some_and(|v| !v.is_null()), "{m} in {s}");
        }
        // Every period, not before.
        assert!(drain(&mut p, SECOND, &with(&snap, &b))
            .iter()
            .all(|m| m.2 != Kind::BatteryState));
        assert!(p.next_due() <= 5 * SECOND);
        let later = drain(&mut p, 5 * SECOND, &with(&snap, &b));
        assert_eq!(
            later.iter().filter(|m| m.2 == Kind::BatteryState).count(),
            1
        );
        // Home Assistant restarted: announced again.
        p.on_ha_status(b"online");
        let again = drain(&mut p, 6 * SECOND, &with(&snap, &b));
        assert_eq!(
            again
                .iter()
                .filter(|m| m.2 == Kind::BatteryDiscovery)
                .count(),
            battery::ENTITIES.len()
        );
    }

    #[test]
    fn a_bridge_that_does_not_speak_publishes_no_battery() {
        let (snap, _) = inputs();
        let b = battery_view(false, true);
        let mut p = Publisher::new(settings(), &bridge());
        p.connected(0, id());
        for t in [0, 5, 10] {
            let out = drain(&mut p, t * SECOND, &with(&snap, &b));
            assert!(out.iter().all(|m| !matches!(
                m.2,
                Kind::BatteryDiscovery | Kind::BatteryState | Kind::BatteryRemoval
            )));
        }
        // It starts speaking: configs, then the state.
        let s = battery_view(true, true);
        let out = drain(&mut p, 11 * SECOND, &with(&snap, &s));
        assert_eq!(
            out.iter().filter(|m| m.2 == Kind::BatteryDiscovery).count(),
            battery::ENTITIES.len()
        );
        assert_eq!(out.iter().filter(|m| m.2 == Kind::BatteryState).count(), 1);
        // No pack takes part: the state says so with nulls (entities unavailable).
        let none = battery_view(true, false);
        let out = drain(&mut p, 20 * SECOND, &with(&snap, &none));
        let st = json(&out.iter().find(|m| m.2 == Kind::BatteryState).unwrap().1);
        assert_eq!(st["packs_online"], 0);
        assert!(st["soc_percent"].is_null() && st["ccl_a"].is_null());
    }

    #[test]
    fn discovery_off_removes_the_battery_device_too() {
        let (snap, _) = inputs();
        let b = battery_view(true, true);
        let mut s = settings();
        s.discovery = false;
        let mut p = Publisher::new(s, &bridge());
        p.connected(0, id());
        let out = drain(&mut p, 0, &with(&snap, &b));
        let removed: Vec<_> = out.iter().filter(|m| m.2 == Kind::BatteryRemoval).collect();
        assert_eq!(removed.len(), battery::ENTITIES.len());
        assert!(removed.iter().all(|m| m.1.is_empty() && m.3));
        assert!(out.iter().all(|m| m.2 != Kind::BatteryDiscovery));
        // The state all the same (for other MQTT clients).
        assert_eq!(out.iter().filter(|m| m.2 == Kind::BatteryState).count(), 1);
        // Removed once per connection.
        let out = drain(&mut p, 5 * SECOND, &with(&snap, &b));
        assert!(out.iter().all(|m| m.2 != Kind::BatteryRemoval));
        assert_eq!(out.iter().filter(|m| m.2 == Kind::BatteryState).count(), 1);
    }
}

/// The bridge the publisher speaks for.
fn bridge() -> tinybms_firmware::identity::Identity {
    tinybms_firmware::identity::Identity::desktop("test", Default::default())
}

/// No value older than the owner is told: every entity of the pack but the
/// event expires after the documented time, at every publish period the
/// configuration allows, and the keep-alive lets the broker notice a silent
/// connection (1.5 keep-alives) no later than that.
#[test]
fn every_entity_expires_and_a_silent_connection_is_noticed_as_soon() {
    let (snap, _) = inputs();
    for period_s in [1u16, 2, 5, 7, 10, 20, 29, 30, 60, 600, 3600] {
        let config = Config {
            publish_period_s: period_s,
            ..Config::default()
        };
        let s = Settings::from_config(&config);
        let expire = s.expire_after_s();
        assert_eq!(
            expire,
            (3 * u64::from(period_s)).max(15),
            "period {period_s} s"
        );
        let keep_alive = u64::from(s.keep_alive_s());
        // The will: 1.5 keep-alives after a ping half a keep-alive after the
        // last state, and a broker that looks every 5 s.
        assert!(
            2 * keep_alive + 5 <= expire,
            "period {period_s} s: keep-alive {keep_alive} s"
        );
        assert!((5..=60).contains(&keep_alive));
        let mut p = Publisher::new(s.clone(), &bridge());
        p.connected(0, id());
        let out = drain(&mut p, 0, &view(&snap, 0));
        let configs: Vec<_> = out.iter().filter(|m| m.2 == Kind::Discovery).collect();
        assert_eq!(configs.len(), discovery::count(16));
        for (topic, payload, _, _) in configs {
            let c = json(payload);
            if topic.contains("/event/") {
                assert!(c.get("expire_after").is_none(), "{topic}");
                assert_eq!(c["event_types"][0], "fault");
            } else if topic.contains("/update/") {
                // A version does not go stale.
                assert!(c.get("expire_after").is_none(), "{topic}");
                assert_eq!(c["device_class"], "firmware");
            } else {
                assert_eq!(c["expire_after"], expire, "{topic}");
            }
        }
    }
    // The default: 15 s, a keep-alive of 5 s.
    let s = settings();
    assert_eq!((s.expire_after_s(), s.keep_alive_s()), (15, 5));
}

#[test]
fn balancing_cells_are_named_one_based() {
    use tinybms_firmware::host_link::encode::balancing_cells;
    assert_eq!(balancing_cells(0, 16), "none");
    assert_eq!(balancing_cells(0b1000_0000_0000_0101, 16), "1, 3, 16");
    // Bits beyond the pack's cells are not cells.
    assert_eq!(balancing_cells(0b1000_0000_0000_0100, 8), "3");
    assert_eq!(balancing_cells(u16::MAX, 16).len(), 53);
}

/// Issue 26, "a friendly pack name": `pack_name` names the pack's device in
/// Home Assistant (its entities are shown as `<name> Pack voltage`, …); with
/// two packs `TinyBMS 76D4E3` and `TinyBMS 1A2B3C` were all an owner had.
/// Empty (the default) keeps `TinyBMS` and the serial's last six digits.
#[test]
fn the_pack_name_names_the_device() {
    let (snap, _) = inputs();
    let v = view(&snap, 0);
    let name_of = |config: &Config| {
        let mut p = Publisher::new(Settings::from_config(config), &bridge());
        p.connected(0, id());
        let out = drain(&mut p, 0, &v);
        let names: std::collections::BTreeSet<std::string::String> = out
            .iter()
            .filter(|m| m.2 == Kind::Discovery)
            .map(|m| json(&m.1)["device"]["name"].as_str().unwrap().to_string())
            .collect();
        assert_eq!(names.len(), 1, "{names:?}");
        names.into_iter().next().unwrap()
    };
    let serial = id().serial_hex();
    assert_eq!(
        name_of(&Config::default()),
        format!("TinyBMS {}", &serial[serial.len() - 6..])
    );
    let mut c = Config::default();
    c.set(
        tinybms_firmware::config::FieldId::PackName,
        tinybms_firmware::config::Value::Text("Garage \"east\" pack"),
    )
    .unwrap();
    assert_eq!(name_of(&c), "Garage \"east\" pack");
}

/// Issue 26, the bridge's diagnostics: the Wi-Fi signal (RSSI, dBm) as a
/// diagnostic entity Home Assistant knows (`signal_strength`); the state
/// carries it as `wifi_rssi_dbm`, null while unknown (the entity is then
/// unavailable, never a made-up 0 dBm).
#[test]
fn the_wifi_signal_is_a_diagnostic_and_null_when_unknown() {
    let e = ENTITIES
        .iter()
        .find(|e| e.object == "wifi_signal")
        .expect("a Wi-Fi signal entity");
    assert_eq!(e.component, Component::Sensor);
    assert_eq!(e.device_class, Some("signal_strength"));
    assert_eq!(e.unit, Some("dBm"));
    assert_eq!(e.state_class, Some("measurement"));
    assert_eq!(e.category, Some("diagnostic"));
    assert_eq!(e.read, Read::Nullable("wifi_rssi_dbm"));
    let (snap, _) = inputs();
    let state_of = |v: &View<'_>| {
        let mut p = Publisher::new(settings(), &bridge());
        p.connected(0, id());
        let out = drain(&mut p, 0, v);
        json(&out.iter().find(|m| m.2 == Kind::State).unwrap().1)
    };
    assert_eq!(state_of(&view(&snap, 0))["wifi_rssi_dbm"], -61);
    let unknown = View {
        wifi_rssi_dbm: None,
        ..view(&snap, 0)
    };
    let s = state_of(&unknown);
    assert!(s.get("wifi_rssi_dbm").is_some_and(|v| v.is_null()), "{s}");
}

/// The station hands the Wi-Fi task's reading to what MQTT publishes (as the
/// chip's Wi-Fi task does through `wires::WIFI_RSSI`), and a change is a new
/// generation (published at once).
#[test]
fn the_station_publishes_the_wifi_signal_it_is_given() {
    let mut st = host_tests::fixtures::station(bridge(), Config::default());
    assert_eq!(st.published(0).wifi_rssi_dbm, None);
    let g = st.generation();
    st.wifi_rssi(Some(-67));
    assert_eq!(st.published(0).wifi_rssi_dbm, Some(-67));
    assert_ne!(st.generation(), g);
    let g = st.generation();
    st.wifi_rssi(Some(-67));
    assert_eq!(st.generation(), g, "the same reading changes nothing");
    st.wifi_rssi(None);
    assert_eq!(st.published(0).wifi_rssi_dbm, None);
}

/// Issue 40: Home Assistant's "Charge stopped by" and "Discharge stopped by"
/// offer every cause the bridge can give, and `none`.
#[test]
fn every_stop_cause_is_an_option_of_home_assistant() {
    use tinybms_firmware::inverter::dialect::{shared::stop_key, StopWhy};
    let all = [
        StopWhy::Fault,
        StopWhy::CellHigh,
        StopWhy::CellLow,
        StopWhy::Temperature,
        StopWhy::Current,
        StopWhy::LinkLost,
        StopWhy::InverterAsked,
        StopWhy::Limit,
    ];
    let mut keys: Vec<&str> = all.iter().map(|w| stop_key(Some(*w))).collect();
    keys.insert(0, stop_key(None));
    assert_eq!(keys, discovery::STOP_CAUSES);
}

/// The state with 16 cells, every value and every text at its widest, fits
/// a payload with a margin (a state that does not fit is not published at
/// all: Home Assistant would see nothing). It was 1,831 bytes before the
/// limits' reasons and the doctor's verdicts (2,123 with them), over the
/// 1,536 of the payload then: the payload is 2,560 bytes since; 2,380 with
/// the pack's aging (issue 55), and 2,816 since.
#[test]
fn the_widest_state_fits_the_payload() {
    use tinybms_firmware::host_link::encode::{self, StateExtras, TelemetryHead};
    use tinybms_firmware::inverter::why::Why;
    let snapshot = host_tests::fixtures::widest_snapshot();
    let why = Why::OverCurrent { cutoff_a: u16::MAX }.text();
    let long = "x".repeat(120);
    let doctor = "no_ack, bus_off, no_inverter, heartbeat_late, other_dialect, over_limit, voltage_disagrees, unknown_name, export_after_step";
    let extras = StateExtras {
        status: "other",
        status_name: "Other",
        age_ms: u64::MAX,
        link_quality_permille: Some(u32::MAX),
        limits: Some((u16::MAX, u16::MAX, u16::MAX)),
        remaining_cah: Some(u32::MAX),
        energy_mwh: (u64::MAX, u64::MAX),
        uptime_s: u64::MAX,
        bridge_firmware: &long[..64],
        can_state: Some("bus_off"),
        inverter_heard: Some(false),
        stops: Some(("inverter_asked", "inverter_asked")),
        soc_told: Some(100),
        ignored_stop: Some("discharge: 6553.5 A for 65535 s"),
        charge_stage: Some(&long),
        why: [Some(why.as_str()); 3],
        can_doctor: Some(doctor),
        bms_wire: Some(&long[..110]),
        wifi_rssi_dbm: Some(-128),
        update_rolled_back: Some(&long),
        update_latest: Some(&long[..32]),
        aging: tinybms_firmware::history::Aging {
            capacity: Some((u32::MAX, u16::MAX)),
            cycles: Some(u16::MAX),
            top_spread_mv: Some(u16::MAX),
            recording: false,
        },
    };
    let head = TelemetryHead {
        req: None,
        seq: u32::MAX,
        age_ms: Some(u64::MAX),
        stale_after_ms: None,
        online: true,
        ready: true,
        inverter: None,
        restart_pending: 0,
    };
    let mut payload = vec![0u8; PAYLOAD_MAX];
    let n = encode::state(
        &mut payload,
        head,
        Some(&snapshot),
        Some("cell_count_mismatch"),
        Some(&extras),
    )
    .expect("the widest state fits");
    eprintln!("widest state: {n} bytes of {PAYLOAD_MAX}");
    assert!(n < PAYLOAD_MAX * 9 / 10, "{n}");
    serde_json::from_slice::<Value>(&payload[..n]).expect("valid JSON");
}
