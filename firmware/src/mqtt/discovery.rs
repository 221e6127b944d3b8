//! The entities of the battery in Home Assistant, as data, and their discovery
//! configs (Home Assistant's MQTT discovery: a retained JSON config per entity
//! under `<discovery_prefix>/<component>/<node_id>/<object_id>/config`). One
//! writer, [`write()`], for the pack's device and the battery's
//! ([`super::battery`]).
//!
//! Every entity reads one member of the state JSON (the host link's telemetry
//! fields plus the members [`crate::host_link::encode::StateExtras`] adds), or
//! the event topic. A value that can be absent — an external sensor that is not
//! connected, the limits of a bridge without CAN output — makes its entity
//! *unavailable* (an availability template on the state topic), never 0. Every
//! entity but the event expires ([`Settings::expire_after_s`]): a bridge that
//! stops publishing leaves no value shown as live.

use heapless::String;
use serde::ser::{Serialize, SerializeSeq, Serializer};

use super::{device_topic, topic, Identity, Settings, TOPIC_MAX};

/// A Home Assistant entity platform.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Component {
    /// `sensor`.
    Sensor,
    /// `binary_sensor`.
    BinarySensor,
    /// `event`: the BMS's events, from the event topic.
    Event,
    /// `update`: the bridge's firmware (installed version; install is not
    /// offered: updates come from `tinybms update`).
    Update,
}

impl Component {
    /// As in the discovery topic.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Sensor => "sensor",
            Self::BinarySensor => "binary_sensor",
            Self::Event => "event",
            Self::Update => "update",
        }
    }
}

/// How an entity reads the state JSON.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Read {
    /// `value_json.<member>`.
    Member(&'static str),
    /// `value_json.<member>`, unavailable while the member is null.
    Nullable(&'static str),
    /// Element `i` of `value_json.cell_voltages_v`.
    Cell(u8),
    /// `ON` when `value_json.<member>` is above 0, else `OFF` (a binary sensor).
    NonZero(&'static str),
    /// `ON` when `value_json.<member>` is true, else `OFF`; unavailable while
    /// it is null (a binary sensor).
    Flag(&'static str),
    /// An event line on the event topic: its `severity` is the event type.
    Event,
    /// The update entity's JSON: the installed version (`bridge_firmware`,
    /// also the latest: nothing newer is announced) and, after a rollback,
    /// its words as the release summary (`update_rolled_back`; empty
    /// otherwise: Home Assistant refuses a null summary).
    Update,
}

impl Read {
    /// The state member it reads.
    pub const fn member(self) -> &'static str {
        match self {
            Self::Member(m) | Self::Nullable(m) | Self::NonZero(m) | Self::Flag(m) => m,
            Self::Cell(_) => "cell_voltages_v",
            Self::Event => "severity",
            Self::Update => "bridge_firmware",
        }
    }
}

/// One entity.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Entity {
    /// Object id (`pack_voltage`); its `unique_id` is `<device id>_<object>`.
    pub object: &'static str,
    /// Name in Home Assistant (the device name is prefixed by Home Assistant).
    pub name: &'static str,
    /// Platform.
    pub component: Component,
    /// `device_class`, if any.
    pub device_class: Option<&'static str>,
    /// `state_class`, if any.
    pub state_class: Option<&'static str>,
    /// Unit, if any.
    pub unit: Option<&'static str>,
    /// What it reads.
    pub read: Read,
    /// Display precision (decimals), if any.
    pub precision: Option<u8>,
    /// `entity_category` (`diagnostic`), if any.
    pub category: Option<&'static str>,
    /// The values an `enum` sensor takes, or an event's types.
    pub options: Option<&'static [&'static str]>,
}

/// The values the status entity takes: Rev D's names of the online status
/// (register 50), and `Other` for a value no table knows. The state's `status`
/// member keeps the keys (`fully_charged`) for automations.
pub const STATUS_OPTIONS: &[&str] = &[
    "Charging",
    "Fully Charged",
    "Discharging",
    "Regeneration",
    "Idle",
    "Fault",
    "Other",
];

