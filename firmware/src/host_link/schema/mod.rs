//! The host link's output lines as types: one definition of every line's
//! members, which the firmware writes ([`encode`](super::encode), its values in
//! [`wire`](super::wire)) and a host
//! reads (`feature = "read-lines"`: [`Read`] and [`HostLine`]). A member renamed
//! or added here changes both sides at once; nothing on either side spells a
//! member's name in a string.
//!
//! Each line is generic over its [`Form`]: the firmware's [`Wire`] borrows its
//! text and writes exact decimals ([`Dec`]) without allocating; a host's
//! [`Read`] owns its text and reads numbers as `f64`. Members are written in the
//! order they are declared. A member that a line
//! leaves out when it has no value is `Option` with `skip_serializing_if`; a
//! member written as `null` is `Option` without it.

use serde::Serialize;

use super::wire::{Cells, Hex, Name};
use crate::units::Dec;

mod flat;
use flat::Flat;

/// What a line's members are made of, on one side of the link.
pub trait Form {
    /// Text: keys, names, free text.
    type Text: Serialize + core::fmt::Debug + Clone + PartialEq;
    /// A name from a table of the BMS's (status, event, reason, sensor) or
    /// `unknown_0xNN`.
    type Name: Serialize + core::fmt::Debug + Clone + PartialEq;
    /// A decimal quantity.
    type Number: Serialize + core::fmt::Debug + Clone + PartialEq;
    /// Cell voltages, V.
    type Cells: Serialize + core::fmt::Debug + Clone + PartialEq;
    /// Bytes as upper-case hex.
    type Hex: Serialize + core::fmt::Debug + Clone + PartialEq;
    /// A list of names.
    type Names: Serialize + core::fmt::Debug + Clone + PartialEq;
    /// The line's `type` member as written; on a host the member is the
    /// [`HostLine`] variant instead.
    type Tag: Serialize + Default + core::fmt::Debug + Clone + PartialEq;
}

/// The firmware's side: borrowed text, exact decimals, no allocation.
#[derive(Debug, Clone, Copy)]
pub struct Wire<'a>(core::marker::PhantomData<&'a ()>);

impl<'a> Form for Wire<'a> {
    type Text = &'a str;
    type Name = Name;
    type Number = Dec;
    type Cells = Cells<'a>;
    type Hex = Hex<'a>;
    type Names = &'a [&'static str];
    type Tag = &'static str;
}

