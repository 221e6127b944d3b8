//! How the log reads: the words of every line the bridge logs, in one place.
//!
//! The chip shell writes a [`Report`] or an [`InverterReport`] into a [`Line`]
//! and hands the text to `defmt` as one string; the host simulator prints the
//! same text ([`core::fmt::Display`] for [`Report`] goes through here too). So
//! the words are tested on the host (host-tests/tests/log_text.rs) and the chip
//! prints exactly what the tests saw.
//!
//! Values read as people read them: `3.304 V`, `-12.3 A`, `24.5 °C`,
//! `not connected`, the setting's physical value next to its raw one. Numbers
//! are formatted here, without `core::fmt` (which the chip does not link: see
//! `src/chip/panic.rs`).

use protocol_core::events::{EventId, OnlineStatus};
use protocol_core::settings::Setting;
use protocol_core::views::VersionInfo;

use crate::bms::link::{Failure, LinkStats};
use crate::bridge::report::{permille, Report, SnapshotLine, WriteOutcome};
use crate::inverter::{InverterReport, StaleMode};

pub use crate::log_line::{Line, LINE_MAX};

/// 32 bytes (a key, a Wi-Fi PSK) as 64 lower-case hex digits.
pub fn hex32(bytes: &[u8; 32]) -> heapless::String<64> {
    let mut s = heapless::String::new();
    for b in bytes {
        for n in [b >> 4, b & 0xF] {
            let _ = s.push(char::from_digit(u32::from(n), 16).unwrap_or('0'));
        }
    }
    s
}

/// A status as printed: its name, or `unknown_0xNN`.
fn status(out: &mut Line, s: OnlineStatus) {
    match s {
        OnlineStatus::Unknown(raw) => out.push("unknown_").hex(u32::from(raw)),
        known => out.push(known.name()),
    };
}

/// An event id as printed: `0xNN name` (`unknown_0xNN` for an id no table
/// knows, the style of `replay` and the host link).
fn event_id(out: &mut Line, id: EventId) {
    out.hex(u32::from(id.raw())).push(" ");
    match id {
        EventId::Unknown(raw) => out.push("unknown_").hex(u32::from(raw)),
        known => out.push(known.name()),
    };
}

/// A setting and its value: `over_voltage_cutoff (315) = 3650 (3.650 V)`.
fn setting(out: &mut Line, s: &Setting) {
    out.push(s.id.name())
        .push(" (")
        .uint(u64::from(s.id.address()))
        .push(") = ")
        .int(i64::from(s.value));
    let unit = s.id.register().map(|r| r.unit).unwrap_or("");
    if let Some(d) = crate::units::physical(s.id, s.value) {
        if !unit.is_empty() && d.k > 0 {
            out.push(" (")
                .fixed(d.n, d.k)
                .push(" ")
                .push(unit)
                .push(")");
        }
    }
}

fn snapshot(out: &mut Line, s: &SnapshotLine) {
    out.push("pack ")
        .quantity(s.pack_v, 2, "V")
        .push(" ")
        .quantity(s.current_a, 1, "A")
        .push(", SOC ")
        .quantity(s.soc_percent, 1, "%")
        .push(", cells ")
        .quantity(s.min_cell.1, 3, "V")
        .push(" (#")
        .uint(u64::from(s.min_cell.0))
        .push(") to ")
        .quantity(s.max_cell.1, 3, "V")
        .push(" (#")
        .uint(u64::from(s.max_cell.0))
        .push("), BMS ")
        .celsius(Some(s.internal_c))
        .push(", sensors ")
        .celsius(s.external_c.0)
        .push(" / ")
        .celsius(s.external_c.1)
        .push(", ");
    status(out, s.status);
}