/// The values the CAN output's entity takes ([`crate::inverter::CanState`]).
pub const CAN_STATES: &[&str] = &["off", "waiting", "running", "no_ack", "bus_off"];

/// What stops charging or discharging, with a 48 V hybrid inverter's
/// protocol ([`crate::inverter::dialect::StopWhy::key`], or `none`).
pub const STOP_CAUSES: &[&str] = &[
    "none",
    "fault",
    "cell_high",
    "cell_low",
    "temperature",
    "current",
    "link_lost",
    "inverter_asked",
    "limit",
];

/// The event types of the event entity: the events' severities (the event's
/// name, id and time are its attributes).
pub const EVENT_TYPES: &[&str] = &["fault", "warning", "info", "unknown"];

const fn sensor(
    object: &'static str,
    name: &'static str,
    device_class: Option<&'static str>,
    unit: Option<&'static str>,
    read: Read,
    precision: u8,
) -> Entity {
    Entity {
        object,
        name,
        component: Component::Sensor,
        device_class,
        state_class: Some("measurement"),
        unit,
        read,
        precision: Some(precision),
        category: None,
        options: None,
    }
}

/// A sensor without unit or state class (text, enum, duration since).
const fn plain(
    object: &'static str,
    name: &'static str,
    device_class: Option<&'static str>,
    read: Read,
    options: Option<&'static [&'static str]>,
) -> Entity {
    Entity {
        object,
        name,
        component: Component::Sensor,
        device_class,
        state_class: None,
        unit: None,
        read,
        precision: None,
        category: None,
        options,
    }
}

const fn diagnostic(e: Entity) -> Entity {
    Entity {
        category: Some("diagnostic"),
        ..e
    }
}

