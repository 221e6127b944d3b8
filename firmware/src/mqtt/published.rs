//! What the MQTT output reads: the copy the station publishes (the chip puts
//! it in a `Watch`; the desktop runners in a mutex), which the session reads
//! at its own pace, so nothing of the session reaches back into the station.
//! It lives on the MQTT side: the station writes it (`Station::published`),
//! MQTT never names the station.

use protocol_core::views::{LiveSnapshot, VersionInfo};

use crate::freshness::{DataState, Freshness};
use crate::inverter::packs::BatteryView;
use crate::inverter::CanState;
use crate::Instant;

/// The published picture. See the module documentation.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Published {
    /// The latest snapshot.
    pub snapshot: Option<LiveSnapshot>,
    /// Its sequence number.
    pub seq: u32,
    /// When it was decoded (µs on the station's clock).
    pub taken_at: Option<Instant>,
    /// The BMS link is up and the bridge synced.
    pub online: bool,
    /// The check a flagged snapshot failed.
    pub flagged: Option<&'static str>,
    /// The BMS's version block.
    pub version: Option<VersionInfo>,
    /// Requests sent to the BMS and replies received.
    pub link: (u32, u32),
    /// The UART wire's verdict of the last window ([`crate::bms::wire`]).
    pub wire: crate::bms::wire::WireVerdict,
    /// What the inverter is told (CVL 0.1 V, CCL 0.1 A, DCL 0.1 A), while the
    /// CAN output sends it.
    pub limits: Option<(u16, u16, u16)>,
    /// The freshness rule with the configured limit.
    pub freshness: Freshness,
    /// Several packs: the battery as this bridge sees it.
    pub battery: Option<BatteryView>,
    /// Energy into and out of the pack since start-up, mWh
    /// ([`crate::energy`]).
    pub energy_mwh: (u64, u64),
    /// The pack's capacity (register 306, 0.01 Ah), once the settings are read.
    pub capacity_cah: Option<u16>,
    /// The inverter output, when built in.
    pub inverter: Option<InverterStatus>,
    /// The Wi-Fi signal of the access point, dBm, while joined (the chip's
    /// Wi-Fi task reads it; `None`: unknown).
    pub wifi_rssi_dbm: Option<i8>,
    /// "update to X rolled back: reason", when the running image came back
    /// from an update that failed its trial (the update entity's summary).
    pub update_rolled_back: Option<crate::host_link::RolledBack>,
    /// The newest version known to exist beyond the running one (an update
    /// rolled back, a file checked): the update entity's latest version.
    pub update_latest: Option<crate::update::transfer::Version>,
    /// How the pack ages (capacity, cycles, the spread at the top of charge).
    pub aging: crate::history::Aging,
}

/// The inverter output as the MQTT diagnostics show it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InverterStatus {
    /// `victron` or `sma`.
    pub protocol: &'static str,
    /// The CAN output's state.
    pub can: CanState,
    /// The inverter's keep-alive is heard.
    pub heard: bool,
    /// What must stop (`None`: the output off).
    pub stops: Option<crate::inverter::dialect::Stops>,
    /// What the frames sent tell the inverter, read back from them.
    pub told: crate::inverter::dialect::Told,
    /// The last stop the inverter was seen ignoring.
    pub ignored: Option<crate::inverter::ignored::Ignored>,
    /// Where the charge is and why.
    pub stage: Option<crate::inverter::finish::Stage>,
    /// Why each limit is what it is.
    pub reasons: Option<crate::inverter::why::Reasons>,
    /// The doctor's verdicts of the last minute.
    pub verdicts: [Option<crate::inverter::doctor::Verdict>; crate::inverter::doctor::KINDS],
}

impl Published {
    /// The snapshot's age at `now`, µs.
    pub fn age_us(&self, now: Instant) -> Option<Instant> {
        self.taken_at.map(|t| now.saturating_sub(t))
    }

    /// How current it is at `now` (the one rule).
    pub fn state(&self, now: Instant) -> DataState {
        if self.snapshot.is_none() {
            return DataState::NoData;
        }
        self.freshness.state(self.online, self.age_us(now))
    }
}
