//! The MQTT connection (feature `mqtt`): rust-mqtt (MQTT 5) over any byte
//! stream, driven by the [`Publisher`]. The same code runs on the chip (over
//! embassy-net on Wi-Fi) and on the desktop (over a TCP socket, or embassy-net
//! on a TAP device in the end-to-end test).
//!
//! [`run`] never returns: connect (a TCP connection, then MQTT CONNECT with a
//! retained will `offline` on the availability topic), subscribe to Home
//! Assistant's status, publish what the publisher hands out, keep the
//! connection alive, and on any failure reconnect after a backoff ([`crate::backoff`]: 1 s,
//! doubling up to 60 s). Every wait is bounded by a timeout, so a broker that
//! stalls, refuses, drops the connection or sends garbage costs a reconnect,
//! never a hang and never a panic. Nothing here touches the bridge: it reads
//! the telemetry through a [`Feed`].

extern crate alloc;

use core::future::Future;
use core::num::NonZero;

use embassy_futures::select::{select, select3, Either, Either3};
use heapless::String;
use protocol_core::events::Event as BmsEvent;
use rust_mqtt::buffer::AllocBuffer;
use rust_mqtt::client::event::Event;
use rust_mqtt::client::options::{
    ConnectOptions, DisconnectOptions, PublicationOptions, SubscriptionOptions, TopicReference,
    WillOptions,
};
use rust_mqtt::client::Client;
use rust_mqtt::config::{KeepAlive, SessionExpiryInterval};
use rust_mqtt::types::{MqttBinary, MqttString, ReasonCode, TopicFilter, TopicName};
use rust_mqtt::Bytes;

use super::publisher::{Publisher, View};
use super::{device_topic, ha_status_topic, Identity, PAYLOAD_MAX, TOPIC_MAX};
use crate::config::Config;
use crate::{Instant, MS, SECOND};

/// Longest a TCP connect (with the name lookup) may take.
pub const CONNECT_TIMEOUT_US: Instant = 10 * SECOND;
/// Longest the broker may take to answer CONNECT or SUBSCRIBE.
pub const ANSWER_TIMEOUT_US: Instant = 10 * SECOND;
/// Longest one message may take to write.
pub const WRITE_TIMEOUT_US: Instant = 10 * SECOND;
/// Longest the rest of a packet may take once its header came.
pub const BODY_TIMEOUT_US: Instant = 5 * SECOND;
/// Longest a TCP socket may stay silent before the stack gives it up: past
/// the longest write and answer waits above, so those decide first.
pub const SOCKET_TIMEOUT_US: Instant = 30 * SECOND;
/// A connection the broker drops sooner than this after it came up counts as
/// dropped at once.
pub const QUICK_DROP_US: Instant = 10 * SECOND;
/// Connections dropped at once in a row that mean another client uses the
/// client id.
pub const QUICK_DROPS: u8 = 3;
/// Longest the session waits for new telemetry before it looks again (so a
/// BMS link that goes quiet turns the availability `offline` on time).
pub const IDLE_WAKE_US: Instant = SECOND;

/// Why the network could not connect.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum NetError {
    /// The host name did not resolve.
    Dns,
    /// The connection was refused, reset or could not be made.
    Connect,
    /// No network (no link, no address).
    NoNetwork,
}

/// Opens byte streams to the broker.
pub trait Network {
    /// One connection (it may borrow the network, e.g. a socket from its pool).
    type Conn<'a>: embedded_io_async::Read + embedded_io_async::Write
    where
        Self: 'a;
    /// A TCP connection to `host:port` (a name is resolved first).
    fn connect<'a>(
        &'a mut self,
        host: &str,
        port: u16,
    ) -> impl Future<Output = Result<Self::Conn<'a>, NetError>>;
}

/// Time.
pub trait Clock {
    /// Now, µs (the bridge's time base).
    fn now(&self) -> Instant;
    /// Completes at `t` (at once when past). Cancel-safe.
    fn sleep_until(&self, t: Instant) -> impl Future<Output = ()>;
}

