//! Typed views over register blocks: the live snapshot (0-55), statistics
//! (100-117), the event log (200-297), the version block (500-509).

use crate::events::{Event, OnlineStatus, ResetReason, WakeupReason};
use crate::registers::{self as regs, MAX_CELLS};
use crate::response::{sensor, RegisterBlock};

/// The view needs registers the block does not hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MissingRegisters {
    /// First register needed.
    pub first: u16,
    /// Last register needed.
    pub last: u16,
}

fn need(block: &RegisterBlock, first: u16, last: u16) -> Result<(), MissingRegisters> {
    if block.covers(first, last) {
        Ok(())
    } else {
        Err(MissingRegisters { first, last })
    }
}

/// Cell voltages as measured, with the register the first one came from.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Cells {
    /// Register (0-15) of the first cell reported.
    pub first_register: u8,
    /// Voltages in 0.1 mV.
    pub raw: heapless::Vec<u16, MAX_CELLS>,
}

/// A cell reading (0.1 mV) in mV, rounded to the nearest: the unit of the
/// min/max cell registers 40/41.
pub const fn cell_mv(raw: u16) -> u16 {
    raw.saturating_add(5) / 10
}

impl Cells {
    /// Picks the measured cells out of registers 0-15.
    ///
    /// Real units leave unused inputs at 0, and on a 14S pack the cells sat in
    /// registers 2-15 (HARDWARE-NOTES). So: `count` cells (register 53, at most 16)
    /// starting at the first non-zero register, moved back if that would run past
    /// register 15. A cell reading 0 inside the block is reported as 0 V, not hidden.
    pub fn select(registers: &[u16; MAX_CELLS], count: u16) -> Self {
        let n = (count as usize).min(MAX_CELLS);
        let first_nonzero = registers.iter().position(|&v| v != 0).unwrap_or(0);
        let start = first_nonzero.min(MAX_CELLS - n);
        // start + n <= MAX_CELLS: one slice copy.
        let raw = registers
            .get(start..start + n)
            .and_then(|r| heapless::Vec::from_slice(r).ok())
            .unwrap_or_default();
        Cells {
            first_register: start as u8,
            raw,
        }
    }
    /// Volts of cell `i` (0-based within the reported cells).
    pub fn volts(&self, i: usize) -> Option<f32> {
        self.raw.get(i).map(|&v| f32::from(v) * 0.0001)
    }
    /// (index, raw) of the lowest cell.
    /// The first of equal lowest cells, as `min_by_key`.
    pub fn min(&self) -> Option<(usize, u16)> {
        let (&first, rest) = self.raw.split_first()?;
        let mut best = (0, first);
        for (i, &v) in rest.iter().enumerate() {
            if v < best.1 {
                best = (i + 1, v);
            }
        }
        Some(best)
    }
    /// (index, raw) of the highest cell. The last of equal highest cells, as
    /// `max_by_key`.
    pub fn max(&self) -> Option<(usize, u16)> {
        let (&first, rest) = self.raw.split_first()?;
        let mut best = (0, first);
        for (i, &v) in rest.iter().enumerate() {
            if v >= best.1 {
                best = (i + 1, v);
            }
        }
        Some(best)
    }
}

/// Everything in registers 0-55, decoded (Rev D §3.1).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LiveSnapshot {
    /// Cells (see [`Cells::select`]).
    pub cells: Cells,
    /// Register 53.
    pub cell_count: u16,
    /// Registers 32-33, seconds.
    pub lifetime_s: u32,
    /// Registers 34-35, seconds.
    pub estimated_time_left_s: u32,
    /// Registers 36-37, volts.
    pub pack_voltage_v: f32,
    /// Registers 38-39, amps.
    pub pack_current_a: f32,
    /// Register 40, mV.
    pub min_cell_mv: u16,
    /// Register 41, mV.
    pub max_cell_mv: u16,
    /// Register 42, 0.1 °C, `None` when disconnected.
    pub external1_dc: Option<i16>,
    /// Register 43, 0.1 °C, `None` when disconnected.
    pub external2_dc: Option<i16>,
    /// Register 44, km.
    pub distance_left_km: u16,
    /// Register 45, 0.002 %.
    pub soh_raw: u16,
    /// Registers 46-47, 0.000001 %.
    pub soc_raw: u32,
    /// Register 48, 0.1 °C.
    pub internal_dc: i16,
    /// Register 50.
    pub status: OnlineStatus,
    /// Register 51 (bit 0 = first cell).
    pub balancing_decision_bits: u16,
    /// Register 52.
    pub real_balancing_bits: u16,
    /// Registers 54-55, km/h.
    pub speed_kmh: f32,
}