/// Declares a line type with what every line type derives: `Serialize` for
/// any form (each member's type says how it writes), and with `read-lines`
/// `Deserialize` for a host's form ([`ReadSide`]).
macro_rules! line_type {
    // `answer`: the line's `type` member, then the request id it echoes (a
    // line that answers a command), then the members given.
    ($(#[$m:meta])* pub struct $name:ident<F: Form> answer { $($body:tt)* }) => {
        line_type! {
            $(#[$m])*
            pub struct $name<F: Form> tagged {
                /// Echoed request id.
                #[serde(skip_serializing_if = "Option::is_none")]
                pub req: Option<u32>,
                $($body)*
            }
        }
    };
    // `tagged`: the line's `type` member, then the members given.
    ($(#[$m:meta])* pub struct $name:ident<F: Form> tagged { $($body:tt)* }) => {
        line_type! {
            $(#[$m])*
            pub struct $name<F: Form> {
                #[serde(rename = "type", skip_deserializing)]
                #[allow(missing_docs)]
                pub ty: F::Tag,
                $($body)*
            }
        }
    };
    ($(#[$m:meta])* pub struct $name:ident<F: Form> { $($body:tt)* }) => {
        $(#[$m])*
        #[derive(Serialize)]
        #[serde(bound(serialize = ""))]
        #[cfg_attr(
            feature = "read-lines",
            derive(serde::Deserialize, Debug, Clone, PartialEq),
            serde(bound(deserialize = "F: ReadSide"))
        )]
        pub struct $name<F: Form> { $($body)* }
    };
}

line_type! {
    /// `hello`: who the bridge is.
    pub struct Hello<F: Form> answer {
        /// [`super::PROTOCOL_VERSION`].
        pub protocol: u32,
        /// The firmware's version.
        pub firmware: F::Text,
        /// What the image was built from.
        pub build: F::Text,
        /// The chip.
        pub chip: F::Text,
        /// The board.
        pub board: F::Text,
        /// What the image has built in.
        pub features: F::Names,
        /// The configuration record's layout.
        pub record_version: u8,
        /// Read-only.
        pub read_only: bool,
        /// The stream period, ms.
        pub stream_period_ms: u32,
        /// Lines the host did not get since start-up.
        pub dropped_lines: u32,
        /// Where the configuration store lives.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub store: Option<Store<F>>,
        /// Where the MQTT connection stands (images with Wi-Fi).
        #[serde(skip_serializing_if = "Option::is_none")]
        pub mqtt: Option<F::Text>,
        /// The radio's start ([`crate::wifi::Radio::key`]; images with Wi-Fi).
        #[serde(skip_serializing_if = "Option::is_none")]
        pub radio: Option<F::Text>,
        /// The Wi-Fi link (images with Wi-Fi).
        #[serde(skip_serializing_if = "Option::is_none")]
        pub wifi: Option<Wifi<F>>,
        /// "update to X rolled back: reason", when this image came back from
        /// an update that failed its trial.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub rolled_back: Option<F::Text>,
        /// Updates: the slot running, its trial, the keys trusted.
        #[serde(skip_serializing_if = "Option::is_none", default)]
        pub update: Option<UpdateHello<F>>,
        /// The history in flash: `recording`, or why there is none (a table
        /// from before the history partition: one reinstall by cable adds
        /// it). Absent from a bridge older than the history.
        #[serde(skip_serializing_if = "Option::is_none", default)]
        pub history: Option<F::Text>,
    }
}

line_type! {
    /// Updates, in `hello`: what runs and which keys an update file must
    /// be signed with (public keys).
    pub struct UpdateHello<F: Form> {
        /// The app slot running (`ota_0`, `ota_1`); none without two slots
        /// (an install from before updates without a cable).
        pub slot: Option<F::Text>,
        /// `confirmed` or `on_trial`.
        pub trial: F::Text,
        /// The key built into the image, hex.
        pub built_in_key: Option<F::Hex>,
        /// The owner's key (`update_key`), hex.
        pub owner_key: Option<F::Hex>,
    }
}

line_type! {
    /// The Wi-Fi link, in `hello`.
    pub struct Wifi<F: Form> {
        /// [`crate::improv::WifiLink::key`].
        pub state: F::Text,
        /// The address, once joined.
        pub ip: Option<F::Text>,
    }
}

line_type! {
    /// Where the configuration store lives, in `hello`.
    pub struct Store<F: Form> {
        /// The flash's size, KiB.
        pub flash_kib: u32,
        /// The store partition's offset.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub partition_offset: Option<u32>,
        /// The store partition's size, bytes.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub partition_bytes: Option<u32>,
        /// What the store needs, bytes.
        pub needs_bytes: u32,
        /// Why the store cannot be used, if it cannot.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub problem: Option<F::Text>,
    }
}

/// `telemetry` (and, with [`Extras`], the MQTT state): the head, the snapshot
/// when there is one, what the inverter is told, the MQTT state's members. One
/// JSON object: the parts' members side by side (see `Flat`).
#[cfg_attr(
    feature = "read-lines",
    derive(serde::Deserialize, Debug, Clone, PartialEq),
    serde(bound(deserialize = "F: ReadSide"))
)]
pub struct Telemetry<F: Form> {
    /// Sequence, age, freshness limit, link.
    #[cfg_attr(feature = "read-lines", serde(flatten))]
    pub head: Head<F>,
    /// The live values, once a snapshot was taken.
    #[cfg_attr(feature = "read-lines", serde(flatten))]
    pub snapshot: Option<Snapshot<F>>,
    /// What the inverter is told (images with CAN output, host link only).
    #[cfg_attr(feature = "read-lines", serde(flatten))]
    pub told: Told<F>,
    /// The MQTT state's members (absent on the host link).
    #[cfg_attr(feature = "read-lines", serde(flatten))]
    pub extras: Option<Extras<F>>,
}

impl<F: Form> Serialize for Telemetry<F> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut m = s.serialize_map(None)?;
        self.head.serialize(Flat(&mut m))?;
        self.snapshot.serialize(Flat(&mut m))?;
        self.told.serialize(Flat(&mut m))?;
        self.extras.serialize(Flat(&mut m))?;
        m.end()
    }
}

