//! TinyBMS firmware — chip-specific shell (ESP32-C3 / ESP32-C6).
//!
//! Structure: init (clocks, watchdog, esp-rtos, UART1, TWAI, USB-Serial-JTAG) → spawn
//! `bridge_task(rx, tx, wdt)`, `consumer_task()`, `can_task(twai)`, `usb_rx_task` and
//! `usb_tx_task`. The inverter output (module `can_output`: TWAI, `can_task`) and the
//! host link (module `host_port`: USB-Serial-JTAG, `usb_rx_task`, `usb_tx_task`) are
//! the cargo features `can` and `host-link`, both on by default; without
//! `host-link`, `host_port` is a stub whose calls the compiler removes, so the
//! bridge task reads the same either way. All protocol and state-machine logic lives in the library
//! (`tinybms_firmware::Bridge` and `tinybms_firmware::host_link::HostLink`, sans-IO,
//! tested on the host); this file only moves bytes and time between UART1, the USB
//! port and them, logs the bridge's reports and shares the latest telemetry through
//! an embassy-sync `Watch`.
//!
//! Host link (JSON Lines on the USB cable): the `HostLink` lives in the bridge task
//! next to the bridge (in a `host_port::HostPort`). Host bytes come in through the `HOST_RX` pipe (filled by
//! `usb_rx_task`); encoded lines go out through the `HOST_TX` pipe, taken only while
//! it has room for a whole line, to `usb_tx_task`, which writes them with a timeout.
//! The bridge task never awaits the host: a missing or slow host fills the pipe, then
//! the host link's bounded queue, which drops streamed telemetry first.
//!
//! Board: the pins come from `tinybms_firmware::boards::SELECTED`, chosen by one
//! `board-…` feature and checked at compile time (no strapping, flash, USB, UART0 or
//! on-board-part pin). Logging: defmt over RTT (`log-rtt`, read with `probe-rs run`)
//! or defmt frames on UART0 (`log-uart`, read with `espflash flash --monitor
//! --log-format defmt`). See README, "Boards, log paths and the first flash".

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

use defmt::{info, warn};
#[cfg(feature = "log-rtt")]
use defmt_rtt as _; // defmt global logger: RTT
use embassy_executor::{SpawnError, SpawnToken, Spawner};
use embassy_futures::select::{select3, Either3};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::watch::Watch;
use embassy_time::{with_timeout, Duration, Instant, Timer};
use esp_hal::clock::CpuClock;
use esp_hal::gpio::AnyPin;
use esp_hal::peripherals::TIMG0;
use esp_hal::timer::timg::{MwdtStage, TimerGroup, Wdt};
use esp_hal::uart::{Config as UartConfig, RxConfig, RxError, Uart, UartRx, UartTx};
use esp_hal::Async;
#[cfg(feature = "log-uart")]
use esp_println as _; // defmt global logger: UART0, espflash's defmt framing
use protocol_core::events::OnlineStatus;
use protocol_core::views::LiveSnapshot;
use tinybms_firmware::boards::{self, Board, Chip, LogPath};
use tinybms_firmware::bridge::Step;
use tinybms_firmware::config::Config as BridgeConfig;
use tinybms_firmware::link::Failure;
use tinybms_firmware::{profile, Bridge, Level, Report};

// ESP-IDF 2nd-stage bootloader requires an application descriptor in the image.
esp_bootloader_esp_idf::esp_app_desc!();

// ---------------------------------------------------------------------------
// Board wiring (TinyBMS UART, 115200 8N1, 3.3 V logic): see firmware/src/boards.rs
// ---------------------------------------------------------------------------

/// The board this image is built for (`board-…` feature).
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
/// Watchdog timeout (MWDT stage 0 → system reset). Fed by the bridge loop.
const WDT_TIMEOUT: esp_hal::time::Duration = esp_hal::time::Duration::from_secs(4);
/// After a panic, time for the log reader to fetch the panic line and backtrace
/// before the reset (RTT is polled by the host; UART0 drains its FIFO). Shorter
/// than [`WDT_TIMEOUT`], so the watchdog is only the fallback.
const PANIC_RESET_DELAY_US: u32 = 1_000_000;
/// UART receive errors are logged at most once per this period.
const RX_ERROR_LOG_PERIOD: Duration = Duration::from_secs(10);
/// Telemetry older than this is reported stale by the consumer task.
const STALE_AFTER: Duration = Duration::from_secs(5);

