//! The inverter output (feature `can`): the TWAI controller and `can_task`,
//! between the shared telemetry and the library's sans-IO `Inverter`.

use defmt::{info, warn};
use embassy_executor::Spawner;
use embassy_futures::select::{select, Either};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::channel::Channel;
use embassy_sync::signal::Signal;
use embassy_sync::watch::Watch;
use embassy_time::{with_timeout, Duration, Instant, Timer};
use esp_hal::gpio::AnyPin;
use esp_hal::peripherals::TWAI0;
use esp_hal::twai::{
    BaudRate, EspTwaiError, EspTwaiFrame, Id, StandardId, Twai, TwaiConfiguration, TwaiMode,
};
use esp_hal::Async;
use protocol_core::events::Event;
use protocol_core::views::VersionInfo;
use tinybms_firmware::config::Config;
use tinybms_firmware::inverter::control::PackSettings;
use tinybms_firmware::inverter::{Inverter, InverterAction, InverterConfig, Protocol, TxResult};
use tinybms_firmware::{Report, Telemetry};

use crate::{now_us, spawn, BOARD, TELEMETRY};

/// New BMS events for the CAN output (charge-blocking faults); a full channel
/// drops the event for it (the BMS status still says "fault").
static EVENTS: Channel<CriticalSectionRawMutex, Event, 8> = Channel::new();

/// Packs in parallel: the battery as the inverter output sees it, once a
/// second (latest wins): for the host link's `battery` and `pack` lines (the
/// bridge task) and the battery's device in Home Assistant (the Wi-Fi task).
pub static BATTERY: Watch<
    CriticalSectionRawMutex,
    tinybms_firmware::inverter::packs::BatteryView,
    2,
> = Watch::new();

/// The configuration's at-once fields changed (latest wins): the bridge task
/// signals, the CAN task applies them (`Inverter::reconfigure`).
static RECONFIGURE: Signal<CriticalSectionRawMutex, InverterConfig> = Signal::new();

/// CAN bit rate of both inverter protocols.
const CAN_BAUDRATE: BaudRate = BaudRate::B500K;
/// Longest a CAN transmission may take before it counts as failed.
const CAN_TX_TIMEOUT: Duration = Duration::from_millis(100);
/// Longest the CAN task sleeps (it re-reads the telemetry at least this often).
const CAN_MAX_WAIT: Duration = Duration::from_millis(200);
/// Bus-off recovery: how long to wait for the controller to come back.
const CAN_RECOVERY_WAIT: Duration = Duration::from_millis(500);

/// What the inverter output needs with each snapshot: the BMS settings charge
/// control uses and the version.
#[derive(Clone)]
pub struct Inputs {
    settings: Option<PackSettings>,
    version: Option<VersionInfo>,
}

impl Inputs {
    pub fn from_telemetry(t: &Telemetry) -> Self {
        Self {
            settings: t.settings.as_ref().and_then(PackSettings::from_registers),
            version: t.version,
        }
    }
}

/// A bridge report the inverter output wants: new BMS events.
pub fn on_report(report: &Report) {
    if let Report::NewEvent(e) = report {
        let _ = EVENTS.try_send(*e);
    }
}

/// The running configuration changed: its at-once fields to the CAN task.
pub fn reconfigure(running: &Config) {
    RECONFIGURE.signal(running.inverter());
}

/// TWAI (CAN) to the inverter, on the board's CAN pins, 500 kbit/s, unless
/// the configuration has the output off (then the pins stay untouched).
pub fn start(spawner: Spawner, twai0: TWAI0<'static>, config: InverterConfig) {
    if !config.enabled {
        info!("CAN to the inverter off (can_output = off)");
        return;
    }
    // SAFETY: as for the UART pins above: used nowhere else, checked distinct and
    // not flash/USB/UART0/strapping pins by the board table.
    let (can_tx, can_rx) = unsafe { (AnyPin::steal(BOARD.can_tx), AnyPin::steal(BOARD.can_rx)) };
    let twai = TwaiConfiguration::new(twai0, can_rx, can_tx, CAN_BAUDRATE, TwaiMode::Normal)
        .into_async()
        .start();
    info!(
        "CAN to the inverter: {=str}, 500 kbit/s, TX=GPIO{=u8} RX=GPIO{=u8}",
        match config.protocol {
            Protocol::Victron => "Victron",
            Protocol::SmaSunnyIsland => "SMA Sunny Island",
        },
        BOARD.can_tx,
        BOARD.can_rx,
    );
    if config.node != 0 {
        info!(
            "CAN: pack node {=u8} of packs in parallel (summaries on 0x6A0-0x6BF; node 1 speaks first)",
            config.node
        );
    }
    spawn(spawner, can_task(twai, config));
}

