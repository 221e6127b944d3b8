//! The one line a panicking chip writes to the host, on a board whose log
//! reaches the cable only through the host link (UART0): a `log` line at
//! `warn`, "panic, restarting; backtrace 0x…", written byte by byte through
//! the ROM's console output (no driver, no allocation, whatever state the
//! tasks were in). It starts with a newline, ending whatever line the writer
//! was in the middle of. The words and the bytes are made here; the shell's
//! panic handler (`src/chip/panic.rs`) only hands each byte to the ROM.

use crate::Instant;

/// After a panic, the time the log reader gets to fetch the panic line and
/// the backtrace before the reset (RTT is polled by the host; UART0 drains
/// its FIFO): shorter than the watchdog ([`crate::station::pumps::WATCHDOG_US`]),
/// which is only the fallback.
pub const RESET_DELAY_US: Instant = crate::SECOND;
const _: () = assert!(RESET_DELAY_US < crate::station::pumps::WATCHDOG_US);

/// Return addresses the line carries at most.
pub const FRAMES_MAX: usize = 10;

/// Writes the line for the return addresses `pcs` (innermost first; at most
/// [`FRAMES_MAX`]) through `out`.
pub fn write_line(pcs: impl IntoIterator<Item = u32>, mut out: impl FnMut(&[u8])) {
    out(b"\n{\"type\":\"log\",\"level\":\"warn\",\"text\":\"panic, restarting; backtrace");
    for pc in pcs.into_iter().take(FRAMES_MAX) {
        let mut hex = *b" 0x00000000";
        for (i, d) in hex.iter_mut().skip(3).enumerate() {
            let n = (pc >> (28 - 4 * i as u32)) & 0xF;
            *d = b"0123456789abcdef".get(n as usize).copied().unwrap_or(b'0');
        }
        out(&hex);
    }
    out(b"\"}\n");
}
