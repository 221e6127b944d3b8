//! The telemetry model: the published picture of the BMS ([`Telemetry`]) and the
//! rules a live block passes before it joins it.
//!
//! A complete live block is checked ([`checks::check_live`], and
//! [`checks::check_jump`] against the last published snapshot of this sync). One
//! that fails, and the first one after a (re)sync, is held as a *suspect* and read
//! again at once; it is published only when an independent second read agrees
//! (no jump between the two, the same verdict), and then flagged with the check it
//! failed. After [`SUSPECT_TRIES`] disagreeing reads the block is refused and
//! counted for the next line quality report.
//!
//! [`TelemetryModel`] owns the picture and that bookkeeping. The other parts of
//! the bridge write the slow blocks (version, settings, limits, statistics) and
//! the `online`/`ready` flags straight into [`TelemetryModel::telemetry`]; the
//! live snapshot is published only here.

use protocol_core::response::RegisterBlock;
use protocol_core::settings::SettingId;
use protocol_core::views::{LiveSnapshot, Statistics, VersionInfo};

use super::Reports;
use crate::bms::checks::{self, Check};
use crate::bms::reader::Assembled;
use crate::bms::timing::Timing;
use crate::bridge::report::{Report, SnapshotLine};
use crate::Instant;

/// How the published live snapshot was obtained.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LiveMeta {
    /// Requests the block was assembled from (1 on a clean line).
    pub pieces: u8,
    /// First piece asked for to last piece received, µs.
    pub span_us: u32,
    /// A check the snapshot fails although a second read confirmed it.
    pub flagged: Option<Check>,
}

/// The bridge's picture of the BMS.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Telemetry {
    /// Latest live snapshot.
    pub snapshot: Option<LiveSnapshot>,
    /// Registers 0-55 it was decoded from (reserved registers read as 0 when the
    /// block was assembled from pieces).
    pub live_registers: Option<RegisterBlock>,
    /// How it was read.
    pub live: LiveMeta,
    /// When it was decoded.
    pub snapshot_at: Option<Instant>,
    /// Incremented at every new snapshot.
    pub snapshot_seq: u32,
    /// Latest statistics.
    pub statistics: Option<Statistics>,
    /// Registers 100-117 they were decoded from.
    pub statistics_registers: Option<RegisterBlock>,
    /// Version block.
    pub version: Option<VersionInfo>,
    /// Settings 300-343 as last read.
    pub settings: Option<RegisterBlock>,
    /// BMS-reported minimum of each setting (0x1D option 1).
    pub limits_min: Option<RegisterBlock>,
    /// BMS-reported maximum of each setting (0x1D option 2).
    pub limits_max: Option<RegisterBlock>,
    /// The link is up.
    pub online: bool,
    /// Version, settings and limits are read since the last (re)connection.
    pub ready: bool,
}

impl Telemetry {
    /// Age of the snapshot at `now`, µs.
    pub fn snapshot_age_us(&self, now: Instant) -> Option<Instant> {
        self.snapshot_at.map(|t| now.saturating_sub(t))
    }
}

/// Second reads of a suspect live block before it is dropped.
const SUSPECT_TRIES: u8 = 3;

/// A live block that failed a check, waiting for a second read.
#[derive(Debug, Clone, PartialEq)]
struct Suspect {
    snapshot: LiveSnapshot,
    at: Instant,
    verdict: Result<(), Check>,
    tries: u8,
}

/// The published picture and what it takes to publish a live block.
#[derive(Debug, Clone)]
pub(super) struct TelemetryModel {
    /// What consumers read ([`super::Bridge::telemetry`]).
    pub(super) telemetry: Telemetry,
    suspect: Option<Suspect>,
    /// Live blocks refused since the last line quality report, and the check the
    /// last of them failed.
    refused: u32,
    refused_check: Option<Check>,
    /// Snapshots published since the last line quality report.
    snapshots_in_window: u32,
    /// The check the published snapshot is flagged with (reported on change).
    flagged: Option<Check>,
    /// The published snapshot is from the current sync: jumps are checked
    /// against it.
    live_base_valid: bool,
    next_snapshot_log: Instant,
}