/// Every entity but the cells.
pub const ENTITIES: &[Entity] = &[
    sensor(
        "pack_voltage",
        "Pack voltage",
        Some("voltage"),
        Some("V"),
        Read::Member("pack_voltage_v"),
        2,
    ),
    sensor(
        "pack_current",
        "Pack current",
        Some("current"),
        Some("A"),
        Read::Member("pack_current_a"),
        1,
    ),
    sensor(
        "pack_power",
        "Pack power",
        Some("power"),
        Some("W"),
        Read::Member("pack_power_w"),
        0,
    ),
    sensor(
        "soc",
        "State of charge",
        Some("battery"),
        Some("%"),
        Read::Member("soc_percent"),
        1,
    ),
    sensor(
        "soh",
        "State of health",
        None,
        Some("%"),
        Read::Member("soh_percent"),
        1,
    ),
    sensor(
        "min_cell_voltage",
        "Lowest cell",
        Some("voltage"),
        Some("V"),
        Read::Member("min_cell_voltage_v"),
        3,
    ),
    sensor(
        "max_cell_voltage",
        "Highest cell",
        Some("voltage"),
        Some("V"),
        Read::Member("max_cell_voltage_v"),
        3,
    ),
    sensor(
        "cell_voltage_difference",
        "Cell difference",
        Some("voltage"),
        Some("V"),
        Read::Member("cell_spread_v"),
        3,
    ),
    sensor(
        "temperature_internal",
        "BMS temperature",
        Some("temperature"),
        Some("°C"),
        Read::Member("internal_temperature_c"),
        1,
    ),
    sensor(
        "temperature_external_1",
        "Temperature 1",
        Some("temperature"),
        Some("°C"),
        Read::Nullable("external_temperature_1_c"),
        1,
    ),
    sensor(
        "temperature_external_2",
        "Temperature 2",
        Some("temperature"),
        Some("°C"),
        Read::Nullable("external_temperature_2_c"),
        1,
    ),
    plain(
        "status",
        "Status",
        Some("enum"),
        Read::Member("status_name"),
        Some(STATUS_OPTIONS),
    ),
    Entity {
        object: "balancing",
        name: "Balancing",
        component: Component::BinarySensor,
        device_class: None,
        state_class: None,
        unit: None,
        read: Read::NonZero("real_balancing_bits"),
        precision: None,
        category: None,
        options: None,
    },
    plain(
        "balancing_cells",
        "Balancing cells",
        None,
        Read::Member("balancing_cells"),
        None,
    ),
    sensor(
        "remaining_capacity",
        "Remaining capacity",
        None,
        Some("Ah"),
        Read::Nullable("remaining_capacity_ah"),
        1,
    ),
    sensor(
        "time_left",
        "Time left",
        Some("duration"),
        Some("s"),
        Read::Member("estimated_time_left_s"),
        0,
    ),
    sensor(
        "capacity_measured",
        "Measured capacity",
        None,
        Some("Ah"),
        Read::Nullable("capacity_measured_ah"),
        1,
    ),
    sensor(
        "top_spread",
        "Spread at the top of charge",
        Some("voltage"),
        Some("mV"),
        Read::Nullable("top_spread_mv"),
        0,
    ),
    Entity {
        state_class: Some("total_increasing"),
        ..sensor(
            "charge_cycles",
            "Charge cycles",
            None,
            None,
            Read::Nullable("charge_cycles"),
            0,
        )
    },
    energy("energy_charged", "Energy charged", "energy_charged_kwh"),
    energy(
        "energy_discharged",
        "Energy discharged",
        "energy_discharged_kwh",
    ),
    sensor(
        "charge_voltage_limit",
        "Charge voltage limit",
        Some("voltage"),
        Some("V"),
        Read::Nullable("cvl_v"),
        1,
    ),
    sensor(
        "charge_current_limit",
        "Charge current limit",
        Some("current"),
        Some("A"),
        Read::Nullable("ccl_a"),
        1,
    ),
    sensor(
        "discharge_current_limit",
        "Discharge current limit",
        Some("current"),
        Some("A"),
        Read::Nullable("dcl_a"),
        1,
    ),
    diagnostic(sensor(
        "data_age",
        "Data age",
        Some("duration"),
        Some("s"),
        Read::Member("data_age_s"),
        1,
    )),
    diagnostic(sensor(
        "link_quality",
        "Link quality",
        None,
        Some("%"),
        Read::Nullable("link_quality_percent"),
        1,
    )),
    diagnostic(Entity {
        unit: Some("s"),
        ..plain(
            "uptime",
            "Bridge uptime",
            Some("duration"),
            Read::Member("uptime_s"),
            None,
        )
    }),
    diagnostic(plain(
        "bridge_firmware",
        "Bridge firmware",
        None,
        Read::Member("bridge_firmware"),
        None,
    )),
    diagnostic(plain(
        "can_output",
        "CAN output",
        Some("enum"),
        Read::Nullable("can_state"),
        Some(CAN_STATES),
    )),
    diagnostic(Entity {
        object: "inverter_heard",
        name: "Inverter heard",
        component: Component::BinarySensor,
        device_class: Some("connectivity"),
        state_class: None,
        unit: None,
        read: Read::Flag("inverter_heard"),
        precision: None,
        category: None,
        options: None,
    }),
    diagnostic(plain(
        "charge_stop",
        "Charge stopped by",
        Some("enum"),
        Read::Nullable("charge_stop"),
        Some(STOP_CAUSES),
    )),
    diagnostic(plain(
        "discharge_stop",
        "Discharge stopped by",
        Some("enum"),
        Read::Nullable("discharge_stop"),
        Some(STOP_CAUSES),
    )),
    diagnostic(Entity {
        object: "soc_told",
        name: "SOC told to the inverter",
        component: Component::Sensor,
        device_class: None,
        state_class: Some("measurement"),
        unit: Some("%"),
        read: Read::Nullable("soc_told"),
        precision: Some(0),
        category: None,
        options: None,
    }),
    diagnostic(plain(
        "ignored_stop",
        "Inverter ignored a stop",
        None,
        Read::Nullable("ignored_stop"),
        None,
    )),
    plain(
        "charge_stage",
        "Charge stage",
        None,
        Read::Nullable("charge_stage"),
        None,
    ),
    diagnostic(plain(
        "cvl_why",
        "Why CVL",
        None,
        Read::Nullable("cvl_why"),
        None,
    )),
    diagnostic(plain(
        "ccl_why",
        "Why CCL",
        None,
        Read::Nullable("ccl_why"),
        None,
    )),
    diagnostic(plain(
        "dcl_why",
        "Why DCL",
        None,
        Read::Nullable("dcl_why"),
        None,
    )),
    diagnostic(plain(
        "can_doctor",
        "CAN doctor",
        None,
        Read::Nullable("can_doctor"),
        None,
    )),
    diagnostic(plain(
        "bms_wire",
        "BMS wire",
        None,
        Read::Nullable("bms_wire"),
        None,
    )),
    diagnostic(plain(
        "history",
        "History in flash",
        None,
        Read::Member("history"),
        None,
    )),
    diagnostic(Entity {
        object: "firmware_update",
        name: "Bridge firmware update",
        component: Component::Update,
        device_class: Some("firmware"),
        state_class: None,
        unit: None,
        read: Read::Update,
        precision: None,
        category: None,
        options: None,
    }),
    diagnostic(sensor(
        "wifi_signal",
        "Wi-Fi signal",
        Some("signal_strength"),
        Some("dBm"),
        Read::Nullable("wifi_rssi_dbm"),
        0,
    )),
    Entity {
        object: "events",
        name: "BMS event",
        component: Component::Event,
        device_class: None,
        state_class: None,
        unit: None,
        read: Read::Event,
        precision: None,
        category: None,
        options: Some(EVENT_TYPES),
    },
];

