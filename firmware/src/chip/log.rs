//! Reports → defmt lines. The words are the library's (`tinybms_firmware::text`,
//! tested on the host); here they only get their level. With the host link,
//! each line also goes to the host as a `log` line (through [`for_host`]: the
//! bridge task hands them on), so the log is on the host link's cable too.

use defmt::{info, warn};
use tinybms_firmware::config::state::{ConfigState, Note};
#[cfg(feature = "can")]
use tinybms_firmware::inverter::InverterReport;
use tinybms_firmware::text::{self, Line};
use tinybms_firmware::{Level, Report};

/// Lines for the host link, from any task; when full, a line is only logged.
#[cfg(feature = "host-link")]
static FOR_HOST: embassy_sync::channel::Channel<
    embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex,
    (Level, Line),
    2,
> = embassy_sync::channel::Channel::new();

/// Logs `line` at `level` (and hands it to the host link).
pub fn line(level: Level, line: &Line) {
    match level {
        Level::Info => info!("{=str}", line.as_str()),
        Level::Warn => warn!("{=str}", line.as_str()),
    }
    #[cfg(feature = "host-link")]
    let _ = FOR_HOST.try_send((level, line.clone()));
}

/// The next line for the host link (the bridge task's pass takes them).
#[cfg(feature = "host-link")]
pub fn for_host() -> Option<(Level, Line)> {
    FOR_HOST.try_receive().ok()
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
