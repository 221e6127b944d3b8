//! TinyBMS firmware — the chip shell (ESP32-C3 / ESP32-C6): init, then one task
//! per wire. Everything that decides anything is in the library
//! (`tinybms_firmware`, sans-IO, tested on the host); the modules here only move
//! bytes, frames and time between the peripherals and it.
//!
//! | module | task | wire |
//! | --- | --- | --- |
//! | [`station`] | `station_task` | UART1 to the TinyBMS; owns the library's `Station` |
//! | [`can`] | `can_task` | TWAI to the inverter (feature `can`): a pump |
//! | [`usb`] | `usb_rx_task`, `usb_tx_task` (or `uart0_…`) | the host link's wire (feature `host-link`): pumps |
//! | [`button`] | `button_task` | the BOOT button's samples (feature `host-link`) |
//! | [`network`] | `wifi_task`, `net_task`, `mqtt_task` | Wi-Fi and MQTT to Home Assistant (feature `wifi`) |
//! | [`store`] | — | the configuration record in the `nvs` flash partition |
//! | [`log`] | — | log lines → defmt (the words come from the library) |
//! | [`wires`] | — | every static the tasks share, each with its role |
//! | [`ota`] | — | updates: `otadata` at boot, the slot's flash work, the restart |
//! | [`panic`] | — | the panic handler: backtrace, then reset |
//!
//! The station task owns the `Station` and does what it says; the other tasks
//! only move bytes and frames between a driver and the queues in [`wires`].
//! The station task never waits on another task.
//!
//! Every task runs on `main`'s executor, whose esp-rtos thread gets the highest
//! task priority ([`MAIN_PRIORITY`]) before anything else starts. esp-rtos would
//! start it at 0, below the Wi-Fi driver's own threads (the IDF blob asks 23),
//! which can keep the CPU for up to a second while the station connects
//! (esp-hal issue #4940); above them, the driver runs only while the executor
//! waits, so it cannot delay a BMS request or a CAN frame. (An interrupt
//! executor would preempt them too, but would run the bridge on whatever task
//! stack it interrupts, the radio's small ones included.) Not measured on a unit.
//!
//! Board: the pins come from `tinybms_firmware::boards::SELECTED`, chosen by one
//! `board-…` feature and checked at compile time. Logging: defmt over RTT
//! (`log-rtt`, read with `probe-rs run`) or defmt frames on UART0 (`log-uart`,
//! read with `espflash flash --monitor --log-format defmt`). See docs/boards.md.

#![no_std]
#![no_main]

#[cfg(all(feature = "esp32c3", feature = "esp32c6"))]
compile_error!("features `esp32c3` and `esp32c6` are mutually exclusive");
#[cfg(all(feature = "log-rtt", feature = "log-uart"))]
compile_error!("features `log-rtt` and `log-uart` are mutually exclusive (use --no-default-features to drop the default `log-rtt`)");
#[cfg(not(any(feature = "log-rtt", feature = "log-uart")))]
compile_error!(
    "select a log path: feature `log-rtt` (RTT via probe-rs) or `log-uart` (UART0 via espflash)"
);

#[cfg(feature = "host-link")]
mod button;
#[cfg(feature = "can")]
mod can;
mod log;
#[cfg(feature = "wifi")]
mod network;
mod ota;
mod panic;
mod station;
mod store;
mod usb;
mod wires;

#[cfg(feature = "log-rtt")]
use defmt_rtt as _; // defmt global logger: RTT
use embassy_executor::{SpawnError, SpawnToken, Spawner};
use embassy_time::Instant;
use esp_hal::clock::CpuClock;
use esp_hal::timer::timg::{MwdtStage, TimerGroup};
#[cfg(feature = "log-uart")]
use esp_println as _; // defmt global logger: UART0, espflash's defmt framing
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::boards::{self, Board, Chip, LogPath};
use tinybms_firmware::station::{Setup, Station};
use tinybms_firmware::text::Boot;

// ESP-IDF 2nd-stage bootloader requires an application descriptor in the image.
// Its version is the one the image reports (`TINYBMS_VERSION` aware), its
// project name the build (what `hello` says it was built from): `tinybms
// sign` reads both from here, so an update file's header is the image's own.
esp_bootloader_esp_idf::esp_app_desc!(
    tinybms_firmware::identity::FIRMWARE,
    tinybms_firmware::identity::BUILD,
    esp_bootloader_esp_idf::BUILD_TIME,
    esp_bootloader_esp_idf::BUILD_DATE,
    esp_bootloader_esp_idf::ESP_IDF_COMPATIBLE_VERSION,
    esp_bootloader_esp_idf::MMU_PAGE_SIZE,
    0,
    u16::MAX,
    esp_bootloader_esp_idf::SECURE_VERSION
);

/// The board this image is built for (`board-…` feature; pins in
/// `firmware/src/boards.rs`).
const BOARD: Board = boards::SELECTED;
// The library checks the whole table; checked again here for the board this image
// actually uses (the error then points at this line).
const _: () = boards::assert_valid(&BOARD);
#[cfg(feature = "esp32c3")]
const _: () = assert!(
    matches!(BOARD.chip, Chip::Esp32c3),
    "the selected board is not an ESP32-C3 board"
);
#[cfg(feature = "esp32c6")]
const _: () = assert!(
    matches!(BOARD.chip, Chip::Esp32c6),
    "the selected board is not an ESP32-C6 board"
);

/// Where this image sends its logs.
const LOG_PATH: LogPath = if cfg!(feature = "log-uart") {
    LogPath::Uart0
} else {
    LogPath::Rtt
};

