//! The bridge task: bytes and time between UART1 and the sans-IO bridge, which
//! it owns (with the host link and the configuration next to it). It publishes
//! every new snapshot to [`crate::TELEMETRY`], logs the bridge's reports, hands
//! changes of the configuration to the other tasks and saves it to flash when
//! the BMS link is quiet.

use defmt::{info, warn};
use embassy_executor::Spawner;
use embassy_futures::select::{select3, Either3};
use embassy_time::{Duration, Instant, Timer};
use esp_hal::gpio::AnyPin;
use esp_hal::peripherals::{TIMG0, UART1};
use esp_hal::timer::timg::Wdt;
use esp_hal::uart::{Config as UartConfig, RxConfig, RxError, Uart, UartRx, UartTx};
use esp_hal::Async;
use tinybms_firmware::bms::profile;
use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::bridge::Step;
use tinybms_firmware::config::state::ConfigState;

use tinybms_firmware::Bridge;

use crate::{log, now_us, spawn, store, usb, SharedSnapshot, BOARD, TELEMETRY};

/// TinyBMS UART baud rate (8N1 is the esp-hal default frame format; Rev D §1).
const BMS_BAUDRATE: u32 = 115_200;
/// UART1 RX FIFO "full" interrupt level, bytes (of the 128-byte FIFO).
///
/// esp-hal's default is 120, which leaves 8 bytes (≈ 0.7 ms at 115 200 Bd) between
/// the interrupt and an overflow; replies longer than 120 bytes exist (0x03 with
/// ≥ 58 registers, packetized events). An overflow resets the FIFO: a CRC error
/// and a retry. At 64 the task has 64 bytes ≈ 5.5 ms to read (issue 11).
const RX_FIFO_FULL_THRESHOLD: u16 = 64;
/// Most `read_buffered` calls when draining the FIFO at a deadline (128-byte FIFO,
/// read into the bridge's receive space, which holds a whole reply's remaining
/// bytes and grows as the bridge takes them; the bound only guards against a line
/// that keeps delivering).
const DEADLINE_DRAIN_READS: usize = 4;
/// Longest the bridge task sleeps without feeding the watchdog.
const MAX_WAIT: Duration = Duration::from_millis(500);
/// UART receive errors are logged at most once per this period.
const RX_ERROR_LOG_PERIOD: Duration = Duration::from_secs(10);

/// The bridge's configuration as the bridge task holds it.
pub struct Configuration {
    /// The record it runs with and the one it stores.
    pub state: ConfigState,
    /// The store (`None`: no usable partition; changes then live in RAM).
    pub store: Option<store::ChipStore>,
}

/// UART1 to the TinyBMS on the board's pins, and the bridge task on it.
pub fn start(
    spawner: Spawner,
    uart1: UART1<'static>,
    wdt: Wdt<TIMG0<'static>>,
    config: Configuration,
) {
    // SAFETY: `AnyPin::steal` hands out a second handle to a GPIO. These two GPIOs
    // are used nowhere else: the shell never touches `p.GPIOn`, and the board
    // check (const, main.rs) guarantees they exist on the chip, are distinct from
    // each other and from the CAN pins, and are not flash/USB/UART0 pins.
    let (tx_pin, rx_pin) = unsafe { (AnyPin::steal(BOARD.bms_tx), AnyPin::steal(BOARD.bms_rx)) };
    let uart_config = UartConfig::default()
        .with_baudrate(BMS_BAUDRATE)
        .with_rx(RxConfig::default().with_fifo_full_threshold(RX_FIFO_FULL_THRESHOLD));
    let uart = Uart::new(uart1, uart_config)
        .expect("UART1 config")
        .with_tx(tx_pin)
        .with_rx(rx_pin)
        .into_async();
    let (rx, tx) = uart.split();
    info!(
        "UART1 {=u32} 8N1 to the BMS: TX=GPIO{=u8} RX=GPIO{=u8} (rx fifo threshold {=u16})",
        BMS_BAUDRATE, BOARD.bms_tx, BOARD.bms_rx, RX_FIFO_FULL_THRESHOLD,
    );
    spawn(spawner, bridge_task(rx, tx, wdt, config));
}