/// Writes what a [`Report`] says into `out` (appended).
pub fn report(r: &Report, out: &mut Line) {
    match r {
        Report::Snapshot(s) => snapshot(out, s),
        Report::StatusChanged { from, to } => {
            out.push("status ");
            if let Some(from) = from {
                status(out, *from);
                out.push(" -> ");
            }
            status(out, *to);
        }
        Report::NewEvent(e) => {
            out.push("event ")
                .push(e.id.severity().name())
                .push(" at BMS time ")
                .uint(u64::from(e.timestamp_s))
                .push(" s: ");
            event_id(out, e.id);
        }
        Report::EventHistory { count, newest } => {
            out.push("event log: ")
                .uint(u64::from(*count))
                .push(" recent events");
            if let Some(e) = newest {
                out.push(", the newest at BMS time ")
                    .uint(u64::from(e.timestamp_s))
                    .push(" s: ");
                event_id(out, e.id);
            }
        }
        Report::LinkError {
            command,
            failure,
            suppressed,
        } => {
            out.push("link error, command ")
                .hex(u32::from(*command))
                .push(": ")
                .push(failure.name());
            if let Failure::Nack(code) = failure {
                out.push(" (code ").hex(u32::from(code.to_u8())).push(")");
            }
            if *suppressed > 0 {
                out.push(" (+")
                    .uint(u64::from(*suppressed))
                    .push(" more since the last line)");
            }
        }
        Report::Offline { failures } => {
            out.push("BMS offline after ")
                .uint(u64::from(*failures))
                .push(" failed requests");
        }
        Report::Online => {
            out.push("BMS online; re-reading version and settings");
        }
        Report::Version(v) => version(out, v),
        Report::Ready { series_cells } => {
            out.push("settings and limits read (")
                .uint(u64::from(*series_cells))
                .push(" cells): ready");
        }
        Report::Write {
            setting: s,
            outcome,
        }
        | Report::WriteFollowUp {
            setting: s,
            outcome,
        } => {
            write(out, s, outcome, matches!(r, Report::WriteFollowUp { .. }));
        }
        Report::ResetDone { confirmed } => {
            out.push(if *confirmed {
                "BMS reset confirmed (register 114: software reset)"
            } else {
                "BMS reset not confirmed"
            });
        }
        Report::Cleared { option, ok } => {
            out.push("clear ")
                .push(if *option == 1 { "events" } else { "statistics" })
                .push(if *ok { ": ok" } else { ": failed" });
        }
        Report::LinkStats(s) => link_stats(out, s),
        Report::Dropped(n) => {
            out.uint(u64::from(*n)).push(" log reports dropped");
        }
        Report::Flagged(Some(c)) => {
            out.push("live data confirmed by a second read but fails check ")
                .push(c.name())
                .push(": published, flagged");
        }
        Report::Flagged(None) => {
            out.push("live data passes every check again");
        }
        Report::Refused { check, count } => {
            out.uint(u64::from(*count))
                .push(" live block(s) failed check ")
                .push(check.map(|c| c.name()).unwrap_or("first_read"))
                .push(" and were not confirmed: not published");
        }
        Report::LineQuality {
            attempts,
            clean,
            piece_registers,
            snapshots,
        } => {
            out.push("line quality: ")
                .fixed(i64::from(permille(*clean, *attempts)), 1)
                .push(" % of ")
                .uint(u64::from(*attempts))
                .push(" reads answered at the first attempt; ")
                .uint(u64::from(*piece_registers))
                .push(" registers per request; ")
                .uint(u64::from(*snapshots))
                .push(" snapshots");
        }
        Report::Wire { figures, verdict } => {
            out.push("wire: ");
            verdict.text(out);
            out.push(" (")
                .uint(u64::from(figures.replies))
                .push(" replies; per 1000 sends ")
                .uint(u64::from(figures.corrupted_permille))
                .push(" corrupted, ")
                .uint(u64::from(figures.lost_permille))
                .push(" lost, ")
                .uint(u64::from(figures.resent_permille))
                .push(" resent)");
        }
    }
}