/// What the session reads of the bridge: copies, never a borrow of the
/// bridge's own state.
pub trait Feed {
    /// The latest telemetry, as the publisher sees it (its age computed at `now`).
    fn with_view<R>(&mut self, now: Instant, f: impl FnOnce(&View<'_>) -> R) -> R;
    /// A new BMS event, oldest first.
    fn next_event(&mut self) -> Option<BmsEvent>;
    /// Completes when new telemetry or an event may be there. Cancel-safe.
    fn changed(&mut self) -> impl Future<Output = ()>;
}

/// What the connection's log says (one line each).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Note {
    /// Connected to the broker (CONNACK), announcing this BMS.
    Connected,
    /// The connection has held [`QUICK_DROP_US`]: not one the broker drops at
    /// once (no client with the same id took it over).
    Held,
    /// The connection ended: why, and the delay before the next attempt, ms.
    Disconnected(Failure, u32),
    /// An attempt failed: why, and the delay before the next one, ms.
    Failed(Failure, u32),
    /// Waiting for the BMS's serial number before connecting.
    WaitingForBms,
}

impl Note {
    /// The log line's words.
    pub fn write(&self, out: &mut crate::log_line::Line) {
        match self {
            Self::Connected => {
                out.push("MQTT: connected to the broker");
            }
            Self::Held => {
                out.push("MQTT: the connection holds");
            }
            Self::Disconnected(f, ms) => {
                out.push("MQTT: connection lost (")
                    .push(f.reason())
                    .push("), reconnecting in ")
                    .uint(u64::from(*ms))
                    .push(" ms");
            }
            Self::Failed(f, ms) => {
                out.push("MQTT: cannot connect (")
                    .push(f.reason())
                    .push("), next try in ")
                    .uint(u64::from(*ms))
                    .push(" ms");
            }
            Self::WaitingForBms => {
                out.push("MQTT: waiting for the BMS's serial number");
            }
        }
    }

    /// The log line's level; `None`: the chip does not log it (it only
    /// changes what `hello` says).
    pub const fn level(&self) -> Option<crate::Level> {
        match self {
            Self::Held => None,
            Self::Connected | Self::WaitingForBms => Some(crate::Level::Info),
            Self::Disconnected(..) | Self::Failed(..) => Some(crate::Level::Warn),
        }
    }

    /// Where the connection stands after this note (`hello` says it).
    pub const fn state(&self) -> super::MqttState {
        use super::MqttState as S;
        match self {
            Self::Connected => S::Connected,
            Self::Held => S::Held,
            Self::WaitingForBms => S::WaitingForBms,
            Self::Disconnected(Failure::TakenOver, _) | Self::Failed(Failure::TakenOver, _) => {
                S::ClientIdTaken
            }
            Self::Disconnected(..) => S::Reconnecting,
            Self::Failed(..) => S::CannotConnect,
        }
    }
}

/// Why a connection attempt or a connection ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Failure {
    /// The network could not connect.
    Net(NetError),
    /// The broker did not answer in time.
    Timeout,
    /// The broker refused the login: its CONNACK says "bad user name or
    /// password" (0x86) or "not authorized" (0x87, what mosquitto answers to
    /// a wrong password, and to no login where it needs one).
    Login,
    /// The broker refused the connection for another reason (banned, a
    /// client id it does not take, busy, …).
    Refused,
    /// The broker sent something that is not MQTT, or broke the protocol.
    Protocol,
    /// The connection broke (closed, reset, a write that failed).
    Connection,
    /// The BMS is another one: reconnecting with its identity.
    NewBms,
    /// Another client uses the same client id: the broker ended the session
    /// saying so (MQTT 5 reason 0x8E), or closed connections that had come up
    /// within [`QUICK_DROP_US`] [`QUICK_DROPS`] times in a row (what this
    /// session sees of mosquitto 2.0.11 when another client takes its id).
    /// Two bridges with one host name, or a try-out beside a bridge; a link
    /// that drops every connection at once looks the same, so the words
    /// say "probably".
    TakenOver,
}

impl Failure {
    /// In a few words.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::Net(NetError::Dns) => "the broker's name does not resolve",
            Self::Net(NetError::Connect) => "the broker refuses the TCP connection",
            Self::Net(NetError::NoNetwork) => "no network",
            Self::Timeout => "the broker does not answer",
            Self::Login => {
                "the broker refused the login: wrong or missing mqtt_user / mqtt_password"
            }
            Self::Refused => "the broker refused the connection",
            Self::Protocol => "the broker broke the protocol",
            Self::Connection => "the connection broke",
            Self::NewBms => "another BMS: reconnecting",
            Self::TakenOver => {
                "another client uses this client id; give each bridge its own hostname"
            }
        }
    }
}

/// The TCP buffers of the broker's connection on the chip, bytes each way.
pub const TCP_BUFFER: usize = 2048;

