//! Values hard to get wrong: what a profile line and `tinybms set` accept — a
//! raw integer, a number with the setting's unit (or its milli-unit) converted
//! exactly, an enumeration value's name (as `tinybms settings` prints it) — and
//! what they refuse: a decimal without its unit, another unit, a value between
//! two register steps, an unknown name, a setting given twice.

use host_tests::profile::{parse_profile, snake_name};
use protocol_core::settings::SettingId;
use tinybms::settings::physical;
use tinybms_firmware::bms::profile::{self as fw, parse_value, ProfileErrorKind as K};

fn v(id: SettingId, text: &str) -> Result<i32, K> {
    parse_value(id, text)
}

#[test]
fn numbers_with_units_are_converted_exactly() {
    use SettingId::*;
    for t in [
        "3650", "3.65 V", "3.65V", "3.650 v", "3650 mV", "3650mV", "+3.65 V",
    ] {
        assert_eq!(v(OverVoltageCutoff, t), Ok(3650), "{t}");
    }
    assert_eq!(v(BatteryCapacity, "100 Ah"), Ok(10_000));
    assert_eq!(v(BatteryCapacity, "100000 mAh"), Ok(10_000));
    assert_eq!(v(BatteryCapacity, "0.25 Ah"), Ok(25));
    assert_eq!(v(StateOfHealth, "99.5 %"), Ok(49_750));
    assert_eq!(v(ChargeFinishedCurrent, "1.5 A"), Ok(1500));
    assert_eq!(v(ChargeFinishedCurrent, "1500 mA"), Ok(1500));
    assert_eq!(v(DischargeOverCurrentCutoff, "60 A"), Ok(60));
    for t in ["-10 °C", "-10°C", "-10 C", "-10 degC", "-10"] {
        assert_eq!(v(LowTemperatureChargerCutoff, t), Ok(-10), "{t}");
    }
    assert_eq!(v(ChargerStartupDelay, "20 s"), Ok(20));
}

#[test]
fn what_would_be_a_guess_is_refused() {
    use SettingId::*;
    assert_eq!(v(OverVoltageCutoff, "3.65"), Err(K::DecimalWithoutUnit));
    assert_eq!(v(OverVoltageCutoff, "3.6505 V"), Err(K::NotAStep));
    assert_eq!(v(OverVoltageCutoff, "3650.5 mV"), Err(K::NotAStep));
    assert_eq!(v(OverVoltageCutoff, "3.65 A"), Err(K::WrongUnit));
    assert_eq!(v(OverVoltageCutoff, "3.65 kV"), Err(K::WrongUnit));
    assert_eq!(v(StateOfHealth, "99.501 %"), Err(K::NotAStep));
    assert_eq!(v(DischargeOverCurrentCutoff, "60.5 A"), Err(K::NotAStep));
    assert_eq!(v(DischargeOverCurrentCutoff, "60 mA"), Err(K::NotAStep));
    assert_eq!(v(NumberOfSeriesCells, "16 V"), Err(K::WrongUnit));
    assert_eq!(v(OverVoltageCutoff, "lots"), Err(K::BadValue));
    assert_eq!(v(OverVoltageCutoff, ""), Err(K::BadValue));
    assert_eq!(
        v(OverVoltageCutoff, "99999999999999999 V"),
        Err(K::BadValue)
    );
}

#[test]
fn enumeration_values_by_name() {
    use SettingId::*;
    assert_eq!(v(ChargerType, "CC/CV"), Ok(1));
    assert_eq!(v(ChargerType, "cc cv"), Ok(1));
    assert_eq!(v(ChargerType, "CC/CV (1)"), Ok(1));
    assert_eq!(v(ChargerType, "CC/CV (2)"), Err(K::NotAnOption));
    assert_eq!(v(DistanceUnit, "Kilometer (2)"), Ok(2));
    assert_eq!(v(DistanceUnit, "kilometer"), Ok(2));
    assert_eq!(v(DistanceUnit, "lightyear"), Err(K::NotAnOption));
    assert_eq!(v(LoadSwitchType, "AIHO1 Active Low"), Ok(5));
    assert_eq!(v(LoadSwitchType, "aiho1_active_low"), Ok(5));
    assert_eq!(v(LoadSwitchType, "5"), Ok(5));
    // Rev D names two values of 337 alike: the number decides.
    assert_eq!(v(PrechargePin, "AIHO2 Active High (16)"), Ok(16));
    assert_eq!(v(PrechargePin, "AIHO2 Active High (10)"), Ok(10));
    assert_eq!(v(PrechargePin, "AIHO2 Active High"), Err(K::AmbiguousName));
    assert_eq!(
        v(PrechargePin, "AIHO2 Active High (11)"),
        Err(K::NotAnOption)
    );
}

