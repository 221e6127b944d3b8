//! Supported boards as data: which GPIOs carry the TinyBMS UART and the
//! CAN/TWAI lines of the inverter output, where the BOOT button is, and where
//! the logs go.
//!
//! One cargo feature per board (`board-…`, see `firmware/Cargo.toml`) selects
//! `SELECTED`; each board feature implies its chip feature. Every board in
//! [`BOARDS`] is checked at compile time by [`check`]: none of its four signal
//! pins may be
//! * missing from the chip or from the board's pin header,
//! * a strapping, SPI-flash, USB-Serial-JTAG or UART0 (console) pin of the chip
//!   ([`Chip::restriction`]),
//! * wired to a part on the board, e.g. an LED, a button or a sensor
//!   ([`Board::on_board`]),
//! * used twice.
//!
//! The check is a `const fn`, so a wrong entry stops the build (of the firmware
//! and of the host tests) instead of surprising someone at the bench; the host
//! tests also call it on deliberately wrong boards to show that it rejects them.
//!
//! Sources for the chip facts: ESP-IDF "GPIO & RTC GPIO" pages for the ESP32-C3
//! and ESP32-C6 (strapping, SPI0/1 and USB-JTAG pins), the ESP32-C3 datasheet
//! §"Strapping Pins" (GPIO2/8/9), the ESP32-C6-DevKitC-1 user guide note 3
//! (MTMS/GPIO4, MTDI/GPIO5, GPIO8, GPIO9, GPIO15 are strapping pins). Board
//! sources are given per board; facts that no manufacturer document confirms
//! are marked *uncertain*.

/// The chip of a board.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Chip {
    /// ESP32-C3 (RV32IMC), GPIO0..=GPIO21.
    Esp32c3,
    /// ESP32-C6 (RV32IMAC), GPIO0..=GPIO30.
    Esp32c6,
}

/// Why a chip's GPIO may not carry a signal of the bridge.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Restriction {
    /// The chip has no such GPIO.
    Missing,
    /// Sampled at reset to choose the boot mode (or other boot options): a line
    /// driven by the BMS or a transceiver at power-up could stop the chip booting.
    Strapping,
    /// Wired to the SPI flash (or its supply) inside the module/package.
    Flash,
    /// The built-in USB-Serial-JTAG (D-/D+): flashing, RTT logs.
    UsbJtag,
    /// UART0: the ROM and bootloader print here, espflash flashes and
    /// `log-uart` logs here.
    Uart0,
}

impl Restriction {
    /// Short description for messages.
    pub const fn name(self) -> &'static str {
        match self {
            Restriction::Missing => "does not exist on this chip",
            Restriction::Strapping => "strapping pin",
            Restriction::Flash => "SPI flash pin",
            Restriction::UsbJtag => "USB-Serial-JTAG pin",
            Restriction::Uart0 => "UART0 console pin",
        }
    }
}

impl Chip {
    /// Number of GPIOs (GPIO0 up to this, exclusive).
    pub const fn gpio_count(self) -> u8 {
        match self {
            Chip::Esp32c3 => 22,
            Chip::Esp32c6 => 31,
        }
    }

    /// Chip name as in esp-hal's features.
    pub const fn name(self) -> &'static str {
        match self {
            Chip::Esp32c3 => "esp32c3",
            Chip::Esp32c6 => "esp32c6",
        }
    }

    /// UART0's own pins (TX, RX): where the ROM prints, and where the host
    /// link runs on a board whose connector is a USB-UART bridge
    /// ([`HostWire::Uart0`]). The [`Restriction::Uart0`] pins below.
    pub const fn uart0_pins(self) -> (u8, u8) {
        match self {
            Chip::Esp32c3 => (21, 20),
            Chip::Esp32c6 => (16, 17),
        }
    }

    /// The reason `gpio` can never carry a bridge signal on this chip, if any.
    pub const fn restriction(self, gpio: u8) -> Option<Restriction> {
        if gpio >= self.gpio_count() {
            return Some(Restriction::Missing);
        }
        match self {
            // ESP32-C3: strapping GPIO2/8/9 (datasheet §Strapping Pins); GPIO11 is
            // VDD_SPI and GPIO12-17 the SPI flash (ESP-IDF GPIO page); GPIO18/19
            // USB D-/D+; GPIO20/21 U0RXD/U0TXD.
            Chip::Esp32c3 => match gpio {
                2 | 8 | 9 => Some(Restriction::Strapping),
                11..=17 => Some(Restriction::Flash),
                18 | 19 => Some(Restriction::UsbJtag),
                20 | 21 => Some(Restriction::Uart0),
                _ => None,
            },
            // ESP32-C6: strapping MTMS/GPIO4, MTDI/GPIO5, GPIO8, GPIO9, GPIO15;
            // GPIO24-30 SPI0/1 flash; GPIO12/13 USB D-/D+; GPIO16/17 U0TXD/U0RXD
            // (ESP-IDF ESP32-C6 GPIO page, DevKitC-1 user guide).
            Chip::Esp32c6 => match gpio {
                4 | 5 | 8 | 9 | 15 => Some(Restriction::Strapping),
                24..=30 => Some(Restriction::Flash),
                12 | 13 => Some(Restriction::UsbJtag),
                16 | 17 => Some(Restriction::Uart0),
                _ => None,
            },
        }
    }
}

