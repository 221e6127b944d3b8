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
    let setting = |name: &str, raw: i64, value: f64| {
        json!({"type": "setting", "name": name, "raw": raw, "value": value, "unit": "V",
               "min": 1.2, "max": 4.5, "bms_min": null, "bms_max": null})
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
    let t = json!({"type": "telemetry", "online": true, "age_ms": 300, "stale_after_ms": 5000});
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
    let off = json!({"type": "telemetry", "online": false, "age_ms": 300, "stale_after_ms": 5000});
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
