//! Wi-Fi and MQTT (feature `wifi`): the battery in Home Assistant. Publish
//! only, and never in the charge-control path: these tasks read the copy the
//! station publishes ([`wires::PUBLISHED`]: the snapshot with its freshness,
//! the limits the inverter is told, the battery) and its events
//! ([`wires::MQTT_EVENTS`]), and nothing waits on them — a missing network or
//! a bad broker only costs their own reconnects.
//!
//! * `wifi_task` — station mode with the record's SSID and 64-hex pre-shared
//!   key (the ESP Wi-Fi driver takes 64 hex digits as the PSK itself), reconnect
//!   with backoff, one log line per link up/down; and what the station asks for
//!   Improv Wi-Fi (the browser installer, over the host port): a scan, or a join
//!   of a new network — kept only once it has an address, else the stored one
//!   is joined again. The key of an Improv passphrase is derived by the station
//!   (the library), not here. Link changes and results go to the station
//!   ([`wires::WIFI_DONE`]).
//! * `net_task` — embassy-net (DHCP with the bridge's host name).
//! * `mqtt_task` — the library's MQTT session (`tinybms_firmware::mqtt`), the
//!   code the host tests run against mosquitto.

use defmt::{info, warn};
use embassy_executor::Spawner;
use embassy_futures::select::{select, select3, Either, Either3};
use embassy_net::tcp::client::{TcpClient, TcpClientState};
use embassy_net::{DhcpConfig, Runner, Stack, StackResources};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::watch::Receiver;
use embassy_time::{Duration, Instant, Timer};
use esp_hal::peripherals::WIFI;
use esp_hal::rng::Rng;
use esp_radio::wifi::scan::ScanConfig;
use esp_radio::wifi::sta::StationConfig;
use esp_radio::wifi::{
    AuthenticationMethod, AuthenticationMethodConfig, Config as WifiConfig, ConnectionError,
    ControllerConfig, DisconnectReason, Interface, Password, Ssid, WifiController,
};
use heapless::String;
use protocol_core::events::Event;
use static_cell::StaticCell;
use tinybms_firmware::backoff::Backoff;
use tinybms_firmware::config::Config;
use tinybms_firmware::improv::{JoinFailure, Network, WifiLink, WifiRequest, SCAN_MAX};
use tinybms_firmware::mqtt::net::StackNet;
use tinybms_firmware::mqtt::publisher::{Publisher, View};
use tinybms_firmware::mqtt::session::{self, Clock, Feed, Note, Target};
use tinybms_firmware::mqtt::Settings;
use tinybms_firmware::station::Published;
use tinybms_firmware::text::Line;
use tinybms_firmware::wifi::{self as wifi_rules, Cause};
use tinybms_firmware::Level;

use crate::{spawn, wires};

/// Heap for the Wi-Fi driver and the MQTT client's packet buffers, bytes: the
/// station needs 47-57 KiB (esp-radio's documentation), MQTT a few.
const HEAP_RECLAIMED: usize = 64 * 1024;
const HEAP_MORE: usize = 36 * 1024;

/// TCP buffers of the MQTT connection, bytes each way.
const TCP_BUFFER: usize = 2048;

/// The library's rules ([`tinybms_firmware::wifi`]) as driver durations.
const RSSI_PERIOD: Duration = Duration::from_micros(wifi_rules::RSSI_PERIOD_US);
const DHCP_TIMEOUT: Duration = Duration::from_micros(wifi_rules::DHCP_TIMEOUT_US);
const JOIN_TIME: Duration = Duration::from_micros(wifi_rules::JOIN_TIME_US);
const SCAN_TIME: Duration = Duration::from_micros(wifi_rules::SCAN_TIME_US);
const MQTT_SOCKET_TIMEOUT: Duration = Duration::from_micros(session::SOCKET_TIMEOUT_US);

/// One log line (defmt and the host link's `log` lines) from pieces.
fn say(level: Level, pieces: &[&str]) {
    let mut l = Line::new();
    for p in pieces {
        l.push(p);
    }
    crate::log::line(level, &l);
}

/// The driver's disconnect reason sorted into the library's causes (what
/// the log says and Improv answers come from [`Cause`]; defmt logs the exact
/// reason).
fn cause(r: DisconnectReason) -> Cause {
    use DisconnectReason as R;
    match r {
        R::NoAccessPointFound | R::NoAccessPointFoundInRssiThreshold | R::BeaconTimeout => {
            Cause::NotFound
        }
        R::NoAccessPointFoundWithCompatibleSecurity | R::NoAccessPointFoundInAuthmodeThreshold => {
            Cause::Security
        }
        R::AuthenticationFailed
        | R::FourWayHandshakeTimeout
        | R::HandshakeTimeout
        | R::MicFailure
        | R::AuthenticationExpired => Cause::KeyRefused,
        R::AssociationFailed | R::ConnectionFailed | R::AssociationTooMany => Cause::Refused,
        _ => Cause::Other,
    }
}

