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
    /// An Ed25519 public key: 64 hex digits, or empty (none).
    Key,
    /// Printable ASCII only (what goes out in a CAN frame byte for byte:
    /// 0x35E's name).
    Ascii,
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

/// The record's one table: each row is a field — its name in code, its tag
/// in flash and the layout version that added it, its name for an owner,
/// unit, group, when a change applies, kind and range — then the record's
/// member that holds it, with its type and default, then its sentence for
/// an owner. From the rows come [`FieldId`], [`FIELDS`], [`Config`], its
/// [`Default`], [`Config::get`], [`Config::set`] and
/// [`introduced`]: adding a field is one row (and its use).
macro_rules! fields {
    (
        defaults($c:ident = $charge:expr, $i:ident = $inverter:expr);
        $( $id:ident = $tag:literal since $since:literal, $name:literal, $unit:literal,
            $group:ident, $applies:ident, $kind:expr,
            $member:ident: $ty:ty = $default:expr,
            $help:literal; )*
    ) => {
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

        /// The bridge's configuration record. See the module documentation;
        /// every field's unit and range is in [`FIELDS`].
        #[derive(Debug, Clone, PartialEq, Eq)]
        pub struct Config {
            $( #[doc = concat!("`", $name, "`: ", $help)] pub $member: $ty, )*
        }

        impl Default for Config {
            /// An unconfigured bridge: Victron protocol, CAN on, a hold on
            /// stale data, charge control's documented defaults
            /// ([`ChargeConfig::default`]), a read-write host link streaming
            /// every second, no network.
            fn default() -> Self {
                let $c = $charge;
                let $i = $inverter;
                Self { $( $member: $default, )* }
            }
        }

        impl Config {
            /// This field's value.
            pub fn get(&self, id: FieldId) -> Value<'_> {
                match id { $( FieldId::$id => Member::get(&self.$member), )* }
            }

            /// Sets this field, after [`value::check`]: a value outside the
            /// field's kind or range is refused and nothing changes.
            pub fn set(&mut self, id: FieldId, v: Value<'_>) -> Result<(), FieldError> {
                value::check(id.field(), &v)?;
                match id { $( FieldId::$id => Member::put(&mut self.$member, v), )* }
            }
        }

        /// Version of the record's layout in flash ([`codec`]): the newest
        /// `since` of the table, so a field added with the next version
        /// makes it (one row, nothing else). A record of an older version
        /// is read with the fields added since at their defaults
        /// ([`codec::introduced`]); one of a newer version is not read: the
        /// bridge runs with the defaults and says so.
        pub const VERSION: u8 = {
            let mut newest = 1;
            let mut rest: &[u8] = &[$($since),*];
            while let [first, tail @ ..] = rest {
                if *first > newest {
                    newest = *first;
                }
                rest = tail;
            }
            newest
        };

        /// The layout version that added the field stored under `tag`
        /// (version 2: `pack_node`; version 3: `pack_name`; version 4:
        /// `inverter_name`; version 5: `update_key`; version 6:
        /// `stop_by_soc` on by default, `current_margin`; 1 for a tag no
        /// field has). [`codec`] reads an older record by it.
        pub const fn introduced(tag: u8) -> u8 {
            match tag {
                $( $tag => $since, )*
                _ => 1,
            }
        }
    };
}

/// How a member of [`Config`] holds a field's [`Value`]. [`value::check`]
/// has bounded every number to its field's range, which fits the member's
/// type: the casts cannot truncate.
trait Member {
    fn get(&self) -> Value<'_>;
    fn put(&mut self, v: Value<'_>) -> Result<(), FieldError>;
}

impl Member for bool {
    fn get(&self) -> Value<'_> {
        Value::Bool(*self)
    }
    fn put(&mut self, v: Value<'_>) -> Result<(), FieldError> {
        match v {
            Value::Bool(b) => *self = b,
            _ => return Err(FieldError::WRONG_KIND),
        }
        Ok(())
    }
}