/// An energy counter for Home Assistant's Energy dashboard (kWh,
/// `total_increasing`).
const fn energy(object: &'static str, name: &'static str, member: &'static str) -> Entity {
    Entity {
        object,
        name,
        component: Component::Sensor,
        device_class: Some("energy"),
        state_class: Some("total_increasing"),
        unit: Some("kWh"),
        read: Read::Member(member),
        precision: Some(3),
        category: None,
        options: None,
    }
}

/// Most cells (Rev D: 16).
pub const MAX_CELLS: u8 = 16;

/// The entity of cell `n` (1-based).
pub fn cell(n: u8) -> Entity {
    const OBJECTS: [&str; 16] = [
        "cell_01", "cell_02", "cell_03", "cell_04", "cell_05", "cell_06", "cell_07", "cell_08",
        "cell_09", "cell_10", "cell_11", "cell_12", "cell_13", "cell_14", "cell_15", "cell_16",
    ];
    const NAMES: [&str; 16] = [
        "Cell 1", "Cell 2", "Cell 3", "Cell 4", "Cell 5", "Cell 6", "Cell 7", "Cell 8", "Cell 9",
        "Cell 10", "Cell 11", "Cell 12", "Cell 13", "Cell 14", "Cell 15", "Cell 16",
    ];
    let i = usize::from(n.clamp(1, MAX_CELLS) - 1);
    sensor(
        OBJECTS.get(i).copied().unwrap_or("cell_01"),
        NAMES.get(i).copied().unwrap_or("Cell 1"),
        Some("voltage"),
        Some("V"),
        Read::Cell(n.clamp(1, MAX_CELLS) - 1),
        3,
    )
}

/// The `n`-th entity announced for a pack of `cells` cells: the fixed ones,
/// then cells 1..=cells. `None` past the end.
pub fn nth(n: usize, cells: u8) -> Option<Entity> {
    match ENTITIES.get(n) {
        Some(e) => Some(*e),
        None => {
            let c = n - ENTITIES.len();
            (c < usize::from(cells.min(MAX_CELLS))).then(|| cell(c as u8 + 1))
        }
    }
}