/// The station config for `ssid` with `key` (64 hex digits; empty: open), or
/// `None` when the driver would not take them.
fn station_config(ssid: &str, key: &str) -> Option<StationConfig> {
    let ssid = Ssid::try_from(ssid).ok()?;
    let auth = if key.is_empty() {
        AuthenticationMethodConfig::Open
    } else {
        AuthenticationMethodConfig::WpaWpa2Personal(Password::try_from(key).ok()?)
    };
    Some(
        StationConfig::default()
            .with_ssid(ssid)
            .with_authentication(auth),
    )
}

/// Starts the radio, the IP stack and the Wi-Fi task (which joins the
/// record's network, and any network Improv Wi-Fi gives it over the host
/// port), and MQTT when the record names a broker. Returns the bridge's
/// name on the network (Improv shows it).
pub fn start(
    spawner: Spawner,
    wifi: WIFI<'static>,
    config: &Config,
    bridge: tinybms_firmware::identity::Identity,
) -> Option<String<32>> {
    esp_alloc::heap_allocator!(#[esp_hal::ram(reclaimed)] size: HEAP_RECLAIMED);
    esp_alloc::heap_allocator!(size: HEAP_MORE);

    let stored = if config.wifi_ssid.is_empty() {
        say(
            Level::Info,
            &["Wi-Fi: no network yet (the browser installer, or tinybms wifi PORT --ssid NAME)"],
        );
        None
    } else {
        let c = station_config(config.wifi_ssid.as_str(), config.wifi_key.as_str());
        if c.is_none() {
            say(
                Level::Warn,
                &["Wi-Fi: the stored network or key is not valid"],
            );
        }
        c
    };
    let iface = Interface::station();
    let mac = iface.mac_address();
    let controller = match WifiController::new(wifi, ControllerConfig::default()) {
        Ok(c) => c,
        Err(e) => {
            warn!("Wi-Fi off: the radio did not start: {}", e);
            say(Level::Warn, &["Wi-Fi off: the radio did not start"]);
            return None;
        }
    };
    let hostname = wifi_rules::hostname(config.hostname.as_str(), mac);
    if stored.is_some() {
        say(
            Level::Info,
            &[
                "Wi-Fi: joining ",
                config.wifi_ssid.as_str(),
                " as ",
                hostname.as_str(),
            ],
        );
    }
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
    spawn(spawner, wifi_task(controller, stack, stored));
    spawn(spawner, net_task(runner));
    if config.mqtt_host.is_empty() {
        say(
            Level::Info,
            &["MQTT off: no mqtt_host (tinybms mqtt PORT --host HOST)"],
        );
    } else {
        let mut port = Line::new();
        port.uint(config.mqtt_port.into());
        say(
            Level::Info,
            &["MQTT to ", config.mqtt_host.as_str(), ":", port.as_str()],
        );
        let target = Target::from_config(config, &hostname);
        let settings = Settings::from_config(config);
        spawn(spawner, mqtt_task(stack, target, settings, bridge));
    }
    spawn(spawner, heap_task());
    Some(hostname)
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

/// Hands the station what the Wi-Fi side did.
fn tell(done: wires::WifiDone) {
    // The station takes them at every pass; two fit (a result and a link).
    let _ = wires::WIFI_DONE.try_send(done);
    wires::wake();
}

/// What a failed connect means for the owner.
fn failure(e: &ConnectionError) -> JoinFailure {
    match e {
        ConnectionError::Failed(d) => cause(d.reason).failure(),
        _ => JoinFailure::Other,
    }
}

/// Joins the network the controller is configured for and waits for an
/// address (DHCP).
async fn join(
    controller: &mut WifiController<'static>,
    stack: Stack<'static>,
) -> Result<[u8; 4], JoinFailure> {
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
        }
        Err(e) => {
            warn!("Wi-Fi: cannot join ({})", e);
            return Err(failure(&e));
        }
    }
    match embassy_time::with_timeout(DHCP_TIMEOUT, stack.wait_config_up()).await {
        Ok(()) => Ok(stack
            .config_v4()
            .map_or([0; 4], |c| c.address.address().octets())),
        Err(_) => Err(JoinFailure::NoAddress),
    }
}