// On a board whose connector is a USB-UART bridge, the host link takes UART0:
// defmt frames there would be mixed into its lines.
const _: () = assert!(
    !(cfg!(feature = "log-uart")
        && cfg!(feature = "host-link")
        && matches!(BOARD.host, boards::HostWire::Uart0)),
    "this board's host link runs on UART0: use `log-rtt` (its log lines reach the host link as `log` lines)"
);

/// Watchdog timeout (MWDT stage 0 → system reset), the library's. Fed by the
/// station task, which never sleeps longer than the library's bound.
const WDT_TIMEOUT: esp_hal::time::Duration =
    esp_hal::time::Duration::from_micros(tinybms_firmware::station::pumps::WATCHDOG_US);

/// esp-rtos task priority of `main`'s thread, which runs every task (module
/// docs): esp-rtos's highest.
const MAIN_PRIORITY: usize = 31;

/// Who this image is (the host link's `hello`, Home Assistant's diagnostics).
const IDENTITY: tinybms_firmware::identity::Identity = tinybms_firmware::identity::Identity {
    chip: BOARD.chip.name(),
    board: BOARD.name,
    firmware: tinybms_firmware::identity::FIRMWARE,
    features: tinybms_firmware::identity::Features {
        can: cfg!(feature = "can"),
        host_link: cfg!(feature = "host-link"),
        wifi: cfg!(feature = "wifi"),
        store: cfg!(feature = "store"),
    },
};
/// The features built in, in the image's bytes, for `tinybms sign` (an
/// update file's header names the image's own features).
#[used]
static FEATURES_TAG: [u8; tinybms_firmware::identity::FEATURES_TAG_LEN] = IDENTITY.features.tag();

#[esp_rtos::main]
async fn main(spawner: Spawner) {
    // Referenced, so that no linker drops it.
    core::hint::black_box(&FEATURES_TAG);
    // Watchdog coverage at boot:
    //  - until `esp_hal::init` disables it, the 2nd-stage bootloader's RTC watchdog
    //    (ESP-IDF default CONFIG_BOOTLOADER_WDT_ENABLE, 9 s; depends on the
    //    bootloader image espflash/probe-rs flash — not verified on hardware);
    //  - any panic, from the first instruction on, resets through the panic handler;
    //  - a hang after `init`: the MWDT, armed right below before anything else runs.
    let config = esp_hal::Config::default().with_cpu_clock(CpuClock::max());
    let p = esp_hal::init(config);

    // Main watchdog of TIMG0 (esp_hal::init disabled it; re-armed before any boot
    // code that can fail or wait).
    let timg0 = TimerGroup::new(p.TIMG0);
    let mut wdt = timg0.wdt;
    wdt.set_timeout(MwdtStage::Stage0, WDT_TIMEOUT);
    wdt.enable();

    // esp-rtos: TIMG0 timer0 as time base + FROM_CPU_INTR0 software interrupt.
    esp_rtos::start(timg0.timer0, p.FROM_CPU_INTR0);
    esp_rtos::CurrentThreadHandle::get().set_priority(MAIN_PRIORITY);

    // Updates: otadata, the trial's mark or the rollback (which restarts
    // here), before anything runs.
    let (mut chip_ota, ota) = ota::boot();
    // The configuration record, before any task that runs with it. (Reading
    // flash stops the CPU only for microseconds; nothing runs yet anyway.)
    let (store, loaded, site) = store::open(p.FLASH);
    let station = wires::STATION.init(Station::new(
        Setup {
            timing: Timing::default(),
            identity: IDENTITY,
            inverter: None,
        },
        loaded,
        now_us(),
    ));
    #[cfg(feature = "store")]
    station.set_store_site(site);
    #[cfg(not(feature = "store"))]
    let _ = site;
    station.set_ota(ota);
    // The history: its partition and where its rings stand (reads only).
    let history = chip_ota.open_history();
    if let Some(p) = history.problem() {
        defmt::warn!("history: {=str}", p);
    }
    station.set_history(
        now_us(),
        history,
        esp_hal::system::reset_reason().map(|r| r as u8),
    );
    // The boot lines go to defmt and stay in the host link for every host
    // (`tinybms log PORT` shows them however late it connects).
    log::boot(
        station,
        &Boot::Image {
            log: Some(LOG_PATH),
        },
    );
    let running = station.config().running();

    #[cfg(feature = "can")]
    let can = can::start(spawner, p.TWAI0, &running.inverter());
    let host = usb::start(spawner, p.USB_DEVICE, p.UART0, running);
    #[cfg(feature = "host-link")]
    button::start(spawner);
    // Nothing here waits for the radio: `network::start` only prepares it and
    // spawns its start, which runs on a thread below this one's once the
    // station task (spawned last, first to run) waits.
    #[cfg(feature = "wifi")]
    let name = network::start(spawner, p.WIFI, running, IDENTITY);
    #[cfg(not(feature = "wifi"))]
    let name: Option<heapless::String<32>> =
        (!running.hostname.is_empty()).then(|| running.hostname.clone());
    #[cfg(feature = "can")]
    log::boot(station, &can);
    if let Some(host) = host {
        log::boot(station, &host);
    }
    if let Some(name) = name {
        station.set_network_name(&name);
    }
    station::start(spawner, p.UART1, wdt, station, store, chip_ota);
}

/// Spawns a task. A pool without a free slot is a bug in this shell: it panics
/// (the backtrace shows which call), not through `expect`, which would link
/// `SpawnError`'s `Debug` for a message never printed.
fn spawn<S>(spawner: Spawner, task: Result<SpawnToken<S>, SpawnError>) {
    match task {
        Ok(token) => spawner.spawn(token),
        Err(_) => panic!("spawn"),
    }
}

/// Microseconds since boot: the library's `Instant`.
fn now_us() -> u64 {
    Instant::now().as_micros()
}
