//! The browser console's checks, compiled to WebAssembly: the firmware's
//! configuration field table, value parser and rules between fields, its
//! register conversions and relations between BMS settings, its freshness
//! rule and board table, with the desktop tool's words
//! ([`tinybms_rules`]) — so the console refuses what `tinybms` refuses, with
//! the same sentence, and never re-implements a rule in JavaScript.
//!
//! One entry point, [`call`]: a function name and a JSON argument in, JSON
//! out. In the `.wasm` it is exported as `tb_call` over the module's memory
//! (`tb_alloc`/`tb_free` for the strings), which `src/wasm.ts` wraps in a
//! dozen lines; no binding generator to install or keep in step.
//!
//! | name | argument | answer |
//! | --- | --- | --- |
//! | `about` | — | `{protocol, product, firmware}`: the host-link protocol and the firmware this was built with |
//! | `boards` | — | the board table: name, feature, chip, pins and their labels, host wire |
//! | `fields` | — | every configuration field: name, unit, group, applies, help, range, default |
//! | `check_config` | `{changes: ["NAME=VALUE"…], current: [config lines]}` | `{ok, messages, wire: {name: text}}` |
//! | `check_settings` | `{changes: ["NAME=VALUE"…], current: [setting lines], raw}` | `{ok, messages, values: {name: raw}}` |
//! | `freshness` | `{telemetry: line or null, received_ago_ms}` | `{state, age_s, text}` |
//! | `link_quality` | a `link` line | `{text}` |

use serde_json::{json, Value};
use tinybms_firmware::boards::BOARDS;

/// Answers `name` with `arg` (JSON text); an unknown name or an argument
/// that is not JSON gets `{"error": "…"}`. Never panics.
pub fn call(name: &str, arg: &str) -> String {
    let arg: Value = if arg.trim().is_empty() {
        Value::Null
    } else {
        match serde_json::from_str(arg) {
            Ok(v) => v,
            Err(e) => {
                return json!({ "error": format!("the argument is not JSON: {e}") }).to_string()
            }
        }
    };
    let out = match name {
        "about" => json!({
            "protocol": tinybms_firmware::host_link::PROTOCOL_VERSION,
            "product": tinybms_firmware::improv::PRODUCT,
            "firmware": tinybms_firmware::identity::FIRMWARE,
        }),
        "boards" => boards(),
        "fields" => tinybms_rules::config::fields_json(),
        "check_config" => check_config(&arg),
        "check_settings" => check_settings(&arg),
        "freshness" => freshness(&arg),
        "link_quality" => link_quality(&arg),
        other => json!({ "error": format!("no function `{other}`") }),
    };
    out.to_string()
}

fn boards() -> Value {
    Value::Array(
        BOARDS
            .iter()
            .map(|b| {
                json!({
                    "name": b.name,
                    "feature": b.feature,
                    "board": b.feature.trim_start_matches("board-"),
                    "chip": b.chip.name(),
                    "chip_family": tinybms_firmware::improv::chip_family(b.chip.name()),
                    "bms_tx": b.bms_tx,
                    "bms_rx": b.bms_rx,
                    "can_tx": b.can_tx,
                    "can_rx": b.can_rx,
                    "labels": b.labels,
                    "host": b.host.name(),
                })
            })
            .collect(),
    )
}

