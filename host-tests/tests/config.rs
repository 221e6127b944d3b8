//! The bridge's configuration record (`tinybms_firmware::config`): the field
//! table, every field's range and text form, the rules between fields, the flash
//! codec (round trip, other versions, corrupted and fuzzed bytes), and changes
//! by name with one outcome per field.

#![allow(clippy::field_reassign_with_default)]

use proptest::prelude::*;
use tinybms_firmware::config::codec::{self, DecodeError, MAGIC, RECORD_MAX};
use tinybms_firmware::config::state::{ConfigState, Outcome};
use tinybms_firmware::config::store::Source;
use tinybms_firmware::config::value::{self, Parsed};
use tinybms_firmware::config::{
    Applies, Config, FieldId, Kind, PackSettings, Value, FIELDS, VERSION,
};
use tinybms_firmware::inverter::{InverterConfig, Protocol, StaleMode};
use tinybms_firmware::text::Line;
use tinybms_firmware::SECOND;

fn field(name: &str) -> FieldId {
    FieldId::from_name(name).unwrap_or_else(|| panic!("no field {name}"))
}

fn parse(name: &str, text: &str) -> Result<Parsed, value::FieldError> {
    value::parse(field(name).field(), text)
}

fn shown(c: &Config, id: FieldId) -> String {
    let mut l = Line::new();
    value::write(id.field(), &c.get(id), true, &mut l);
    l.as_str().to_string()
}

fn bms() -> PackSettings {
    PackSettings {
        fully_charged_mv: 3450,
        capacity_cah: 28_000,
        cells: 16,
        allowed_disbalance_mv: 15,
        ov_cutoff_mv: 3650,
        uv_cutoff_mv: 2800,
        discharge_cutoff_a: 150,
        charge_cutoff_a: 100,
        discharge_cutoff_s: 5,
        overheat_c: 55,
        low_temp_charge_c: 2,
    }
}

#[test]
fn the_table_is_consistent() {
    let mut names = std::collections::HashSet::new();
    let mut tags = std::collections::HashSet::new();
    for f in FIELDS {
        assert!(names.insert(f.name), "name {} twice", f.name);
        assert!(tags.insert(f.tag), "tag {} twice", f.tag);
        assert_eq!(f.id.field().name, f.name);
        assert_eq!(FieldId::from_name(f.name), Some(f.id));
        assert_eq!(FieldId::from_tag(f.tag), Some(f.id));
        assert!(
            f.name
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_'),
            "{}",
            f.name
        );
        assert!(f.help.ends_with('.'), "{}: help is a sentence", f.name);
        if let Kind::Number { min, max, .. } = f.kind {
            assert!(min <= max, "{}", f.name);
        }
    }
}

#[test]
fn the_defaults_are_what_the_bridge_ran_with_before_the_record() {
    let c = Config::default();
    c.validate().unwrap();
    // What firmware/src/site.rs compiled in before the record (CAN on, Victron,
    // stop sending on stale data, read-write, 1 s stream), and charge
    // control's defaults.
    assert!(c.can_output);
    assert_eq!(c.protocol, Protocol::Victron);
    assert_eq!(c.inverter(), InverterConfig::default());
    assert!(!c.read_only);
    assert_eq!(c.stream_period_ms, 1000);
    assert!(c.wifi_ssid.is_empty() && c.mqtt_host.is_empty());
    // Every default passes its own field's check.
    for f in FIELDS {
        value::check(f, &c.get(f.id)).unwrap_or_else(|e| panic!("{}: {e:?}", f.name));
    }
}

#[test]
fn every_number_field_takes_its_range_and_refuses_one_step_beyond() {
    for f in FIELDS {
        let Kind::Number {
            min,
            max,
            decimals,
            off,
        } = f.kind
        else {
            continue;
        };
        let mut c = Config::default();
        for v in [min, max, (min + max) / 2] {
            c.set(f.id, Value::Number(v)).unwrap();
            assert_eq!(c.get(f.id), Value::Number(v), "{}", f.name);
            // Its text reads back to the same raw value, with and without unit.
            for unit in [true, false] {
                let mut l = Line::new();
                value::write(f, &Value::Number(v), unit, &mut l);
                let back = value::parse(f, l.as_str()).unwrap();
                assert_eq!(back, Parsed::Number(v), "{}: {}", f.name, l.as_str());
            }
        }
        for v in [min - 1, max + 1] {
            if v == 0 && off.is_some() {
                continue;
            }
            let e = c.set(f.id, Value::Number(v)).unwrap_err();
            assert!(e.out_of_range, "{}: {v}", f.name);
        }
        match off {
            Some(word) => {
                c.set(f.id, Value::Number(0)).unwrap();
                assert_eq!(value::parse(f, word).unwrap(), Parsed::Number(0));
                assert_eq!(shown(&c, f.id), word);
            }
            None if min > 0 => assert!(c.set(f.id, Value::Number(0)).is_err(), "{}", f.name),
            None => {}
        }
        // More decimals than the field holds are refused, not rounded.
        let mut l = Line::new();
        l.fixed(i64::from(min) * 10 + 1, u32::from(decimals) + 1);
        assert!(
            value::parse(f, l.as_str()).is_err(),
            "{}: {}",
            f.name,
            l.as_str()
        );
    }
}