line_type! {
    /// A `telemetry` line's head.
    pub struct Head<F: Form> answer {
        /// [`crate::Telemetry::snapshot_seq`].
        pub seq: u32,
        /// The snapshot's age, ms (`None`: none yet).
        pub age_ms: Option<u64>,
        /// The freshness rule's limit the bridge runs with, ms: a host shows
        /// "stale" by the bridge's rule, not a constant of its own.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub stale_after_ms: Option<u64>,
        /// The BMS answers.
        pub online: bool,
        /// Settings and limits read.
        pub ready: bool,
        /// Configuration fields changed that apply at the next restart
        /// (absent: none).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub restart_pending: Option<u32>,
    }
}

line_type! {
    /// What the inverter is told, as a `telemetry` line's `inverter` member.
    pub struct Told<F: Form> {
        /// The inverter output (`None`: no CAN output, or the MQTT state).
        #[serde(skip_serializing_if = "Option::is_none")]
        pub inverter: Option<Inverter<F>>,
    }
}

line_type! {
    /// A snapshot's live values, in replay's names and units.
    pub struct Snapshot<F: Form> {
        /// Pack voltage, V.
        pub pack_voltage_v: Option<F::Number>,
        /// Pack current, A (negative: discharging).
        pub pack_current_a: Option<F::Number>,
        /// Lowest cell, V.
        pub min_cell_voltage_v: Option<F::Number>,
        /// Highest cell, V.
        pub max_cell_voltage_v: Option<F::Number>,
        /// Every cell register, V.
        pub cell_voltages_v: F::Cells,
        /// The register of the first cell (register 53's rule).
        pub cell_first_register: u8,
        /// Cells.
        pub cell_count: u16,
        /// State of charge, %.
        pub soc_percent: Option<F::Number>,
        /// State of health, %.
        pub soh_percent: Option<F::Number>,
        /// The BMS's lifetime counter, s.
        pub lifetime_s: u32,
        /// Estimated time left, s.
        pub estimated_time_left_s: u32,
        /// The BMS's own temperature, °C.
        pub internal_temperature_c: Option<F::Number>,
        /// External sensor 1, °C (`None`: not connected).
        pub external_temperature_1_c: Option<F::Number>,
        /// External sensor 2, °C.
        pub external_temperature_2_c: Option<F::Number>,
        /// Register 50's status.
        pub online_status: F::Name,
        /// Cells the BMS decided to balance (bit 0: cell 1).
        pub balancing_decision_bits: u16,
        /// Cells balancing now.
        pub real_balancing_bits: u16,
        /// Speed, km/h.
        pub speed_kmh: Option<F::Number>,
        /// Distance left, km.
        pub distance_left_km: u16,
        /// Why a value in this snapshot is doubtful, when one is.
        pub flagged: Option<F::Text>,
    }
}

/// The registers each member of a [`Snapshot`] is read from (Rev D §3.1,
/// HARDWARE-NOTES for register 53's cell rule), as inclusive ranges: a member
/// can be told only when all of them were read. `replay` prints a partial read
/// by it; a test checks that these are exactly the members a line writes.
pub const SNAPSHOT_REGISTERS: &[(&str, &[(u16, u16)])] = &[
    ("pack_voltage_v", &[(36, 37)]),
    ("pack_current_a", &[(38, 39)]),
    ("min_cell_voltage_v", &[(40, 40)]),
    ("max_cell_voltage_v", &[(41, 41)]),
    ("cell_voltages_v", &[(0, 15), (53, 53)]),
    ("cell_first_register", &[(0, 15), (53, 53)]),
    ("cell_count", &[(53, 53)]),
    ("soc_percent", &[(46, 47)]),
    ("soh_percent", &[(45, 45)]),
    ("lifetime_s", &[(32, 33)]),
    ("estimated_time_left_s", &[(34, 35)]),
    ("internal_temperature_c", &[(48, 48)]),
    ("external_temperature_1_c", &[(42, 42)]),
    ("external_temperature_2_c", &[(43, 43)]),
    ("online_status", &[(50, 50)]),
    ("balancing_decision_bits", &[(51, 51)]),
    ("real_balancing_bits", &[(52, 52)]),
    ("speed_kmh", &[(54, 55)]),
    ("distance_left_km", &[(44, 44)]),
];

