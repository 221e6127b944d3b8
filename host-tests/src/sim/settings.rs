//! The simulated BMS's own settings table (registers 300-399): what 0x1D
//! reports as min / max / default, and how a write is checked.
//!
//! Ranges are Rev D §3.4's. Where Rev D gives none or marks a range "*"
//! (depends on the current sensor: 304, 305, 317, 318) the values below are this
//! simulator's choice, documented on [`sensor_limits`].

use super::config::{CurrentSensor, PackModel};

/// How a settings register is checked on write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    /// Reserved (302, 309, 324-327, 344-399): a write is refused.
    Reserved,
    /// Unsigned 16 bits, `min..=max`.
    Unsigned,
    /// Signed 16 bits (319, 320), `min..=max` as `i16`.
    Signed,
    /// 312 / 313: one u32 over both registers; checked as a whole.
    PulsesPerUnit,
    /// 323 / 328: `min..=max`, or 0xFFFF = "no change" (the value these
    /// registers read back once a write was accepted).
    Marker,
    /// Low byte checked (`min` / `max` low bytes), high byte reserved (kept as
    /// written, unchecked).
    LowByte,
    /// 330: both bytes checked (low: charger type, high: discharge
    /// over-current cutoff timeout).
    TwoBytes,
}

/// One row of the table.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Spec {
    pub kind: Kind,
    pub min: u16,
    pub max: u16,
    pub default: u16,
}

const fn s(kind: Kind, min: u16, max: u16, default: u16) -> Spec {
    Spec {
        kind,
        min,
        max,
        default,
    }
}

const RESERVED: Spec = s(Kind::Reserved, 0, 0, 0);

/// Limits of the sensor-dependent settings, as (min, max, default):
///
/// | sensor            | 304 Charge Finished Current (mA) | 305 Peak Discharge (A) | 317 / 318 (A) |
/// |-------------------|------------------------|--------------|-------------|
/// | internal resistor | 100-5000               | 1-100        | 1-60        |
/// | internal HALL     | 100-5000               | 1-200        | 1-150       |
/// | external          | 1000-50000             | 1-750        | 1-750       |
///
/// Rev D gives 100-5000 mA for 304 and 1-750 A for 317/318, all starred; the
/// per-sensor splits are this simulator's (plausible, not measured).
pub(crate) fn sensor_limits(addr: u16, sensor: CurrentSensor) -> Option<(u16, u16, u16)> {
    use CurrentSensor::*;
    Some(match (addr, sensor) {
        (304, InternalResistor | InternalHall) => (100, 5000, 1000),
        (304, External) => (1000, 50000, 1000),
        (305, InternalResistor) => (1, 100, 60),
        (305, InternalHall) => (1, 200, 60),
        (305, External) => (1, 750, 60),
        (317, InternalResistor) => (1, 60, 60),
        (317, InternalHall) => (1, 150, 60),
        (317, External) => (1, 750, 60),
        (318, InternalResistor) => (1, 60, 30),
        (318, InternalHall) => (1, 150, 30),
        (318, External) => (1, 750, 30),
        _ => return None,
    })
}

/// The table row of settings register `addr` (300-399) for `sensor`; `None`
/// outside 300-399.
pub(crate) fn spec(addr: u16, sensor: CurrentSensor) -> Option<Spec> {
    use Kind::*;
    if let Some((min, max, default)) = sensor_limits(addr, sensor) {
        return Some(s(Unsigned, min, max, default));
    }
    Some(match addr {
        300 => s(Unsigned, 1200, 4500, 3650),
        301 => s(Unsigned, 1000, 3500, 3000),
        303 => s(Unsigned, 1000, 4500, 3400),
        306 => s(Unsigned, 10, 65500, 10000),
        307 => s(Unsigned, 4, 16, 16),
        308 => s(Unsigned, 15, 100, 15),
        310 => s(Unsigned, 5, 60, 20),
        311 => s(Unsigned, 0, 60, 5),
        // 312-313: 1..=100000 as one u32, low word first (0x0001_86A0).
        312 => s(PulsesPerUnit, 1, 0x86A0, 1000),
        313 => s(PulsesPerUnit, 0, 0x0001, 0),
        314 => s(Unsigned, 1, 5, 2),
        315 => s(Unsigned, 1200, 4500, 3650),
        316 => s(Unsigned, 800, 3500, 2500),
        319 => s(Signed, 20, 90, 60),
        320 => s(Signed, (-40i16) as u16, 10, 0),
        321 => s(Unsigned, 60, 95, 90),
        322 => s(Unsigned, 10, 65000, 3000),
        323 => s(Marker, 0, 50000, 50000),
        328 => s(Marker, 0, 50000, 50000),
        329 => s(Unsigned, 0, 0b111, 0),
        330 => s(TwoBytes, 0x0000, 0x1E02, 0x0501),
        331 => s(LowByte, 0, 8, 0),
        332 => s(LowByte, 1, 30, 5),
        333 => s(LowByte, 1, 9, 1),
        334 => s(LowByte, 0, 6, 0),
        335 => s(LowByte, 1, 7, 1),
        336 => s(LowByte, 0, 2, 0),
        337 => s(LowByte, 0, 0x10, 0),
        338 => s(LowByte, 0, 7, 3),
        339 => s(LowByte, 0, 1, 0),
        340 => s(LowByte, 0, 1, 0),
        341 => s(LowByte, 0, 8, 0),
        342 => s(LowByte, 0, 7, 0),
        343 => s(LowByte, 0, 2, 0),
        302 | 309 | 324..=327 | 344..=399 => RESERVED,
        _ => return None,
    })
}