macro_rules! number_member {
    ($($t:ty),*) => { $(
        impl Member for $t {
            fn get(&self) -> Value<'_> {
                Value::Number(u32::from(*self) as i32)
            }
            fn put(&mut self, v: Value<'_>) -> Result<(), FieldError> {
                match v {
                    Value::Number(n) => *self = n as $t,
                    _ => return Err(FieldError::WRONG_KIND),
                }
                Ok(())
            }
        }
    )* };
}
number_member!(u8, u16, u32);

impl<const N: usize> Member for String<N> {
    fn get(&self) -> Value<'_> {
        Value::Text(self)
    }
    fn put(&mut self, v: Value<'_>) -> Result<(), FieldError> {
        let Value::Text(s) = v else {
            return Err(FieldError::WRONG_KIND);
        };
        if set_text(self, s) {
            Ok(())
        } else {
            Err(FieldError::TOO_LONG)
        }
    }
}

/// A choice of two values held as the value: the first is choice 0.
macro_rules! choice_member {
    ($t:ty: $zero:expr, $one:expr) => {
        impl Member for $t {
            fn get(&self) -> Value<'_> {
                Value::Choice(u8::from(*self != $zero))
            }
            fn put(&mut self, v: Value<'_>) -> Result<(), FieldError> {
                match v {
                    Value::Choice(c) => *self = if c == 0 { $zero } else { $one },
                    _ => return Err(FieldError::WRONG_KIND),
                }
                Ok(())
            }
        }
    };
}
choice_member!(StaleMode: StaleMode::Stop, StaleMode::Hold);

/// A protocol is held as its place in [`PROTOCOLS`] (the order of
/// [`crate::inverter::dialect::DIALECTS`]: the record stores the index).
impl Member for Protocol {
    fn get(&self) -> Value<'_> {
        Value::Choice(self.index())
    }
    fn put(&mut self, v: Value<'_>) -> Result<(), FieldError> {
        match v {
            Value::Choice(c) => {
                *self = Protocol::from_index(c).ok_or(FieldError::WRONG_KIND)?;
                Ok(())
            }
            _ => Err(FieldError::WRONG_KIND),
        }
    }
}

/// Choices of `inverter_protocol`: the dialects' keys, in the order of
/// [`crate::inverter::dialect::DIALECTS`] (the record stores the index).
pub const PROTOCOLS: &[&str] = &crate::inverter::dialect::KEYS;