impl TelemetryModel {
    pub(super) fn new(now: Instant) -> Self {
        Self {
            telemetry: Telemetry {
                online: true,
                ..Telemetry::default()
            },
            suspect: None,
            refused: 0,
            refused_check: None,
            snapshots_in_window: 0,
            flagged: None,
            live_base_valid: false,
            next_snapshot_log: now,
        }
    }

    /// A (re)sync starts: not ready, and the next snapshot is confirmed by a
    /// second read before it is published.
    pub(super) fn restart(&mut self) {
        self.telemetry.ready = false;
        self.suspect = None;
        self.live_base_valid = false;
    }

    /// A snapshot was published since the last (re)sync.
    pub(super) fn live_base_valid(&self) -> bool {
        self.live_base_valid
    }

    /// The line quality window closes: reports the refused blocks, if any, and
    /// returns the snapshots published in the window.
    pub(super) fn take_window(&mut self, out: &mut Reports) -> u32 {
        let snapshots = core::mem::take(&mut self.snapshots_in_window);
        if self.refused > 0 {
            let count = core::mem::take(&mut self.refused);
            let check = self.refused_check.take();
            out.push(Report::Refused { check, count });
        }
        snapshots
    }

    /// A complete live block: check it, confirm it when it fails, publish it.
    /// True when it must be read again at once (it is a suspect).
    pub(super) fn on_live(
        &mut self,
        now: Instant,
        a: &Assembled,
        config: &Timing,
        out: &mut Reports,
    ) -> bool {
        // Decoded where it stays until published (one copy, into the
        // telemetry), not moved from function to function.
        let mut slot = None;
        let Ok(()) = LiveSnapshot::decode_into(a.block, &mut slot) else {
            return false;
        };
        let Some(snap) = &slot else {
            return false;
        };
        let ctx = checks::Context {
            series_cells: self
                .telemetry
                .settings
                .as_ref()
                .and_then(|b| b.get(SettingId::NumberOfSeriesCells.address())),
            assembled: a.pieces > 1,
        };
        let at = a.started_at;
        let statics = checks::check_live(a.block, snap, ctx);
        let jump = match (&self.telemetry.snapshot, self.telemetry.snapshot_at) {
            (Some(p), Some(p_at)) if self.telemetry.ready && self.suspect_base_valid() => {
                checks::check_jump(p, p_at, snap, at)
            }
            _ => Ok(()),
        };
        let first = !self.suspect_base_valid();
        let verdict = statics.and(jump);
        let flag = match self.suspect.take() {
            None if verdict.is_ok() && !first => Some(None),
            None => {
                self.suspect = Some(Suspect {
                    snapshot: snap.clone(),
                    at,
                    verdict: statics,
                    tries: 1,
                });
                return true; // read again at once
            }
            Some(_) if verdict.is_ok() && !first => Some(None),
            Some(q) => {
                let agrees =
                    q.verdict == statics && checks::check_jump(&q.snapshot, q.at, snap, at).is_ok();
                if agrees {
                    Some(verdict.err())
                } else if q.tries < SUSPECT_TRIES {
                    self.suspect = Some(Suspect {
                        snapshot: snap.clone(),
                        at,
                        verdict: statics,
                        tries: q.tries + 1,
                    });
                    return true;
                } else {
                    self.refused = self.refused.wrapping_add(1);
                    self.refused_check = verdict.err().or(q.verdict.err());
                    None
                }
            }
        };
        let Some(flag) = flag else {
            return false;
        };
        if flag != self.flagged {
            self.flagged = flag;
            out.push(Report::Flagged(flag));
        }
        self.publish(now, &mut slot, a, flag, config, out);
        false
    }

