//! The board table (`tinybms_firmware::boards`): its compile-time check rejects
//! each kind of bad pin, every board passes it, and the places that repeat the
//! table (Cargo features, cargo aliases, the README wiring table) agree with it.

use tinybms_firmware::boards::{
    check, Board, Chip, LogPath, PinError, Restriction, Role, BOARDS, C3_DEVKITM_1, C3_RUST_1,
    C6_DEVKITC_1, LOLIN_C3_MINI, XIAO_ESP32C3, XIAO_ESP32C6,
};

fn repo_file(path: &str) -> String {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(path);
    std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn every_board_passes_the_check() {
    assert_eq!(BOARDS.len(), 7);
    for b in BOARDS {
        assert_eq!(check(b), Ok(()), "{}", b.name);
    }
}

#[test]
fn strapping_pins_are_rejected() {
    // C3: GPIO2 (on the DevKitM-1 header).
    let b = Board {
        bms_tx: 2,
        ..C3_DEVKITM_1
    };
    assert_eq!(
        check(&b),
        Err(PinError::Chip {
            role: Role::BmsTx,
            gpio: 2,
            why: Restriction::Strapping
        })
    );
    // C6: the pins the firmware used before the table, MTMS/GPIO4 and MTDI/GPIO5.
    let old_c6 = Board {
        bms_tx: 5,
        bms_rx: 4,
        ..C6_DEVKITC_1
    };
    assert_eq!(
        check(&old_c6),
        Err(PinError::Chip {
            role: Role::BmsTx,
            gpio: 5,
            why: Restriction::Strapping
        })
    );
    assert!(matches!(
        check(&Board {
            can_rx: 15,
            ..C6_DEVKITC_1
        }),
        Err(PinError::Chip {
            why: Restriction::Strapping,
            ..
        })
    ));
}

#[test]
fn flash_usb_uart0_and_missing_pins_are_rejected() {
    let cases = [
        (Chip::Esp32c3, 12, Restriction::Flash),
        (Chip::Esp32c3, 11, Restriction::Flash),
        (Chip::Esp32c3, 18, Restriction::UsbJtag),
        (Chip::Esp32c3, 21, Restriction::Uart0),
        (Chip::Esp32c3, 22, Restriction::Missing),
        (Chip::Esp32c6, 24, Restriction::Flash),
        (Chip::Esp32c6, 13, Restriction::UsbJtag),
        (Chip::Esp32c6, 16, Restriction::Uart0),
        (Chip::Esp32c6, 31, Restriction::Missing),
    ];
    for (chip, gpio, why) in cases {
        assert_eq!(chip.restriction(gpio), Some(why), "{chip:?} GPIO{gpio}");
        let base = if chip == Chip::Esp32c3 {
            C3_DEVKITM_1
        } else {
            C6_DEVKITC_1
        };
        let b = Board {
            can_tx: gpio,
            // the header must not be what rejects it
            header: &[
                0, 1, 2, 3, 4, 5, 6, 7, 10, 11, 12, 13, 16, 18, 21, 22, 23, 24, 31,
            ],
            ..base
        };
        assert_eq!(
            check(&b),
            Err(PinError::Chip {
                role: Role::CanTx,
                gpio,
                why
            }),
            "{chip:?} GPIO{gpio}"
        );
    }
    // Pins every board may use are not restricted.
    for gpio in [0, 1, 3, 4, 5, 6, 7, 10] {
        assert_eq!(Chip::Esp32c3.restriction(gpio), None, "C3 GPIO{gpio}");
    }
    for gpio in [0, 1, 2, 3, 6, 7, 18, 19, 20, 21, 22, 23] {
        assert_eq!(Chip::Esp32c6.restriction(gpio), None, "C6 GPIO{gpio}");
    }
}

#[test]
fn on_board_parts_are_rejected() {
    // GPIO7, the C3 default TX, drives an LED on the RUST-1 and the LOLIN C3 Mini.
    for base in [C3_RUST_1, LOLIN_C3_MINI] {
        let b = Board { bms_tx: 7, ..base };
        assert!(
            matches!(
                check(&b),
                Err(PinError::OnBoard {
                    role: Role::BmsTx,
                    gpio: 7,
                    ..
                })
            ),
            "{}",
            base.name
        );
    }
    // The XIAO ESP32C6's RF switch enable.
    assert!(matches!(
        check(&Board {
            can_tx: 3,
            ..XIAO_ESP32C6
        }),
        Err(PinError::OnBoard { gpio: 3, .. })
    ));
}

#[test]
fn pins_off_the_header_and_shared_pins_are_rejected() {
    // GPIO0 is a fine C3 pin, but not on the XIAO ESP32C3's header.
    assert_eq!(
        check(&Board {
            can_rx: 0,
            ..XIAO_ESP32C3
        }),
        Err(PinError::NotOnHeader {
            role: Role::CanRx,
            gpio: 0
        })
    );
    // GPIO4/5 exist on the C6 but are not on the XIAO ESP32C6 header (and are
    // strapping pins, which is what the check reports first).
    assert!(check(&Board {
        bms_rx: 4,
        ..XIAO_ESP32C6
    })
    .is_err());
    assert_eq!(
        check(&Board {
            can_tx: 6,
            ..C3_DEVKITM_1
        }),
        Err(PinError::Shared {
            first: Role::BmsRx,
            second: Role::CanTx,
            gpio: 6
        })
    );
}

#[test]
fn cargo_features_list_the_same_boards_with_their_chips() {
    let toml = repo_file("firmware/Cargo.toml");
    let features: Vec<(String, String)> = toml
        .lines()
        .filter_map(|l| {
            let (name, rest) = l.split_once(" = [\"")?;
            let chip = rest.strip_suffix("\"]")?;
            name.starts_with("board-")
                .then(|| (name.to_string(), chip.to_string()))
        })
        .collect();
    let table: Vec<(String, String)> = BOARDS
        .iter()
        .map(|b| (b.feature.to_string(), b.chip.name().to_string()))
        .collect();
    assert_eq!(features, table);
    assert!(
        toml.contains("default = [\"board-c3-supermini\", \"log-rtt\", \"can\", \"host-link\"]"),
        "default build: the C3 SuperMini (one cable), RTT, inverter output and host link"
    );
}

/// A board whose connector is a USB-UART bridge runs its host link on UART0,
/// so its image cannot log defmt frames there: its log path is RTT (the log
/// lines reach the connector as the host link's `log` lines).
#[test]
fn a_board_with_the_host_link_on_uart0_does_not_log_there() {
    use tinybms_firmware::boards::HostWire;
    let mut uart0 = 0;
    for b in BOARDS {
        if b.host == HostWire::Uart0 {
            uart0 += 1;
            assert_eq!(b.log, LogPath::Rtt, "{}", b.name);
        }
    }
    assert_eq!(
        uart0, 1,
        "only the C3-DevKitM-1 has no native USB connector"
    );
    assert_eq!(C3_DEVKITM_1.host, HostWire::Uart0);
}

#[test]
fn each_board_has_a_build_alias_with_its_log_path() {
    let config = repo_file("firmware/.cargo/config.toml");
    for b in BOARDS {
        let short = b.feature.strip_prefix("board-").unwrap();
        let mut expected = format!(
            "build-{short} = \"build --release --no-default-features --features {},{},can,host-link",
            b.feature,
            b.log.feature()
        );
        if b.chip == Chip::Esp32c6 {
            expected.push_str(" --target riscv32imac-unknown-none-elf");
        }
        expected.push('"');
        assert!(
            config.lines().any(|l| l == expected),
            "missing alias line: {expected}"
        );
    }
}

fn readme_row(b: &Board) -> String {
    let log = match b.log {
        LogPath::Rtt => "RTT (`log-rtt`)",
        LogPath::Uart0 => "UART0 (`log-uart`)",
    };
    format!(
        "| {} | `{}` | GPIO{} ({}) | GPIO{} ({}) | GPIO{} ({}) | GPIO{} ({}) | {} |",
        b.name,
        b.feature,
        b.bms_tx,
        b.labels[0],
        b.bms_rx,
        b.labels[1],
        b.can_tx,
        b.labels[2],
        b.can_rx,
        b.labels[3],
        log
    )
}

#[test]
fn the_readme_wiring_table_matches_the_board_table() {
    for file in ["README.md", "docs/boards.md"] {
        let text = repo_file(file);
        for b in BOARDS {
            let row = readme_row(b);
            assert!(
                text.lines().any(|l| l.starts_with(&row)),
                "{file} has no wiring row starting with:\n{row}"
            );
        }
    }
}

/// The physical way out of read-only (holding BOOT 5 s) exists on every
/// board: each has a BOOT button in its table, at the chip's boot strap GPIO9,
/// and no signal of the bridge on it.
#[test]
fn every_board_has_a_boot_button_for_the_read_only_unlock() {
    for b in BOARDS {
        let gpio = b
            .boot_button()
            .unwrap_or_else(|| panic!("{}: no BOOT button in the table", b.name));
        assert_eq!(gpio, 9, "{}", b.name);
        assert!(
            b.signals().iter().all(|(_, g)| *g != gpio),
            "{}: a signal on the BOOT button",
            b.name
        );
    }
}
