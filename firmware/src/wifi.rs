//! The Wi-Fi side's rules, sans-IO: how long a join, a scan and DHCP may
//! take, how often the signal is read, what a disconnect means for an owner,
//! the bridge's name on the network and which signal readings are real. The
//! chip's Wi-Fi task (`src/chip/network.rs`) makes the driver calls and goes by
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

/// Heap for the radio's driver and the MQTT client's packet buffers, bytes:
/// the part esp-hal reclaims from the bootloader's RAM, and more. The
/// station needs 47-57 KiB (esp-radio's documentation), MQTT a few, the
/// radio's start thread its stack ([`RADIO_START_STACK`]) until it ends.
pub const HEAP_RECLAIMED: usize = 64 * 1024;
/// See [`HEAP_RECLAIMED`].
pub const HEAP_MORE: usize = 36 * 1024;
/// How often the heap's use is logged (the figure a run on a unit gives for
/// docs/performance.md).
pub const HEAP_LOG_PERIOD_US: Instant = 600 * SECOND;

/// The stack of the thread that starts the radio, bytes (from the heap).
pub const RADIO_START_STACK: usize = 12 * 1024;

/// A line the Wi-Fi side logs (defmt and the host link's `log` lines).
#[derive(Debug, Clone, Copy)]
pub enum Said<'a> {
    /// No network in the record.
    NoNetwork,
    /// The record's network or key is one the driver does not take.
    StoredInvalid,
    /// The driver refused the record's network when it was set.
    DriverRefused,
    /// No broker in the record.
    MqttOff,
    /// Joining the record's network (its name), as this host name.
    Joining(&'a str, &'a str),
    /// MQTT will connect to this broker and port.
    MqttTo(&'a str, u16),
    /// Joined this network on this channel.
    Up(&'a str, u8),
    /// The link went down: why, when the driver said.
    Down(Option<Cause>),
    /// A join failed; the next try in so many seconds.
    CannotJoin(JoinFailure, u64),
    /// DHCP gave this address and prefix.
    Address([u8; 4], u8),
}

impl Said<'_> {
    /// Whether it is a warning.
    pub const fn warns(&self) -> bool {
        matches!(
            self,
            Self::StoredInvalid | Self::DriverRefused | Self::Down(_) | Self::CannotJoin(..)
        )
    }

    /// The words.
    pub fn write(&self, out: &mut crate::log_line::Line) {
        match *self {
            Self::NoNetwork => {
                out.push("Wi-Fi: no network yet (the browser installer, or tinybms wifi PORT --ssid NAME)");
            }
            Self::StoredInvalid => {
                out.push("Wi-Fi: the stored network or key is not valid");
            }
            Self::DriverRefused => {
                out.push("Wi-Fi: the driver refused the stored network");
            }
            Self::MqttOff => {
                out.push("MQTT off: no mqtt_host (tinybms mqtt PORT --host HOST)");
            }
            Self::Joining(ssid, name) => {
                out.push("Wi-Fi: joining ")
                    .push(ssid)
                    .push(" as ")
                    .push(name);
            }
            Self::MqttTo(host, port) => {
                out.push("MQTT to ")
                    .push(host)
                    .push(":")
                    .uint(u64::from(port));
            }
            Self::Up(ssid, channel) => {
                out.push("Wi-Fi up: ")
                    .push(ssid)
                    .push(", channel ")
                    .uint(u64::from(channel));
            }
            Self::Down(cause) => {
                out.push("Wi-Fi down");
                if let Some(c) = cause {
                    out.push(": ").push(c.text());
                }
            }
            Self::CannotJoin(f, secs) => {
                out.push("Wi-Fi: cannot join (")
                    .push(f.text())
                    .push("), next try in ")
                    .uint(secs)
                    .push(" s");
            }
            Self::Address(ip, prefix) => {
                out.push("IP ");
                crate::text::ipv4(ip, out);
                out.push("/").uint(u64::from(prefix)).push(" (DHCP)");
            }
        }
    }
}

