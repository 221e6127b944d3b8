//! Settings profiles for the simulator command: `name = value` lines.
//!
//! ```text
//! # comment
//! over_voltage_cutoff = 3650     # snake_case of the setting, or
//! Under-Voltage Cutoff = 2700    # Rev D's name, or
//! 316 = 2700                     # the register address (whole-register settings)
//! ```
//! Values are raw register units (mV, A, s, enumeration values), as in Rev D §3.4.
//!
//! The parser is the firmware's own (`tinybms_firmware::bms::profile`, no_std): the
//! firmware's start-up profile `firmware/profile.txt`, `sim --profile` and the
//! desktop tool read the same format with the same code. These wrappers turn its
//! errors into messages.

use protocol_core::settings::SettingId;
use tinybms_firmware::bms::profile::{self as fw, ProfileError};

/// snake_case name of a setting (`OverVoltageCutoff` → `over_voltage_cutoff`).
pub fn snake_name(id: SettingId) -> String {
    fw::setting_key(id).to_string()
}

/// Finds a setting by snake_case name, Rev D name (case-insensitive) or address.
pub fn find_setting(name: &str) -> Option<SettingId> {
    fw::find_setting(name)
}

/// How a setting's value may be written (for messages).
pub fn value_forms(id: SettingId) -> String {
    let Some(r) = id.register() else {
        return "an integer".into();
    };
    if !r.options.is_empty() {
        let names: Vec<&str> = r.options.iter().map(|(_, n)| *n).collect();
        return format!("one of: {} (or its raw number)", names.join(", "));
    }
    let (step, k) = fw::scale_parts(r.scale);
    let step = tinybms_firmware::units::fixed(step, k)
        .map(|d| crate::words::short(d.as_f64()))
        .unwrap_or_else(|| "1".into());
    match r.unit {
        "" => "an integer".into(),
        u @ ("V" | "A" | "Ah") => {
            format!("a raw integer, or a value in {u} or m{u} (steps of {step} {u})")
        }
        "°C" => format!("a raw integer, or a value in °C or C (steps of {step} °C)"),
        u => format!("a raw integer, or a value in {u} (steps of {step} {u})"),
    }
}

fn message(e: &ProfileError<'_>, id: Option<SettingId>) -> String {
    let forms = id.map(|id| format!(" ({}: {})", snake_name(id), value_forms(id)));
    let forms = forms.unwrap_or_default();
    match e.kind {
        fw::ProfileErrorKind::ExpectedAssignment => format!("`{}`: expected NAME=VALUE", e.text),
        fw::ProfileErrorKind::UnknownSetting => {
            let names: Vec<&str> = SettingId::ALL.iter().map(|&i| fw::setting_key(i)).collect();
            match crate::words::suggest(e.text, &names) {
                Some(s) => format!("`{}`: no such setting (did you mean `{s}`?)", e.text),
                None => format!("`{}`: no such setting", e.text),
            }
        }
        fw::ProfileErrorKind::Duplicate => {
            format!("`{}` is given twice: give each setting once", e.text)
        }
        kind => format!("`{}`: {}{forms}", e.text, kind.reason()),
    }
}

/// The setting an assignment names, if it names one.
fn named(assignment: &str) -> Option<SettingId> {
    assignment
        .split_once('=')
        .and_then(|(n, _)| find_setting(n))
}

/// Parses one `name=value` assignment.
pub fn parse_assignment(s: &str) -> Result<(SettingId, i32), String> {
    fw::parse_assignment(s).map_err(|e| message(&e, named(s)))
}