/// The latest live snapshot, with the time it was decoded (so readers know its age)
/// and, for the inverter output, the BMS settings charge control needs and the version.
#[derive(Clone)]
struct SharedSnapshot {
    snapshot: LiveSnapshot,
    taken_at: Instant,
    #[cfg(feature = "can")]
    inverter: can_output::Inputs,
}

/// Latest telemetry for the other tasks: one sender (bridge_task), up to 3 receivers
/// (the example consumer, the CAN output).
static TELEMETRY: Watch<CriticalSectionRawMutex, SharedSnapshot, 3> = Watch::new();

/// Every panic ends here: log "panic" and the backtrace (return addresses from
/// the frame-pointer walk, innermost first: the panic helper(s) that were called —
/// `unwrap_failed`, `panic_bounds_check`, … — when there are any, then the code
/// that failed and its callers; `addr2line -i -f -e <elf> ADDR…` turns them into
/// file:line), wait for the log to get out, then reset, so a panic anywhere —
/// including in `esp_hal::init` before any watchdog is armed — ends in a reset
/// rather than a hang. `info` is deliberately not read: LTO then finds that the
/// message and location handed to `panic_fmt` are never read and drops their
/// building at every panic site, and with it `core::fmt`, the `Debug` impls of the
/// dependencies' error types and the source paths (17.8 KB of flash on the C3,
/// README "Performance"). The backtrace carries the same location.
#[panic_handler]
fn panic(_info: &core::panic::PanicInfo) -> ! {
    defmt::error!("panic");
    for frame in esp_backtrace::Backtrace::capture().frames() {
        defmt::error!("  backtrace 0x{=usize:08x}", frame.program_counter());
    }
    esp_hal::rom::ets_delay_us(PANIC_RESET_DELAY_US);
    esp_hal::system::software_reset()
}

#[esp_rtos::main]
async fn main(spawner: Spawner) {
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

    info!(
        "tinybms-firmware {} on {=str} ({=str}), logs over {=str}",
        env!("CARGO_PKG_VERSION"),
        BOARD.name,
        BOARD.chip.name(),
        match LOG_PATH {
            LogPath::Rtt => "RTT",
            LogPath::Uart0 => "UART0",
        }
    );

    // esp-rtos: TIMG0 timer0 as time base + FROM_CPU_INTR0 software interrupt.
    esp_rtos::start(timg0.timer0, p.FROM_CPU_INTR0);

    // UART1 to the TinyBMS, on the board's pins.
    // SAFETY: `AnyPin::steal` hands out a second handle to a GPIO. These two GPIOs
    // are used nowhere else: this file never touches `p.GPIOn`, and the board
    // check (const, above) guarantees they exist on the chip, are distinct from
    // each other and from the CAN pins, and are not flash/USB/UART0 pins.
    let (tx_pin, rx_pin) = unsafe { (AnyPin::steal(BOARD.bms_tx), AnyPin::steal(BOARD.bms_rx)) };
    let uart_config = UartConfig::default()
        .with_baudrate(BMS_BAUDRATE)
        .with_rx(RxConfig::default().with_fifo_full_threshold(RX_FIFO_FULL_THRESHOLD));
    let uart = Uart::new(p.UART1, uart_config)
        .expect("UART1 config")
        .with_tx(tx_pin)
        .with_rx(rx_pin)
        .into_async();
    let (rx, tx) = uart.split();
    info!(
        "UART1 {} 8N1 TX=GPIO{=u8} RX=GPIO{=u8} (rx fifo threshold {=u16}); CAN reserved TX=GPIO{=u8} RX=GPIO{=u8}",
        BMS_BAUDRATE,
        BOARD.bms_tx,
        BOARD.bms_rx,
        RX_FIFO_FULL_THRESHOLD,
        BOARD.can_tx,
        BOARD.can_rx
    );

    #[cfg(feature = "can")]
    can_output::start(spawner, p.TWAI0);
    #[cfg(feature = "host-link")]
    host_port::start(spawner, p.USB_DEVICE);

    spawn(spawner, bridge_task(rx, tx, wdt));
    spawn(spawner, consumer_task());
}

