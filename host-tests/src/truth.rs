//! Ground truth: is every value the bridge published one the simulated BMS really
//! sent? The simulator records each block it answers before any fault is applied
//! ([`crate::sim::SimBms::record_reads`]); a published block passes when every one
//! of its values (a register, or a 32-bit pair, or an event slot) equals that
//! value in one recorded answer. A snapshot assembled from pieces passes the
//! same way: each value from one real answer, never spliced.

use std::collections::VecDeque;

use protocol_core::registers::{self, ValueType, EVENTS_FIRST, EVENTS_LAST};
use protocol_core::request::SettingsOption;
use protocol_core::response::RegisterBlock;

use crate::sim::TrueRead;

/// The values of a register map that stand alone: (first address, registers).
/// Reserved registers are skipped; a 32-bit value, the serial number and an event
/// slot are one value each.
pub fn fields(first: u16, last: u16) -> Vec<(u16, u16)> {
    let mut out = Vec::new();
    let mut a = first;
    while a <= last {
        if (EVENTS_FIRST..=EVENTS_LAST).contains(&a) {
            let width = if (a - EVENTS_FIRST).is_multiple_of(2) {
                2
            } else {
                1
            };
            out.push((a, width.min(last - a + 1)));
            a += width;
            continue;
        }
        let rows = registers::lookup(a);
        let reserved = rows
            .iter()
            .all(|r| matches!(r.value_type, ValueType::Reserved | ValueType::Continuation));
        let mut width = 1;
        while a + width <= last && registers::is_continuation(a + width) {
            width += 1;
        }
        if !reserved {
            out.push((a, width));
        }
        a += width;
    }
    out
}

/// Checks every value of `block` against the recorded answers. `Err` names the
/// first value no answer contains.
pub fn check_registers(block: &RegisterBlock, reads: &VecDeque<TrueRead>) -> Result<(), String> {
    let last = block.start + block.values.len() as u16 - 1;
    for (a, width) in fields(block.start, last) {
        let want: Vec<u16> = (a..a + width).filter_map(|x| block.get(x)).collect();
        let found = reads.iter().rev().any(|r| {
            r.option.is_none()
                && (a..a + width)
                    .map(|x| r.block.get(x))
                    .collect::<Option<Vec<u16>>>()
                    .is_some_and(|v| v == want)
        });
        if !found {
            return Err(format!(
                "register {a}..{} = {want:04X?} was never sent by the BMS",
                a + width - 1
            ));
        }
    }
    Ok(())
}

/// As [`check_registers`], for a block that replaces `previous` (the same
/// block as published before, already checked then): only the values that
/// differ from it are checked. A value the bridge kept unchanged was judged
/// when it was first published, and the recorded answers only reach back
/// [`crate::virtual_time::TRUTH_WINDOW_US`]: the settings block is patched
/// by a write's read-back (one register, from a reply the BMS sent) while its
/// other values were read at the last settings read, which may be older than
/// that when the writes in between changed nothing (`unchanged`,
/// `not_written`). A value that changes is checked as before, also when it
/// goes back to an earlier one.
pub fn check_changed(
    block: &RegisterBlock,
    previous: Option<&RegisterBlock>,
    reads: &VecDeque<TrueRead>,
) -> Result<(), String> {
    let Some(prev) = previous.filter(|p| p.start == block.start) else {
        return check_registers(block, reads);
    };
    let last = block.start + block.values.len() as u16 - 1;
    for (a, width) in fields(block.start, last) {
        let same = (a..a + width).all(|x| prev.get(x).is_some() && prev.get(x) == block.get(x));
        if same {
            continue;
        }
        let values = (a..a + width).filter_map(|x| block.get(x)).collect();
        check_registers(&RegisterBlock { start: a, values }, reads)?;
    }
    Ok(())
}

/// Checks a 0x1D table: it must equal one recorded answer for that option.
pub fn check_table(
    block: &RegisterBlock,
    option: SettingsOption,
    reads: &VecDeque<TrueRead>,
) -> Result<(), String> {
    if reads
        .iter()
        .any(|r| r.option == Some(option) && r.block == *block)
    {
        Ok(())
    } else {
        Err(format!("0x1D {option:?} table was never sent by the BMS"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(start: u16, values: &[u16]) -> TrueRead {
        TrueRead {
            at_us: 0,
            option: None,
            block: RegisterBlock {
                start,
                values: heapless::Vec::from_slice(values).unwrap(),
            },
        }
    }

    #[test]
    fn fields_keep_wide_values_whole() {
        let f = fields(30, 40);
        assert!(f.contains(&(32, 2)) && f.contains(&(36, 2)) && f.contains(&(40, 1)));
        assert!(!f.iter().any(|&(a, _)| a == 30 || a == 33));
        assert_eq!(fields(504, 509), vec![(504, 6)]);
        assert_eq!(fields(200, 203), vec![(200, 2), (202, 2)]);
    }

    /// Seed 7 at fault rate 0.1 (issue 54): the settings block patched by the
    /// read-back of 312 while 300 was last read more than the truth window
    /// ago. 300 is unchanged (judged when first published): no wrong value;
    /// a changed value no answer holds still is one.
    #[test]
    fn an_unchanged_value_is_not_judged_again() {
        let reads: VecDeque<TrueRead> = [read(312, &[1000, 0])].into_iter().collect();
        let block = |v300: u16, v312: u16| {
            let mut values = heapless::Vec::new();
            for a in 300..=313u16 {
                let v = match a {
                    300 => v300,
                    312 => v312,
                    _ => 0,
                };
                values.push(v).unwrap();
            }
            RegisterBlock { start: 300, values }
        };
        let before = block(3650, 1001);
        let after = block(3650, 1000);
        // The whole block against the window: 300 is too old for it.
        assert!(check_registers(&after, &reads).is_err());
        assert_eq!(check_changed(&after, Some(&before), &reads), Ok(()));
        // Nothing to compare with: every value is checked.
        assert!(check_changed(&after, None, &reads).is_err());
        // A value that changed to one no answer holds is caught.
        let forged = block(3600, 1000);
        let e = check_changed(&forged, Some(&before), &reads).unwrap_err();
        assert!(e.contains("register 300..300"), "{e}");
        // 312 going back to 1001, which no recorded answer holds, is caught too.
        let back = block(3650, 1001);
        assert!(check_changed(&back, Some(&after), &reads).is_err());
    }

    #[test]
    fn a_spliced_value_is_caught() {
        let reads: VecDeque<TrueRead> =
            [read(36, &[1, 2]), read(36, &[3, 4])].into_iter().collect();
        let ok = RegisterBlock {
            start: 36,
            values: heapless::Vec::from_slice(&[3, 4]).unwrap(),
        };
        assert_eq!(check_registers(&ok, &reads), Ok(()));
        // Low word of one answer, high word of another: never sent as such.
        let spliced = RegisterBlock {
            start: 36,
            values: heapless::Vec::from_slice(&[1, 4]).unwrap(),
        };
        assert!(check_registers(&spliced, &reads).is_err());
    }
}
