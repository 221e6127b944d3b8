//! The calls the console makes, natively: the same functions the `.wasm`
//! exports, with the tool's words.

use serde_json::{json, Value};
use tinybms_web::call;

fn ask(name: &str, arg: Value) -> Value {
    serde_json::from_str(&call(name, &arg.to_string())).unwrap()
}

#[test]
fn a_refused_value_reads_as_the_tool_says_it() {
    let r = ask(
        "check_config",
        json!({"changes": ["charge_current_cap=0"], "current": []}),
    );
    assert_eq!(r["ok"], false);
    let tool = tinybms_rules::config::check_assignment("charge_current_cap", "0").unwrap_err();
    assert_eq!(r["messages"], json!([tool]));
    assert!(tool.starts_with("charge_current_cap = 0: "), "{tool}");
}

#[test]
fn a_good_change_gives_the_text_to_send_and_a_typo_a_suggestion() {
    let r = ask(
        "check_config",
        json!({"changes": ["charge_current_cap=50000mA", "inverter_protocol=sma"], "current": []}),
    );
    assert_eq!(r["ok"], true, "{r}");
    assert_eq!(r["wire"]["charge_current_cap"], "50.0 A");
    assert_eq!(r["wire"]["inverter_protocol"], "sma");
    let r = ask("check_config", json!({"changes": ["charge_curent_cap=5A"]}));
    assert!(
        r["messages"][0]
            .as_str()
            .unwrap()
            .contains("did you mean `charge_current_cap`?"),
        "{r}"
    );
    let r = ask("check_config", json!({"changes": []}));
    assert_eq!(r["ok"], false);
}

#[test]
fn settings_are_checked_against_each_other_as_the_tool_checks_them() {
    // As the bridge writes them (`host_link::schema::SettingLine`).
    let setting = |name: &str, raw: i64, value: f64| {
        let address = tinybms_rules::settings::find_setting(name)
            .unwrap()
            .address();
        json!({"type": "setting", "name": name, "address": address, "raw": raw, "value": value,
               "unit": "V", "min": 1.2, "max": 4.5, "bms_min": null, "bms_max": null})
    };
    let current = json!([
        setting("under_voltage_cutoff", 2500, 2.5),
        setting("over_voltage_cutoff", 3650, 3.65),
        setting("fully_charged_voltage", 3550, 3.55),
        setting("fully_discharged_voltage", 2800, 2.8),
    ]);
    let r = ask(
        "check_settings",
        json!({"changes": ["over_voltage_cutoff=2.4V"], "current": current}),
    );
    assert_eq!(r["ok"], false);
    let msg = r["messages"][0].as_str().unwrap();
    assert!(
        msg.contains("under_voltage_cutoff must stay below over_voltage_cutoff"),
        "{msg}"
    );
    let r = ask(
        "check_settings",
        json!({"changes": ["over_voltage_cutoff=3700mV"], "current": current}),
    );
    assert_eq!(r["ok"], true, "{r}");
    assert_eq!(r["values"]["over_voltage_cutoff"], 3700);
}

#[test]
fn the_freshness_rule_is_the_firmwares() {
    // The members the rule reads: a telemetry line's head (the snapshot's
    // members left out).
    let t = json!({"type": "telemetry", "seq": 0, "age_ms": 300, "stale_after_ms": 5000,
                   "online": true, "ready": true});
    let r = ask(
        "freshness",
        json!({"telemetry": t, "received_ago_ms": 1000}),
    );
    assert_eq!(r["state"], "fresh");
    let r = ask(
        "freshness",
        json!({"telemetry": t, "received_ago_ms": 4800}),
    );
    assert_eq!(r["state"], "no_data", "5.1 s old against 5 s: {r}");
    assert!(r["text"]
        .as_str()
        .unwrap()
        .starts_with("NO DATA: nothing new from the port"));
    let off = json!({"type": "telemetry", "seq": 0, "age_ms": 300, "stale_after_ms": 5000,
                     "online": false, "ready": false});
    assert_eq!(
        ask("freshness", json!({"telemetry": off}))["state"],
        "offline"
    );
    assert_eq!(
        ask("freshness", json!({"telemetry": null}))["state"],
        "no_data"
    );
}