impl LiveSnapshot {
    /// Decodes registers 0-55 from `block` (which may hold more).
    pub fn from_registers(block: &RegisterBlock) -> Result<Self, MissingRegisters> {
        need(block, regs::LIVE_FIRST, regs::LIVE_LAST)?;
        Ok(Self::decode(block))
    }

    /// As [`LiveSnapshot::from_registers`], written into `out` (left as it was
    /// on an error): built where it is kept instead of returned and moved.
    #[inline(never)]
    pub fn decode_into(
        block: &RegisterBlock,
        out: &mut Option<LiveSnapshot>,
    ) -> Result<(), MissingRegisters> {
        need(block, regs::LIVE_FIRST, regs::LIVE_LAST)?;
        *out = Some(Self::decode(block));
        Ok(())
    }

    /// The decoding of [`LiveSnapshot::from_registers`], registers checked.
    #[inline(always)]
    fn decode(block: &RegisterBlock) -> Self {
        let g = |a: u16| block.get(a).unwrap_or(0);
        let u32_at = |a: u16| block.get_u32(a).unwrap_or(0);
        let f32_at = |a: u16| block.get_f32(a).unwrap_or(0.0);
        let mut cells = [0u16; MAX_CELLS];
        for (i, c) in cells.iter_mut().enumerate() {
            *c = g(i as u16);
        }
        let cell_count = g(53);
        LiveSnapshot {
            cells: Cells::select(&cells, cell_count),
            cell_count,
            lifetime_s: u32_at(32),
            estimated_time_left_s: u32_at(34),
            pack_voltage_v: f32_at(36),
            pack_current_a: f32_at(38),
            min_cell_mv: g(40),
            max_cell_mv: g(41),
            external1_dc: sensor(g(42) as i16),
            external2_dc: sensor(g(43) as i16),
            distance_left_km: g(44),
            soh_raw: g(45),
            soc_raw: u32_at(46),
            internal_dc: g(48) as i16,
            status: OnlineStatus::from_raw(g(50)),
            balancing_decision_bits: g(51),
            real_balancing_bits: g(52),
            speed_kmh: f32_at(54),
        }
    }
    /// SOC in percent.
    pub fn soc_percent(&self) -> f32 {
        (f64::from(self.soc_raw) / 1_000_000.0) as f32
    }
    /// SOH in percent.
    pub fn soh_percent(&self) -> f32 {
        f32::from(self.soh_raw) / 500.0
    }
    /// Internal temperature, °C.
    pub fn internal_c(&self) -> f32 {
        f32::from(self.internal_dc) * 0.1
    }
    /// External sensor 1, °C.
    pub fn external1_c(&self) -> Option<f32> {
        self.external1_dc.map(|v| f32::from(v) * 0.1)
    }
    /// External sensor 2, °C.
    pub fn external2_c(&self) -> Option<f32> {
        self.external2_dc.map(|v| f32::from(v) * 0.1)
    }
}

/// Registers 100-117 (Rev D §3.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Statistics {
    /// 0.01 km.
    pub total_distance_raw: u32,
    /// Peak discharge current seen, 0.1 A.
    pub max_discharge_current_da: u16,
    /// Peak charge current seen, 0.1 A.
    pub max_charge_current_da: u16,
    /// 0.1 mV.
    pub max_cell_difference_raw: u16,
    /// Count.
    pub under_voltage_count: u16,
    /// Count.
    pub over_voltage_count: u16,
    /// Count.
    pub discharge_over_current_count: u16,
    /// Count.
    pub charge_over_current_count: u16,
    /// Count.
    pub over_heat_count: u16,
    /// Count.
    pub charging_count: u16,
    /// Count.
    pub full_charge_count: u16,
    /// °C.
    pub min_pack_temperature_c: i8,
    /// °C.
    pub max_pack_temperature_c: i8,
    /// Register 114 low byte.
    pub last_reset: ResetReason,
    /// Register 114 high byte.
    pub last_wakeup: WakeupReason,
    /// Seconds.
    pub stats_cleared_at_s: u32,
}

