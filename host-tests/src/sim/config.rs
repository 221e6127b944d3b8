//! Configuration of the simulated BMS: pack model, current sensor, timing,
//! sleep, fault injection. Builder style (`SimConfig::default().with_..(..)`).

/// Which pack the simulated BMS manages. Sets the cell count and layout, the
/// chemistry (open-circuit voltage curve), the capacity and the settings values.
#[allow(non_camel_case_types)] // the names say chemistry and series count, as on the label
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PackModel {
    /// 16 LiFePO4 cells (~3.30 V), 280 Ah, cells in registers 0-15, both
    /// external temperature sensors connected.
    LiFePO4_16S,
    /// 14 Li-ion (NMC) cells (~3.9 V), 50 Ah, laid out as on the real 14S unit of
    /// HARDWARE-NOTES: registers 0 and 1 read 0, the cells are in registers 2-15;
    /// external sensor 2 disconnected (-32768).
    LiIon_14S,
}

impl PackModel {
    /// Cells in series (register 53, setting 307).
    pub const fn cell_count(self) -> usize {
        match self {
            Self::LiFePO4_16S => 16,
            Self::LiIon_14S => 14,
        }
    }
    /// Register holding the first cell (HARDWARE-NOTES: 2 on the real 14S unit).
    pub const fn first_cell_register(self) -> u16 {
        match self {
            Self::LiFePO4_16S => 0,
            Self::LiIon_14S => 2,
        }
    }
}

/// Current sensor fitted (register 501, BCS bits; Rev D §3.5). The min/max of
/// settings 304, 305, 317 and 318 depend on it (Rev D §3.4 "*", HARDWARE-NOTES).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum CurrentSensor {
    /// BCS 0: internal shunt resistor (317/318 up to 60 A).
    #[default]
    InternalResistor,
    /// BCS 1: internal HALL sensor (317/318 up to 150 A).
    InternalHall,
    /// BCS 2: external sensor (317/318 up to 750 A).
    External,
}

impl CurrentSensor {
    /// BCS bits value (Rev D §3.5).
    pub const fn bcs(self) -> u16 {
        match self {
            Self::InternalResistor => 0,
            Self::InternalHall => 1,
            Self::External => 2,
        }
    }
}

/// Seeded fault injection. Every rate is a probability in `0.0..=1.0`; 0 disables
/// the fault (and draws no random number, so other faults keep their stream).
///
/// Byte faults apply to every byte the BMS puts on the wire (binary replies and
/// ASCII broadcast lines); reply faults to binary replies (ACK, NACK, data);
/// `no_reply` to complete requests (the request is lost as if it had never
/// arrived: no reply and no side effect).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FaultConfig {
    /// Per output byte: the byte is lost (its wire time still passes).
    pub drop_byte: f64,
    /// Per output byte: one random bit of the byte is inverted.
    pub bit_flip: f64,
    /// Per reply: only a random non-empty strict prefix of the reply is sent.
    pub truncate: f64,
    /// Per request: the request is lost (no reply, no effect).
    pub no_reply: f64,
    /// Per reply: the reply is sent twice, back to back.
    pub duplicate: f64,
    /// Per reply: the reply starts [`FaultConfig::delay_us`] later than normal.
    pub delay: f64,
    /// Extra delay of a delayed reply, µs.
    pub delay_us: u64,
    /// Per reply byte: a random byte is inserted after it (a glitch on the line
    /// read as a start bit).
    pub insert_byte: f64,
    /// Per reply: a burst of 1-16 random bytes lands at a random point of it.
    pub noise_burst: f64,
    /// Per reply: a fragment of the previous reply (random start and length) is
    /// sent right before or after it — the pattern that makes a damaged reply run
    /// into bytes that look like the start of a frame, and now and then yields a
    /// CRC-valid frame that was never sent.
    pub repeat_fragment: f64,
}

impl FaultConfig {
    /// No fault at all.
    pub const NONE: Self = Self {
        drop_byte: 0.0,
        bit_flip: 0.0,
        truncate: 0.0,
        no_reply: 0.0,
        duplicate: 0.0,
        delay: 0.0,
        delay_us: 0,
        insert_byte: 0.0,
        noise_burst: 0.0,
        repeat_fragment: 0.0,
    };

