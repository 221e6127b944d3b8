//! The bridge's own configuration: one record, kept in the chip's flash and
//! changed over USB (`tinybms config`), instead of constants compiled in.
//!
//! * [`Config`] — the record: the inverter output (protocol, CAN on/off, what
//!   stale data does), every option of charge control, the host link (read-only,
//!   stream period) and the network (Wi-Fi, MQTT, Home Assistant discovery).
//!   [`Config::default`] is what an unconfigured bridge runs with.
//! * [`FIELDS`] — the record as data: every field's name, unit, range, default,
//!   when a change takes effect ([`Applies`]) and a sentence of help. The host
//!   link, the desktop tool and the documentation are driven by this table.
//! * [`value`] — a field's value as text (`50 A`, `3.45 V`, `sma`, `on`) and
//!   back, exactly (no floating point), and the checks of one field.
//! * [`Config::validate`] — the rules between fields, and
//!   [`Config::validate_with_bms`] those against the BMS's own settings (a cap
//!   above the BMS's cutoff is refused).
//! * [`codec`] — the record's bytes in flash: versioned, every field checked on
//!   the way in.
//! * [`state`] — the record the bridge runs with and the one it will store,
//!   changes by name with one outcome per field, when the flash may be written.
//! * [`store`] — the record in a flash partition through `sequential-storage`
//!   (power-loss safe: a write cut at any point leaves the old record or the new).
//! * [`site`] — where that partition is: found through the partition table on
//!   the flash itself, the same way on the chip and in the host tests.
//! * [`button`] — the physical way out of read-only: the BOOT button held down.
//!
//! Sans-IO like the rest of the library: the chip shell moves the bytes between
//! flash and [`store`]; the host runs the same code on a mock and a file-backed
//! flash.

pub mod button;
pub mod codec;
mod host;
pub mod site;
pub mod state;
pub mod store;
pub mod value;

use heapless::String;

use crate::freshness::Freshness;
use crate::inverter::control::ChargeConfig;
use crate::inverter::{InverterConfig, Protocol};
use crate::{Instant, SECOND};

pub use host::{HostLinkConfig, DEFAULT_STREAM_PERIOD_MS};
pub use value::{FieldError, Value};

/// Version of the record's layout in flash ([`codec`]). A record of an older
/// version is read with the fields added since at their defaults
/// ([`codec::introduced`]); one of a newer version is not read: the bridge
/// runs with the defaults and says so.
pub const VERSION: u8 = 3;

/// When a change of a field takes effect.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Applies {
    /// At once (caps, margins, stream period, stale age: safe to change while
    /// running — a limit that falls falls at once, one that rises ramps).
    Now,
    /// At the next restart (the inverter protocol, CAN on/off, the network:
    /// what the tasks are started with).
    Restart,
}

impl Applies {
    /// As printed (`now`, `restart`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Now => "now",
            Self::Restart => "restart",
        }
    }
}

/// Which part of the bridge a field belongs to (how `tinybms config` groups them).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Group {
    /// The inverter output (CAN).
    Inverter,
    /// Charge control: the limits sent to the inverter.
    Charge,
    /// The host link (USB).
    Host,
    /// Wi-Fi and MQTT.
    Network,
}

impl Group {
    /// As printed.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Inverter => "inverter",
            Self::Charge => "charge",
            Self::Host => "host",
            Self::Network => "network",
        }
    }
}

/// Characters a text field accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TextRule {
    /// Any printable character (a Wi-Fi name, a user name).
    Printable,
    /// A host name or an IPv4 address: letters, digits, `-` and `.`.
    Host,
    /// An MQTT topic prefix: letters, digits, `-`, `_` and `/` between levels
    /// (no wildcard, no empty level, no `/` at either end).
    Topic,
}

/// What kind of value a field holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// `on` / `off`.
    Bool,
    /// One of these names (stored as its index).
    Choice(&'static [&'static str]),
    /// A whole number of `10^-decimals` units, within `min..=max`; `off` names
    /// the value 0 when 0 is allowed too and means "not set" (`bms`, `none`, `auto`).
    Number {
        /// Smallest value (raw).
        min: i32,
        /// Largest value (raw).
        max: i32,
        /// Decimals of the unit the raw value counts.
        decimals: u8,
        /// The word for 0, when 0 is allowed outside `min..=max`.
        off: Option<&'static str>,
    },
    /// Text of at most `max` bytes (UTF-8); empty means "not set".
    Text {
        /// Longest, bytes.
        max: u8,
        /// What it may contain.
        rule: TextRule,
    },
    /// A secret: never shown, only whether it is set. `hex64`: exactly 64 hex
    /// digits (a WPA2 pre-shared key); else printable text of at most `max` bytes.
    Secret {
        /// Longest, bytes.
        max: u8,
        /// Exactly 64 hex digits.
        hex64: bool,
    },
}