/// Configuration flags (329) are bits: shown and given by the names of the
/// bits set (they showed as if an enumeration: 2 as bit 2's name, which is 4).
#[test]
fn configuration_flags_are_bits_by_name() {
    use SettingId::ConfigurationFlags as F;
    assert_eq!(physical(F, 0), "none (0)");
    assert_eq!(
        physical(F, 2),
        "Disable Load/Charger Switch Diagnostics (2)"
    );
    assert_eq!(
        physical(F, 5),
        "Invert External Current Sensor Direction + Enable Charger Restart Level (5)"
    );
    assert_eq!(
        v(
            F,
            "Invert External Current Sensor Direction + Enable Charger Restart Level"
        ),
        Ok(5)
    );
    assert_eq!(v(F, "enable charger restart level"), Ok(4));
    assert_eq!(v(F, "none"), Ok(0));
    assert_eq!(v(F, "5"), Ok(5));
    assert_eq!(
        v(F, "Enable Charger Restart Level (5)"),
        Err(K::NotAnOption)
    );
    assert_eq!(v(F, "Enable Turbo"), Err(K::NotAnOption));
}

/// Every value `tinybms settings` prints reads back as the raw value it came
/// from: `3.65 V`, `CC/CV (1)`, `60 A`, `49.75 %` …, for every setting, at the
/// ends of its range and in between.
#[test]
fn what_settings_prints_reads_back_as_the_same_raw_value() {
    let mut checked = 0;
    for &id in SettingId::ALL {
        let r = id.register().unwrap();
        let (lo, hi) = r.range.unwrap_or((0, 100));
        let mut raws: Vec<i32> = vec![lo, hi, lo + (hi - lo) / 3, lo + (hi - lo) / 2];
        if r.value_type == protocol_core::registers::ValueType::Bits {
            raws.extend(0..=hi);
        } else {
            raws.extend(r.options.iter().map(|(v, _)| i32::from(*v)));
        }
        for raw in raws {
            let text = physical(id, i64::from(raw));
            // What the physical text shows is a number and a unit, a bare
            // number (unitless settings), or `Name (N)`.
            let got = v(id, &text);
            assert_eq!(got, Ok(raw), "{}: `{text}`", snake_name(id));
            checked += 1;
        }
    }
    assert!(checked > 150, "{checked}");
}

#[test]
fn the_const_scale_split_agrees_with_the_bridges() {
    for &id in SettingId::ALL {
        let r = id.register().unwrap();
        assert_eq!(
            fw::scale_parts(r.scale),
            tinybms_firmware::units::scale_parts(r),
            "{}",
            snake_name(id)
        );
    }
}

#[test]
fn a_setting_twice_in_a_profile_is_an_error_naming_both_lines() {
    let text = "# x\nover_voltage_cutoff = 3.65 V\n\nunder_voltage_cutoff = 2800\nOver-Voltage Cutoff = 3600 # again\n";
    let e = parse_profile(text).unwrap_err();
    assert!(
        e.contains("line 5") && e.contains("line 2") && e.contains("twice"),
        "{e}"
    );
    // The firmware's start-up profile parser refuses it too (at compile time).
    let p = fw::parse::<8>(text);
    assert!(
        matches!(p, Err(fw::ParseError::Line(l)) if l.kind == K::Duplicate && l.line == 5),
        "{p:?}"
    );
    // Units and names in a profile.
    let ok = parse_profile(
        "over_voltage_cutoff = 3.65 V\ncharger_type = CC/CV\nbattery_capacity = 100 Ah\n",
    )
    .unwrap();
    assert_eq!(
        ok,
        vec![
            (SettingId::OverVoltageCutoff, 3650),
            (SettingId::ChargerType, 1),
            (SettingId::BatteryCapacity, 10_000)
        ]
    );
}

#[test]
fn refusals_say_what_the_setting_takes() {
    let e = parse_profile("over_voltage_cutoff = 3.65\n").unwrap_err();
    assert!(e.contains("in V or mV") && e.contains("0.001"), "{e}");
    let e = parse_profile("charger_type = CCCV2\n").unwrap_err();
    assert!(e.contains("CC/CV"), "{e}");
    let e = parse_profile("over_volatge_cutoff = 3650\n").unwrap_err();
    assert!(e.contains("did you mean `over_voltage_cutoff`"), "{e}");
}