/// The registers each member of a [`StatisticsLine`] is read from (Rev D
/// §3.2), as [`SNAPSHOT_REGISTERS`].
pub const STATISTICS_REGISTERS: &[(&str, &[(u16, u16)])] = &[
    ("total_distance_km", &[(100, 101)]),
    ("max_discharge_current_a", &[(102, 102)]),
    ("max_charge_current_a", &[(103, 103)]),
    ("max_cell_voltage_difference_v", &[(104, 104)]),
    ("under_voltage_count", &[(105, 105)]),
    ("over_voltage_count", &[(106, 106)]),
    ("discharge_over_current_count", &[(107, 107)]),
    ("charge_over_current_count", &[(108, 108)]),
    ("over_heat_count", &[(109, 109)]),
    ("charging_count", &[(111, 111)]),
    ("full_charge_count", &[(112, 112)]),
    ("min_pack_temperature_c", &[(113, 113)]),
    ("max_pack_temperature_c", &[(113, 113)]),
    ("last_reset", &[(114, 114)]),
    ("last_wakeup", &[(114, 114)]),
    ("stats_cleared_at_s", &[(116, 117)]),
];

/// The registers each member of a [`Version`] line is read from (Rev D §3.5),
/// as [`SNAPSHOT_REGISTERS`].
pub const VERSION_REGISTERS: &[(&str, &[(u16, u16)])] = &[
    ("hardware_version", &[(500, 500)]),
    ("hardware_changes_version", &[(500, 500)]),
    ("firmware_public_version", &[(501, 501)]),
    ("high_power", &[(501, 501)]),
    ("current_sensor", &[(501, 501)]),
    ("firmware_internal_version", &[(502, 502)]),
    ("bootloader_version", &[(503, 503)]),
    ("profile_version", &[(503, 503)]),
    ("serial_number", &[(504, 509)]),
];

line_type! {
    /// The inverter output as a `telemetry` line's `inverter` member says it.
    pub struct Inverter<F: Form> {
        /// `victron` or `sma`.
        pub protocol: F::Text,
        /// [`crate::inverter::CanState::key`].
        pub can: F::Text,
        /// The inverter's keep-alive is heard.
        pub heard: bool,
        /// Charge voltage limit told, V (`None`: nothing sent).
        pub cvl_v: Option<F::Number>,
        /// Charge current limit told, A.
        pub ccl_a: Option<F::Number>,
        /// Discharge current limit told, A.
        pub dcl_a: Option<F::Number>,
        /// What stops charging (a cause, or `none`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub charge_stop: Option<F::Text>,
        /// What stops discharging.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub discharge_stop: Option<F::Text>,
        /// The SOC the frames tell the inverter, % (read back from them: 100
        /// or 0 while a stop is said by the SOC).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub soc_told: Option<u8>,
        /// The charge enable bit told (the dialects that have one).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub charge_enabled: Option<bool>,
        /// The discharge enable bit told.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub discharge_enabled: Option<bool>,
        /// The name 0x35E tells (the dialects that send one).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub name: Option<F::Text>,
        /// The last stop the inverter was seen ignoring (`charge: 9.8 A for
        /// 3 s`): every stop goes out with every signal since.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub ignored: Option<F::Text>,
        /// Where the charge is ([`crate::inverter::finish::Stage::key`]).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub stage: Option<F::Text>,
        /// Why, in words (`absorption held: cells 3 and 7 balancing,
        /// spread 24 mV (at most 40 min more)`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub stage_reason: Option<F::Text>,
        /// Why CVL is what it is, in words ([`crate::inverter::why`]).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub cvl_why: Option<F::Text>,
        /// Why CCL is what it is.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub ccl_why: Option<F::Text>,
        /// Why DCL is what it is.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub dcl_why: Option<F::Text>,
        /// The inverter's heartbeat: mean interval, ms ([`crate::inverter::doctor::Heartbeat`]).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub heartbeat_ms: Option<u32>,
        /// Its longest gap, ms.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub heartbeat_longest_ms: Option<u32>,
        /// Its gaps longer than 3 s.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub heartbeat_late: Option<u32>,
        /// The doctor's verdicts of the last minute, their keys separated by
        /// commas ([`crate::inverter::doctor::Verdict::key`]; none: absent).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub doctor: Option<F::Text>,
    }
}

