//! Improv Wi-Fi over the host port: a browser installer (ESP Web Tools)
//! asks who the bridge is and gives it a network to join, right after
//! flashing, on the same cable as the host link. Sans-IO like the rest:
//! packets in ([`Improv::on_packet`]), what the Wi-Fi side did in
//! ([`Improv::joined`], [`Improv::scanned`], [`Improv::wifi_link`]), time in
//! ([`Improv::poll`]); packets out ([`Improv::next_packet`]), requests for
//! the Wi-Fi side out ([`WifiRequest`]), log lines out ([`Improv::next_note`]).
//!
//! * Every image with a host link answers "current state" and "device info",
//!   so the installer recognises the firmware and offers an update that
//!   keeps the stored configuration. An image without Wi-Fi says
//!   [`State::Stopped`] and refuses the Wi-Fi commands.
//! * Wi-Fi settings: the passphrase is turned into the WPA2 key here
//!   (`psk`, 16 rounds per poll, never stored, never echoed), the Wi-Fi
//!   side is asked to join ([`WifiRequest::Join`]), and only once it has
//!   joined are the network and its key handed to the configuration
//!   ([`Improv::take_joined`]); a network that cannot be joined (not found,
//!   the key refused, no answer within [`JOIN_TIMEOUT`]) is Improv's
//!   "unable to connect", and the stored network stays as it was.
//! * Bad packets (checksum, version, type, lengths) get "invalid RPC", unknown
//!   commands "unknown command"; nothing else happens.
//!
//! The wire format is [`wire`].

#[cfg(feature = "provision")]
pub mod psk;
pub mod wire;

use heapless::{Deque, String, Vec};

use crate::identity::Identity;
use crate::log_line::Line;
use crate::Instant;
pub use wire::{ErrorState, PacketError, Rpc, State};

/// The firmware's name as the installer sees it: the ESP Web Tools manifest
/// carries the same name, which is how an installed bridge is recognised
/// (an update then keeps the configuration).
pub const PRODUCT: &str = "TinyBMS bridge";

/// What an image with Wi-Fi adds to its version in Improv's device info and
/// its installer manifest (`0.1.0+wifi`).
pub const WIFI_VERSION_SUFFIX: &str = "+wifi";

/// Longest the Wi-Fi side may take to join a network and get an address
/// before the host is told "unable to connect", µs (the installer itself
/// waits 45 s).
pub const JOIN_TIMEOUT: Instant = 30 * crate::SECOND;

/// Longest a scan may take, µs; after it the host gets an empty list.
pub const SCAN_TIMEOUT: Instant = 15 * crate::SECOND;

/// Networks a scan reports at most (the strongest first).
pub const SCAN_MAX: usize = 12;

/// Packets waiting for the host (a whole scan fits).
const OUT_QUEUE: usize = SCAN_MAX + 4;

/// What the station asks of the Wi-Fi side.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WifiRequest {
    /// Join this network with this key (empty: open), and say how it went
    /// ([`Improv::joined`]); until then keep the network it had.
    Join {
        /// The network.
        ssid: String<32>,
        /// 64 hex digits, or empty for an open network.
        psk: String<64>,
    },
    /// List the networks in range ([`Improv::scanned`]).
    Scan,
}

/// The Wi-Fi link as the Wi-Fi side reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WifiLink {
    /// No network configured (or no Wi-Fi in this image).
    #[default]
    Off,
    /// Joining, or lost and trying again.
    Down,
    /// Joined, with this IPv4 address.
    Up([u8; 4]),
}

impl WifiLink {
    /// As `hello` says it.
    pub const fn key(self) -> &'static str {
        match self {
            Self::Off => "off",
            Self::Down => "connecting",
            Self::Up(_) => "connected",
        }
    }
}

/// Why a join failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum JoinFailure {
    /// No network of that name answered.
    NotFound,
    /// The network refused the key (a wrong passphrase).
    KeyRefused,
    /// Joined, but no address came (DHCP).
    NoAddress,
    /// Anything else the driver said.
    Other,
}

impl JoinFailure {
    /// In words an owner can act on.
    pub const fn text(self) -> &'static str {
        match self {
            Self::NotFound => "network not found (its name? in range?)",
            Self::KeyRefused => "the passphrase was not accepted",
            Self::NoAddress => "joined, but no address came (DHCP)",
            Self::Other => "the Wi-Fi driver refused",
        }
    }
}