fn strings(v: &Value) -> Vec<String> {
    v.as_array()
        .map(|a| {
            a.iter()
                .filter_map(|x| x.as_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default()
}

fn lines(v: &Value) -> Vec<Value> {
    v.as_array().cloned().unwrap_or_default()
}

/// `NAME=VALUE`s for the bridge's configuration, as `tinybms config PORT
/// NAME=VALUE… --dry-run` checks them.
fn check_config(arg: &Value) -> Value {
    use tinybms_rules::config::{check_assignment, check_locally, record_of, split_assignment};
    let mut messages = Vec::new();
    let mut changes = Vec::new();
    for a in strings(&arg["changes"]) {
        match split_assignment(&a).and_then(|(n, t)| check_assignment(&n, &t)) {
            Ok(c) => changes.push(c),
            Err(m) => messages.push(m),
        }
    }
    if messages.is_empty() && changes.is_empty() {
        messages.push("nothing to change: give NAME=VALUE".to_string());
    }
    if messages.is_empty() {
        if let Err(m) = check_locally(&record_of(&lines(&arg["current"])), &changes) {
            messages.push(m);
        }
    }
    let wire: serde_json::Map<String, Value> = changes
        .iter()
        .map(|(id, p)| {
            (
                id.name().to_string(),
                Value::String(tinybms_rules::config::wire_text(*id, p)),
            )
        })
        .collect();
    json!({ "ok": messages.is_empty(), "messages": messages, "wire": wire })
}

/// `NAME=VALUE`s for the BMS's settings, as `tinybms set PORT NAME=VALUE…
/// --dry-run` checks them against the settings the bridge reported.
fn check_settings(arg: &Value) -> Value {
    let raw = arg["raw"] == true;
    let current = lines(&arg["current"]);
    let mut messages = Vec::new();
    let mut items = Vec::new();
    let mut bare = Vec::new();
    for a in strings(&arg["changes"]) {
        match tinybms_rules::settings::parse_set_arg(&a, raw) {
            Ok((id, v, plain)) => {
                items.push((id, v));
                if plain {
                    bare.push(id);
                }
            }
            Err(m) => messages.push(m),
        }
    }
    if messages.is_empty() && items.is_empty() {
        messages.push("nothing to change: give NAME=VALUE".to_string());
    }
    if messages.is_empty() {
        if let Err(m) = tinybms_rules::settings::check_all(&current, &items, Some(&bare)) {
            messages.push(m);
        }
    }
    let values: serde_json::Map<String, Value> = items
        .iter()
        .map(|(id, v)| (tinybms_rules::settings::snake_name(*id), Value::from(*v)))
        .collect();
    json!({ "ok": messages.is_empty(), "messages": messages, "values": values })
}

/// The firmware's one freshness rule on the newest telemetry line (`null`:
/// none yet), received `received_ago_ms` ago — its age then plus the time
/// since, against the limit the bridge gave — in the monitor's words.
fn freshness(arg: &Value) -> Value {
    use tinybms_rules::view::{freshness, freshness_text, Freshness};
    let line = arg.get("telemetry").filter(|t| t.is_object());
    let since = arg["received_ago_ms"].as_f64().unwrap_or(0.0).max(0.0);
    let f = freshness(line, std::time::Duration::from_secs_f64(since / 1000.0));
    let (state, age) = match f {
        Freshness::Fresh(a) => ("fresh", Some(a)),
        Freshness::Offline(a) => ("offline", a),
        Freshness::NoData(a) => ("no_data", a),
    };
    json!({ "state": state, "age_s": age, "text": freshness_text(f) })
}

/// The link quality of a `link` line, in the monitor's words.
fn link_quality(arg: &Value) -> Value {
    json!({ "text": tinybms_rules::view::link_quality(arg) })
}

/// The exports of the `.wasm` (see the module documentation).
#[cfg(target_arch = "wasm32")]
mod exports {
    /// `len` bytes for the page to write an argument into.
    #[no_mangle]
    pub extern "C" fn tb_alloc(len: usize) -> *mut u8 {
        Box::into_raw(vec![0u8; len.max(1)].into_boxed_slice()) as *mut u8
    }

    /// Gives back what [`tb_alloc`] or [`tb_call`] handed out.
    ///
    /// # Safety
    /// `ptr` and `len` are exactly what one of them handed out, once.
    #[no_mangle]
    pub unsafe extern "C" fn tb_free(ptr: *mut u8, len: usize) {
        drop(Box::from_raw(core::ptr::slice_from_raw_parts_mut(
            ptr,
            len.max(1),
        )));
    }

    /// [`super::call`] on UTF-8 strings in the module's memory; the answer's
    /// address in the high 32 bits and its length in the low ones (free it
    /// with [`tb_free`]).
    ///
    /// # Safety
    /// Both ranges lie in memory the page wrote.
    #[no_mangle]
    pub unsafe extern "C" fn tb_call(
        name: *const u8,
        name_len: usize,
        arg: *const u8,
        arg_len: usize,
    ) -> u64 {
        let name = core::slice::from_raw_parts(name, name_len);
        let arg = core::slice::from_raw_parts(arg, arg_len);
        let out = super::call(
            core::str::from_utf8(name).unwrap_or(""),
            core::str::from_utf8(arg).unwrap_or(""),
        )
        .into_bytes()
        .into_boxed_slice();
        let len = out.len();
        let ptr = Box::into_raw(out) as *mut u8;
        ((ptr as u64) << 32) | len as u64
    }
}