#[test]
fn numbers_parse_exactly_in_related_units() {
    assert_eq!(
        parse("absorption_voltage", "3.45 V").unwrap(),
        Parsed::Number(3450)
    );
    assert_eq!(
        parse("absorption_voltage", "3450mV").unwrap(),
        Parsed::Number(3450)
    );
    assert_eq!(
        parse("charge_current_cap", "50 A").unwrap(),
        Parsed::Number(500)
    );
    assert_eq!(
        parse("charge_current_cap", "50.5a").unwrap(),
        Parsed::Number(505)
    );
    assert_eq!(
        parse("charge_current_cap", "none").unwrap(),
        Parsed::Number(0)
    );
    assert_eq!(
        parse("stream_period", "1.5 s").unwrap(),
        Parsed::Number(1500)
    );
    assert_eq!(parse("stream_period", "off").unwrap(), Parsed::Number(0));
    assert_eq!(parse("stale_hold", "2 min").unwrap(), Parsed::Number(120));
    // Issue 26, item 13: durations as the help writes them, and the related
    // units docs/configuration.md promises.
    assert_eq!(parse("stale_hold", "2m").unwrap(), Parsed::Number(120));
    assert_eq!(
        parse("stream_period", "1m").unwrap(),
        Parsed::Number(60_000)
    );
    assert_eq!(
        parse("charge_current_cap", "50000mA").unwrap(),
        Parsed::Number(500)
    );
    assert!(
        parse("charge_current_cap", "50050mA").is_err(),
        "0.05 A: finer than the field"
    );
    assert_eq!(
        parse("temperature_margin", "5 °C").unwrap(),
        Parsed::Number(5)
    );
    // Refused: a unit of another quantity, too many decimals, not a number.
    assert!(parse("charge_current_cap", "50 V").is_err());
    assert!(parse("charge_current_cap", "0.15 A").is_err());
    assert!(parse("absorption_voltage", "3.4505 V").is_err());
    assert!(parse("stale_after", "five").is_err());
    assert!(parse("stale_after", "").is_err());
    assert!(parse("stale_after", "1e3").is_err());
    // Out of range, with that code.
    let e = parse("charge_current_cap", "9999 A").unwrap_err();
    assert!(e.out_of_range);
    let e = parse("stale_after", "0").unwrap_err();
    assert!(e.out_of_range);
}

#[test]
fn choices_switches_text_and_secrets() {
    assert_eq!(
        parse("inverter_protocol", "SMA").unwrap(),
        Parsed::Choice(1)
    );
    assert!(parse("inverter_protocol", "pylontech").is_err());
    for (t, b) in [("on", true), ("off", false), ("yes", true), ("0", false)] {
        assert_eq!(parse("can_output", t).unwrap(), Parsed::Bool(b));
    }
    assert!(parse("can_output", "maybe").is_err());
    assert!(parse("mqtt_host", "broker.lan").is_ok());
    assert!(parse("mqtt_host", "192.168.1.10").is_ok());
    assert!(parse("mqtt_host", "bad host").is_err());
    assert!(parse("topic_prefix", "home/battery-1").is_ok());
    for bad in ["home/#", "a/+/b", "/lead", "trail/", "a//b", ""] {
        assert!(parse("topic_prefix", bad).is_err(), "{bad}");
    }
    assert!(parse("wifi_ssid", &"x".repeat(33)).is_err());
    assert!(parse("wifi_ssid", "Café WLAN ").is_ok());
    assert!(parse("wifi_ssid", "a\u{7}b").is_err());
    // The Wi-Fi key is 64 hex digits or nothing; never shown.
    let key = "0123456789abcdef".repeat(4);
    let mut c = Config::default();
    c.set(field("wifi_ssid"), Value::Text("home")).unwrap();
    c.set(field("wifi_key"), Value::Text(&key)).unwrap();
    assert_eq!(shown(&c, field("wifi_key")), "set");
    assert!(c.set(field("wifi_key"), Value::Text("passphrase")).is_err());
    assert!(c.set(field("wifi_key"), Value::Text(&key[1..])).is_err());
    c.set(field("wifi_key"), Value::Text("")).unwrap();
    assert_eq!(shown(&c, field("wifi_key")), "unset");
}

#[test]
fn rules_between_fields() {
    let mut c = Config::default();
    c.absorption_voltage_mv = 3400;
    c.float_voltage_mv = 3450;
    assert_eq!(c.validate().unwrap_err().field, field("float_voltage"));
    let mut c = Config::default();
    c.wifi_key.push_str(&"a".repeat(64)).unwrap();
    assert_eq!(c.validate().unwrap_err().field, field("wifi_key"));
    let mut c = Config::default();
    c.topic_prefix = c.discovery_prefix.clone();
    assert!(c.validate().is_err());
    c.discovery = false;
    assert!(c.validate().is_ok());
    // Against the BMS: a cap above the cutoff it caps, a target past the cutoffs.
    let mut c = Config::default();
    c.charge_current_cap_da = 1001; // 100.1 A, the BMS allows 100 A
    assert_eq!(
        c.validate_with_bms(&bms()).unwrap_err().field,
        field("charge_current_cap")
    );
    c.charge_current_cap_da = 1000;
    assert!(c.validate_with_bms(&bms()).is_ok());
    c.discharge_current_cap_da = 1501;
    assert!(c.validate_with_bms(&bms()).is_err());
    let mut c = Config::default();
    c.absorption_voltage_mv = 3600; // 3650 - 100 margin = 3550 at most
    assert_eq!(
        c.validate_with_bms(&bms()).unwrap_err().field,
        field("absorption_voltage")
    );
    c.absorption_voltage_mv = 2800; // at the under-voltage cutoff
    assert!(c.validate_with_bms(&bms()).is_err());
}

#[test]
fn fields_tied_by_a_rule_take_effect_together() {
    // A running record mixes the start-up record's restart fields with the
    // newest at-once fields: each rule's fields must apply at the same time, or
    // the mix could break it.
    for group in [
        ["absorption_voltage", "float_voltage"],
        ["wifi_ssid", "wifi_key"],
        ["mqtt_user", "mqtt_password"],
        ["topic_prefix", "discovery_prefix"],
    ] {
        let a = field(group[0]).field().applies;
        let b = field(group[1]).field().applies;
        assert_eq!(a, b, "{group:?}");
    }
    assert_eq!(field("discovery").field().applies, Applies::Restart);
}

