//! The Wi-Fi side of a desktop station in real time (`sim --bridge-pty
//! --wifi-network …`): simulated networks the station's Improv Wi-Fi can
//! scan and join, so the browser installer's network set-up runs against
//! the firmware's own code without a radio.
//!
//! A join succeeds only when the key the station derived equals the WPA2
//! key of the network's passphrase, computed here independently (the
//! `pbkdf2` crate, IEEE 802.11i); a network that does not exist is "not
//! found", a wrong key "refused". The addresses handed out are in
//! 192.0.2.0/24 (TEST-NET-1, RFC 5737): data only, never contacted. At a
//! start with a stored network the station joins it by itself, as the chip's
//! Wi-Fi task does at boot.

use std::time::Duration;

use tinybms_desk::WifiSide;
use tinybms_firmware::config::Config;
use tinybms_firmware::improv::{JoinFailure, Network, WifiLink, WifiRequest};
use tinybms_firmware::station::Station;
use tinybms_firmware::wifi::{Radio, RADIO_START_LIMIT_US};
use tinybms_firmware::Instant;

/// A simulated network.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SimNetwork {
    /// Its name.
    pub ssid: String,
    /// Its WPA2 passphrase; `None`: open.
    pub passphrase: Option<String>,
    /// Signal strength, dBm.
    pub rssi: i8,
}

impl SimNetwork {
    /// `NAME`, `NAME:PASSPHRASE` or `NAME:PASSPHRASE:RSSI` (`--wifi-network`).
    pub fn parse(spec: &str) -> Result<Self, String> {
        let mut parts = spec.splitn(3, ':');
        let ssid = parts.next().unwrap_or("").to_string();
        if ssid.is_empty() || ssid.len() > 32 {
            return Err(format!("`{spec}`: a network's name has 1 to 32 bytes"));
        }
        let passphrase = parts.next().filter(|p| !p.is_empty()).map(str::to_string);
        if let Some(p) = &passphrase {
            if !(8..=63).contains(&p.len()) {
                return Err(format!(
                    "`{spec}`: a WPA2 passphrase has 8 to 63 characters"
                ));
            }
        }
        let rssi = match parts.next() {
            Some(r) => r
                .parse::<i8>()
                .ok()
                .filter(|r| (-100..=0).contains(r))
                .ok_or_else(|| format!("`{spec}`: the signal is -100..0 dBm"))?,
            None => -55,
        };
        Ok(Self {
            ssid,
            passphrase,
            rssi,
        })
    }

    /// The key a station must present (64 hex digits; empty when open).
    pub fn psk(&self) -> String {
        match &self.passphrase {
            None => String::new(),
            Some(p) => {
                let mut key = [0u8; 32];
                pbkdf2::pbkdf2_hmac::<sha1::Sha1>(
                    p.as_bytes(),
                    self.ssid.as_bytes(),
                    4096,
                    &mut key,
                );
                key.iter().map(|b| format!("{b:02x}")).collect()
            }
        }
    }
}

/// What the Wi-Fi side has for the station.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Done {
    Joined(Result<[u8; 4], JoinFailure>),
    Scanned(Vec<Network>),
    Link(WifiLink),
    Radio(Radio),
}

/// The simulated radio. See the module documentation.
#[derive(Debug, Clone)]
pub struct SimWifi {
    networks: Vec<SimNetwork>,
    /// How long a join or a scan takes.
    pub delay: Duration,
    pending: Vec<(Instant, Done)>,
    /// Joins asked for, and how they ended (for tests).
    pub joins: Vec<(String, Result<[u8; 4], JoinFailure>)>,
    /// The radio never finishes starting (a radio that hangs): the station
    /// hears `starting`, then `late`, and nothing else of Wi-Fi.
    pub radio_hangs: bool,
    /// When a hanging radio is said to be late (the chip's
    /// [`RADIO_START_LIMIT_US`]; shorter in tests).
    pub late_after: Instant,
}

/// How long the simulated radio takes to start.
pub const RADIO_START_US: Instant = 50 * tinybms_firmware::MS;

impl SimWifi {
    /// These networks in range.
    pub fn new(networks: Vec<SimNetwork>) -> Self {
        Self {
            networks,
            delay: Duration::from_millis(1500),
            pending: Vec::new(),
            joins: Vec::new(),
            radio_hangs: false,
            late_after: RADIO_START_LIMIT_US,
        }
    }

    fn outcome(&self, ssid: &str, psk: &str) -> Result<[u8; 4], JoinFailure> {
        let Some((i, n)) = self
            .networks
            .iter()
            .enumerate()
            .find(|(_, n)| n.ssid == ssid)
        else {
            return Err(JoinFailure::NotFound);
        };
        if n.psk() != psk.to_ascii_lowercase() {
            return Err(JoinFailure::KeyRefused);
        }
        Ok([192, 0, 2, 10 + i as u8])
    }

    fn after(&mut self, now: Instant, done: Done) {
        let at = now + self.delay.as_micros() as Instant;
        self.pending.push((at, done));
    }
}

impl WifiSide for SimWifi {
    /// The station starts (boot or restart) with `record`: a stored network
    /// is joined in the background.
    /// The radio starts first, as on the chip (`starting`, then `up`, or
    /// `late` when it hangs).
    fn boot(&mut self, now: Instant, record: &Config) {
        self.pending.clear();
        self.pending.push((now, Done::Radio(Radio::Starting)));
        if self.radio_hangs {
            self.pending
                .push((now + self.late_after, Done::Radio(Radio::Late)));
            return;
        }
        let up = now + RADIO_START_US;
        self.pending.push((up, Done::Radio(Radio::Up)));
        if record.wifi_ssid.is_empty() {
            self.pending.push((up, Done::Link(WifiLink::Off)));
            return;
        }
        self.pending.push((up, Done::Link(WifiLink::Down)));
        if let Ok(ip) = self.outcome(&record.wifi_ssid, &record.wifi_key) {
            self.after(up, Done::Link(WifiLink::Up(ip)));
        }
    }

    /// The station asks at `now`.
    fn request(&mut self, now: Instant, req: WifiRequest) {
        if self.radio_hangs {
            // Nobody takes the request (the chip's Wi-Fi task never started):
            // the station's own limits end it.
            return;
        }
        match req {
            WifiRequest::Join { ssid, psk } => {
                let r = self.outcome(&ssid, &psk);
                self.joins.push((ssid.to_string(), r));
                self.after(now, Done::Joined(r));
            }
            WifiRequest::Scan => {
                let list = self
                    .networks
                    .iter()
                    .map(|n| Network {
                        ssid: heapless::String::try_from(n.ssid.as_str()).unwrap_or_default(),
                        rssi: n.rssi,
                        secured: n.passphrase.is_some(),
                    })
                    .collect();
                self.after(now, Done::Scanned(list));
            }
        }
    }

    /// Hands the station what is done by `now`.
    fn deliver(&mut self, now: Instant, station: &mut Station) {
        let mut i = 0;
        while i < self.pending.len() {
            if self.pending[i].0 > now {
                i += 1;
                continue;
            }
            match self.pending.remove(i).1 {
                Done::Joined(r) => station.wifi_joined(now, r),
                Done::Scanned(list) => station.wifi_scanned(now, &list),
                Done::Link(l) => station.wifi_link(l),
                Done::Radio(r) => station.radio(r),
            }
        }
    }

    /// When something is next due.
    fn next_due(&self) -> Option<Instant> {
        self.pending.iter().map(|(t, _)| *t).min()
    }
}
