//! Every static the tasks share, in one place, each with its role. The
//! station task owns the [`Station`](tinybms_firmware::station::Station); the
//! other tasks are pumps between a driver and these queues. Whatever a pump
//! puts in, it follows with [`WAKE`], so the station task's one wait ends.
//! No queue is waited on by the station task while full: it writes with
//! `try_*`, and what does not fit is dropped whole and counted where the
//! station says so.
//!
//! Memory that one driver's set-up hands out once and no other task touches
//! (the network stack's and the TCP client's buffers in `wifi.rs`, the flash
//! region in `store.rs`) stays beside that set-up.

use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex as Raw;
use embassy_sync::signal::Signal;

/// The station, which the station task owns: in a static of its own, not in
/// the task's future (an `async fn`'s argument and the local it becomes
/// would each take its size).
pub static STATION: static_cell::StaticCell<tinybms_firmware::station::Station> =
    static_cell::StaticCell::new();

/// Something for the station arrived (bytes, a frame, a result, a button
/// sample, a log line): the station task wakes and drains every queue.
pub static WAKE: Signal<Raw, ()> = Signal::new();

/// Tells the station task that something arrived for it.
#[cfg_attr(not(any(feature = "host-link", feature = "can")), allow(dead_code))]
pub fn wake() {
    WAKE.signal(());
}

#[cfg(feature = "host-link")]
pub use host::*;
#[cfg(feature = "host-link")]
mod host {
    use embassy_sync::channel::Channel;
    use embassy_sync::pipe::Pipe;
    use embassy_sync::signal::Signal;
    use tinybms_firmware::host_link::OUT_LINE_MAX;
    use tinybms_firmware::text::Line;
    use tinybms_firmware::Level;

    use super::Raw;

    /// Bytes from the host (a host-link reader task → the station task). When
    /// full, the reader waits, and the USB endpoint makes the host wait:
    /// nothing is lost.
    pub static HOST_RX: Pipe<Raw, 256> = Pipe::new();
    /// Whole encoded lines for the host (the station task → the writer task).
    /// The station task writes a line only when it fits whole.
    pub static HOST_TX: Pipe<Raw, { 2 * OUT_LINE_MAX }> = Pipe::new();
    /// The writer saw a write go through after none could (at boot, or after
    /// a host stopped reading): a host (re)opened the port; `hello` follows.
    pub static HOST_CONNECTED: Signal<Raw, ()> = Signal::new();
    /// A sample of the BOOT button (pressed): the button task sends them while
    /// it is held and once when it is let go.
    pub static BUTTON: Signal<Raw, bool> = Signal::new();
    /// Log lines of other tasks (Wi-Fi, MQTT) for the host link's `log` lines;
    /// when full, a line is only logged.
    pub static FOREIGN_LOG: Channel<Raw, (Level, Line), 4> = Channel::new();
}

#[cfg(feature = "can")]
pub use can::*;
#[cfg(feature = "can")]
mod can {
    use embassy_sync::channel::Channel;
    use tinybms_firmware::inverter::dialect::CanFrame;
    use tinybms_firmware::inverter::port::{CanCommand, CanDone};

    use super::Raw;

    /// The station task → the CAN task.
    pub static CAN_COMMAND: Channel<Raw, CanCommand, 1> = Channel::new();
    /// The CAN task → the station task.
    pub static CAN_DONE: Channel<Raw, CanDone, 2> = Channel::new();
    /// Frames from the bus (the CAN task → the station task); when full, a
    /// frame is dropped (the station's inputs are periodic).
    pub static CAN_RX: Channel<Raw, CanFrame, 16> = Channel::new();
}

#[cfg(feature = "wifi")]
pub use mqtt::*;
#[cfg(feature = "wifi")]
mod mqtt {
    use embassy_sync::channel::Channel;
    use embassy_sync::watch::Watch;
    use protocol_core::events::Event;
    use tinybms_firmware::station::Published;