/// Tags a field of an older layout was stored under and no field has now:
/// (tag, the version that added it, the version that retired it, kind). A
/// record of a version that had it may carry it; [`codec`] reads its value's
/// length by the kind and drops it, so the field takes its new default.
///
/// Tag 8, `stop_by_soc` of versions 4-5, was off by default: a record
/// saved with the old default cannot be told from an owner's choice, so it
/// is read as the new field (tag 9), on by default since version 6 — the
/// safe side for the inverters it serves.
pub const RETIRED: &[(u8, u8, u8, Kind)] = &[(8, 4, 6, Kind::Bool)];
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
    defaults(c = ChargeConfig::default(), i = InverterConfig::default());
    CanOutput = 1 since 1, "can_output", "", Inverter, Restart, Kind::Bool,
        can_output: bool = true,
        "Send the battery's limits and state to the inverter over CAN.";
    InverterProtocol = 2 since 1, "inverter_protocol", "", Inverter, Restart, Kind::Choice(PROTOCOLS),
        protocol: Protocol = Protocol::Victron,
        "The inverter's CAN protocol: victron (a GX, \"CAN-bus BMS 500 kbit/s\"), sma (Sunny Island), or a 48 V hybrid inverter's: pylon (Pylontech LV V1.2: Deye, Sunsynk, Sofar, Growatt SPF, EG4 \"Lithium 2\", GoodWe, Solis \"Pylon LV\", MidNite…), solark (Sol-Ark LV V1.3), luxpower (Luxpower V04.2, EG4 \"Lithium 6\"), growatt (Growatt LV V1.04, answers the inverter's queries only).";
    StaleAfter = 3 since 1, "stale_after", "s", Inverter, Now, num(1, 60, 0),
        stale_after_s: u16 = (i.freshness.limit_us / SECOND) as u16,
        "BMS data older than this is stale: the stale policy applies.";
    StalePolicyField = 4 since 1, "stale_policy", "", Inverter, Now, Kind::Choice(STALE_MODES),
        stale_policy: StaleMode = StaleMode::Hold,
        "On stale data: hold (no charge; the discharge goes on for at most stale_hold within what the last data proves the pack holds above its discharge stop, its limit falling to 0: an island inverter keeps the house on through a short loss) or stop (both stop at once). Then the stop is said with every signal: once to an inverter that stops on silence (a GX), every second to the others until the data is back.";
    StaleHold = 5 since 1, "stale_hold", "s", Inverter, Now, num(10, 3600, 0),
        stale_hold_s: u16 = (i.stale_hold_us / SECOND) as u16,
        "With stale_policy hold: how long the inverter may keep discharging on stale data at most (less when the last data proves less charge above the discharge stop).";
    InverterName = 7 since 4, "inverter_name", "", Inverter, Now, text(8, TextRule::Ascii),
        inverter_name: String<8> = fixed_text("PYLON"),
        "What 0x35E says in the protocols pylon, solark and luxpower (at most 8 ASCII characters): PYLON for most inverters (Deye, Sunsynk, Sofar, Growatt SPF, EG4, MidNite), GOODWE for a GoodWe, DEYE as Deye's copy of the spec prints it; inverters key their behaviour on this name.";
    StopBySoc = 9 since 6, "stop_by_soc", "", Inverter, Now, Kind::Bool,
        stop_by_soc: bool = i.stop_by_soc,
        "In the protocols whose inverters are known to ignore a current limit of 0 A (pylon, solark, luxpower, growatt: Deye, Solis…): report SOC 100 % while charging must stop and 0 % while discharging must (the real SOC stays in the monitor and Home Assistant). On by default; an inverter seen ignoring a stop is told by SOC whatever this says.";
    PackNode = 6 since 2, "pack_node", "", Inverter, Restart, num_or(1, 8, 0, "alone"),
        pack_node: u8 = i.node,
        "Packs in parallel, one bridge each, on one CAN bus: this bridge's number (1 = the primary, which speaks to the inverter); alone = this pack is the whole battery.";
    AbsorptionVoltage = 10 since 1, "absorption_voltage", "mV", Charge, Now, num_or(1000, 4500, 0, "bms"),
        absorption_voltage_mv: u16 = c.absorption_voltage_mv.unwrap_or(0),
        "Charge target per cell; bms = the BMS's own fully charged voltage setting.";
    AbsorptionMargin = 11 since 1, "absorption_margin", "mV", Charge, Now, num(20, 500, 0),
        absorption_margin_mv: u16 = c.absorption_margin_mv,
        "The charge target stays at least this far below the BMS's over-voltage cutoff.";
    FloatVoltage = 12 since 1, "float_voltage", "mV", Charge, Now, num_or(1000, 4500, 0, "auto"),
        float_voltage_mv: u16 = c.float_voltage_mv.unwrap_or(0),
        "Float target per cell after a full charge; auto = 15/16 of the charge target.";
    CeilingMargin = 13 since 1, "ceiling_margin", "mV", Charge, Now, num(20, 500, 0),
        ceiling_margin_mv: u16 = c.ceiling_margin_mv,
        "No cell is charged closer than this to the over-voltage cutoff (the charge limit is 0 there).";
    DischargeMargin = 14 since 1, "discharge_margin", "mV", Charge, Now, num(0, 1000, 0),
        discharge_margin_mv: u16 = c.discharge_margin_mv,
        "Discharge stops this far above the BMS's under-voltage cutoff.";
    ChargeTaper = 15 since 1, "charge_taper", "mV", Charge, Now, num(10, 1000, 0),
        charge_taper_mv: u16 = c.charge_taper_mv,
        "The charge limit falls from full to 0 over this window below the ceiling.";
    DischargeTaper = 16 since 1, "discharge_taper", "mV", Charge, Now, num(10, 1000, 0),
        discharge_taper_mv: u16 = c.discharge_taper_mv,
        "The discharge limit falls from full to 0 over this window above the discharge stop.";
    RunnerTolerance = 17 since 1, "runner_tolerance", "mV", Charge, Now, num(0, 200, 0),
        runner_tolerance_mv: u16 = c.runner_tolerance_mv,
        "How far the highest cell may run ahead of the average before the charge voltage is lowered for it.";
    TailCurrent = 18 since 1, "tail_current", "A", Charge, Now, num(1, 1000, 1),
        tail_current_da: u16 = (c.tail_current_a * 10.0) as u16,
        "Charge current below which a full pack counts as tapered (for the switch to float).";
    FullHold = 19 since 1, "full_hold", "s", Charge, Now, num(10, 3600, 0),
        full_hold_s: u16 = (c.full_hold_us / SECOND) as u16,
        "How long the pack stays at the target, tapered, before float.";
    RebulkSoc = 20 since 1, "rebulk_soc", "%", Charge, Now, num(50, 99, 0),
        rebulk_soc_pct: u8 = c.rebulk_soc_pct as u8,
        "Below this state of charge float ends and charging starts again.";
    BalanceHold = 30 since 7, "balance_hold", "min", Charge, Now, num(0, 600, 0),
        balance_hold_min: u16 = (c.balance_hold_us / (60 * SECOND)) as u16,
        "At the end of a charge, absorption is held while the BMS balances and the cells' spread is above its allowed disbalance (308): at most this long for each day since the last full charge (up to full_charge_days times); 0 = never.";
    FullChargeDays = 31 since 7, "full_charge_days", "days", Charge, Now, num(0, 90, 0),
        full_charge_days: u16 = c.full_charge_days,
        "A full charge (absorption and its balance hold) at least this often: float ends for it and the SOC ceiling waits; 0 = off. Due at every start.";
    FloatStep = 32 since 7, "float_step", "mV/min", Charge, Now, num(0, 100, 0),
        float_step_mv_per_min: u16 = c.float_step_mv_per_min,
        "The charge voltage steps down into float at most this fast per cell, and never below the pack's own voltage while it is not charging (no discharge to the grid); 0 = at once.";
    SocCeiling = 33 since 7, "soc_ceiling", "%", Charge, Now, num(50, 100, 0),
        soc_ceiling_pct: u8 = c.soc_ceiling_pct,
        "Charging pauses at this state of charge (resumes 3 % below) for daily cycling, except for the periodic full charge; 100 = no ceiling.";
    ChargeCurrentCap = 21 since 1, "charge_current_cap", "A", Charge, Now, num_or(1, 7500, 1, "none"),
        charge_current_cap_da: u16 = c.charge_current_cap_da.unwrap_or(0),
        "Most charge current ever asked for; none = the BMS's charge over-current cutoff (a cap above it is refused).";
    DischargeCurrentCap = 22 since 1, "discharge_current_cap", "A", Charge, Now, num_or(1, 7500, 1, "none"),
        discharge_current_cap_da: u16 = c.discharge_current_cap_da.unwrap_or(0),
        "Most discharge current ever allowed; none = the BMS's discharge over-current cutoff (a cap above it is refused).";
    TemperatureMargin = 23 since 1, "temperature_margin", "°C", Charge, Now, num(1, 20, 0),
        temperature_margin_c: u8 = c.temperature_margin_c as u8,
        "Current limits are derated over this window inside each temperature cutoff.";
    LimitHold = 24 since 1, "limit_hold", "s", Charge, Now, num(0, 600, 0),
        limit_hold_s: u16 = (c.limit_hold_us / SECOND) as u16,
        "After a limit was cut to 0 for a cause in the BMS's data (a fault, a cell at its cutoff, a temperature), how long before it may rise again (a lost link is no such cause).";
    RampRate = 25 since 1, "ramp_rate", "A/s", Charge, Now, num(1, 1000, 1),
        ramp_rate_da_per_s: u16 = c.ramp_rate_da_per_s,
        "How fast a current limit may rise.";
    CvlRaiseInterval = 26 since 1, "cvl_raise_interval", "s", Charge, Now, num(5, 600, 0),
        cvl_raise_interval_s: u16 = (c.cvl_raise_interval_us / SECOND) as u16,
        "The charge voltage is raised at most this often (lowered at once).";
    WarningMargin = 27 since 1, "warning_margin", "mV", Charge, Now, num(0, 500, 0),
        warning_margin_mv: u16 = c.warn_margin_mv,
        "Voltage warnings start this far inside a cutoff.";
    WarningCurrent = 28 since 1, "warning_current", "%", Charge, Now, num(50, 100, 0),
        warning_current_pct: u8 = c.warn_current_pct,
        "Current warnings start at this share of a current cutoff.";
    CurrentMargin = 29 since 6, "current_margin", "%", Charge, Now, num(0, 50, 0),
        current_margin_pct: u8 = c.current_margin_pct,
        "The largest charge and discharge current limits stay this share below the BMS's over-current cutoffs (318, 317), so an inverter that overshoots a limit by as much never trips the BMS (real ones overshoot by up to 20 %).";
    ReadOnly = 40 since 1, "read_only", "", Host, Now, Kind::Bool,
        read_only: bool = false,
        "Refuse every write from the computer: BMS settings, resets, clears and this configuration.";
    StreamPeriod = 41 since 1, "stream_period", "ms", Host, Now, num_or(100, 60_000, 0, "off"),
        stream_period_ms: u32 = DEFAULT_STREAM_PERIOD_MS,
        "How often telemetry is pushed to the computer.";
    UpdateKey = 42 since 5, "update_key", "", Host, Now, text(64, TextRule::Key),
        update_key: String<64> = String::new(),
        "The owner's public update key (64 hex digits: the .pub file of `tinybms keygen`; a private key, 128 digits, is refused and never stored): updates signed with it are taken besides the release key's; empty = none. Set over USB only.";
    WifiSsid = 60 since 1, "wifi_ssid", "", Network, Restart, text(32, TextRule::Printable),
        wifi_ssid: String<32> = String::new(),
        "The Wi-Fi network's name; empty = no Wi-Fi.";
    WifiKey = 61 since 1, "wifi_key", "", Network, Restart, Kind::Secret { max: 64, hex64: true },
        wifi_key: String<64> = String::new(),
        "The WPA2 pre-shared key, 64 hex digits (`tinybms wifi` derives it from the passphrase).";
    Hostname = 62 since 1, "hostname", "", Network, Restart, text(32, TextRule::Host),
        hostname: String<32> = String::new(),
        "The bridge's name on the network; empty = tinybms-XXXXXX from its MAC address.";
    MqttHost = 63 since 1, "mqtt_host", "", Network, Restart, text(64, TextRule::Host),
        mqtt_host: String<64> = String::new(),
        "The MQTT broker (host name or IPv4 address); empty = no MQTT.";
    MqttPort = 64 since 1, "mqtt_port", "", Network, Restart, num(1, 65_535, 0),
        mqtt_port: u16 = 1883,
        "The broker's TCP port.";
    MqttUser = 65 since 1, "mqtt_user", "", Network, Restart, text(32, TextRule::Printable),
        mqtt_user: String<32> = String::new(),
        "User name at the broker; empty = none.";
    MqttPassword = 66 since 1, "mqtt_password", "", Network, Restart, Kind::Secret { max: 64, hex64: false },
        mqtt_password: String<64> = String::new(),
        "Password at the broker.";
    TopicPrefix = 67 since 1, "topic_prefix", "", Network, Restart, text(32, TextRule::Topic),
        topic_prefix: String<32> = fixed_text("tinybms"),
        "The bridge's MQTT topics start with this.";
    Discovery = 68 since 1, "discovery", "", Network, Restart, Kind::Bool,
        discovery: bool = true,
        "Publish Home Assistant discovery configs (off: remove them).";
    DiscoveryPrefix = 69 since 1, "discovery_prefix", "", Network, Restart, text(32, TextRule::Topic),
        discovery_prefix: String<32> = fixed_text("homeassistant"),
        "Home Assistant's discovery prefix.";
    PublishPeriod = 70 since 1, "publish_period", "s", Network, Restart, num(1, 3600, 0),
        publish_period_s: u16 = 5,
        "How often the state is published (and at once on a status change).";
    PackName = 71 since 3, "pack_name", "", Network, Restart, text(24, TextRule::Printable),
        pack_name: String<24> = String::new(),
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