#[test]
fn the_record_drives_the_inverter_and_the_host_link() {
    let mut c = Config::default();
    c.protocol = Protocol::SmaSunnyIsland;
    c.charge_current_cap_da = 500;
    c.stale_after_s = 8;
    c.stale_policy = StaleMode::Hold;
    c.stale_hold_s = 300;
    c.tail_current_da = 35;
    let i = c.inverter();
    assert_eq!(i.protocol, Protocol::SmaSunnyIsland);
    assert_eq!(i.charge.charge_current_cap_da, Some(500));
    assert_eq!(i.charge.discharge_current_cap_da, None);
    assert_eq!(i.charge.tail_current_a, 3.5);
    assert_eq!(i.freshness.limit_us, 8 * SECOND);
    assert_eq!(i.stale_policy, StaleMode::Hold);
    assert_eq!(i.stale_hold_us, 300 * SECOND);
    assert_eq!(i.node, 0, "alone by default");
    c.pack_node = 2;
    assert_eq!(c.inverter().node, 2);
    c.read_only = true;
    c.stream_period_ms = 0;
    let h = c.host_link(&tinybms_firmware::identity::Identity::desktop(
        "sim",
        Default::default(),
    ));
    assert!(h.read_only);
    assert_eq!(h.stream_period_ms, 0);
}

fn encoded(c: &Config) -> Vec<u8> {
    let mut buf = [0u8; RECORD_MAX];
    let n = codec::encode(c, &mut buf).unwrap();
    buf[..n].to_vec()
}

fn full_record() -> Config {
    let mut c = Config::default();
    c.wifi_ssid.push_str(&"s".repeat(32)).unwrap();
    c.wifi_key.push_str(&"f".repeat(64)).unwrap();
    c.hostname.push_str(&"h".repeat(32)).unwrap();
    c.mqtt_host.push_str(&"m".repeat(64)).unwrap();
    c.mqtt_user.push_str(&"u".repeat(32)).unwrap();
    c.mqtt_password.push_str(&"p".repeat(64)).unwrap();
    c.topic_prefix.clear();
    c.topic_prefix.push_str(&"t".repeat(32)).unwrap();
    c.discovery_prefix.clear();
    c.discovery_prefix.push_str(&"d".repeat(32)).unwrap();
    c.pack_node = 3;
    c.pack_name.push_str(&"n".repeat(24)).unwrap();
    c.inverter_name.clear();
    c.inverter_name.push_str("GOODWE").unwrap();
    c.stop_by_soc = true;
    c.update_key.clear();
    c.update_key.push_str(&"ab".repeat(32)).unwrap();
    c.balance_hold_min = 90;
    c.full_charge_days = 14;
    c.float_step_mv_per_min = 10;
    c.soc_ceiling_pct = 85;
    c
}

/// `c` as a record of an older layout holds it: the fields added in
/// version 4 (`inverter_name`), 5 (`update_key`) and 6 (`stop_by_soc` on
/// by default, `current_margin`) at their defaults.
fn before_version_4(mut c: Config) -> Config {
    c.inverter_name = Config::default().inverter_name;
    before_version_5(c)
}

/// `c` as a version-4 record holds it: `update_key` (version 5) empty.
fn before_version_5(mut c: Config) -> Config {
    c.update_key = Config::default().update_key;
    before_version_6(c)
}

/// `c` as a version-5 record holds it: `stop_by_soc` and `current_margin`
/// (version 6) at their defaults, whatever the old record said of the
/// retired `stop_by_soc` (tag 8).
fn before_version_6(mut c: Config) -> Config {
    let d = Config::default();
    c.stop_by_soc = d.stop_by_soc;
    c.current_margin_pct = d.current_margin_pct;
    before_version_7(c)
}

/// `c` as a version-6 record holds it: the end of a charge (version 7:
/// `balance_hold`, `full_charge_days`, `float_step`, `soc_ceiling`) at its
/// defaults.
fn before_version_7(mut c: Config) -> Config {
    let d = Config::default();
    c.balance_hold_min = d.balance_hold_min;
    c.full_charge_days = d.full_charge_days;
    c.float_step_mv_per_min = d.float_step_mv_per_min;
    c.soc_ceiling_pct = d.soc_ceiling_pct;
    c
}

#[test]
fn the_codec_round_trips_and_the_longest_record_fits() {
    for c in [Config::default(), full_record()] {
        let bytes = encoded(&c);
        assert_eq!(codec::decode(&bytes).unwrap(), c);
        assert_eq!(&bytes[..2], &MAGIC);
        assert_eq!(bytes[2], VERSION);
    }
    let n = encoded(&full_record()).len();
    assert!(n <= RECORD_MAX, "{n}");
    println!("longest record: {n} bytes of {RECORD_MAX}");
}

/// A record of version 1 (before `pack_node`): as a v1 firmware wrote it.
fn v1_record(c: &Config) -> Vec<u8> {
    record_of_version(c, 1)
}

/// A record of an older `version`: as that firmware wrote it (the fields
/// of that version only).
fn record_of_version(c: &Config, version: u8) -> Vec<u8> {
    record_with_retired(c, version, false)
}

/// [`record_of_version`], with the retired `stop_by_soc` (tag 8, versions
/// 4-5) saying `old_stop_by_soc`.
fn record_with_retired(c: &Config, version: u8, old_stop_by_soc: bool) -> Vec<u8> {
    let now = encoded(c);
    let mut out = vec![b'T', b'C', version, 0];
    let mut rest = &now[4..];
    let mut n = 0u8;
    while let [tag, len, tail @ ..] = rest {
        let (value, after) = tail.split_at(usize::from(*len));
        if codec::introduced(*tag) <= version {
            out.extend_from_slice(&[*tag, *len]);
            out.extend_from_slice(value);
            n += 1;
        }
        rest = after;
    }
    for &(tag, from, until, _) in tinybms_firmware::config::RETIRED {
        if (from..until).contains(&version) {
            out.extend_from_slice(&[tag, 1, u8::from(old_stop_by_soc)]);
            n += 1;
        }
    }
    out[3] = n;
    out
}