/// One field of the record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Field {
    /// Which.
    pub id: FieldId,
    /// Its stable number in the flash record ([`codec`]): never reused.
    pub tag: u8,
    /// snake_case name, as `tinybms config` and the host link write it.
    pub name: &'static str,
    /// Unit of the value ("" when it has none).
    pub unit: &'static str,
    /// Kind and range.
    pub kind: Kind,
    /// When a change takes effect.
    pub applies: Applies,
    /// Which part of the bridge it belongs to.
    pub group: Group,
    /// One sentence for the user.
    pub help: &'static str,
}

impl Field {
    /// True for a secret (shown only as set or unset).
    pub const fn is_secret(&self) -> bool {
        matches!(self.kind, Kind::Secret { .. })
    }
}

/// Longest text of any field, bytes.
pub const TEXT_MAX: usize = 64;

pub use crate::freshness::StaleMode;

macro_rules! fields {
    ($( $id:ident = $tag:literal, $name:literal, $unit:literal, $group:ident, $applies:ident,
        $kind:expr, $help:literal; )*) => {
        /// A field of the record, by name in code.
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        pub enum FieldId { $( #[doc = $help] $id, )* }

        /// Every field, in the order `tinybms config` shows them.
        pub const FIELDS: &[Field] = &[ $( Field {
            id: FieldId::$id,
            tag: $tag,
            name: $name,
            unit: $unit,
            kind: $kind,
            applies: Applies::$applies,
            group: Group::$group,
            help: $help,
        }, )* ];
    };
}

/// Choices of `inverter_protocol`.
pub const PROTOCOLS: &[&str] = &["victron", "sma"];
/// Choices of `stale_policy`.
pub const STALE_MODES: &[&str] = &["stop", "hold"];

const fn num(min: i32, max: i32, decimals: u8) -> Kind {
    Kind::Number {
        min,
        max,
        decimals,
        off: None,
    }
}

const fn num_or(min: i32, max: i32, decimals: u8, off: &'static str) -> Kind {
    Kind::Number {
        min,
        max,
        decimals,
        off: Some(off),
    }
}

const fn text(max: u8, rule: TextRule) -> Kind {
    Kind::Text { max, rule }
}

fields! {
    CanOutput = 1, "can_output", "", Inverter, Restart, Kind::Bool,
        "Send the battery's limits and state to the inverter over CAN.";
    InverterProtocol = 2, "inverter_protocol", "", Inverter, Restart, Kind::Choice(PROTOCOLS),
        "The inverter's CAN protocol: victron (a GX, \"CAN-bus BMS 500 kbit/s\") or sma (Sunny Island).";
    StaleAfter = 3, "stale_after", "s", Inverter, Now, num(1, 60, 0),
        "BMS data older than this is stale: the stale policy applies.";
    StalePolicyField = 4, "stale_policy", "", Inverter, Now, Kind::Choice(STALE_MODES),
        "On stale data: hold (charge limit 0, discharge allowed, for stale_hold: an island inverter keeps the house on through a short loss, the BMS's own cutoffs still protect the pack) or stop (stop sending: the inverter stops charging and discharging).";
    StaleHold = 5, "stale_hold", "s", Inverter, Now, num(10, 3600, 0),
        "With stale_policy hold: how long the inverter may keep discharging on stale data.";
    PackNode = 6, "pack_node", "", Inverter, Restart, num_or(1, 8, 0, "alone"),
        "Packs in parallel, one bridge each, on one CAN bus: this bridge's number (1 = the primary, which speaks to the inverter); alone = this pack is the whole battery.";
    AbsorptionVoltage = 10, "absorption_voltage", "mV", Charge, Now, num_or(1000, 4500, 0, "bms"),
        "Charge target per cell; bms = the BMS's own fully charged voltage setting.";
    AbsorptionMargin = 11, "absorption_margin", "mV", Charge, Now, num(20, 500, 0),
        "The charge target stays at least this far below the BMS's over-voltage cutoff.";
    FloatVoltage = 12, "float_voltage", "mV", Charge, Now, num_or(1000, 4500, 0, "auto"),
        "Float target per cell after a full charge; auto = 15/16 of the charge target.";
    CeilingMargin = 13, "ceiling_margin", "mV", Charge, Now, num(20, 500, 0),
        "No cell is charged closer than this to the over-voltage cutoff (the charge limit is 0 there).";
    DischargeMargin = 14, "discharge_margin", "mV", Charge, Now, num(0, 1000, 0),
        "Discharge stops this far above the BMS's under-voltage cutoff.";
    ChargeTaper = 15, "charge_taper", "mV", Charge, Now, num(10, 1000, 0),
        "The charge limit falls from full to 0 over this window below the ceiling.";
    DischargeTaper = 16, "discharge_taper", "mV", Charge, Now, num(10, 1000, 0),
        "The discharge limit falls from full to 0 over this window above the discharge stop.";
    RunnerTolerance = 17, "runner_tolerance", "mV", Charge, Now, num(0, 200, 0),
        "How far the highest cell may run ahead of the average before the charge voltage is lowered for it.";
    TailCurrent = 18, "tail_current", "A", Charge, Now, num(1, 1000, 1),
        "Charge current below which a full pack counts as tapered (for the switch to float).";
    FullHold = 19, "full_hold", "s", Charge, Now, num(10, 3600, 0),
        "How long the pack stays at the target, tapered, before float.";
    RebulkSoc = 20, "rebulk_soc", "%", Charge, Now, num(50, 99, 0),
        "Below this state of charge float ends and charging starts again.";
    ChargeCurrentCap = 21, "charge_current_cap", "A", Charge, Now, num_or(1, 7500, 1, "none"),
        "Most charge current ever asked for; none = the BMS's charge over-current cutoff (a cap above it is refused).";
    DischargeCurrentCap = 22, "discharge_current_cap", "A", Charge, Now, num_or(1, 7500, 1, "none"),
        "Most discharge current ever allowed; none = the BMS's discharge over-current cutoff (a cap above it is refused).";
    TemperatureMargin = 23, "temperature_margin", "°C", Charge, Now, num(1, 20, 0),
        "Current limits are derated over this window inside each temperature cutoff.";
    LimitHold = 24, "limit_hold", "s", Charge, Now, num(0, 600, 0),
        "After a limit was cut to 0 for a cause in the BMS's data (a fault, a cell at its cutoff, a temperature), how long before it may rise again (a lost link is no such cause).";
    RampRate = 25, "ramp_rate", "A/s", Charge, Now, num(1, 1000, 1),
        "How fast a current limit may rise.";
    CvlRaiseInterval = 26, "cvl_raise_interval", "s", Charge, Now, num(5, 600, 0),
        "The charge voltage is raised at most this often (lowered at once).";
    WarningMargin = 27, "warning_margin", "mV", Charge, Now, num(0, 500, 0),
        "Voltage warnings start this far inside a cutoff.";
    WarningCurrent = 28, "warning_current", "%", Charge, Now, num(50, 100, 0),
        "Current warnings start at this share of a current cutoff.";
    ReadOnly = 40, "read_only", "", Host, Now, Kind::Bool,
        "Refuse every write from the computer: BMS settings, resets, clears and this configuration.";
    StreamPeriod = 41, "stream_period", "ms", Host, Now, num_or(100, 60_000, 0, "off"),
        "How often telemetry is pushed to the computer.";
    WifiSsid = 60, "wifi_ssid", "", Network, Restart, text(32, TextRule::Printable),
        "The Wi-Fi network's name; empty = no Wi-Fi.";
    WifiKey = 61, "wifi_key", "", Network, Restart, Kind::Secret { max: 64, hex64: true },
        "The WPA2 pre-shared key, 64 hex digits (`tinybms wifi` derives it from the passphrase).";
    Hostname = 62, "hostname", "", Network, Restart, text(32, TextRule::Host),
        "The bridge's name on the network; empty = tinybms-XXXXXX from its MAC address.";
    MqttHost = 63, "mqtt_host", "", Network, Restart, text(64, TextRule::Host),
        "The MQTT broker (host name or IPv4 address); empty = no MQTT.";
    MqttPort = 64, "mqtt_port", "", Network, Restart, num(1, 65_535, 0),
        "The broker's TCP port.";
    MqttUser = 65, "mqtt_user", "", Network, Restart, text(32, TextRule::Printable),
        "User name at the broker; empty = none.";
    MqttPassword = 66, "mqtt_password", "", Network, Restart, Kind::Secret { max: 64, hex64: false },
        "Password at the broker.";
    TopicPrefix = 67, "topic_prefix", "", Network, Restart, text(32, TextRule::Topic),
        "The bridge's MQTT topics start with this.";
    Discovery = 68, "discovery", "", Network, Restart, Kind::Bool,
        "Publish Home Assistant discovery configs (off: remove them).";
    DiscoveryPrefix = 69, "discovery_prefix", "", Network, Restart, text(32, TextRule::Topic),
        "Home Assistant's discovery prefix.";
    PublishPeriod = 70, "publish_period", "s", Network, Restart, num(1, 3600, 0),
        "How often the state is published (and at once on a status change).";
    PackName = 71, "pack_name", "", Network, Restart, text(24, TextRule::Printable),
        "The pack's name: its device in Home Assistant and `tinybms monitor`'s header; empty = TinyBMS and the end of the BMS's serial.";
}

impl FieldId {
    /// Its entry in [`FIELDS`].
    pub fn field(self) -> &'static Field {
        // Every id is in the table (one entry per variant, by construction);
        // the fallback is never taken.
        FIELDS
            .iter()
            .find(|f| f.id == self)
            .unwrap_or(&FIELDS_FALLBACK)
    }

    /// The field named `name` (snake_case, as printed; ASCII case ignored).
    pub fn from_name(name: &str) -> Option<Self> {
        FIELDS
            .iter()
            .find(|f| f.name.eq_ignore_ascii_case(name))
            .map(|f| f.id)
    }

    /// The field stored under `tag`.
    pub fn from_tag(tag: u8) -> Option<Self> {
        FIELDS.iter().find(|f| f.tag == tag).map(|f| f.id)
    }

    /// snake_case name.
    pub fn name(self) -> &'static str {
        self.field().name
    }
}