/// Where to connect and as whom (the record's network fields).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    /// Broker host.
    pub host: String<64>,
    /// Broker port.
    pub port: u16,
    /// User name (empty: none).
    pub user: String<32>,
    /// Password (empty: none).
    pub password: String<64>,
    /// MQTT client id.
    pub client_id: String<32>,
}

impl Target {
    /// From the configuration record; `client_id` names the bridge (its host
    /// name).
    pub fn from_config(c: &Config, client_id: &str) -> Self {
        let mut id = String::new();
        for ch in client_id.chars() {
            if id.push(ch).is_err() {
                break;
            }
        }
        Self {
            host: c.mqtt_host.clone(),
            port: c.mqtt_port,
            user: c.mqtt_user.clone(),
            password: c.mqtt_password.clone(),
            client_id: id,
        }
    }
}

type Mqtt<'c, N> = Client<'static, 'c, N, AllocBuffer, 1, 1, 1, 1, 0, 0, 0>;

/// `f` unless `us` pass first.
async fn timeout<C: Clock, F: Future>(clock: &C, us: Instant, f: F) -> Option<F::Output> {
    let end = clock.now().saturating_add(us);
    match select(f, clock.sleep_until(end)).await {
        Either::First(v) => Some(v),
        Either::Second(()) => None,
    }
}

/// Runs the MQTT output for ever (see the module documentation). `note` gets
/// one call per line the log should say.
pub async fn run<N: Network, C: Clock, F: Feed>(
    net: &mut N,
    clock: &C,
    feed: &mut F,
    target: &Target,
    publisher: &mut Publisher,
    note: &mut dyn FnMut(Note),
) -> ! {
    let mut backoff = crate::backoff::Backoff::new();
    let mut waiting_noted = false;
    let mut quick_drops: u8 = 0;
    loop {
        // One device per BMS: nothing to announce before its serial is known.
        let identity = loop {
            let now = clock.now();
            if let Some(id) = feed.with_view(now, |v| v.identity) {
                break id;
            }
            if !waiting_noted {
                waiting_noted = true;
                note(Note::WaitingForBms);
            }
            let _ = timeout(clock, IDLE_WAKE_US, feed.changed()).await;
        };
        waiting_noted = false;
        let mut result = connection(net, clock, feed, target, publisher, identity, note).await;
        publisher.disconnected();
        // The broker closing a connection again and again right after it
        // came up: another client with this id takes it over each time.
        match result {
            Ok((Failure::Connection, up_for)) if up_for < QUICK_DROP_US => {
                quick_drops = quick_drops.saturating_add(1);
                if quick_drops >= QUICK_DROPS {
                    result = Ok((Failure::TakenOver, up_for));
                }
            }
            _ => quick_drops = 0,
        }
        // A connection that held a while starts the backoff afresh.
        if let Ok((_, up_for)) = result {
            backoff.ended_after(up_for);
        }
        let wait = backoff.wait();
        let delay_ms = (wait / MS) as u32;
        note(match result {
            Ok((f, _)) => Note::Disconnected(f, delay_ms),
            Err(f) => Note::Failed(f, delay_ms),
        });
        clock.sleep_until(clock.now().saturating_add(wait)).await;
    }
}