/// A write's outcome (`follow_up`: a later read settled it).
fn write(out: &mut Line, s: &Setting, outcome: &WriteOutcome, follow_up: bool) {
    out.push("write ");
    if follow_up {
        out.push("follow-up ");
    }
    setting(out, s);
    out.push(": ").push(outcome.name());
    match outcome {
        WriteOutcome::Rejected(e) => {
            out.push(" (").push(e.reason());
            if let protocol_core::settings::SettingError::Contradicts {
                relation, other, ..
            } = e
            {
                let (low, high) = (relation.low.name(), relation.high.name());
                out.push(": ")
                    .push(low)
                    .push(if relation.gap > 0 {
                        " must stay below "
                    } else {
                        " may not exceed "
                    })
                    .push(high)
                    .push(", ")
                    .push(if s.id == relation.low { high } else { low })
                    .push(" is ")
                    .int(i64::from(*other));
            }
            if let protocol_core::settings::SettingError::OutsideChemistry {
                chemistry,
                min,
                max,
                ..
            } = e
            {
                out.push(": ")
                    .push(chemistry.name())
                    .push(" takes ")
                    .int(i64::from(*min))
                    .push("..")
                    .int(i64::from(*max))
                    .push(" mV; force to write it anyway");
            }
            out.push(")");
        }
        WriteOutcome::Mismatch { read_back } => {
            out.push(" (read back ")
                .uint(u64::from(*read_back))
                .push(")");
        }
        WriteOutcome::Nacked(c) => {
            out.push(" (code ").hex(u32::from(c.to_u8())).push(")");
        }
        WriteOutcome::Failed(e) | WriteOutcome::Unconfirmed(e) | WriteOutcome::NotWritten(e) => {
            out.push(" (").push(e.name()).push(")");
        }
        WriteOutcome::Verified | WriteOutcome::Unchanged => {}
    }
}

/// The link's counters since the last such line.
fn link_stats(out: &mut Line, s: &LinkStats) {
    out.push("link: requests ")
        .uint(u64::from(s.requests))
        .push(", replies ")
        .uint(u64::from(s.replies))
        .push(", timeouts ")
        .uint(u64::from(s.timeouts))
        .push(", wake-ups ")
        .uint(u64::from(s.wakeup_resends))
        .push(", retries ")
        .uint(u64::from(s.retries))
        .push(", CRC ")
        .uint(u64::from(s.crc_errors))
        .push(", framing ")
        .uint(u64::from(s.framing_errors))
        .push(", invalid ")
        .uint(u64::from(s.invalid_replies))
        .push(", NACK ")
        .uint(u64::from(s.nacks_command))
        .push("/")
        .uint(u64::from(s.nacks_crc))
        .push("/")
        .uint(u64::from(s.nacks_other))
        .push(", skipped bytes ")
        .uint(u64::from(s.skipped_bytes))
        .push(", unsolicited ")
        .uint(u64::from(s.unsolicited))
        .push(", failures ")
        .uint(u64::from(s.failures))
        .push(", latency ")
        .fixed(i64::from(s.latency_min_us) / 100, 1)
        .push("/")
        .fixed(i64::from(s.latency_mean_us()) / 100, 1)
        .push("/")
        .fixed(i64::from(s.latency_max_us) / 100, 1)
        .push(" ms");
}

/// The BMS's version block.
fn version(out: &mut Line, v: &VersionInfo) {
    out.push("BMS hardware ")
        .uint(u64::from(v.hardware))
        .push(".")
        .uint(u64::from(v.hardware_changes))
        .push(", firmware ")
        .uint(u64::from(v.firmware_public))
        .push(" (internal ")
        .uint(u64::from(v.firmware_internal))
        .push("), bootloader ")
        .uint(u64::from(v.bootloader))
        .push(", profile ")
        .uint(u64::from(v.profile))
        .push(", serial ")
        .hex_bytes(&v.serial);
}

