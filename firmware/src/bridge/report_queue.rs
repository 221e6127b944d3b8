//! What the bridge has to say: the queue of [`Report`]s that
//! [`super::Bridge::next_report`] hands out, and the periodic, rate-limited lines
//! (link statistics, line quality, link errors) so that a bad line gives a figure
//! per period instead of a line per failed request.

use heapless::Deque;
use protocol_core::request::Request;

use crate::bms::link::Failure;
use crate::bms::timing::{self, Timing};
use crate::bridge::report::Report;
use crate::Instant;

/// The reports not yet taken, oldest first (when full, the oldest is dropped and
/// counted), and when the periodic lines are due.
#[derive(Debug, Clone)]
pub(super) struct Reports {
    queue: Deque<Report, { timing::REPORT_QUEUE }>,
    dropped: u32,
    next_link_log: Instant,
    next_quality_log: Instant,
    /// The sooner of the two above (looked at on every step).
    next_periodic: Instant,
    next_error_log: Instant,
    suppressed_errors: u32,
}

impl Reports {
    pub(super) fn new(config: &Timing, now: Instant) -> Self {
        let next_link_log = now.saturating_add(config.link_stats_log_period_us);
        let next_quality_log = now.saturating_add(config.line_quality_log_period_us);
        Self {
            queue: Deque::new(),
            dropped: 0,
            next_link_log,
            next_quality_log,
            next_periodic: next_link_log.min(next_quality_log),
            next_error_log: now,
            suppressed_errors: 0,
        }
    }

    pub(super) fn push(&mut self, r: Report) {
        if self.queue.is_full() {
            let _oldest = self.queue.pop_front();
            self.dropped = self.dropped.wrapping_add(1);
        }
        let _room = self.queue.push_back(r);
    }

    /// The next report, oldest first; a count of dropped ones goes first.
    pub(super) fn next(&mut self) -> Option<Report> {
        if self.dropped > 0 {
            let n = self.dropped;
            self.dropped = 0;
            return Some(Report::Dropped(n));
        }
        self.queue.pop_front()
    }

    /// The periodic lines due at `now`: (link statistics, line quality); the
    /// next ones are planned. Called at every step: one comparison when none is.
    pub(super) fn periodic_due(&mut self, now: Instant, config: &Timing) -> (bool, bool) {
        if now < self.next_periodic {
            return (false, false);
        }
        let link = due(
            &mut self.next_link_log,
            now,
            config.link_stats_log_period_us,
        );
        let quality = due(
            &mut self.next_quality_log,
            now,
            config.line_quality_log_period_us,
        );
        self.next_periodic = self.next_link_log.min(self.next_quality_log);
        (link, quality)
    }

    /// When the next periodic line is due.
    pub(super) fn next_periodic(&self) -> Instant {
        self.next_periodic
    }

    /// A link error worth a line: at most one per
    /// [`Timing::link_error_log_period_us`], the others are counted.
    pub(super) fn link_error(
        &mut self,
        now: Instant,
        config: &Timing,
        request: &Request,
        failure: Failure,
    ) {
        if now >= self.next_error_log {
            self.next_error_log = now.saturating_add(config.link_error_log_period_us);
            let suppressed = core::mem::take(&mut self.suppressed_errors);
            self.push(Report::LinkError {
                command: request.command(),
                failure,
                suppressed,
            });
        } else {
            self.suppressed_errors = self.suppressed_errors.wrapping_add(1);
        }
    }
}

/// True when `*next` has come at `now`; the next one is then a `period` later.
fn due(next: &mut Instant, now: Instant, period: Instant) -> bool {
    if now < *next {
        return false;
    }
    *next = now.saturating_add(period);
    true
}
