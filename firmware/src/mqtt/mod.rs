//! The battery in Home Assistant: what the bridge publishes over MQTT, when,
//! and under which topics — sans-IO, like the rest of the library. Publish
//! only: the bridge subscribes to nothing but Home Assistant's status topic,
//! and nothing can be written over the network.
//!
//! * [`discovery`] — the entities as data (pack voltage, current, power, SOC,
//!   SOH, every cell, min/max cell and their difference, temperatures, status,
//!   balancing, the limits sent to the inverter, data age, link quality) and
//!   their retained discovery configs, in Home Assistant's MQTT discovery format.
//! * [`publisher`] — the schedule: availability (online on connect and while
//!   the BMS data is fresh, offline otherwise: stale data is never published as
//!   current), discovery configs (again when Home Assistant says it is back
//!   online; removed with empty retained payloads when discovery is off), the
//!   state every publish period and at once on a status change, events as they
//!   arrive. It hands out one message at a time, encoded only then.
//! * `session` (feature `mqtt`) — the MQTT connection itself (rust-mqtt): connect
//!   with a retained will `offline`, subscribe to Home Assistant's status, publish
//!   what the publisher hands out, keep-alive, reconnect with backoff; over any
//!   byte stream (embassy-net on the chip, a TCP socket or a TAP device on the
//!   desktop), every wait bounded.
//!
//! Never in the charge-control path: the publisher reads copies of the
//! telemetry; the bridge and the inverter output never wait on it (host-tests
//! tests/mqtt_in_the_way.rs shows the poll and CAN timing unchanged while the
//! broker misbehaves).
//!
//! Topics, for a bridge with `topic_prefix` `tinybms` on a BMS of serial `S`
//! (24 hex digits):
//!
//! | topic | retained | what |
//! | --- | --- | --- |
//! | `tinybms/S/availability` | yes | `online` / `offline` (also the will) |
//! | `tinybms/S/state` | no | the host link's telemetry JSON plus a few members (below) |
//! | `tinybms/S/event` | no | each new BMS event (the host link's `event` line) |
//! | `homeassistant/sensor/tinybms_S/OBJECT/config` | yes | discovery configs |
//! | `homeassistant/status` | (subscribed) | Home Assistant's own `online`/`offline` |

#[cfg(feature = "net")]
pub mod net;
#[cfg(feature = "mqtt")]
pub mod session;

pub mod battery;
pub mod discovery;
pub mod published;
pub mod publisher;

use heapless::String;

use crate::config::Config;
use crate::Instant;

/// Longest topic, bytes (`<discovery_prefix 32>/binary_sensor/tinybms_<24>/<object>/config`).
pub const TOPIC_MAX: usize = 128;

/// Longest payload the publisher writes, bytes (a discovery config is about
/// 800, the state with 16 cells about 1,200; with every value and text at
/// its widest, the limits' reasons, the doctor's verdicts and the pack's
/// aging, 2,380: the test `the_widest_state_fits_the_payload`, which keeps a
/// tenth spare). On the heap, while connected.
pub const PAYLOAD_MAX: usize = 2816;

/// Device manufacturer in Home Assistant.
pub const MANUFACTURER: &str = "Energus";

/// Where the MQTT connection stands, as `hello` says it (the session's latest
/// note: `session::Note::state`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MqttState {
    /// Nothing is announced before the BMS's serial number is known.
    WaitingForBms,
    /// Connected to the broker.
    Connected,
    /// Connected, and the connection has held (10 s): this ends a
    /// [`MqttState::ClientIdTaken`], a new connection alone does not.
    Held,
    /// The connection was lost; reconnecting.
    Reconnecting,
    /// Connecting fails (the log line says why).
    CannotConnect,
    /// Another client uses this client id: the broker drops one for the other.
    ClientIdTaken,
}

impl MqttState {
    /// As `hello` writes it.
    pub const fn key(self) -> &'static str {
        match self {
            Self::WaitingForBms => "waiting_for_bms",
            Self::Connected | Self::Held => "connected",
            Self::Reconnecting => "reconnecting",
            Self::CannotConnect => "cannot_connect",
            Self::ClientIdTaken => "client_id_taken",
        }
    }

    /// From its key (`None` for another text: a newer bridge).
    pub fn from_key(k: &str) -> Option<Self> {
        [
            Self::WaitingForBms,
            Self::Held,
            Self::Reconnecting,
            Self::CannotConnect,
            Self::ClientIdTaken,
        ]
        .into_iter()
        .find(|s| s.key() == k)
    }
}

/// What the publisher is configured with (the record's network fields).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Settings {
    /// Every topic of the bridge starts with this.
    pub topic_prefix: String<32>,
    /// Publish discovery configs (off: remove them).
    pub discovery: bool,
    /// Home Assistant's discovery prefix.
    pub discovery_prefix: String<32>,
    /// State period, µs.
    pub publish_period_us: Instant,
    /// The pack's device name (`pack_name`; empty: `TinyBMS` and the end of
    /// the serial).
    pub pack_name: String<24>,
}

