//! What a job of the command queue (a settings group, a reset, a clear) asks of
//! the rest of the bridge: shared by the write/verify machine (`writes.rs`) and
//! the reset job (`reset.rs`), so that neither imports the other's types.

use protocol_core::request::Request;

use crate::bms::link::Silence;
use crate::Instant;

/// What the rest of the bridge must do for a job.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Effect {
    /// Send nothing before this time (a restart in progress, a read-back retry).
    Hold(Instant),
    /// The BMS restarted: everything is read again.
    Resync,
    /// Settings were written: read them again before the next command.
    RereadSettings,
    /// The BMS's event log was cleared (ACKed).
    EventsCleared,
    /// A write was verified: the bridge's copy of the settings takes the words
    /// the BMS read back (register `address`, and the next one for a 32-bit
    /// setting), so it never shows the old value until the next settings read.
    ReadBack {
        /// First register of the setting.
        address: u16,
        /// Its words as read back.
        first: u16,
        /// The second register's, for a 32-bit setting.
        second: Option<u16>,
    },
}

/// The running job's next step.
pub(super) enum JobNext {
    Send(Request, Silence),
    Wait,
    /// The job is done (and dropped), with what it leaves to do.
    Finished(Option<Effect>),
}