/// Parses a profile file.
/// A setting given twice is an error (which one is meant is not clear).
pub fn parse_profile(text: &str) -> Result<Vec<(SettingId, i32)>, String> {
    let mut out: Vec<(SettingId, i32, u32)> = Vec::new();
    let lines: Vec<&str> = text.lines().collect();
    let mut it = fw::entries(text);
    while let Some(e) = it.next() {
        match e {
            Ok((id, v)) => {
                let n = it.line();
                if let Some((_, _, first)) = out.iter().find(|(o, _, _)| *o == id) {
                    return Err(format!(
                        "line {n}: `{}` is given twice (also on line {first}): give each setting once",
                        snake_name(id)
                    ));
                }
                out.push((id, v, n));
            }
            Err(e) => {
                let line = lines.get(e.line as usize - 1).copied().unwrap_or("");
                let content = line.split('#').next().unwrap_or("");
                return Err(format!("line {}: {}", e.line, message(&e, named(content))));
            }
        }
    }
    Ok(out.into_iter().map(|(id, v, _)| (id, v)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use tinybms_firmware::bms::profile::{setting_key, ParseError};

    #[test]
    fn names_and_files() {
        assert_eq!(
            snake_name(SettingId::OverVoltageCutoff),
            "over_voltage_cutoff"
        );
        assert_eq!(
            find_setting("over_voltage_cutoff"),
            Some(SettingId::OverVoltageCutoff)
        );
        assert_eq!(
            find_setting("Under-Voltage Cutoff"),
            Some(SettingId::UnderVoltageCutoff)
        );
        assert_eq!(find_setting("342"), Some(SettingId::BroadcastTime));
        assert_eq!(find_setting("nope"), None);
        let p = parse_profile("# x\nover_voltage_cutoff = 3650 # mV\n\n316=2700\n").unwrap();
        assert_eq!(
            p,
            vec![
                (SettingId::OverVoltageCutoff, 3650),
                (SettingId::UnderVoltageCutoff, 2700)
            ]
        );
        assert!(parse_profile("a = b").unwrap_err().starts_with("line 1"));
        assert!(parse_assignment("over_voltage_cutoff=x").is_err());
    }

    #[test]
    fn keys_are_the_variant_names_in_snake_case() {
        for &id in SettingId::ALL {
            let debug = format!("{id:?}");
            let mut want = String::new();
            for (i, c) in debug.chars().enumerate() {
                if c.is_ascii_uppercase() {
                    if i > 0 {
                        want.push('_');
                    }
                    want.push(c.to_ascii_lowercase());
                } else {
                    want.push(c);
                }
            }
            assert_eq!(snake_name(id), want);
            assert_eq!(find_setting(&want), Some(id));
            assert_eq!(find_setting(id.name()), Some(id));
        }
    }

    #[test]
    fn the_firmware_profile_parses() {
        let text = tinybms_firmware::bms::profile::PROFILE_TEXT;
        let entries = parse_profile(text).unwrap();
        // Shipped empty: out of the box the firmware never writes to the BMS.
        assert!(entries.is_empty(), "{entries:?}");
        assert!(tinybms_firmware::bms::profile::parse::<
            { tinybms_firmware::bms::profile::MAX_PROFILE_ENTRIES },
        >(text)
        .unwrap()
        .is_empty());
        // The commented example in it parses once uncommented.
        let example: String = text
            .lines()
            .filter_map(|l| l.strip_prefix("# "))
            .filter(|l| l.contains(" = ") && !l.contains('`'))
            .map(|l| format!("{l}\n"))
            .collect();
        assert_eq!(parse_profile(&example).unwrap().len(), 4, "{example}");
    }

    /// The parser before it became a `const fn` (the firmware parses its start-up
    /// profile at compile time): `str::lines`, `split('#')`, `str::trim`,
    /// `split_once`, `str::parse`. The oracle of the properties below.
    mod str_parser {
        use protocol_core::registers::Field;
        use protocol_core::settings::SettingId;
        use tinybms_firmware::bms::profile::{setting_key, ProfileErrorKind};

        pub type Entry = Result<(SettingId, i32), (u32, ProfileErrorKind, String)>;

        /// Each entry with its line number.
        pub fn entries_at(text: &str) -> Vec<(u32, Entry)> {
            let mut out = Vec::new();
            for (i, raw) in text.lines().enumerate() {
                let line = raw.split('#').next().unwrap_or("").trim();
                if !line.is_empty() {
                    out.push((i as u32 + 1, assignment(line, i as u32 + 1)));
                }
            }
            out
        }

        pub fn find_setting(name: &str) -> Option<SettingId> {
            let n = name.trim();
            if let Ok(addr) = n.parse::<u16>() {
                return SettingId::from_address(addr, Field::Whole)
                    .or_else(|| SettingId::from_address(addr, Field::LowByte));
            }
            SettingId::ALL.iter().copied().find(|id| {
                setting_key(*id).eq_ignore_ascii_case(n) || id.name().eq_ignore_ascii_case(n)
            })
        }

        fn assignment(s: &str, line: u32) -> Entry {
            let Some((name, value)) = s.split_once('=') else {
                return Err((line, ProfileErrorKind::ExpectedAssignment, s.trim().into()));
            };
            let Some(id) = find_setting(name) else {
                return Err((line, ProfileErrorKind::UnknownSetting, name.trim().into()));
            };
            // The value's own syntax (units, names) has tests of its own
            // (tests/profile_values.rs); here the lines and names are modelled.
            match tinybms_firmware::bms::profile::parse_value(id, value.trim()) {
                Ok(v) => Ok((id, v)),
                Err(k) => Err((line, k, value.trim().into())),
            }
        }

        pub fn entries(text: &str) -> Vec<Entry> {
            entries_at(text).into_iter().map(|(_, e)| e).collect()
        }
    }

    fn entries(text: &str) -> Vec<str_parser::Entry> {
        fw::entries(text)
            .map(|e| e.map_err(|e| (e.line, e.kind, e.text.to_string())))
            .collect()
    }

    /// Lines made of the profile's parts: names (snake_case, Rev D's in any case,
    /// addresses), `=`, values, comments, blank lines, and runs of every character
    /// `str::trim` strips (the 25 of Unicode's White_Space) or not (U+200B), with
    /// `\n` or `\r\n` endings.
    fn profile_text() -> impl Strategy<Value = String> {
        let name = prop_oneof![
            proptest::sample::select(SettingId::ALL).prop_map(|id| setting_key(id).to_string()),
            proptest::sample::select(SettingId::ALL).prop_map(|id| id.name().to_uppercase()),
            proptest::sample::select(SettingId::ALL).prop_map(|id| id.address().to_string()),
            (250u16..400).prop_map(|a| a.to_string()),
            "[a-zA-Z_ -]{0,12}",
        ];
        let value = prop_oneof![
            any::<i32>().prop_map(|v| v.to_string()),
            any::<i64>().prop_map(|v| v.to_string()),
            "[+-]?[0-9]{0,12}",
            "[0-9a-x=#.]{0,4}",
        ];
        // Every White_Space character (what `str::trim` strips), U+200B (which it
        // does not), nothing, and runs of them.
        let one = proptest::sample::select(vec![
            "", " ", "\t", "\u{b}", "\u{c}", "\r", "\u{85}", "\u{a0}", "\u{1680}", "\u{2000}",
            "\u{2001}", "\u{2002}", "\u{2003}", "\u{2004}", "\u{2005}", "\u{2006}", "\u{2007}",
            "\u{2008}", "\u{2009}", "\u{200a}", "\u{2028}", "\u{2029}", "\u{202f}", "\u{205f}",
            "\u{3000}", "\u{200b}",
        ]);
        let space = proptest::collection::vec(one, 0..3).prop_map(|v| v.concat());
        let line = prop_oneof![
            4 => (space.clone(), name, space.clone(), value, space.clone(),
                  proptest::option::of("#[^\n]{0,10}"))
                .prop_map(|(a, n, b, v, c, comment)| {
                    format!("{a}{n}{b}={v}{c}{}", comment.unwrap_or_default())
                }),
            1 => "[^\n]{0,20}",
            1 => space.clone(),
            1 => "#[^\n]{0,20}",
        ];
        (
            proptest::collection::vec(line, 0..8),
            proptest::sample::select(vec!["\n", "\r\n"]),
            any::<bool>(),
        )
            .prop_map(|(lines, end, last)| {
                let mut t = lines.join(end);
                if last {
                    t.push_str(end);
                }
                t
            })
    }

    proptest! {
        #[test]
        fn const_parser_agrees_with_the_str_parser(text in profile_text()) {
            prop_assert_eq!(entries(&text), str_parser::entries(&text));
            // The whole-profile parse: the entries, or the first error, or the
            // line of the first entry beyond 3.
            let want = str_parser::entries_at(&text);
            let got = fw::parse::<3>(&text);
            // What the whole-profile parse must give: the first error, a
            // setting given twice, or the entry beyond 3 — whichever comes first.
            let mut seen: Vec<SettingId> = Vec::new();
            let mut expected: Result<Vec<(SettingId, i32)>, String> = Ok(Vec::new());
            for (line, e) in &want {
                match e {
                    Err(err) => {
                        expected = Err(format!("{:?}", Err::<(), _>(err.clone())));
                        break;
                    }
                    Ok((id, _)) if seen.contains(id) => {
                        expected = Err(format!(
                            "{:?}",
                            Err::<(), _>((*line, fw::ProfileErrorKind::Duplicate, setting_key(*id).to_string()))
                        ));
                        break;
                    }
                    Ok(_) if seen.len() == 3 => {
                        expected = Err(format!("too many at {line}"));
                        break;
                    }
                    Ok((id, v)) => {
                        seen.push(*id);
                        if let Ok(list) = expected.as_mut() {
                            list.push((*id, *v));
                        }
                    }
                }
            }
            let got = match got {
                Ok(p) => Ok(p.as_slice().to_vec()),
                Err(ParseError::Line(e)) => Err(format!("{:?}", Err::<(), _>((e.line, e.kind, e.text.to_string())))),
                Err(ParseError::TooMany { line }) => Err(format!("too many at {line}")),
            };
            prop_assert_eq!(got, expected);
        }

        /// Any characters, control characters (line ends, tabs, NEL) included.
        #[test]
        fn any_text_parses_as_the_str_parser_does(text in "(?s).{0,60}") {
            prop_assert_eq!(entries(&text), str_parser::entries(&text));
        }

        /// Any text made of `=`, `#`, line ends, whitespace and a few others.
        #[test]
        fn punctuation_and_line_ends_parse_as_the_str_parser_does(
            text in "[=#\r\n \t\u{b}\u{85}\u{a0}\u{2029}0-9a-z_+-]{0,40}"
        ) {
            prop_assert_eq!(entries(&text), str_parser::entries(&text));
        }

        #[test]
        fn trim_is_str_trim_on_any_text(s in "(?s).{0,12}") {
            prop_assert_eq!(fw::trim(&s), s.trim());
        }
    }

    /// `trim` against `str::trim` for every `char`: alone, doubled, before and
    /// after a letter, and around one.
    #[test]
    fn trim_is_str_trim_for_every_char() {
        let mut buf = String::new();
        for c in (0..=0x10FFFF).filter_map(char::from_u32) {
            for shape in 0..5 {
                buf.clear();
                match shape {
                    0 => buf.push(c),
                    1 => buf.extend([c, c]),
                    2 => buf.extend([c, 'a']),
                    3 => buf.extend(['a', c]),
                    _ => buf.extend([c, 'a', c]),
                }
                assert_eq!(
                    fw::trim(&buf),
                    buf.trim(),
                    "U+{:04X}, shape {shape}",
                    c as u32
                );
            }
        }
    }

    #[test]
    fn find_setting_agrees_with_the_str_parser_on_every_name() {
        for &id in SettingId::ALL {
            for n in [
                setting_key(id).to_string(),
                id.name().to_lowercase(),
                id.address().to_string(),
            ] {
                for padded in [n.clone(), format!("\u{a0} {n}\t"), n.to_uppercase()] {
                    assert_eq!(
                        find_setting(&padded),
                        str_parser::find_setting(&padded),
                        "{padded:?}"
                    );
                }
            }
        }
    }

    /// The firmware's use: a profile parsed in constant evaluation.
    #[test]
    fn a_profile_parses_at_compile_time() {
        const P: fw::Profile<4> =
            match fw::parse("# c\nover_voltage_cutoff = 3650 # mV\r\n\n316=2700\n") {
                Ok(p) => p,
                Err(_) => panic!("does not parse"),
            };
        const E: Result<fw::Profile<1>, ParseError<'static>> = fw::parse("a\nb = 1 2");
        assert_eq!(
            P.as_slice(),
            [
                (SettingId::OverVoltageCutoff, 3650),
                (SettingId::UnderVoltageCutoff, 2700)
            ]
        );
        let Err(ParseError::Line(e)) = E else {
            panic!("{E:?}")
        };
        assert_eq!(
            (e.line, e.kind, e.text),
            (1, fw::ProfileErrorKind::ExpectedAssignment, "a")
        );
        assert!(matches!(
            fw::parse::<1>("316 = 1\n317 = 2\n"),
            Err(ParseError::TooMany { line: 2 })
        ));
    }
}
