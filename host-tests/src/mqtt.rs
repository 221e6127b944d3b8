//! The firmware's MQTT output on the desktop, in real time: the library's
//! publisher and session (`tinybms_firmware::mqtt`, the code the chip runs)
//! fed by a bridge running against the simulated BMS (`sim --mqtt HOST:PORT`,
//! the MQTT end-to-end tests).
//!
//! * [`Shared`] — what the station's loop hands over after every pass: a copy
//!   of what it publishes and its new events (never a wait: a full event
//!   queue drops the oldest, as on the chip).
//! * [`HostClock`], [`TcpNet`] — the session's time and network on `async-io`:
//!   an ordinary TCP socket to the broker.
//! * [`spawn`] — the session on a thread of its own, as the MQTT task is on the
//!   chip.

use std::collections::VecDeque;
use std::net::{TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use async_io::{Async, Timer};
use embedded_io_adapters::futures_03::FromFutures;
use protocol_core::events::Event;
use tinybms_firmware::identity::Identity;
use tinybms_firmware::mqtt::publisher::{Publisher, View};
use tinybms_firmware::mqtt::session::{self, Clock, Feed, NetError, Network, Note, Target};
use tinybms_firmware::mqtt::Settings;
use tinybms_firmware::station::{Published, Station};
use tinybms_firmware::Instant;

/// Events kept for the session; beyond, the oldest are dropped.
pub const EVENTS: usize = 16;

/// What the session sees of the station.
#[derive(Debug, Clone, Default)]
pub struct FeedState {
    /// What the station published last.
    pub published: Published,
    /// New events.
    pub events: VecDeque<Event>,
    /// Events dropped because the session did not take them.
    pub events_dropped: u64,
    /// Bumped on every change.
    pub generation: u64,
    /// The station's generation last copied.
    station_generation: Option<u32>,
}

/// The station's side and the session's side of the feed.
#[derive(Clone, Default)]
pub struct Shared(pub Arc<Mutex<FeedState>>);

impl Shared {
    /// Locks the state.
    pub fn lock(&self) -> std::sync::MutexGuard<'_, FeedState> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// After a pass of the station: what it publishes, copied when it
    /// changed, and its new events (what the chip's station task hands the
    /// MQTT task).
    pub fn update(&self, station: &mut Station, now: Instant) {
        let mut s = self.lock();
        if s.station_generation != Some(station.generation()) {
            s.station_generation = Some(station.generation());
            s.published = station.published(now);
            s.generation += 1;
        }
        while let Some(e) = station.take_event() {
            if s.events.len() >= EVENTS {
                s.events.pop_front();
                s.events_dropped += 1;
            }
            s.events.push_back(e);
            s.generation += 1;
        }
    }
}

/// A simulated bridge's Wi-Fi signal at `now` (µs), dBm: what a chip's
/// Wi-Fi task would read from its access point, a few metres away — around
/// -58 dBm, a step every 10 s (`salt` shifts the pattern: one per pack).
pub fn simulated_rssi(now: Instant, salt: usize) -> i8 {
    const STEPS: [i8; 8] = [0, -1, -3, -2, 1, -1, 0, -4];
    let k = (now / (10 * tinybms_firmware::SECOND)) as usize + salt;
    -58 + STEPS[k % STEPS.len()]
}

/// The session's [`Feed`] over a [`Shared`].
pub struct SharedFeed {
    shared: Shared,
    seen: u64,
}

impl SharedFeed {
    /// On `shared`.
    pub fn new(shared: Shared) -> Self {
        Self { shared, seen: 0 }
    }
}

impl Feed for SharedFeed {
    fn with_view<R>(&mut self, now: Instant, f: impl FnOnce(&View<'_>) -> R) -> R {
        let s = self.shared.lock();
        self.seen = s.generation;
        f(&View::of(&s.published, now))
    }

    fn next_event(&mut self) -> Option<Event> {
        self.shared.lock().events.pop_front()
    }

    async fn changed(&mut self) {
        // Polled every 20 ms: the station's loop has no waker to call.
        loop {
            if self.shared.lock().generation != self.seen {
                return;
            }
            Timer::after(Duration::from_millis(20)).await;
        }
    }
}

/// The session's clock: the bridge's (µs since its start), timers from async-io.
#[derive(Clone, Copy)]
pub struct HostClock(pub tinybms_desk::Clock);

impl Clock for HostClock {
    fn now(&self) -> Instant {
        self.0.now()
    }

    async fn sleep_until(&self, t: Instant) {
        let wait = self.0.until(t);
        if !wait.is_zero() {
            Timer::after(wait).await;
        }
    }
}

/// A switch a test flips to break the session's connection abruptly (no MQTT
/// DISCONNECT: as when the bridge loses its network); the broker then
/// publishes the will. The next connect clears it.
#[derive(Clone, Default)]
pub struct Kill(Arc<AtomicBool>);

impl Kill {
    /// Breaks the current connection.
    pub fn kill(&self) {
        self.0.store(true, Ordering::Relaxed);
    }
    fn killed(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
    fn clear(&self) {
        self.0.store(false, Ordering::Relaxed);
    }
}

/// A connection that fails once its [`Kill`] switch is flipped (and shuts its
/// TCP socket down, when it has one of the host's).
pub struct KillConn<C> {
    io: C,
    kill: Kill,
    raw: Option<TcpStream>,
}

impl<C> KillConn<C> {
    /// `io`, breakable by `kill`.
    pub fn new(io: C, kill: Kill, raw: Option<TcpStream>) -> Self {
        Self { io, kill, raw }
    }

    fn check(&self) -> Result<(), std::io::Error> {
        if self.kill.killed() {
            if let Some(r) = &self.raw {
                let _ = r.shutdown(std::net::Shutdown::Both);
            }
            return Err(std::io::Error::new(
                std::io::ErrorKind::ConnectionAborted,
                "killed by the test",
            ));
        }
        Ok(())
    }
}

/// An error of the wrapped connection or of the kill switch.
#[derive(Debug)]
pub struct ConnError;

impl std::fmt::Display for ConnError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("the connection broke")
    }
}

impl std::error::Error for ConnError {}

impl embedded_io_async::Error for ConnError {
    fn kind(&self) -> embedded_io_async::ErrorKind {
        embedded_io_async::ErrorKind::ConnectionAborted
    }
}

impl<C: embedded_io_async::ErrorType> embedded_io_async::ErrorType for KillConn<C> {
    type Error = ConnError;
}

impl<C: embedded_io_async::Read> embedded_io_async::Read for KillConn<C> {
    async fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        self.check().map_err(|_| ConnError)?;
        let n = self.io.read(buf).await.map_err(|_| ConnError)?;
        self.check().map_err(|_| ConnError)?;
        Ok(n)
    }
}

