//! Log lines → defmt. The words are the library's (`tinybms_firmware::text`,
//! tested on the host); here they only get their level. The station hands its
//! own lines to the host link itself; lines of other tasks ([`line`]) reach it
//! through [`crate::wires::FOREIGN_LOG`].

use defmt::{info, warn};
use tinybms_firmware::station::{Logged, Station};
use tinybms_firmware::text::{Boot, Line};
use tinybms_firmware::Level;

fn print(level: Level, line: &Line) {
    match level {
        Level::Info => info!("{=str}", line.as_str()),
        Level::Warn => warn!("{=str}", line.as_str()),
    }
}

/// What the station says to log.
pub fn logged(station: &Station, item: &Logged) {
    let mut out = Line::new();
    station.log_text(item, &mut out);
    print(item.level(), &out);
}

/// A line of the boot (image, CAN, host link, UART, profile): logged, and
/// kept by the host link for every host after its `hello`.
pub fn boot(station: &mut Station, line: &Boot) {
    let (level, out) = station.boot_line(line);
    print(level, &out);
}

/// A line of another task: logged, and handed to the host link.
#[cfg_attr(not(feature = "wifi"), allow(dead_code))]
pub fn line(level: Level, line: &Line) {
    print(level, line);
    #[cfg(feature = "host-link")]
    {
        let _ = crate::wires::FOREIGN_LOG.try_send((level, line.clone()));
        crate::wires::wake();
    }
}
