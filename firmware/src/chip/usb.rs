//! The host link's wire (feature `host-link`), the one the board's own USB
//! connector reaches (`BOARD.host`): the chip's USB-Serial-JTAG, or UART0 at
//! 115 200 8N1 on a board whose connector is a USB-UART bridge. Two pumps per
//! wire: bytes from the host into [`wires::HOST_RX`], whole lines from
//! [`wires::HOST_TX`] to the host.
//!
//! **A host that does not read never holds the station back.** The station
//! only puts lines into the pipe when one fits whole and never waits on it.
//! The writer gives a line whole or not at all, and waits a bounded time:
//!
//! * USB-Serial-JTAG (esp-hal 1.2): `write_async` puts up to 64 bytes in the
//!   IN endpoint's FIFO, sets WR_DONE, then waits for the IN_EMPTY interrupt
//!   *and* the `serial_in_ep_data_free` bit; when no host reads (a USB charger,
//!   a power-only cable, a closed terminal) it never returns, and on an
//!   endpoint that keeps raising the interrupt without room it loops, taking
//!   the interrupt-enable lock each time. So the writer follows the library's
//!   rule (`tinybms_firmware::host_link::writer`, tested on the host): a line
//!   starts only when its first byte fits (`write_byte_nb`, tried every
//!   [`PROBE_STEP`]), the rest has a deadline, an absent host's lines are
//!   dropped whole without touching the driver, and a probe a second finds it
//!   again (`hello` follows).
//! * UART0: the UART always drains (115 200 Bd, about 11 KB/s), whether or
//!   not anyone listens; `write_async` waits only for FIFO room. A write error
//!   drops the rest of that line and the writer ends it with a newline.
//!
//! Lines dropped on the wire are counted ([`wires::host_lines_dropped`]) and
//! reach the host link's `dropped_lines` (`stats`, `hello`).

#[cfg(not(feature = "host-link"))]
pub use off::*;
#[cfg(feature = "host-link")]
pub use on::*;

#[cfg(feature = "host-link")]
mod on {
    use embassy_executor::Spawner;
    use embassy_time::{with_deadline, with_timeout, Duration, Instant, Timer};
    use esp_hal::gpio::AnyPin;
    use esp_hal::peripherals::{UART0, USB_DEVICE};
    use esp_hal::uart::{Config as UartConfig, Uart, UartRx, UartTx};
    use esp_hal::usb::usb_serial_jtag::{UsbSerialJtag, UsbSerialJtagRx, UsbSerialJtagTx};
    use esp_hal::Async;
    use tinybms_firmware::boards::{HostWire, HOST_UART_BAUD};
    use tinybms_firmware::config::Config;
    use tinybms_firmware::host_link::writer::{self, DrainingPort, LineWriter, Pieces, Start};
    use tinybms_firmware::text::Boot;

    use crate::{now_us, spawn, wires, BOARD};

    /// How often it looks for room meanwhile (the library's).
    const PROBE_STEP: Duration = Duration::from_micros(writer::PROBE_STEP_US);
    /// Longest a UART0 write of a piece may take: the library's limit for the
    /// rest of a started line ([`tinybms_firmware::host_link::writer::LINE_WRITE_US`];
    /// a UART drains whether anyone reads or not, so only a fault meets it).
    const LINE_WRITE_TIMEOUT: Duration = Duration::from_micros(writer::LINE_WRITE_US);

    /// The host link on the USB cable: the USB-Serial-JTAG (CDC-ACM; its JTAG
    /// side, probe-rs and RTT, is a separate USB interface of the same device:
    /// both run together), or UART0 through the board's USB-UART bridge.
    pub fn start(
        spawner: Spawner,
        usb: USB_DEVICE<'static>,
        uart0: UART0<'static>,
        config: &Config,
    ) -> Option<Boot> {
        match BOARD.host {
            HostWire::UsbSerialJtag => {
                let (usb_rx, usb_tx) = UsbSerialJtag::new(usb).into_async().split();
                spawn(spawner, usb_rx_task(usb_rx));
                spawn(spawner, usb_tx_task(usb_tx));
            }
            HostWire::Uart0 => {
                // UART0's own pins (the ROM and the bootloader print there too).
                let (tx, rx) = BOARD.chip.uart0_pins();
                // SAFETY: UART0's pins, used by nothing else in this build: the
                // board check keeps every signal of the bridge off them, and
                // `log-uart` (defmt on UART0) is refused with this host wire (main.rs).
                let (tx, rx) = unsafe { (AnyPin::steal(tx), AnyPin::steal(rx)) };
                match Uart::new(uart0, UartConfig::default().with_baudrate(HOST_UART_BAUD)) {
                    Ok(u) => {
                        let (rx, tx) = u.with_tx(tx).with_rx(rx).into_async().split();
                        spawn(spawner, uart0_rx_task(rx));
                        spawn(spawner, uart0_tx_task(tx));
                        // No line state on a UART: a host says `hello`; the
                        // first one is sent at boot.
                        wires::HOST_CONNECTED.signal(());
                        wires::wake();
                    }
                    Err(_) => defmt::warn!("host link: UART0 config refused"),
                }
            }
        }
        Some(Boot::HostLink {
            wire: Some(BOARD.host),
            read_only: config.read_only,
            stream_period_ms: config.stream_period_ms,
        })
    }

    /// The next piece of a line from [`wires::HOST_TX`] (the library's
    /// [`Pieces`] split what was read at newlines; reads when they are used up).
    async fn next_piece(pieces: &mut Pieces) -> (&[u8], bool, bool) {
        while !pieces.has_piece() {
            if let Some(space) = pieces.space() {
                let n = wires::HOST_TX.read(space).await;
                pieces.filled(n);
            }
        }
        pieces.take().map_or((&[][..], false, false), |p| {
            (p.bytes, p.starts_line, p.ends_line)
        })
    }