impl<C: embedded_io_async::Write> embedded_io_async::Write for KillConn<C> {
    async fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.check().map_err(|_| ConnError)?;
        self.io.write(buf).await.map_err(|_| ConnError)
    }

    async fn flush(&mut self) -> Result<(), Self::Error> {
        self.check().map_err(|_| ConnError)?;
        self.io.flush().await.map_err(|_| ConnError)
    }
}

/// TCP to the broker over the host's network.
#[derive(Clone, Default)]
pub struct TcpNet {
    /// Breaks the current connection.
    pub kill: Kill,
}

impl Network for TcpNet {
    type Conn<'a> = KillConn<FromFutures<Async<TcpStream>>>;

    async fn connect<'a>(&'a mut self, host: &str, port: u16) -> Result<Self::Conn<'a>, NetError> {
        let addr = (host, port)
            .to_socket_addrs()
            .map_err(|_| NetError::Dns)?
            .next()
            .ok_or(NetError::Dns)?;
        let stream = Async::<TcpStream>::connect(addr)
            .await
            .map_err(|_| NetError::Connect)?;
        let raw = stream
            .get_ref()
            .try_clone()
            .map_err(|_| NetError::Connect)?;
        self.kill.clear();
        Ok(KillConn::new(
            FromFutures::new(stream),
            self.kill.clone(),
            Some(raw),
        ))
    }
}

/// The notes the session logged, in order (what `sim --mqtt` prints).
pub type Notes = Arc<Mutex<Vec<Note>>>;

/// One log line for a session note (the chip's words).
pub fn note_text(n: &Note) -> String {
    let mut l = tinybms_firmware::log_line::Line::new();
    n.write(&mut l);
    l.as_str().to_string()
}

/// Starts the session on a thread of its own, over `net`, publishing with
/// `settings` for the bridge `bridge`. `log`: print its notes to stderr.
pub fn spawn<N: Network + Send + 'static>(
    target: Target,
    (settings, bridge): (Settings, Identity),
    shared: Shared,
    clock: tinybms_desk::Clock,
    net: N,
    log: bool,
) -> Notes {
    spawn_with(target, (settings, bridge), shared, clock, log, move || {
        (net, Box::pin(std::future::pending()))
    })
}

/// A future the session's thread runs beside it (a network stack's runner).
pub type Beside = std::pin::Pin<Box<dyn std::future::Future<Output = ()>>>;

/// Starts the session on a thread of its own, over the network `make` builds
/// there, together with the future it returns (which should never end: the
/// session stops when it does).
pub fn spawn_with<N: Network + 'static>(
    target: Target,
    (settings, bridge): (Settings, Identity),
    shared: Shared,
    clock: tinybms_desk::Clock,
    log: bool,
    make: impl FnOnce() -> (N, Beside) + Send + 'static,
) -> Notes {
    let notes: Notes = Arc::default();
    let out = notes.clone();
    let _ = std::thread::Builder::new()
        .name("mqtt".into())
        .spawn(move || {
            let mut publisher = Publisher::new(settings, &bridge);
            let mut feed = SharedFeed::new(shared);
            let (mut net, beside) = make();
            let clock = HostClock(clock);
            let mut note = |n: Note| {
                if log {
                    eprintln!("{:>10.3}s {}", clock.now() as f64 / 1e6, note_text(&n));
                }
                out.lock().unwrap_or_else(|e| e.into_inner()).push(n);
            };
            let session = session::run(
                &mut net,
                &clock,
                &mut feed,
                &target,
                &mut publisher,
                &mut note,
            );
            async_io::block_on(embassy_futures::select::select(session, beside));
        });
    notes
}

/// Any network whose connections a [`Kill`] switch breaks.
pub struct Killable<N> {
    /// The network.
    pub net: N,
    /// Breaks the current connection.
    pub kill: Kill,
}

impl<N: Network> Network for Killable<N> {
    type Conn<'a>
        = KillConn<N::Conn<'a>>
    where
        Self: 'a;

    async fn connect<'a>(&'a mut self, host: &str, port: u16) -> Result<Self::Conn<'a>, NetError> {
        let c = self.net.connect(host, port).await?;
        self.kill.clear();
        Ok(KillConn::new(c, self.kill.clone(), None))
    }
}