#[test]
fn a_version_1_record_keeps_the_owners_configuration_and_pack_node_defaults() {
    let mut c = before_version_4(full_record());
    c.pack_node = 0;
    c.pack_name.clear();
    let v1 = v1_record(&c);
    assert_eq!(v1[2], 1);
    assert_eq!(usize::from(v1[3]), FIELDS.len() - 10);
    assert_eq!(codec::decode(&v1).unwrap(), c);
    // A field a version-1 record cannot hold is refused in one.
    let mut with_node = v1.clone();
    with_node[3] += 1;
    with_node.extend_from_slice(&[6, 4, 2, 0, 0, 0]);
    assert_eq!(codec::decode(&with_node), Err(DecodeError::UnknownTag(6)));
    // A version-2 record without it is incomplete.
    let mut v2_short = v1;
    v2_short[2] = 2;
    assert_eq!(
        codec::decode(&v2_short),
        Err(DecodeError::Missing(FieldId::PackNode))
    );
    // Version 0 does not exist.
    let mut zero = encoded(&Config::default());
    zero[2] = 0;
    assert_eq!(codec::decode(&zero), Err(DecodeError::Version(0)));
}

/// Issue 26, "a friendly pack name": `pack_name` came with layout version
/// 3. A version-2 record (what the bridge stored before) keeps the owner's
/// configuration with no name; a version-3 record must hold it; a version-2
/// record cannot.
#[test]
fn a_version_2_record_keeps_the_owners_configuration_and_no_pack_name() {
    let mut c = before_version_4(full_record());
    c.pack_name.clear();
    let v2 = record_of_version(&c, 2);
    assert_eq!(usize::from(v2[3]), FIELDS.len() - 9);
    assert_eq!(codec::decode(&v2).unwrap(), c);
    let tag = field("pack_name").field().tag;
    assert_eq!(codec::introduced(tag), 3);
    let mut named = v2.clone();
    named[3] += 1;
    named.extend_from_slice(&[tag, 6]);
    named.extend_from_slice(b"Garage");
    assert_eq!(codec::decode(&named), Err(DecodeError::UnknownTag(tag)));
    named[2] = 3;
    let mut want = c.clone();
    want.pack_name.push_str("Garage").unwrap();
    assert_eq!(codec::decode(&named).unwrap(), want);
    let mut short = v2;
    short[2] = 3;
    assert_eq!(
        codec::decode(&short),
        Err(DecodeError::Missing(FieldId::PackName))
    );
}

/// Issue 41: `update_key` came with layout version 5. A version-4 record
/// keeps the owner's configuration with no key of the owner's: only the key
/// built into the image is trusted.
#[test]
fn a_version_4_record_keeps_the_owners_configuration_and_no_update_key() {
    let full = full_record();
    let v4 = record_of_version(&full, 4);
    assert_eq!(v4[2], 4);
    // Its fields less update_key, stop_by_soc and current_margin, and the
    // retired stop_by_soc.
    assert_eq!(usize::from(v4[3]), FIELDS.len() - 6);
    let got = codec::decode(&v4).unwrap();
    assert_eq!(got, before_version_5(full.clone()));
    assert!(got.update_key.is_empty() && got.update_key().is_none());
    assert_eq!(codec::introduced(field("update_key").field().tag), 5);
    assert!(full.update_key().is_some());
}

/// Issue 40: `inverter_name` came with layout version 4 (with the first
/// `stop_by_soc`, retired in version 6). A version-3 record (what the
/// bridge stored before) keeps the owner's configuration with the name PYLON
/// and stop_by_soc at today's default; a version-4 record must hold the name;
/// a version-3 record cannot.
#[test]
fn a_version_3_record_keeps_the_owners_configuration_and_the_hybrid_defaults() {
    let full = full_record();
    let c = before_version_4(full.clone());
    let v3 = record_of_version(&full, 3);
    assert_eq!(v3[2], 3);
    assert_eq!(usize::from(v3[3]), FIELDS.len() - 8);
    let got = codec::decode(&v3).unwrap();
    assert_eq!(got, c);
    assert_eq!(got.inverter_name.as_str(), "PYLON");
    assert!(got.stop_by_soc);
    assert_eq!(codec::introduced(field("inverter_name").field().tag), 4);
    // A version-3 record cannot hold the retired stop_by_soc (tag 8); a
    // version-4 one must hold the name.
    let mut with = v3.clone();
    with[3] += 1;
    with.extend_from_slice(&[8, 1, 1]);
    assert_eq!(codec::decode(&with), Err(DecodeError::UnknownTag(8)));
    let mut short = v3;
    short[2] = 4;
    assert!(matches!(
        codec::decode(&short),
        Err(DecodeError::Missing(_))
    ));
    assert_eq!(codec::decode(&encoded(&full)).unwrap(), full);
}

/// Issue 50: `stop_by_soc` is on by default since layout version 6 (a new
/// tag, 9) and `current_margin` came with it. A version-4 or -5 record said
/// the old `stop_by_soc` (tag 8), off by default then and not to be told
/// from an owner's choice: it is read as today's default, on — whatever it
/// said — with `current_margin` 20 %. A version-6 record must hold both new
/// fields and cannot hold tag 8.
#[test]
fn a_version_5_record_reads_stop_by_soc_as_on_and_the_current_margin_at_its_default() {
    let mut full = full_record();
    full.stop_by_soc = false;
    full.current_margin_pct = 35;
    for version in [4, 5] {
        for old in [false, true] {
            let rec = record_with_retired(&full, version, old);
            let got = codec::decode(&rec).unwrap();
            assert!(got.stop_by_soc, "version {version}, old {old}");
            assert_eq!(got.current_margin_pct, 20);
        }
    }
    // A retired field of the wrong length is refused, as an unknown tag.
    let mut bad = record_with_retired(&full, 5, false);
    let n = bad.len();
    bad[n - 2] = 2;
    bad.push(0);
    assert_eq!(codec::decode(&bad), Err(DecodeError::UnknownTag(8)));
    for name in ["stop_by_soc", "current_margin"] {
        assert_eq!(codec::introduced(field(name).field().tag), 6, "{name}");
    }
    assert_eq!(field("stop_by_soc").field().tag, 9);
    // Version 6: tag 8 is unknown; the new fields must be there.
    let v6 = record_of_version(&full, 6);
    assert_eq!(v6[2], 6);
    assert_eq!(codec::decode(&v6).unwrap(), before_version_7(full.clone()));
    let mut with8 = v6.clone();
    with8[3] += 1;
    with8.extend_from_slice(&[8, 1, 0]);
    assert_eq!(codec::decode(&with8), Err(DecodeError::UnknownTag(8)));
    let v5_as_6 = {
        let mut r = record_of_version(&full, 5);
        r[2] = 6;
        r
    };
    assert!(
        codec::decode(&v5_as_6).is_err(),
        "a version-5 record is no version 6"
    );
    assert!(Config::default().stop_by_soc);
    assert_eq!(Config::default().current_margin_pct, 20);
}

