//! Records what the bridge's wiring does, for a before/after comparison of a
//! change that should not change behaviour: every call made to the bridge (the
//! trace format of `host_tests::trace`), every CAN frame (candump lines) and
//! every host-link line, over the closed-loop scenarios (Victron and SMA), a
//! closed loop driven through the host link, the multi-pack scenarios and a
//! faulted soak. One file per run in the folder given (default
//! `target/wiring-trace`); compare two folders with `diff -r` or `cmp`.
//!
//! ```sh
//! cargo run --release -p host-tests --example wiring_trace -- target/after
//! ```

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use host_tests::closed_loop::{self, ClosedLoop};
use host_tests::multi_pack;
use host_tests::sim::{FaultConfig, PackModel, SimBms, SimConfig};
use host_tests::virtual_time::Harness;
use tinybms_desk::flash::RamFlash;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::inverter::{InverterConfig, Protocol};

/// A `Write` whose bytes can be read after the loop that owns it is gone.
#[derive(Clone, Default)]
struct Shared(Arc<Mutex<Vec<u8>>>);

impl Write for Shared {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn save(dir: &Path, name: &str, bytes: &[u8]) {
    std::fs::write(dir.join(name), bytes).unwrap();
    println!("{name:<40} {:>10} bytes", bytes.len());
}

fn main() {
    let dir = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "target/wiring-trace".into()),
    );
    std::fs::create_dir_all(&dir).unwrap();

    for protocol in [Protocol::Victron, Protocol::SmaSunnyIsland] {
        let tag = protocol.key();
        for name in closed_loop::SCENARIOS {
            let can = Shared::default();
            let inverter = InverterConfig {
                protocol,
                ..InverterConfig::default()
            };
            let (l, _) = closed_loop::run_scenario(name, inverter, |l| {
                l.h.trace = Some(Vec::new());
                l.can_log = Some(Box::new(can.clone()));
            })
            .unwrap();
            save(
                &dir,
                &format!("loop-{tag}-{name}.trace"),
                l.h.trace.as_deref().unwrap(),
            );
            drop(l);
            save(
                &dir,
                &format!("loop-{tag}-{name}.candump"),
                &can.0.lock().unwrap(),
            );
        }
    }

    // A closed loop as the chip runs it with its configuration record and a
    // host that asks for things and changes the configuration.
    {
        let can = Shared::default();
        let mut l = ClosedLoop::from_flash(PackModel::LiFePO4_16S, 3, RamFlash::new(), 100.0);
        l.h.trace = Some(Vec::new());
        l.can_log = Some(Box::new(can.clone()));
        l.h.sim.set_soc_percent(40.0);
        let script: [(u64, &str); 8] = [
            (1, r#"{"cmd":"hello","req":1}"#),
            (5, r#"{"cmd":"stream","period_ms":500,"req":2}"#),
            (30, r#"{"cmd":"get","what":"settings","req":3}"#),
            (
                60,
                r#"{"cmd":"set_config","fields":{"charge_current_cap":"40 A"},"req":4}"#,
            ),
            (90, r#"{"cmd":"get","what":"config","req":5}"#),
            (
                120,
                r#"{"cmd":"set","raw":{"over_voltage_cutoff":3640},"req":6}"#,
            ),
            (300, r#"{"cmd":"capture","on":true,"req":7}"#),
            (302, r#"{"cmd":"capture","on":false,"req":8}"#),
        ];
        for (at_s, line) in script {
            l.run_until(at_s * 1_000_000);
            l.host_line(line);
        }
        l.run_until(20 * 60 * 1_000_000);
        let lines: Vec<String> = l
            .host
            .as_ref()
            .unwrap()
            .lines
            .iter()
            .map(|v| v.to_string())
            .collect();
        save(&dir, "host-loop.trace", l.h.trace.as_deref().unwrap());
        save(
            &dir,
            "host-loop.lines",
            (lines.join("\n") + "\n").as_bytes(),
        );
        drop(l);
        save(&dir, "host-loop.candump", &can.0.lock().unwrap());
    }

    for name in multi_pack::SCENARIOS {
        let can = Shared::default();
        let (l, _) = multi_pack::run_scenario(name, 4, InverterConfig::default(), |l| {
            l.can_log = Some(Box::new(can.clone()));
        })
        .unwrap();
        let mut limits = String::new();
        for (t, n, lim) in &l.sent_limits {
            limits += &format!("{t} {n} {lim:?}\n");
        }
        for (t, n, r) in &l.figures.reports {
            limits += &format!("{t} {n} report {r:?}\n");
        }
        save(&dir, &format!("packs-{name}.limits"), limits.as_bytes());
        drop(l);
        save(
            &dir,
            &format!("packs-{name}.candump"),
            &can.0.lock().unwrap(),
        );
    }

    // A faulted soak: every fault kind at 5 %, writes every 30 s.
    {
        let config = SimConfig {
            sleep_after_us: Some(30_000_000),
            faults: FaultConfig::all(0.05),
            ..SimConfig::default()
        };
        let sim = SimBms::new(PackModel::LiFePO4_16S, config, 7);
        let mut h = Harness::checked(sim, Timing::default());
        h.retain = false;
        h.trace = Some(Vec::new());
        let mut k = 0u16;
        let mut t = 0;
        while t < 2 * 3600 * 1_000_000 {
            t += 30 * 1_000_000;
            h.run_until(t);
            // Above the fully-charged voltage (3.65 V): a lower cutoff is refused.
            let value = if k.is_multiple_of(2) { 3660 } else { 3650 };
            let mut items = heapless::Vec::new();
            let _ = items.push(protocol_core::settings::Setting {
                id: protocol_core::settings::SettingId::OverVoltageCutoff,
                value,
            });
            let _ = h
                .bridge_mut()
                .submit(tinybms_firmware::Command::ApplySettings(
                    items,
                    protocol_core::settings::ChemistryCheck::Inferred,
                ));
            k += 1;
        }
        let s = h.soak.clone().unwrap_or_default();
        println!(
            "soak: published {} wrong {} false successes {} offline {}",
            s.published, s.wrong, s.false_successes, s.offline_transitions
        );
        save(&dir, "soak.trace", h.trace.as_deref().unwrap());
    }
}
