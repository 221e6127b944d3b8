//! Events, online status, reset and wake-up reasons (Rev D chapter 4, §3.1 reg 50,
//! §3.2 reg 114) as open enums: an unknown value is kept, never an error.

/// How serious an event is (Rev D chapter 4 groups IDs by range).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Severity {
    /// Informational (IDs 0x61-0x90).
    Info,
    /// Warning (IDs 0x31-0x60).
    Warning,
    /// Fault (IDs 0x01-0x30).
    Fault,
    /// Outside every documented range.
    Unknown,
}

impl Severity {
    /// Lower-case name.
    pub const fn name(self) -> &'static str {
        match self {
            Severity::Info => "info",
            Severity::Warning => "warning",
            Severity::Fault => "fault",
            Severity::Unknown => "unknown",
        }
    }
}

macro_rules! open_enum {
    (
        $(#[$m:meta])* $name:ident : $raw:ty {
            $( $(#[$vm:meta])* $variant:ident = $value:literal => $text:literal ),* $(,)?
        }
    ) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        pub enum $name {
            $( $(#[$vm])* $variant, )*
            /// A value this crate does not know, kept as received.
            Unknown($raw),
        }

        impl $name {
            /// Every known value, in document order.
            pub const KNOWN: &'static [$name] = &[$($name::$variant),*];

            /// From the raw value.
            pub const fn from_raw(raw: $raw) -> Self {
                match raw {
                    $( $value => $name::$variant, )*
                    other => $name::Unknown(other),
                }
            }
            /// To the raw value.
            pub const fn raw(self) -> $raw {
                match self {
                    $( $name::$variant => $value, )*
                    $name::Unknown(v) => v,
                }
            }
            /// The document's name for the value, or "Unknown".
            pub const fn name(self) -> &'static str {
                match self {
                    $( $name::$variant => $text, )*
                    $name::Unknown(_) => "Unknown",
                }
            }
        }
    };
}

open_enum! {
    /// Event message ID (Rev D chapter 4).
    EventId: u8 {
        /// 0x02
        UnderVoltageCutoff = 0x02 => "Under-Voltage Cutoff Occurred",
        /// 0x03
        OverVoltageCutoff = 0x03 => "Over-Voltage Cutoff Occurred",
        /// 0x04
        OverTemperatureCutoff = 0x04 => "Over-Temperature Cutoff Occurred",
        /// 0x05
        DischargingOverCurrentCutoff = 0x05 => "Discharging Over-Current Cutoff Occurred",
        /// 0x06
        ChargingOverCurrentCutoff = 0x06 => "Charging Over-Current Cutoff Occurred",
        /// 0x07
        RegenerationOverCurrentCutoff = 0x07 => "Regeneration Over-Current Cutoff Occurred",
        /// 0x0A
        LowTemperatureCutoff = 0x0A => "Low Temperature Cutoff Occurred",
        /// 0x0B
        ChargerSwitchError = 0x0B => "Charger Switch Error Detected",
        /// 0x0C
        LoadSwitchError = 0x0C => "Load Switch Error Detected",
        /// 0x0D
        SinglePortSwitchError = 0x0D => "Single Port Switch Error Detected",
        /// 0x0E
        ExternalCurrentSensorDisconnectedRestart = 0x0E => "External Current Sensor Disconnected (BMS restart required)",
        /// 0x0F
        ExternalCurrentSensorConnectedRestart = 0x0F => "External Current Sensor Connected (BMS restart required)",
        /// 0x31
        FullyDischargedCutoff = 0x31 => "Fully Discharged Cutoff Occurred",
        /// 0x37
        LowTemperatureChargingCutoff = 0x37 => "Low Temperature Charging Cutoff Occurred",
        /// 0x38
        ChargingDoneVoltageTooHigh = 0x38 => "Charging Done (Charger voltage too high)",
        /// 0x39
        ChargingDoneVoltageTooLow = 0x39 => "Charging Done (Charger voltage too low)",
        /// 0x61
        SystemStarted = 0x61 => "System Started",
        /// 0x62
        ChargingStarted = 0x62 => "Charging Started",
        /// 0x63
        ChargingDone = 0x63 => "Charging Done",
        /// 0x64
        ChargerConnected = 0x64 => "Charger Connected",
        /// 0x65
        ChargerDisconnected = 0x65 => "Charger Disconnected",
        /// 0x66
        DualPortModeActivated = 0x66 => "Dual Port Operation Mode Activated",
        /// 0x67
        SinglePortModeActivated = 0x67 => "Single Port Operation Mode Activated",
        /// 0x73
        RecoveredOverTemperature = 0x73 => "Recovered From Over-Temperature Fault Condition",
        /// 0x74
        RecoveredLowTemperatureWarning = 0x74 => "Recovered From Low Temperature Warning Condition",
        /// 0x75
        RecoveredLowTemperatureFault = 0x75 => "Recovered From Low Temperature Fault Condition",
        /// 0x76
        RecoveredChargingOverCurrent = 0x76 => "Recovered From Charging Over-Current Fault Condition",
        /// 0x77
        RecoveredDischargingOverCurrent = 0x77 => "Recovered From Discharging Over-Current Fault Condition",
        /// 0x78
        RecoveredRegenerationOverCurrent = 0x78 => "Recovered From Regeneration Over-Current Fault Condition",
        /// 0x79
        RecoveredOverVoltage = 0x79 => "Recovered From Over-Voltage Fault Condition",
        /// 0x7A
        RecoveredFullyDischarged = 0x7A => "Recovered From Fully Discharged Voltage Warning Condition",
        /// 0x7B
        RecoveredUnderVoltage = 0x7B => "Recovered From Under-Voltage Fault Condition",
        /// 0x7C
        ExternalCurrentSensorConnected = 0x7C => "External Current Sensor Connected",
        /// 0x7D
        ExternalCurrentSensorDisconnected = 0x7D => "External Current Sensor Disconnected",
    }
}

impl EventId {
    /// Severity by the ID ranges of Rev D chapter 4 (known or not).
    pub const fn severity(self) -> Severity {
        match self.raw() {
            0x01..=0x30 => Severity::Fault,
            0x31..=0x60 => Severity::Warning,
            0x61..=0x90 => Severity::Info,
            _ => Severity::Unknown,
        }
    }
}

open_enum! {
    /// BMS online status, register 50 / command 0x18 (Rev D §1.1.15, §3.1).
    OnlineStatus: u16 {
        /// 0x91
        Charging = 0x91 => "Charging",
        /// 0x92
        FullyCharged = 0x92 => "Fully Charged",
        /// 0x93
        Discharging = 0x93 => "Discharging",
        /// 0x96
        Regeneration = 0x96 => "Regeneration",
        /// 0x97
        Idle = 0x97 => "Idle",
        /// 0x9B
        Fault = 0x9B => "Fault",
    }
}

impl OnlineStatus {
    /// Rev D marks Fault as `[ERROR]` and the others as `[INFO]`.
    pub const fn severity(self) -> Severity {
        match self {
            OnlineStatus::Fault => Severity::Fault,
            OnlineStatus::Unknown(_) => Severity::Unknown,
            _ => Severity::Info,
        }
    }
    /// snake_case key: `charging`, `fully_charged`, ..., or `None` when unknown.
    pub const fn key(self) -> Option<&'static str> {
        match self {
            OnlineStatus::Charging => Some("charging"),
            OnlineStatus::FullyCharged => Some("fully_charged"),
            OnlineStatus::Discharging => Some("discharging"),
            OnlineStatus::Regeneration => Some("regeneration"),
            OnlineStatus::Idle => Some("idle"),
            OnlineStatus::Fault => Some("fault"),
            OnlineStatus::Unknown(_) => None,
        }
    }
}

open_enum! {
    /// Last BMS reset event, register 114 low byte (Rev D §3.2).
    ResetReason: u8 {
        /// 0x00
        Unspecified = 0x00 => "Unknown",
        /// 0x01
        LowPower = 0x01 => "Low power reset",
        /// 0x02
        WindowWatchdog = 0x02 => "Window watchdog reset",
        /// 0x03
        IndependentWatchdog = 0x03 => "Independent watchdog reset",
        /// 0x04
        Software = 0x04 => "Software reset",
        /// 0x05
        PowerOn = 0x05 => "POR/PDR reset",
        /// 0x06
        Pin = 0x06 => "PIN reset",
        /// 0x07
        OptionBytesLoading = 0x07 => "Options bytes loading reset",
    }
}

open_enum! {
    /// Last wake-up from sleep, register 114 high byte (Rev D §3.2).
    WakeupReason: u8 {
        /// 0x00
        ChargerConnected = 0x00 => "Charger connected",
        /// 0x01
        Ignition = 0x01 => "Ignition",
        /// 0x02
        DischargingDetected = 0x02 => "Discharging detected",
        /// 0x03
        UartCommunication = 0x03 => "UART communication detected",
    }
}

/// One entry of the event log: 24-bit timestamp in seconds and an event ID
/// (Rev D §1.1.9, §3.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Event {
    /// Seconds, 24 bits (BMS lifetime clock).
    pub timestamp_s: u32,
    /// What happened.
    pub id: EventId,
}

