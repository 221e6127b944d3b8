//! Packs in parallel in Home Assistant: one device for the whole battery,
//! published by whichever bridge speaks to the inverter
//! ([`crate::inverter::packs`]). Each bridge with Wi-Fi publishes its own pack
//! as before (a device per BMS serial number).
//!
//! The battery has no serial number of its own, and its speaker may change, so
//! its device is named by the topic prefix every bridge of the battery shares:
//! `tinybms_battery_<topic_prefix>` (`/` as `_`), state on
//! `<topic_prefix>/battery/state` — the host link's `battery` line as JSON.
//! Its entities expire ([`EXPIRE_AFTER_PERIODS`] publish periods without a
//! state make them unavailable): a speaker that falls silent leaves no stale
//! value behind, whichever bridge it was, and needs no will of its own.

use heapless::String;

use super::discovery::{presence_template, value_template, Component, Entity, Read};
use super::{topic, Settings, TOPIC_MAX};

/// The battery's entities expire after this many publish periods without a
/// state.
pub const EXPIRE_AFTER_PERIODS: u64 = 3;

const fn sensor(
    object: &'static str,
    name: &'static str,
    device_class: Option<&'static str>,
    unit: Option<&'static str>,
    member: &'static str,
    precision: u8,
) -> Entity {
    Entity {
        object,
        name,
        component: Component::Sensor,
        device_class,
        state_class: Some("measurement"),
        unit,
        read: Read::Nullable(member),
        precision: Some(precision),
        category: None,
    }
}

/// The battery's entities; each reads one member of the `battery` line.
pub const ENTITIES: &[Entity] = &[
    sensor(
        "soc",
        "State of charge",
        Some("battery"),
        Some("%"),
        "soc_percent",
        1,
    ),
    sensor("soh", "State of health", None, Some("%"), "soh_percent", 0),
    sensor(
        "voltage",
        "Voltage",
        Some("voltage"),
        Some("V"),
        "voltage_v",
        2,
    ),
    sensor(
        "current",
        "Current",
        Some("current"),
        Some("A"),
        "current_a",
        1,
    ),
    sensor("capacity", "Capacity", None, Some("Ah"), "capacity_ah", 0),
    Entity {
        object: "packs_online",
        name: "Packs in the battery",
        component: Component::Sensor,
        device_class: None,
        state_class: Some("measurement"),
        unit: None,
        read: Read::Member("packs_online"),
        precision: Some(0),
        category: None,
    },
    Entity {
        object: "packs_offline",
        name: "Packs out of the battery",
        component: Component::Sensor,
        device_class: None,
        state_class: Some("measurement"),
        unit: None,
        read: Read::Member("packs_offline"),
        precision: Some(0),
        category: None,
    },
    sensor(
        "min_cell_voltage",
        "Lowest cell",
        Some("voltage"),
        Some("V"),
        "min_cell_v",
        3,
    ),
    sensor(
        "max_cell_voltage",
        "Highest cell",
        Some("voltage"),
        Some("V"),
        "max_cell_v",
        3,
    ),
    sensor(
        "max_temperature",
        "Highest temperature",
        Some("temperature"),
        Some("°C"),
        "max_temperature_c",
        1,
    ),
    sensor(
        "charge_voltage_limit",
        "Charge voltage limit",
        Some("voltage"),
        Some("V"),
        "cvl_v",
        1,
    ),
    sensor(
        "charge_current_limit",
        "Charge current limit",
        Some("current"),
        Some("A"),
        "ccl_a",
        1,
    ),
    sensor(
        "discharge_current_limit",
        "Discharge current limit",
        Some("current"),
        Some("A"),
        "dcl_a",
        1,
    ),
];

/// `tinybms_battery_<topic_prefix>` with `/` as `_`.
pub fn device_id(s: &Settings) -> String<48> {
    let mut id = String::new();
    let _ = id.push_str("tinybms_battery_");
    for c in s.topic_prefix.chars() {
        let _ = id.push(if c == '/' { '_' } else { c });
    }
    id
}

/// `<topic_prefix>/battery/state`.
pub fn state_topic(out: &mut String<TOPIC_MAX>, s: &Settings) -> bool {
    topic(out, &[&s.topic_prefix, "/battery/state"])
}

/// `<discovery_prefix>/<component>/<battery device id>/<object>/config`.
pub fn config_topic(out: &mut String<TOPIC_MAX>, s: &Settings, e: &Entity) -> bool {
    topic(
        out,
        &[
            &s.discovery_prefix,
            "/",
            e.component.name(),
            "/",
            &device_id(s),
            "/",
            e.object,
            "/config",
        ],
    )
}

#[derive(serde::Serialize)]
struct Device<'a> {
    identifiers: [&'a str; 1],
    name: &'static str,
    manufacturer: &'static str,
    model: &'static str,
    sw_version: &'a str,
}

#[derive(serde::Serialize)]
struct Origin<'a> {
    name: &'static str,
    sw_version: &'a str,
}

#[derive(serde::Serialize)]
struct Availability<'a> {
    topic: &'a str,
    value_template: &'a str,
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
    expire_after: u64,
    #[serde(skip_serializing_if = "Option::is_none")]
    availability: Option<[Availability<'a>; 1]>,
    device: Device<'a>,
    origin: Origin<'a>,
}

/// Writes the discovery config of the battery's entity `e` into `out`; its
/// length (`None` when it does not fit).
pub fn config(out: &mut [u8], s: &Settings, bridge_version: &str, e: &Entity) -> Option<usize> {
    let id = device_id(s);
    let mut unique: String<72> = String::new();
    unique.push_str(&id).ok()?;
    unique.push('_').ok()?;
    unique.push_str(e.object).ok()?;
    let mut state = String::<TOPIC_MAX>::new();
    if !state_topic(&mut state, s) {
        return None;
    }
    let template = value_template(e.read);
    // A value that is null (no pack takes part) makes the entity unavailable.
    let presence = match e.read {
        Read::Nullable(m) => Some(presence_template(m)),
        _ => None,
    };
    let period_s = s.publish_period_us / crate::SECOND;
    let c = Config {
        name: e.name,
        unique_id: &unique,
        state_topic: &state,
        value_template: &template,
        device_class: e.device_class,
        state_class: e.state_class,
        unit_of_measurement: e.unit,
        suggested_display_precision: e.precision,
        expire_after: (period_s * EXPIRE_AFTER_PERIODS).max(EXPIRE_AFTER_PERIODS),
        availability: presence.as_deref().map(|t| {
            [Availability {
                topic: &state,
                value_template: t,
            }]
        }),
        device: Device {
            identifiers: [&id],
            name: "TinyBMS battery",
            manufacturer: super::MANUFACTURER,
            model: "TinyBMS packs in parallel",
            sw_version: bridge_version,
        },
        origin: Origin {
            name: "tinybms-esp32",
            sw_version: bridge_version,
        },
    };
    serde_json_core::to_slice(&c, out).ok()
}