/// Every entity for a pack of `cells` cells.
pub fn count(cells: u8) -> usize {
    ENTITIES.len() + usize::from(cells.min(MAX_CELLS))
}

/// Writes the discovery topic of `e`.
pub fn config_topic(out: &mut String<TOPIC_MAX>, s: &Settings, id: &Identity, e: &Entity) -> bool {
    topic(
        out,
        &[
            &s.discovery_prefix,
            "/",
            e.component.name(),
            "/",
            &id.device_id(),
            "/",
            e.object,
            "/config",
        ],
    )
}

/// What the device block says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeviceInfo<'a> {
    /// The BMS.
    pub id: &'a Identity,
    /// The bridge that publishes it (its board and chip; its firmware and
    /// build are [`crate::identity::FIRMWARE`] and [`crate::identity::BUILD`]).
    pub bridge: &'a crate::identity::Identity,
}

/// The name of the bridge's firmware in Home Assistant (the `origin` of
/// every discovery config, and the device's versions).
pub const ORIGIN: &str = "tinybms-esp32";

/// Appends `parts` to `s`, as much as fits (a character is never cut).
pub(crate) fn push_all<const N: usize>(s: &mut String<N>, parts: &[&str]) {
    for p in parts {
        for c in p.chars() {
            if s.push(c).is_err() {
                return;
            }
        }
    }
}

/// The bridge's firmware and build: `0.1.0 (build v0.1.0-3-gabc1234)`.
pub fn bridge_version() -> String<72> {
    let mut s = String::new();
    push_all(
        &mut s,
        &[
            crate::identity::FIRMWARE,
            " (build ",
            crate::identity::BUILD,
            ")",
        ],
    );
    s
}

/// What a device's versions say of the bridge that publishes it: its
/// software (`bridge: tinybms-esp32 0.1.0 (build …)`) and its hardware
/// (`bridge: ESP32-C3 SuperMini (esp32c3)`), after `bms_sw` / `bms_hw`, the
/// BMS's own, when there is one.
pub fn bridge_versions(
    bridge: &crate::identity::Identity,
    bms_sw: &str,
    bms_hw: &str,
) -> (String<128>, String<96>) {
    let mut sw = String::new();
    let mut hw = String::new();
    if !bms_sw.is_empty() {
        push_all(&mut sw, &["BMS ", bms_sw, ", "]);
    }
    if !bms_hw.is_empty() {
        push_all(&mut hw, &["BMS ", bms_hw, ", "]);
    }
    push_all(&mut sw, &["bridge: ", ORIGIN, " ", &bridge_version()]);
    push_all(&mut hw, &["bridge: ", bridge.board, " (", bridge.chip, ")"]);
    (sw, hw)
}

/// A device block: the pack's (a BMS, with its serial) or the battery's.
#[derive(serde::Serialize)]
pub struct Device<'a> {
    /// One identifier.
    pub identifiers: [&'a str; 1],
    /// The device's name.
    pub name: &'a str,
    /// Its maker.
    pub manufacturer: &'static str,
    /// Its model.
    pub model: &'static str,
    /// Hardware version, if known.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hw_version: Option<&'a str>,
    /// Software version.
    pub sw_version: &'a str,
    /// Serial number, if any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub serial_number: Option<&'a str>,
}

#[derive(serde::Serialize)]
struct Origin<'a> {
    name: &'static str,
    sw_version: &'a str,
}

/// One availability condition.
#[derive(serde::Serialize)]
struct Availability<'a> {
    topic: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    value_template: Option<&'a str>,
}

struct Strs(&'static [&'static str]);

impl Serialize for Strs {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut seq = s.serialize_seq(Some(self.0.len()))?;
        for o in self.0 {
            seq.serialize_element(o)?;
        }
        seq.end()
    }
}

