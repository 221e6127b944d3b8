//! TinyBMS firmware — chip-specific shell (ESP32-C3 / ESP32-C6).
//!
//! Structure: init (clocks, esp-rtos, watchdog, UART1) → spawn `uart_task(rx, tx, wdt)`
//! and `log_task()`. The bridge logic lives in the library crate (`tinybms_firmware`)
//! and will be wired in here later.
//!
//! Logging: defmt over RTT (`defmt-rtt`), read with `probe-rs run` (see .cargo/config.toml).

#![no_std]
#![no_main]

#[cfg(all(feature = "esp32c3", feature = "esp32c6"))]
compile_error!("features `esp32c3` and `esp32c6` are mutually exclusive");

use defmt::{info, warn};
use defmt_rtt as _; // defmt global logger (RTT transport)
use embassy_executor::Spawner;
use embassy_futures::select::{select, Either};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::watch::Watch;
use embassy_time::{Duration, Instant, Ticker, Timer};
use esp_backtrace as _; // panic handler (prints via defmt)
use esp_hal::clock::CpuClock;
use esp_hal::gpio::Pin;
use esp_hal::peripherals::TIMG0;
use esp_hal::timer::timg::{MwdtStage, TimerGroup, Wdt};
use esp_hal::uart::{Config as UartConfig, Uart, UartRx, UartTx};
use esp_hal::Async;

// ESP-IDF 2nd-stage bootloader requires an application descriptor in the image.
esp_bootloader_esp_idf::esp_app_desc!();

// ---------------------------------------------------------------------------
// Board wiring (TinyBMS UART, 115200 8N1, 3.3 V logic)
// ---------------------------------------------------------------------------
//
// ESP32-C3: GPIO20/21 are the UART0 console pins, GPIO18/19 are USB (USB-Serial-JTAG,
//           used by probe-rs), GPIO2/8/9 are strapping pins, GPIO12-17 are SPI flash.
//           → TX = GPIO7, RX = GPIO6 (pad-JTAG pins, free when the built-in USB-JTAG is used).
// ESP32-C6: GPIO16/17 are the UART0 console pins, GPIO12/13 are USB, GPIO8/9/15 are
//           strapping pins, GPIO24-30 are SPI flash.
//           → TX = GPIO5, RX = GPIO4 (MTDI/MTMS: pad-JTAG, only sampled at reset for SDIO
//           slave timing; free when the built-in USB-JTAG is used).
//
// The `bms_uart_pins!` macro must select the same GPIOs as the constants (checked at boot).

/// GPIO number of the UART TX line (ESP32 TX → TinyBMS RX).
#[cfg(feature = "esp32c3")]
pub const BMS_UART_TX_GPIO: u8 = 7;
/// GPIO number of the UART RX line (TinyBMS TX → ESP32 RX).
#[cfg(feature = "esp32c3")]
pub const BMS_UART_RX_GPIO: u8 = 6;
#[cfg(feature = "esp32c3")]
macro_rules! bms_uart_pins {
    ($p:ident) => {
        ($p.GPIO7, $p.GPIO6)
    };
}

/// GPIO number of the UART TX line (ESP32 TX → TinyBMS RX).
#[cfg(feature = "esp32c6")]
pub const BMS_UART_TX_GPIO: u8 = 5;
/// GPIO number of the UART RX line (TinyBMS TX → ESP32 RX).
#[cfg(feature = "esp32c6")]
pub const BMS_UART_RX_GPIO: u8 = 4;
#[cfg(feature = "esp32c6")]
macro_rules! bms_uart_pins {
    ($p:ident) => {
        ($p.GPIO5, $p.GPIO4)
    };
}

/// TinyBMS UART baud rate (8N1 is the esp-hal default frame format).
const BMS_BAUDRATE: u32 = 115_200;
/// Poll period of the UART task.
const POLL_PERIOD: Duration = Duration::from_millis(250);
/// How long to wait for response bytes after a request.
const RESPONSE_DEADLINE: Duration = Duration::from_millis(100);
/// Watchdog timeout (MWDT stage 0 → system reset). Fed once per poll cycle.
const WDT_TIMEOUT: esp_hal::time::Duration = esp_hal::time::Duration::from_secs(4);

/// Placeholder request frame (TinyBMS "read" style command).
const REQUEST: [u8; 4] = [0xAA, 0x14, 0x7F, 0x1F];