line_type! {
    /// The MQTT state's members beyond the host link's telemetry (`None` is
    /// published as `null`: unknown).
    #[allow(missing_docs)]
    pub struct Extras<F: Form> {
        pub status: F::Text,
        pub pack_power_w: Option<F::Number>,
        pub cell_spread_v: Option<F::Number>,
        pub data_age_s: Option<F::Number>,
        pub link_quality_percent: Option<F::Number>,
        pub cvl_v: Option<F::Number>,
        pub ccl_a: Option<F::Number>,
        pub dcl_a: Option<F::Number>,
        pub status_name: F::Text,
        pub balancing_cells: F::Text,
        pub remaining_capacity_ah: Option<F::Number>,
        pub energy_charged_kwh: Option<F::Number>,
        pub energy_discharged_kwh: Option<F::Number>,
        pub uptime_s: u64,
        pub bridge_firmware: F::Text,
        pub can_state: Option<F::Text>,
        pub inverter_heard: Option<bool>,
        pub charge_stop: Option<F::Text>,
        pub discharge_stop: Option<F::Text>,
        pub soc_told: Option<u8>,
        pub ignored_stop: Option<F::Text>,
        #[serde(default)]
        pub charge_stage: Option<F::Text>,
        #[serde(default)]
        pub cvl_why: Option<F::Text>,
        #[serde(default)]
        pub ccl_why: Option<F::Text>,
        #[serde(default)]
        pub dcl_why: Option<F::Text>,
        #[serde(default)]
        pub can_doctor: Option<F::Text>,
        #[serde(default)]
        pub bms_wire: Option<F::Text>,
        pub wifi_rssi_dbm: Option<i8>,
        pub update_rolled_back: Option<F::Text>,
        #[serde(default)]
        pub update_latest: Option<F::Text>,
        #[serde(default)]
        pub capacity_measured_ah: Option<F::Number>,
        #[serde(default)]
        pub capacity_uncertainty_percent: Option<F::Number>,
        #[serde(default)]
        pub charge_cycles: Option<u16>,
        #[serde(default)]
        pub top_spread_mv: Option<u16>,
        pub history: F::Text,
    }
}

line_type! {
    /// `setting`: one BMS setting, its value, Rev D's range and the BMS's own.
    pub struct SettingLine<F: Form> answer {
        /// The setting's key.
        pub name: F::Text,
        /// Its register.
        pub address: u16,
        /// The raw register value, when read.
        pub raw: Option<i32>,
        /// The physical value, in `unit`.
        pub value: Option<F::Number>,
        /// The unit.
        pub unit: F::Text,
        /// Rev D's lowest value.
        pub min: Option<F::Number>,
        /// Rev D's highest value.
        pub max: Option<F::Number>,
        /// The BMS's own lowest value (its 0x0D reply).
        pub bms_min: Option<F::Number>,
        /// The BMS's own highest value.
        pub bms_max: Option<F::Number>,
    }
}

line_type! {
    /// `settings_end`, `events_end`: how many lines the answer had.
    pub struct End<F: Form> answer {
        /// Lines.
        pub count: u32,
    }
}

line_type! {
    /// `statistics`: registers 100-118.
    #[allow(missing_docs)]
    pub struct StatisticsLine<F: Form> {
        #[serde(rename = "type", skip_deserializing)]
        pub ty: F::Tag,
        #[serde(skip_serializing_if = "Option::is_none")]
        pub req: Option<u32>,
        pub total_distance_km: Option<F::Number>,
        pub max_discharge_current_a: Option<F::Number>,
        pub max_charge_current_a: Option<F::Number>,
        pub max_cell_voltage_difference_v: Option<F::Number>,
        pub under_voltage_count: u16,
        pub over_voltage_count: u16,
        pub discharge_over_current_count: u16,
        pub charge_over_current_count: u16,
        pub over_heat_count: u16,
        pub charging_count: u16,
        pub full_charge_count: u16,
        pub min_pack_temperature_c: i8,
        pub max_pack_temperature_c: i8,
        pub last_reset: F::Name,
        pub last_wakeup: F::Name,
        pub stats_cleared_at_s: u32,
    }
}

