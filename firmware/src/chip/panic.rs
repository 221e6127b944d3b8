//! The panic handler.

/// After a panic, time for the log reader to fetch the panic line and backtrace
/// before the reset (RTT is polled by the host; UART0 drains its FIFO). Shorter
/// than the watchdog's [`crate::WDT_TIMEOUT`], so the watchdog is only the fallback.
const PANIC_RESET_DELAY_US: u32 = 1_000_000;

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
