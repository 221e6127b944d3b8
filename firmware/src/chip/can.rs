//! The inverter output's wire (feature `can`): the TWAI controller and
//! `can_task`, a pump between it and the station. The task sends the one
//! frame the station hands out ([`wires::CAN_COMMAND`]), says what came of it
//! ([`wires::CAN_DONE`]) and passes every frame it hears on
//! ([`wires::CAN_RX`]); what to send, when, and what a failure means is the
//! library's `Inverter`, inside the station.
//!
//! esp-hal 1.2's `transmit_async` returns once the frame is acknowledged, or
//! with `TransmissionAborted` when the controller goes error-passive (nobody
//! acknowledges: a bus with no inverter) and `BusOff` when it leaves the bus;
//! the task bounds it with [`CAN_TX_TIMEOUT`] anyway, so a bus nobody
//! acknowledges costs the station nothing: it never waits on this task.

use embassy_executor::Spawner;
use embassy_futures::select::{select, Either};
use embassy_time::{with_timeout, Duration, Instant, Timer};
use esp_hal::gpio::AnyPin;
use esp_hal::peripherals::TWAI0;
use esp_hal::twai::{
    BaudRate, EspTwaiError, EspTwaiFrame, Id, StandardId, Twai, TwaiConfiguration, TwaiMode,
};
use esp_hal::Async;
use tinybms_firmware::inverter::dialect::CanFrame;
use tinybms_firmware::inverter::port::{self, CanCommand, CanDone, Sent};
use tinybms_firmware::inverter::{self, InverterConfig};
use tinybms_firmware::text::Boot;

use crate::wires;
use crate::{spawn, BOARD};

/// The protocols' bit rate ([`port::BITRATE`]) as the driver names it.
const CAN_BAUDRATE: BaudRate = match port::BITRATE {
    500_000 => BaudRate::B500K,
    _ => panic!("no TWAI rate for the protocols' bit rate"),
};
/// The library's limits ([`tinybms_firmware::inverter`]) as driver durations.
const CAN_TX_TIMEOUT: Duration = Duration::from_micros(inverter::CAN_TX_TIMEOUT_US);
const CAN_RECOVERY_WAIT: Duration = Duration::from_micros(inverter::BUS_RECOVERY_WAIT_US);
const CAN_RECOVERY_POLL: Duration = Duration::from_micros(inverter::BUS_RECOVERY_POLL_US);

/// TWAI (CAN) to the inverter, on the board's CAN pins, 500 kbit/s, unless
/// the configuration has the output off (then the pins stay untouched and
/// the station's output, off too, never hands out a frame). Returns its boot
/// line.
pub fn start(spawner: Spawner, twai0: TWAI0<'static>, config: &InverterConfig) -> Boot {
    if !config.enabled {
        return Boot::CanOff;
    }
    // SAFETY: as for the UART pins: used nowhere else, checked distinct and
    // not flash/USB/UART0/strapping pins by the board table.
    let (can_tx, can_rx) = unsafe { (AnyPin::steal(BOARD.can_tx), AnyPin::steal(BOARD.can_rx)) };
    let twai = TwaiConfiguration::new(twai0, can_rx, can_tx, CAN_BAUDRATE, TwaiMode::Normal)
        .into_async()
        .start();
    spawn(spawner, can_task(twai));
    Boot::Can {
        protocol: config.protocol,
        pins: Some((BOARD.can_tx, BOARD.can_rx)),
        node: config.node,
    }
}

/// Tells the station, and wakes it.
fn done(d: CanDone) {
    // Room for it: the station hands out one command at a time.
    let _ = wires::CAN_DONE.try_send(d);
    wires::wake();
}

/// See the module documentation.
#[embassy_executor::task]
async fn can_task(mut twai: Twai<'static, Async>) {
    loop {
        match select(wires::CAN_COMMAND.receive(), twai.receive_async()).await {
            Either::First(CanCommand::Send(f)) => {
                let Some(frame) =
                    StandardId::new(f.id).and_then(|id| EspTwaiFrame::new(id, f.bytes()))
                else {
                    done(CanDone::Failed);
                    continue;
                };
                let sent = match with_timeout(CAN_TX_TIMEOUT, twai.transmit_async(&frame)).await {
                    Ok(Ok(())) => Sent::Acked,
                    Ok(Err(EspTwaiError::BusOff)) => Sent::BusOff,
                    Ok(Err(_)) => Sent::Error,
                    Err(_) => Sent::TimedOut,
                };
                done(CanDone::after_send(sent, twai.is_bus_off()));
            }
            Either::First(CanCommand::Recover) => {
                twai.initiate_recovery();
                let until = Instant::now() + CAN_RECOVERY_WAIT;
                while twai.is_bus_off() && Instant::now() < until {
                    Timer::after(CAN_RECOVERY_POLL).await;
                }
                done(CanDone::Recovered(!twai.is_bus_off()));
            }
            Either::Second(Ok(frame)) => {
                let id = match frame.identifier() {
                    Id::Standard(id) => u32::from(id.as_raw()),
                    Id::Extended(id) => id.as_raw(),
                };
                // An extended frame is none of the protocols' (`None`).
                if let Some(f) = CanFrame::from_bus(id, frame.data()) {
                    // Full: the frame is dropped (summaries and keep-alives repeat).
                    let _ = wires::CAN_RX.try_send(f);
                    wires::wake();
                }
            }
            Either::Second(Err(_)) => {}
        }
    }
}
