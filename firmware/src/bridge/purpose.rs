//! What a request is for, and how its silence counts: the words the
//! schedule and the synchronisation share (a leaf of the bridge).

use protocol_core::request::SettingsOption;

use crate::bms::link::Silence;

/// How the silence of a request counts, and what its answer is for. The
/// request itself is written in place, into the link's slot (see
/// [`State::next_request`]): it is hundreds of bytes.
pub(super) type Ask = (Silence, Purpose);

/// What a confirmed block read is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Aux {
    Version,
    Settings,
    Stats,
    Events,
}

/// What the request in flight is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Purpose {
    Live,
    Aux(Aux),
    Limits(SettingsOption),
    NewestEvents,
    EventSlot,
    Probe,
    Job,
}
