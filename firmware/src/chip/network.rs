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
use embassy_sync::signal::Signal;
use embassy_sync::watch::Receiver;
use embassy_time::{Duration, Instant, Timer};
use esp_hal::peripherals::WIFI;
use esp_hal::rng::Rng;
use esp_radio::wifi::scan::ScanConfig;
use esp_radio::wifi::sta::StationConfig;
use esp_radio::wifi::{
    AuthenticationMethod, AuthenticationMethodConfig, Config as WifiConfig, ConnectionError,
    ControllerConfig, DisconnectReason, Interface, Password, Ssid, WifiController, WifiError,
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
use tinybms_firmware::wifi::{self as wifi_rules, Bringup, Cause, Radio, RadioMark, Said};
use tinybms_firmware::Level;

use crate::{spawn, wires};

/// The library's sizes ([`tinybms_firmware::wifi`], the MQTT session's).
const HEAP_RECLAIMED: usize = wifi_rules::HEAP_RECLAIMED;
const HEAP_MORE: usize = wifi_rules::HEAP_MORE;
const TCP_BUFFER: usize = session::TCP_BUFFER;

/// The library's rules ([`tinybms_firmware::wifi`]) as driver durations.
const RSSI_PERIOD: Duration = Duration::from_micros(wifi_rules::RSSI_PERIOD_US);
const DHCP_TIMEOUT: Duration = Duration::from_micros(wifi_rules::DHCP_TIMEOUT_US);
const JOIN_TIME: Duration = Duration::from_micros(wifi_rules::JOIN_TIME_US);
const SCAN_TIME: Duration = Duration::from_micros(wifi_rules::SCAN_TIME_US);
const MQTT_SOCKET_TIMEOUT: Duration = Duration::from_micros(session::SOCKET_TIMEOUT_US);

/// One log line (defmt and the host link's `log` lines), the library's words.
fn say(said: Said<'_>) {
    let mut l = Line::new();
    said.write(&mut l);
    crate::log::line(
        if said.warns() {
            Level::Warn
        } else {
            Level::Info
        },
        &l,
    );
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

/// What the Wi-Fi side starts with, handed to [`radio_task`].
struct Plan {
    iface: Interface,
    stored: Option<StationConfig>,
    hostname: String<32>,
    mqtt: Option<(Target, Settings)>,
    bridge: tinybms_firmware::identity::Identity,
}

/// Prepares Wi-Fi and MQTT and hands the radio's start to [`radio_task`],
/// which starts the driver on a thread of its own below the bridge's (the
/// station, CAN and USB tasks run first and never wait for it), unless the
/// last start never finished (the chip's RTC memory says so:
/// [`RadioMark`]): then the radio stays off. Returns the bridge's name on the
/// network (Improv shows it) at once.
pub fn start(
    spawner: Spawner,
    wifi: WIFI<'static>,
    config: &Config,
    bridge: tinybms_firmware::identity::Identity,
) -> Option<String<32>> {
    esp_alloc::heap_allocator!(#[esp_hal::ram(reclaimed)] size: HEAP_RECLAIMED);
    esp_alloc::heap_allocator!(size: HEAP_MORE);

    let iface = Interface::station();
    let hostname = wifi_rules::hostname(config.hostname.as_str(), iface.mac_address());
    if mark(RadioMark::at_boot) == Bringup::HoldOff {
        radio(Radio::HeldOff);
        return Some(hostname);
    }
    let stored = if config.wifi_ssid.is_empty() {
        say(Said::NoNetwork);
        None
    } else {
        let c = station_config(config.wifi_ssid.as_str(), config.wifi_key.as_str());
        if c.is_none() {
            say(Said::StoredInvalid);
        } else {
            say(Said::Joining(config.wifi_ssid.as_str(), hostname.as_str()));
        }
        c
    };
    let mqtt = if config.mqtt_host.is_empty() {
        say(Said::MqttOff);
        None
    } else {
        Some((
            Target::from_config(config, &hostname),
            Settings::from_config(config),
        ))
    };
    RADIO_PERIPHERAL.lock(|p| p.set(Some(wifi)));
    spawn(
        spawner,
        radio_task(
            spawner,
            Plan {
                iface,
                stored,
                hostname: hostname.clone(),
                mqtt,
                bridge,
            },
        ),
    );
    Some(hostname)
}

/// The radio's mark in RTC memory: kept across a reset (a watchdog's, a
/// panic's), zeroed by esp-hal's start-up only after a power-on.
#[esp_hal::ram(unstable(rtc_fast, persistent))]
static mut RADIO_MARK: [u32; RadioMark::WORDS] = [0; RadioMark::WORDS];

/// Reads the mark, lets the library's rule change it, writes it back.
fn mark<R>(f: impl FnOnce(&mut RadioMark) -> R) -> R {
    critical_section::with(|_| {
        // SAFETY: the mark is touched only here, inside a critical section.
        let cell = unsafe { &mut *core::ptr::addr_of_mut!(RADIO_MARK) };
        let mut m = RadioMark(*cell);
        let r = f(&mut m);
        *cell = m.0;
        r
    })
}

/// Tells the station where the radio's start stands (it logs it, and
/// `hello` says it).
fn radio(r: Radio) {
    wires::RADIO.signal(r);
    wires::wake();
}

/// The Wi-Fi peripheral, handed from `start` to the radio's thread.
static RADIO_PERIPHERAL: embassy_sync::blocking_mutex::Mutex<
    CriticalSectionRawMutex,
    core::cell::Cell<Option<WIFI<'static>>>,
> = embassy_sync::blocking_mutex::Mutex::new(core::cell::Cell::new(None));

/// What the radio's thread made of the driver.
static CONTROLLER: Signal<CriticalSectionRawMutex, Result<WifiController<'static>, WifiError>> =
    Signal::new();

/// esp-rtos priority of the radio's start thread: below the thread that runs
/// the bridge's tasks (`MAIN_PRIORITY`, main.rs) and below the radio
/// driver's own threads.
const RADIO_START_PRIORITY: u32 = 1;
/// Its stack, bytes (from the heap; freed when the thread ends).
const RADIO_START_STACK: usize = wifi_rules::RADIO_START_STACK;

/// The radio's start thread: the driver's set-up (the RF calibration
/// included), which blocks for as long as it takes; then it hands the
/// controller over and ends.
extern "C" fn radio_start_thread(_: *mut core::ffi::c_void) {
    if let Some(wifi) = RADIO_PERIPHERAL.lock(|p| p.take()) {
        CONTROLLER.signal(WifiController::new(wifi, ControllerConfig::default()));
    }
    // SAFETY: `None` is the current task, which the scheduler ends.
    unsafe { esp_radio_rtos_driver::schedule_task_deletion(None) };
    loop {
        esp_radio_rtos_driver::yield_task();
    }
}

/// Starts the radio on its own thread, waits for it (saying so when it is
/// late), then starts the IP stack, the Wi-Fi task and MQTT.
#[embassy_executor::task]
async fn radio_task(spawner: Spawner, plan: Plan) {
    radio(Radio::Starting);
    mark(RadioMark::starting);
    // SAFETY: the thread's parameter is unused; the function never returns
    // (it ends itself).
    unsafe {
        esp_radio_rtos_driver::task_create(
            "radio start",
            radio_start_thread,
            core::ptr::null_mut(),
            RADIO_START_PRIORITY,
            None,
            RADIO_START_STACK,
        );
    }
    let started = match select(
        CONTROLLER.wait(),
        Timer::after(Duration::from_micros(wifi_rules::RADIO_START_LIMIT_US)),
    )
    .await
    {
        Either::First(r) => r,
        Either::Second(()) => {
            radio(Radio::Late);
            CONTROLLER.wait().await
        }
    };
    mark(RadioMark::started);
    let controller = match started {
        Ok(c) => c,
        Err(e) => {
            warn!("the radio did not start: {}", e);
            radio(Radio::Failed);
            return;
        }
    };
    radio(Radio::Up);
    let Plan {
        iface,
        stored,
        hostname,
        mqtt,
        bridge,
    } = plan;
    let mut dhcp = DhcpConfig::default();
    dhcp.hostname = Some(hostname);
    // The true RNG is on once the controller runs.
    let rng = Rng::new();
    let seed = (u64::from(rng.random()) << 32) | u64::from(rng.random());
    // DHCP, DNS, the MQTT session's socket and the update port's.
    static RESOURCES: StaticCell<StackResources<4>> = StaticCell::new();
    let (stack, runner) = embassy_net::new(
        iface,
        embassy_net::Config::dhcpv4(dhcp),
        RESOURCES.init(StackResources::new()),
        seed,
    );
    spawn(spawner, wifi_task(controller, stack, stored));
    spawn(spawner, net_task(runner));
    if let Some((target, settings)) = mqtt {
        say(Said::MqttTo(target.host.as_str(), target.port));
        spawn(spawner, mqtt_task(stack, target, settings, bridge));
    }
    spawn(spawner, update_port_task(stack));
    spawn(spawner, heap_task());
}

/// The update port (`tinybms_firmware::update::TCP_PORT`): one connection at
/// a time, its bytes to the station task and the station's lines back
/// (`hello` and the `update_…` commands: the station's update-port link).
/// A connection silent for 60 s is closed; the transfer's own stall rule
/// (30 s) has abandoned it by then.
#[embassy_executor::task]
async fn update_port_task(stack: Stack<'static>) {
    use embassy_net::tcp::TcpSocket;
    use embedded_io_async::Write as _;
    let mut rx = [0u8; 1024];
    let mut tx = [0u8; 2048];
    let mut inbox = [0u8; 256];
    let mut outbox = [0u8; 512];
    loop {
        stack.wait_config_up().await;
        let mut socket = TcpSocket::new(stack, &mut rx, &mut tx);
        socket.set_timeout(Some(Duration::from_secs(60)));
        if socket
            .accept(tinybms_firmware::update::TCP_PORT)
            .await
            .is_err()
        {
            Timer::after(Duration::from_secs(1)).await;
            continue;
        }
        info!("update port: a connection");
        wires::UPDATE_TX.clear();
        wires::UPDATE_CONNECTION.signal(true);
        wires::WAKE.signal(());
        loop {
            match select(socket.read(&mut inbox), wires::UPDATE_TX.read(&mut outbox)).await {
                Either::First(Ok(0) | Err(_)) => break,
                Either::First(Ok(n)) => {
                    wires::UPDATE_RX
                        .write_all(inbox.get(..n).unwrap_or(&[]))
                        .await;
                    wires::WAKE.signal(());
                }
                Either::Second(n) => {
                    if socket
                        .write_all(outbox.get(..n).unwrap_or(&[]))
                        .await
                        .is_err()
                    {
                        break;
                    }
                }
            }
        }
        socket.close();
        let _ = socket.flush().await;
        socket.abort();
        wires::UPDATE_CONNECTION.signal(false);
        wires::WAKE.signal(());
        info!("update port: the connection closed");
    }
}

/// How often the heap's use is logged (the library's).
const HEAP_LOG_PERIOD: Duration = Duration::from_micros(wifi_rules::HEAP_LOG_PERIOD_US);

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
        Ok(info) => say(Said::Up(info.ssid.as_str(), info.channel)),
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
                            say(Said::Down(Some(cause(d.reason))));
                        }
                        Err(e) => {
                            warn!("Wi-Fi down: {}", e);
                            say(Said::Down(None));
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
            say(Said::DriverRefused);
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
                say(Said::CannotJoin(f, wait / tinybms_firmware::SECOND));
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
        say(Said::Address(a.address().octets(), a.prefix_len()));
    });
    let mut feed = ChipFeed {
        published,
        latest: Published::default(),
    };
    let mut publisher = Publisher::new(settings, &bridge);
    let mut note = |n: Note| {
        wires::MQTT_STATE.signal(n.state());
        wires::wake();
        if let Some(level) = n.level() {
            let mut l = Line::new();
            n.write(&mut l);
            crate::log::line(level, &l);
        }
        if n == Note::Connected {
            log_heap();
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
