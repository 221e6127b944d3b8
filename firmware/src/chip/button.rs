//! The BOOT button: held down for 5 s while the bridge runs, it lifts
//! read-only (`tinybms_firmware::config::button`, tested on the host). The pin
//! is the board's BOOT button from the board table (GPIO9 on every supported
//! board: a strapping pin, read here only once the firmware runs; held while
//! the chip resets, it starts the ROM's download mode instead).

use embassy_executor::Spawner;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::signal::Signal;
use embassy_time::{Duration, Timer};
use esp_hal::gpio::{AnyPin, Input, InputConfig, Pull};
use tinybms_firmware::config::button::{Hold, SAMPLE_PERIOD_US};

use crate::{now_us, spawn, BOARD};

/// Raised when the button has been held long enough; the bridge task takes it.
pub static UNLOCK: Signal<CriticalSectionRawMutex, ()> = Signal::new();

/// Starts watching the board's BOOT button (when it has one).
pub fn start(spawner: Spawner) {
    if let Some(gpio) = BOARD.boot_button() {
        // SAFETY: the BOOT button's GPIO is used nowhere else: the board check
        // keeps every signal pin off parts on the board, the button included.
        let pin = unsafe { AnyPin::steal(gpio) };
        let input = Input::new(pin, InputConfig::default().with_pull(Pull::Up));
        spawn(spawner, button_task(input));
    }
}

#[embassy_executor::task]
async fn button_task(pin: Input<'static>) {
    let mut hold = Hold::new();
    loop {
        // The button pulls the pin low.
        if hold.sample(now_us(), pin.is_low()) {
            UNLOCK.signal(());
        }
        Timer::after(Duration::from_micros(SAMPLE_PERIOD_US)).await;
    }
}
