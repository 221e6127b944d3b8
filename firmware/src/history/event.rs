//! The bridge's events as the history keeps them: what happened, when (the
//! time since the bridge started, the start's number and, when the bridge
//! knows it, the date), and two numbers and a short text that say the rest.
//! One event is one record of the ring ([`super::ring::PAYLOAD_BYTES`]).

use super::ring::PAYLOAD_BYTES;

/// Bytes of an event's text.
pub const TEXT_BYTES: usize = PAYLOAD_BYTES - 23;

/// What happened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Code {
    /// The bridge started: `a` the chip's reset reason (its raw code; 0xFF
    /// unknown), the text its firmware version.
    Started = 1,
    /// An event of the TinyBMS's own log: `a` its id, `b` the BMS's time
    /// stamp (s), the text its name.
    Bms = 2,
    /// The BMS stopped answering (`a`: failures in a row).
    BmsOffline = 3,
    /// The BMS answers again.
    BmsOnline = 4,
    /// The data went stale (`a`: the newest snapshot's age, ms).
    StaleBegan = 5,
    /// Fresh data again after a stale episode of `a` seconds.
    StaleEnded = 6,
    /// Charging (`a` bit 0) and/or discharging (bit 1) stopped; the text
    /// says why (the key of the rule).
    Stop = 7,
    /// Charging (`a` bit 0) and/or discharging (bit 1) allowed again.
    Resume = 8,
    /// The inverter's keep-alive is no longer heard.
    InverterLost = 9,
    /// The inverter is heard again.
    InverterSeen = 10,
    /// The CAN controller went bus-off (`a`: bus-offs so far).
    BusOff = 11,
    /// A configuration field changed: `b` who ([`Who`]), the text its name.
    Config = 12,
    /// Every configuration field went back to its default (`b`: who).
    ConfigReset = 13,
    /// An update is installed (the text: its version); the bridge restarts.
    UpdateInstalled = 14,
    /// This image came back from an update that failed its trial (the text:
    /// the version that failed; `a`: why, the key's index).
    RolledBack = 15,
    /// An update confirmed itself (the text: this version).
    UpdateConfirmed = 16,
    /// The Wi-Fi network was lost.
    WifiLost = 17,
    /// The Wi-Fi network is back after `a` seconds.
    WifiBack = 18,
    /// The MQTT connection was lost.
    MqttLost = 19,
    /// The MQTT connection is back after `a` seconds.
    MqttBack = 20,
    /// `a` events were not kept (too many too fast).
    Dropped = 21,
    /// The date was set (`b`: who, [`Who`]).
    TimeSet = 22,
}

impl Code {
    const ALL: [Code; 22] = [
        Self::Started,
        Self::Bms,
        Self::BmsOffline,
        Self::BmsOnline,
        Self::StaleBegan,
        Self::StaleEnded,
        Self::Stop,
        Self::Resume,
        Self::InverterLost,
        Self::InverterSeen,
        Self::BusOff,
        Self::Config,
        Self::ConfigReset,
        Self::UpdateInstalled,
        Self::RolledBack,
        Self::UpdateConfirmed,
        Self::WifiLost,
        Self::WifiBack,
        Self::MqttLost,
        Self::MqttBack,
        Self::Dropped,
        Self::TimeSet,
    ];

    /// From its byte.
    pub fn from_byte(b: u8) -> Option<Self> {
        Self::ALL.into_iter().find(|c| *c as u8 == b)
    }

    /// A short key (the host link, the tool's CSV).
    pub const fn key(self) -> &'static str {
        match self {
            Self::Started => "started",
            Self::Bms => "bms_event",
            Self::BmsOffline => "bms_offline",
            Self::BmsOnline => "bms_online",
            Self::StaleBegan => "stale",
            Self::StaleEnded => "fresh",
            Self::Stop => "stop",
            Self::Resume => "resume",
            Self::InverterLost => "inverter_lost",
            Self::InverterSeen => "inverter_seen",
            Self::BusOff => "bus_off",
            Self::Config => "config",
            Self::ConfigReset => "config_reset",
            Self::UpdateInstalled => "update_installed",
            Self::RolledBack => "rolled_back",
            Self::UpdateConfirmed => "update_confirmed",
            Self::WifiLost => "wifi_lost",
            Self::WifiBack => "wifi_back",
            Self::MqttLost => "mqtt_lost",
            Self::MqttBack => "mqtt_back",
            Self::Dropped => "dropped",
            Self::TimeSet => "time_set",
        }
    }
}

/// Who changed the configuration (or set the date).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Who {
    /// Over USB (the host link).
    Usb = 1,
    /// Over the network (the update port's link).
    Network = 2,
    /// The BOOT button.
    Button = 3,
    /// The browser installer's Wi-Fi set-up (Improv).
    WifiSetup = 4,
    /// A program driving the bridge's station on a computer.
    Host = 5,
}

impl Who {
    /// From its number (unknown: `None`).
    pub const fn from_u32(v: u32) -> Option<Self> {
        match v {
            1 => Some(Self::Usb),
            2 => Some(Self::Network),
            3 => Some(Self::Button),
            4 => Some(Self::WifiSetup),
            5 => Some(Self::Host),
            _ => None,
        }
    }

