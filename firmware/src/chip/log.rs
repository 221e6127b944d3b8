//! Report → defmt lines.

use defmt::{info, warn};
use protocol_core::events::OnlineStatus;
use tinybms_firmware::bms::link::Failure;
use tinybms_firmware::{Level, Report};

/// One defmt line per report, in the same words as the host simulator prints.
pub fn report(r: &Report) {
    match r {
        Report::Snapshot(s) => info!(
            "pack {=f32}V {=f32}A soc {=f32}% min #{=u8} {=f32}V max #{=u8} {=f32}V temp {=f32}C ext {} {} status {=str}",
            s.pack_v,
            s.current_a,
            s.soc_percent,
            s.min_cell.0,
            s.min_cell.1,
            s.max_cell.0,
            s.max_cell.1,
            s.internal_c,
            s.external_c.0,
            s.external_c.1,
            s.status.name()
        ),
        Report::StatusChanged { from, to } => {
            let from = from.map(|f| f.name()).unwrap_or("-");
            if *to == OnlineStatus::Fault {
                warn!("status {=str} -> {=str}", from, to.name());
            } else {
                info!("status {=str} -> {=str}", from, to.name());
            }
        }
        Report::NewEvent(e) => {
            if r.level() == Level::Warn {
                warn!(
                    "event {=str} t={=u32}s 0x{=u8:02X} {=str}",
                    e.id.severity().name(),
                    e.timestamp_s,
                    e.id.raw(),
                    e.id.name()
                );
            } else {
                info!(
                    "event {=str} t={=u32}s 0x{=u8:02X} {=str}",
                    e.id.severity().name(),
                    e.timestamp_s,
                    e.id.raw(),
                    e.id.name()
                );
            }
        }
        Report::EventHistory { count, newest } => match newest {
            Some(e) => info!(
                "event log: {=u8} recent events, newest t={=u32}s 0x{=u8:02X} {=str}",
                count,
                e.timestamp_s,
                e.id.raw(),
                e.id.name()
            ),
            None => info!("event log: {=u8} recent events", count),
        },
        Report::LinkError {
            command,
            failure,
            suppressed,
        } => {
            let code = match failure {
                Failure::Nack(c) => c.to_u8(),
                _ => 0xFF,
            };
            if *suppressed > 0 {
                warn!(
                    "link error cmd 0x{=u8:02X}: {=str} (nack code 0x{=u8:02X}) (+{=u32} more since the last line)",
                    command,
                    failure.name(),
                    code,
                    suppressed
                );
            } else {
                warn!(
                    "link error cmd 0x{=u8:02X}: {=str} (nack code 0x{=u8:02X})",
                    command,
                    failure.name(),
                    code
                );
            }
        }
        Report::Offline { failures } => warn!("BMS offline after {=u8} failed requests", failures),
        Report::Online => info!("BMS online; re-reading version and settings"),
        Report::Version(v) => info!(
            "version hw {=u8}.{=u8} fw {=u8} ({=u16}) bootloader {=u8} profile {=u8} serial {=[u8]:02X}",
            v.hardware,
            v.hardware_changes,
            v.firmware_public,
            v.firmware_internal,
            v.bootloader,
            v.profile,
            v.serial
        ),
        Report::Ready { series_cells } => {
            info!("settings and limits read ({=u16} cells): ready", series_cells)
        }
        Report::Write { setting, outcome } | Report::WriteFollowUp { setting, outcome } => {
            let follow = if matches!(r, Report::WriteFollowUp { .. }) {
                "follow-up "
            } else {
                ""
            };
            if outcome.is_success() {
                info!(
                    "write {=str}{=str} ({=u16}) = {=i32}: {=str}",
                    follow,
                    setting.id.name(),
                    setting.id.address(),
                    setting.value,
                    outcome.name()
                );
            } else {
                warn!(
                    "write {=str}{=str} ({=u16}) = {=i32}: {=str} {}",
                    follow,
                    setting.id.name(),
                    setting.id.address(),
                    setting.value,
                    outcome.name(),
                    outcome
                );
            }
        }
        Report::Flagged(Some(c)) => warn!(
            "live data confirmed by a second read but fails check {=str}: published, flagged",
            c.name()
        ),
        Report::Flagged(None) => info!("live data passes every check again"),
        Report::Refused { check, count } => warn!(
            "{=u32} live block(s) failed check {=str} and were not confirmed: not published",
            count,
            check.map(|c| c.name()).unwrap_or("first_read")
        ),
        Report::LineQuality {
            attempts,
            clean,
            piece_registers,
            snapshots,
        } => {
            let permille = tinybms_firmware::bridge::report::permille(*clean, *attempts);
            if r.level() == Level::Warn {
                warn!(
                    "line quality: {=u32} permille of {=u32} reads answered at the first attempt; {=u16} registers per request; {=u32} snapshots",
                    permille, attempts, piece_registers, snapshots
                );
            } else {
                info!(
                    "line quality: {=u32} permille of {=u32} reads answered at the first attempt; {=u16} registers per request; {=u32} snapshots",
                    permille, attempts, piece_registers, snapshots
                );
            }
        }
        Report::ResetDone { confirmed } => {
            if *confirmed {
                info!("BMS reset confirmed (reg 114 = software reset)")
            } else {
                warn!("BMS reset not confirmed")
            }
        }
        Report::Cleared { option, ok } => {
            let what = if *option == 1 { "events" } else { "statistics" };
            if *ok {
                info!("clear {=str} ok", what);
            } else {
                warn!("clear {=str} failed", what);
            }
        }
        Report::LinkStats(s) => info!(
            "link: req {=u32} rep {=u32} timeouts {=u32} wake {=u32} retries {=u32} crc {=u32} framing {=u32} invalid {=u32} nack {=u32}/{=u32}/{=u32} skipped {=u32} unsolicited {=u32} failures {=u32} latency {=u32}/{=u32}/{=u32} us",
            s.requests,
            s.replies,
            s.timeouts,
            s.wakeup_resends,
            s.retries,
            s.crc_errors,
            s.framing_errors,
            s.invalid_replies,
            s.nacks_command,
            s.nacks_crc,
            s.nacks_other,
            s.skipped_bytes,
            s.unsolicited,
            s.failures,
            s.latency_min_us,
            s.latency_mean_us(),
            s.latency_max_us
        ),
        Report::Dropped(n) => warn!("{=u32} log reports dropped", n),
    }
}