/// Where defmt logs go.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogPath {
    /// defmt over RTT through the chip's USB-Serial-JTAG, read by `probe-rs`
    /// (feature `log-rtt`, the default).
    Rtt,
    /// defmt frames on UART0 (GPIO20/21 on the C3, GPIO16/17 on the C6) through
    /// the board's USB-UART bridge, read by `espflash flash --monitor
    /// --log-format defmt` (feature `log-uart`).
    Uart0,
}

impl LogPath {
    /// The cargo feature that selects this path.
    pub const fn feature(self) -> &'static str {
        match self {
            LogPath::Rtt => "log-rtt",
            LogPath::Uart0 => "log-uart",
        }
    }
}

/// The host link's rate on [`HostWire::Uart0`] (8N1): what the USB-UART
/// bridges of these boards and every serial monitor take by default.
pub const HOST_UART_BAUD: u32 = 115_200;

/// Where the host link (JSON Lines to a computer, with the bridge's log lines)
/// runs: on the wire the board's own USB connector reaches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HostWire {
    /// The chip's USB-Serial-JTAG: the connector is the chip's own USB.
    UsbSerialJtag,
    /// UART0 at 115 200 8N1 (GPIO21 TX / GPIO20 RX on the C3, GPIO16 / GPIO17
    /// on the C6): the connector goes to a USB-UART bridge chip on UART0.
    Uart0,
}

impl HostWire {
    /// In a few words.
    pub const fn name(self) -> &'static str {
        match self {
            HostWire::UsbSerialJtag => "USB-Serial-JTAG",
            HostWire::Uart0 => "UART0 (the board's USB-UART bridge)",
        }
    }
}

/// A part on the board wired to a GPIO.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OnBoard {
    /// The GPIO.
    pub gpio: u8,
    /// What is connected to it.
    pub part: &'static str,
}

/// One supported board.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Board {
    /// Human name.
    pub name: &'static str,
    /// The cargo feature that selects it.
    pub feature: &'static str,
    /// Its chip.
    pub chip: Chip,
    /// GPIO of the UART TX line (ESP32 TX → TinyBMS RX).
    pub bms_tx: u8,
    /// GPIO of the UART RX line (TinyBMS TX → ESP32 RX).
    pub bms_rx: u8,
    /// GPIO of the CAN transceiver's TXD (the TWAI output, feature `can`).
    pub can_tx: u8,
    /// GPIO of the CAN transceiver's RXD (the TWAI input, feature `can`).
    pub can_rx: u8,
    /// The defmt log path of the board's ready-made image and alias. On a
    /// board whose connector is a USB-UART bridge, the host link takes UART0
    /// and the log lines reach the connector as its `log` lines.
    pub log: LogPath,
    /// Where the host link runs.
    pub host: HostWire,
    /// GPIOs on the board's pin headers.
    pub header: &'static [u8],
    /// GPIOs wired to parts on the board.
    pub on_board: &'static [OnBoard],
    /// Header labels of the four signal pins, in the order TX, RX, CAN TX, CAN RX.
    pub labels: [&'static str; 4],
}

/// Which signal of the bridge a pin carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// UART TX to the BMS.
    BmsTx,
    /// UART RX from the BMS.
    BmsRx,
    /// CAN TXD.
    CanTx,
    /// CAN RXD.
    CanRx,
}