/// A network a scan found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Network {
    /// Its name.
    pub ssid: String<32>,
    /// Signal strength, dBm.
    pub rssi: i8,
    /// True when it needs a key.
    pub secured: bool,
}

/// What the log says about provisioning (never a passphrase or a key).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Note {
    /// A host sent a packet that is not a command.
    BadPacket(PacketError),
    /// A host asked for a command this bridge does not do.
    Unsupported(u8),
    /// Provisioning this network started.
    Joining(String<32>),
    /// Joined it, with this address.
    Joined(String<32>, [u8; 4]),
    /// Could not join it.
    Failed(String<32>, JoinFailure),
    /// The network or passphrase could never work (lengths, characters).
    Refused(&'static str),
    /// No answer from the Wi-Fi side in time.
    TimedOut(String<32>),
}

/// A packet to be encoded when the host can take it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Out {
    State(State),
    Error(ErrorState),
    /// An RPC result without strings (a join's URLs: none).
    Empty(u8),
    DeviceInfo,
    /// The `n`th network of the last scan.
    Network(u8),
}

/// The provisioning under way (an image that cannot derive a key never
/// starts one).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(not(feature = "provision"), allow(dead_code))]
enum Job {
    /// The key is being derived.
    #[cfg(feature = "provision")]
    Derive {
        ssid: String<32>,
        psk: psk::PskDerivation,
    },
    /// The Wi-Fi side is to be asked (`asked` once it was handed out).
    Join {
        ssid: String<32>,
        psk: String<64>,
        asked: bool,
        deadline: Instant,
    },
}

/// Improv over the host port. See the module documentation.
#[derive(Debug, Clone)]
pub struct Improv {
    wifi: bool,
    chip_family: &'static str,
    name: String<32>,
    link: WifiLink,
    job: Option<Job>,
    /// A scan asked for (handed out once `asked`), and its deadline.
    scan: Option<(bool, Instant)>,
    networks: Vec<Network, SCAN_MAX>,
    out: Deque<Out, OUT_QUEUE>,
    notes: Deque<Note, 4>,
    joined: Option<(String<32>, String<64>)>,
}

