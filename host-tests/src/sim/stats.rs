//! Counters of what the simulated BMS saw and did.

use std::collections::BTreeMap;

/// Injected faults, by kind (see [`crate::sim::FaultConfig`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FaultCounts {
    /// Output bytes lost.
    pub dropped_bytes: u64,
    /// Output bytes with one bit inverted.
    pub bit_flips: u64,
    /// Replies cut short.
    pub truncated: u64,
    /// Requests lost (no reply, no effect).
    pub no_reply: u64,
    /// Replies sent twice.
    pub duplicated: u64,
    /// Replies delayed.
    pub delayed: u64,
    /// Random bytes inserted into replies.
    pub inserted_bytes: u64,
    /// Bursts of noise into replies.
    pub noise_bursts: u64,
    /// Fragments of an earlier reply repeated.
    pub repeated_fragments: u64,
}

impl FaultCounts {
    /// All faults injected.
    pub fn total(&self) -> u64 {
        self.dropped_bytes
            + self.bit_flips
            + self.truncated
            + self.no_reply
            + self.duplicated
            + self.delayed
            + self.inserted_bytes
            + self.noise_bursts
            + self.repeated_fragments
    }
}

/// What the simulated BMS saw and did since it was created.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SimStats {
    /// Bytes received from the host (all of them).
    pub bytes_received: u64,
    /// Bytes ignored because the BMS was rebooting or silent.
    pub bytes_ignored: u64,
    /// Bytes dropped while resynchronising on the preamble.
    pub garbage_bytes: u64,
    /// Partial requests dropped after an idle gap.
    pub partial_requests_dropped: u64,
    /// Complete request frames (valid or not, answered or not).
    pub requests: u64,
    /// Complete request frames by command byte.
    pub requests_by_command: BTreeMap<u8, u64>,
    /// Requests swallowed because they woke the BMS from sleep.
    pub wake_requests: u64,
    /// Requests ignored while a settings write was settling.
    pub busy_ignored: u64,
    /// Reply frames sent (ACK, NACK, data; a duplicated reply counts once).
    pub replies: u64,
    /// Data replies among them.
    pub data_replies: u64,
    /// ACKs among them.
    pub acks: u64,
    /// NACK 0x00 (command error) among them.
    pub nacks_command: u64,
    /// NACK 0x01 (CRC error) among them.
    pub nacks_crc: u64,
    /// Replies protocol-core could not encode (a simulator bug if ever non-zero).
    pub encode_errors: u64,
    /// ASCII broadcast lines sent.
    pub broadcasts: u64,
    /// Bytes put on the wire (after fault injection).
    pub bytes_sent: u64,
    /// Wake-ups from sleep by UART traffic.
    pub wakeups: u64,
    /// Times the BMS fell asleep.
    pub sleeps: u64,
    /// Reboots (0x02 option 0x05, write to 340).
    pub reboots: u64,
    /// Events logged since creation (the initial history not counted).
    pub events_logged: u64,
    /// Injected faults by kind.
    pub faults: FaultCounts,
}
