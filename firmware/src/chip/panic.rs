//! The panic handler.

#[cfg(feature = "host-link")]
unsafe extern "C" {
    /// The ROM's console output: one byte to UART0 (blocking).
    fn esp_rom_uart_tx_one_char(c: u8) -> i32;
}

/// The library's delay before the reset (the log reader fetches the panic line).
const PANIC_RESET_DELAY_US: u32 = tinybms_firmware::host_link::panic::RESET_DELAY_US as u32;

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
/// docs/performance.md). The backtrace carries the same location.
#[panic_handler]
fn panic(_info: &core::panic::PanicInfo) -> ! {
    defmt::error!("panic");
    let backtrace = esp_backtrace::Backtrace::capture();
    for frame in backtrace.frames() {
        defmt::error!("  backtrace 0x{=usize:08x}", frame.program_counter());
    }
    #[cfg(feature = "host-link")]
    if matches!(crate::BOARD.host, tinybms_firmware::boards::HostWire::Uart0) {
        // On this board the log only reaches the cable through the host link:
        // the same facts as one `log` line (the library's bytes), written by
        // the ROM (no driver, no allocation, whatever state the UART task was in).
        let pcs = backtrace
            .frames()
            .iter()
            .map(|f| f.program_counter() as u32);
        tinybms_firmware::host_link::panic::write_line(pcs, |b: &[u8]| {
            for &c in b {
                // SAFETY: the ROM's console output (UART0), provided by the ROM
                // linker script of esp-rom-sys; blocking, reentrancy irrelevant
                // here (nothing else runs any more).
                unsafe { esp_rom_uart_tx_one_char(c) };
            }
        });
    }
    esp_hal::rom::ets_delay_us(PANIC_RESET_DELAY_US);
    esp_hal::system::software_reset()
}