/// How long the radio may take to start (its driver's set-up, the RF
/// calibration) before the bridge says it is late. The bridge's own work does
/// not wait for it either way: the radio starts on a thread of its own, below
/// the bridge's.
pub const RADIO_START_LIMIT_US: Instant = 20 * SECOND;

/// The radio's start, as the bridge tells it (`hello`'s `radio`, the log).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Radio {
    /// Its driver is being set up.
    Starting,
    /// Still setting up after [`RADIO_START_LIMIT_US`].
    Late,
    /// Up: Wi-Fi and MQTT run.
    Up,
    /// Its driver refused to start: Wi-Fi off until a restart.
    Failed,
    /// It did not finish starting before the chip was reset (a radio that
    /// hangs with the CPU held: a damaged antenna, a marginal supply, an
    /// emulator without one): kept off until the bridge is powered off and
    /// on, so it cannot keep resetting the bridge.
    HeldOff,
}

impl Radio {
    /// Every state, for the tests and the tool.
    pub const ALL: [Self; 5] = [
        Self::Starting,
        Self::Late,
        Self::Up,
        Self::Failed,
        Self::HeldOff,
    ];

    /// As `hello` says it.
    pub const fn key(self) -> &'static str {
        match self {
            Self::Starting => "starting",
            Self::Late => "late",
            Self::Up => "up",
            Self::Failed => "failed",
            Self::HeldOff => "held_off",
        }
    }

    /// From `hello`'s key.
    pub fn from_key(key: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|r| r.key() == key)
    }

    /// In words (the log line, `tinybms version`).
    pub const fn text(self) -> &'static str {
        match self {
            Self::Starting => "radio: starting (the BMS, the inverter and USB do not wait for it)",
            Self::Late => {
                "radio: not up after 20 s; still trying (the BMS, the inverter and USB run on)"
            }
            Self::Up => "radio: up",
            Self::Failed => "radio: its driver did not start; Wi-Fi and MQTT off until a restart",
            Self::HeldOff => {
                "radio: off, it did not finish starting before the last reset; power the \
                 bridge off and on to try it again (the BMS, the inverter and USB run on)"
            }
        }
    }

    /// Whether the line is a warning.
    pub const fn warns(self) -> bool {
        matches!(self, Self::Late | Self::Failed | Self::HeldOff)
    }
}

/// What the chip keeps across a reset, but not across a power cut (its RTC
/// memory), so that a radio whose start takes the chip down is not started
/// again at the next boot: four words, [`RadioMark::WORDS`], with a magic and
/// a check so that noise reads as "nothing marked".
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RadioMark(pub [u32; 4]);

/// What [`RadioMark::at_boot`] decides.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bringup {
    /// Start the radio.
    Start,
    /// Keep it off ([`Radio::HeldOff`]).
    HoldOff,
}

const MARK_MAGIC: u32 = 0x7261_6469; // "radi"
const MARK_CLEAR: u32 = 0;
const MARK_STARTING: u32 = 0x5354_5254; // "STRT"
const MARK_HELD: u32 = 0x484F_4C44; // "HOLD"

impl RadioMark {
    /// The words a chip keeps.
    pub const WORDS: usize = 4;

    fn state(&self) -> u32 {
        let [magic, state, inverse, check] = self.0;
        if magic == MARK_MAGIC && inverse == !state && check == magic ^ state {
            state
        } else {
            MARK_CLEAR
        }
    }

    fn set(&mut self, state: u32) {
        self.0 = [MARK_MAGIC, state, !state, MARK_MAGIC ^ state];
    }

    /// At boot, from what the memory held (zeros after a power cut, anything
    /// on a chip that never had it): start the radio, or keep it off because
    /// the last start never finished. Keeps holding it off at every later
    /// reset until a power cut clears the memory.
    pub fn at_boot(&mut self) -> Bringup {
        match self.state() {
            MARK_STARTING | MARK_HELD => {
                self.set(MARK_HELD);
                Bringup::HoldOff
            }
            _ => {
                self.set(MARK_CLEAR);
                Bringup::Start
            }
        }
    }