#[test]
fn the_link_quality_of_a_link_line_and_of_anything_else() {
    // A `link` line as the bridge writes it (`host_link::schema::Link`).
    let link = json!({"type": "link", "requests": 200, "replies": 198, "timeouts": 2,
        "wakeup_resends": 1, "retries": 3, "crc_errors": 1, "framing_errors": 0,
        "invalid_replies": 0, "nacks_command": 0, "nacks_crc": 0, "nacks_other": 0,
        "skipped_bytes": 0, "unsolicited": 0, "failures": 2, "latency_min_us": 9000,
        "latency_mean_us": 12000, "latency_max_us": 30000, "online": true,
        "piece_registers": 16, "lines_in": 12, "errors": 0, "dropped_lines": 0});
    assert_eq!(
        ask("link_quality", link)["text"],
        "99.0 % ok (200 requests, 198 replies, 2 failed, 3 retries, 1 CRC errors)"
    );
    assert_eq!(
        ask("link_quality", json!({"type": "link", "requests": 5}))["text"],
        Value::Null,
        "not a line the bridge writes"
    );
    assert_eq!(
        ask("link_quality", json!({"type": "telemetry"}))["text"],
        Value::Null
    );
}

#[test]
fn anything_else_is_an_error_never_a_panic() {
    assert!(ask("no_such", json!(null))["error"].is_string());
    let r: Value = serde_json::from_str(&call("check_config", "{not json")).unwrap();
    assert!(r["error"].as_str().unwrap().contains("not JSON"));
    for name in [
        "check_config",
        "check_settings",
        "freshness",
        "link_quality",
    ] {
        for arg in [
            json!(7),
            json!("x"),
            json!([1, 2]),
            json!({"changes": 3, "current": "y"}),
        ] {
            let _ = ask(name, arg);
        }
    }
    let about = ask("about", json!(null));
    assert_eq!(about["product"], "TinyBMS bridge");
    assert_eq!(ask("boards", json!(null)).as_array().unwrap().len(), 7);
}

#[test]
fn direct_mode_runs_the_station_against_a_bms() {
    use host_tests::sim::{PackModel, SimBms, SimConfig};
    let mut bms = SimBms::new(PackModel::LiFePO4_16S, SimConfig::default(), 3);
    assert_eq!(ask("direct_start", json!({"now_ms": 0.0})), json!({}));
    let mut now_ms = 0.0f64;
    let mut rx: Vec<u8> = Vec::new();
    let mut lines: Vec<Value> = Vec::new();
    let mut host = String::new();
    // 20 s of the page's loop: bytes from the BMS in, bytes to it out.
    while now_ms < 20_000.0 {
        if now_ms >= 15_000.0 && !lines.iter().any(|l| l["req"] == 5) && host.is_empty() {
            // Synced by now: the console asks as it would a bridge.
            host = "{\"cmd\":\"get\",\"what\":\"version\",\"req\":5}\n".into();
        }
        let r = ask(
            "direct_step",
            json!({"now_ms": now_ms, "rx": rx, "host": std::mem::take(&mut host)}),
        );
        rx.clear();
        let now_us = (now_ms * 1000.0) as u64;
        let tx: Vec<u8> = r["tx"]
            .as_array()
            .unwrap()
            .iter()
            .map(|b| b.as_u64().unwrap() as u8)
            .collect();
        if !tx.is_empty() {
            bms.host_send(now_us, &tx);
        }
        for l in r["lines"].as_array().unwrap() {
            lines.push(serde_json::from_str(l.as_str().unwrap()).unwrap());
        }
        let wake = r["wake_ms"].as_f64().unwrap();
        now_ms = (now_ms + 5.0).min(wake.max(now_ms + 1.0));
        bms.take_output((now_ms * 1000.0) as u64, &mut rx);
    }
    assert_eq!(
        lines[0]["type"], "hello",
        "the page's station greets the page"
    );
    let t = lines
        .iter()
        .rev()
        .find(|l| l["type"] == "telemetry")
        .expect("telemetry");
    assert_eq!(t["online"], true, "{t}");
    assert_eq!(t["cell_voltages_v"].as_array().unwrap().len(), 16);
    let v = lines
        .iter()
        .find(|l| l["type"] == "version")
        .expect("the version answer");
    assert_eq!(v["req"], 5);
    assert!(v["serial_number"].is_string(), "{v}");
}

#[test]
fn a_step_before_a_start_is_refused() {
    // Each test runs on a thread of its own: no station here yet.
    let r = ask("direct_step", json!({"now_ms": 1}));
    assert_eq!(r["error"], "direct_start first");
}
