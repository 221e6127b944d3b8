//! Wi-Fi and MQTT (feature `wifi`): the battery in Home Assistant. Publish
//! only, and never in the charge-control path: these tasks read the copy the
//! station publishes ([`wires::PUBLISHED`]: the snapshot with its freshness,
//! the limits the inverter is told, the battery) and its events
//! ([`wires::MQTT_EVENTS`]), and nothing waits on them — a missing network or
//! a bad broker only costs their own reconnects.
//!
//! * `wifi_task` — station mode with the record's SSID and 64-hex pre-shared
//!   key (the ESP Wi-Fi driver takes 64 hex digits as the PSK itself, so the chip
//!   never runs PBKDF2: see docs), reconnect with backoff, one log line per link
//!   up/down.
//! * `net_task` — embassy-net (DHCP with the bridge's host name).
//! * `mqtt_task` — the library's MQTT session (`tinybms_firmware::mqtt`), the
//!   code the host tests run against mosquitto.

use defmt::{info, warn};
use embassy_executor::Spawner;
use embassy_futures::select::{select, Either};
use embassy_net::tcp::client::{TcpClient, TcpClientState};
use embassy_net::{DhcpConfig, Runner, Stack, StackResources};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::watch::Receiver;
use embassy_time::{Duration, Instant, Timer};
use esp_hal::peripherals::WIFI;
use esp_hal::rng::Rng;
use esp_radio::wifi::sta::StationConfig;
use esp_radio::wifi::{
    AuthenticationMethodConfig, Config as WifiConfig, ConnectionError, ControllerConfig,
    DisconnectReason, Interface, Password, Ssid, WifiController,
};
use heapless::String;
use protocol_core::events::Event;
use static_cell::StaticCell;
use tinybms_firmware::config::Config;
use tinybms_firmware::mqtt::net::StackNet;
use tinybms_firmware::mqtt::publisher::{Publisher, View};
use tinybms_firmware::mqtt::session::{self, Clock, Feed, Note, Target};
use tinybms_firmware::mqtt::Settings;
use tinybms_firmware::station::Published;
use tinybms_firmware::text::Line;
use tinybms_firmware::Level;

use crate::{spawn, wires};

/// Heap for the Wi-Fi driver and the MQTT client's packet buffers, bytes: the
/// station needs 47-57 KiB (esp-radio's documentation), MQTT a few.
const HEAP_RECLAIMED: usize = 64 * 1024;
const HEAP_MORE: usize = 36 * 1024;

/// TCP buffers of the MQTT connection, bytes each way.
const TCP_BUFFER: usize = 2048;

/// How often the access point's signal (RSSI) is read while joined.
const RSSI_PERIOD: Duration = Duration::from_secs(10);

/// Wi-Fi reconnect delays: the first, and the longest (doubling between).
const WIFI_BACKOFF_MIN: Duration = Duration::from_secs(1);
const WIFI_BACKOFF_MAX: Duration = Duration::from_secs(60);

/// One log line (defmt and the host link's `log` lines) from pieces.
fn say(level: Level, pieces: &[&str]) {
    let mut l = Line::new();
    for p in pieces {
        l.push(p);
    }
    crate::log::line(level, &l);
}

/// A disconnect reason in words an owner can act on (defmt logs the exact one).
fn reason_text(r: DisconnectReason) -> &'static str {
    use DisconnectReason as R;
    match r {
        R::NoAccessPointFound | R::NoAccessPointFoundInRssiThreshold | R::BeaconTimeout => {
            "network not found (its name? in range?)"
        }
        R::NoAccessPointFoundWithCompatibleSecurity | R::NoAccessPointFoundInAuthmodeThreshold => {
            "the network's security does not fit (WPA3 only? it needs WPA2)"
        }
        R::AuthenticationFailed
        | R::FourWayHandshakeTimeout
        | R::HandshakeTimeout
        | R::MicFailure
        | R::AuthenticationExpired => "the key was not accepted (the passphrase? tinybms wifi)",
        R::AssociationFailed | R::ConnectionFailed | R::AssociationTooMany => {
            "the access point refused the station"
        }
        _ => "see the reason in the RTT log",
    }
}