const FIELDS_FALLBACK: Field = Field {
    id: FieldId::CanOutput,
    tag: 1,
    name: "can_output",
    unit: "",
    kind: Kind::Bool,
    applies: Applies::Restart,
    group: Group::Inverter,
    help: "",
};

/// The bridge's configuration record. See the module documentation; every
/// field's unit and range is in [`FIELDS`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Config {
    /// `can_output`.
    pub can_output: bool,
    /// `inverter_protocol`.
    pub protocol: Protocol,
    /// `stale_after`, s.
    pub stale_after_s: u16,
    /// `stale_policy`.
    pub stale_policy: StaleMode,
    /// `stale_hold`, s.
    pub stale_hold_s: u16,
    /// `pack_node` (0: alone).
    pub pack_node: u8,
    /// `absorption_voltage`, mV per cell (0: the BMS's register 300).
    pub absorption_mv: u16,
    /// `absorption_margin`, mV.
    pub absorption_margin_mv: u16,
    /// `float_voltage`, mV per cell (0: 15/16 of absorption).
    pub float_mv: u16,
    /// `ceiling_margin`, mV.
    pub ceiling_margin_mv: u16,
    /// `discharge_margin`, mV.
    pub discharge_margin_mv: u16,
    /// `charge_taper`, mV.
    pub charge_taper_mv: u16,
    /// `discharge_taper`, mV.
    pub discharge_taper_mv: u16,
    /// `runner_tolerance`, mV.
    pub runner_tolerance_mv: u16,
    /// `tail_current`, 0.1 A.
    pub tail_current_da: u16,
    /// `full_hold`, s.
    pub full_hold_s: u16,
    /// `rebulk_soc`, %.
    pub rebulk_soc_pct: u8,
    /// `charge_current_cap`, 0.1 A (0: none).
    pub ccl_cap_da: u16,
    /// `discharge_current_cap`, 0.1 A (0: none).
    pub dcl_cap_da: u16,
    /// `temperature_margin`, °C.
    pub temperature_margin_c: u8,
    /// `limit_hold`, s.
    pub limit_hold_s: u16,
    /// `ramp_rate`, 0.1 A/s.
    pub ramp_da_per_s: u16,
    /// `cvl_raise_interval`, s.
    pub cvl_raise_interval_s: u16,
    /// `warning_margin`, mV.
    pub warning_margin_mv: u16,
    /// `warning_current`, %.
    pub warning_current_pct: u8,
    /// `read_only`.
    pub read_only: bool,
    /// `stream_period`, ms (0: off).
    pub stream_period_ms: u32,
    /// `wifi_ssid`.
    pub wifi_ssid: String<32>,
    /// `wifi_key` (64 hex digits or empty).
    pub wifi_key: String<64>,
    /// `hostname`.
    pub hostname: String<32>,
    /// `mqtt_host`.
    pub mqtt_host: String<64>,
    /// `mqtt_port`.
    pub mqtt_port: u16,
    /// `mqtt_user`.
    pub mqtt_user: String<32>,
    /// `mqtt_password`.
    pub mqtt_password: String<64>,
    /// `topic_prefix`.
    pub topic_prefix: String<32>,
    /// `discovery`.
    pub discovery: bool,
    /// `discovery_prefix`.
    pub discovery_prefix: String<32>,
    /// `publish_period`, s.
    pub publish_period_s: u16,
    /// `pack_name` (empty: none).
    pub pack_name: String<24>,
}