/// One connection, from TCP connect to its end: `Ok((why it ended, how long
/// it was up))` once it was up, `Err(why)` when it never came up.
async fn connection<N: Network, C: Clock, F: Feed>(
    net: &mut N,
    clock: &C,
    feed: &mut F,
    target: &Target,
    publisher: &mut Publisher,
    identity: Identity,
    note: &mut dyn FnMut(Note),
) -> Result<(Failure, Instant), Failure> {
    let conn = match timeout(
        clock,
        CONNECT_TIMEOUT_US,
        net.connect(&target.host, target.port),
    )
    .await
    {
        None => return Err(Failure::Timeout),
        Some(Err(e)) => return Err(Failure::Net(e)),
        Some(Ok(c)) => c,
    };
    let mut buffer = AllocBuffer;
    let mut client: Mqtt<'_, N::Conn<'_>> = Client::new(&mut buffer);
    let settings = publisher.settings().clone();
    let mut avail = String::<TOPIC_MAX>::new();
    let mut status = String::<TOPIC_MAX>::new();
    if !device_topic(&mut avail, &settings, &identity, "availability")
        || !ha_status_topic(&mut status, &settings)
    {
        return Err(Failure::Protocol);
    }
    let will_topic = MqttString::from_str(&avail).ok().and_then(TopicName::new);
    let will_msg = MqttBinary::try_from("offline").ok();
    let (Some(will_topic), Some(will_msg)) = (will_topic, will_msg) else {
        return Err(Failure::Protocol);
    };
    // The keep-alive follows the publish period (`Settings::keep_alive_s`):
    // a PINGREQ goes out after half of it without traffic, and a connection
    // whose PINGRESP does not come within the other half is dropped.
    let keep_alive =
        NonZero::new(settings.keep_alive_s()).map_or(KeepAlive::Infinite, KeepAlive::Seconds);
    let mut options = ConnectOptions::new()
        .clean_start()
        .keep_alive(keep_alive)
        .session_expiry_interval(SessionExpiryInterval::EndOnDisconnect)
        .will(WillOptions::new(will_topic, will_msg).retain());
    let user = MqttString::from_str(&target.user).ok();
    let password = MqttBinary::try_from(target.password.as_str()).ok();
    if let (Some(u), false) = (user, target.user.is_empty()) {
        options = options.user_name(u);
    }
    if let (Some(p), false) = (password, target.password.is_empty()) {
        options = options.password(p);
    }
    let client_id = MqttString::from_str(&target.client_id).ok();
    match timeout(
        clock,
        ANSWER_TIMEOUT_US,
        client.connect(conn, &options, client_id),
    )
    .await
    {
        None => return Err(Failure::Timeout),
        Some(Err(rust_mqtt::client::MqttError::Disconnect { reason, .. })) => {
            use rust_mqtt::types::ReasonCode;
            return Err(match reason {
                ReasonCode::BadUserNameOrPassword | ReasonCode::NotAuthorized => Failure::Login,
                _ => Failure::Refused,
            });
        }
        Some(Err(rust_mqtt::client::MqttError::Network(_))) => return Err(Failure::Connection),
        Some(Err(_)) => return Err(Failure::Protocol),
        Some(Ok(_)) => {}
    }
    let up_at = clock.now();
    note(Note::Connected);
    publisher.connected(up_at, identity);
    let end = serve(
        &mut client,
        clock,
        feed,
        publisher,
        (identity, up_at),
        &status,
        note,
    )
    .await;
    let up_for = clock.now().saturating_sub(up_at);
    // A polite end where the connection still carries it (the broker then
    // drops the will: publish `offline` ourselves first).
    if matches!(end, Failure::NewBms) {
        let _ = timeout(clock, WRITE_TIMEOUT_US, async {
            let topic = MqttString::from_str(&avail).ok().and_then(TopicName::new)?;
            let o = PublicationOptions::new(TopicReference::Name(topic)).retain();
            client
                .publish(&o, Bytes::from("offline".as_bytes()))
                .await
                .ok()?;
            client.disconnect(&DisconnectOptions::new()).await.ok()
        })
        .await;
    }
    Ok((end, up_for))
}

/// Subscribes to Home Assistant's status topic: the one subscription.
async fn subscribe_status<N: embedded_io_async::Read + embedded_io_async::Write, C: Clock>(
    client: &mut Mqtt<'_, N>,
    clock: &C,
    status_topic: &str,
) -> Result<(), Failure> {
    let Some(filter) = MqttString::from_str(status_topic)
        .ok()
        .and_then(TopicFilter::new)
    else {
        return Err(Failure::Protocol);
    };
    match timeout(
        clock,
        WRITE_TIMEOUT_US,
        client.subscribe(filter, &SubscriptionOptions::new()),
    )
    .await
    {
        None => Err(Failure::Timeout),
        Some(Err(_)) => Err(Failure::Connection),
        Some(Ok(_)) => Ok(()),
    }
}

/// Publishes everything the publisher has now (`topic` and `payload` are
/// its buffers); when the last message went out, if one did.
async fn publish_due<N: embedded_io_async::Read + embedded_io_async::Write, C: Clock, F: Feed>(
    client: &mut Mqtt<'_, N>,
    clock: &C,
    feed: &mut F,
    publisher: &mut Publisher,
    (topic, payload): (&mut String<TOPIC_MAX>, &mut alloc::vec::Vec<u8>),
) -> Result<Option<Instant>, Failure> {
    let mut last_sent = None;
    loop {
        let now = clock.now();
        let msg = feed.with_view(now, |v| publisher.next(now, v, topic, payload));
        let Some(m) = msg else { break };
        let Some(t) = MqttString::from_str(topic).ok().and_then(TopicName::new) else {
            continue;
        };
        let mut o = PublicationOptions::new(TopicReference::Name(t));
        if m.retain {
            o = o.retain();
        }
        let body = payload.get(..m.len).unwrap_or(&[]);
        match timeout(
            clock,
            WRITE_TIMEOUT_US,
            client.publish(&o, Bytes::from(body)),
        )
        .await
        {
            None => return Err(Failure::Timeout),
            Some(Err(_)) => return Err(Failure::Connection),
            Some(Ok(_)) => last_sent = Some(clock.now()),
        }
    }
    Ok(last_sent)
}