#[derive(serde::Serialize)]
struct Config<'a> {
    name: &'static str,
    unique_id: &'a str,
    state_topic: &'a str,
    value_template: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    device_class: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    state_class: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    unit_of_measurement: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    suggested_display_precision: Option<u8>,
    #[serde(skip_serializing_if = "Option::is_none")]
    entity_category: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    options: Option<Strs>,
    #[serde(skip_serializing_if = "Option::is_none")]
    event_types: Option<Strs>,
    #[serde(skip_serializing_if = "Option::is_none")]
    expire_after: Option<u64>,
    #[serde(skip_serializing_if = "<[Availability<'_>]>::is_empty")]
    availability: &'a [Availability<'a>],
    #[serde(skip_serializing_if = "Option::is_none")]
    availability_mode: Option<&'static str>,
    device: Device<'a>,
    origin: Origin<'a>,
}

/// The template reading `r` from the state JSON (or, for the event entity,
/// turning an event line into Home Assistant's event payload).
pub fn value_template(r: Read) -> String<256> {
    let mut t = String::new();
    let mut push = |s: &str| {
        let _ = t.push_str(s);
    };
    match r {
        Read::Member(m) | Read::Nullable(m) => {
            push("{{ value_json.");
            push(m);
            push(" }}");
        }
        Read::Cell(i) => {
            push("{{ value_json.cell_voltages_v[");
            let mut n = String::<3>::new();
            if i >= 10 {
                let _ = n.push(char::from(b'0' + i / 10));
            }
            let _ = n.push(char::from(b'0' + i % 10));
            push(&n);
            push("] }}");
        }
        Read::NonZero(m) => {
            push("{{ 'ON' if value_json.");
            push(m);
            push(" > 0 else 'OFF' }}");
        }
        Read::Flag(m) => {
            push("{{ 'ON' if value_json.");
            push(m);
            push(" else 'OFF' }}");
        }
        Read::Event => push(
            "{{ {'event_type': value_json.severity, 'name': value_json.name, \
             'id': value_json.id, 'timestamp_s': value_json.timestamp_s} | to_json }}",
        ),
        // Home Assistant refuses the whole message when a version is null (its
        // schema wants a string): the latest version is named only when known,
        // which leaves the entity's state unknown, never "up to date".
        Read::Update => push(
            "{% set v = {'installed_version': value_json.bridge_firmware, 'release_summary': \
             value_json.update_rolled_back or ''} %}{% if value_json.update_latest %}{% set v = \
             dict(v, latest_version=value_json.update_latest) %}{% endif %}{{ v | to_json }}",
        ),
    }
    t
}

/// The availability template of a nullable member: `offline` while it is null.
pub(crate) fn presence_template(m: &str) -> String<112> {
    let mut t = String::new();
    let _ = t.push_str("{{ 'offline' if value_json.");
    let _ = t.push_str(m);
    let _ = t.push_str(" is none else 'online' }}");
    t
}

/// Where an entity's config points.
pub struct Topics<'a> {
    /// Its state (the state topic, or the event topic for the event entity).
    pub state: &'a str,
    /// The device's availability topic, if it has one (the battery has none:
    /// its speaker may change, its entities expire instead).
    pub availability: Option<&'a str>,
}

