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
//! | `check_settings` | `{changes: ["NAME=VALUE"…], current: [setting lines], raw}` | `{ok, messages, values: {name: raw}, chemistry}` |
//! | `freshness` | `{telemetry: line or null, received_ago_ms}` | `{state, age_s, text}` |
//! | `link_quality` | a `link` line | `{text}` |
//! | `direct_start` | `{now_ms}` | `{}`: the firmware's station starts in the page (direct mode) |
//! | `direct_step` | `{now_ms, rx: [bytes from the BMS], host: "command lines"}` | `{tx: [bytes for the BMS], lines: [host-link lines], wake_ms}` |
//!
//! The bridge's lines the page passes in (`current`, `telemetry`, a `link`
//! line) are read through the host link's own types
//! ([`tinybms_firmware::host_link::schema::HostLine`]), as the tool
//! reads them; one that is not a line the bridge writes counts as none
//! (left out of `current`; no `telemetry`; `link_quality` answers `{text: null}`).
//!
//! **Direct mode**: with a TinyBMS behind a plain USB-UART adapter there is no
//! bridge on the port, so the page runs one — the firmware's own
//! [`Station`](tinybms_firmware::station::Station), as `tinybms` does in its
//! direct mode: the page hands it what the BMS sent and the console's command
//! lines, writes what it transmits to the port, and reads its host-link lines
//! as it would a bridge's.

use serde_json::{json, Value};
use tinybms_firmware::boards::BOARDS;
use tinybms_firmware::host_link::schema::HostLine;

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
        "direct_start" => direct::start(&arg),
        "direct_step" => direct::step(&arg),
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

/// A host-link line the page passes on, read through the host link's types
/// (`None`: not a line the bridge writes).
fn line(v: &Value) -> Option<HostLine> {
    serde_json::from_value(v.clone()).ok()
}