impl Event {
    /// Largest 24-bit timestamp.
    pub const MAX_TIMESTAMP: u32 = 0x00FF_FFFF;

    /// From the four wire bytes `TSP:LSB TSP TSP:MSB ID`.
    pub const fn from_bytes(b: [u8; 4]) -> Self {
        Event {
            timestamp_s: u32::from_le_bytes([b[0], b[1], b[2], 0]),
            id: EventId::from_raw(b[3]),
        }
    }
    /// To the four wire bytes (timestamp truncated to 24 bits).
    pub const fn to_bytes(self) -> [u8; 4] {
        let t = self.timestamp_s.to_le_bytes();
        [t[0], t[1], t[2], self.id.raw()]
    }
    /// From the two registers of an event slot (Rev D §3.3): the first holds the
    /// timestamp's low 16 bits, the second its high 8 bits (low byte) and the ID
    /// (high byte).
    pub const fn from_registers(first: u16, second: u16) -> Self {
        let f = first.to_le_bytes();
        let s = second.to_le_bytes();
        Self::from_bytes([f[0], f[1], s[0], s[1]])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_enums_keep_unknown_values() {
        for raw in 0..=255u8 {
            assert_eq!(EventId::from_raw(raw).raw(), raw);
            assert_eq!(ResetReason::from_raw(raw).raw(), raw);
            assert_eq!(WakeupReason::from_raw(raw).raw(), raw);
        }
        for raw in [0u16, 0x91, 0x9B, 0x1234, 0xFFFF] {
            assert_eq!(OnlineStatus::from_raw(raw).raw(), raw);
        }
        assert_eq!(EventId::from_raw(0x99), EventId::Unknown(0x99));
        assert_eq!(EventId::from_raw(0x99).severity(), Severity::Unknown);
        assert_eq!(EventId::from_raw(0x20).severity(), Severity::Fault);
    }

    #[test]
    fn chapter_4_names_and_severity() {
        assert_eq!(EventId::KNOWN.len(), 12 + 4 + 18);
        assert_eq!(
            EventId::from_raw(0x02).name(),
            "Under-Voltage Cutoff Occurred"
        );
        assert_eq!(EventId::from_raw(0x31).severity(), Severity::Warning);
        assert_eq!(EventId::from_raw(0x61).name(), "System Started");
        assert_eq!(EventId::from_raw(0x7D).severity(), Severity::Info);
        for id in EventId::KNOWN {
            assert_ne!(id.severity(), Severity::Unknown);
        }
        assert_eq!(OnlineStatus::from_raw(0x9B).severity(), Severity::Fault);
        assert_eq!(OnlineStatus::from_raw(0x96).key(), Some("regeneration"));
    }

    #[test]
    fn event_bytes_round_trip() {
        // 000 example 5: TSP = 0x3B2810, ID 0x62.
        let e = Event::from_bytes([0x10, 0x28, 0x3B, 0x62]);
        assert_eq!(e.timestamp_s, 0x3B2810);
        assert_eq!(e.id, EventId::ChargingStarted);
        assert_eq!(e.to_bytes(), [0x10, 0x28, 0x3B, 0x62]);
        assert_eq!(Event::from_registers(0x2810, 0x623B), e);
    }
}