/// Writes what an [`InverterReport`] says into `out` (appended).
pub fn inverter(r: &InverterReport, out: &mut Line) {
    match r {
        InverterReport::InverterSeen => {
            out.push("CAN: inverter seen (keep-alive)");
        }
        InverterReport::InverterLost => {
            out.push("CAN: inverter lost (no keep-alive)");
        }
        InverterReport::Stale {
            age_ms,
            policy,
            hold,
        } => {
            out.push("CAN: BMS data ")
                .fixed(i64::from(*age_ms) / 100, 1)
                .push(" s old: ");
            match (policy, hold) {
                (_, None) => out.push("this pack leaves the battery"),
                (StaleMode::Stop, _) => {
                    out.push("charge and discharge stopped (stale_policy stop)")
                }
                (StaleMode::Hold, Some(h)) if h.spend_us == 0 => {
                    out.push("charge and discharge stopped (the last data proves no charge above the discharge stop)")
                }
                (StaleMode::Hold, Some(h)) => out
                    .push("charge stopped; discharge for at most ")
                    .duration_s(h.spend_us / crate::SECOND)
                    .push(", its limit falling to 0 (the last data proves ")
                    .fixed(h.budget_mah.min(u64::from(u32::MAX)) as i64 / 10, 2)
                    .push(" Ah above the discharge stop)"),
            };
        }
        InverterReport::StaleHoldEnded(on_silence) => {
            out.push("CAN: hold over: charge and discharge stopped, said every way ");
            match on_silence {
                crate::inverter::dialect::OnSilence::Stops => out
                    .push("for ")
                    .uint(u64::from(crate::inverter::dialect::STOP_BEFORE_QUIET))
                    .push(" s, then nothing (the inverter stops on silence)"),
                crate::inverter::dialect::OnSilence::RunsOn => {
                    out.push("every second until the BMS data is back")
                }
            };
        }
        InverterReport::Fresh => {
            out.push("CAN: BMS data fresh again, sending");
        }
        InverterReport::NoAck { failures } => {
            out.push("CAN: ").uint(u64::from(*failures)).push(
                " frames not acknowledged (nothing else on the bus? wiring, termination, bit rate)",
            );
        }
        InverterReport::BusOk => {
            out.push("CAN: frames acknowledged again");
        }
        InverterReport::BusOff { count, backoff_ms } => {
            out.push("CAN: bus-off #")
                .uint(u64::from(*count))
                .push(", recovering in ")
                .uint(u64::from(*backoff_ms))
                .push(" ms");
        }
        InverterReport::Limits(l) => {
            out.push("CAN limits: ");
            limits(l, out);
        }
        InverterReport::BatteryLimits(l) => {
            out.push("CAN limits of the battery (all packs): ");
            limits(l, out);
        }
        InverterReport::Speaker(true) => {
            out.push("CAN: this bridge now speaks to the inverter for the battery");
        }
        InverterReport::Speaker(false) => {
            out.push("CAN: this bridge no longer speaks to the inverter");
        }
        InverterReport::Packs { online, offline } => {
            out.push("CAN: battery of ")
                .uint(u64::from(*online))
                .push(if *online == 1 { " pack" } else { " packs" });
            if *offline > 0 {
                out.push(", ")
                    .uint(u64::from(*offline))
                    .push(" left (lost, stale or faulted)");
            }
        }
        InverterReport::BatteryLost => {
            out.push("CAN: no pack takes part in the battery: the inverter is stopped");
        }
        InverterReport::DuplicateNode(n) => {
            out.push("CAN: another bridge sends summaries as node ")
                .uint(u64::from(*n))
                .push(": give each bridge its own pack_node (this one sends no summary until it restarts)");
        }
        InverterReport::SummaryRefused(n, e) => {
            out.push("CAN: a summary of node ")
                .uint(u64::from(*n))
                .push(" refused (")
                .push(e.reason())
                .push("): it counts nowhere");
        }
        InverterReport::Protection { stops, told } => protection(stops, told, out),
        InverterReport::Stage(s) => {
            out.push("charge: ");
            s.write(out);
        }
        InverterReport::Doctor(v) => {
            out.push("CAN doctor: ");
            v.write(out);
        }
        InverterReport::Reasons(r) => {
            out.push("limits because: CVL ");
            r.cvl.write(out);
            out.push("; CCL ");
            r.ccl.write(out);
            out.push("; DCL ");
            r.dcl.write(out);
        }
        InverterReport::IgnoresStop(e) => {
            out.push("CAN: the inverter ignores the ")
                .push(e.side.text())
                .push(" stop: ")
                .fixed(i64::from(e.current_da), 1)
                .push(" A for ")
                .uint(u64::from(e.for_s))
                .push(" s; every stop now goes out with every signal (SOC, charge voltage, protection bits)");
        }
        InverterReport::ShutdownAsked(true) => {
            out.push("CAN: the inverter asks the battery to shut down (0x300): charge and discharge stopped while it asks (the BMS is not switched off)");
        }
        InverterReport::ShutdownAsked(false) => {
            out.push("CAN: the inverter no longer asks the battery to shut down");
        }
    }
}

