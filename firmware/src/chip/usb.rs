//! The host link (feature `host-link`) on the wire the board's own USB
//! connector reaches (`BOARD.host`): the chip's USB-Serial-JTAG, or UART0 at
//! 115 200 8N1 on a board whose connector is a USB-UART bridge. Its two tasks
//! and the [`HostPort`] the bridge task drives; the bridge's log lines go out
//! as `log` lines too. Without the feature, [`HostPort`] is a stub whose calls
//! the compiler removes, so the bridge task reads the same either way.

#[cfg(not(feature = "host-link"))]
pub use off::*;
#[cfg(feature = "host-link")]
pub use on::*;

#[cfg(feature = "host-link")]
mod on {
    use defmt::info;
    use embassy_executor::Spawner;
    use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
    use embassy_sync::pipe::Pipe;
    use embassy_sync::signal::Signal;
    use embassy_time::{with_timeout, Duration};
    use esp_hal::gpio::AnyPin;
    use esp_hal::peripherals::{UART0, USB_DEVICE};
    use esp_hal::uart::{Config as UartConfig, Uart, UartRx, UartTx};
    use esp_hal::usb::usb_serial_jtag::{UsbSerialJtag, UsbSerialJtagRx, UsbSerialJtagTx};
    use esp_hal::Async;
    use tinybms_firmware::boards::{Chip, HostWire};
    use tinybms_firmware::config::state::ConfigState;
    use tinybms_firmware::config::store::{Saved, StoreError};
    use tinybms_firmware::config::Config;
    use tinybms_firmware::host_link::{HostLink, OUT_LINE_MAX};
    use tinybms_firmware::{Bridge, Report};

    use crate::{now_us, spawn, BOARD};

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

    /// The host link on the USB cable: the USB-Serial-JTAG (CDC-ACM; its JTAG
    /// side, probe-rs and RTT, is a separate USB interface of the same device:
    /// both run together), or UART0 through the board's USB-UART bridge.
    pub fn start(
        spawner: Spawner,
        usb: USB_DEVICE<'static>,
        uart0: UART0<'static>,
        config: &Config,
    ) {
        info!(
            "host link on {=str}: {=str}, telemetry every {=u32} ms",
            BOARD.host.name(),
            if config.read_only {
                "read-only"
            } else {
                "read-write"
            },
            config.stream_period_ms
        );
        match BOARD.host {
            HostWire::UsbSerialJtag => {
                let (usb_rx, usb_tx) = UsbSerialJtag::new(usb).into_async().split();
                spawn(spawner, usb_rx_task(usb_rx));
                spawn(spawner, usb_tx_task(usb_tx));
            }
            HostWire::Uart0 => {
                // UART0's own pins (the ROM and the bootloader print there too).
                let (tx, rx) = match BOARD.chip {
                    Chip::Esp32c3 => (21, 20),
                    Chip::Esp32c6 => (16, 17),
                };
                // SAFETY: UART0's pins, used by nothing else in this build: the
                // board check keeps every signal of the bridge off them, and
                // `log-uart` (defmt on UART0) is refused with this host wire (main.rs).
                let (tx, rx) = unsafe { (AnyPin::steal(tx), AnyPin::steal(rx)) };
                match Uart::new(uart0, UartConfig::default().with_baudrate(115_200)) {
                    Ok(u) => {
                        let (rx, tx) = u.with_tx(tx).with_rx(rx).into_async().split();
                        spawn(spawner, uart0_rx_task(rx));
                        spawn(spawner, uart0_tx_task(tx));
                        // No line state on a UART: a host says `hello`; the
                        // first one is sent at boot.
                        HOST_CONNECTED.signal(());
                    }
                    Err(_) => defmt::warn!("host link: UART0 config refused"),
                }
            }
        }
    }

    /// The bridge task's side of the host link.
    pub struct HostPort {
        link: HostLink,
        /// When the host link's timers want it called again (set at the end of every
        /// pass, after whatever the pass changed).
        due: u64,
        rx_buf: [u8; 64],
        line: [u8; OUT_LINE_MAX],
        /// Packs in parallel: the battery from the CAN task.
        #[cfg(feature = "can")]
        battery: Option<
            embassy_sync::watch::Receiver<
                'static,
                embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex,
                tinybms_firmware::inverter::packs::BatteryView,
                2,
            >,
        >,
    }