impl Statistics {
    /// Decodes registers 100-117 from `block`.
    pub fn from_registers(block: &RegisterBlock) -> Result<Self, MissingRegisters> {
        need(block, regs::STATS_FIRST, regs::STATS_LAST)?;
        let g = |a: u16| block.get(a).unwrap_or(0);
        let [tmin, tmax] = g(113).to_le_bytes();
        let [reset, wake] = g(114).to_le_bytes();
        Ok(Statistics {
            total_distance_raw: block.get_u32(100).unwrap_or(0),
            max_discharge_current_da: g(102),
            max_charge_current_da: g(103),
            max_cell_difference_raw: g(104),
            under_voltage_count: g(105),
            over_voltage_count: g(106),
            discharge_over_current_count: g(107),
            charge_over_current_count: g(108),
            over_heat_count: g(109),
            charging_count: g(111),
            full_charge_count: g(112),
            min_pack_temperature_c: tmin as i8,
            max_pack_temperature_c: tmax as i8,
            last_reset: ResetReason::from_raw(reset),
            last_wakeup: WakeupReason::from_raw(wake),
            stats_cleared_at_s: block.get_u32(116).unwrap_or(0),
        })
    }
}

/// One used slot of the event log registers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct EventSlot {
    /// Slot 0-48.
    pub slot: u8,
    /// The event.
    pub event: Event,
}

/// Decodes the event log from registers 200-297 (Rev D §3.3). Empty slots
/// (all bits 0 or all bits 1) are left out.
pub fn event_log(
    block: &RegisterBlock,
) -> Result<heapless::Vec<EventSlot, { regs::EVENT_SLOTS }>, MissingRegisters> {
    need(block, regs::EVENTS_FIRST, regs::EVENTS_LAST)?;
    let mut out = heapless::Vec::new();
    for slot in 0..regs::EVENT_SLOTS as u16 {
        let a = regs::EVENTS_FIRST + 2 * slot;
        let (first, second) = (block.get(a).unwrap_or(0), block.get(a + 1).unwrap_or(0));
        let both = crate::registers::u32_from_words(first, second);
        if both == 0 || both == u32::MAX {
            continue;
        }
        let _fits = out.push(EventSlot {
            slot: slot as u8,
            event: Event::from_registers(first, second),
        });
    }
    Ok(out)
}

/// BMS current sensor (register 501 BCS bits).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CurrentSensor {
    /// 0: internal resistor.
    InternalResistor,
    /// 1: internal HALL.
    InternalHall,
    /// 2: external.
    External,
    /// 3: undocumented.
    Unknown(u8),
}

/// Registers 500-509 (Rev D §3.5).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VersionInfo {
    /// 500 low byte.
    pub hardware: u8,
    /// 500 high byte.
    pub hardware_changes: u8,
    /// 501 low byte.
    pub firmware_public: u8,
    /// 501 high byte bit 0: true = high power.
    pub high_power: bool,
    /// 501 high byte bits 1-2.
    pub current_sensor: CurrentSensor,
    /// 502.
    pub firmware_internal: u16,
    /// 503 low byte.
    pub bootloader: u8,
    /// 503 high byte.
    pub profile: u8,
    /// 504-509, 96 bits, as the 12 bytes in register order (each register
    /// little-endian).
    pub serial: [u8; 12],
}