/// "protection active: why: what was told", each stop with its cause and
/// what the frames sent tell the inverter, read back from their bytes.
fn protection(
    stops: &crate::inverter::dialect::Stops,
    told: &crate::inverter::dialect::Told,
    out: &mut Line,
) {
    if stops.none() {
        out.push("CAN protection: none active");
    } else {
        out.push("CAN protection active:");
        if let Some(why) = stops.charge {
            out.push(" charge stopped (").push(why.text()).push(")");
        }
        if let Some(why) = stops.discharge {
            out.push(if stops.charge.is_some() { "," } else { "" })
                .push(" discharge stopped (")
                .push(why.text())
                .push(")");
        }
    }
    out.push("; told:");
    if let Some(l) = told.limits {
        out.push(" charge current ")
            .fixed(i64::from(l.ccl_da), 1)
            .push(" A, discharge current ")
            .fixed(i64::from(l.dcl_da), 1)
            .push(" A, charge voltage ")
            .fixed(i64::from(l.cvl_dv), 1)
            .push(" V");
    }
    let on_off = |b: bool| if b { "on" } else { "off" };
    if let Some(c) = told.charge_enabled {
        out.push(", charge enable ").push(on_off(c));
    }
    if let Some(d) = told.discharge_enabled {
        out.push(", discharge enable ").push(on_off(d));
    }
    if let Some(soc) = told.soc_pct {
        out.push(", SOC ").uint(u64::from(soc)).push(" %");
    }
    if told.protection == Some(true) {
        out.push(", protection flagged");
    }
    if told.link_lost == Some(true) {
        out.push(", BMS data lost flagged");
    }
}

fn limits(l: &crate::inverter::control::Limits, out: &mut Line) {
    out.push("charge voltage ")
        .fixed(i64::from(l.cvl_dv), 1)
        .push(" V, charge current ")
        .fixed(i64::from(l.ccl_da), 1)
        .push(" A, discharge current ")
        .fixed(i64::from(l.dcl_da), 1)
        .push(" A");
}

/// Log level of a configuration note: what needs attention is a warning.
pub fn config_level(n: &crate::config::state::Note) -> crate::Level {
    use crate::config::state::Note;
    use crate::config::store::Source;
    match n {
        Note::Loaded(Source::Invalid(_) | Source::Unreadable(_))
        | Note::Unlocked
        | Note::SaveFailed(_) => crate::Level::Warn,
        _ => crate::Level::Info,
    }
}

/// Writes what a configuration note says into `out` (appended). Values are
/// taken from `config`'s stored record; a secret is only ever `set` or
/// `unset`.
pub fn config_note(
    n: &crate::config::state::Note,
    config: &crate::config::state::ConfigState,
    out: &mut Line,
) {
    use crate::config::state::Note;
    use crate::config::store::{Saved, Source};
    use crate::config::{value, Applies};
    match n {
        Note::Loaded(Source::Flash) => {
            out.push("configuration from flash");
        }
        Note::Loaded(Source::Empty) => {
            out.push("configuration: none stored, running with the defaults");
        }
        Note::Loaded(Source::Invalid(e)) => {
            out.push("configuration in flash is not valid (")
                .push(e.reason())
                .push("): running with the defaults");
        }
        Note::Loaded(Source::Unreadable(e)) => {
            out.push("configuration store cannot be read (")
                .push(e.reason())
                .push("): running with the defaults");
            // Only an image with a store has a site (and links its words).
            if let (true, Some(site)) = (cfg!(feature = "store"), config.site()) {
                out.push("; ");
                store_site(&site, out);
            }
        }
        Note::Changed(id, applies) => {
            let f = id.field();
            out.push("config: ").push(f.name);
            if f.is_secret() {
                out.push(" ");
            } else {
                out.push(" = ");
            }
            value::write(f, &config.stored().get(*id), true, out);
            out.push(match applies {
                Applies::Now => " (now)",
                Applies::Restart => " (at the next restart)",
            });
        }
        Note::Reset => {
            out.push("config: every field back to its default");
        }
        Note::Unlocked => {
            out.push("BOOT button held 5 s: read-only lifted");
        }
        Note::Saved(Saved::Written) => {
            out.push("config saved to flash");
        }
        Note::Saved(Saved::Unchanged) => {
            out.push("config unchanged: nothing written");
        }
        Note::SaveFailed(e) => {
            out.push("config save failed: ").push(e.reason());
            // Only an image with a store has a site (and links its words).
            if let (true, Some(site)) = (cfg!(feature = "store"), config.site()) {
                out.push("; ");
                store_site(&site, out);
            }
        }
    }
}

