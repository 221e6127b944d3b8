//! Bytes to the host: frames on the wire with their timing and the faults asked for.

use super::*;

impl SimBms {
    /// Encodes `frame` with protocol-core, applies the reply faults and queues
    /// it one latency after `t`. Returns the time its last byte leaves the wire.
    pub(super) fn send_frame(&mut self, t: u64, frame: &Frame) -> Option<u64> {
        let mut buf = match frame.encoded_len() {
            Ok(n) => vec![0u8; n],
            Err(_) => {
                self.stats.encode_errors += 1;
                return None;
            }
        };
        match frame.encode(&mut buf) {
            Ok(n) => buf.truncate(n),
            Err(_) => {
                self.stats.encode_errors += 1;
                return None;
            }
        }
        self.stats.replies += 1;
        if self.record {
            self.sent_log.push(frame.clone());
        }
        match frame {
            Frame::Ack { .. } => self.stats.acks += 1,
            Frame::Nack {
                code: NackCode::CrcError,
                ..
            } => self.stats.nacks_crc += 1,
            Frame::Nack { .. } => self.stats.nacks_command += 1,
            Frame::Data { command, .. } => {
                self.stats.data_replies += 1;
                if cmd::is_packetized(*command) && self.config.first_packet_id != FIRST_PACKET_ID {
                    renumber_packets(&mut buf, self.config.first_packet_id);
                }
            }
        }
        if let Some(n) = self.drop_replies.get_mut(&frame.command()) {
            if *n > 0 {
                *n -= 1;
                return None;
            }
        }
        if let Some(forged) = self.forged.take() {
            buf = forged;
        } else if matches!(frame, Frame::Data { command: 0x03, payload, .. } if payload.len() == 112)
        {
            if let Some(forged) = self.forged_live.take() {
                buf = forged;
            }
        }
        let faults = self.config.faults;
        let mut start = t.saturating_add(self.draw_latency());
        if self.rng_faults.chance(faults.delay) {
            self.stats.faults.delayed += 1;
            start = start.saturating_add(faults.delay_us);
        }
        if buf.len() > 1 && self.rng_faults.chance(faults.truncate) {
            self.stats.faults.truncated += 1;
            let keep = 1 + self.rng_faults.below(buf.len() as u64 - 1) as usize;
            buf.truncate(keep);
        }
        if self.rng_faults.chance(faults.duplicate) {
            self.stats.faults.duplicated += 1;
            buf.extend_from_within(..);
        }
        let clean = buf.clone();
        if faults.insert_byte > 0.0 {
            let mut out = Vec::with_capacity(buf.len() + 4);
            for &b in &buf {
                out.push(b);
                if self.rng_faults.chance(faults.insert_byte) {
                    self.stats.faults.inserted_bytes += 1;
                    out.push(self.rng_faults.below(256) as u8);
                }
            }
            buf = out;
        }
        if self.rng_faults.chance(faults.noise_burst) {
            self.stats.faults.noise_bursts += 1;
            let n = 1 + self.rng_faults.below(16) as usize;
            let at = self.rng_faults.below(buf.len() as u64 + 1) as usize;
            let noise: Vec<u8> = (0..n).map(|_| self.rng_faults.below(256) as u8).collect();
            buf.splice(at..at, noise);
        }
        if !self.last_reply.is_empty() && self.rng_faults.chance(faults.repeat_fragment) {
            self.stats.faults.repeated_fragments += 1;
            let len = self.last_reply.len() as u64;
            let from = self.rng_faults.below(len) as usize;
            let n = 1 + self.rng_faults.below(len - from as u64) as usize;
            let fragment = self.last_reply.get(from..from + n).unwrap_or(&[]).to_vec();
            if self.rng_faults.chance(0.5) {
                buf.splice(0..0, fragment);
            } else {
                buf.extend_from_slice(&fragment);
            }
        }
        self.last_reply = clean;
        let start = start.max(self.out_free);
        Some(self.transmit(start, &buf))
    }

    /// Puts `bytes` on the wire from `start`, applying the byte faults. Returns
    /// the time the last byte has left.
    pub(super) fn transmit(&mut self, start: u64, bytes: &[u8]) -> u64 {
        let faults = self.config.faults;
        for (k, &b) in bytes.iter().enumerate() {
            let at = start.saturating_add(wire_time_us(k as u64 + 1));
            if self.silent_at(at) {
                continue;
            }
            if self.rng_faults.chance(faults.drop_byte) {
                self.stats.faults.dropped_bytes += 1;
                continue;
            }
            let mut b = b;
            if self.rng_faults.chance(faults.bit_flip) {
                self.stats.faults.bit_flips += 1;
                b ^= 1 << self.rng_faults.below(8);
            }
            self.out.push_back((at, b));
            self.stats.bytes_sent += 1;
        }
        let end = start.saturating_add(wire_time_us(bytes.len() as u64));
        self.out_free = self.out_free.max(end);
        end
    }
}
