//! The BOOT button: samples to the station, which lifts read-only when it is
//! held for 5 s (`tinybms_firmware::config::button`, tested on the host). The
//! pin is the board's BOOT button from the board table (GPIO9 on every
//! supported board: a strapping pin, read here only once the firmware runs;
//! held while the chip resets, it starts the ROM's download mode instead).

use embassy_executor::Spawner;
use embassy_time::{Duration, Timer};
use esp_hal::gpio::{AnyPin, Input, InputConfig, Pull};
use tinybms_firmware::config::button::{Samples, SAMPLE_PERIOD_US};

use crate::{spawn, wires, BOARD};

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

/// Samples the pin every [`SAMPLE_PERIOD_US`]; the library's [`Samples`]
/// says which reach the station (every one while the button is down, and the
/// one that says it is up: an untouched button never wakes the station task).
#[embassy_executor::task]
async fn button_task(pin: Input<'static>) {
    let mut samples = Samples::new();
    loop {
        // The button pulls the pin low.
        if let Some(pressed) = samples.take(pin.is_low()) {
            wires::BUTTON.signal(pressed);
            wires::wake();
        }
        Timer::after(Duration::from_micros(SAMPLE_PERIOD_US)).await;
    }
}