/// Where the store lives, with the figures an owner needs to see why it
/// fails: `flash 4096 KiB (as the chip reports it), nvs partition at 0x9000,
/// 24 KiB; the store needs 8 KiB in whole 4 KiB sectors inside the flash`.
pub fn store_site(site: &crate::config::store::StoreSite, out: &mut Line) {
    use crate::config::store::STORE_MIN_BYTES;
    out.push("flash ")
        .uint(u64::from(site.flash_bytes / 1024))
        .push(" KiB (as the chip reports it), ");
    match site.partition {
        Some((offset, size)) => {
            out.push("nvs partition at ").hex(offset).push(", ");
            if size % 1024 == 0 {
                out.uint(u64::from(size / 1024)).push(" KiB");
            } else {
                out.uint(u64::from(size)).push(" bytes");
            }
        }
        None => {
            out.push("no nvs partition");
        }
    }
    out.push("; the store needs ")
        .uint(u64::from(STORE_MIN_BYTES / 1024))
        .push(" KiB in whole 4 KiB sectors inside the flash");
    if let Some(p) = site.problem() {
        out.push(": ").push(p.reason());
    }
}

/// A line the chip shell writes once at boot: the first lines of the
/// first-flash check-list (docs/boards.md). The host link keeps them from boot
/// and gives them to every host after its `hello`
/// ([`crate::station::Station::boot_line`]), so `tinybms log PORT` shows them
/// however late it connects.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Boot {
    /// The image: its firmware and build, the board and chip it runs on,
    /// where its defmt log goes (`None`: a bridge run on the desktop).
    Image {
        /// The defmt log path.
        log: Option<crate::boards::LogPath>,
    },
    /// The CAN output is switched off in the configuration.
    CanOff,
    /// The CAN output runs.
    Can {
        /// Its protocol.
        protocol: crate::inverter::Protocol,
        /// (TX, RX) GPIOs; `None`: a simulated bus.
        pins: Option<(u8, u8)>,
        /// The pack node among packs in parallel (0: this pack alone).
        node: u8,
    },
    /// The host link: its wire (`None`: a desktop port), its start-up mode.
    HostLink {
        /// The wire.
        wire: Option<crate::boards::HostWire>,
        /// Host writes off.
        read_only: bool,
        /// Telemetry period, ms (0: off).
        stream_period_ms: u32,
    },
    /// The UART to the BMS.
    Uart {
        /// Baud rate.
        baud: u32,
        /// (TX, RX) GPIOs and the RX FIFO threshold; `None`: a simulated BMS.
        pins: Option<(u8, u8, u16)>,
    },
    /// The start-up profile (`firmware/profile.txt`): its settings, and
    /// whether they fit the bridge's command queue (else none is written).
    Profile {
        /// Settings in it.
        settings: usize,
        /// Queued for writing.
        queued: bool,
    },
}

impl Boot {
    /// The level it is logged at.
    pub const fn level(&self) -> crate::Level {
        match self {
            Self::Profile { queued: false, .. } => crate::Level::Warn,
            _ => crate::Level::Info,
        }
    }
}