/// Snapshot published by the UART task.
#[derive(Clone, Copy, Default, defmt::Format)]
struct UartStats {
    cycles: u32,
    last_rx_len: usize,
    rx_errors: u32,
    timeouts: u32,
}

/// Shared state: one sender (uart_task), up to 2 receivers.
static STATS: Watch<CriticalSectionRawMutex, UartStats, 2> = Watch::new();

#[esp_rtos::main]
async fn main(spawner: Spawner) {
    let config = esp_hal::Config::default().with_cpu_clock(CpuClock::max());
    let p = esp_hal::init(config);

    info!("tinybms-firmware {} starting", env!("CARGO_PKG_VERSION"));

    // esp-rtos: TIMG0 timer0 as time base + FROM_CPU_INTR0 software interrupt.
    let timg0 = TimerGroup::new(p.TIMG0);
    esp_rtos::start(timg0.timer0, p.FROM_CPU_INTR0);

    // Main watchdog of TIMG0 (esp_hal::init disabled it; we re-arm it).
    let mut wdt = timg0.wdt;
    wdt.set_timeout(MwdtStage::Stage0, WDT_TIMEOUT);
    wdt.enable();

    // UART1 to the TinyBMS.
    let (tx_pin, rx_pin) = bms_uart_pins!(p);
    assert!(tx_pin.number() == BMS_UART_TX_GPIO && rx_pin.number() == BMS_UART_RX_GPIO);
    let uart = Uart::new(p.UART1, UartConfig::default().with_baudrate(BMS_BAUDRATE))
        .expect("UART1 config")
        .with_tx(tx_pin)
        .with_rx(rx_pin)
        .into_async();
    let (rx, tx) = uart.split();
    info!(
        "UART1 {} 8N1 TX=GPIO{} RX=GPIO{}",
        BMS_BAUDRATE, BMS_UART_TX_GPIO, BMS_UART_RX_GPIO
    );

    spawner.spawn(uart_task(rx, tx, wdt).expect("spawn uart_task"));
    spawner.spawn(log_task().expect("spawn log_task"));
}

/// Periodically sends `REQUEST` and collects whatever arrives before the deadline.
#[embassy_executor::task]
async fn uart_task(
    mut rx: UartRx<'static, Async>,
    mut tx: UartTx<'static, Async>,
    mut wdt: Wdt<TIMG0<'static>>,
) {
    let sender = STATS.sender();
    let mut stats = UartStats::default();
    let mut buf = [0u8; 64];
    let mut ticker = Ticker::every(POLL_PERIOD);

    loop {
        wdt.feed();
        stats.cycles = stats.cycles.wrapping_add(1);

        if let Err(e) = tx.write_async(&REQUEST).await {
            warn!("uart tx error: {}", e);
        }
        if let Err(e) = tx.flush_async().await {
            warn!("uart flush error: {}", e);
        }

        // Collect bytes until the buffer is full or the deadline passes.
        // `read_async` is cancellation-safe, so racing it against a timer is fine.
        let deadline = Instant::now() + RESPONSE_DEADLINE;
        let mut len = 0;
        while len < buf.len() {
            match select(rx.read_async(&mut buf[len..]), Timer::at(deadline)).await {
                Either::First(Ok(n)) => len += n,
                Either::First(Err(e)) => {
                    warn!("uart rx error: {}", e);
                    stats.rx_errors = stats.rx_errors.wrapping_add(1);
                    break;
                }
                Either::Second(()) => break,
            }
        }

        if len == 0 {
            stats.timeouts = stats.timeouts.wrapping_add(1);
            warn!("no response within {} ms", RESPONSE_DEADLINE.as_millis());
        } else {
            info!("received {} bytes: {=[u8]:02x}", len, &buf[..len]);
        }
        stats.last_rx_len = len;
        sender.send(stats);

        ticker.next().await;
    }
}

/// Logs a summary whenever the UART task publishes new stats (rate-limited).
#[embassy_executor::task]
async fn log_task() {
    let Some(mut receiver) = STATS.receiver() else {
        warn!("STATS watch has no free receiver slot");
        return;
    };
    loop {
        let stats = receiver.changed().await;
        if stats.cycles % 20 == 0 {
            info!("stats: {}", stats);
        }
    }
}
