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
//! **The battery** ([`aggregate`]) is made of the packs that *take part*: a
//! summary heard within [`PACK_LOST_US`], data younger than the stale age, no
//! fault. A pack that stops taking part leaves the sums at once.
//!
//! * CVL: the lowest CVL of the packs taking part; discharge voltage the highest.
//! * CCL: packs in parallel share the current by their voltages and
//!   resistances, not evenly, and a pack may even take current from the others.
//!   When the total changes by ΔI, a pack's share changes by α·ΔI with
//!   0 ≤ α ≤ 1 (its conductance over the sum of all). So the battery's CCL is
//!   the present total plus the *smallest* headroom of any pack
//!   (`CCL_k − I_k`): whichever way the extra current splits, no pack gets more
//!   than its headroom. A pack already past its own CCL turns the headroom
//!   negative, scaled by the number of packs (its share of a cut is about
//!   1/N). Never above the sum of the packs' CCLs; never below 0. While the
//!   battery discharges (or rests), the CCL starts from 0 current: the
//!   smallest headroom, so a limit is never 0 for a current that is not there.
//!   DCL the same way with discharge currents. Each pack's limit counts 2 %
//!   (at least 0.5 A) less ([`usable`]): its current was measured a moment ago.
//! * **One pack may open its switch at any moment** (a fault, a cutoff): until
//!   the inverter hears new limits, the others carry its current. So the total
//!   is also kept where, without any one pack, each other pack's share
//!   (measured: its current over the total) would stay within its own limit:
//!   `total ≤ limit_k × (total − I_j) / I_k` for every pair. Four equal packs
//!   are asked for at most three packs' current; two, for one pack's — the
//!   price of never tripping the others in a cascade.
//! * Those limits then go through the single pack's hold and ramp
//!   ([`super::control`]): they fall at once; they rise at most
//!   `ramp_da_per_s`; when a pack leaves or comes (back), a rise waits
//!   `hold_us` first. They start once the bridge has listened for
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
//! one refused or incomplete summary does not start a takeover. Two speakers
//! exist only while one of them hears nothing of the bus, and at most for one
//! period after a speaker's summaries went missing for 1.5 s; as soon as they
//! hear each other, the higher one stops.
//!
//! Every bridge with a node number computes the battery every second, speaker
//! or not, so a new speaker takes over with the hold and ramp state of the
//! battery as it was.

mod battery;
mod election;
mod heard;
mod summary;

pub use self::battery::*;
pub use self::election::*;
pub use self::heard::*;
pub use self::summary::*;