/// Writes a boot line of the bridge `id` into `out` (appended).
pub fn boot(b: &Boot, id: &crate::identity::Identity, out: &mut Line) {
    use crate::boards::LogPath;
    match *b {
        Boot::Image { log } => {
            out.push("tinybms-firmware ")
                .push(crate::identity::FIRMWARE)
                .push(" (build ")
                .push(crate::identity::BUILD)
                .push(") on ")
                .push(id.board)
                .push(" (")
                .push(id.chip)
                .push("), logs over ")
                .push(match log {
                    Some(LogPath::Rtt) => "RTT",
                    Some(LogPath::Uart0) => "UART0",
                    None => "the host link",
                });
        }
        Boot::CanOff => {
            out.push("CAN to the inverter off (can_output = off)");
        }
        Boot::Can {
            protocol,
            pins,
            node,
        } => {
            out.push("CAN to the inverter: ")
                .push(protocol.title())
                .push(", 500 kbit/s, ");
            match pins {
                Some((tx, rx)) => {
                    out.push("TX=GPIO")
                        .uint(u64::from(tx))
                        .push(" RX=GPIO")
                        .uint(u64::from(rx));
                }
                None => {
                    out.push("a simulated bus");
                }
            }
            if node != 0 {
                out.push("; pack node ")
                    .uint(u64::from(node))
                    .push(" of packs in parallel (summaries on 0x6A0-0x6BF; node 1 speaks first)");
            }
        }
        Boot::HostLink {
            wire,
            read_only,
            stream_period_ms,
        } => {
            out.push("host link on ")
                .push(match wire {
                    Some(w) => w.name(),
                    None => "a desktop port",
                })
                .push(": ")
                .push(if read_only { "read-only" } else { "read-write" });
            if stream_period_ms == 0 {
                out.push(", telemetry only when asked");
            } else {
                out.push(", telemetry every ")
                    .uint(u64::from(stream_period_ms))
                    .push(" ms");
            }
        }
        Boot::Uart { baud, pins } => {
            out.push("UART1 ")
                .uint(u64::from(baud))
                .push(" 8N1 to the BMS: ");
            match pins {
                Some((tx, rx, threshold)) => {
                    out.push("TX=GPIO")
                        .uint(u64::from(tx))
                        .push(" RX=GPIO")
                        .uint(u64::from(rx))
                        .push(" (rx fifo threshold ")
                        .uint(u64::from(threshold))
                        .push(")");
                }
                None => {
                    out.push("a simulated TinyBMS");
                }
            }
        }
        Boot::Profile { settings: 0, .. } => {
            out.push("settings profile empty: nothing written");
        }
        Boot::Profile { settings, queued } => {
            out.push("settings profile: ")
                .uint(settings as u64)
                .push(" settings");
            if !queued {
                out.push(", too many for the command queue: none written");
            }
        }
    }
}

/// The same words as the chip's log ([`report`]).
impl core::fmt::Display for Report {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let mut line = Line::new();
        report(self, &mut line);
        f.write_str(line.as_str())
    }
}

/// The level an Improv note is logged at.
pub fn improv_level(n: &crate::improv::Note) -> crate::Level {
    use crate::improv::Note;
    match n {
        Note::Joining(_) | Note::Joined(..) => crate::Level::Info,
        _ => crate::Level::Warn,
    }
}

/// An IPv4 address, dotted.
pub fn ipv4(ip: [u8; 4], out: &mut Line) {
    for (i, b) in ip.iter().enumerate() {
        if i > 0 {
            out.push(".");
        }
        out.uint(u64::from(*b));
    }
}

/// What Improv Wi-Fi did (never a passphrase or a key).
pub fn improv_note(n: &crate::improv::Note, out: &mut Line) {
    use crate::improv::Note;
    out.push("Improv Wi-Fi: ");
    match n {
        Note::BadPacket(e) => {
            out.push("a packet refused (").push(e.text()).push(")");
        }
        Note::Unsupported(c) => {
            out.push("command ")
                .hex(u32::from(*c))
                .push(" refused: not one this image does");
        }
        Note::Joining(ssid) => {
            out.push("joining ")
                .push(ssid)
                .push(" (the key is derived here)");
        }
        Note::Joined(ssid, ip) => {
            out.push("joined ").push(ssid).push(", IP ");
            ipv4(*ip, out);
            out.push("; network stored");
        }
        Note::Failed(ssid, f) => {
            out.push("cannot join ")
                .push(ssid)
                .push(": ")
                .push(f.text())
                .push("; the stored network is unchanged");
        }
        Note::Refused(why) => {
            out.push("settings refused: ").push(why);
        }
        Note::TimedOut(ssid) => {
            out.push("cannot join ")
                .push(ssid)
                .push(": no answer within 30 s; the stored network is unchanged");
        }
    }
}