line_type! {
    /// `version`: the BMS's identity.
    #[allow(missing_docs)]
    pub struct Version<F: Form> {
        #[serde(rename = "type", skip_deserializing)]
        pub ty: F::Tag,
        #[serde(skip_serializing_if = "Option::is_none")]
        pub req: Option<u32>,
        pub hardware_version: u8,
        pub hardware_changes_version: u8,
        pub firmware_public_version: u8,
        pub high_power: bool,
        pub current_sensor: F::Name,
        pub firmware_internal_version: u16,
        pub bootloader_version: u8,
        pub profile_version: u8,
        /// Hex digits, no spaces.
        pub serial_number: F::Hex,
    }
}

line_type! {
    /// `event`: one of the BMS's events, new or from its history.
    pub struct EventLine<F: Form> answer {
        /// The BMS's timestamp, s.
        pub timestamp_s: u32,
        /// The event's id.
        pub id: u8,
        /// Its name.
        pub name: F::Name,
        /// `fault`, `warning` or `info`.
        pub severity: F::Text,
        /// From the history (`get events`), not new.
        #[serde(skip_serializing_if = "core::ops::Not::not", default)]
        pub history: bool,
    }
}

line_type! {
    /// `log`: a line of the bridge's log.
    pub struct Log<F: Form> tagged {
        /// `info` or `warn`.
        pub level: F::Text,
        /// The text.
        pub text: F::Text,
        /// Kept from start-up and replayed after `hello`.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub boot: Option<bool>,
    }
}

line_type! {
    /// `link`: the UART link's and the host link's figures.
    #[allow(missing_docs)]
    pub struct Link<F: Form> {
        #[serde(rename = "type", skip_deserializing)]
        pub ty: F::Tag,
        #[serde(skip_serializing_if = "Option::is_none")]
        pub req: Option<u32>,
        pub requests: u32,
        pub replies: u32,
        pub timeouts: u32,
        pub wakeup_resends: u32,
        pub retries: u32,
        pub crc_errors: u32,
        pub framing_errors: u32,
        pub invalid_replies: u32,
        pub nacks_command: u32,
        pub nacks_crc: u32,
        pub nacks_other: u32,
        pub skipped_bytes: u32,
        pub unsolicited: u32,
        pub failures: u32,
        pub latency_min_us: u32,
        pub latency_mean_us: u32,
        pub latency_max_us: u32,
        pub online: bool,
        pub piece_registers: u16,
        pub lines_in: u32,
        pub errors: u32,
        pub dropped_lines: u32,
        #[serde(default)]
        pub corrupted_permille: u16,
        #[serde(default)]
        pub lost_permille: u16,
        #[serde(default)]
        pub resent_permille: u16,
        #[serde(default)]
        pub wire: F::Text,
        #[serde(default)]
        pub wire_verdict: F::Text,
    }
}

line_type! {
    /// `accepted`: a command taken, its answer follows.
    pub struct Accepted<F: Form> answer {
        /// The command.
        pub cmd: F::Text,
    }
}

line_type! {
    /// `outcome`: one setting's write, verified by reading it back.
    pub struct Outcome<F: Form> answer {
        /// The setting's key.
        pub name: F::Text,
        /// The raw value asked for.
        pub raw: i32,
        /// Its physical value.
        pub value: Option<F::Number>,
        /// [`crate::bridge::report::WriteOutcome::name`].
        pub outcome: F::Text,
        /// Why, when not verified.
        pub detail: Option<F::Text>,
        /// What the BMS held instead.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub read_back: Option<u16>,
        /// The BMS's refusal code.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub nack_code: Option<u8>,
        /// The chemistry whose window refused the value.
        #[serde(skip_serializing_if = "Option::is_none")]
        pub chemistry: Option<F::Text>,
        /// A value written because another one was (the follow-up of a pair).
        #[serde(skip_serializing_if = "core::ops::Not::not", default)]
        pub follow_up: bool,
    }
}