/// A connected session until it fails.
async fn serve<N: embedded_io_async::Read + embedded_io_async::Write, C: Clock, F: Feed>(
    client: &mut Mqtt<'_, N>,
    clock: &C,
    feed: &mut F,
    publisher: &mut Publisher,
    (identity, up_at): (Identity, Instant),
    status_topic: &str,
    note: &mut dyn FnMut(Note),
) -> Failure {
    if let Err(f) = subscribe_status(client, clock, status_topic).await {
        return f;
    }
    let mut topic = String::<TOPIC_MAX>::new();
    let mut payload = alloc::vec![0u8; PAYLOAD_MAX];
    // The keep-alive counts what this client sends: a PINGREQ after half of
    // it without a packet out, and a PINGRESP may take a whole keep-alive.
    let keep_alive = Instant::from(publisher.settings().keep_alive_s()) * SECOND;
    let half = keep_alive / 2;
    let mut last_sent = clock.now();
    let mut ping_sent: Option<Instant> = None;
    let mut held = false;
    loop {
        // The connection held: quick drops are over (`hello` says connected).
        if !held && clock.now().saturating_sub(up_at) >= QUICK_DROP_US {
            held = true;
            note(Note::Held);
        }
        // Everything the publisher has now.
        while let Some(e) = feed.next_event() {
            publisher.on_event(e);
        }
        let now = clock.now();
        if feed.with_view(now, |v| v.identity) != Some(identity) {
            return Failure::NewBms;
        }
        match publish_due(client, clock, feed, publisher, (&mut topic, &mut payload)).await {
            Err(f) => return f,
            Ok(Some(t)) => last_sent = t,
            Ok(None) => {}
        }
        // Keep-alive.
        let now = clock.now();
        if let Some(sent) = ping_sent {
            if now.saturating_sub(sent) >= keep_alive {
                return Failure::Timeout;
            }
        } else if now.saturating_sub(last_sent) >= half {
            match timeout(clock, WRITE_TIMEOUT_US, client.ping()).await {
                None => return Failure::Timeout,
                Some(Err(_)) => return Failure::Connection,
                Some(Ok(())) => {
                    last_sent = clock.now();
                    ping_sent = Some(last_sent);
                }
            }
        }
        // Wait: a packet from the broker, new telemetry, or the next due time.
        let wake = publisher
            .next_due()
            .min(now.saturating_add(IDLE_WAKE_US))
            .min(ping_sent.map_or(last_sent.saturating_add(half), |s| {
                s.saturating_add(keep_alive)
            }))
            .min(if held {
                Instant::MAX
            } else {
                up_at.saturating_add(QUICK_DROP_US)
            });
        let header = match select3(
            client.poll_header(),
            feed.changed(),
            clock.sleep_until(wake),
        )
        .await
        {
            Either3::First(Ok(h)) => h,
            Either3::First(Err(_)) => return Failure::Connection,
            Either3::Second(()) | Either3::Third(()) => continue,
        };
        let event = match timeout(clock, BODY_TIMEOUT_US, client.poll_body(header)).await {
            None => return Failure::Timeout,
            Some(Err(rust_mqtt::client::MqttError::Network(_))) => return Failure::Connection,
            Some(Err(rust_mqtt::client::MqttError::Disconnect {
                reason: ReasonCode::SessionTakenOver,
                ..
            })) => return Failure::TakenOver,
            Some(Err(rust_mqtt::client::MqttError::Disconnect { .. })) => {
                return Failure::Connection
            }
            Some(Err(_)) => return Failure::Protocol,
            Some(Ok(e)) => e,
        };
        match event {
            Event::Pingresp => ping_sent = None,
            Event::Publish(p) => {
                let is_status = p
                    .topic
                    .name()
                    .is_some_and(|n| AsRef::<MqttString<'_>>::as_ref(n).as_str() == status_topic);
                if is_status {
                    publisher.on_ha_status(&p.message);
                }
            }
            _ => {}
        }
    }
}
