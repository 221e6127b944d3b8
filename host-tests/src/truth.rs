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