line_type! {
    /// `update`: the answer to every `update_…` command.
    pub struct Update<F: Form> answer {
        /// What the command met: `next`, `busy`, `acceptable`, `ended`,
        /// `bad_chunk`, `not_started` or `status`.
        pub state: F::Text,
        /// The file offset to send next.
        pub at: Option<u32>,
        /// `idle`, `receiving`, `finishing` or `installed`.
        pub phase: F::Text,
        /// The file's size, while one is received.
        pub size: Option<u32>,
        /// The version being received or installed.
        pub version: Option<F::Text>,
        /// How the last transfer ended without an update (a key).
        pub ended: Option<F::Text>,
        /// Its words.
        pub detail: Option<F::Text>,
        /// The running image: `confirmed` or `on_trial`.
        pub trial: F::Text,
        /// "update to X rolled back: reason", when the running image came
        /// back from one.
        pub rolled_back: Option<F::Text>,
    }
}

line_type! {
    /// `reset_done`.
    pub struct ResetDone<F: Form> answer {
        /// The BMS said it restarts.
        pub confirmed: bool,
    }
}

line_type! {
    /// `cleared`: events or statistics cleared.
    pub struct Cleared<F: Form> answer {
        /// `events` or `statistics`.
        pub what: F::Text,
        /// The BMS acknowledged.
        pub ok: bool,
    }
}

line_type! {
    /// `can`: one entry of the CAN capture (`get can`), as a candump log
    /// line ([`crate::inverter::capture`]).
    pub struct CanLine<F: Form> answer {
        /// The candump line (`(SECONDS) can0 ID#DATA T|R`).
        pub line: F::Text,
    }
}

line_type! {
    /// `can_end`: the end of a `get can` listing.
    pub struct CanEnd<F: Form> answer {
        /// Lines.
        pub count: u32,
        /// The protocol the bridge speaks on the bus (`inverter_protocol`):
        /// what the capture's frames mean.
        pub protocol: F::Text,
    }
}

line_type! {
    /// `history_event`: one event of the bridge's history in flash (`get
    /// history`; [`crate::history::event`]).
    pub struct HistoryEvent<F: Form> answer {
        /// The record's id (its place in the ring: later is larger).
        pub id: u32,
        /// What happened (`started`, `bms_event`, `stop`, …).
        pub code: F::Text,
        /// The bridge's start it happened in.
        pub boot: u32,
        /// Time since that start, ms.
        pub uptime_ms: u64,
        /// The date, Unix seconds, when the bridge knew it.
        pub date: Option<u64>,
        /// First number (what it is depends on the code).
        pub a: u32,
        /// Second number.
        pub b: u32,
        /// The rest in words or a key (a version, a rule, a field).
        pub text: F::Text,
    }
}

line_type! {
    /// `history_day`: one day record of the history (`get history`), its
    /// bytes as stored ([`crate::history::day`] reads them).
    pub struct HistoryDay<F: Form> answer {
        /// The record's id (later is larger).
        pub id: u32,
        /// The record, upper-case hex.
        pub record: F::Hex,
    }
}

line_type! {
    /// `history_skipped`: a record of the history that could not be read.
    pub struct HistorySkipped<F: Form> answer {
        /// `events` or `days`.
        pub ring: F::Text,
        /// Where (a flash address, or the record's id).
        pub at: u32,
        /// Why, in words.
        pub reason: F::Text,
    }
}

line_type! {
    /// `history_end`: the end of a `get history` listing.
    pub struct HistoryEnd<F: Form> answer {
        /// `history_event` lines.
        pub events: u32,
        /// `history_day` lines.
        pub days: u32,
        /// `history_skipped` lines.
        pub skipped: u32,
    }
}

line_type! {
    /// `raw`: UART bytes while capture is on.
    pub struct Raw<F: Form> tagged {
        /// `tx` or `rx`.
        pub dir: F::Text,
        /// The bytes, upper-case hex separated by spaces.
        pub hex: F::Hex,
    }
}

line_type! {
    /// `error`: a command refused.
    pub struct Error<F: Form> tagged {
        /// Echoed request id (`null`: the line had none, or could not be read).
        pub req: Option<u32>,
        /// The code.
        pub error: F::Text,
        /// The reason, and the offending name after `: `.
        pub detail: F::Text,
    }
}

