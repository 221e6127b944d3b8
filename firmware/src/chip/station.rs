//! The station task: the library's sans-IO [`Station`] (the bridge, its
//! configuration, the host link, the inverter output, what MQTT publishes)
//! on UART1 to the TinyBMS, with every other wire reached through the queues
//! of [`crate::wires`]. It decides nothing: it does what [`Station::poll`]
//! says, hands in what arrived, and waits for the earliest of the station's
//! wake time, a byte from the BMS, a byte from the host or anything a pump
//! queued.

use defmt::warn;
use embassy_executor::Spawner;
use embassy_futures::select::{select4, Either4};
use embassy_time::{Instant, Timer};
use esp_hal::gpio::AnyPin;
use esp_hal::peripherals::{TIMG0, UART1};
use esp_hal::timer::timg::Wdt;
use esp_hal::uart::{Config as UartConfig, RxConfig, RxError, Uart, UartRx, UartTx};
use esp_hal::Async;
use tinybms_firmware::bms::profile;
use tinybms_firmware::bms::uart::{self, RxErrors, WriteError};
use tinybms_firmware::station::pumps::bounded_wait;
use tinybms_firmware::station::{Action, Station};
use tinybms_firmware::text::Boot;

#[cfg(feature = "can")]
use tinybms_firmware::inverter::port::{CanCommand, CanDone};

use crate::{log, now_us, ota, spawn, store, wires, BOARD};

/// UART1 to the TinyBMS on the board's pins, and the station task on it.
pub fn start(
    spawner: Spawner,
    uart1: UART1<'static>,
    wdt: Wdt<TIMG0<'static>>,
    station: &'static mut Station,
    store: Option<store::ChipStore>,
    chip_ota: ota::ChipOta,
) {
    // SAFETY: `AnyPin::steal` hands out a second handle to a GPIO. These two GPIOs
    // are used nowhere else: the shell never touches `p.GPIOn`, and the board
    // check (const, main.rs) guarantees they exist on the chip, are distinct from
    // each other and from the CAN pins, and are not flash/USB/UART0 pins.
    let (tx_pin, rx_pin) = unsafe { (AnyPin::steal(BOARD.bms_tx), AnyPin::steal(BOARD.bms_rx)) };
    let uart_config = UartConfig::default()
        .with_baudrate(uart::BAUD)
        .with_rx(RxConfig::default().with_fifo_full_threshold(uart::RX_FIFO_FULL_THRESHOLD));
    let uart = Uart::new(uart1, uart_config)
        .expect("UART1 config")
        .with_tx(tx_pin)
        .with_rx(rx_pin)
        .into_async();
    let (rx, tx) = uart.split();
    log::boot(
        station,
        &Boot::Uart {
            baud: uart::BAUD,
            pins: Some((BOARD.bms_tx, BOARD.bms_rx, uart::RX_FIFO_FULL_THRESHOLD)),
        },
    );
    // Before the task's first poll: the profile's boot line is kept too.
    submit_profile(station);
    spawn(spawner, station_task(rx, tx, wdt, station, store, chip_ota));
}

/// Logs the receive error the library's rule says is due (its words are
/// the driver's).
fn log_rx_errors(rx_errors: &mut RxErrors<RxError>) {
    if let Some((e, count)) = rx_errors.due(now_us()) {
        warn!("uart rx error: {} ({=u32} so far)", e, count);
    }
}