/// Why a write is refused (answered NACK 0x00).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum WriteError {
    /// Outside 300-399 or a reserved register.
    NotWritable,
    /// Outside the min/max this BMS reports through 0x1D.
    OutOfRange,
}

/// Checks the value of `addr` in the candidate register file `regs` (all writes
/// of the request already applied) against the table.
pub(crate) fn check(addr: u16, regs: &[u16], sensor: CurrentSensor) -> Result<(), WriteError> {
    let Some(spec) = spec(addr, sensor) else {
        return Err(WriteError::NotWritable);
    };
    let get = |a: u16| regs.get(usize::from(a)).copied().unwrap_or(0);
    let v = get(addr);
    let ok = match spec.kind {
        Kind::Reserved => return Err(WriteError::NotWritable),
        Kind::Unsigned => (spec.min..=spec.max).contains(&v),
        Kind::Signed => (spec.min as i16..=spec.max as i16).contains(&(v as i16)),
        Kind::PulsesPerUnit => {
            let value = u32::from(get(312)) | (u32::from(get(313)) << 16);
            (1..=100_000).contains(&value)
        }
        Kind::Marker => v == 0xFFFF || (spec.min..=spec.max).contains(&v),
        Kind::LowByte => (spec.min & 0xFF..=spec.max & 0xFF).contains(&(v & 0xFF)),
        Kind::TwoBytes => {
            (spec.min & 0xFF..=spec.max & 0xFF).contains(&(v & 0xFF))
                && (spec.min >> 8..=spec.max >> 8).contains(&(v >> 8))
        }
    };
    if ok {
        Ok(())
    } else {
        Err(WriteError::OutOfRange)
    }
}

/// The settings values (300-343) of a model before clamping to the sensor's
/// limits. 323 and 328 read 0xFFFF as on the real unit (HARDWARE-NOTES).
pub(crate) fn model_values(model: PackModel) -> [(u16, u16); 39] {
    let lfp = model == PackModel::LiFePO4_16S;
    let pick = |a: u16, b: u16| if lfp { a } else { b };
    [
        (300, pick(3650, 4150)),
        (301, pick(2800, 3200)),
        (303, pick(3400, 4000)),
        (304, pick(5000, 1000)),
        (305, pick(120, 80)),
        (306, pick(28000, 5000)),
        (307, model.cell_count() as u16),
        (308, pick(15, 20)),
        (310, 20),
        (311, 5),
        (312, 1000),
        (313, 0),
        (314, 2),
        (315, pick(3650, 4200)),
        (316, pick(2500, 3000)),
        (317, pick(150, 50)),
        (318, pick(90, 25)),
        (319, pick(60, 55)),
        (320, 0),
        (321, pick(90, 85)),
        (322, pick(6000, 1000)),
        (323, 0xFFFF),
        (328, 0xFFFF),
        (329, 0b100),
        (330, 0x0501),
        (331, 0),
        (332, 5),
        (333, 1),
        (334, 0),
        (335, 1),
        (336, 0),
        (337, 0),
        (338, 3),
        (339, 0),
        (340, 0),
        (341, 0),
        (342, 0),
        (343, 0),
        (302, 0),
    ]
}

/// Clamps a model value into the sensor's limits (sensor-dependent settings only).
pub(crate) fn clamp_to_sensor(addr: u16, v: u16, sensor: CurrentSensor) -> u16 {
    match sensor_limits(addr, sensor) {
        Some((min, max, _)) => v.clamp(min, max),
        None => v,
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_models_pass_their_own_checks() {
        for sensor in [
            CurrentSensor::InternalResistor,
            CurrentSensor::InternalHall,
            CurrentSensor::External,
        ] {
            let mut regs = [0u16; 600];
            for a in 300..=399u16 {
                regs[a as usize] = spec(a, sensor).unwrap().default;
            }
            for a in 300..=343u16 {
                if spec(a, sensor).unwrap().kind != Kind::Reserved {
                    assert_eq!(check(a, &regs, sensor), Ok(()), "default {a}");
                }
            }
            for model in [PackModel::LiFePO4_16S, PackModel::LiIon_14S] {
                for (a, v) in model_values(model) {
                    regs[a as usize] = clamp_to_sensor(a, v, sensor);
                }
                for (a, _) in model_values(model) {
                    if a != 302 {
                        assert_eq!(check(a, &regs, sensor), Ok(()), "{model:?} {a}");
                    }
                }
            }
        }
    }

    #[test]
    fn sensor_changes_limits() {
        assert_eq!(spec(317, CurrentSensor::InternalResistor).unwrap().max, 60);
        assert_eq!(spec(318, CurrentSensor::External).unwrap().max, 750);
        assert_eq!(
            spec(302, CurrentSensor::External).unwrap().kind,
            Kind::Reserved
        );
        assert_eq!(spec(299, CurrentSensor::External), None);
        assert_eq!(spec(400, CurrentSensor::External), None);
    }
}
