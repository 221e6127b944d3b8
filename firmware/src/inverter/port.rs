//! The CAN controller's side of the inverter output, as the chip shell's CAN
//! task pumps it: what the station asks ([`CanCommand`], one at a time), what
//! came of it ([`CanDone`], read from the driver's answer by
//! [`CanDone::after_send`]), and a frame the bus carried ([`CanFrame::from_bus`]).
//! The driver's calls are the shell's (`src/chip/can.rs`); what its answers
//! mean is decided here. The limits the task waits by are
//! [`super::CAN_TX_TIMEOUT_US`], [`super::BUS_RECOVERY_WAIT_US`] and
//! [`super::BUS_RECOVERY_POLL_US`].

use super::dialect::CanFrame;

/// The bit rate of every inverter protocol here (Victron, SMA), bit/s.
pub const BITRATE: u32 = 500_000;

/// What the station asks of the CAN controller (one at a time: the next only
/// after the result).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CanCommand {
    /// Send this frame.
    Send(CanFrame),
    /// Start a bus-off recovery and wait for it.
    Recover,
}

/// What came of a [`CanCommand`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CanDone {
    /// Sent and acknowledged.
    Sent,
    /// Not acknowledged (no other node: error-passive), refused, or too slow.
    Failed,
    /// The controller left the bus.
    BusOff,
    /// The recovery ended: back on the bus (`true`) or still off.
    Recovered(bool),
}

/// How a transmission ended, in the driver's terms the shell sorts into.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sent {
    /// Acknowledged.
    Acked,
    /// The driver said the controller went bus-off.
    BusOff,
    /// Any other error of the driver's.
    Error,
    /// It took longer than [`super::CAN_TX_TIMEOUT_US`].
    TimedOut,
}

impl CanDone {
    /// What a transmission's end means; `bus_off_now` is what the controller
    /// says of itself afterwards (it can leave the bus with a frame that
    /// timed out).
    pub const fn after_send(sent: Sent, bus_off_now: bool) -> Self {
        match (sent, bus_off_now) {
            (Sent::BusOff, _) | (_, true) => Self::BusOff,
            (Sent::Acked, false) => Self::Sent,
            (Sent::Error | Sent::TimedOut, false) => Self::Failed,
        }
    }
}

impl CanFrame {
    /// A frame with this identifier and data, as the bus carried it: `None`
    /// for an identifier over 11 bits (an extended frame: no protocol here
    /// uses one); data past 8 bytes is cut.
    pub fn from_bus(id: u32, data: &[u8]) -> Option<Self> {
        let id = u16::try_from(id).ok().filter(|i| *i <= 0x7FF)?;
        let mut f = Self {
            id,
            len: 0,
            data: [0; 8],
        };
        let n = data.len().min(8);
        if let (Some(dst), Some(src)) = (f.data.get_mut(..n), data.get(..n)) {
            dst.copy_from_slice(src);
            f.len = n as u8;
        }
        Some(f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_transmission_s_end_is_read_as_the_station_needs_it() {
        assert_eq!(CanDone::after_send(Sent::Acked, false), CanDone::Sent);
        assert_eq!(CanDone::after_send(Sent::Acked, true), CanDone::BusOff);
        assert_eq!(CanDone::after_send(Sent::BusOff, false), CanDone::BusOff);
        assert_eq!(CanDone::after_send(Sent::Error, false), CanDone::Failed);
        assert_eq!(CanDone::after_send(Sent::TimedOut, false), CanDone::Failed);
        assert_eq!(CanDone::after_send(Sent::TimedOut, true), CanDone::BusOff);
    }

    #[test]
    fn frames_from_the_bus_keep_eight_bytes_and_standard_ids() {
        let f = CanFrame::from_bus(0x305, &[1, 2, 3]).unwrap();
        assert_eq!((f.id, f.bytes()), (0x305, &[1u8, 2, 3][..]));
        let f = CanFrame::from_bus(0x7FF, &[9; 12]).unwrap();
        assert_eq!(f.bytes(), &[9u8; 8][..]);
        assert_eq!(CanFrame::from_bus(0x800, &[]), None);
        assert_eq!(CanFrame::from_bus(0x1234_5678, &[1]), None);
        assert_eq!(
            CanFrame::from_bus(0x100, &[]).unwrap().bytes(),
            &[] as &[u8]
        );
    }
}