/// `s` as a heapless string (a default's text always fits its field).
fn fixed_text<const N: usize>(s: &str) -> String<N> {
    let mut out = String::new();
    let _ = out.push_str(s);
    out
}

impl Default for Config {
    /// An unconfigured bridge: Victron protocol, CAN on, stop sending on stale
    /// data, charge control's documented defaults
    /// ([`ChargeConfig::default`]), a read-write host link streaming every
    /// second, no network.
    fn default() -> Self {
        let c = ChargeConfig::default();
        let i = InverterConfig::default();
        Self {
            can_output: true,
            protocol: Protocol::Victron,
            stale_after_s: (i.freshness.limit_us / SECOND) as u16,
            stale_policy: StaleMode::Hold,
            stale_hold_s: (i.stale_hold_us / SECOND) as u16,
            pack_node: i.node,
            absorption_mv: c.absorption_mv.unwrap_or(0),
            absorption_margin_mv: c.absorption_margin_mv,
            float_mv: c.float_mv.unwrap_or(0),
            ceiling_margin_mv: c.ov_margin_mv,
            discharge_margin_mv: c.uv_margin_mv,
            charge_taper_mv: c.ccl_taper_mv,
            discharge_taper_mv: c.dcl_taper_mv,
            runner_tolerance_mv: c.runner_tolerance_mv,
            tail_current_da: (c.tail_current_a * 10.0) as u16,
            full_hold_s: (c.full_hold_us / SECOND) as u16,
            rebulk_soc_pct: c.rebulk_soc_pct as u8,
            ccl_cap_da: c.ccl_cap_da.unwrap_or(0),
            dcl_cap_da: c.dcl_cap_da.unwrap_or(0),
            temperature_margin_c: c.temp_margin_c as u8,
            limit_hold_s: (c.hold_us / SECOND) as u16,
            ramp_da_per_s: c.ramp_da_per_s,
            cvl_raise_interval_s: (c.cvl_raise_interval_us / SECOND) as u16,
            warning_margin_mv: c.warn_margin_mv,
            warning_current_pct: c.warn_current_pct,
            read_only: false,
            stream_period_ms: DEFAULT_STREAM_PERIOD_MS,
            wifi_ssid: String::new(),
            wifi_key: String::new(),
            hostname: String::new(),
            mqtt_host: String::new(),
            mqtt_port: 1883,
            mqtt_user: String::new(),
            mqtt_password: String::new(),
            topic_prefix: fixed_text("tinybms"),
            discovery: true,
            discovery_prefix: fixed_text("homeassistant"),
            publish_period_s: 5,
            pack_name: String::new(),
        }
    }
}

