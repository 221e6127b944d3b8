//! ASCII broadcast lines (HARDWARE-NOTES "Framing"): sent unsolicited when
//! register 343 (Protocol) is ASCII and register 342 (Broadcast Time) is not 0.
//!
//! The real line starts `MST:<TAB>EXT1:----<TAB>EXT2:----<TAB>OS:155...` and ends
//! with CR LF; the rest of its fields are not documented, so after `OS:` (online
//! status, decimal) this simulator adds pack voltage, current, SOC, internal
//! temperature and min/max cell (all derived from the registers). Only printable
//! ASCII, TAB, CR and LF: never 0xAA.

/// Register 343 low byte: ASCII protocol (Rev D §3.4).
pub(crate) const PROTOCOL_ASCII: u16 = 0x01;

/// Broadcast interval for register 342's low byte (Rev D §3.4), µs.
pub(crate) fn interval_us(code: u16) -> Option<u64> {
    Some(match code {
        0x01 => 100_000,
        0x02 => 200_000,
        0x03 => 500_000,
        0x04 => 1_000_000,
        0x05 => 2_000_000,
        0x06 => 5_000_000,
        0x07 => 10_000_000,
        _ => return None,
    })
}

/// The interval when broadcasting is on (343 = ASCII, 342 = 1..=7).
pub(crate) fn active_interval(regs: &[u16]) -> Option<u64> {
    let g = |a: usize| regs.get(a).copied().unwrap_or(0);
    if g(343) & 0xFF == PROTOCOL_ASCII {
        interval_us(g(342) & 0xFF)
    } else {
        None
    }
}

fn temp(raw: u16) -> String {
    if raw == 0x8000 {
        "----".to_string()
    } else {
        format!("{:.1}", f32::from(raw as i16) * 0.1)
    }
}

/// One broadcast line built from the register file, CR LF terminated.
pub(crate) fn line(regs: &[u16]) -> Vec<u8> {
    let g = |a: usize| regs.get(a).copied().unwrap_or(0);
    let f = |a: usize| f32::from_bits(u32::from(g(a)) | (u32::from(g(a + 1)) << 16));
    let soc = f64::from(u32::from(g(46)) | (u32::from(g(47)) << 16)) / 1_000_000.0;
    let s = format!(
        "MST:\tEXT1:{}\tEXT2:{}\tOS:{}\tV:{:.2}\tI:{:.1}\tSOC:{:.1}\tT:{}\tCMIN:{}\tCMAX:{}\r\n",
        temp(g(42)),
        temp(g(43)),
        g(50),
        f(36),
        f(38),
        soc,
        temp(g(48)),
        g(40),
        g(41),
    );
    // Formatting of numbers only ever yields ASCII; keep the guarantee explicit.
    s.bytes().filter(|b| b.is_ascii()).collect()
}