/// Starts Wi-Fi and MQTT when the record names a network and a broker.
pub fn start(
    spawner: Spawner,
    wifi: WIFI<'static>,
    config: &Config,
    bridge: tinybms_firmware::identity::Identity,
) {
    if config.wifi_ssid.is_empty() || config.mqtt_host.is_empty() {
        say(
            Level::Info,
            &[
                "Wi-Fi off: ",
                if config.wifi_ssid.is_empty() {
                    "no wifi_ssid (tinybms wifi PORT --ssid NAME)"
                } else {
                    "no mqtt_host (tinybms mqtt PORT --host HOST)"
                },
            ],
        );
        return;
    }
    esp_alloc::heap_allocator!(#[esp_hal::ram(reclaimed)] size: HEAP_RECLAIMED);
    esp_alloc::heap_allocator!(size: HEAP_MORE);

    let Ok(ssid) = Ssid::try_from(config.wifi_ssid.as_str()) else {
        say(Level::Warn, &["Wi-Fi off: the SSID is not valid"]);
        return;
    };
    let auth = if config.wifi_key.is_empty() {
        AuthenticationMethodConfig::Open
    } else {
        match Password::try_from(config.wifi_key.as_str()) {
            Ok(p) => AuthenticationMethodConfig::WpaWpa2Personal(p),
            Err(_) => {
                say(Level::Warn, &["Wi-Fi off: the key is not valid"]);
                return;
            }
        }
    };
    let station = StationConfig::default()
        .with_ssid(ssid)
        .with_authentication(auth);
    let iface = Interface::station();
    let mac = iface.mac_address();
    let controller = match WifiController::new(
        wifi,
        ControllerConfig::default().with_initial_config(WifiConfig::Station(station)),
    ) {
        Ok(c) => c,
        Err(e) => {
            warn!("Wi-Fi off: the radio did not start: {}", e);
            say(Level::Warn, &["Wi-Fi off: the radio did not start"]);
            return;
        }
    };
    let hostname = hostname(config, mac);
    let mut port = Line::new();
    port.uint(config.mqtt_port.into());
    say(
        Level::Info,
        &[
            "Wi-Fi: joining ",
            config.wifi_ssid.as_str(),
            " as ",
            hostname.as_str(),
            "; MQTT to ",
            config.mqtt_host.as_str(),
            ":",
            port.as_str(),
        ],
    );
    let mut dhcp = DhcpConfig::default();
    dhcp.hostname = Some(hostname.clone());
    // The true RNG is on once the controller runs.
    let rng = Rng::new();
    let seed = (u64::from(rng.random()) << 32) | u64::from(rng.random());
    static RESOURCES: StaticCell<StackResources<3>> = StaticCell::new();
    let (stack, runner) = embassy_net::new(
        iface,
        embassy_net::Config::dhcpv4(dhcp),
        RESOURCES.init(StackResources::new()),
        seed,
    );
    let target = Target::from_config(config, &hostname);
    let settings = Settings::from_config(config);
    spawn(spawner, wifi_task(controller));
    spawn(spawner, net_task(runner));
    spawn(spawner, mqtt_task(stack, target, settings, bridge));
    spawn(spawner, heap_task());
}

/// `hostname`, or `tinybms-` and the last three bytes of the MAC address.
fn hostname(config: &Config, mac: [u8; 6]) -> String<32> {
    if !config.hostname.is_empty() {
        return config.hostname.clone();
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

/// How often the heap's use is logged.
const HEAP_LOG_PERIOD: Duration = Duration::from_secs(600);

/// One line: the heap now and its high-water mark (the figure a run on a unit
/// gives for docs/performance.md).
fn log_heap() {
    let s = esp_alloc::HEAP.stats();
    info!(
        "heap: {=usize} B used, at most {=usize} B so far, of {=usize} B",
        s.current_usage, s.max_usage, s.size
    );
}

#[embassy_executor::task]
async fn heap_task() {
    loop {
        Timer::after(HEAP_LOG_PERIOD).await;
        log_heap();
    }
}

#[embassy_executor::task]
async fn wifi_task(mut controller: WifiController<'static>) {
    let mut backoff = WIFI_BACKOFF_MIN;
    loop {
        match controller.connect_async().await {
            Ok(info) => {
                let mut channel = Line::new();
                channel.uint(info.channel.into());
                say(
                    Level::Info,
                    &[
                        "Wi-Fi up: ",
                        info.ssid.as_str(),
                        ", channel ",
                        channel.as_str(),
                    ],
                );
                let up = Instant::now();
                // The signal now and every RSSI_PERIOD until the link drops.
                // `wait_for_disconnect_async` returns at once when the station
                // is no longer connected, so a disconnect between two waits
                // is not missed.
                let down = loop {
                    hand_rssi(&controller);
                    match select(
                        controller.wait_for_disconnect_async(),
                        Timer::after(RSSI_PERIOD),
                    )
                    .await
                    {
                        Either::First(d) => break d,
                        Either::Second(()) => {}
                    }
                };
                wires::WIFI_RSSI.signal(None);
                wires::wake();
                match down {
                    Ok(d) => {
                        warn!("Wi-Fi down: {}", d.reason);
                        say(Level::Warn, &["Wi-Fi down: ", reason_text(d.reason)]);
                    }
                    Err(e) => {
                        warn!("Wi-Fi down: {}", e);
                        say(Level::Warn, &["Wi-Fi down"]);
                    }
                }
                if up.elapsed() > WIFI_BACKOFF_MAX {
                    backoff = WIFI_BACKOFF_MIN;
                }
            }
            Err(e) => {
                warn!("Wi-Fi: cannot join ({})", e);
                let why = match e {
                    ConnectionError::Failed(d) => reason_text(d.reason),
                    _ => "the driver refused (see the RTT log)",
                };
                let mut secs = Line::new();
                secs.uint(backoff.as_secs());
                say(
                    Level::Warn,
                    &[
                        "Wi-Fi: cannot join (",
                        why,
                        "), next try in ",
                        secs.as_str(),
                        " s",
                    ],
                );
            }
        }
        Timer::after(backoff).await;
        backoff = (backoff * 2).min(WIFI_BACKOFF_MAX);
    }
}

/// The access point's signal, from its last beacon, to the station (what
/// MQTT publishes as the Wi-Fi signal diagnostic); `None` when the driver
/// cannot say.
fn hand_rssi(controller: &WifiController<'static>) {
    let rssi = controller
        .rssi()
        .ok()
        .and_then(|r| i8::try_from(r).ok())
        .filter(|r| *r < 0);
    wires::WIFI_RSSI.signal(rssi);
    wires::wake();
}

#[embassy_executor::task]
async fn net_task(mut runner: Runner<'static, Interface>) {
    runner.run().await
}

/// embassy-time as the session's clock.
struct ChipClock;

impl Clock for ChipClock {
    fn now(&self) -> u64 {
        Instant::now().as_micros()
    }

    async fn sleep_until(&self, t: u64) {
        Timer::at(Instant::from_micros(t)).await
    }
}

/// What the station published, and its events, as the session's feed.
struct ChipFeed {
    published: Receiver<'static, CriticalSectionRawMutex, Published, 1>,
    latest: Published,
}

impl Feed for ChipFeed {
    fn with_view<R>(&mut self, now: u64, f: impl FnOnce(&View<'_>) -> R) -> R {
        if let Some(p) = self.published.try_changed() {
            self.latest = p;
        }
        f(&View::of(&self.latest, now))
    }

    fn next_event(&mut self) -> Option<Event> {
        let e = wires::MQTT_EVENTS.try_receive().ok();
        if e.is_some() {
            // Room again: the station hands on the next one.
            wires::wake();
        }
        e
    }

    async fn changed(&mut self) {
        // A new picture or an event waiting. Both cancel-safe.
        let _ = select(
            self.published.changed(),
            wires::MQTT_EVENTS.ready_to_receive(),
        )
        .await;
    }
}

#[embassy_executor::task]
async fn mqtt_task(
    stack: Stack<'static>,
    target: Target,
    settings: Settings,
    bridge: tinybms_firmware::identity::Identity,
) {
    let Some(published) = wires::PUBLISHED.receiver() else {
        warn!("the published watch has no free receiver slot: no MQTT output");
        return;
    };
    static STATE: StaticCell<TcpClientState<1, TCP_BUFFER, TCP_BUFFER>> = StaticCell::new();
    let mut client = TcpClient::new(stack, STATE.init(TcpClientState::new()));
    client.set_timeout(Some(embassy_time::Duration::from_secs(30)));
    let mut net = StackNet::new(stack, client, ChipClock, |a| {
        info!("IP {} (DHCP)", a);
        let o = a.address().octets();
        let mut l = Line::new();
        l.push("IP ");
        for (i, b) in o.iter().enumerate() {
            if i > 0 {
                l.push(".");
            }
            l.uint((*b).into());
        }
        l.push("/").uint(a.prefix_len().into()).push(" (DHCP)");
        crate::log::line(Level::Info, &l);
    });
    let mut feed = ChipFeed {
        published,
        latest: Published::default(),
    };
    let mut publisher = Publisher::new(settings, &bridge);
    let mut note = |n: Note| {
        wires::MQTT_STATE.signal(n.state());
        wires::wake();
        let mut ms_text = Line::new();
        match n {
            Note::Connected => {
                say(Level::Info, &["MQTT: connected to the broker"]);
                log_heap();
            }
            Note::Disconnected(f, ms) => {
                ms_text.uint(ms.into());
                say(
                    Level::Warn,
                    &[
                        "MQTT: connection lost (",
                        f.reason(),
                        "), reconnecting in ",
                        ms_text.as_str(),
                        " ms",
                    ],
                );
            }
            Note::Failed(f, ms) => {
                ms_text.uint(ms.into());
                say(
                    Level::Warn,
                    &[
                        "MQTT: cannot connect (",
                        f.reason(),
                        "), next try in ",
                        ms_text.as_str(),
                        " ms",
                    ],
                );
            }
            Note::WaitingForBms => say(Level::Info, &["MQTT: waiting for the BMS's serial number"]),
            // For `hello` only.
            Note::Held => {}
        }
    };
    session::run(
        &mut net,
        &ChipClock,
        &mut feed,
        &target,
        &mut publisher,
        &mut note,
    )
    .await
}