/// Why a record (or a change to it) breaks a rule between fields.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct RuleError {
    /// The field the rule is about (the one a user would change).
    pub field: FieldId,
    /// The rule, in a sentence.
    pub detail: &'static str,
    /// The values the rule allows the field, raw (in the field's unit), when
    /// they come from the BMS's own settings: what a refusal says the field
    /// takes, instead of the field's whole range.
    pub allowed: Option<(i32, i32)>,
}

impl RuleError {
    const fn between_fields(field: FieldId, detail: &'static str) -> Self {
        Self {
            field,
            detail,
            allowed: None,
        }
    }
}

/// What charge control and its checks need of the BMS's settings (Rev D §3.4),
/// for [`Config::validate_with_bms`].
pub use crate::inverter::control::PackSettings;

fn opt(v: u16) -> Option<u16> {
    (v != 0).then_some(v)
}

impl Config {
    /// This field's value.
    pub fn get(&self, id: FieldId) -> Value<'_> {
        use FieldId::*;
        let n = |v: u32| Value::Number(v as i32);
        match id {
            CanOutput => Value::Bool(self.can_output),
            InverterProtocol => Value::Choice(match self.protocol {
                Protocol::Victron => 0,
                Protocol::SmaSunnyIsland => 1,
            }),
            StaleAfter => n(self.stale_after_s.into()),
            StalePolicyField => Value::Choice(match self.stale_policy {
                StaleMode::Stop => 0,
                StaleMode::Hold => 1,
            }),
            StaleHold => n(self.stale_hold_s.into()),
            PackNode => n(self.pack_node.into()),
            AbsorptionVoltage => n(self.absorption_mv.into()),
            AbsorptionMargin => n(self.absorption_margin_mv.into()),
            FloatVoltage => n(self.float_mv.into()),
            CeilingMargin => n(self.ceiling_margin_mv.into()),
            DischargeMargin => n(self.discharge_margin_mv.into()),
            ChargeTaper => n(self.charge_taper_mv.into()),
            DischargeTaper => n(self.discharge_taper_mv.into()),
            RunnerTolerance => n(self.runner_tolerance_mv.into()),
            TailCurrent => n(self.tail_current_da.into()),
            FullHold => n(self.full_hold_s.into()),
            RebulkSoc => n(self.rebulk_soc_pct.into()),
            ChargeCurrentCap => n(self.ccl_cap_da.into()),
            DischargeCurrentCap => n(self.dcl_cap_da.into()),
            TemperatureMargin => n(self.temperature_margin_c.into()),
            LimitHold => n(self.limit_hold_s.into()),
            RampRate => n(self.ramp_da_per_s.into()),
            CvlRaiseInterval => n(self.cvl_raise_interval_s.into()),
            WarningMargin => n(self.warning_margin_mv.into()),
            WarningCurrent => n(self.warning_current_pct.into()),
            ReadOnly => Value::Bool(self.read_only),
            StreamPeriod => n(self.stream_period_ms),
            WifiSsid => Value::Text(&self.wifi_ssid),
            WifiKey => Value::Text(&self.wifi_key),
            Hostname => Value::Text(&self.hostname),
            MqttHost => Value::Text(&self.mqtt_host),
            MqttPort => n(self.mqtt_port.into()),
            MqttUser => Value::Text(&self.mqtt_user),
            MqttPassword => Value::Text(&self.mqtt_password),
            TopicPrefix => Value::Text(&self.topic_prefix),
            Discovery => Value::Bool(self.discovery),
            DiscoveryPrefix => Value::Text(&self.discovery_prefix),
            PublishPeriod => n(self.publish_period_s.into()),
            PackName => Value::Text(&self.pack_name),
        }
    }

    /// Sets this field, after [`value::check`]: a value outside the field's
    /// kind or range is refused and nothing changes.
    pub fn set(&mut self, id: FieldId, v: Value<'_>) -> Result<(), FieldError> {
        value::check(id.field(), &v)?;
        use FieldId::*;
        let text = |s: &str, out: &mut dyn FnMut(&str) -> bool| {
            if out(s) {
                Ok(())
            } else {
                Err(FieldError::TOO_LONG)
            }
        };
        // `check` has bounded every number to its field's range, which fits
        // the field's type: the casts below cannot truncate.
        match (id, v) {
            (CanOutput, Value::Bool(b)) => self.can_output = b,
            (ReadOnly, Value::Bool(b)) => self.read_only = b,
            (Discovery, Value::Bool(b)) => self.discovery = b,
            (InverterProtocol, Value::Choice(c)) => {
                self.protocol = if c == 0 {
                    Protocol::Victron
                } else {
                    Protocol::SmaSunnyIsland
                }
            }
            (StalePolicyField, Value::Choice(c)) => {
                self.stale_policy = if c == 0 {
                    StaleMode::Stop
                } else {
                    StaleMode::Hold
                }
            }
            (StaleAfter, Value::Number(n)) => self.stale_after_s = n as u16,
            (StaleHold, Value::Number(n)) => self.stale_hold_s = n as u16,
            (PackNode, Value::Number(n)) => self.pack_node = n as u8,
            (AbsorptionVoltage, Value::Number(n)) => self.absorption_mv = n as u16,
            (AbsorptionMargin, Value::Number(n)) => self.absorption_margin_mv = n as u16,
            (FloatVoltage, Value::Number(n)) => self.float_mv = n as u16,
            (CeilingMargin, Value::Number(n)) => self.ceiling_margin_mv = n as u16,
            (DischargeMargin, Value::Number(n)) => self.discharge_margin_mv = n as u16,
            (ChargeTaper, Value::Number(n)) => self.charge_taper_mv = n as u16,
            (DischargeTaper, Value::Number(n)) => self.discharge_taper_mv = n as u16,
            (RunnerTolerance, Value::Number(n)) => self.runner_tolerance_mv = n as u16,
            (TailCurrent, Value::Number(n)) => self.tail_current_da = n as u16,
            (FullHold, Value::Number(n)) => self.full_hold_s = n as u16,
            (RebulkSoc, Value::Number(n)) => self.rebulk_soc_pct = n as u8,
            (ChargeCurrentCap, Value::Number(n)) => self.ccl_cap_da = n as u16,
            (DischargeCurrentCap, Value::Number(n)) => self.dcl_cap_da = n as u16,
            (TemperatureMargin, Value::Number(n)) => self.temperature_margin_c = n as u8,
            (LimitHold, Value::Number(n)) => self.limit_hold_s = n as u16,
            (RampRate, Value::Number(n)) => self.ramp_da_per_s = n as u16,
            (CvlRaiseInterval, Value::Number(n)) => self.cvl_raise_interval_s = n as u16,
            (WarningMargin, Value::Number(n)) => self.warning_margin_mv = n as u16,
            (WarningCurrent, Value::Number(n)) => self.warning_current_pct = n as u8,
            (StreamPeriod, Value::Number(n)) => self.stream_period_ms = n as u32,
            (MqttPort, Value::Number(n)) => self.mqtt_port = n as u16,
            (PublishPeriod, Value::Number(n)) => self.publish_period_s = n as u16,
            (WifiSsid, Value::Text(s)) => text(s, &mut |s| set_text(&mut self.wifi_ssid, s))?,
            (WifiKey, Value::Text(s)) => text(s, &mut |s| set_text(&mut self.wifi_key, s))?,
            (Hostname, Value::Text(s)) => text(s, &mut |s| set_text(&mut self.hostname, s))?,
            (MqttHost, Value::Text(s)) => text(s, &mut |s| set_text(&mut self.mqtt_host, s))?,
            (MqttUser, Value::Text(s)) => text(s, &mut |s| set_text(&mut self.mqtt_user, s))?,
            (MqttPassword, Value::Text(s)) => {
                text(s, &mut |s| set_text(&mut self.mqtt_password, s))?
            }
            (TopicPrefix, Value::Text(s)) => text(s, &mut |s| set_text(&mut self.topic_prefix, s))?,
            (DiscoveryPrefix, Value::Text(s)) => {
                text(s, &mut |s| set_text(&mut self.discovery_prefix, s))?
            }
            (PackName, Value::Text(s)) => text(s, &mut |s| set_text(&mut self.pack_name, s))?,
            _ => return Err(FieldError::WRONG_KIND),
        }
        Ok(())
    }

    /// The rules between fields. A record that breaks one is never stored nor
    /// run with.
    pub fn validate(&self) -> Result<(), RuleError> {
        if self.float_mv != 0 && self.absorption_mv != 0 && self.float_mv > self.absorption_mv {
            return Err(RuleError::between_fields(
                FieldId::FloatVoltage,
                "the float voltage is above the absorption voltage",
            ));
        }
        if !self.wifi_key.is_empty() && self.wifi_ssid.is_empty() {
            return Err(RuleError::between_fields(
                FieldId::WifiKey,
                "a Wi-Fi key is set but no wifi_ssid",
            ));
        }
        if !self.mqtt_password.is_empty() && self.mqtt_user.is_empty() {
            return Err(RuleError::between_fields(
                FieldId::MqttPassword,
                "an MQTT password is set but no mqtt_user",
            ));
        }
        if self.discovery && self.topic_prefix == self.discovery_prefix {
            return Err(RuleError::between_fields(
                FieldId::TopicPrefix,
                "the topic prefix is the discovery prefix",
            ));
        }
        Ok(())
    }

    /// [`Config::validate`], then the rules against the BMS's own settings: no
    /// cap above the cutoff it caps (a cap that can never act is a mistake),
    /// per-cell targets between the under-voltage cutoff and the over-voltage
    /// cutoff less the margin.
    pub fn validate_with_bms(&self, bms: &PackSettings) -> Result<(), RuleError> {
        self.validate()?;
        // The caps in 0.1 A: from 0.1 A to the cutoff they cap.
        let cap = |field: FieldId, set: u16, cutoff_a: u16, detail: &'static str| {
            let cutoff_da = i32::from(cutoff_a) * 10;
            (set != 0 && i32::from(set) > cutoff_da).then_some(RuleError {
                field,
                detail,
                allowed: Some((1, cutoff_da)),
            })
        };
        if let Some(e) = cap(
            FieldId::ChargeCurrentCap,
            self.ccl_cap_da,
            bms.charge_cutoff_a,
            "above the BMS's charge over-current cutoff, which it could never lower",
        ) {
            return Err(e);
        }
        if let Some(e) = cap(
            FieldId::DischargeCurrentCap,
            self.dcl_cap_da,
            bms.discharge_cutoff_a,
            "above the BMS's discharge over-current cutoff, which it could never lower",
        ) {
            return Err(e);
        }
        let top = bms.ov_cutoff_mv.saturating_sub(self.absorption_margin_mv);
        let allowed = Some((i32::from(bms.uv_cutoff_mv) + 1, i32::from(top)));
        for (field, v) in [
            (FieldId::AbsorptionVoltage, self.absorption_mv),
            (FieldId::FloatVoltage, self.float_mv),
        ] {
            if v != 0 && v > top {
                return Err(RuleError {
                    field,
                    detail: "above the BMS's over-voltage cutoff less absorption_margin",
                    allowed,
                });
            }
            if v != 0 && v <= bms.uv_cutoff_mv {
                return Err(RuleError {
                    field,
                    detail: "at or below the BMS's under-voltage cutoff",
                    allowed,
                });
            }
        }
        Ok(())
    }

    /// Charge control's settings.
    pub fn charge(&self) -> ChargeConfig {
        ChargeConfig {
            absorption_mv: opt(self.absorption_mv),
            absorption_margin_mv: self.absorption_margin_mv,
            float_mv: opt(self.float_mv),
            ov_margin_mv: self.ceiling_margin_mv,
            uv_margin_mv: self.discharge_margin_mv,
            ccl_taper_mv: self.charge_taper_mv,
            dcl_taper_mv: self.discharge_taper_mv,
            runner_tolerance_mv: self.runner_tolerance_mv,
            tail_current_a: f32::from(self.tail_current_da) / 10.0,
            full_hold_us: Instant::from(self.full_hold_s) * SECOND,
            rebulk_soc_pct: f32::from(self.rebulk_soc_pct),
            ccl_cap_da: opt(self.ccl_cap_da),
            dcl_cap_da: opt(self.dcl_cap_da),
            temp_margin_c: i16::from(self.temperature_margin_c),
            hold_us: Instant::from(self.limit_hold_s) * SECOND,
            ramp_da_per_s: self.ramp_da_per_s,
            cvl_raise_interval_us: Instant::from(self.cvl_raise_interval_s) * SECOND,
            warn_margin_mv: self.warning_margin_mv,
            warn_current_pct: self.warning_current_pct,
        }
    }

    /// The freshness rule with the record's `stale_after_s`: the one limit
    /// the inverter output, the packs, MQTT and the host link go by.
    pub fn freshness(&self) -> Freshness {
        Freshness::new(Instant::from(self.stale_after_s) * SECOND)
    }

    /// The inverter output's settings (periods and timeouts keep their
    /// documented defaults).
    pub fn inverter(&self) -> InverterConfig {
        InverterConfig {
            enabled: self.can_output,
            protocol: self.protocol,
            charge: self.charge(),
            freshness: self.freshness(),
            stale_policy: self.stale_policy,
            stale_hold_us: Instant::from(self.stale_hold_s) * SECOND,
            node: self.pack_node,
            ..InverterConfig::default()
        }
    }

    /// The host link's settings, with this firmware's version and the chip's name.
    pub fn host_link(&self, who: &crate::identity::Identity) -> HostLinkConfig {
        HostLinkConfig {
            read_only: self.read_only,
            stream_period_ms: self.stream_period_ms,
            firmware: crate::identity::FIRMWARE,
            chip: who.chip,
            board: who.board,
            features: who.features,
            freshness: self.freshness(),
        }
    }

    /// Copies into `self` the fields that apply at once ([`Applies::Now`]) from
    /// `newer`: what a running bridge takes over from a changed record; the
    /// others wait for the restart.
    pub fn take_immediate(&mut self, newer: &Config) {
        for f in FIELDS.iter().filter(|f| f.applies == Applies::Now) {
            // Both records are valid: a value of one is valid for the other.
            let _ = self.set(f.id, newer.get(f.id));
        }
    }
}

fn set_text<const N: usize>(slot: &mut String<N>, s: &str) -> bool {
    let mut t = String::new();
    if t.push_str(s).is_err() {
        return false;
    }
    *slot = t;
    true
}