/// Writes the discovery config of `e` into `out`: the one writer of every
/// config, the pack's and the battery's; its length (`None` when it does not
/// fit). `expire_after_s`: when a value expires (the event entity has none).
pub fn write(
    out: &mut [u8],
    e: &Entity,
    unique_id: &str,
    topics: &Topics<'_>,
    expire_after_s: u64,
    device: Device<'_>,
    origin_version: &str,
) -> Option<usize> {
    // `origin_version`: the bridge's firmware and build ([`bridge_version`]).
    let template = value_template(e.read);
    // A member that can be null makes the entity unavailable while it is.
    let presence = match e.read {
        Read::Nullable(m) | Read::Flag(m) => Some(presence_template(m)),
        _ => None,
    };
    let mut conditions: heapless::Vec<Availability<'_>, 2> = heapless::Vec::new();
    if let Some(a) = topics.availability {
        let _ = conditions.push(Availability {
            topic: a,
            value_template: None,
        });
    }
    if let Some(p) = presence.as_deref() {
        let _ = conditions.push(Availability {
            topic: topics.state,
            value_template: Some(p),
        });
    }
    let event = e.component == Component::Event;
    let c = Config {
        name: e.name,
        unique_id,
        state_topic: topics.state,
        value_template: &template,
        device_class: e.device_class,
        state_class: e.state_class,
        unit_of_measurement: e.unit,
        suggested_display_precision: e.precision,
        entity_category: e.category,
        options: e.options.filter(|_| !event).map(Strs),
        event_types: e.options.filter(|_| event).map(Strs),
        // An update entity's version does not go stale (it has no expiry).
        expire_after: (!event && e.component != Component::Update).then_some(expire_after_s),
        availability: &conditions,
        availability_mode: (conditions.len() > 1).then_some("all"),
        device,
        origin: Origin {
            name: ORIGIN,
            sw_version: origin_version,
        },
    };
    serde_json_core::to_slice(&c, out).ok()
}

/// Writes the discovery config of the pack's entity `e` into `out`; its
/// length (`None` when it does not fit).
pub fn config(out: &mut [u8], s: &Settings, info: &DeviceInfo<'_>, e: &Entity) -> Option<usize> {
    let id = info.id;
    let device_id = id.device_id();
    let mut unique: String<64> = String::new();
    unique.push_str(&device_id).ok()?;
    unique.push('_').ok()?;
    unique.push_str(e.object).ok()?;
    let mut state = String::<TOPIC_MAX>::new();
    let mut avail = String::<TOPIC_MAX>::new();
    let leaf = if e.component == Component::Event {
        "event"
    } else {
        "state"
    };
    if !device_topic(&mut state, s, id, leaf) || !device_topic(&mut avail, s, id, "availability") {
        return None;
    }
    let serial = id.serial_hex();
    // The owner's name for the pack, else TinyBMS and the serial's end.
    let mut name: String<40> = String::new();
    if s.pack_name.is_empty() {
        name.push_str("TinyBMS ").ok()?;
        name.push_str(serial.get(serial.len().saturating_sub(6)..).unwrap_or(""))
            .ok()?;
    } else {
        name.push_str(&s.pack_name).ok()?;
    }
    let mut bms_hw: String<8> = String::new();
    push_u32(&mut bms_hw, u32::from(id.hardware.0));
    let _ = bms_hw.push('.');
    push_u32(&mut bms_hw, u32::from(id.hardware.1));
    let mut bms_sw: String<24> = String::new();
    push_u32(&mut bms_sw, u32::from(id.firmware.0));
    let _ = bms_sw.push_str(" (");
    push_u32(&mut bms_sw, u32::from(id.firmware.1));
    let _ = bms_sw.push(')');
    // The device is the BMS; its versions name the bridge too.
    let (sw, hw) = bridge_versions(info.bridge, &bms_sw, &bms_hw);
    write(
        out,
        e,
        &unique,
        &Topics {
            state: &state,
            availability: Some(&avail),
        },
        s.expire_after_s(),
        Device {
            identifiers: [&device_id],
            name: &name,
            manufacturer: super::MANUFACTURER,
            model: "TinyBMS s516",
            hw_version: Some(&hw),
            sw_version: &sw,
            serial_number: Some(&serial),
        },
        &bridge_version(),
    )
}

fn push_u32<const N: usize>(s: &mut String<N>, v: u32) {
    let mut digits = [0u8; 10];
    let mut i = digits.len();
    let mut v = v;
    loop {
        i -= 1;
        if let Some(d) = digits.get_mut(i) {
            *d = b'0' + (v % 10) as u8;
        }
        v /= 10;
        if v == 0 || i == 0 {
            break;
        }
    }
    for &d in digits.get(i..).unwrap_or(&[]) {
        let _ = s.push(char::from(d));
    }
}