/// UART receive errors, counted as they happen and logged (rate-limited) with the
/// reports, i.e. never while a reply is arriving.
struct RxErrors {
    count: u32,
    last: Option<RxError>,
    next_log: Instant,
}

impl RxErrors {
    fn record(&mut self, e: RxError) {
        self.count = self.count.wrapping_add(1);
        self.last = Some(e);
    }

    fn log(&mut self) {
        if let Some(e) = self.last {
            if Instant::now() >= self.next_log {
                warn!("uart rx error: {} ({=u32} so far)", e, self.count);
                self.next_log = Instant::now() + RX_ERROR_LOG_PERIOD;
                self.last = None;
            }
        }
    }
}

/// Moves bytes and time between UART1 and the sans-IO bridge; logs its reports.
///
/// Two timing rules (issue 11):
/// * Reports are logged just before the next request goes out, never right after
///   one: the reply starts 1-2 ms after the request's last byte (HARDWARE-NOTES
///   "Timing"), and a defmt write can block (RTT with probe-rs attached waits for
///   the host; UART0 logging writes byte by byte at 115 200 Bd). Logging then
///   would delay reading the RX FIFO while the reply fills it. The cost: a report
///   reaches the log up to one request later (≤ 250 ms online, ≤ 2 s offline).
/// * When the timer wins the race against `read_async`, bytes may already be in the
///   FIFO: below the full threshold, the RX-timeout interrupt (10 symbols ≈ 0.9 ms)
///   has not fired yet. They are drained with `read_buffered` and handed to the
///   bridge *before* `poll` handles the deadline, so a reply that ends just at the
///   deadline still completes its transaction (host-tests/tests/deadline_drain.rs).
#[embassy_executor::task]
async fn bridge_task(
    mut rx: UartRx<'static, Async>,
    mut tx: UartTx<'static, Async>,
    mut wdt: Wdt<TIMG0<'static>>,
    config: Configuration,
) {
    let Configuration {
        state: mut config,
        mut store,
    } = config;
    let sender = TELEMETRY.sender();
    let mut bridge = Bridge::new(Timing::default(), now_us());
    submit_profile(&mut bridge);
    let mut host = usb::HostPort::new(&bridge, config.running());
    let mut published_seq = 0u32;
    let mut rx_errors = RxErrors {
        count: 0,
        last: None,
        next_log: Instant::now(),
    };

    loop {
        wdt.feed();
        match bridge.step(now_us()) {
            Step::Transmit => {
                // The line is quiet now: log what the last exchanges produced.
                while let Some(report) = bridge.next_report() {
                    #[cfg(feature = "can")]
                    crate::can::on_report(&report);
                    #[cfg(feature = "wifi")]
                    crate::wifi::on_report(&report);
                    host.on_report(&report);
                    log::report(&report);
                }
                while let Some(note) = config.next_note() {
                    log::config(&note, &config);
                }
                rx_errors.log();
                // Written from where the link keeps them (no copy).
                let bytes = bridge.transmit_bytes();
                host.on_uart_tx(bytes);
                let mut rest: &[u8] = bytes;
                while !rest.is_empty() {
                    match tx.write_async(rest).await {
                        Ok(n) => rest = rest.get(n..).unwrap_or(&[]),
                        Err(e) => {
                            warn!("uart tx error: {}", e);
                            break;
                        }
                    }
                }
                if let Err(e) = tx.flush_async().await {
                    warn!("uart flush error: {}", e);
                }
            }
            Step::WaitUntil(t) => {
                let t = t.min(host.due());
                let deadline = Instant::from_micros(t).min(Instant::now() + MAX_WAIT);
                // `read_async` and `Pipe::read` are cancellation-safe: racing them
                // against a timer loses nothing.
                // The UART driver writes straight into the bridge's receive
                // space (no copy of ours); it is the same space until
                // `handle_received`, so the capture reads the bytes there.
                match select3(
                    rx.read_async(bridge.rx_buffer()),
                    Timer::at(deadline),
                    host.receive(),
                )
                .await
                {
                    Either3::First(Ok(n)) => {
                        host.on_uart_rx(bridge.rx_buffer().get(..n).unwrap_or(&[]));
                        bridge.handle_received(now_us(), n);
                    }
                    Either3::First(Err(e)) => rx_errors.record(e),
                    Either3::Third(n) => host.handle_rx(n, &mut bridge, &mut config),
                    Either3::Second(()) => {
                        // Bytes already received but not yet signalled go in before
                        // the deadline is handled by the next `poll`.
                        for _ in 0..DEADLINE_DRAIN_READS {
                            match rx.read_buffered(bridge.rx_buffer()) {
                                Ok(0) => break,
                                Ok(n) => {
                                    host.on_uart_rx(bridge.rx_buffer().get(..n).unwrap_or(&[]));
                                    bridge.handle_received(now_us(), n);
                                }
                                Err(e) => {
                                    rx_errors.record(e);
                                    break;
                                }
                            }
                        }
                    }
                }
            }
        }
        #[cfg(feature = "host-link")]
        if crate::button::UNLOCK.try_take().is_some() {
            config.unlock();
        }
        if let Some(running) = config.take_running_change() {
            host.apply_config(running);
            #[cfg(feature = "can")]
            crate::can::reconfigure(running);
        }
        // The flash write stops the CPU: only when no BMS reply can be on its
        // way, and nothing is sent until it is done (the poll is held).
        let saved = store::save_when_quiet(&mut config, &mut store, &bridge, now_us());
        if let Some(result) = saved {
            host.on_config_saved(result);
        }
        host.after_pass(&bridge, &config);
        // Publishing is a copy into the Watch, no I/O: done on every step.
        let t = bridge.telemetry();
        if t.snapshot_seq != published_seq {
            published_seq = t.snapshot_seq;
            if let (Some(snapshot), Some(at)) = (&t.snapshot, t.snapshot_at) {
                sender.send(SharedSnapshot {
                    snapshot: snapshot.clone(),
                    taken_at: Instant::from_micros(at),
                    #[cfg(feature = "can")]
                    inverter: crate::can::Inputs::from_telemetry(t),
                    #[cfg(feature = "wifi")]
                    mqtt: crate::wifi::Inputs::from_telemetry(t, {
                        let s = bridge.link_stats();
                        (s.requests, s.replies)
                    }),
                });
            }
        }
    }
}

/// The start-up profile (`firmware/profile.txt`), parsed at compile time: a
/// profile that does not parse fails the build, and the chip links neither the
/// parser nor the names it matches against (snake_case keys), nor the file's text.
const STARTUP_PROFILE: profile::Profile<{ profile::MAX_PROFILE_ENTRIES }> =
    match profile::parse(profile::PROFILE_TEXT) {
        Ok(p) => p,
        Err(_) => panic!(
            "firmware/profile.txt does not parse (or holds too many settings): \
             `cargo run -p host-tests --bin sim -- --profile firmware/profile.txt` names the line"
        ),
    };

/// Queues the start-up profile: every assignment.
fn submit_profile(bridge: &mut Bridge) {
    if STARTUP_PROFILE.is_empty() {
        info!("settings profile empty: nothing written");
    } else {
        info!("settings profile: {=usize} settings", STARTUP_PROFILE.len());
        if bridge.submit_profile(STARTUP_PROFILE.as_slice()).is_err() {
            warn!("settings profile too long for the command queue");
        }
    }
}
