//! The Wi-Fi side's rules, sans-IO: how long a join, a scan and DHCP may
//! take, how often the signal is read, what a disconnect means for an owner,
//! the bridge's name on the network and which signal readings are real. The
//! chip's Wi-Fi task (`src/chip/wifi.rs`) makes the driver calls and goes by
//! these; it retries a lost network by [`crate::backoff`], as MQTT retries a
//! lost broker.

use heapless::String;

use crate::improv::{JoinFailure, JOIN_TIMEOUT, SCAN_TIMEOUT};
use crate::{Instant, SECOND};

/// Longest the driver may take for a join Improv asked for: inside the
/// station's own limit ([`JOIN_TIMEOUT`]), so that the driver's answer, not
/// the station's timeout, says why a join failed.
pub const JOIN_TIME_US: Instant = JOIN_TIMEOUT - 5 * SECOND;
/// Longest a scan may take: inside the station's limit ([`SCAN_TIMEOUT`]),
/// so the host gets what was found rather than an empty list.
pub const SCAN_TIME_US: Instant = SCAN_TIMEOUT - 5 * SECOND;
/// Longest the wait for an address (DHCP) once joined.
pub const DHCP_TIMEOUT_US: Instant = 10 * SECOND;
/// How often the access point's signal is read while joined (what MQTT
/// publishes as the Wi-Fi signal).
pub const RSSI_PERIOD_US: Instant = 10 * SECOND;

/// Why the station could not join, or left, a network: the driver's
/// reasons sorted by what an owner can do about them (the chip sorts them).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Cause {
    /// No access point of that name answered (or it went out of range).
    NotFound,
    /// The network's security is not one the station speaks.
    Security,
    /// The key was refused or the handshake failed.
    KeyRefused,
    /// The access point refused the station (association).
    Refused,
    /// Anything else (the RTT log has the driver's own reason).
    Other,
}

impl Cause {
    /// What Improv tells the browser of a failed join.
    pub const fn failure(self) -> JoinFailure {
        match self {
            Self::NotFound => JoinFailure::NotFound,
            Self::KeyRefused => JoinFailure::KeyRefused,
            Self::Security | Self::Refused | Self::Other => JoinFailure::Other,
        }
    }

    /// In words an owner can act on (the log's `Wi-Fi down: ...`).
    pub const fn text(self) -> &'static str {
        match self {
            Self::NotFound => "network not found (its name? in range?)",
            Self::Security => "the network's security does not fit (WPA3 only? it needs WPA2)",
            Self::KeyRefused => "the key was not accepted (the passphrase? tinybms wifi)",
            Self::Refused => "the access point refused the station",
            Self::Other => "see the reason in the RTT log",
        }
    }
}

/// The bridge's name on the network: the record's `hostname`, or, when it
/// has none (or one longer than a name may be, which the record's checks
/// never let through), `tinybms-` and the last three bytes of the MAC
/// address in hex (`tinybms-a1b2c3`), so two bridges on one network differ.
pub fn hostname(stored: &str, mac: [u8; 6]) -> String<32> {
    if let Ok(h) = String::try_from(stored) {
        if !h.is_empty() {
            return h;
        }
    }
    let mut h = String::new();
    let _ = h.push_str("tinybms-");
    for b in mac.get(3..).unwrap_or(&[]) {
        for nibble in [b >> 4, b & 0xF] {
            let _ = h.push(char::from_digit(u32::from(nibble), 16).unwrap_or('0'));
        }
    }
    h
}

/// A signal reading from the driver, dBm: a real one is negative; 0 or more
/// (or out of range) means the driver does not know.
pub fn rssi(raw: i32) -> Option<i8> {
    i8::try_from(raw).ok().filter(|r| *r < 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_name_is_the_record_s_or_made_from_the_mac() {
        assert_eq!(hostname("shed-battery", [0; 6]).as_str(), "shed-battery");
        assert_eq!(
            hostname("", [0x10, 0x20, 0x30, 0xA1, 0x0B, 0xFF]).as_str(),
            "tinybms-a10bff"
        );
        let longest = "a".repeat(32);
        assert_eq!(hostname(&longest, [0; 6]).as_str(), longest);
        // Never an empty or cut name.
        let too_long = "a".repeat(33);
        assert_eq!(
            hostname(&too_long, [0, 0, 0, 1, 2, 3]).as_str(),
            "tinybms-010203"
        );
    }

    #[test]
    fn only_negative_readings_are_a_signal() {
        assert_eq!(rssi(-67), Some(-67));
        assert_eq!(rssi(-128), Some(-128));
        assert_eq!(rssi(0), None);
        assert_eq!(rssi(12), None);
        assert_eq!(rssi(-129), None);
    }

    #[test]
    fn the_driver_answers_before_the_station_gives_up() {
        // A join (association, then DHCP) ends inside the station's limit.
        assert!(DHCP_TIMEOUT_US < JOIN_TIME_US && JOIN_TIME_US < JOIN_TIMEOUT);
        assert!(SCAN_TIME_US < SCAN_TIMEOUT);
        assert_eq!(Cause::NotFound.failure(), JoinFailure::NotFound);
        assert_eq!(Cause::KeyRefused.failure(), JoinFailure::KeyRefused);
        assert_eq!(Cause::Security.failure(), JoinFailure::Other);
    }
}
