//! What the live picture says in words, wherever it is shown (the desktop
//! monitor in every mode, the browser console): the freshness by the
//! bridge's own rule, and the link quality.

use std::time::Duration;

use tinybms_firmware::host_link::schema::{Link, Read, Telemetry};

/// Link quality from a `link` line: share of requests answered at once, and the
/// counts.
pub fn link_quality(link: &Link<Read>) -> String {
    let (requests, replies, failures) = (link.requests, link.replies, link.failures);
    let pct = if requests == 0 {
        100.0
    } else {
        100.0 * f64::from(requests.saturating_sub(failures)) / f64::from(requests)
    };
    format!(
        "{pct:.1} % ok ({requests} requests, {replies} replies, {failures} failed, {} retries, {} CRC errors)",
        link.retries, link.crc_errors
    )
}

/// How fresh the picture is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Freshness {
    /// Data `age` old, the BMS online.
    Fresh(f64),
    /// The bridge lost the BMS (its telemetry says offline); data `age` old.
    Offline(Option<f64>),
    /// Nothing new for too long: the newest data is `age` old (None: never any).
    NoData(Option<f64>),
}

/// The age of `t`'s data now (seconds): its `age_ms` when it arrived plus the
/// time since.
pub fn data_age(t: &Telemetry<Read>, received_ago: Duration) -> Option<f64> {
    t.head
        .age_ms
        .map(|ms| ms as f64 / 1000.0 + received_ago.as_secs_f64())
}

/// The freshness rule of the bridge that sent `t`: the limit its line gives
/// (`stale_after_ms`), or the default for a bridge whose lines carry none.
pub fn rule_of(t: &Telemetry<Read>) -> tinybms_firmware::freshness::Freshness {
    let limit_us = t
        .head
        .stale_after_ms
        .map_or(tinybms_firmware::freshness::DEFAULT_STALE_AFTER_US, |ms| {
            ms.saturating_mul(1000)
        });
    tinybms_firmware::freshness::Freshness::new(limit_us)
}

/// What the picture should say about `t`, received `received_ago`: the
/// firmware's one freshness rule with the bridge's limit, on the age the line
/// gave plus the time since it came (a bridge that stopped sending ages too).
pub fn freshness(t: Option<&Telemetry<Read>>, received_ago: Duration) -> Freshness {
    use tinybms_firmware::freshness::DataState;
    let Some(t) = t else {
        return Freshness::NoData(None);
    };
    let age = data_age(t, received_ago);
    let age_us = age.map(|a| (a * 1e6) as u64);
    match rule_of(t).state(t.head.online, age_us) {
        DataState::Offline => Freshness::Offline(age),
        DataState::Fresh => Freshness::Fresh(age.unwrap_or(0.0)),
        DataState::NoData | DataState::Stale => Freshness::NoData(age),
    }
}

/// One line about the freshness: `Data age 0.4 s`, `NO DATA (newest 12.0 s
/// old)`, `OFFLINE (…)`.
pub fn freshness_text(f: Freshness) -> String {
    let age = |a: Option<f64>| match a {
        Some(a) => format!("newest data {a:.1} s old"),
        None => "no data yet".into(),
    };
    match f {
        Freshness::Fresh(a) => format!("Data age {a:.1} s   online"),
        Freshness::Offline(a) => format!("OFFLINE: the bridge has lost the BMS ({})", age(a)),
        Freshness::NoData(a) => format!("NO DATA: nothing new from the port ({})", age(a)),
    }
}
