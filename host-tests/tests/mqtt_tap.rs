//! The MQTT scenario over embassy-net, the chip's network stack, on a TAP
//! device in a network namespace the test creates (`unshare -n`, or `-rn`
//! without root): the `mqtt-tap` binary, which refuses any namespace but a new
//! one. Without namespaces (a container that forbids them) the test says so and
//! passes — unless `TINYBMS_TAP_TEST=required` (set by `.ci/run`), when it fails.

use std::process::{Command, Stdio};

fn required() -> bool {
    std::env::var("TINYBMS_TAP_TEST").is_ok_and(|v| v == "required")
}

/// `unshare` arguments that make a new network namespace here, if any do.
fn namespace_args() -> Option<&'static [&'static str]> {
    for args in [&["-n"][..], &["-rn"][..]] {
        let ok = Command::new("unshare")
            .args(args)
            .args(["--", "ip", "tuntap", "add", "dev", "tap0", "mode", "tap"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if ok {
            return Some(args);
        }
    }
    None
}

#[test]
fn the_session_on_embassy_net_over_a_tap_device_passes_the_broker_scenario() {
    let Some(args) = namespace_args() else {
        assert!(
            !required(),
            "TINYBMS_TAP_TEST=required, but `unshare -n` cannot make a network namespace with a TAP device here"
        );
        eprintln!("skipped: no network namespace with a TAP device here (unshare -n / -rn)");
        return;
    };
    let out = Command::new("unshare")
        .args(args)
        .arg("--")
        .arg(env!("CARGO_BIN_EXE_mqtt-tap"))
        .output()
        .expect("unshare");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    println!("{stdout}");
    assert!(
        out.status.success() && stdout.contains("mqtt-tap: passed"),
        "mqtt-tap failed ({}):\n{stdout}\n{stderr}",
        out.status
    );
}
