//! Reports → defmt lines. The words are the library's (`tinybms_firmware::text`,
//! tested on the host); here they only get their level.

use defmt::{info, warn};
use tinybms_firmware::config::state::{ConfigState, Note};
#[cfg(feature = "can")]
use tinybms_firmware::inverter::InverterReport;
use tinybms_firmware::text::{self, Line};
use tinybms_firmware::{Level, Report};

/// Logs `line` at `level`.
pub fn line(level: Level, line: &Line) {
    match level {
        Level::Info => info!("{=str}", line.as_str()),
        Level::Warn => warn!("{=str}", line.as_str()),
    }
}

/// One line per bridge report.
pub fn report(r: &Report) {
    let mut out = Line::new();
    text::report(r, &mut out);
    line(r.level(), &out);
}

/// One line per configuration note (secrets only as set/unset).
pub fn config(n: &Note, config: &ConfigState) {
    let mut out = Line::new();
    text::config_note(n, config, &mut out);
    line(text::config_level(n), &out);
}

/// One line per inverter report.
#[cfg(feature = "can")]
pub fn inverter(r: &InverterReport) {
    let mut out = Line::new();
    text::inverter(r, &mut out);
    line(r.level(), &out);
}
