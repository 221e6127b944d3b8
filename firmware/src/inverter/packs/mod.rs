//! Several packs, one battery: the summaries bridges exchange on the inverter's
//! bus, the battery they add up to, and which bridge speaks to the inverter.
//! Sans-IO like the rest of the inverter output.
//!
//! **Summaries.** A bridge with a node number (1..=[`MAX_NODES`]) sends its
//! pack's summary every second as [`SUMMARY_FRAMES`] classic frames with the
//! 11-bit identifiers `SUMMARY_BASE_ID + 4 × (node − 1) + k`, k = 0..=3
//! (0x6A0-0x6BF: outside every identifier the Victron and SMA protocols use).
//! The last byte of each frame carries a 4-bit sequence number; a summary is
//! taken only when all four frames with one sequence number have arrived, so a
//! lost or late frame never mixes two summaries. Every field is checked on
//! receipt (see [`SummaryError`]); a summary that fails is dropped whole.
//!
//! **The battery** ([`aggregate_with`]) is made of the packs that *take
//! part*: a frame heard within [`PACK_LOST_US`], data younger than the stale
//! age, no fault. A pack without fresh data whose switch is not known to be
//! open ([`Member::unknown`]: its bridge lost, its BMS link stale) may still
//! conduct: it stays in the limits' sums with its last limits until it is
//! back or known open.
//!
//! * CVL: the lowest CVL of the packs taking part; discharge voltage the highest.
//! * CCL and DCL: packs in parallel are voltages behind resistances; when the
//!   total changes by ΔT, pack k's current changes by α_k·ΔT (its
//!   conductance over all: its *share of a change*), whatever it carries now.
//!   [`Shares`] learns α from how each pack's current moves with the total;
//!   until it knows, α = 1 (any pack may take all of a change). The battery's
//!   limit keeps every pack within its own limit now, should any one pack
//!   open its switch, for a pack without data, and for a pack whose switch is
//!   open and may close again (see `battery::limit_of`). Each pack's limit
//!   counts 2 % (at least 0.5 A) less ([`usable`]): its current was measured
//!   a moment ago.
//! * Those limits then go through the single pack's hold and ramp
//!   ([`super::control`]): they fall at once; they rise at most
//!   `ramp_rate_da_per_s`; when a pack leaves the sums or comes (back) into them,
//!   a rise waits `limit_hold_us` first (a pack that comes and goes without data
//!   never left them). They start once the bridge has listened for
//!   [`LISTEN_US`] (it knows every pack then).
//! * SOC and SOH weighted by capacity; capacity, current summed; voltage the
//!   mean; cell and temperature extremes across the packs; alarms and warnings
//!   of the packs taking part combined (the highest level of each field). A
//!   pack that left shows as a BMS internal *warning* — never as an alarm that
//!   would stop the whole battery, nor as "link lost", which a GX reads as the
//!   battery offline.
//!
//! **One speaker** ([`Election`]): a bridge that is not speaking starts only
//! when (a) it has listened for [`LISTEN_US`] since it started or recovered from
//! a bus-off, (b) no other node heard within [`SPEAKER_LOST_US`] says it is
//! speaking, and (c) no lower node number is heard. A speaker goes on until it
//! hears a *lower* node that says it is speaking. So node 1, the primary,
//! speaks after its first 3 s; when the speaker falls silent, the lowest node
//! still heard takes over once [`SPEAKER_LOST_US`] have passed since its last
//! summary: the inverter is without limits for at most 2.5 s (a Victron GX
//! waits 3 s); a node that comes back finds a speaker
//! and stays quiet (no handover, no gap). A bridge speaks only while it sends
//! its own summary (it has BMS data, and no other bridge has its number), so
//! the others always hear the speaker; "heard" counts any frame of a node, so
//! one refused or incomplete summary does not start a takeover, and a bridge
//! that hears any speaker's inverter frames does not take over either. A
//! bridge that heard two or more others and then hears nobody at all waits
//! [`DEAF_GUARD_US`] (its own receiver is the likelier cause). Two speakers
//! exist only while one of them hears nothing of the bus for longer; as soon
//! as they hear each other, the higher one stops.
//!
//! Every bridge with a node number computes the battery every second, speaker
//! or not, so a new speaker takes over with the hold and ramp state of the
//! battery as it was.

mod battery;
mod election;
mod heard;
mod shares;
mod summary;

pub use self::battery::*;
pub use self::election::*;
pub use self::heard::*;
pub use self::shares::*;
pub use self::summary::*;