impl Role {
    /// Short name.
    pub const fn name(self) -> &'static str {
        match self {
            Role::BmsTx => "BMS UART TX",
            Role::BmsRx => "BMS UART RX",
            Role::CanTx => "CAN TX",
            Role::CanRx => "CAN RX",
        }
    }
}

/// Why a board entry is wrong.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PinError {
    /// The pin cannot be used on this chip.
    Chip {
        /// Which signal.
        role: Role,
        /// The GPIO.
        gpio: u8,
        /// Why.
        why: Restriction,
    },
    /// The pin is not on the board's header.
    NotOnHeader {
        /// Which signal.
        role: Role,
        /// The GPIO.
        gpio: u8,
    },
    /// The pin drives or reads a part on the board.
    OnBoard {
        /// Which signal.
        role: Role,
        /// The GPIO.
        gpio: u8,
        /// The part.
        part: &'static str,
    },
    /// Two signals share a pin.
    Shared {
        /// The first signal.
        first: Role,
        /// The second signal.
        second: Role,
        /// The GPIO.
        gpio: u8,
    },
}

impl PinError {
    /// A fixed message (usable in a `const` panic).
    pub const fn message(&self) -> &'static str {
        match self {
            PinError::Chip { why, .. } => match why {
                Restriction::Missing => "board table: a signal pin does not exist on the chip",
                Restriction::Strapping => "board table: a signal pin is a strapping pin",
                Restriction::Flash => "board table: a signal pin is an SPI flash pin",
                Restriction::UsbJtag => "board table: a signal pin is a USB-Serial-JTAG pin",
                Restriction::Uart0 => "board table: a signal pin is a UART0 console pin",
            },
            PinError::NotOnHeader { .. } => {
                "board table: a signal pin is not on the board's header"
            }
            PinError::OnBoard { .. } => {
                "board table: a signal pin is wired to a part on the board (LED, button, sensor)"
            }
            PinError::Shared { .. } => "board table: two signals share a pin",
        }
    }
}

const fn contains(list: &[u8], gpio: u8) -> bool {
    let mut rest = list;
    while let [first, tail @ ..] = rest {
        if *first == gpio {
            return true;
        }
        rest = tail;
    }
    false
}

const fn part_at(list: &[OnBoard], gpio: u8) -> Option<&'static str> {
    let mut rest = list;
    while let [first, tail @ ..] = rest {
        if first.gpio == gpio {
            return Some(first.part);
        }
        rest = tail;
    }
    None
}

impl Board {
    /// The GPIO of the board's BOOT button (from [`Board::on_board`]), the
    /// physical way out of read-only ([`crate::config::button`]).
    pub const fn boot_button(&self) -> Option<u8> {
        let mut rest = self.on_board;
        while let [first, tail @ ..] = rest {
            if matches!(first.part.as_bytes(), b"BOOT button") {
                return Some(first.gpio);
            }
            rest = tail;
        }
        None
    }

    /// The four signal pins with their roles.
    pub const fn signals(&self) -> [(Role, u8); 4] {
        [
            (Role::BmsTx, self.bms_tx),
            (Role::BmsRx, self.bms_rx),
            (Role::CanTx, self.can_tx),
            (Role::CanRx, self.can_rx),
        ]
    }
}

/// Checks one board: see the module documentation. `const`, so it runs at
/// compile time for every board in [`BOARDS`].
pub const fn check(board: &Board) -> Result<(), PinError> {
    let signals = board.signals();
    let mut rest: &[(Role, u8)] = &signals;
    while let [(role, gpio), tail @ ..] = rest {
        let (role, gpio) = (*role, *gpio);
        if let Some(why) = board.chip.restriction(gpio) {
            return Err(PinError::Chip { role, gpio, why });
        }
        if let Some(part) = part_at(board.on_board, gpio) {
            return Err(PinError::OnBoard { role, gpio, part });
        }
        if !contains(board.header, gpio) {
            return Err(PinError::NotOnHeader { role, gpio });
        }
        let mut others = tail;
        while let [(other, g), more @ ..] = others {
            if *g == gpio {
                return Err(PinError::Shared {
                    first: role,
                    second: *other,
                    gpio,
                });
            }
            others = more;
        }
        rest = tail;
    }
    Ok(())
}

/// [`check`], as a compile-time assertion: meant for `const _: () = …;` items,
/// where a failure is a build error carrying [`PinError::message`].
pub const fn assert_valid(board: &Board) {
    let result = check(board);
    let message = match result {
        Err(e) => e.message(),
        Ok(()) => "",
    };
    assert!(result.is_ok(), "{}", message);
}