    impl HostPort {
        pub fn new(bridge: &Bridge, config: &Config) -> Self {
            let mut link = HostLink::new(config.host_link(BOARD.chip.name()), now_us());
            let due = link.poll(now_us(), bridge);
            Self {
                link,
                due,
                rx_buf: [0; 64],
                line: [0; OUT_LINE_MAX],
                #[cfg(feature = "can")]
                battery: crate::can::BATTERY.receiver(),
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
        pub fn handle_rx(&mut self, n: usize, bridge: &mut Bridge, config: &mut ConfigState) {
            let bytes = self.rx_buf.get(..n).unwrap_or(&[]);
            self.link.handle_rx(now_us(), bytes, bridge, config);
        }

        /// The running configuration changed.
        pub fn apply_config(&mut self, running: &Config) {
            self.link.apply_config(now_us(), running);
        }

        /// The configuration's save is done.
        pub fn on_config_saved(&mut self, result: Result<Saved, StoreError>) {
            self.link.on_config_saved(result);
        }

        /// End of a bridge-task pass: a (re)connected host gets `hello`; streamed
        /// telemetry when due; encoded lines move to the USB writer while its pipe
        /// has room for a whole one (no I/O here, never a wait).
        pub fn after_pass(&mut self, bridge: &Bridge, config: &ConfigState) {
            if HOST_CONNECTED.try_take().is_some() {
                self.link.connected(now_us());
            }
            while let Some((level, line)) = crate::log::for_host() {
                self.link.log(level, line.as_str());
            }
            #[cfg(feature = "can")]
            if let Some(v) = self.battery.as_mut().and_then(|r| r.try_changed()) {
                self.link.on_battery(Some(v));
            }
            self.due = self.link.poll(now_us(), bridge);
            while HOST_TX.free_capacity() >= OUT_LINE_MAX {
                let Some(n) = self
                    .link
                    .next_line(now_us(), bridge, config, &mut self.line)
                else {
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

    /// Host → bridge over UART0 (see [`usb_rx_task`]). Receive errors (a
    /// framing error while the USB-UART bridge powers up) are skipped: the line
    /// assembler resyncs at the next newline.
    #[embassy_executor::task]
    async fn uart0_rx_task(mut rx: UartRx<'static, Async>) {
        let mut buf = [0u8; 64];
        loop {
            if let Ok(n) = rx.read_async(&mut buf).await {
                HOST_RX.write_all(buf.get(..n).unwrap_or(&[])).await;
            }
        }
    }

    /// Bridge → host over UART0: the UART always drains (115 200 Bd, about
    /// 11 KB/s), whether or not anyone listens.
    #[embassy_executor::task]
    async fn uart0_tx_task(mut tx: UartTx<'static, Async>) {
        let mut buf = [0u8; USB_WRITE_CHUNK];
        loop {
            let n = HOST_TX.read(&mut buf).await;
            let mut rest = buf.get(..n).unwrap_or(&[]);
            while !rest.is_empty() {
                match tx.write_async(rest).await {
                    Ok(k) => rest = rest.get(k..).unwrap_or(&[]),
                    Err(_) => break,
                }
            }
        }
    }
}

/// Without the host link: nothing to drive (the compiler removes these calls).
#[cfg(not(feature = "host-link"))]
mod off {
    use embassy_executor::Spawner;
    use esp_hal::peripherals::{UART0, USB_DEVICE};
    use tinybms_firmware::config::state::ConfigState;
    use tinybms_firmware::config::store::{Saved, StoreError};
    use tinybms_firmware::config::Config;
    use tinybms_firmware::{Bridge, Report};

    /// Nothing to start: the USB port stays unused.
    pub fn start(_: Spawner, _: USB_DEVICE<'static>, _: UART0<'static>, _: &Config) {}

    pub struct HostPort;

    impl HostPort {
        pub fn new(_: &Bridge, _: &Config) -> Self {
            Self
        }
        pub fn apply_config(&mut self, _: &Config) {}
        pub fn on_config_saved(&mut self, _: Result<Saved, StoreError>) {}
        pub fn on_report(&mut self, _: &Report) {}
        pub fn on_uart_tx(&mut self, _: &[u8]) {}
        pub fn on_uart_rx(&mut self, _: &[u8]) {}
        pub fn due(&self) -> u64 {
            u64::MAX
        }
        pub async fn receive(&mut self) -> usize {
            core::future::pending().await
        }
        pub fn handle_rx(&mut self, _: usize, _: &mut Bridge, _: &mut ConfigState) {}
        pub fn after_pass(&mut self, _: &Bridge, _: &ConfigState) {}
    }
}