/// `s` as a heapless string (a default's text always fits its field).
fn fixed_text<const N: usize>(s: &str) -> String<N> {
    let mut out = String::new();
    let _ = out.push_str(s);
    out
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
    /// The rules between fields. A record that breaks one is never stored nor
    /// run with.
    pub fn validate(&self) -> Result<(), RuleError> {
        if self.float_voltage_mv != 0
            && self.absorption_voltage_mv != 0
            && self.float_voltage_mv > self.absorption_voltage_mv
        {
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
            self.charge_current_cap_da,
            bms.charge_cutoff_a,
            "above the BMS's charge over-current cutoff, which it could never lower",
        ) {
            return Err(e);
        }
        if let Some(e) = cap(
            FieldId::DischargeCurrentCap,
            self.discharge_current_cap_da,
            bms.discharge_cutoff_a,
            "above the BMS's discharge over-current cutoff, which it could never lower",
        ) {
            return Err(e);
        }
        let top = bms.ov_cutoff_mv.saturating_sub(self.absorption_margin_mv);
        let allowed = Some((i32::from(bms.uv_cutoff_mv) + 1, i32::from(top)));
        for (field, v) in [
            (FieldId::AbsorptionVoltage, self.absorption_voltage_mv),
            (FieldId::FloatVoltage, self.float_voltage_mv),
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
            absorption_voltage_mv: opt(self.absorption_voltage_mv),
            absorption_margin_mv: self.absorption_margin_mv,
            float_voltage_mv: opt(self.float_voltage_mv),
            ceiling_margin_mv: self.ceiling_margin_mv,
            discharge_margin_mv: self.discharge_margin_mv,
            charge_taper_mv: self.charge_taper_mv,
            discharge_taper_mv: self.discharge_taper_mv,
            runner_tolerance_mv: self.runner_tolerance_mv,
            tail_current_a: f32::from(self.tail_current_da) / 10.0,
            full_hold_us: Instant::from(self.full_hold_s) * SECOND,
            rebulk_soc_pct: f32::from(self.rebulk_soc_pct),
            balance_hold_us: Instant::from(self.balance_hold_min) * 60 * SECOND,
            full_charge_days: self.full_charge_days,
            float_step_mv_per_min: self.float_step_mv_per_min,
            soc_ceiling_pct: self.soc_ceiling_pct,
            charge_current_cap_da: opt(self.charge_current_cap_da),
            discharge_current_cap_da: opt(self.discharge_current_cap_da),
            temperature_margin_c: i16::from(self.temperature_margin_c),
            limit_hold_us: Instant::from(self.limit_hold_s) * SECOND,
            ramp_rate_da_per_s: self.ramp_rate_da_per_s,
            cvl_raise_interval_us: Instant::from(self.cvl_raise_interval_s) * SECOND,
            warn_margin_mv: self.warning_margin_mv,
            warn_current_pct: self.warning_current_pct,
            current_margin_pct: self.current_margin_pct,
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
            name: crate::inverter::dialect::pylon::name_bytes(&self.inverter_name),
            stop_by_soc: self.stop_by_soc,
            ..InverterConfig::default()
        }
    }

    /// The owner's update key, when one is set.
    pub fn update_key(&self) -> Option<crate::update::file::Key> {
        crate::update::parse_key(self.update_key.as_bytes())
    }

    /// The host link's settings, with this firmware's version and the chip's name.
    pub fn host_link(&self, who: &crate::identity::Identity) -> HostLinkConfig {
        HostLinkConfig {
            read_only: self.read_only,
            stream_period_ms: self.stream_period_ms,
            firmware: who.firmware,
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