/// Does what the station says; see the module documentation.
///
/// When the timer wins the race against `read_async`, bytes may already be in
/// the FIFO: below the full threshold, the RX-timeout interrupt (10 symbols ≈
/// 0.9 ms) has not fired yet. They are drained with `read_buffered` and handed
/// in *before* the station handles the deadline, so a reply that ends just at
/// the deadline still completes its transaction
/// (host-tests/tests/deadline_drain.rs).
#[embassy_executor::task]
async fn station_task(
    mut rx: UartRx<'static, Async>,
    mut tx: UartTx<'static, Async>,
    mut wdt: Wdt<TIMG0<'static>>,
    station: &'static mut Station,
    mut store: Option<store::ChipStore>,
    mut chip_ota: ota::ChipOta,
) {
    let mut rx_errors = RxErrors::new();
    let mut pumps = Pumps::new();
    loop {
        wdt.feed();
        pumps.take_in(station);
        pumps.hand_out(station);
        match station.poll(now_us()) {
            Action::Log(item) => {
                log::logged(station, &item);
                log_rx_errors(&mut rx_errors);
            }
            Action::Transmit => {
                // The line is quiet until the request is out.
                log_rx_errors(&mut rx_errors);
                // Written from where the link keeps them (no copy); every
                // byte, through the driver's partial writes.
                let sent =
                    uart::write_all(station.transmit_bytes(), async |b| tx.write_async(b).await)
                        .await;
                match sent {
                    Ok(()) => {}
                    Err(WriteError::Driver(e)) => warn!("uart tx error: {}", e),
                    Err(WriteError::TookNothing) => warn!("uart tx: the driver took nothing"),
                }
                if let Err(e) = tx.flush_async().await {
                    warn!("uart flush error: {}", e);
                }
            }
            Action::Save => {
                let result = store::save(&mut store, station.record());
                station.saved(result);
            }
            Action::Flash(op) => {
                let ok = chip_ota.run(station.ota(), op, station.program_bytes());
                station.flashed(now_us(), ok);
            }
            Action::Restart => esp_hal::system::software_reset(),
            Action::History(op) => {
                let ok = tinybms_firmware::history::log::run(&mut chip_ota, op);
                station.history_done(ok);
            }
            Action::HistoryRead(at, len) => {
                use tinybms_firmware::update::flash::OtaFlash;
                let mut b = [0u8; tinybms_firmware::history::log::READ_MAX];
                let n = usize::from(len).min(b.len());
                let ok = chip_ota.read(at, &mut b[..n]);
                station.history_read(ok.then_some(&b[..n]));
            }
            #[cfg(feature = "can")]
            Action::Can(frame) => {
                if wires::CAN_COMMAND
                    .try_send(CanCommand::Send(frame))
                    .is_err()
                {
                    // No CAN task takes it (cannot happen: one at a time).
                    station.can_done(now_us(), CanDone::Failed);
                }
            }
            #[cfg(feature = "can")]
            Action::CanRecover => {
                if wires::CAN_COMMAND.try_send(CanCommand::Recover).is_err() {
                    station.can_done(now_us(), CanDone::Recovered(false));
                }
            }
            #[cfg(not(feature = "can"))]
            Action::Can(_) | Action::CanRecover => {}
            #[cfg(feature = "wifi")]
            Action::Wifi(req) => {
                if let Err(embassy_sync::channel::TrySendError::Full(req)) =
                    wires::WIFI_REQUEST.try_send(req)
                {
                    // One at a time: the station asks again only after a
                    // result, so this is a Wi-Fi task that is not there.
                    station.wifi_unavailable(now_us(), &req);
                }
            }
            #[cfg(not(feature = "wifi"))]
            Action::Wifi(_) => {}
            Action::WaitUntil(t) => {
                let deadline = Instant::from_micros(bounded_wait(t, now_us()));
                // `read_async`, `Pipe::read` and `Signal::wait` are
                // cancellation-safe: racing them against a timer loses nothing.
                // The UART driver writes straight into the bridge's receive
                // space (no copy of ours).
                match select4(
                    rx.read_async(station.rx_buffer()),
                    Timer::at(deadline),
                    pumps.host_receive(),
                    wires::WAKE.wait(),
                )
                .await
                {
                    Either4::First(Ok(n)) => station.received(now_us(), n),
                    Either4::First(Err(e)) => rx_errors.record(e),
                    Either4::Third(n) => pumps.host_received(station, n),
                    Either4::Fourth(()) => {}
                    Either4::Second(()) => {
                        // Bytes already received but not yet signalled go in
                        // before the deadline is handled by the next `poll`.
                        for _ in 0..uart::DEADLINE_DRAIN_READS {
                            match rx.read_buffered(station.rx_buffer()) {
                                Ok(0) => break,
                                Ok(n) => station.received(now_us(), n),
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
    }
}

/// The station's side of the queues to the other tasks.
struct Pumps {
    #[cfg(feature = "host-link")]
    rx: [u8; 64],
    #[cfg(feature = "host-link")]
    line: [u8; tinybms_firmware::host_link::OUT_LINE_MAX],
    #[cfg(feature = "wifi")]
    generation: Option<u32>,
}

impl Pumps {
    fn new() -> Self {
        Self {
            #[cfg(feature = "host-link")]
            rx: [0; 64],
            #[cfg(feature = "host-link")]
            line: [0; tinybms_firmware::host_link::OUT_LINE_MAX],
            #[cfg(feature = "wifi")]
            generation: None,
        }
    }

    /// Everything the pumps queued, into the station (never waits).
    #[allow(clippy::unused_self)]
    fn take_in(&mut self, station: &mut Station) {
        #[cfg(feature = "can")]
        {
            while let Ok(done) = wires::CAN_DONE.try_receive() {
                station.can_done(now_us(), done);
            }
            while let Ok(f) = wires::CAN_RX.try_receive() {
                station.can_received(now_us(), f.id, f.bytes());
            }
        }
        #[cfg(feature = "host-link")]
        {
            if let Some(pressed) = wires::BUTTON.try_take() {
                station.button(now_us(), pressed);
            }
            let dropped = wires::take_host_lines_dropped();
            if dropped > 0 {
                station.host_lines_dropped(dropped);
            }
            if wires::HOST_CONNECTED.try_take().is_some() {
                station.host_connected(now_us());
            }
            while let Ok((level, line)) = wires::FOREIGN_LOG.try_receive() {
                station.foreign_log(level, line.as_str());
            }
            #[cfg(feature = "wifi")]
            if let Some(state) = wires::MQTT_STATE.try_take() {
                station.mqtt_state(state);
            }
            #[cfg(feature = "wifi")]
            while let Ok(done) = wires::WIFI_DONE.try_receive() {
                match done {
                    wires::WifiDone::Joined(r) => station.wifi_joined(now_us(), r),
                    wires::WifiDone::Scanned(list) => station.wifi_scanned(now_us(), &list),
                    wires::WifiDone::Link(l) => station.wifi_link(l),
                }
            }
            #[cfg(feature = "wifi")]
            if let Some(rssi) = wires::WIFI_RSSI.try_take() {
                station.wifi_rssi(rssi);
            }
            #[cfg(feature = "wifi")]
            {
                match wires::UPDATE_CONNECTION.try_take() {
                    Some(true) => station.update_port_connected(now_us()),
                    Some(false) => station.update_port_closed(),
                    None => {}
                }
                let mut buf = [0u8; 256];
                while let Ok(n) = wires::UPDATE_RX.try_read(&mut buf) {
                    station.update_port_rx(now_us(), buf.get(..n).unwrap_or(&[]));
                }
            }
            #[cfg(feature = "wifi")]
            if let Some(r) = wires::RADIO.try_take() {
                station.radio(r);
            }
        }
        #[cfg(not(any(feature = "host-link", feature = "can")))]
        let _ = station;
    }

    /// What the station has for the other tasks, into their queues (never
    /// waits: a host line goes only when the pipe holds it whole).
    #[allow(clippy::unused_self)]
    fn hand_out(&mut self, station: &mut Station) {
        // Whole lines only (the pipe's `try_write` stops at its wrap point).
        #[cfg(feature = "host-link")]
        station.hand_out_host_lines(now_us(), &mut &wires::HOST_TX, &mut self.line);
        #[cfg(feature = "wifi")]
        {
            station.hand_out_update_port_lines(now_us(), &mut &wires::UPDATE_TX, &mut self.line);
            // A copy into the Watch, no I/O: only when it changed.
            if self.generation != Some(station.generation()) {
                self.generation = Some(station.generation());
                wires::PUBLISHED.sender().send(station.published(now_us()));
            }
            while wires::MQTT_EVENTS.free_capacity() > 0 {
                let Some(e) = station.take_event() else {
                    break;
                };
                let _ = wires::MQTT_EVENTS.try_send(e);
            }
        }
        #[cfg(not(any(feature = "host-link", feature = "wifi")))]
        let _ = station;
    }

    /// Waits for bytes from the host (cancellation-safe); their count.
    async fn host_receive(&mut self) -> usize {
        #[cfg(feature = "host-link")]
        return wires::HOST_RX.read(&mut self.rx).await;
        #[cfg(not(feature = "host-link"))]
        core::future::pending().await
    }

    /// The `n` bytes [`Pumps::host_receive`] got, into the station.
    #[allow(clippy::unused_self)]
    fn host_received(&mut self, station: &mut Station, n: usize) {
        #[cfg(feature = "host-link")]
        station.host_rx(now_us(), self.rx.get(..n).unwrap_or(&[]));
        #[cfg(not(feature = "host-link"))]
        let _ = (station, n);
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
fn submit_profile(station: &mut Station) {
    let queued =
        STARTUP_PROFILE.is_empty() || station.submit_profile(STARTUP_PROFILE.as_slice()).is_ok();
    log::boot(
        station,
        &Boot::Profile {
            settings: STARTUP_PROFILE.len(),
            queued,
        },
    );
}