// ---------------------------------------------------------------------------
// The boards
// ---------------------------------------------------------------------------

/// Espressif ESP32-C3-DevKitM-1 (ESP32-C3-MINI-1 module).
///
/// Source: esp-dev-kits "ESP32-C3-DevKitM-1" user guide, Header Block J1/J3 and
/// Description of Components (RGB LED on GPIO8; the Micro-USB port goes to a
/// USB-to-UART bridge on UART0). GPIO18/19 are on J3 pins 13/14: RTT and the
/// USB-Serial-JTAG need a second USB cable wired there, hence the host link on
/// UART0, with the bridge's log lines in it.
pub const C3_DEVKITM_1: Board = Board {
    name: "ESP32-C3-DevKitM-1",
    feature: "board-c3-devkitm-1",
    chip: Chip::Esp32c3,
    bms_tx: 7,
    bms_rx: 6,
    can_tx: 4,
    can_rx: 5,
    log: LogPath::Rtt,
    host: HostWire::Uart0,
    header: &[0, 1, 2, 3, 10, 21, 20, 9, 8, 7, 6, 5, 4, 18, 19],
    on_board: &[
        OnBoard {
            gpio: 8,
            part: "addressable RGB LED",
        },
        OnBoard {
            gpio: 9,
            part: "BOOT button",
        },
    ],
    labels: ["J3 IO7", "J3 IO6", "J3 IO4", "J3 IO5"],
};

/// "ESP32-C3 SuperMini" (generic, many makers).
///
/// No manufacturer document: pins from widely copied community pinouts —
/// header GPIO0-10, GPIO20 (RX), GPIO21 (TX); blue LED on GPIO8 (active low);
/// BOOT button on GPIO9; USB-C wired to the chip's USB-Serial-JTAG. *Uncertain*:
/// clones differ (one report of the LED on another pin); check your board.
pub const C3_SUPERMINI: Board = Board {
    name: "ESP32-C3 SuperMini",
    feature: "board-c3-supermini",
    chip: Chip::Esp32c3,
    bms_tx: 7,
    bms_rx: 6,
    can_tx: 4,
    can_rx: 5,
    log: LogPath::Rtt,
    host: HostWire::UsbSerialJtag,
    header: &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 20, 21],
    on_board: &[
        OnBoard {
            gpio: 8,
            part: "blue LED (uncertain on clones)",
        },
        OnBoard {
            gpio: 9,
            part: "BOOT button",
        },
    ],
    labels: ["7", "6", "4", "5"],
};

/// Seeed Studio XIAO ESP32C3.
///
/// Source: Seeed wiki pin list (D0=GPIO2, D1=GPIO3, D2=GPIO4, D3=GPIO5,
/// D4=GPIO6, D5=GPIO7, D6=GPIO21/TX, D7=GPIO20/RX, D8=GPIO8, D9=GPIO9 with the
/// BOOT button and pull-up, D10=GPIO10); no user LED (the charge LED is not on
/// a GPIO); USB-C to the chip's USB-Serial-JTAG.
pub const XIAO_ESP32C3: Board = Board {
    name: "Seeed XIAO ESP32C3",
    feature: "board-xiao-esp32c3",
    chip: Chip::Esp32c3,
    bms_tx: 7,
    bms_rx: 6,
    can_tx: 4,
    can_rx: 5,
    log: LogPath::Rtt,
    host: HostWire::UsbSerialJtag,
    header: &[2, 3, 4, 5, 6, 7, 21, 20, 8, 9, 10],
    on_board: &[OnBoard {
        gpio: 9,
        part: "BOOT button",
    }],
    labels: ["D5", "D4", "D2", "D3"],
};