/// Issue 53: the end of a charge (`balance_hold`, `full_charge_days`,
/// `float_step`, `soc_ceiling`) came with layout version 7. A version-6
/// record keeps the owner's configuration with their defaults; a version-7
/// record must hold them.
#[test]
fn a_version_6_record_keeps_the_owners_configuration_and_the_end_of_charge_defaults() {
    let full = full_record();
    let v6 = record_of_version(&full, 6);
    assert_eq!(v6[2], 6);
    assert_eq!(usize::from(v6[3]), FIELDS.len() - 4);
    let got = codec::decode(&v6).unwrap();
    assert_eq!(got, before_version_7(full.clone()));
    assert_eq!(got.balance_hold_min, 60);
    assert_eq!(got.full_charge_days, 7);
    assert_eq!(got.float_step_mv_per_min, 5);
    assert_eq!(got.soc_ceiling_pct, 100);
    for name in [
        "balance_hold",
        "full_charge_days",
        "float_step",
        "soc_ceiling",
    ] {
        assert_eq!(codec::introduced(field(name).field().tag), 7, "{name}");
    }
    let mut short = v6;
    short[2] = 7;
    assert!(matches!(
        codec::decode(&short),
        Err(DecodeError::Missing(_))
    ));
    let v7 = encoded(&full);
    assert_eq!(v7[2], 7);
    assert_eq!(codec::decode(&v7).unwrap(), full);
    // What charge control runs with.
    let c = full.charge();
    assert_eq!(c.balance_hold_us, 90 * 60 * 1_000_000);
    assert_eq!(
        (
            c.full_charge_days,
            c.float_step_mv_per_min,
            c.soc_ceiling_pct
        ),
        (14, 10, 85)
    );
}

/// `pack_name`: printable text, at most 24 bytes, empty by default.
#[test]
fn the_pack_name_is_short_printable_text() {
    let f = field("pack_name").field();
    assert_eq!(
        f.kind,
        Kind::Text {
            max: 24,
            rule: tinybms_firmware::config::TextRule::Printable
        }
    );
    assert_eq!(Config::default().pack_name.as_str(), "");
    let mut c = Config::default();
    assert!(c.set(f.id, Value::Text("Garage — pack 2")).is_ok());
    assert!(c.set(f.id, Value::Text(&"x".repeat(25))).is_err());
    assert!(c.set(f.id, Value::Text("tab\there")).is_err());
    assert_eq!(c.pack_name.as_str(), "Garage — pack 2");
}

#[test]
fn another_version_or_a_foreign_record_is_refused() {
    let mut bytes = encoded(&Config::default());
    bytes[2] = VERSION + 1;
    assert_eq!(
        codec::decode(&bytes),
        Err(DecodeError::Version(VERSION + 1))
    );
    let mut bytes = encoded(&Config::default());
    bytes[0] = b'X';
    assert_eq!(codec::decode(&bytes), Err(DecodeError::Magic));
    assert_eq!(codec::decode(&[]), Err(DecodeError::Truncated));
    assert_eq!(codec::decode(b"TC"), Err(DecodeError::Truncated));
}

#[test]
fn every_kind_of_damage_is_named() {
    let good = encoded(&Config::default());
    // A field's value out of range: stale_after (tag 3) = 0.
    let mut b = good.clone();
    let at = find_tag(&b, 3);
    b[at + 2..at + 6].copy_from_slice(&0i32.to_le_bytes());
    assert_eq!(
        codec::decode(&b),
        Err(DecodeError::Value(field("stale_after")))
    );
    // A bool that is neither 0 nor 1.
    let mut b = good.clone();
    let at = find_tag(&b, 1);
    b[at + 2] = 2;
    assert_eq!(
        codec::decode(&b),
        Err(DecodeError::Value(field("can_output")))
    );
    // A number of the wrong length.
    let mut b = good.clone();
    let at = find_tag(&b, 3);
    b[at + 1] = 2;
    assert!(codec::decode(&b).is_err());
    // An unknown tag.
    let mut b = good.clone();
    let at = find_tag(&b, 3);
    b[at] = 250;
    assert_eq!(codec::decode(&b), Err(DecodeError::UnknownTag(250)));
    // A field twice (count says one more, the last field repeated).
    let mut b = good.clone();
    b[3] += 1;
    b.extend_from_slice(&[3, 4, 5, 0, 0, 0]);
    assert_eq!(
        codec::decode(&b),
        Err(DecodeError::Duplicate(field("stale_after")))
    );
    // A field missing (count one less, the last field cut off).
    let mut b = good.clone();
    let last = FIELDS.last().unwrap();
    let at = find_tag(&b, last.tag);
    b.truncate(at);
    b[3] -= 1;
    assert_eq!(codec::decode(&b), Err(DecodeError::Missing(last.id)));
    // Trailing bytes.
    let mut b = good.clone();
    b.push(0);
    assert_eq!(codec::decode(&b), Err(DecodeError::Trailing));
    // Invalid UTF-8 in a text field.
    let mut c = Config::default();
    c.hostname.push_str("ab").unwrap();
    let mut b = encoded(&c);
    let at = find_tag(&b, field("hostname").field().tag);
    b[at + 2] = 0xFF;
    assert!(codec::decode(&b).is_err());
    // Fields that break a rule between them.
    let mut c = Config::default();
    c.absorption_voltage_mv = 3400;
    c.float_voltage_mv = 3450;
    assert_eq!(
        codec::decode(&encoded(&c)),
        Err(DecodeError::Rule(field("float_voltage")))
    );
}