    use super::Raw;

    /// What the MQTT output publishes (the station task → the MQTT task;
    /// latest wins).
    pub static PUBLISHED: Watch<Raw, Published, 1> = Watch::new();
    /// New BMS events for the MQTT output; when full, the station keeps them
    /// (and drops its oldest, counted) until there is room.
    pub static MQTT_EVENTS: Channel<Raw, Event, 8> = Channel::new();
    /// Where the MQTT connection stands (the MQTT task → the station task,
    /// for `hello`; latest wins).
    pub static MQTT_STATE: embassy_sync::signal::Signal<Raw, tinybms_firmware::mqtt::MqttState> =
        embassy_sync::signal::Signal::new();

    /// What the station asks of the Wi-Fi task (Improv Wi-Fi: a join, a
    /// scan); one at a time.
    pub static WIFI_REQUEST: Channel<Raw, tinybms_firmware::improv::WifiRequest, 1> =
        Channel::new();

    /// What the Wi-Fi task did. (A scan's list travels whole, once: the
    /// channel's few slots are the only copies.)
    #[allow(clippy::large_enum_variant)]
    pub enum WifiDone {
        /// The asked join ended.
        Joined(Result<[u8; 4], tinybms_firmware::improv::JoinFailure>),
        /// The asked scan ended.
        Scanned(
            heapless::Vec<
                tinybms_firmware::improv::Network,
                { tinybms_firmware::improv::SCAN_MAX },
            >,
        ),
        /// The link changed.
        Link(tinybms_firmware::improv::WifiLink),
    }

    /// The Wi-Fi task → the station task; when full, a link change is lost
    /// (the next one says it again).
    pub static WIFI_DONE: Channel<Raw, WifiDone, 4> = Channel::new();

    /// Where the radio's start stands (the Wi-Fi side → the station task, for
    /// `hello`; latest wins).
    pub static RADIO: embassy_sync::signal::Signal<Raw, tinybms_firmware::wifi::Radio> =
        embassy_sync::signal::Signal::new();

    /// The access point's signal, dBm, while joined (`None`: not joined or
    /// not read): the Wi-Fi task → the station task, for what MQTT
    /// publishes; latest wins.
    pub static WIFI_RSSI: embassy_sync::signal::Signal<Raw, Option<i8>> =
        embassy_sync::signal::Signal::new();

    /// Bytes from the update port's connection (its task → the station task);
    /// when full, the task waits and TCP makes the sender wait.
    pub static UPDATE_RX: embassy_sync::pipe::Pipe<Raw, 512> = embassy_sync::pipe::Pipe::new();
    /// Whole lines for the update port's connection (the station task → its
    /// task).
    pub static UPDATE_TX: embassy_sync::pipe::Pipe<
        Raw,
        { 2 * tinybms_firmware::host_link::OUT_LINE_MAX },
    > = embassy_sync::pipe::Pipe::new();
    /// A connection to the update port came (`true`) or closed (`false`);
    /// latest wins.
    pub static UPDATE_CONNECTION: embassy_sync::signal::Signal<Raw, bool> =
        embassy_sync::signal::Signal::new();
}

/// Lines for the host the writer dropped on the wire since the station last
/// looked (a host that does not read; a write error).
#[cfg(feature = "host-link")]
static HOST_LINES_DROPPED: embassy_sync::blocking_mutex::Mutex<Raw, core::cell::Cell<u32>> =
    embassy_sync::blocking_mutex::Mutex::new(core::cell::Cell::new(0));

/// The writer dropped `n` lines.
#[cfg(feature = "host-link")]
pub fn host_lines_dropped(n: u32) {
    HOST_LINES_DROPPED.lock(|c| c.set(c.get().wrapping_add(n)));
}

/// The lines dropped since the last call.
#[cfg(feature = "host-link")]
pub fn take_host_lines_dropped() -> u32 {
    HOST_LINES_DROPPED.lock(|c| c.replace(0))
}