/// The chip family as the installer names it (`ESP32-C3`).
pub fn chip_family(chip: &'static str) -> &'static str {
    match chip {
        "esp32c3" => "ESP32-C3",
        "esp32c6" => "ESP32-C6",
        other => other,
    }
}

fn text32(b: &[u8]) -> String<32> {
    let mut s = String::new();
    for c in core::str::from_utf8(b).unwrap_or("").chars() {
        if s.push(c).is_err() {
            break;
        }
    }
    s
}

impl Improv {
    /// Improv for a bridge of this identity (with Wi-Fi or without).
    pub fn new(identity: &Identity) -> Self {
        let mut name = String::new();
        let _ = name.push_str("tinybms");
        Self {
            wifi: identity.features.wifi,
            chip_family: chip_family(identity.chip),
            name,
            link: WifiLink::Off,
            job: None,
            scan: None,
            networks: Vec::new(),
            out: Deque::new(),
            notes: Deque::new(),
            joined: None,
        }
    }

    /// The bridge's name on the network (its host name): the installer
    /// shows it.
    pub fn set_name(&mut self, name: &str) {
        self.name = text32(name.as_bytes());
    }

    /// The state the host is told.
    pub fn state(&self) -> State {
        if !self.wifi {
            State::Stopped
        } else if self.job.is_some() {
            State::Provisioning
        } else if matches!(self.link, WifiLink::Up(_)) {
            State::Provisioned
        } else {
            State::Ready
        }
    }

    /// The Wi-Fi link now.
    pub fn link(&self) -> WifiLink {
        self.link
    }

    fn send(&mut self, o: Out) {
        if self.out.is_full() {
            self.out.pop_front();
        }
        let _ = self.out.push_back(o);
    }

    fn note(&mut self, n: Note) {
        if self.notes.is_full() {
            self.notes.pop_front();
        }
        let _ = self.notes.push_back(n);
    }

    /// One whole packet from the host (without its `\n`), at `now`.
    pub fn on_packet(&mut self, now: Instant, packet: &[u8]) {
        let rpc = match wire::parse(packet) {
            Ok(r) => r,
            Err(e) => {
                self.note(Note::BadPacket(e));
                self.send(Out::Error(ErrorState::InvalidRpc));
                return;
            }
        };
        match rpc {
            Rpc::CurrentState => {
                self.send(Out::State(self.state()));
                if self.state() == State::Provisioned {
                    self.send(Out::Empty(wire::command::CURRENT_STATE));
                }
            }
            Rpc::DeviceInfo => self.send(Out::DeviceInfo),
            Rpc::WifiSettings { ssid, passphrase } if self.wifi => {
                self.provision(now, ssid, passphrase)
            }
            Rpc::Scan if self.wifi => {
                if self.scan.is_none() {
                    self.scan = Some((false, now.saturating_add(SCAN_TIMEOUT)));
                }
            }
            Rpc::WifiSettings { .. } | Rpc::Scan => self.unsupported(packet),
            Rpc::Other(c) => {
                self.note(Note::Unsupported(c));
                self.send(Out::Error(ErrorState::UnknownCommand));
            }
        }
    }

    fn unsupported(&mut self, packet: &[u8]) {
        let c = packet.get(9).copied().unwrap_or(0);
        self.note(Note::Unsupported(c));
        self.send(Out::Error(ErrorState::UnknownCommand));
    }

    fn refuse(&mut self, why: &'static str) {
        self.note(Note::Refused(why));
        self.send(Out::Error(ErrorState::UnableToConnect));
        self.send(Out::State(self.state()));
    }

    #[cfg(feature = "provision")]
    fn provision(&mut self, now: Instant, ssid: &[u8], passphrase: &[u8]) {
        let Ok(name) = core::str::from_utf8(ssid) else {
            return self.refuse("the network's name is not UTF-8 text");
        };
        if name.chars().any(char::is_control) {
            return self.refuse("the network's name has control characters");
        }
        let start = match psk::PskDerivation::start(ssid, passphrase) {
            Ok(s) => s,
            Err(e) => return self.refuse(e.text()),
        };
        let ssid = text32(ssid);
        // A newer request replaces one under way (the host has given up on it).
        self.job = Some(match start {
            psk::Start::Open => Job::Join {
                ssid: ssid.clone(),
                psk: String::new(),
                asked: false,
                deadline: now.saturating_add(JOIN_TIMEOUT),
            },
            psk::Start::Key(k) => Job::Join {
                ssid: ssid.clone(),
                psk: k,
                asked: false,
                deadline: now.saturating_add(JOIN_TIMEOUT),
            },
            psk::Start::Derive(d) => Job::Derive {
                ssid: ssid.clone(),
                psk: d,
            },
        });
        self.note(Note::Joining(ssid));
        self.send(Out::Error(ErrorState::None));
        self.send(Out::State(State::Provisioning));
    }

    #[cfg(not(feature = "provision"))]
    fn provision(&mut self, _: Instant, _: &[u8], _: &[u8]) {
        self.refuse("this image cannot derive a Wi-Fi key");
    }

    /// What the Wi-Fi side has to do now, if anything; call until `None`.
    /// A step of a key derivation is done here too.
    pub fn poll(&mut self, now: Instant) -> Option<WifiRequest> {
        #[cfg(feature = "provision")]
        if let Some(Job::Derive { ssid, psk }) = &mut self.job {
            if let Some(key) = psk.step() {
                let ssid = ssid.clone();
                self.job = Some(Job::Join {
                    ssid,
                    psk: key,
                    asked: false,
                    deadline: now.saturating_add(JOIN_TIMEOUT),
                });
            }
        }
        match &mut self.job {
            Some(Job::Join {
                ssid,
                psk,
                asked: asked @ false,
                ..
            }) => {
                *asked = true;
                return Some(WifiRequest::Join {
                    ssid: ssid.clone(),
                    psk: psk.clone(),
                });
            }
            Some(Job::Join {
                ssid,
                deadline,
                asked: true,
                ..
            }) if now >= *deadline => {
                let ssid = ssid.clone();
                self.job = None;
                self.note(Note::TimedOut(ssid));
                self.send(Out::Error(ErrorState::UnableToConnect));
                self.send(Out::State(self.state()));
            }
            _ => {}
        }
        match &mut self.scan {
            Some((asked @ false, _)) => {
                *asked = true;
                return Some(WifiRequest::Scan);
            }
            Some((true, deadline)) if now >= *deadline => self.scanned(now, &[]),
            _ => {}
        }
        None
    }

    /// When to be polled again: at once while a key is derived, else at the
    /// earliest deadline.
    pub fn wake(&self, now: Instant) -> Instant {
        let mut t = Instant::MAX;
        match &self.job {
            #[cfg(feature = "provision")]
            Some(Job::Derive { .. }) => t = now,
            Some(Job::Join { asked: false, .. }) => t = now,
            Some(Job::Join { deadline, .. }) => t = t.min(*deadline),
            None => {}
        }
        if let Some((asked, deadline)) = self.scan {
            t = t.min(if asked { deadline } else { now });
        }
        t
    }

    /// The Wi-Fi link changed (the Wi-Fi side reports it at any time).
    pub fn wifi_link(&mut self, link: WifiLink) {
        self.link = link;
    }

    /// The join asked for with [`WifiRequest::Join`] ended.
    pub fn joined(&mut self, now: Instant, result: Result<[u8; 4], JoinFailure>) {
        let _ = now;
        let Some(Job::Join {
            ssid,
            psk,
            asked: true,
            ..
        }) = self.job.take()
        else {
            return;
        };
        match result {
            Ok(ip) => {
                self.link = WifiLink::Up(ip);
                self.note(Note::Joined(ssid.clone(), ip));
                self.joined = Some((ssid, psk));
                self.send(Out::State(State::Provisioned));
                self.send(Out::Empty(wire::command::WIFI_SETTINGS));
            }
            Err(f) => {
                self.note(Note::Failed(ssid, f));
                self.send(Out::Error(ErrorState::UnableToConnect));
                self.send(Out::State(self.state()));
            }
        }
    }

    /// The scan asked for with [`WifiRequest::Scan`] ended (strongest
    /// first; more than [`SCAN_MAX`] are left out).
    pub fn scanned(&mut self, _now: Instant, networks: &[Network]) {
        if self.scan.take().is_none() {
            return;
        }
        self.networks.clear();
        for n in networks {
            if n.ssid.is_empty() || self.networks.iter().any(|m| m.ssid == n.ssid) {
                continue;
            }
            if self.networks.push(n.clone()).is_err() {
                break;
            }
        }
        self.networks
            .sort_unstable_by_key(|n| core::cmp::Reverse(n.rssi));
        for i in 0..self.networks.len() {
            self.send_network(i as u8);
        }
        self.send(Out::Empty(wire::command::SCAN));
    }

    fn send_network(&mut self, i: u8) {
        // The list waits whole: a network is never pushed out by the next.
        let _ = self.out.push_back(Out::Network(i));
    }

    /// A network joined through Improv, with its key: for the record (once).
    pub fn take_joined(&mut self) -> Option<(String<32>, String<64>)> {
        self.joined.take()
    }

    /// The next line for the log.
    pub fn next_note(&mut self) -> Option<Note> {
        self.notes.pop_front()
    }

    /// True when packets wait for the host.
    pub fn has_output(&self) -> bool {
        !self.out.is_empty()
    }

    /// The next packet for the host (`\n` included).
    pub fn next_packet(&mut self, firmware: &str) -> Option<wire::Packet> {
        let o = self.out.pop_front()?;
        Some(match o {
            Out::State(s) => wire::current_state(s),
            Out::Error(e) => wire::error_state(e),
            Out::Empty(c) => wire::result(c, &[]),
            Out::DeviceInfo => {
                // The image's version as its installer manifest carries it:
                // an image with Wi-Fi says `VERSION+wifi` (semver build
                // metadata), so the installer offers the switch between the
                // two images of one version as an update.
                let mut version = Line::new();
                version.push(firmware);
                if self.wifi {
                    version.push(WIFI_VERSION_SUFFIX);
                }
                wire::result(
                    wire::command::DEVICE_INFO,
                    &[
                        PRODUCT.as_bytes(),
                        version.as_str().as_bytes(),
                        self.chip_family.as_bytes(),
                        self.name.as_bytes(),
                    ],
                )
            }
            Out::Network(i) => {
                let n = self.networks.get(usize::from(i))?;
                let mut rssi = Line::new();
                rssi.int(i64::from(n.rssi));
                wire::result(
                    wire::command::SCAN,
                    &[
                        n.ssid.as_bytes(),
                        rssi.as_str().as_bytes(),
                        if n.secured { &b"YES"[..] } else { &b"NO"[..] },
                    ],
                )
            }
        })
    }
}
