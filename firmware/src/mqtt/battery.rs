//! Packs in parallel in Home Assistant: one device for the whole battery,
//! published by whichever bridge speaks to the inverter
//! ([`crate::inverter::packs`]). Each bridge with Wi-Fi publishes its own pack
//! as before (a device per BMS serial number).
//!
//! The battery has no serial number of its own, and its speaker may change, so
//! its device is named by the topic prefix every bridge of the battery shares:
//! `tinybms_battery_<topic_prefix>` (`/` as `_`), state on
//! `<topic_prefix>/battery/state` — the host link's `battery` line as JSON.
//! Its entities expire as the pack's do ([`Settings::expire_after_s`]): a
//! speaker that falls silent leaves no stale value behind, whichever bridge it
//! was, and needs no will of its own.

use heapless::String;

use super::discovery::{self, Component, Device, Entity, Read, Topics};
use super::{topic, Settings, TOPIC_MAX};

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
        options: None,
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
        options: None,
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
        options: None,
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

/// Writes the discovery config of the battery's entity `e` into `out`; its
/// length (`None` when it does not fit).
pub fn config(
    out: &mut [u8],
    s: &Settings,
    bridge: &crate::identity::Identity,
    e: &Entity,
) -> Option<usize> {
    let id = device_id(s);
    let mut unique: String<72> = String::new();
    unique.push_str(&id).ok()?;
    unique.push('_').ok()?;
    unique.push_str(e.object).ok()?;
    let mut state = String::<TOPIC_MAX>::new();
    if !state_topic(&mut state, s) {
        return None;
    }
    // The battery is the bridges' own device: its versions are the bridge's.
    let (sw, hw) = discovery::bridge_versions(bridge, "", "");
    discovery::write(
        out,
        e,
        &unique,
        &Topics {
            state: &state,
            availability: None,
        },
        s.expire_after_s(),
        Device {
            identifiers: [&id],
            name: "TinyBMS battery",
            manufacturer: super::MANUFACTURER,
            model: "TinyBMS packs in parallel",
            hw_version: Some(&hw),
            sw_version: &sw,
            serial_number: None,
        },
        &discovery::bridge_version(),
    )
}