/// Offset of the field with `tag` in an encoded record.
fn find_tag(b: &[u8], tag: u8) -> usize {
    let mut at = 4;
    while at < b.len() {
        if b[at] == tag {
            return at;
        }
        at += 2 + b[at + 1] as usize;
    }
    panic!("tag {tag} not found");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(4000))]

    /// Any bytes: an error or a record that is valid, never a panic.
    #[test]
    fn fuzzed_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..700)) {
        if let Ok(c) = codec::decode(&bytes) {
            prop_assert!(c.validate().is_ok());
        }
    }

    /// A valid record with bytes flipped: refused, or a record whose every
    /// field passes its check (a flip inside a value's range is not visible to
    /// the codec: that is what sequential-storage's CRC is for).
    #[test]
    fn corrupted_records_are_refused_or_valid(flips in proptest::collection::vec((0usize..600, any::<u8>()), 1..4)) {
        let mut b = encoded(&full_record());
        for (at, x) in flips {
            let n = b.len();
            b[at % n] ^= x.max(1);
        }
        if let Ok(c) = codec::decode(&b) {
            prop_assert!(c.validate().is_ok());
            for f in FIELDS {
                prop_assert!(value::check(f, &c.get(f.id)).is_ok());
            }
        }
    }

    /// Any text for any field: refused, or a value that passes the field's
    /// check and prints back to text that parses to the same value.
    #[test]
    fn any_text_is_refused_or_round_trips(i in 0usize..FIELDS.len(), text in "\\PC{0,12}") {
        let f = &FIELDS[i];
        if let Ok(p) = value::parse(f, &text) {
            prop_assert!(value::check(f, &p.as_value()).is_ok());
            if !f.is_secret() {
                let mut l = Line::new();
                value::write(f, &p.as_value(), true, &mut l);
                let again = value::parse(f, l.as_str());
                prop_assert_eq!(again, Ok(p.clone()), "{} -> {}", text, l.as_str());
            }
        }
    }
}

fn state() -> ConfigState {
    ConfigState::new(Config::default(), Source::Empty)
}

fn change(
    s: &mut ConfigState,
    pairs: &[(&str, &str)],
    bms: Option<&PackSettings>,
) -> Vec<(String, Outcome)> {
    let parsed: Vec<(FieldId, Parsed)> = pairs
        .iter()
        .map(|(n, t)| (field(n), parse(n, t).unwrap()))
        .collect();
    s.change(&parsed, false, bms)
        .iter()
        .map(|(id, o)| (id.name().to_string(), *o))
        .collect()
}

#[test]
fn a_change_gives_one_outcome_per_field_and_says_when_it_applies() {
    let mut s = state();
    let o = change(
        &mut s,
        &[
            ("charge_current_cap", "50 A"),
            ("inverter_protocol", "sma"),
            ("stale_after", "5 s"),
        ],
        None,
    );
    assert_eq!(
        o,
        vec![
            ("charge_current_cap".into(), Outcome::Applied),
            ("inverter_protocol".into(), Outcome::AtRestart),
            ("stale_after".into(), Outcome::Unchanged),
        ]
    );
    assert_eq!(s.running().charge_current_cap_da, 500);
    assert_eq!(s.running().protocol, Protocol::Victron);
    assert_eq!(s.stored().protocol, Protocol::SmaSunnyIsland);
    assert!(s.restart_pending(field("inverter_protocol")));
    assert_eq!(s.restarts_pending(), 1);
    assert!(s.save_due());
    assert!(s.take_running_change().is_some());
    assert!(s.take_running_change().is_none());
    // Back to what runs: applied (no restart needed any more).
    let o = change(&mut s, &[("inverter_protocol", "victron")], None);
    assert_eq!(o[0].1, Outcome::Applied);
    assert_eq!(s.restarts_pending(), 0);
}

#[test]
fn one_refusal_and_nothing_changes() {
    let mut s = state();
    let before = s.stored().clone();
    let o = change(
        &mut s,
        &[
            ("charge_current_cap", "120 A"),
            ("inverter_protocol", "sma"),
        ],
        Some(&bms()),
    );
    assert!(matches!(o[0].1, Outcome::RuleBroken(..)), "{o:?}");
    assert_eq!(o[1].1, Outcome::NotApplied);
    assert_eq!(s.stored(), &before);
    assert!(!s.save_due());
    // A rule about a field that was not named: it gets its own outcome.
    let mut s = state();
    change(&mut s, &[("float_voltage", "3.40 V")], None);
    let o = change(&mut s, &[("absorption_voltage", "3.35 V")], None);
    assert_eq!(o.len(), 2, "{o:?}");
    assert_eq!(o[0].1, Outcome::NotApplied);
    assert_eq!(o[1].0, "float_voltage");
    assert!(matches!(o[1].1, Outcome::RuleBroken(..)));
    // The same field twice.
    let mut s = state();
    let o = change(&mut s, &[("stale_after", "7"), ("stale_after", "9")], None);
    assert!(matches!(o[1].1, Outcome::Refused(_)));
    assert_eq!(s.stored().stale_after_s, 5);
}

#[test]
fn reset_and_unlock() {
    let mut s = state();
    change(
        &mut s,
        &[
            ("read_only", "on"),
            ("charge_current_cap", "40"),
            ("can_output", "off"),
        ],
        None,
    );
    assert!(s.running().read_only);
    s.saved(Ok(tinybms_firmware::config::store::Saved::Written));
    s.unlock();
    assert!(!s.running().read_only);
    assert!(!s.stored().read_only);
    assert!(s.save_due());
    let o = s.reset();
    let names: Vec<_> = o.iter().map(|(id, _)| id.name()).collect();
    assert_eq!(names, vec!["can_output", "charge_current_cap"]);
    assert_eq!(s.stored(), &Config::default());
    assert_eq!(s.running(), &Config::default());
}