/// Espressif ESP32-C3-DevKit-RUST-1.
///
/// Source: esp-rs/esp-rust-board README (pin layout tables; GPIO devices: WS2812
/// LED GPIO2, LED GPIO7, button GPIO9; I2C SDA GPIO10 / SCL GPIO8 to the
/// ICM-42670-P IMU and SHTC3 sensor); USB-C to the chip's USB-Serial-JTAG.
/// GPIO7 (the default C3 TX) drives the LED here, so the UART moves to 5/6.
pub const C3_RUST_1: Board = Board {
    name: "ESP32-C3-DevKit-RUST-1",
    feature: "board-c3-rust-1",
    chip: Chip::Esp32c3,
    bms_tx: 5,
    bms_rx: 6,
    can_tx: 4,
    can_rx: 3,
    log: LogPath::Rtt,
    host: HostWire::UsbSerialJtag,
    header: &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 18, 19, 20, 21],
    on_board: &[
        OnBoard {
            gpio: 2,
            part: "WS2812 RGB LED",
        },
        OnBoard {
            gpio: 7,
            part: "LED",
        },
        OnBoard {
            gpio: 8,
            part: "I2C SCL (IMU, SHTC3)",
        },
        OnBoard {
            gpio: 9,
            part: "BOOT button",
        },
        OnBoard {
            gpio: 10,
            part: "I2C SDA (IMU, SHTC3)",
        },
    ],
    labels: ["IO5", "IO6", "IO4", "IO3"],
};

/// WEMOS LOLIN C3 Mini (v1.0.0 and v2.1.0).
///
/// Sources: RIOT's esp32c3-wemos-mini board (v2.1.0: WS2812B RGB LED on GPIO7;
/// v1.0.0: LED on GPIO7; button GPIO9) and its Arduino pin map, the
/// arduino-esp32 `lolin_c3_mini` variant as summarised by frugal-iot (I2C
/// SCL=10 SDA=8, LED=7). Header GPIO0-10, 20, 21 is *uncertain* (no table from
/// WEMOS was at hand). USB-C to the chip's USB-Serial-JTAG.
pub const LOLIN_C3_MINI: Board = Board {
    name: "LOLIN C3 Mini",
    feature: "board-lolin-c3-mini",
    chip: Chip::Esp32c3,
    bms_tx: 5,
    bms_rx: 6,
    can_tx: 4,
    can_rx: 3,
    log: LogPath::Rtt,
    host: HostWire::UsbSerialJtag,
    header: &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 20, 21],
    on_board: &[
        OnBoard {
            gpio: 7,
            part: "WS2812B RGB LED (v2.1.0) / LED (v1.0.0)",
        },
        OnBoard {
            gpio: 9,
            part: "BOOT button",
        },
    ],
    labels: ["5", "6", "4", "3"],
};

/// Espressif ESP32-C6-DevKitC-1 (ESP32-C6-WROOM-1 module).
///
/// Source: esp-dev-kits "ESP32-C6-DevKitC-1" user guide, Header Block J1/J3
/// (RGB LED on GPIO8; MTMS/GPIO4, MTDI/GPIO5, GPIO8, GPIO9, GPIO15 are strapping
/// pins). Two USB-C ports: "USB" goes to the chip's USB-Serial-JTAG (RTT), "UART"
/// to a USB-UART bridge on UART0. The earlier C6 pins GPIO4/5 were strapping
/// pins; the bridge now uses the same GPIOs as on the XIAO ESP32C6.
pub const C6_DEVKITC_1: Board = Board {
    name: "ESP32-C6-DevKitC-1",
    feature: "board-c6-devkitc-1",
    chip: Chip::Esp32c6,
    bms_tx: 23,
    bms_rx: 22,
    can_tx: 2,
    can_rx: 21,
    log: LogPath::Rtt,
    host: HostWire::UsbSerialJtag,
    header: &[
        4, 5, 6, 7, 0, 1, 8, 10, 11, 2, 3, 16, 17, 15, 23, 22, 21, 20, 19, 18, 9, 13, 12,
    ],
    on_board: &[
        OnBoard {
            gpio: 8,
            part: "addressable RGB LED",
        },
        OnBoard {
            gpio: 9,
            part: "BOOT button",
        },
    ],
    labels: ["J3 23", "J3 22", "J1 2", "J3 21"],
};