/// Entities expire after this many publish periods without a state (Home
/// Assistant's `expire_after`): a bridge that hangs, or loses its network
/// without closing the connection, leaves no value shown as live.
pub const EXPIRE_AFTER_PERIODS: u64 = 3;

/// ... and never sooner than this, s: a state may come a few seconds late
/// over Wi-Fi, and that is not a silent bridge.
pub const EXPIRE_MIN_S: u64 = 15;

/// Longest MQTT keep-alive, s.
pub const KEEP_ALIVE_MAX_S: u64 = 60;

/// Shortest MQTT keep-alive, s.
pub const KEEP_ALIVE_MIN_S: u64 = 5;

/// How late a broker may notice a keep-alive that ran out, s (mosquitto
/// checks its clients' keep-alives every 5 s).
pub const BROKER_CHECK_S: u64 = 5;

impl Settings {
    /// When the entities expire: [`EXPIRE_AFTER_PERIODS`] publish periods,
    /// at least [`EXPIRE_MIN_S`], s (15 s at the default period of 5 s).
    pub fn expire_after_s(&self) -> u64 {
        (self.publish_period_us / crate::SECOND)
            .saturating_mul(EXPIRE_AFTER_PERIODS)
            .max(EXPIRE_MIN_S)
    }

    /// The MQTT keep-alive, s. The broker gives up on a silent connection
    /// 1.5 keep-alives after the last packet it got and publishes the will
    /// (`offline`); mosquitto looks every few seconds ([`BROKER_CHECK_S`]);
    /// and that last packet can be a ping half a keep-alive after the last
    /// state. So `2 × keep-alive + BROKER_CHECK_S` must not pass
    /// [`Settings::expire_after_s`]: 5 s by default, within
    /// [`KEEP_ALIVE_MIN_S`]..=[`KEEP_ALIVE_MAX_S`]. The event entity, which
    /// cannot expire, turns unavailable with the will within the same bound.
    pub fn keep_alive_s(&self) -> u16 {
        (self.expire_after_s().saturating_sub(BROKER_CHECK_S) / 2)
            .clamp(KEEP_ALIVE_MIN_S, KEEP_ALIVE_MAX_S) as u16
    }

    /// From the configuration record.
    pub fn from_config(c: &Config) -> Self {
        Self {
            topic_prefix: c.topic_prefix.clone(),
            discovery: c.discovery,
            discovery_prefix: c.discovery_prefix.clone(),
            publish_period_us: Instant::from(c.publish_period_s) * crate::SECOND,
            pack_name: c.pack_name.clone(),
        }
    }
}

/// The BMS the messages are about: its serial number identifies the Home
/// Assistant device (never the bridge's MAC: a bridge moved to another pack is
/// another device).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Identity {
    /// Registers 504-509.
    pub serial: [u8; 12],
    /// Hardware version and changes (500).
    pub hardware: (u8, u8),
    /// Public and internal firmware version (501, 502).
    pub firmware: (u8, u16),
}

impl Identity {
    /// From the BMS's version block.
    pub fn from_version(v: &protocol_core::views::VersionInfo) -> Self {
        Self {
            serial: v.serial,
            hardware: (v.hardware, v.hardware_changes),
            firmware: (v.firmware_public, v.firmware_internal),
        }
    }

    /// The serial as 24 upper-case hex digits (as the log, `replay` and the host
    /// link print it).
    pub fn serial_hex(&self) -> String<24> {
        let mut s = String::new();
        for b in self.serial {
            for nibble in [b >> 4, b & 0xF] {
                let c = char::from_digit(u32::from(nibble), 16).unwrap_or('0');
                let _ = s.push(c.to_ascii_uppercase());
            }
        }
        s
    }

    /// The device's id in Home Assistant and in every `unique_id`:
    /// `tinybms_<serial>` (letters, digits and `_` only).
    pub fn device_id(&self) -> String<32> {
        let mut s = String::new();
        let _ = s.push_str("tinybms_");
        let _ = s.push_str(&self.serial_hex());
        s
    }
}

/// Writes `parts` into a topic (nothing when it does not fit: `false`).
pub fn topic(out: &mut String<TOPIC_MAX>, parts: &[&str]) -> bool {
    out.clear();
    for p in parts {
        if out.push_str(p).is_err() {
            out.clear();
            return false;
        }
    }
    true
}

/// `<prefix>/<serial>/<leaf>`: the bridge's own topics.
pub fn device_topic(out: &mut String<TOPIC_MAX>, s: &Settings, id: &Identity, leaf: &str) -> bool {
    topic(out, &[&s.topic_prefix, "/", &id.serial_hex(), "/", leaf])
}

/// Home Assistant's status topic: `<discovery_prefix>/status`.
pub fn ha_status_topic(out: &mut String<TOPIC_MAX>, s: &Settings) -> bool {
    topic(out, &[&s.discovery_prefix, "/status"])
}