#[test]
fn a_failed_save_is_tried_again_then_reported() {
    use tinybms_firmware::config::store::{Saved, StoreError};
    let mut s = state();
    change(&mut s, &[("charge_current_cap", "40")], None);
    assert_eq!(s.saved(Err(StoreError::Flash)), None);
    assert!(s.save_due());
    assert_eq!(s.saved(Err(StoreError::Flash)), None);
    assert_eq!(
        s.saved(Err(StoreError::Flash)),
        Some(Err(StoreError::Flash))
    );
    assert!(!s.save_due());
    // The change is kept in RAM.
    assert_eq!(s.running().charge_current_cap_da, 400);
    change(&mut s, &[("charge_current_cap", "41")], None);
    assert_eq!(s.saved(Ok(Saved::Written)), Some(Ok(Saved::Written)));
}

/// docs/configuration.md lists every field with the range, default, "applies"
/// and help the firmware has: the guide cannot drift from the table.
#[test]
fn the_guide_lists_every_field_as_the_firmware_has_it() {
    let guide = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../docs/configuration.md"
    ))
    .unwrap();
    let d = Config::default();
    let mut lacking = Vec::new();
    for f in FIELDS {
        let mut r = Line::new();
        value::write_range(f, &mut r);
        let mut v = Line::new();
        value::write(f, &d.get(f.id), true, &mut v);
        let default = if v.as_str().is_empty() {
            "(empty)"
        } else {
            v.as_str()
        };
        let applies = match f.applies {
            Applies::Now => "at once",
            Applies::Restart => "restart",
        };
        let row = format!(
            "| `{}` | {} | {} | {} | {} |",
            f.name,
            r.as_str(),
            default,
            applies,
            f.help
        );
        if !guide.contains(&row) {
            lacking.push(row);
        }
    }
    assert!(
        lacking.is_empty(),
        "docs/configuration.md lacks:\n{}",
        lacking.join("\n")
    );
    let rows = guide.lines().filter(|l| l.starts_with("| `")).count();
    assert_eq!(
        rows,
        FIELDS.len(),
        "a field in the guide that the firmware has not"
    );
}

/// The log line of a changed secret says `set`, never the secret.
#[test]
fn a_secret_never_reaches_a_log_line() {
    use tinybms_firmware::config::state::Note;
    use tinybms_firmware::text;
    let key = "ab".repeat(32);
    let mut s = state();
    let o = change(
        &mut s,
        &[
            ("wifi_ssid", "home"),
            ("wifi_key", &key),
            ("mqtt_user", "u"),
            ("mqtt_password", "hunter22"),
        ],
        None,
    );
    assert!(o.iter().all(|(_, o)| *o == Outcome::AtRestart), "{o:?}");
    let mut lines = Vec::new();
    while let Some(n) = s.next_note() {
        let mut l = Line::new();
        text::config_note(&n, &s, &mut l);
        lines.push(l.as_str().to_string());
        if let Note::Changed(id, _) = n {
            if id.field().is_secret() {
                assert!(
                    l.as_str().ends_with("set (at the next restart)"),
                    "{}",
                    l.as_str()
                );
            }
        }
    }
    let all = lines.join("\n");
    assert!(!all.contains(&key) && !all.contains("hunter22"), "{all}");
    assert!(all.contains("config: wifi_ssid = home"), "{all}");
}

// ------------------------------------------------- the store explains itself

mod store_site {
    use tinybms_firmware::config::state::{ConfigState, Note};
    use tinybms_firmware::config::store::{SiteProblem, Source, StoreError, StoreSite};
    use tinybms_firmware::config::Config;
    use tinybms_firmware::text::{self, Line};

    fn said(site: Option<StoreSite>, note: Note) -> String {
        let mut s = ConfigState::new(Config::default(), Source::Unreadable(StoreError::Partition));
        if let Some(site) = site {
            s.set_site(site);
        }
        let mut l = Line::new();
        text::config_note(&note, &s, &mut l);
        l.as_str().to_string()
    }

    const MIB4: u32 = 4 * 1024 * 1024;

    #[test]
    fn every_store_message_names_the_flash_the_partition_and_what_the_store_needs() {
        let good = StoreSite {
            flash_bytes: MIB4,
            partition: Some((0x9000, 0x6000)),
            lookup: None,
        };
        assert_eq!(good.problem(), None);
        let cases = [
            (
                StoreSite {
                    flash_bytes: MIB4,
                    partition: None,
                    lookup: None,
                },
                Some(SiteProblem::NoPartition),
                "flash 4096 KiB (as the chip reports it), no nvs partition; the store needs 8 KiB \
                 in whole 4 KiB sectors inside the flash: no `nvs` partition in the partition table",
            ),
            (
                StoreSite {
                    flash_bytes: MIB4,
                    partition: Some((0x9000, 0x1000)),
                    lookup: None,
                },
                Some(SiteProblem::TooSmall),
                "flash 4096 KiB (as the chip reports it), nvs partition at 0x9000, 4 KiB; the store \
                 needs 8 KiB in whole 4 KiB sectors inside the flash: the `nvs` partition is smaller \
                 than the store needs",
            ),
            (
                StoreSite {
                    flash_bytes: MIB4,
                    partition: Some((0x9000, 0x6800)),
                    lookup: None,
                },
                Some(SiteProblem::NotAligned),
                "flash 4096 KiB (as the chip reports it), nvs partition at 0x9000, 26 KiB; the store \
                 needs 8 KiB in whole 4 KiB sectors inside the flash: the `nvs` partition is not on \
                 4 KiB sector boundaries",
            ),
            (
                // The emulator's flash: no answer to the read-ID command.
                StoreSite {
                    flash_bytes: 0,
                    partition: Some((0x9000, 0x6000)),
                    lookup: None,
                },
                Some(SiteProblem::BeyondFlash),
                "flash 0 KiB (as the chip reports it), nvs partition at 0x9000, 24 KiB; the store \
                 needs 8 KiB in whole 4 KiB sectors inside the flash: the `nvs` partition ends past \
                 the flash the chip reports",
            ),
        ];
        for (site, problem, words) in cases {
            assert_eq!(site.problem(), problem);
            let start = said(
                Some(site),
                Note::Loaded(Source::Unreadable(StoreError::Partition)),
            );
            assert_eq!(
                start,
                format!(
                    "configuration store cannot be read (the partition cannot hold a store): \
                     running with the defaults; {words}"
                )
            );
            let save = said(Some(site), Note::SaveFailed(StoreError::Partition));
            assert_eq!(
                save,
                format!("config save failed: the partition cannot hold a store; {words}")
            );
        }
        // A good site with a failing flash: the figures, no problem named.
        assert_eq!(
            said(Some(good), Note::SaveFailed(StoreError::Flash)),
            "config save failed: flash driver error; flash 4096 KiB (as the chip reports it), nvs \
             partition at 0x9000, 24 KiB; the store needs 8 KiB in whole 4 KiB sectors inside the \
             flash"
        );
        // Without a site (a desktop run): as before.
        assert_eq!(
            said(None, Note::SaveFailed(StoreError::Flash)),
            "config save failed: flash driver error"
        );
    }
}