/// Spawns a task. A pool without a free slot is a bug in this file: it panics
/// (the backtrace shows which call), not through `expect`, which would link
/// `SpawnError`'s `Debug` for a message never printed.
fn spawn<S>(spawner: Spawner, task: Result<SpawnToken<S>, SpawnError>) {
    match task {
        Ok(token) => spawner.spawn(token),
        Err(_) => panic!("spawn"),
    }
}

fn now_us() -> u64 {
    Instant::now().as_micros()
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
) {
    let sender = TELEMETRY.sender();
    let mut bridge = Bridge::new(BridgeConfig::default(), now_us());
    submit_profile(&mut bridge);
    let mut host = host_port::HostPort::new(&bridge);
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
                    can_output::on_report(&report);
                    host.on_report(&report);
                    log_report(&report);
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
                    Either3::Third(n) => host.handle_rx(n, &mut bridge),
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
        host.after_pass(&bridge);
        // Publishing is a copy into the Watch, no I/O: done on every step.
        let t = bridge.telemetry();
        if t.snapshot_seq != published_seq {
            published_seq = t.snapshot_seq;
            if let (Some(snapshot), Some(at)) = (&t.snapshot, t.snapshot_at) {
                sender.send(SharedSnapshot {
                    snapshot: snapshot.clone(),
                    taken_at: Instant::from_micros(at),
                    #[cfg(feature = "can")]
                    inverter: can_output::Inputs::from_telemetry(t),
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

/// The host link (feature `host-link`): the USB-Serial-JTAG port, its two tasks and
/// the [`HostLink`](tinybms_firmware::host_link::HostLink) the bridge task drives.
#[cfg(feature = "host-link")]
mod host_port {
    use super::*;
    use embassy_sync::pipe::Pipe;
    use embassy_sync::signal::Signal;
    use esp_hal::peripherals::USB_DEVICE;
    use esp_hal::usb::usb_serial_jtag::{UsbSerialJtag, UsbSerialJtagRx, UsbSerialJtagTx};
    use tinybms_firmware::host_link::{HostLink, OUT_LINE_MAX};

    /// Bytes from the host (USB-Serial-JTAG → bridge task). When full, `usb_rx_task`
    /// waits, and the USB endpoint makes the host wait: nothing is lost.
    static HOST_RX: Pipe<CriticalSectionRawMutex, HOST_RX_PIPE> = Pipe::new();
    /// Encoded lines for the host (bridge task → `usb_tx_task`).
    static HOST_TX: Pipe<CriticalSectionRawMutex, HOST_TX_PIPE> = Pipe::new();
    /// `usb_tx_task` saw a write go through after none could (at boot, or after a
    /// timeout): a host has (re)opened the port. The bridge task then queues `hello`.
    static HOST_CONNECTED: Signal<CriticalSectionRawMutex, ()> = Signal::new();

    /// Size of [`HOST_RX`], bytes.
    const HOST_RX_PIPE: usize = 256;
    /// Size of [`HOST_TX`], bytes: two of the longest lines.
    const HOST_TX_PIPE: usize = 2 * OUT_LINE_MAX;
    /// Longest a write of one chunk to the USB port may take (the host reads the IN
    /// endpoint every millisecond while the port is open). On timeout the chunk is
    /// dropped and the host is deemed gone until a write goes through again.
    const USB_WRITE_TIMEOUT: Duration = Duration::from_millis(50);
    /// Bytes written to the USB port at once (the endpoint's FIFO is 64 bytes).
    const USB_WRITE_CHUNK: usize = 256;

    /// The host link on the USB cable (USB-Serial-JTAG, CDC-ACM). Its JTAG side
    /// (probe-rs, RTT) is a separate USB interface of the same device: both run
    /// together (README, "Host link").
    pub fn start(spawner: Spawner, usb: USB_DEVICE<'static>) {
        let (usb_rx, usb_tx) = UsbSerialJtag::new(usb).into_async().split();
        info!(
            "host link on USB-Serial-JTAG: {=str}, telemetry every {=u32} ms",
            if tinybms_firmware::site::HOST_READ_ONLY {
                "read-only"
            } else {
                "read-write"
            },
            tinybms_firmware::site::HOST_STREAM_PERIOD_MS
        );
        spawn(spawner, usb_rx_task(usb_rx));
        spawn(spawner, usb_tx_task(usb_tx));
    }

    /// The bridge task's side of the host link.
    pub struct HostPort {
        link: HostLink,
        /// When the host link's timers want it called again (set at the end of every
        /// pass, after whatever the pass changed).
        due: u64,
        rx_buf: [u8; 64],
        line: [u8; OUT_LINE_MAX],
    }

    impl HostPort {
        pub fn new(bridge: &Bridge) -> Self {
            let mut link = HostLink::new(
                tinybms_firmware::site::host_link_config(BOARD.chip.name()),
                now_us(),
            );
            let due = link.poll(now_us(), bridge);
            Self {
                link,
                due,
                rx_buf: [0; 64],
                line: [0; OUT_LINE_MAX],
            }
        }

        pub fn on_report(&mut self, report: &Report) {
            self.link.on_report(report);
        }

        pub fn on_uart_tx(&mut self, bytes: &[u8]) {
            self.link.on_uart_tx(bytes);
        }

        pub fn on_uart_rx(&mut self, bytes: &[u8]) {
            self.link.on_uart_rx(bytes);
        }

        /// When the host link wants to be called again (µs).
        pub fn due(&self) -> u64 {
            self.due
        }

        /// Waits for bytes from the host (cancellation-safe); their count.
        pub async fn receive(&mut self) -> usize {
            HOST_RX.read(&mut self.rx_buf).await
        }

        /// The `n` bytes [`HostPort::receive`] got, into the host link.
        pub fn handle_rx(&mut self, n: usize, bridge: &mut Bridge) {
            let bytes = self.rx_buf.get(..n).unwrap_or(&[]);
            self.link.handle_rx(now_us(), bytes, bridge);
        }

        /// End of a bridge-task pass: a (re)connected host gets `hello`; streamed
        /// telemetry when due; encoded lines move to the USB writer while its pipe
        /// has room for a whole one (no I/O here, never a wait).
        pub fn after_pass(&mut self, bridge: &Bridge) {
            if HOST_CONNECTED.try_take().is_some() {
                self.link.connected(now_us());
            }
            self.due = self.link.poll(now_us(), bridge);
            while HOST_TX.free_capacity() >= OUT_LINE_MAX {
                let Some(n) = self.link.next_line(now_us(), bridge, &mut self.line) else {
                    break;
                };
                let _ = HOST_TX.try_write(self.line.get(..n).unwrap_or(&[]));
            }
        }
    }

    /// Host → bridge: bytes from the USB port into [`HOST_RX`]. Waits (and so makes
    /// the host wait) while the bridge task has not taken the previous ones.
    #[embassy_executor::task]
    async fn usb_rx_task(mut rx: UsbSerialJtagRx<'static, Async>) {
        use embedded_io_async::Read;
        let mut buf = [0u8; 64];
        loop {
            let Ok(n) = rx.read(&mut buf).await; // the error type is `Infallible`
            HOST_RX.write_all(buf.get(..n).unwrap_or(&[])).await;
        }
    }

    /// Bridge → host: lines from [`HOST_TX`] to the USB port, each chunk with a
    /// timeout. A chunk that times out is dropped (the host sees a cut line and
    /// resyncs at the next newline); the first write that goes through afterwards
    /// (and the first one after boot) signals [`HOST_CONNECTED`].
    #[embassy_executor::task]
    async fn usb_tx_task(mut tx: UsbSerialJtagTx<'static, Async>) {
        use embedded_io_async::Write;
        let mut buf = [0u8; USB_WRITE_CHUNK];
        let mut reading = false;
        loop {
            let n = HOST_TX.read(&mut buf).await;
            let chunk = buf.get(..n).unwrap_or(&[]);
            let sent = with_timeout(USB_WRITE_TIMEOUT, async {
                tx.write_all(chunk).await?;
                tx.flush().await
            })
            .await;
            match sent {
                Ok(Ok(())) => {
                    if !reading {
                        reading = true;
                        HOST_CONNECTED.signal(());
                    }
                }
                _ => reading = false,
            }
        }
    }
}

/// Without the host link: nothing to drive (the compiler removes these calls).
#[cfg(not(feature = "host-link"))]
mod host_port {
    use super::{Bridge, Report};

    pub struct HostPort;

    impl HostPort {
        pub fn new(_: &Bridge) -> Self {
            Self
        }
        pub fn on_report(&mut self, _: &Report) {}
        pub fn on_uart_tx(&mut self, _: &[u8]) {}
        pub fn on_uart_rx(&mut self, _: &[u8]) {}
        pub fn due(&self) -> u64 {
            u64::MAX
        }
        pub async fn receive(&mut self) -> usize {
            core::future::pending().await
        }
        pub fn handle_rx(&mut self, _: usize, _: &mut Bridge) {}
        pub fn after_pass(&mut self, _: &Bridge) {}
    }
}

/// The inverter output (feature `can`): the TWAI controller and `can_task`.
#[cfg(feature = "can")]
mod can_output {
    use super::*;
    use embassy_futures::select::{select, Either};
    use embassy_sync::channel::Channel;
    use esp_hal::peripherals::TWAI0;
    use esp_hal::twai::{
        BaudRate, EspTwaiError, EspTwaiFrame, Id, StandardId, Twai, TwaiConfiguration, TwaiMode,
    };
    use protocol_core::events::Event;
    use protocol_core::views::VersionInfo;
    use tinybms_firmware::inverter::control::PackSettings;
    use tinybms_firmware::inverter::{
        Inverter, InverterAction, InverterReport, Protocol, TxResult,
    };
    use tinybms_firmware::Telemetry;

    /// New BMS events for the CAN output (charge-blocking faults); a full channel
    /// drops the event for it (the BMS status still says "fault").
    static EVENTS: Channel<CriticalSectionRawMutex, Event, 8> = Channel::new();

    /// CAN bit rate of both inverter protocols.
    const CAN_BAUDRATE: BaudRate = BaudRate::B500K;
    /// Longest a CAN transmission may take before it counts as failed.
    const CAN_TX_TIMEOUT: Duration = Duration::from_millis(100);
    /// Longest the CAN task sleeps (it re-reads the telemetry at least this often).
    const CAN_MAX_WAIT: Duration = Duration::from_millis(200);
    /// Bus-off recovery: how long to wait for the controller to come back.
    const CAN_RECOVERY_WAIT: Duration = Duration::from_millis(500);

    /// What the inverter output needs with each snapshot: the BMS settings charge
    /// control uses and the version.
    #[derive(Clone)]
    pub struct Inputs {
        settings: Option<PackSettings>,
        version: Option<VersionInfo>,
    }

    impl Inputs {
        pub fn from_telemetry(t: &Telemetry) -> Self {
            Self {
                settings: t.settings.as_ref().and_then(PackSettings::from_registers),
                version: t.version,
            }
        }
    }

    /// A bridge report the inverter output wants: new BMS events.
    pub fn on_report(report: &Report) {
        if let Report::NewEvent(e) = report {
            let _ = EVENTS.try_send(*e);
        }
    }

    /// TWAI (CAN) to the inverter, on the board's CAN pins, 500 kbit/s.
    pub fn start(spawner: Spawner, twai0: TWAI0<'static>) {
        // SAFETY: as for the UART pins above: used nowhere else, checked distinct and
        // not flash/USB/UART0/strapping pins by the board table.
        let (can_tx, can_rx) =
            unsafe { (AnyPin::steal(BOARD.can_tx), AnyPin::steal(BOARD.can_rx)) };
        let twai = TwaiConfiguration::new(twai0, can_rx, can_tx, CAN_BAUDRATE, TwaiMode::Normal)
            .into_async()
            .start();
        info!(
            "CAN {=str} 500 kbit/s TX=GPIO{=u8} RX=GPIO{=u8} ({=str})",
            if tinybms_firmware::site::CAN_OUTPUT {
                "on"
            } else {
                "off"
            },
            BOARD.can_tx,
            BOARD.can_rx,
            match tinybms_firmware::site::PROTOCOL {
                Protocol::Victron => "victron",
                Protocol::SmaSunnyIsland => "sma-si",
            }
        );
        spawn(spawner, can_task(twai));
    }

    /// The inverter output: the firmware's sans-IO [`Inverter`] between the shared
    /// telemetry and the TWAI controller. It never waits on the BMS link (it reads
    /// the `Watch` without blocking) and the BMS link never waits on it.
    #[embassy_executor::task]
    async fn can_task(mut twai: Twai<'static, Async>) {
        let Some(mut telemetry) = TELEMETRY.receiver() else {
            warn!("telemetry watch has no free receiver slot: no CAN output");
            return;
        };
        let mut inverter = Inverter::new(tinybms_firmware::site::inverter_config(), now_us());
        loop {
            if let Some(shared) = telemetry.try_changed() {
                inverter.on_snapshot(
                    shared.taken_at.as_micros(),
                    &shared.snapshot,
                    shared.inverter.settings,
                    shared.inverter.version.as_ref(),
                );
            }
            while let Ok(e) = EVENTS.try_receive() {
                inverter.on_event(&e);
            }
            match inverter.poll(now_us()) {
                InverterAction::Send(f) => {
                    let Some(frame) =
                        StandardId::new(f.id).and_then(|id| EspTwaiFrame::new(id, f.bytes()))
                    else {
                        continue;
                    };
                    let result = with_timeout(CAN_TX_TIMEOUT, twai.transmit_async(&frame)).await;
                    if matches!(result, Ok(Err(EspTwaiError::BusOff))) || twai.is_bus_off() {
                        inverter.on_bus_off(now_us());
                    } else if matches!(result, Ok(Ok(()))) {
                        inverter.on_tx(now_us(), TxResult::Sent);
                    } else {
                        // Not acknowledged (no other node: error-passive), or too slow.
                        inverter.on_tx(now_us(), TxResult::Failed);
                    }
                }
                InverterAction::Recover => {
                    twai.initiate_recovery();
                    let until = Instant::now() + CAN_RECOVERY_WAIT;
                    while twai.is_bus_off() && Instant::now() < until {
                        Timer::after(Duration::from_millis(10)).await;
                    }
                    if twai.is_bus_off() {
                        inverter.on_bus_off(now_us());
                    }
                }
                InverterAction::WaitUntil(t) => {
                    let deadline = Instant::from_micros(t).min(Instant::now() + CAN_MAX_WAIT);
                    // The GX keep-alive (0x305/0x307) and anything else on the bus.
                    if let Either::First(Ok(frame)) =
                        select(twai.receive_async(), Timer::at(deadline)).await
                    {
                        if let Id::Standard(id) = frame.identifier() {
                            inverter.on_received(now_us(), id.as_raw(), frame.data());
                        }
                    }
                }
            }
            while let Some(r) = inverter.next_report() {
                log_inverter(&r);
            }
        }
    }

    /// One defmt line per inverter report.
    fn log_inverter(r: &InverterReport) {
        match r {
            InverterReport::InverterSeen => info!("CAN: inverter seen (keep-alive)"),
            InverterReport::InverterLost => warn!("CAN: inverter lost (no keep-alive)"),
            InverterReport::Stale { age_ms, policy } => warn!(
                "CAN: BMS telemetry {=u32} ms old: {}",
                age_ms, policy
            ),
            InverterReport::StaleHoldEnded => warn!("CAN: hold time over, sending stopped"),
            InverterReport::Fresh => info!("CAN: BMS telemetry fresh again, sending"),
            InverterReport::NoAck { failures } => warn!(
                "CAN: {=u32} frames not acknowledged (nothing else on the bus? wiring, termination, bit rate)",
                failures
            ),
            InverterReport::BusOk => info!("CAN: frames acknowledged again"),
            InverterReport::BusOff { count, backoff_ms } => warn!(
                "CAN: bus-off #{=u32}, recovering in {=u32} ms",
                count, backoff_ms
            ),
            InverterReport::Limits(l) => info!(
                "CAN limits: CVL {=u16} dV, CCL {=u16} dA, DCL {=u16} dA",
                l.cvl_dv, l.ccl_da, l.dcl_da
            ),
        }
    }
}

/// An example reader of the shared telemetry: it always knows the age of what it
/// reads, and says so when the data goes stale.
#[embassy_executor::task]
async fn consumer_task() {
    let Some(mut receiver) = TELEMETRY.receiver() else {
        warn!("telemetry watch has no free receiver slot");
        return;
    };
    let mut stale = false;
    loop {
        match with_timeout(STALE_AFTER, receiver.changed()).await {
            Ok(shared) => {
                if stale {
                    info!("telemetry fresh again");
                    stale = false;
                }
                let age = Instant::now().saturating_duration_since(shared.taken_at);
                if age > STALE_AFTER {
                    warn!("telemetry is {} ms old", age.as_millis());
                }
                let _ = shared.snapshot.soc_percent();
            }
            Err(_) => {
                if !stale {
                    warn!(
                        "no telemetry for {} s: values are stale",
                        STALE_AFTER.as_secs()
                    );
                    stale = true;
                }
            }
        }
    }
}

/// One defmt line per report, in the same words as the host simulator prints.
fn log_report(r: &Report) {
    match r {
        Report::Snapshot(s) => info!(
            "pack {=f32}V {=f32}A soc {=f32}% min #{=u8} {=f32}V max #{=u8} {=f32}V temp {=f32}C ext {} {} status {=str}",
            s.pack_v,
            s.current_a,
            s.soc_percent,
            s.min_cell.0,
            s.min_cell.1,
            s.max_cell.0,
            s.max_cell.1,
            s.internal_c,
            s.external_c.0,
            s.external_c.1,
            s.status.name()
        ),
        Report::StatusChanged { from, to } => {
            let from = from.map(|f| f.name()).unwrap_or("-");
            if *to == OnlineStatus::Fault {
                warn!("status {=str} -> {=str}", from, to.name());
            } else {
                info!("status {=str} -> {=str}", from, to.name());
            }
        }
        Report::NewEvent(e) => {
            if r.level() == Level::Warn {
                warn!(
                    "event {=str} t={=u32}s 0x{=u8:02X} {=str}",
                    e.id.severity().name(),
                    e.timestamp_s,
                    e.id.raw(),
                    e.id.name()
                );
            } else {
                info!(
                    "event {=str} t={=u32}s 0x{=u8:02X} {=str}",
                    e.id.severity().name(),
                    e.timestamp_s,
                    e.id.raw(),
                    e.id.name()
                );
            }
        }
        Report::EventHistory { count, newest } => match newest {
            Some(e) => info!(
                "event log: {=u8} recent events, newest t={=u32}s 0x{=u8:02X} {=str}",
                count,
                e.timestamp_s,
                e.id.raw(),
                e.id.name()
            ),
            None => info!("event log: {=u8} recent events", count),
        },
        Report::LinkError {
            command,
            failure,
            suppressed,
        } => {
            let code = match failure {
                Failure::Nack(c) => c.to_u8(),
                _ => 0xFF,
            };
            if *suppressed > 0 {
                warn!(
                    "link error cmd 0x{=u8:02X}: {=str} (nack code 0x{=u8:02X}) (+{=u32} more since the last line)",
                    command,
                    failure.name(),
                    code,
                    suppressed
                );
            } else {
                warn!(
                    "link error cmd 0x{=u8:02X}: {=str} (nack code 0x{=u8:02X})",
                    command,
                    failure.name(),
                    code
                );
            }
        }
        Report::Offline { failures } => warn!("BMS offline after {=u8} failed requests", failures),
        Report::Online => info!("BMS online; re-reading version and settings"),
        Report::Version(v) => info!(
            "version hw {=u8}.{=u8} fw {=u8} ({=u16}) bootloader {=u8} profile {=u8} serial {=[u8]:02X}",
            v.hardware,
            v.hardware_changes,
            v.firmware_public,
            v.firmware_internal,
            v.bootloader,
            v.profile,
            v.serial
        ),
        Report::Ready { series_cells } => {
            info!("settings and limits read ({=u16} cells): ready", series_cells)
        }
        Report::Write { setting, outcome } | Report::WriteFollowUp { setting, outcome } => {
            let follow = if matches!(r, Report::WriteFollowUp { .. }) {
                "follow-up "
            } else {
                ""
            };
            if outcome.is_success() {
                info!(
                    "write {=str}{=str} ({=u16}) = {=i32}: {=str}",
                    follow,
                    setting.id.name(),
                    setting.id.address(),
                    setting.value,
                    outcome.name()
                );
            } else {
                warn!(
                    "write {=str}{=str} ({=u16}) = {=i32}: {=str} {}",
                    follow,
                    setting.id.name(),
                    setting.id.address(),
                    setting.value,
                    outcome.name(),
                    outcome
                );
            }
        }
        Report::Flagged(Some(c)) => warn!(
            "live data confirmed by a second read but fails check {=str}: published, flagged",
            c.name()
        ),
        Report::Flagged(None) => info!("live data passes every check again"),
        Report::Refused { check, count } => warn!(
            "{=u32} live block(s) failed check {=str} and were not confirmed: not published",
            count,
            check.map(|c| c.name()).unwrap_or("first_read")
        ),
        Report::LineQuality {
            attempts,
            clean,
            piece_registers,
            snapshots,
        } => {
            let permille = tinybms_firmware::report::permille(*clean, *attempts);
            if r.level() == Level::Warn {
                warn!(
                    "line quality: {=u32} permille of {=u32} reads answered at the first attempt; {=u16} registers per request; {=u32} snapshots",
                    permille, attempts, piece_registers, snapshots
                );
            } else {
                info!(
                    "line quality: {=u32} permille of {=u32} reads answered at the first attempt; {=u16} registers per request; {=u32} snapshots",
                    permille, attempts, piece_registers, snapshots
                );
            }
        }
        Report::ResetDone { confirmed } => {
            if *confirmed {
                info!("BMS reset confirmed (reg 114 = software reset)")
            } else {
                warn!("BMS reset not confirmed")
            }
        }
        Report::Cleared { option, ok } => {
            let what = if *option == 1 { "events" } else { "statistics" };
            if *ok {
                info!("clear {=str} ok", what);
            } else {
                warn!("clear {=str} failed", what);
            }
        }
        Report::LinkStats(s) => info!(
            "link: req {=u32} rep {=u32} timeouts {=u32} wake {=u32} retries {=u32} crc {=u32} framing {=u32} invalid {=u32} nack {=u32}/{=u32}/{=u32} skipped {=u32} unsolicited {=u32} failures {=u32} latency {=u32}/{=u32}/{=u32} us",
            s.requests,
            s.replies,
            s.timeouts,
            s.wakeup_resends,
            s.retries,
            s.crc_errors,
            s.framing_errors,
            s.invalid_replies,
            s.nacks_command,
            s.nacks_crc,
            s.nacks_other,
            s.skipped_bytes,
            s.unsolicited,
            s.failures,
            s.latency_min_us,
            s.latency_mean_us(),
            s.latency_max_us
        ),
        Report::Dropped(n) => warn!("{=u32} log reports dropped", n),
    }
}
