//! The bridge's configuration over the host link: `get config`, `set_config`
//! with one outcome per field and the save to flash, `reset_config`,
//! read-only, secrets never echoed — on the real bridge and host link against
//! the simulated BMS, in virtual time, with the store on a flash in RAM.

use embassy_futures::block_on;
use host_tests::virtual_host_link::{config, config_with_wifi, Rig};
use serde_json::{json, Value};
use tinybms_firmware::config::{Config, FIELDS};
use tinybms_firmware::inverter::Protocol;
use tinybms_firmware::{MS, SECOND};

fn ready() -> Rig {
    let mut r = Rig::ready(config_with_wifi(false, 0));
    r.drain();
    r
}

fn of_type<'a>(lines: &'a [Value], ty: &str) -> Vec<&'a Value> {
    lines.iter().filter(|l| l["type"] == ty).collect()
}

/// Sends `set_config` with `fields`, runs until its `config_done`, returns
/// every line it produced.
fn set(r: &mut Rig, req: u32, fields: Value) -> Vec<Value> {
    r.line(&json!({"cmd":"set_config","req":req,"fields":fields}).to_string());
    let mut out = r.drain();
    for _ in 0..40 {
        if out
            .iter()
            .any(|l| l["type"] == "config_done" || l["type"] == "error")
        {
            break;
        }
        out.extend(r.run_reading(50 * MS));
    }
    // The log lines of the change (as on the chip) are checked elsewhere.
    out.retain(|l| l["type"] != "telemetry" && l["type"] != "log");
    out
}