/// A typed 0 never turns into the field's word for 0: a cap of 0 is not "no
/// cap" (issue 26), 0 mV is not "the BMS's own setting", node 0 is not a node.
#[test]
fn a_typed_zero_is_never_the_word_for_zero() {
    use tinybms_firmware::config::FieldId;
    for id in [FieldId::ChargeCurrentCap, FieldId::DischargeCurrentCap] {
        let f = id.field();
        for zero in ["0", "0 A", "0.0", "0A", " 0 "] {
            let e = value::parse(f, zero).expect_err(zero);
            assert!(e.detail.contains("no cap"), "{zero}: {}", e.detail);
        }
        assert_eq!(value::parse(f, "none").unwrap(), Parsed::Number(0));
        assert_eq!(value::parse(f, "0.1").unwrap(), Parsed::Number(1));
        assert_eq!(value::parse(f, "50 A").unwrap(), Parsed::Number(500));
    }
    for id in [
        FieldId::AbsorptionVoltage,
        FieldId::FloatVoltage,
        FieldId::PackNode,
    ] {
        let f = id.field();
        assert!(value::parse(f, "0").is_err(), "{}", f.name);
    }
    // `off` is what 0 says: a stream period of 0 is off.
    assert_eq!(
        value::parse(FieldId::StreamPeriod.field(), "0").unwrap(),
        Parsed::Number(0)
    );
}

/// Issue 42, item 7: a `.local` broker name (mDNS, which the bridge cannot
/// resolve) is refused in any case; names that only contain "local" are
/// not.
#[test]
fn a_local_mdns_name_is_refused_and_only_that() {
    for refused in [
        "homeassistant.local",
        "HA.LOCAL",
        "broker.Local",
        "a.b.local",
    ] {
        let e = parse("mqtt_host", refused).unwrap_err();
        assert!(e.detail.contains("mDNS"), "{refused}: {}", e.detail);
    }
    for taken in [
        "local",
        "mylocal",
        "broker.localdomain",
        "192.168.1.10",
        "mqtt.lan",
    ] {
        assert!(parse("mqtt_host", taken).is_ok(), "{taken}");
    }
}

/// Issue 51, item 7: 0x35E's name goes out byte for byte: ASCII only (a
/// name with an accent was "applied" and went out cut, `DEYÉ` as `DEY`).
#[test]
fn the_inverter_name_is_ascii_only() {
    let f = field("inverter_name").field();
    for good in ["PYLON", "GOODWE", "DEYE", "SHEnergy", "A B-C.1"] {
        assert!(value::parse(f, good).is_ok(), "{good}");
    }
    for bad in ["DEYÉ", "PYLON\u{7f}", "ÄÖ"] {
        let e = value::parse(f, bad).unwrap_err();
        assert!(e.detail.contains("ASCII"), "{bad}: {}", e.detail);
    }
}

/// Issue 51, item 1: `update_key` takes a public key (64 hex digits) and
/// refuses a private one (128, as `tinybms keygen` writes it) with words
/// that say which is which, before any "too long".
#[test]
fn update_key_refuses_a_private_key_by_name() {
    let f = field("update_key").field();
    let public = "ab".repeat(32);
    assert!(value::parse(f, &public).is_ok());
    assert!(value::parse(f, "").is_ok());
    let private = format!("{}{public}", "cd".repeat(32));
    let e = value::parse(f, &private).unwrap_err();
    assert!(e.detail.contains("PRIVATE key"), "{}", e.detail);
    let e = value::parse(f, &public[1..]).unwrap_err();
    assert!(e.detail.contains("64 hex digits"), "{}", e.detail);
}

/// `update_key=$(cat mykey.pub)`: the .pub file whole (its `#` lines, then
/// the key) is taken as its 64 hex digits, on the bridge and in the tool
/// (an owner found it refused with words that named that very file).
#[test]
fn update_key_takes_the_pub_file_whole() {
    let f = field("update_key").field();
    let hex = "5f69a1b2c3d4e5f60718293a4b5c6d7e8f9012345678abcdef0123456789abcd";
    let file = format!(
        "# tinybms update public key: give it to a bridge\n# (tinybms config PORT update_key={hex}).\n{}\n",
        hex.to_uppercase()
    );
    for text in [file.as_str(), &format!("{} {}", &hex[..32], &hex[32..])] {
        match value::parse(f, text) {
            Ok(Parsed::Text(s)) => assert_eq!(s.as_str(), hex, "{text}"),
            other => panic!("{text}: {other:?}"),
        }
    }
    // Comments alone, or a private key's file whole: refused, never stored.
    assert!(value::parse(f, "# only a comment\n").is_err());
    let private = format!("# PRIVATE\n{}{hex}\n", "cd".repeat(32));
    let e = value::parse(f, &private).unwrap_err();
    assert!(e.detail.contains("PRIVATE key"), "{}", e.detail);
}