/// The inverter output: the firmware's sans-IO [`Inverter`] between the shared
/// telemetry and the TWAI controller. It never waits on the BMS link (it reads
/// the `Watch` without blocking) and the BMS link never waits on it.
#[embassy_executor::task]
async fn can_task(mut twai: Twai<'static, Async>, config: InverterConfig) {
    let Some(mut telemetry) = TELEMETRY.receiver() else {
        warn!("telemetry watch has no free receiver slot: no CAN output");
        return;
    };
    let mut inverter = Inverter::new(config, now_us());
    let mut next_view = now_us();
    loop {
        if let Some(c) = RECONFIGURE.try_take() {
            inverter.reconfigure(c);
        }
        if let Some(shared) = telemetry.try_changed() {
            inverter.on_snapshot(
                shared.taken_at.as_micros(),
                &shared.snapshot,
                shared.inverter.settings,
                shared.inverter.version.as_ref(),
            );
        }
        while let Ok(e) = EVENTS.try_receive() {
            inverter.on_event(&e);
        }
        match inverter.poll(now_us()) {
            InverterAction::Send(f) => {
                let Some(frame) =
                    StandardId::new(f.id).and_then(|id| EspTwaiFrame::new(id, f.bytes()))
                else {
                    continue;
                };
                let result = with_timeout(CAN_TX_TIMEOUT, twai.transmit_async(&frame)).await;
                if matches!(result, Ok(Err(EspTwaiError::BusOff))) || twai.is_bus_off() {
                    inverter.on_bus_off(now_us());
                } else if matches!(result, Ok(Ok(()))) {
                    inverter.on_tx(now_us(), TxResult::Sent);
                } else {
                    // Not acknowledged (no other node: error-passive), or too slow.
                    inverter.on_tx(now_us(), TxResult::Failed);
                }
            }
            InverterAction::Recover => {
                twai.initiate_recovery();
                let until = Instant::now() + CAN_RECOVERY_WAIT;
                while twai.is_bus_off() && Instant::now() < until {
                    Timer::after(Duration::from_millis(10)).await;
                }
                if twai.is_bus_off() {
                    inverter.on_bus_off(now_us());
                }
            }
            InverterAction::WaitUntil(t) => {
                let deadline = Instant::from_micros(t).min(Instant::now() + CAN_MAX_WAIT);
                // The GX keep-alive (0x305/0x307) and anything else on the bus.
                if let Either::First(Ok(frame)) =
                    select(twai.receive_async(), Timer::at(deadline)).await
                {
                    if let Id::Standard(id) = frame.identifier() {
                        inverter.on_received(now_us(), id.as_raw(), frame.data());
                    }
                }
            }
        }
        if inverter.node() != 0 && now_us() >= next_view {
            next_view = now_us() + 1_000_000;
            if let Some(v) = inverter.battery_view(now_us()) {
                BATTERY.sender().send(v);
            }
        }
        while let Some(r) = inverter.next_report() {
            // What the inverter is sent: this pack's limits when alone, the
            // battery's when this bridge speaks for several packs.
            #[cfg(feature = "wifi")]
            {
                use tinybms_firmware::inverter::InverterReport as R;
                let sent = match r {
                    R::Limits(l) if inverter.node() == 0 => Some(l),
                    R::BatteryLimits(l) => Some(l),
                    _ => None,
                };
                if let Some(l) = sent {
                    crate::wifi::LIMITS
                        .sender()
                        .send((l.cvl_dv, l.ccl_da, l.dcl_da));
                }
            }
            crate::log::inverter(&r);
        }
    }
}