fn get_config(r: &mut Rig) -> Vec<Value> {
    r.line(r#"{"cmd":"get","what":"config","req":9}"#);
    r.drain()
}

/// The record in the rig's flash, as the next start-up would find it.
fn in_flash(r: &Rig) -> Config {
    let (s, _) = restart(r);
    s
}

fn restart(r: &Rig) -> (Config, tinybms_firmware::config::store::Source) {
    // A copy of the flash, as the chip finds it after a restart.
    let mut copy = tinybms_desk::flash::store(clone_flash(r));
    let l = block_on(copy.load());
    (l.config, l.source)
}

fn clone_flash(r: &Rig) -> tinybms_desk::flash::RamFlash {
    r.flash.copy()
}

#[test]
fn get_config_lists_every_field_with_unit_range_default_and_when_it_applies() {
    let mut r = ready();
    let out = get_config(&mut r);
    let fields = of_type(&out, "config");
    assert_eq!(fields.len(), FIELDS.len());
    for (line, f) in fields.iter().zip(FIELDS) {
        assert_eq!(line["req"], 9);
        assert_eq!(line["name"], f.name);
        assert_eq!(line["unit"], f.unit);
        assert_eq!(line["applies"], f.applies.name());
        assert_eq!(line["group"], f.group.name());
        assert_eq!(line["help"], f.help);
        assert_eq!(line["restart_pending"], false);
        assert!(
            line["range"].as_str().is_some_and(|t| !t.is_empty()),
            "{line}"
        );
        // The rig's host link streams nothing: stream_period is off, the rest
        // are the defaults.
        if f.name == "stream_period" {
            assert_eq!(line["value"], "off");
            assert_eq!(line["default"], "1000");
        } else {
            assert_eq!(line["value"], line["default"], "{line}");
        }
    }
    let cap = fields
        .iter()
        .find(|l| l["name"] == "charge_current_cap")
        .unwrap();
    assert_eq!(cap["value"], "none");
    assert_eq!(cap["range"], "0.1 A to 750.0 A, or none");
    let end = of_type(&out, "config_end");
    assert_eq!(end.len(), 1);
    assert_eq!(end[0]["count"], FIELDS.len());
    assert_eq!(end[0]["version"], tinybms_firmware::config::VERSION);
    assert_eq!(end[0]["source"], "defaults");
    assert_eq!(out.last().unwrap()["type"], "config_end");
}

#[test]
fn set_config_gives_one_outcome_per_field_then_saves() {
    let mut r = ready();
    let out = set(
        &mut r,
        3,
        json!({"charge_current_cap":"50 A","inverter_protocol":"sma","stale_after":"5"}),
    );
    assert_eq!(
        out[0],
        json!({"type":"accepted","req":3,"cmd":"set_config"})
    );
    let o = of_type(&out, "config_outcome");
    assert_eq!(o.len(), 3, "{out:#?}");
    assert_eq!(o[0]["name"], "charge_current_cap");
    assert_eq!(o[0]["outcome"], "applied");
    assert_eq!(o[0]["value"], "50.0 A");
    assert_eq!(o[1]["outcome"], "at_restart");
    assert_eq!(o[2]["outcome"], "unchanged");
    let done = of_type(&out, "config_done");
    assert_eq!(done.len(), 1, "{out:#?}");
    assert_eq!(done[0]["changed"], 2);
    assert_eq!(done[0]["saved"], true);
    assert_eq!(done[0]["restart_needed"], 1);
    assert_eq!(out.last().unwrap()["type"], "config_done");
    // It runs now where it may, and it is in flash.
    assert_eq!(r.config().running().charge_current_cap_da, 500);
    assert_eq!(r.config().running().protocol, Protocol::Victron);
    let f = in_flash(&r);
    assert_eq!(f.charge_current_cap_da, 500);
    assert_eq!(f.protocol, Protocol::SmaSunnyIsland);
    // get config shows the stored value and the pending restart.
    let out = get_config(&mut r);
    let p = of_type(&out, "config")
        .into_iter()
        .find(|l| l["name"] == "inverter_protocol")
        .unwrap()
        .clone();
    assert_eq!(p["value"], "sma");
    assert_eq!(p["restart_pending"], true);
    assert_eq!(of_type(&out, "config_end")[0]["restart_pending"], 1);
}

#[test]
fn a_refused_field_changes_nothing_and_says_why() {
    let mut r = ready();
    let before = r.config().stored().clone();
    let out = set(
        &mut r,
        4,
        json!({"charge_current_cap":"9999 A","stale_after":"7 s","no_such_thing":"1","can_output":"perhaps"}),
    );
    let o = of_type(&out, "config_outcome");
    assert_eq!(o.len(), 4, "{out:#?}");
    assert_eq!(o[0]["outcome"], "refused");
    assert_eq!(o[0]["error"], "out_of_range");
    assert_eq!(o[0]["range"], "0.1 A to 750.0 A, or none");
    assert_eq!(o[1]["outcome"], "not_applied");
    assert_eq!(o[2]["error"], "unknown_setting");
    assert_eq!(o[2]["name"], "no_such_thing");
    assert_eq!(o[3]["error"], "invalid_value");
    let done = of_type(&out, "config_done");
    assert_eq!(done[0]["changed"], 0);
    assert_eq!(done[0]["saved"], Value::Null);
    assert_eq!(r.config().stored(), &before);
    assert_eq!(r.saves(), 0);
}

#[test]
fn a_cap_above_what_the_bms_allows_is_refused() {
    let mut r = ready();
    // The simulated 16S pack's charge over-current cutoff (318).
    let cutoff = r.h.sim.register(318);
    let out = set(
        &mut r,
        5,
        json!({"charge_current_cap": format!("{} A", cutoff + 1)}),
    );
    let o = of_type(&out, "config_outcome");
    assert_eq!(o[0]["outcome"], "refused", "{out:#?}");
    assert_eq!(o[0]["error"], "out_of_range");
    // Said in words and with what the BMS allows, not as a register number.
    let detail = o[0]["detail"].as_str().unwrap();
    assert!(detail.contains("charge over-current cutoff"), "{}", o[0]);
    assert!(!detail.contains("318"), "{}", o[0]);
    assert_eq!(
        o[0]["range"],
        format!("0.1 A to {:.1} A", f64::from(cutoff)),
        "{}",
        o[0]
    );
    let out = set(
        &mut r,
        6,
        json!({"charge_current_cap": format!("{cutoff} A")}),
    );
    assert_eq!(of_type(&out, "config_outcome")[0]["outcome"], "applied");
}

#[test]
fn read_only_refuses_configuration_writes_too() {
    let mut r = ready();
    let out = set(&mut r, 1, json!({"read_only":"on"}));
    assert_eq!(of_type(&out, "config_outcome")[0]["outcome"], "applied");
    for line in [
        json!({"cmd":"set_config","req":2,"fields":{"read_only":"off"}}),
        json!({"cmd":"set_config","req":3,"fields":{"charge_current_cap":"10"}}),
        json!({"cmd":"reset_config","req":4}),
    ] {
        r.line(&line.to_string());
        let out = r.drain();
        assert_eq!(out.len(), 1, "{out:#?}");
        assert_eq!(out[0]["type"], "error");
        assert_eq!(out[0]["error"], "read_only");
    }
    assert!(r.config().stored().read_only);
    // get config still works.
    assert_eq!(of_type(&get_config(&mut r), "config").len(), FIELDS.len());
}

#[test]
fn the_boot_button_lifts_read_only() {
    let mut r = ready();
    set(&mut r, 1, json!({"read_only":"on"}));
    assert!(in_flash(&r).read_only);
    r.hold_button(5_100_000);
    r.run(SECOND);
    let out = set(&mut r, 2, json!({"charge_current_cap":"10"}));
    assert_eq!(of_type(&out, "config_outcome")[0]["outcome"], "applied");
    assert!(!in_flash(&r).read_only, "unlocked in flash too");
}

#[test]
fn secrets_are_never_echoed() {
    let mut r = ready();
    let key = "0123456789abcdef".repeat(4);
    let pass = r#"s3cr"et\pa55"#;
    let mut all = set(
        &mut r,
        7,
        json!({"wifi_ssid":"home","wifi_key":key,"mqtt_user":"bms","mqtt_password":pass}),
    );
    all.extend(get_config(&mut r));
    let o = of_type(&all, "config_outcome");
    assert_eq!(o[1]["value"], "set");
    assert_eq!(o[3]["value"], "set");
    let text: String = all.iter().map(|l| l.to_string()).collect();
    assert!(!text.contains(&key), "the key was echoed");
    assert!(!text.contains("s3cr"), "the password was echoed");
    // Escapes in the JSON string are resolved before storing.
    assert_eq!(r.config().stored().mqtt_password.as_str(), pass);
    assert_eq!(in_flash(&r).mqtt_password.as_str(), pass);
    let key_line = of_type(&all, "config")
        .into_iter()
        .find(|l| l["name"] == "wifi_key")
        .unwrap()
        .clone();
    assert_eq!(key_line["value"], "set");
    assert_eq!(key_line["default"], "unset");
    assert_eq!(key_line["secret"], true);
}

/// Issue 51: an image without Wi-Fi refuses the network fields (they used
/// to be stored where nothing reads them), and changes nothing else of the
/// same line.
#[test]
fn an_image_without_wifi_refuses_the_network_fields() {
    let mut r = Rig::ready(config(false, 0));
    r.drain();
    let before = r.config().stored().clone();
    let all = set(&mut r, 5, json!({"wifi_ssid":"home","stream_period":"2 s"}));
    let o = of_type(&all, "config_outcome");
    let ssid = o
        .iter()
        .find(|l| l["name"] == "wifi_ssid")
        .unwrap_or_else(|| panic!("{all:#?}"));
    assert_eq!(ssid["outcome"], "refused", "{ssid}");
    assert!(ssid.to_string().contains("no Wi-Fi"), "{ssid}");
    assert_eq!(r.config().stored(), &before, "nothing of the line applied");
    // With Wi-Fi, the same line is taken.
    let mut r = ready();
    let all = set(&mut r, 6, json!({"wifi_ssid":"home"}));
    assert_eq!(
        of_type(&all, "config_outcome")[0]["outcome"],
        "at_restart",
        "{all:?}"
    );
}

#[test]
fn the_stream_period_applies_at_once() {
    let mut r = ready();
    set(&mut r, 1, json!({"stream_period":"200 ms"}));
    let lines = r.run_reading(2 * SECOND);
    let n = of_type(&lines, "telemetry").len();
    assert!((9..=11).contains(&n), "{n} telemetry lines in 2 s");
    // And a new session starts with it too.
    r.line(r#"{"cmd":"hello"}"#);
    let h = r.drain();
    assert_eq!(h[0]["stream_period_ms"], 200);
}

#[test]
fn reset_config_goes_back_to_the_defaults() {
    let mut r = ready();
    set(
        &mut r,
        1,
        json!({"charge_current_cap":"40","stale_after":"9 s"}),
    );
    r.line(r#"{"cmd":"reset_config","req":2}"#);
    let mut out = r.drain();
    for _ in 0..20 {
        if out.iter().any(|l| l["type"] == "config_done") {
            break;
        }
        out.extend(r.run_reading(50 * MS));
    }
    out.retain(|l| l["type"] != "telemetry" && l["type"] != "log");
    assert_eq!(out[0]["cmd"], "reset_config");
    let done = of_type(&out, "config_done");
    // The two set above, and the rig's stream period (off) back to 1000 ms.
    assert_eq!(done[0]["changed"], 3);
    assert_eq!(done[0]["saved"], true);
    assert_eq!(in_flash(&r), Config::default());
}

#[test]
fn malformed_set_config_lines_are_errors() {
    let mut r = ready();
    for (line, code) in [
        (r#"{"cmd":"set_config"}"#, "missing_field"),
        (r#"{"cmd":"set_config","fields":{}}"#, "invalid_value"),
        (
            r#"{"cmd":"set_config","fields":{"stale_after":5}}"#,
            "invalid_value",
        ),
        (
            r#"{"cmd":"set_config","fields":{"stale_after":"5"},"values":{}}"#,
            "unknown_field",
        ),
        (r#"{"cmd":"reset_config","what":"all"}"#, "unknown_field"),
        (r#"{"cmd":"get","what":"configuration"}"#, "invalid_value"),
    ] {
        r.line(line);
        let out = r.drain();
        assert_eq!(out.len(), 1, "{line}: {out:#?}");
        assert_eq!(out[0]["type"], "error", "{line}");
        assert_eq!(out[0]["error"], code, "{line}: {}", out[0]);
    }
    assert_eq!(
        r.config().stored(),
        &host_tests::virtual_host_link::record_for(&config(false, 0))
    );
}

#[test]
fn a_new_stale_limit_reaches_the_telemetry_lines_the_desktop_reads() {
    let mut r = ready();
    let snapshot = |r: &mut Rig| {
        r.line(r#"{"cmd":"get","what":"snapshot","req":5}"#);
        r.drain()
            .into_iter()
            .find(|l| l["type"] == "telemetry")
            .unwrap()
    };
    assert_eq!(snapshot(&mut r)["stale_after_ms"], 5000);
    let out = set(&mut r, 1, json!({"stale_after": "12"}));
    assert!(of_type(&out, "config_done").len() == 1, "{out:?}");
    let t = snapshot(&mut r);
    assert_eq!(t["stale_after_ms"], 12_000, "{t}");
    // The desktop monitor goes stale by that limit, not by a constant: data
    // 8 s old is still current.
    let mut old = t.clone();
    old["age_ms"] = json!(8000);
    // Read as the desktop reads it: through the host link's types.
    let old: tinybms_firmware::host_link::schema::Telemetry<
        tinybms_firmware::host_link::schema::Read,
    > = serde_json::from_value(old).unwrap();
    assert!(matches!(
        tinybms::monitor::freshness(Some(&old), std::time::Duration::ZERO),
        tinybms::monitor::Freshness::Fresh(_)
    ));
}

/// `charge_current_cap=0` from a host is refused, never applied as `none` (no
/// cap at all, the BMS's own cutoff): the record keeps its cap.
#[test]
fn a_cap_of_zero_is_refused_not_read_as_no_cap() {
    let mut r = ready();
    let out = set(&mut r, 1, json!({"charge_current_cap":"40"}));
    assert_eq!(of_type(&out, "config_outcome")[0]["outcome"], "applied");
    for (req, field) in [(2, "charge_current_cap"), (3, "discharge_current_cap")] {
        let out = set(&mut r, req, json!({ field: "0" }));
        let o = of_type(&out, "config_outcome");
        assert_eq!(o.len(), 1, "{out:?}");
        assert_eq!(o[0]["outcome"], "refused", "{out:?}");
        assert!(
            o[0]["detail"].as_str().unwrap_or("").contains("no cap"),
            "{out:?}"
        );
    }
    assert_eq!(r.config().running().charge_current_cap_da, 400);
    assert_eq!(in_flash(&r).charge_current_cap_da, 400);
}