line_type! {
    /// `config`: one configuration field.
    pub struct ConfigField<F: Form> answer {
        /// The field's name.
        pub name: F::Text,
        /// Its group.
        pub group: F::Text,
        /// The stored value as text (a secret: `set` or empty).
        pub value: F::Text,
        /// Its unit.
        pub unit: F::Text,
        /// The default as text.
        pub default: F::Text,
        /// The range as text.
        pub range: F::Text,
        /// When a change applies.
        pub applies: F::Text,
        /// Stored but not running until a restart.
        pub restart_pending: bool,
        /// A secret (never shown).
        pub secret: bool,
        /// What it is for.
        pub help: F::Text,
        /// What a value that leaves it to the BMS (`bms`, `auto`, `none`)
        /// comes to with the BMS's settings now (`3450 mV`, `60.0 A`), once
        /// they are read.
        #[serde(skip_serializing_if = "Option::is_none", default)]
        pub effective: Option<F::Text>,
    }
}

line_type! {
    /// `config_end`.
    pub struct ConfigEnd<F: Form> answer {
        /// Fields.
        pub count: u32,
        /// The record's layout.
        pub version: u8,
        /// Where the running record came from.
        pub source: F::Text,
        /// Fields waiting for a restart.
        pub restart_pending: u32,
    }
}

line_type! {
    /// `config_outcome`: one field of a `set_config`.
    pub struct ConfigOutcome<F: Form> answer {
        /// The field's name as sent.
        pub name: F::Text,
        /// `applied`, `at_restart`, `unchanged`, `refused`, `not_applied`.
        pub outcome: F::Text,
        /// The value stored, as text.
        pub value: Option<F::Text>,
        /// `out_of_range`, `invalid_value`, `unknown_setting`.
        pub error: Option<F::Text>,
        /// Why.
        pub detail: Option<F::Text>,
        /// The field's range, when refused.
        pub range: Option<F::Text>,
    }
}

line_type! {
    /// `config_done`: the end of a `set_config`.
    pub struct ConfigDone<F: Form> answer {
        /// Fields changed.
        pub changed: u8,
        /// Saved to flash (`None`: nothing to save).
        pub saved: Option<bool>,
        /// Changes that wait for a restart.
        pub restart_needed: u8,
        /// Why the save failed.
        pub detail: Option<F::Text>,
    }
}

line_type! {
    /// `battery`: the battery of several packs, as this bridge sees it.
    #[allow(missing_docs)]
    pub struct Battery<F: Form> {
        #[serde(rename = "type", skip_deserializing)]
        pub ty: F::Tag,
        pub node: u8,
        pub speaking: bool,
        pub packs_online: u8,
        pub packs_offline: u8,
        pub capacity_ah: Option<F::Number>,
        pub soc_percent: Option<F::Number>,
        pub soh_percent: Option<F::Number>,
        pub voltage_v: Option<F::Number>,
        pub current_a: Option<F::Number>,
        pub min_cell_v: Option<F::Number>,
        pub max_cell_v: Option<F::Number>,
        pub min_temperature_c: Option<F::Number>,
        pub max_temperature_c: Option<F::Number>,
        pub cvl_v: Option<F::Number>,
        pub ccl_a: Option<F::Number>,
        pub dcl_a: Option<F::Number>,
    }
}

line_type! {
    /// `pack`: one pack of the battery, from its summary on the bus.
    #[allow(missing_docs)]
    pub struct Pack<F: Form> {
        #[serde(rename = "type", skip_deserializing)]
        pub ty: F::Tag,
        pub node: u8,
        /// [`crate::inverter::packs::PackPart::name`].
        pub state: F::Text,
        pub speaking: bool,
        pub voltage_v: Option<F::Number>,
        pub current_a: Option<F::Number>,
        pub soc_percent: Option<F::Number>,
        pub soh_percent: u8,
        pub min_cell_v: Option<F::Number>,
        pub max_cell_v: Option<F::Number>,
        pub min_temperature_c: Option<F::Number>,
        pub max_temperature_c: Option<F::Number>,
        pub capacity_ah: Option<F::Number>,
        pub data_age_s: Option<F::Number>,
        pub cvl_v: Option<F::Number>,
        pub ccl_a: Option<F::Number>,
        pub dcl_a: Option<F::Number>,
    }
}

#[cfg(feature = "read-lines")]
pub use read::{HostLine, Read, ReadSide};

#[cfg(feature = "read-lines")]
mod read;