    /// Just before the radio's driver is called.
    pub fn starting(&mut self) {
        self.set(MARK_STARTING);
    }

    /// The driver returned (up or refused): a reset from now on is not the
    /// radio's start.
    pub fn started(&mut self) {
        self.set(MARK_CLEAR);
    }
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

    /// One boot after another, as the chip's RTC memory carries the mark.
    fn boots(mark: &mut RadioMark, finish: bool) -> Bringup {
        let b = mark.at_boot();
        if b == Bringup::Start {
            mark.starting();
            if finish {
                mark.started();
            }
        }
        b
    }

    #[test]
    fn a_radio_whose_start_never_ends_is_held_off_until_a_power_cut() {
        // Power on: zeros.
        let mut m = RadioMark([0; 4]);
        assert_eq!(boots(&mut m, true), Bringup::Start);
        assert_eq!(
            boots(&mut m, true),
            Bringup::Start,
            "a reset after a good start"
        );
        // The start hangs; the watchdog resets the chip.
        assert_eq!(boots(&mut m, false), Bringup::Start);
        assert_eq!(boots(&mut m, false), Bringup::HoldOff);
        assert_eq!(
            boots(&mut m, false),
            Bringup::HoldOff,
            "every reset after it"
        );
        // A power cut clears the memory: tried again.
        let mut m = RadioMark([0; 4]);
        assert_eq!(boots(&mut m, true), Bringup::Start);
    }

    #[test]
    fn noise_in_the_memory_is_no_mark() {
        let mut x: u32 = 0xDEAD_BEEF;
        for _ in 0..10_000 {
            let mut w = [0u32; 4];
            for v in &mut w {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                *v = x;
            }
            assert_eq!(RadioMark(w).at_boot(), Bringup::Start, "{w:x?}");
        }
        // One word changed in a real mark: no mark.
        let mut m = RadioMark([0; 4]);
        m.starting();
        for i in 0..4 {
            let mut w = m;
            w.0[i] ^= 1 << 7;
            assert_eq!(w.at_boot(), Bringup::Start);
        }
        assert_eq!(m.at_boot(), Bringup::HoldOff);
    }

    fn said(s: Said<'_>) -> crate::log_line::Line {
        let mut l = crate::log_line::Line::new();
        s.write(&mut l);
        l
    }

    #[test]
    fn the_wifi_side_says_what_happened_in_words() {
        assert_eq!(
            said(Said::Joining("home", "shed")).as_str(),
            "Wi-Fi: joining home as shed"
        );
        assert_eq!(
            said(Said::MqttTo("192.168.1.10", 1883)).as_str(),
            "MQTT to 192.168.1.10:1883"
        );
        assert_eq!(
            said(Said::Up("home", 6)).as_str(),
            "Wi-Fi up: home, channel 6"
        );
        assert_eq!(said(Said::Down(None)).as_str(), "Wi-Fi down");
        assert_eq!(
            said(Said::Down(Some(Cause::NotFound))).as_str(),
            "Wi-Fi down: network not found (its name? in range?)"
        );
        assert_eq!(
            said(Said::Address([10, 0, 0, 7], 24)).as_str(),
            "IP 10.0.0.7/24 (DHCP)"
        );
        assert!(said(Said::CannotJoin(JoinFailure::NoAddress, 30))
            .as_str()
            .ends_with("), next try in 30 s"));
        assert!(Said::Down(None).warns() && !Said::MqttOff.warns());
        // The heap holds the radio's start thread beside what the station needs.
        assert!(HEAP_RECLAIMED + HEAP_MORE >= 57 * 1024 + RADIO_START_STACK + 8 * 1024);
    }

    #[test]
    fn every_radio_state_has_its_key_and_words() {
        for r in Radio::ALL {
            assert_eq!(Radio::from_key(r.key()), Some(r));
            assert!(r.text().starts_with("radio: "));
        }
        assert_eq!(Radio::from_key("on"), None);
        assert!(Radio::HeldOff.warns() && !Radio::Up.warns());
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
