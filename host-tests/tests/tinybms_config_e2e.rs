//! End to end: `tinybms config` (the built binary) against `sim --bridge-pty
//! --flash FILE` — the firmware's bridge, host link and configuration store in
//! the sim process, the record in a file-backed flash that a restarted sim
//! finds again.

mod common;
use common::*;

fn bridge(flash: &std::path::Path, extra: &[&str]) -> Sim {
    let mut args = vec!["--bridge-pty", "--flash", flash.to_str().unwrap()];
    args.extend_from_slice(extra);
    Sim::start(&args)
}

#[test]
fn show_change_restart_and_find_it_again() {
    let flash = tmp("config-flash.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &[]);
    let show = tinybms(&["config", &sim.path]);
    assert_eq!(show.code, 0, "{show}");
    assert!(show.stdout.contains("started from defaults"), "{show}");
    assert!(show.stdout.contains("charge_current_cap"), "{show}");
    assert!(show.stdout.contains("0.1 A to 750.0 A, or none"), "{show}");
    let set = tinybms(&[
        "config",
        &sim.path,
        "charge_current_cap=50A",
        "inverter_protocol=sma",
    ]);
    assert_eq!(set.code, 0, "{set}");
    assert!(
        set.stdout.contains("charge_current_cap = 50.0 A: applied"),
        "{set}"
    );
    assert!(
        set.stdout
            .contains("inverter_protocol = sma: stored, applies at the next restart"),
        "{set}"
    );
    assert!(set.stdout.contains("saved to the bridge's flash"), "{set}");
    let show = tinybms(&["config", &sim.path]);
    assert!(show.stdout.contains("(restart pending)"), "{show}");
    drop(sim);
    // A restart of the bridge: the record is in the flash file.
    let sim = bridge(&flash, &[]);
    let show = tinybms(&["config", &sim.path]);
    assert_eq!(show.code, 0, "{show}");
    assert!(show.stdout.contains("started from flash"), "{show}");
    assert!(!show.stdout.contains("(restart pending)"), "{show}");
    let line = show
        .stdout
        .lines()
        .find(|l| l.contains("charge_current_cap"))
        .unwrap();
    assert!(line.starts_with('*') && line.contains("50.0 A"), "{line}");
    let one = tinybms(&["config", &sim.path, "inverter_protocol"]);
    assert_eq!(one.code, 0, "{one}");
    assert!(one.stdout.contains("value    sma"), "{one}");
    assert!(one.stdout.contains("CAN protocol"), "{one}");
}

#[test]
fn save_load_and_reset() {
    let flash = tmp("config-flash-2.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &[]);
    let set = tinybms(&[
        "config",
        &sim.path,
        "stale_after=8s",
        "wifi_ssid=Home Net",
        "mqtt_user=bms",
        "mqtt_password=hunter2",
    ]);
    assert_eq!(set.code, 0, "{set}");
    assert!(
        !set.stdout.contains("hunter2"),
        "a secret was echoed: {set}"
    );
    let file = tmp("bridge-config.txt");
    let save = tinybms(&["config", &sim.path, "--save", file.to_str().unwrap()]);
    assert_eq!(save.code, 0, "{save}");
    let text = std::fs::read_to_string(&file).unwrap();
    // The names are padded so the comments line up.
    let has = |start: &str| {
        text.lines().any(|l| {
            l.split_whitespace()
                .collect::<Vec<_>>()
                .join(" ")
                .starts_with(start)
        })
    };
    assert!(has("stale_after = 8 s #"), "{text}");
    assert!(has("wifi_ssid = \"Home Net\" #"), "{text}");
    assert!(!text.contains("hunter2"), "a secret was saved: {text}");
    assert!(
        text.contains("# mqtt_password: set (secrets are not saved)"),
        "{text}"
    );
    // Reset, then load the file back.
    let reset = tinybms(&["config", &sim.path, "--reset", "--yes"]);
    assert_eq!(reset.code, 0, "{reset}");
    let show = tinybms(&["config", &sim.path]);
    assert!(show.stdout.contains("0 fields differ"), "{show}");
    let dry = tinybms(&[
        "config",
        &sim.path,
        "--load",
        file.to_str().unwrap(),
        "--dry-run",
    ]);
    assert_eq!(dry.code, 0, "{dry}");
    assert!(dry.stdout.contains("stale_after"), "{dry}");
    assert!(dry.stdout.contains("dry run: nothing changed"), "{dry}");
    assert!(dry.stdout.contains("not restored: mqtt_password"), "{dry}");
    let load = tinybms(&["config", &sim.path, "--load", file.to_str().unwrap()]);
    assert_eq!(load.code, 0, "{load}");
    // Issue 26: the secrets the file could not hold are named, with the way
    // to set them again.
    assert!(
        load.stdout.contains(
            "not restored: mqtt_password (secrets are never saved in a file). Set it again: \
             `tinybms mqtt PORT --host HOST --user USER` (asks for the password)"
        ),
        "{load}"
    );
    let show = tinybms(&["config", &sim.path, "stale_after"]);
    assert!(show.stdout.contains("value    8 s"), "{show}");
    // The password was not in the file: unset after the reset.
    let show = tinybms(&["config", &sim.path, "mqtt_password"]);
    assert!(show.stdout.contains("value    unset"), "{show}");
}

#[test]
fn errors_a_user_meets_get_a_sentence() {
    let flash = tmp("config-flash-3.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &[]);
    // A typo: a suggestion, exit 2, nothing sent.
    let typo = tinybms(&["config", &sim.path, "charge_curent_cap=50"]);
    assert_eq!(typo.code, 2, "{typo}");
    assert!(
        typo.stderr.contains("did you mean `charge_current_cap`"),
        "{typo}"
    );
    // Out of range: the range.
    let far = tinybms(&["config", &sim.path, "charge_current_cap=9999"]);
    // A value the field refuses is a refusal (1), not a usage error (2).
    assert_eq!(far.code, 1, "{far}");
    assert!(far.stderr.contains("refused, nothing changed"), "{far}");
    assert!(far.stderr.contains("0.1 A to 750.0 A, or none"), "{far}");
    // A unit of another quantity.
    let unit = tinybms(&["config", &sim.path, "charge_current_cap=50V"]);
    assert_eq!(unit.code, 1, "{unit}");
    assert!(unit.stderr.contains("not in this field's unit"), "{unit}");
    // A rule between fields, caught before sending.
    let rule = tinybms(&["config", &sim.path, "wifi_key=".to_string().as_str()]);
    assert_eq!(rule.code, 0, "{rule}");
    let key = format!("wifi_key={}", "ab".repeat(32));
    let rule = tinybms(&["config", &sim.path, &key]);
    assert_eq!(rule.code, 1, "{rule}");
    assert!(rule.stderr.contains("refused, nothing changed"), "{rule}");
    assert!(rule.stderr.contains("no wifi_ssid"), "{rule}");
    // The same field twice.
    let twice = tinybms(&["config", &sim.path, "stale_after=7", "stale_after=9"]);
    assert_eq!(twice.code, 2, "{twice}");
    // A bad file names its line.
    let bad = tmp("bad-config.txt");
    std::fs::write(&bad, "# x\nstale_after = 7\nstale_after = 9\n").unwrap();
    let load = tinybms(&["config", &sim.path, "--load", bad.to_str().unwrap()]);
    // Issue 51: a file's content is no usage error: exit 1, no "try --help".
    assert_eq!(load.code, 1, "{load}");
    assert!(!load.stderr.contains("--help"), "{load}");
    assert!(load.stderr.contains("line 3"), "{load}");
    // Nothing of it reached the bridge.
    let show = tinybms(&["config", &sim.path]);
    assert!(show.stdout.contains("0 fields differ"), "{show}");
}

#[test]
fn a_read_only_bridge_refuses_and_says_how_to_unlock() {
    let flash = tmp("config-flash-4.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &["--read-only"]);
    let set = tinybms(&["config", &sim.path, "charge_current_cap=50"]);
    assert_eq!(set.code, 1, "{set}");
    assert!(set.stderr.contains("BOOT button"), "{set}");
    drop(sim);
    // The way out without a computer: the BOOT button, held (simulated at 1 s).
    let sim = bridge(&flash, &["--boot-button", "1s"]);
    let mut ok = None;
    for _ in 0..40 {
        let set = tinybms(&["config", &sim.path, "charge_current_cap=50"]);
        if set.code == 0 {
            ok = Some(set);
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(500));
    }
    let set = ok.expect("the BOOT button did not lift read-only within 20 s");
    assert!(set.stdout.contains("applied"), "{set}");
    drop(sim);
    // And the way out by erasing the store: the defaults, read-write.
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &[]);
    let show = tinybms(&["config", &sim.path, "read_only"]);
    assert!(show.stdout.contains("value    off"), "{show}");
}

#[test]
fn direct_mode_has_no_bridge_configuration() {
    let sim = Sim::start(&["--pty"]);
    let out = tinybms(&["config", &sim.path]);
    assert_eq!(out.code, 1, "{out}");
    assert!(out.stderr.contains("direct mode"), "{out}");
    assert!(!out.stderr.contains("--help"), "{out}");
}

#[test]
fn a_flash_file_that_is_not_one_is_refused() {
    let flash = tmp("not-a-flash.bin");
    std::fs::write(&flash, b"hello").unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_sim"))
        .args([
            "--bridge-pty",
            "--flash",
            flash.to_str().unwrap(),
            "--duration",
            "5s",
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let status = child.wait().unwrap();
    let mut err = String::new();
    use std::io::Read;
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    assert!(!status.success());
    assert!(err.contains("not a 24576-byte flash image"), "{err}");
}

#[test]
fn a_corrupted_flash_file_gives_the_defaults_and_a_bridge_that_runs() {
    let flash = tmp("corrupt-flash.bin");
    let mut bytes = vec![0xFFu8; 0x6000];
    for (i, b) in bytes.iter_mut().enumerate().take(8192) {
        *b = (i * 7 + 3) as u8;
    }
    std::fs::write(&flash, &bytes).unwrap();
    let sim = bridge(&flash, &[]);
    let show = tinybms(&["config", &sim.path]);
    assert_eq!(show.code, 0, "{show}");
    assert!(show.stdout.contains("started from defaults"), "{show}");
    let set = tinybms(&["config", &sim.path, "stale_after=6"]);
    assert_eq!(set.code, 0, "{set}");
}

#[test]
fn wifi_and_mqtt_store_the_key_and_the_broker_and_never_echo_a_secret() {
    let flash = tmp("config-flash-5.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &[]);
    let wifi = tinybms_with_input(
        &["wifi", &sim.path, "--ssid", "Home Net"],
        "correct horse battery\n",
    );
    assert_eq!(wifi.code, 0, "{wifi}");
    assert!(wifi.stdout.contains("wifi_key = set"), "{wifi}");
    assert!(wifi.stdout.contains("next restart"), "{wifi}");
    let mqtt = tinybms_with_input(
        &[
            "mqtt",
            &sim.path,
            "--host",
            "broker.lan",
            "--port",
            "1884",
            "--user",
            "bms",
        ],
        "s3cret-pass\n",
    );
    assert_eq!(mqtt.code, 0, "{mqtt}");
    let show = tinybms(&["config", &sim.path]);
    let all = format!("{wifi}{mqtt}{show}");
    for secret in [
        "correct horse",
        "s3cret-pass",
        &tinybms::config::wpa2_psk("Home Net", "correct horse battery").unwrap(),
    ] {
        assert!(!all.contains(secret), "a secret was shown: {secret}");
    }
    for line in [
        "wifi_ssid",
        "wifi_key",
        "mqtt_host",
        "mqtt_port",
        "mqtt_user",
        "mqtt_password",
    ] {
        let l = show.stdout.lines().find(|l| l.contains(line)).unwrap();
        assert!(l.starts_with('*'), "{l}");
    }
    assert!(show.stdout.contains("broker.lan"), "{show}");
    assert!(show.stdout.contains("1884"), "{show}");
    // A passphrase the standard does not allow: refused before anything is sent.
    let bad = tinybms_with_input(&["wifi", &sim.path, "--ssid", "X"], "short\n");
    assert_eq!(bad.code, 2, "{bad}");
    assert!(bad.stderr.contains("8 to 63"), "{bad}");
    // Issue 51: `--user` without a terminal and nothing on standard input
    // used to set an empty password silently: now nothing changes, said.
    let empty = tinybms_with_input(
        &["mqtt", &sim.path, "--host", "broker.lan", "--user", "other"],
        "",
    );
    assert_eq!(empty.code, 1, "{empty}");
    assert!(empty.stderr.contains("nothing to read"), "{empty}");
    let show = tinybms(&["config", &sim.path]);
    let user = show
        .stdout
        .lines()
        .find(|l| l.contains("mqtt_user"))
        .unwrap();
    assert!(user.contains("bms"), "unchanged: {user}");
}

/// Issue 26: `read_only=on` is one-way over USB, so it asks first; `no`
/// changes nothing, `yes` (or `--yes`) locks. A cap of 0 is refused, never
/// applied as `none` (no cap).
#[test]
fn one_way_changes_ask_and_a_cap_of_zero_is_refused() {
    let flash = tmp("config-flash-oneway.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &[]);
    let zero = tinybms(&["config", &sim.path, "charge_current_cap=0"]);
    assert_ne!(zero.code, 0, "{zero}");
    assert!(zero.stderr.contains("no cap"), "{zero}");
    let show = tinybms(&["config", &sim.path, "charge_current_cap"]);
    assert!(show.stdout.contains("value    none"), "{show}");
    let no = tinybms_with_input(&["config", &sim.path, "read_only=on"], "no\n");
    assert_eq!(no.code, 1, "{no}");
    assert!(no.stdout.contains("read_only=on is one-way"), "{no}");
    assert!(no.stdout.contains("BOOT button"), "{no}");
    assert!(no.stderr.contains("not confirmed: nothing changed"), "{no}");
    let show = tinybms(&["config", &sim.path, "read_only"]);
    assert!(show.stdout.contains("value    off"), "{show}");
    let yes = tinybms_with_input(&["config", &sim.path, "read_only=on"], "yes\n");
    assert_eq!(yes.code, 0, "{yes}");
    let show = tinybms(&["config", &sim.path, "read_only"]);
    assert!(show.stdout.contains("value    on"), "{show}");
}

/// Issue 26, items 5 and 8: the bridge says who it is — firmware, build,
/// chip, board, what is built in, the record's version — in `hello` and in
/// `tinybms version`; on an image without Wi-Fi, `tinybms wifi` and
/// `tinybms mqtt` say so (before asking for a secret) instead of promising a
/// network after the next restart.
#[test]
fn the_bridge_says_who_it_is_and_an_image_without_wifi_says_so() {
    let flash = tmp("config-flash-identity.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &["--no-wifi"]);
    let v = tinybms(&["version", &sim.path]);
    assert_eq!(v.code, 0, "{v}");
    assert!(v.stdout.contains("the bridge (its own firmware):"), "{v}");
    assert!(v.stdout.contains(env!("CARGO_PKG_VERSION")), "{v}");
    assert!(v.stdout.contains("board"), "{v}");
    assert!(
        v.stdout.contains("features        can, host-link, store"),
        "{v}"
    );
    assert!(
        v.stdout.contains(&format!(
            "record_version  {}",
            tinybms_firmware::config::VERSION
        )),
        "{v}"
    );
    let j = tinybms(&["version", &sim.path, "--json"]);
    let line: serde_json::Value = serde_json::from_str(j.stdout.trim()).unwrap();
    assert_eq!(line["bridge"]["chip"], "sim", "{j}");
    assert_eq!(
        line["bridge"]["features"],
        serde_json::json!(["can", "host-link", "store"])
    );
    let wifi = tinybms_with_input(
        &["wifi", &sim.path, "--ssid", "Home Net"],
        "correct horse battery\n",
    );
    assert_eq!(wifi.code, 1, "{wifi}");
    assert!(
        wifi.stderr
            .contains("this bridge's image has no Wi-Fi (built in: can, host-link, store)"),
        "{wifi}"
    );
    assert!(
        !wifi.stdout.contains("Passphrase"),
        "asked for a passphrase: {wifi}"
    );
    let mqtt = tinybms_with_input(&["mqtt", &sim.path, "--host", "broker.lan"], "");
    assert_eq!(mqtt.code, 1, "{mqtt}");
    assert!(mqtt.stderr.contains("has no Wi-Fi"), "{mqtt}");
    let show = tinybms(&["config", &sim.path, "wifi_ssid"]);
    assert!(!show.stdout.contains("Home Net"), "stored anyway: {show}");
}

/// Issue 26, item 13: `config PORT NAME=VALUE --dry-run` checks by the
/// firmware's rules and changes nothing; arguments in the wrong order are
/// named as such; a `--period` the bridge cannot stream is said, not clamped
/// in silence.
#[test]
fn dry_run_swapped_arguments_and_a_clamped_period_are_said() {
    let flash = tmp("config-flash-dry.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &[]);
    let dry = tinybms(&["config", &sim.path, "charge_current_cap=50A", "--dry-run"]);
    assert_eq!(dry.code, 0, "{dry}");
    assert!(dry.stdout.contains("charge_current_cap"), "{dry}");
    assert!(dry.stdout.contains("-> 50"), "{dry}");
    assert!(
        dry.stdout.contains("dry run: checked, nothing changed"),
        "{dry}"
    );
    let after = tinybms(&["config", &sim.path, "charge_current_cap"]);
    assert!(
        !after.stdout.contains("= 50"),
        "changed by a dry run: {after}"
    );
    let bad = tinybms(&["config", &sim.path, "charge_current_cap=0", "--dry-run"]);
    assert_eq!(bad.code, 1, "a typed 0 is refused in a dry run too: {bad}");
    let swapped = tinybms(&["config", "charge_current_cap=5A", &sim.path]);
    assert_eq!(swapped.code, 2, "{swapped}");
    assert!(swapped.stderr.contains("the port comes first"), "{swapped}");
    let m = tinybms(&[
        "monitor", &sim.path, "--json", "--count", "1", "--period", "50ms",
    ]);
    assert_eq!(m.code, 0, "{m}");
    assert!(
        m.stderr
            .contains("--period 50ms: the bridge streams every 100 ms to 60 s; using 100 ms"),
        "{m}"
    );
}

/// Issue 40, as a Deye owner does it: `inverter_protocol=pylon
/// inverter_name=DEYE` is taken (the protocol at the next restart, the name
/// at once), survives a restart, and `monitor` then shows the dialect, the
/// inverter's heartbeat heard (the simulated inverter's 0x305) and the
/// limits it is told, with what the protection stops.
#[test]
fn a_hybrid_inverter_protocol_and_its_name_survive_a_restart_and_show_in_monitor() {
    let flash = tmp("config-flash-pylon.bin");
    let _ = std::fs::remove_file(&flash);
    let sim = bridge(&flash, &[]);
    let set = tinybms(&[
        "config",
        &sim.path,
        "inverter_protocol=pylon",
        "inverter_name=DEYE",
        "stop_by_soc=on",
    ]);
    assert_eq!(set.code, 0, "{set}");
    assert!(
        set.stdout
            .contains("inverter_protocol = pylon: stored, applies at the next restart"),
        "{set}"
    );
    assert!(
        set.stdout.contains("inverter_name = DEYE: applied"),
        "{set}"
    );
    assert!(set.stdout.contains("saved to the bridge's flash"), "{set}");
    // Until the restart the monitor says a change waits for it.
    let waiting = tinybms(&["monitor", &sim.path, "--count", "2", "--plain"]);
    assert!(
        waiting
            .stdout
            .contains("1 configuration change waits for a restart"),
        "{waiting}"
    );
    drop(sim);
    let sim = bridge(&flash, &[]);
    for (name, want) in [
        ("inverter_protocol", "value    pylon"),
        ("inverter_name", "value    DEYE"),
        ("stop_by_soc", "value    on"),
    ] {
        let one = tinybms(&["config", &sim.path, name]);
        assert_eq!(one.code, 0, "{one}");
        assert!(one.stdout.contains(want), "{name}: {one}");
    }
    let text = tinybms(&["monitor", &sim.path, "--count", "3", "--plain"]);
    assert_eq!(text.code, 0, "{text}");
    // The monitor names the protocol and the name 0x35E tells.
    assert!(
        text.stdout
            .contains("Inverter pylon (0x35E DEYE): CAN running, inverter heard   CVL "),
        "{text}"
    );
    assert!(!text.stdout.contains("waits for a restart"), "{text}");
    let json = tinybms(&["monitor", &sim.path, "--count", "2", "--json"]);
    let last: serde_json::Value =
        serde_json::from_str(json.stdout.lines().last().unwrap()).unwrap();
    let inv = &last["inverter"];
    assert_eq!(inv["protocol"], "pylon", "{last}");
    assert_eq!(inv["heard"], true, "{last}");
    assert!(inv["cvl_v"].as_f64().unwrap() > 40.0, "{last}");
    assert!(inv["charge_stop"].is_string(), "{last}");
    assert!(inv["discharge_stop"].is_string(), "{last}");
    // What the frames told, read back: the name, the enable bits, the SOC.
    assert_eq!(inv["name"], "DEYE", "{last}");
    assert_eq!(inv["charge_enabled"], true, "{last}");
    assert_eq!(inv["discharge_enabled"], true, "{last}");
    assert!(inv["soc_told"].as_u64().is_some(), "{last}");
    // The log says the protocol by its name.
    let log = tinybms(&["log", &sim.path, "--duration", "2s"]);
    assert!(
        log.stdout
            .contains("CAN to the inverter: Pylontech LV (V1.2)"),
        "{log}"
    );
}