    /// True when the last published snapshot is from this sync (jumps are
    /// checked against it).
    fn suspect_base_valid(&self) -> bool {
        self.telemetry.snapshot.is_some() && self.live_base_valid
    }

    /// Publishes the snapshot in `slot` (moved into the telemetry, not copied).
    fn publish(
        &mut self,
        now: Instant,
        slot: &mut Option<LiveSnapshot>,
        a: &Assembled,
        flag: Option<Check>,
        config: &Timing,
        out: &mut Reports,
    ) {
        let Some(snap) = slot.as_ref() else {
            return;
        };
        let previous = self.telemetry.snapshot.as_ref().map(|s| s.status);
        if previous != Some(snap.status) {
            out.push(Report::StatusChanged {
                from: previous,
                to: snap.status,
            });
        }
        if let Some(next) =
            snapshot_log_due(self.next_snapshot_log, now, config.snapshot_log_period_us)
        {
            self.next_snapshot_log = next;
            out.push(Report::Snapshot(snapshot_line(snap)));
        }
        core::mem::swap(&mut self.telemetry.snapshot, slot);
        copy_block(&mut self.telemetry.live_registers, a.block);
        self.telemetry.live = LiveMeta {
            pieces: a.pieces,
            span_us: a.span_us.min(u64::from(u32::MAX)) as u32,
            flagged: flag,
        };
        self.telemetry.snapshot_at = Some(now);
        self.telemetry.snapshot_seq = self.telemetry.snapshot_seq.wrapping_add(1);
        self.snapshots_in_window = self.snapshots_in_window.wrapping_add(1);
        self.live_base_valid = true;
    }

    /// The BMS clock (lifetime counter) now, from the last snapshot.
    pub(super) fn expected_bms_clock(&self, now: Instant) -> Option<u32> {
        let s = self.telemetry.snapshot.as_ref()?;
        let at = self.telemetry.snapshot_at?;
        let elapsed = now.saturating_sub(at) / crate::SECOND;
        Some(
            s.lifetime_s
                .wrapping_add(elapsed.min(u64::from(u32::MAX)) as u32),
        )
    }
}

/// `*to = Some(from.clone())`, in place when `to` holds a block already: only
/// the registers are copied, not the whole capacity (the live path runs this at
/// every snapshot).
fn copy_block(to: &mut Option<RegisterBlock>, from: &RegisterBlock) {
    match to {
        Some(block) => {
            block.start = from.start;
            block.values.clear();
            let _fits = block.values.extend_from_slice(&from.values); // same capacity
        }
        None => *to = Some(from.clone()),
    }
}

/// Whether a snapshot line is due at `now` when the next one was planned for
/// `next`, and when the one after it is: `Some(next line time)` or `None`.
/// Period 0 logs every snapshot. Otherwise lines keep to the period's grid (a
/// line every 10 s, not every 10.25 s), and after a long silence the next grid
/// point is computed at once, not walked to step by step.
pub fn snapshot_log_due(next: Instant, now: Instant, period: Instant) -> Option<Instant> {
    if period == 0 {
        return Some(now);
    }
    if now < next {
        return None;
    }
    let steps = (now - next) / period + 1;
    Some(next.saturating_add(steps.saturating_mul(period)))
}

/// The log summary of a snapshot.
pub fn snapshot_line(s: &LiveSnapshot) -> SnapshotLine {
    let volts = |(i, raw): (usize, u16)| ((i + 1) as u8, f32::from(raw) * 0.0001);
    SnapshotLine {
        pack_v: s.pack_voltage_v,
        current_a: s.pack_current_a,
        soc_percent: s.soc_percent(),
        min_cell: s.cells.min().map(volts).unwrap_or((0, 0.0)),
        max_cell: s.cells.max().map(volts).unwrap_or((0, 0.0)),
        internal_c: s.internal_c(),
        external_c: (s.external1_c(), s.external2_c()),
        status: s.status,
    }
}