    /// A short key.
    pub const fn key(self) -> &'static str {
        match self {
            Self::Usb => "usb",
            Self::Network => "network",
            Self::Button => "button",
            Self::WifiSetup => "wifi_setup",
            Self::Host => "host",
        }
    }
}

/// One event. See the module documentation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Record {
    /// What.
    pub code: Code,
    /// The bridge's start it happened in (counted in the history).
    pub boot: u16,
    /// Time since that start, ms.
    pub uptime_ms: u64,
    /// The date, Unix seconds (0: not known then).
    pub unix_s: u32,
    /// First number (see [`Code`]).
    pub a: u32,
    /// Second number.
    pub b: u32,
    text: [u8; TEXT_BYTES],
}

/// Why a payload is not an event.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum EventError {
    /// An event code this firmware does not know.
    Code,
    /// The text is not printable ASCII.
    Text,
}

impl EventError {
    /// In words.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::Code => "an event code this firmware does not know",
            Self::Text => "an event whose text is not printable",
        }
    }
}

impl Record {
    /// An event; the text is cut to [`TEXT_BYTES`] and to printable ASCII
    /// (anything else becomes `?`).
    pub fn new(
        code: Code,
        boot: u16,
        uptime_ms: u64,
        unix_s: u32,
        a: u32,
        b: u32,
        text: &str,
    ) -> Self {
        let mut t = [0u8; TEXT_BYTES];
        for (d, s) in t.iter_mut().zip(text.bytes()) {
            *d = if (0x20..0x7F).contains(&s) { s } else { b'?' };
        }
        Self {
            code,
            boot,
            uptime_ms,
            unix_s,
            a,
            b,
            text: t,
        }
    }

    /// The text.
    pub fn text(&self) -> &str {
        let n = self.text.iter().position(|&b| b == 0).unwrap_or(TEXT_BYTES);
        core::str::from_utf8(self.text.get(..n).unwrap_or(&[])).unwrap_or("")
    }

    /// The payload.
    pub fn encode(&self) -> [u8; PAYLOAD_BYTES] {
        let mut p = [0u8; PAYLOAD_BYTES];
        p[0] = self.code as u8;
        p[1..3].copy_from_slice(&self.boot.to_le_bytes());
        p[3..11].copy_from_slice(&self.uptime_ms.to_le_bytes());
        p[11..15].copy_from_slice(&self.unix_s.to_le_bytes());
        p[15..19].copy_from_slice(&self.a.to_le_bytes());
        p[19..23].copy_from_slice(&self.b.to_le_bytes());
        p[23..].copy_from_slice(&self.text);
        p
    }

    /// From the first [`PAYLOAD_BYTES`] of a ring's payload.
    pub fn decode_payload(p: &super::ring::Payload) -> Result<Self, EventError> {
        let mut b = [0u8; PAYLOAD_BYTES];
        for (d, s) in b.iter_mut().zip(p) {
            *d = *s;
        }
        Self::decode(&b)
    }

    /// From a payload. Never panics.
    pub fn decode(p: &[u8; PAYLOAD_BYTES]) -> Result<Self, EventError> {
        let code = Code::from_byte(p[0]).ok_or(EventError::Code)?;
        let mut text = [0u8; TEXT_BYTES];
        text.copy_from_slice(&p[23..]);
        let n = text.iter().position(|&b| b == 0).unwrap_or(TEXT_BYTES);
        let (words, padding) = text.split_at(n.min(TEXT_BYTES));
        if words.iter().any(|b| !(0x20..0x7F).contains(b)) || padding.iter().any(|&b| b != 0) {
            return Err(EventError::Text);
        }
        let u32_at = |at: usize| {
            let mut w = [0u8; 4];
            w.copy_from_slice(p.get(at..at + 4).unwrap_or(&[0; 4]));
            u32::from_le_bytes(w)
        };
        let mut up = [0u8; 8];
        up.copy_from_slice(&p[3..11]);
        Ok(Self {
            code,
            boot: u16::from_le_bytes([p[1], p[2]]),
            uptime_ms: u64::from_le_bytes(up),
            unix_s: u32_at(11),
            a: u32_at(15),
            b: u32_at(19),
            text,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_event_reads_back_and_its_text_stays_printable() {
        let e = Record::new(
            Code::Config,
            7,
            123_456_789_012,
            1_765_000_000,
            3,
            1,
            "inverter.protocol\u{e9}and more than fits here",
        );
        let d = Record::decode(&e.encode()).unwrap();
        assert_eq!(d, e);
        assert_eq!(d.text(), "inverter.protocol??and more t");
        let mut p = e.encode();
        p[0] = 99;
        assert_eq!(Record::decode(&p), Err(EventError::Code));
        let mut p = e.encode();
        p[24] = 0x07;
        assert_eq!(Record::decode(&p), Err(EventError::Text));
        for c in Code::ALL {
            assert_eq!(Code::from_byte(c as u8), Some(c));
        }
    }
}
