//! The host link's settings as the record gives them (here, not in
//! `host_link`, so the record does not depend on the link that reads it).

/// Default telemetry stream period, ms.
pub const DEFAULT_STREAM_PERIOD_MS: u32 = 1_000;

/// Configuration of the host link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HostLinkConfig {
    /// Refuse `set`, `reset` and `clear` (a read-only bridge).
    pub read_only: bool,
    /// Telemetry stream period at start, ms (0: off; else 100-60000).
    pub stream_period_ms: u32,
    /// Firmware version for `hello`.
    pub firmware: &'static str,
    /// Chip name for `hello` (`esp32c3`, `esp32c6`, `sim`).
    pub chip: &'static str,
    /// Board name for `hello`.
    pub board: &'static str,
    /// What the image has built in, for `hello`.
    pub features: crate::identity::Features,
    /// The freshness rule the bridge runs with ([`super::Config::freshness`]):
    /// its limit goes out in every `telemetry` line.
    pub freshness: crate::freshness::Freshness,
}

impl Default for HostLinkConfig {
    fn default() -> Self {
        Self {
            read_only: false,
            stream_period_ms: DEFAULT_STREAM_PERIOD_MS,
            firmware: crate::identity::FIRMWARE,
            chip: "unknown",
            board: "unknown",
            features: crate::identity::Features::default(),
            freshness: crate::freshness::Freshness::new(crate::freshness::DEFAULT_STALE_AFTER_US),
        }
    }
}