/// Does what the station asked: a scan, or a join of a new network (kept
/// only when it works; the station stores it then). Returns whether the
/// station is joined afterwards (`connected`: before).
async fn serve(
    req: WifiRequest,
    controller: &mut WifiController<'static>,
    stack: Stack<'static>,
    current: &mut Option<StationConfig>,
    connected: bool,
) -> bool {
    match req {
        WifiRequest::Scan => {
            let config = ScanConfig::default().with_max(SCAN_MAX);
            let found = embassy_time::with_timeout(SCAN_TIME, controller.scan_async(&config)).await;
            let mut list = heapless::Vec::new();
            if let Ok(Ok(aps)) = found {
                for ap in aps {
                    let Ok(ssid) = String::try_from(ap.ssid.as_str()) else {
                        continue;
                    };
                    let secured =
                        !matches!(ap.auth_method, None | Some(AuthenticationMethod::None));
                    let _ = list.push(Network {
                        ssid,
                        rssi: ap.signal_strength,
                        secured,
                    });
                }
            }
            tell(wires::WifiDone::Scanned(list));
            connected
        }
        WifiRequest::Join { ssid, psk } => {
            let Some(wanted) = station_config(ssid.as_str(), psk.as_str()) else {
                tell(wires::WifiDone::Joined(Err(JoinFailure::Other)));
                return connected;
            };
            // Returns at once when neither connected nor connecting.
            let _ = controller.disconnect_async().await;
            tell(wires::WifiDone::Link(WifiLink::Down));
            let result = match controller.set_config(&WifiConfig::Station(wanted.clone())) {
                Ok(()) => embassy_time::with_timeout(JOIN_TIME, join(controller, stack))
                    .await
                    .unwrap_or(Err(JoinFailure::NotFound)),
                Err(_) => Err(JoinFailure::Other),
            };
            match result {
                Ok(ip) => {
                    *current = Some(wanted);
                    tell(wires::WifiDone::Joined(Ok(ip)));
                    true
                }
                Err(f) => {
                    let _ = controller.disconnect_async().await;
                    tell(wires::WifiDone::Joined(Err(f)));
                    false
                }
            }
        }
    }
}

#[embassy_executor::task]
async fn wifi_task(
    mut controller: WifiController<'static>,
    stack: Stack<'static>,
    mut current: Option<StationConfig>,
) {
    let mut backoff = Backoff::new();
    let mut connected = false;
    // When the link came up (the backoff starts over after a long one).
    let mut up = Instant::now();
    loop {
        if connected {
            // The signal now and every RSSI_PERIOD until the link drops.
            // `wait_for_disconnect_async` returns at once when the station is
            // no longer connected, so a disconnect between two waits is not
            // missed.
            hand_rssi(&controller);
            match select3(
                controller.wait_for_disconnect_async(),
                wires::WIFI_REQUEST.receive(),
                Timer::after(RSSI_PERIOD),
            )
            .await
            {
                Either3::First(d) => {
                    match d {
                        Ok(d) => {
                            warn!("Wi-Fi down: {}", d.reason);
                            say(Level::Warn, &["Wi-Fi down: ", cause(d.reason).text()]);
                        }
                        Err(e) => {
                            warn!("Wi-Fi down: {}", e);
                            say(Level::Warn, &["Wi-Fi down"]);
                        }
                    }
                    wires::WIFI_RSSI.signal(None);
                    tell(wires::WifiDone::Link(WifiLink::Down));
                    connected = false;
                    backoff.ended_after(up.elapsed().as_micros());
                }
                Either3::Second(req) => {
                    connected = serve(req, &mut controller, stack, &mut current, true).await;
                    up = Instant::now();
                }
                Either3::Third(()) => {}
            }
            continue;
        }
        let Some(config) = current.clone() else {
            tell(wires::WifiDone::Link(WifiLink::Off));
            let req = wires::WIFI_REQUEST.receive().await;
            connected = serve(req, &mut controller, stack, &mut current, false).await;
            up = Instant::now();
            continue;
        };
        tell(wires::WifiDone::Link(WifiLink::Down));
        if controller.set_config(&WifiConfig::Station(config)).is_err() {
            say(
                Level::Warn,
                &["Wi-Fi: the driver refused the stored network"],
            );
            current = None;
            continue;
        }
        match select(join(&mut controller, stack), wires::WIFI_REQUEST.receive()).await {
            Either::First(Ok(ip)) => {
                connected = true;
                up = Instant::now();
                tell(wires::WifiDone::Link(WifiLink::Up(ip)));
            }
            Either::First(Err(f)) => {
                let wait = backoff.wait();
                let mut secs = Line::new();
                secs.uint(wait / tinybms_firmware::SECOND);
                say(
                    Level::Warn,
                    &[
                        "Wi-Fi: cannot join (",
                        f.text(),
                        "), next try in ",
                        secs.as_str(),
                        " s",
                    ],
                );
                if let Either::Second(req) = select(
                    Timer::after(Duration::from_micros(wait)),
                    wires::WIFI_REQUEST.receive(),
                )
                .await
                {
                    connected = serve(req, &mut controller, stack, &mut current, false).await;
                    up = Instant::now();
                }
            }
            Either::Second(req) => {
                // A join under way is cancelled (the request is newer).
                let _ = controller.disconnect_async().await;
                connected = serve(req, &mut controller, stack, &mut current, false).await;
                up = Instant::now();
            }
        }
    }
}

/// The access point's signal, from its last beacon, to the station (what
/// MQTT publishes as the Wi-Fi signal diagnostic); `None` when the driver
/// cannot say.
fn hand_rssi(controller: &WifiController<'static>) {
    let rssi = controller.rssi().ok().and_then(wifi_rules::rssi);
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
    client.set_timeout(Some(MQTT_SOCKET_TIMEOUT));
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