impl VersionInfo {
    /// Decodes registers 500-509 from `block`.
    pub fn from_registers(block: &RegisterBlock) -> Result<Self, MissingRegisters> {
        need(block, regs::VERSION_FIRST, regs::VERSION_LAST)?;
        let g = |a: u16| block.get(a).unwrap_or(0);
        let [hw, hwc] = g(500).to_le_bytes();
        let [fw, flags] = g(501).to_le_bytes();
        let [bl, profile] = g(503).to_le_bytes();
        let mut serial = [0u8; 12];
        for (i, pair) in serial.chunks_exact_mut(2).enumerate() {
            pair.copy_from_slice(&g(504 + i as u16).to_le_bytes());
        }
        Ok(VersionInfo {
            hardware: hw,
            hardware_changes: hwc,
            firmware_public: fw,
            high_power: flags & 1 != 0,
            current_sensor: match (flags >> 1) & 0b11 {
                0 => CurrentSensor::InternalResistor,
                1 => CurrentSensor::InternalHall,
                2 => CurrentSensor::External,
                other => CurrentSensor::Unknown(other),
            },
            firmware_internal: g(502),
            bootloader: bl,
            profile,
            serial,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block(start: u16, values: &[u16]) -> RegisterBlock {
        RegisterBlock {
            start,
            values: heapless::Vec::from_slice(values).unwrap(),
        }
    }

    #[test]
    fn cell_min_and_max_pick_as_min_by_key_and_max_by_key() {
        for raw in [
            &[][..],
            &[7],
            &[3, 1, 4, 1, 5, 9, 2, 6, 5, 3, 5, 9],
            &[5, 5, 5],
            &[9, 1, 9, 1],
            &[0, 65535, 0, 65535],
        ] {
            let c = Cells {
                first_register: 0,
                raw: heapless::Vec::from_slice(raw).unwrap(),
            };
            let e = || raw.iter().copied().enumerate();
            assert_eq!(c.min(), e().min_by_key(|&(_, v)| v), "{raw:?}");
            assert_eq!(c.max(), e().max_by_key(|&(_, v)| v), "{raw:?}");
        }
    }

    #[test]
    fn fourteen_cells_in_registers_2_to_15() {
        let mut r = [0u16; 16];
        for (i, v) in r.iter_mut().enumerate().skip(2) {
            *v = 36000 + i as u16;
        }
        let c = Cells::select(&r, 14);
        assert_eq!(c.first_register, 2);
        assert_eq!(c.raw.len(), 14);
        assert_eq!(c.raw[0], 36002);
        assert_eq!(c.min(), Some((0, 36002)));
        assert_eq!(c.max(), Some((13, 36015)));
        // Cells from register 0 on, a dead top cell reads 0 and is kept.
        let mut r = [33000u16; 16];
        r[15] = 0;
        let c = Cells::select(&r, 16);
        assert_eq!((c.first_register, c.raw.len(), c.raw[15]), (0, 16, 0));
        // Register 53 above 16 is clamped.
        assert_eq!(Cells::select(&r, 300).raw.len(), 16);
    }

    #[test]
    fn live_snapshot_from_0_to_55() {
        let mut v = [0u16; 56];
        for c in v.iter_mut().take(16) {
            *c = 33000;
        }
        v[36] = 0x1EB8;
        v[37] = 0x425F;
        let (lo, hi) = crate::registers::words_from_u32((-12.5f32).to_bits());
        v[38] = lo;
        v[39] = hi;
        v[42] = 0x8000;
        v[43] = 215;
        v[45] = 50000;
        let (lo, hi) = crate::registers::words_from_u32(32_800_000);
        v[46] = lo;
        v[47] = hi;
        v[48] = (-15i16) as u16;
        v[50] = 0x93;
        v[53] = 16;
        let s = LiveSnapshot::from_registers(&block(0, &v)).unwrap();
        assert!((s.pack_voltage_v - 55.78).abs() < 0.005);
        assert_eq!(s.pack_current_a, -12.5);
        assert_eq!(s.external1_dc, None);
        assert_eq!(s.external2_c(), Some(21.5));
        assert!((s.soc_percent() - 32.8).abs() < 1e-4);
        assert_eq!(s.soh_percent(), 100.0);
        assert_eq!(s.internal_c(), -1.5);
        assert_eq!(s.status, OnlineStatus::Discharging);
        assert_eq!(s.cells.volts(0), Some(3.3));
        assert_eq!(
            LiveSnapshot::from_registers(&block(0, &v[..55])),
            Err(MissingRegisters { first: 0, last: 55 })
        );
    }

    #[test]
    fn statistics_and_version() {
        let mut v = [0u16; 18];
        v[13] = u16::from_le_bytes([(-5i8) as u8, 41]);
        v[14] = 0x0304;
        let s = Statistics::from_registers(&block(100, &v)).unwrap();
        assert_eq!(
            (s.min_pack_temperature_c, s.max_pack_temperature_c),
            (-5, 41)
        );
        assert_eq!(s.last_reset, ResetReason::Software);
        assert_eq!(s.last_wakeup, WakeupReason::UartCommunication);
        let mut v = [0u16; 10];
        v[0] = 0x0001;
        v[1] = 0x0514; // FW 20; flags 0b101: bit 0 high power, bits 1-2 = 2 external sensor
        v[2] = 58;
        v[3] = 0x0502;
        v[4] = 0x3412;
        let ver = VersionInfo::from_registers(&block(500, &v)).unwrap();
        assert_eq!(
            (ver.hardware, ver.firmware_public, ver.firmware_internal),
            (1, 20, 58)
        );
        assert!(ver.high_power);
        assert_eq!(ver.current_sensor, CurrentSensor::External);
        assert_eq!((ver.bootloader, ver.profile), (2, 5));
        assert_eq!(&ver.serial[..2], &[0x12, 0x34]);
    }

    #[test]
    fn event_log_skips_empty_slots() {
        let mut v = [0u16; 98];
        v[0] = 0x2810;
        v[1] = 0x623B;
        v[4] = 0xFFFF;
        v[5] = 0xFFFF;
        let log = event_log(&block(200, &v)).unwrap();
        assert_eq!(log.len(), 1);
        assert_eq!(log[0].event.timestamp_s, 0x3B2810);
    }
}