    /// Host → station: bytes from the USB port into [`wires::HOST_RX`]. Waits
    /// (and so makes the host wait) while the station has not taken the
    /// previous ones.
    #[embassy_executor::task]
    async fn usb_rx_task(mut rx: UsbSerialJtagRx<'static, Async>) {
        use embedded_io_async::Read;
        let mut buf = [0u8; 64];
        loop {
            let Ok(n) = rx.read(&mut buf).await; // the error type is `Infallible`
            wires::HOST_RX.write_all(buf.get(..n).unwrap_or(&[])).await;
            wires::wake();
        }
    }

    /// Tries to put `byte` in the IN FIFO, every [`PROBE_STEP`], for at most
    /// `wait`; whether it went in.
    async fn start_line(
        tx: &mut UsbSerialJtagTx<'static, Async>,
        byte: u8,
        wait: Duration,
    ) -> bool {
        let until = Instant::now() + wait;
        loop {
            if tx.write_byte_nb(byte).is_ok() {
                return true;
            }
            if Instant::now() >= until {
                return false;
            }
            Timer::after(PROBE_STEP).await;
        }
    }

    /// Hands the writer's counts to the station.
    fn report(w: &mut LineWriter) {
        let dropped = w.take_dropped();
        if dropped > 0 {
            wires::host_lines_dropped(dropped);
        }
        if w.take_back() {
            wires::HOST_CONNECTED.signal(());
        }
        wires::wake();
    }

    /// Station → host over USB: the library's [`LineWriter`] says what to do
    /// with each line (see the module documentation).
    #[embassy_executor::task]
    async fn usb_tx_task(mut tx: UsbSerialJtagTx<'static, Async>) {
        use embedded_io_async::Write;
        let mut pieces = Pieces::new();
        let mut w = LineWriter::new();
        let mut dropping = false;
        let mut deadline = Instant::now();
        loop {
            let (mut piece, starts_line, ends_line) = next_piece(&mut pieces).await;
            if starts_line {
                let Some(&first) = piece.first() else {
                    continue;
                };
                dropping = true;
                if let Start::Try {
                    wait_us,
                    newline_first,
                } = w.line_ready(now_us())
                {
                    let probe = if newline_first { b'\n' } else { first };
                    let ok = start_line(&mut tx, probe, Duration::from_micros(wait_us)).await;
                    if let Some(d) = w.started(now_us(), ok) {
                        deadline = Instant::from_micros(d);
                        dropping = false;
                        if !newline_first {
                            piece = piece.get(1..).unwrap_or(&[]);
                        }
                    }
                }
                report(&mut w);
            }
            if !dropping {
                let sent = with_deadline(deadline, async {
                    if starts_line {
                        // The first byte goes out alone: `write_async` fills
                        // 64 bytes without looking, and expects an empty FIFO.
                        tx.flush().await?;
                    }
                    tx.write_all(piece).await?;
                    if ends_line {
                        tx.flush().await?;
                    }
                    Ok::<(), core::convert::Infallible>(())
                })
                .await;
                if !matches!(sent, Ok(Ok(()))) {
                    w.finished(now_us(), false);
                    dropping = true;
                    report(&mut w);
                } else if ends_line {
                    w.finished(now_us(), true);
                }
            }
        }
    }

    /// Host → station over UART0 (see [`usb_rx_task`]). Receive errors (a
    /// framing error while the USB-UART bridge powers up) are skipped: the line
    /// assembler resyncs at the next newline.
    #[embassy_executor::task]
    async fn uart0_rx_task(mut rx: UartRx<'static, Async>) {
        let mut buf = [0u8; 64];
        loop {
            if let Ok(n) = rx.read_async(&mut buf).await {
                wires::HOST_RX.write_all(buf.get(..n).unwrap_or(&[])).await;
                wires::wake();
            }
        }
    }

    /// Station → host over UART0: whole lines; the library's [`DrainingPort`]
    /// says what a failed write costs (the rest of its line, ended with a
    /// newline, counted).
    #[embassy_executor::task]
    async fn uart0_tx_task(mut tx: UartTx<'static, Async>) {
        let mut pieces = Pieces::new();
        let mut port = DrainingPort::new();
        loop {
            let (piece, _, ends_line) = next_piece(&mut pieces).await;
            let mut rest = piece;
            while !rest.is_empty() && port.writing() {
                match with_timeout(LINE_WRITE_TIMEOUT, tx.write_async(rest)).await {
                    Ok(Ok(k)) if k > 0 => rest = rest.get(k..).unwrap_or(&[]),
                    _ => {
                        if port.failed() {
                            let _ = with_timeout(LINE_WRITE_TIMEOUT, tx.write_async(b"\n")).await;
                        }
                    }
                }
            }
            if ends_line {
                let dropped = port.line_ended();
                if dropped > 0 {
                    wires::host_lines_dropped(dropped);
                }
            }
        }
    }
}

/// Without the host link: the USB port stays unused.
#[cfg(not(feature = "host-link"))]
mod off {
    use embassy_executor::Spawner;
    use esp_hal::peripherals::{UART0, USB_DEVICE};
    use tinybms_firmware::config::Config;

    /// Nothing to start, no boot line.
    pub fn start(
        _: Spawner,
        _: USB_DEVICE<'static>,
        _: UART0<'static>,
        _: &Config,
    ) -> Option<tinybms_firmware::text::Boot> {
        None
    }
}