    /// Every fault kind at once, as the `sim` command's `--fault-rate R` sets
    /// them: R per reply byte corrupted (dropped, flipped or an extra byte
    /// inserted, a third each), and R per reply of truncation, lost request,
    /// duplicate, delay (150 ms), noise burst and repeated fragment.
    pub fn all(r: f64) -> Self {
        Self {
            drop_byte: r / 3.0,
            bit_flip: r / 3.0,
            insert_byte: r / 3.0,
            truncate: r,
            no_reply: r,
            duplicate: r,
            delay: r,
            delay_us: 150_000,
            noise_burst: r,
            repeat_fragment: r,
        }
    }
}

/// Simulator configuration. `SimConfig::default()` is an awake, fault-free BMS
/// with live values, an internal resistor current sensor, that never sleeps.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Current sensor fitted (settings limits, register 501).
    pub current_sensor: CurrentSensor,
    /// Sleep after this long without a byte from the host (`None` = never).
    pub sleep_after_us: Option<u64>,
    /// Start asleep: the first request only wakes the BMS.
    pub start_asleep: bool,
    /// Silence after a reset (0x02 option 0x05, or a write to register 340)
    /// before the BMS answers again and logs "System Started".
    pub boot_time_us: u64,
    /// Move the live values (current, SOC, cells, temperatures, lifetime
    /// counter...) with virtual time. `false` freezes every register except
    /// what commands and [`crate::sim::SimBms::set_register`] change — handy for
    /// byte-exact tests.
    pub live: bool,
    /// Reply latency after the last request byte, drawn uniformly in this
    /// inclusive range, µs (HARDWARE-NOTES: 1-2 ms).
    pub reply_latency_us: (u64, u64),
    /// A partial request is dropped when the gap before its next byte exceeds
    /// this, µs.
    pub idle_gap_us: u64,
    /// Most events one 0x11 reply returns (the newest ones).
    pub newest_events_max: usize,
    /// Packet ID of the first packet of a multi-packet native reply. 1 by
    /// default (protocol-core's encoder); HARDWARE-NOTES saw 0x82, i.e. 2.
    pub first_packet_id: u8,
    /// After an accepted settings write, requests arriving within this long are
    /// ignored (EEPROM busy; HARDWARE-NOTES "unproven"). 0 = off.
    pub settle_after_write_us: u64,
    /// Seeded fault injection.
    pub faults: FaultConfig,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            current_sensor: CurrentSensor::InternalResistor,
            sleep_after_us: None,
            start_asleep: false,
            boot_time_us: 1_000_000,
            live: true,
            reply_latency_us: (1_000, 2_000),
            idle_gap_us: 5_000,
            newest_events_max: 16,
            first_packet_id: 1,
            settle_after_write_us: 0,
            faults: FaultConfig::NONE,
        }
    }
}

impl SimConfig {
    /// Sets [`SimConfig::current_sensor`].
    pub fn with_current_sensor(mut self, s: CurrentSensor) -> Self {
        self.current_sensor = s;
        self
    }
    /// Sets [`SimConfig::sleep_after_us`].
    pub fn with_sleep_after_us(mut self, t: Option<u64>) -> Self {
        self.sleep_after_us = t;
        self
    }
    /// Sets [`SimConfig::start_asleep`].
    pub fn with_start_asleep(mut self, v: bool) -> Self {
        self.start_asleep = v;
        self
    }
    /// Sets [`SimConfig::boot_time_us`].
    pub fn with_boot_time_us(mut self, t: u64) -> Self {
        self.boot_time_us = t;
        self
    }
    /// Sets [`SimConfig::live`].
    pub fn with_live(mut self, v: bool) -> Self {
        self.live = v;
        self
    }
    /// Sets [`SimConfig::reply_latency_us`].
    pub fn with_reply_latency_us(mut self, min: u64, max: u64) -> Self {
        self.reply_latency_us = (min, max);
        self
    }
    /// Sets [`SimConfig::newest_events_max`].
    pub fn with_newest_events_max(mut self, n: usize) -> Self {
        self.newest_events_max = n;
        self
    }
    /// Sets [`SimConfig::first_packet_id`].
    pub fn with_first_packet_id(mut self, id: u8) -> Self {
        self.first_packet_id = id;
        self
    }
    /// Sets [`SimConfig::settle_after_write_us`].
    pub fn with_settle_after_write_us(mut self, t: u64) -> Self {
        self.settle_after_write_us = t;
        self
    }
    /// Sets [`SimConfig::faults`].
    pub fn with_faults(mut self, f: FaultConfig) -> Self {
        self.faults = f;
        self
    }
}