/// Seeed Studio XIAO ESP32C6.
///
/// Sources: Seeed wiki (pin list: D0=GPIO0, D1=GPIO1, D2=GPIO2, D3=GPIO21,
/// D4=GPIO22, D5=GPIO23, D6=GPIO16/TX, D7=GPIO17/RX, D8=GPIO19, D9=GPIO20,
/// D10=GPIO18; "WiFi usage": GPIO3 enables the RF switch, GPIO14 selects the
/// antenna), RIOT's board page (user LED on GPIO15). GPIO4/5 (the old C6 pins)
/// are not on its header. USB-C to the chip's USB-Serial-JTAG. The UART and CAN
/// sit on the same header positions (D5/D4, D2/D3) as on the XIAO ESP32C3.
pub const XIAO_ESP32C6: Board = Board {
    name: "Seeed XIAO ESP32C6",
    feature: "board-xiao-esp32c6",
    chip: Chip::Esp32c6,
    bms_tx: 23,
    bms_rx: 22,
    can_tx: 2,
    can_rx: 21,
    log: LogPath::Rtt,
    host: HostWire::UsbSerialJtag,
    header: &[0, 1, 2, 21, 22, 23, 16, 17, 19, 20, 18],
    on_board: &[
        OnBoard {
            gpio: 3,
            part: "RF switch enable",
        },
        OnBoard {
            gpio: 9,
            part: "BOOT button",
        },
        OnBoard {
            gpio: 14,
            part: "antenna select",
        },
        OnBoard {
            gpio: 15,
            part: "user LED",
        },
    ],
    labels: ["D5", "D4", "D2", "D3"],
};

/// A board's short key (its feature without `board-`: `c3-supermini`) from
/// its name in the table (`ESP32-C3 SuperMini`); a name the table does not
/// hold (the desktop's `simulated`) is its own key. Update files name
/// boards by key.
pub fn key_of(name: &str) -> &str {
    BOARDS.iter().find(|b| b.name == name).map_or(name, |b| {
        b.feature.strip_prefix("board-").unwrap_or(b.feature)
    })
}

/// Every supported board.
pub const BOARDS: &[Board] = &[
    C3_DEVKITM_1,
    C3_SUPERMINI,
    XIAO_ESP32C3,
    C3_RUST_1,
    LOLIN_C3_MINI,
    C6_DEVKITC_1,
    XIAO_ESP32C6,
];

/// Compile-time check of the whole table: a wrong entry fails every build.
const _: () = {
    let mut rest = BOARDS;
    while let [first, tail @ ..] = rest {
        assert_valid(first);
        rest = tail;
    }
};

// ---------------------------------------------------------------------------
// The selected board (firmware builds)
// ---------------------------------------------------------------------------

/// Number of `board-…` features enabled.
const SELECTED_COUNT: usize = cfg!(feature = "board-c3-devkitm-1") as usize
    + cfg!(feature = "board-c3-supermini") as usize
    + cfg!(feature = "board-xiao-esp32c3") as usize
    + cfg!(feature = "board-c3-rust-1") as usize
    + cfg!(feature = "board-lolin-c3-mini") as usize
    + cfg!(feature = "board-c6-devkitc-1") as usize
    + cfg!(feature = "board-xiao-esp32c6") as usize;

const _: () = assert!(
    matches!(SELECTED_COUNT, 0 | 1),
    "select one board feature only (board-…); use --no-default-features to replace the default board"
);

#[cfg(all(
    feature = "chip",
    not(any(
        feature = "board-c3-devkitm-1",
        feature = "board-c3-supermini",
        feature = "board-xiao-esp32c3",
        feature = "board-c3-rust-1",
        feature = "board-lolin-c3-mini",
        feature = "board-c6-devkitc-1",
        feature = "board-xiao-esp32c6"
    ))
))]
compile_error!(
    "a chip feature is enabled but no board: enable one `board-…` feature (see docs/boards.md)"
);

/// The board chosen by the `board-…` feature.
#[cfg(feature = "board-c3-devkitm-1")]
pub const SELECTED: Board = C3_DEVKITM_1;
/// The board chosen by the `board-…` feature.
#[cfg(feature = "board-c3-supermini")]
pub const SELECTED: Board = C3_SUPERMINI;
/// The board chosen by the `board-…` feature.
#[cfg(feature = "board-xiao-esp32c3")]
pub const SELECTED: Board = XIAO_ESP32C3;
/// The board chosen by the `board-…` feature.
#[cfg(feature = "board-c3-rust-1")]
pub const SELECTED: Board = C3_RUST_1;
/// The board chosen by the `board-…` feature.
#[cfg(feature = "board-lolin-c3-mini")]
pub const SELECTED: Board = LOLIN_C3_MINI;
/// The board chosen by the `board-…` feature.
#[cfg(feature = "board-c6-devkitc-1")]
pub const SELECTED: Board = C6_DEVKITC_1;
/// The board chosen by the `board-…` feature.
#[cfg(feature = "board-xiao-esp32c6")]
pub const SELECTED: Board = XIAO_ESP32C6;