/// The lines of `v` (an array) that `pick` takes; the rest are left out.
fn lines<T>(v: &Value, pick: impl Fn(HostLine) -> Option<T>) -> Vec<T> {
    v.as_array()
        .map(|a| a.iter().filter_map(line).filter_map(&pick).collect())
        .unwrap_or_default()
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
        let current = lines(&arg["current"], |l| match l {
            HostLine::Config(f) => Some(f),
            _ => None,
        });
        if let Err(m) = check_locally(&record_of(&current), &changes) {
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
    let current = lines(&arg["current"], |l| match l {
        HostLine::Setting(s) => Some(s),
        _ => None,
    });
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
    // The chemistry the tool checks against by default: the one the BMS's
    // own cutoffs name.
    let (chem, said) = tinybms_rules::settings::chemistry_of(
        &current,
        &items,
        protocol_core::settings::ChemistryCheck::Inferred,
    );
    if messages.is_empty() {
        if let Err(m) =
            tinybms_rules::settings::check_all(&current, &items, Some(&bare), chem.as_ref())
        {
            messages.push(m);
        }
    }
    let values: serde_json::Map<String, Value> = items
        .iter()
        .map(|(id, v)| (tinybms_rules::settings::snake_name(*id), Value::from(*v)))
        .collect();
    json!({ "ok": messages.is_empty(), "messages": messages, "values": values, "chemistry": said })
}

/// The firmware's one freshness rule on the newest telemetry line (`null`:
/// none yet), received `received_ago_ms` ago — its age then plus the time
/// since, against the limit the bridge gave — in the monitor's words.
fn freshness(arg: &Value) -> Value {
    use tinybms_rules::view::{freshness, freshness_text, Freshness};
    let t = match arg.get("telemetry").and_then(line) {
        Some(HostLine::Telemetry(t)) => Some(t),
        _ => None,
    };
    let since = arg["received_ago_ms"].as_f64().unwrap_or(0.0).max(0.0);
    let f = freshness(
        t.as_ref(),
        std::time::Duration::from_secs_f64(since / 1000.0),
    );
    let (state, age) = match f {
        Freshness::Fresh(a) => ("fresh", Some(a)),
        Freshness::Offline(a) => ("offline", a),
        Freshness::NoData(a) => ("no_data", a),
    };
    json!({ "state": state, "age_s": age, "text": freshness_text(f) })
}

/// The link quality of a `link` line, in the monitor's words.
fn link_quality(arg: &Value) -> Value {
    let text = match line(arg) {
        Some(HostLine::Link(l)) => Some(tinybms_rules::view::link_quality(&l)),
        _ => None,
    };
    json!({ "text": text })
}

/// The firmware's station in the page (direct mode).
mod direct {
    use std::cell::RefCell;

    use serde_json::{json, Value};
    use tinybms_firmware::bms::timing::Timing;
    use tinybms_firmware::config::store::StoreError;
    use tinybms_firmware::config::Config;
    use tinybms_firmware::identity::{Features, Identity};
    use tinybms_firmware::inverter::TxResult;
    use tinybms_firmware::station::{Action, Setup, Station};

    thread_local! {
        static STATION: RefCell<Option<Station>> = const { RefCell::new(None) };
    }

    /// Most actions one step carries out (a bound, never reached: the
    /// station waits after a transmit).
    const MAX_ACTIONS: usize = 256;

    fn us(arg: &Value) -> u64 {
        (arg["now_ms"].as_f64().unwrap_or(0.0).max(0.0) * 1000.0) as u64
    }

    /// A new station at `now_ms`: the bridge and its host link, nothing else
    /// (no inverter output, no store, no Wi-Fi: the page is the host).
    pub fn start(arg: &Value) -> Value {
        let now = us(arg);
        let setup = Setup {
            timing: Timing::default(),
            identity: Identity {
                chip: "browser",
                board: "the console's direct mode",
                firmware: tinybms_firmware::identity::FIRMWARE,
                features: Features {
                    host_link: true,
                    ..Features::default()
                },
            },
            inverter: None,
        };
        let mut station = Station::with_record(setup, Config::default(), now);
        station.host_connected(now);
        STATION.with(|s| *s.borrow_mut() = Some(station));
        json!({})
    }

    /// One round: what the BMS sent and the host's lines in; what to send to
    /// the BMS, the host-link lines, and when to come back out.
    pub fn step(arg: &Value) -> Value {
        let now = us(arg);
        let rx: Vec<u8> = arg["rx"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|b| b.as_u64().and_then(|b| u8::try_from(b).ok()))
                    .collect()
            })
            .unwrap_or_default();
        let host = arg["host"].as_str().unwrap_or("");
        STATION.with(|cell| {
            let mut guard = cell.borrow_mut();
            let Some(station) = guard.as_mut() else {
                return json!({ "error": "direct_start first" });
            };
            if !rx.is_empty() {
                station.handle_rx(now, &rx);
            }
            if !host.is_empty() {
                station.host_rx(now, host.as_bytes());
            }
            let mut tx: Vec<u8> = Vec::new();
            let mut wake = now + 100_000;
            for _ in 0..MAX_ACTIONS {
                match station.poll(now) {
                    Action::Log(_) => {}
                    Action::Transmit => tx.extend_from_slice(station.transmit_bytes()),
                    Action::Save => station.saved(Err(StoreError::Partition)),
                    Action::Can(_) => station.can_sent(now, TxResult::Failed),
                    Action::CanRecover => station.can_recovered(now, false),
                    Action::Wifi(req) => station.wifi_unavailable(now, &req),
                    // No flash in the page: an update has nowhere to go (it is
                    // refused before any flash work: no second slot).
                    Action::Flash(_) => station.flashed(now, false),
                    // No history in the page (the station has none).
                    Action::History(_) => station.history_done(false),
                    Action::HistoryRead(..) => station.history_read(None),
                    Action::Restart => break,
                    Action::WaitUntil(t) => {
                        wake = t;
                        break;
                    }
                }
            }
            let mut lines = Vec::new();
            let mut buf = vec![0u8; tinybms_firmware::host_link::OUT_LINE_MAX];
            while let Some(n) = station.next_host_line(now, &mut buf) {
                let text = String::from_utf8_lossy(buf.get(..n).unwrap_or(&[]));
                lines.push(Value::String(text.trim_end().to_string()));
            }
            json!({ "tx": tx, "lines": lines, "wake_ms": wake as f64 / 1000.0 })
        })
    }
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
