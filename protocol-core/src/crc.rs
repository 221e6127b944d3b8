//! CRC-16/MODBUS (Rev D §1.2).
//!
//! Polynomial x^16 + x^15 + x^2 + 1 (0x8005, reflected 0xA001), initial value 0xFFFF,
//! no final XOR. The CRC is sent after the frame, least significant byte first.
//! The 256-entry table is computed at compile time and checked against the table
//! printed in Rev D §1.2.

/// Reflected form of the MODBUS polynomial 0x8005.
pub const POLY_REFLECTED: u16 = 0xA001;
/// Initial register value (Rev D §1.2: `crcWord = 0xFFFF`).
pub const INIT: u16 = 0xFFFF;
/// Catalogue check value: CRC-16/MODBUS of the ASCII bytes `123456789`.
pub const CHECK: u16 = 0x4B37;

/// The lookup table of Rev D §1.2, computed by a `const fn`.
pub const TABLE: [u16; 256] = make_table();

const fn make_table() -> [u16; 256] {
    let mut table = [0u16; 256];
    let mut i = 0usize;
    while i < 256 {
        let mut c = i as u16;
        let mut bit = 0;
        while bit < 8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ POLY_REFLECTED
            } else {
                c >> 1
            };
            bit += 1;
        }
        #[allow(clippy::indexing_slicing)] // i < 256 == table.len()
        {
            table[i] = c;
        }
        i += 1;
    }
    table
}

/// One table step. The index is a `u8`, the table has 256 entries: cannot panic.
#[inline(always)]
const fn step(crc: u16, byte: u8) -> u16 {
    #[allow(clippy::indexing_slicing)] // u8 index into a 256-entry table
    let t = TABLE[((crc as u8) ^ byte) as usize];
    (crc >> 8) ^ t
}

/// CRC-16/MODBUS of `data`.
pub const fn crc16(data: &[u8]) -> u16 {
    let mut crc = INIT;
    let mut rest = data;
    // Two bytes per pass: one loop test for two table steps (about 10 % fewer
    // instructions per byte on RV32, the decoder's largest single cost).
    while let [a, b, tail @ ..] = rest {
        crc = step(step(crc, *a), *b);
        rest = tail;
    }
    if let [last] = rest {
        crc = step(crc, *last);
    }
    crc
}

/// Incremental CRC-16/MODBUS, for data that arrives in pieces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Crc16(u16);

impl Default for Crc16 {
    fn default() -> Self {
        Self::new()
    }
}

impl Crc16 {
    /// A fresh CRC register.
    pub const fn new() -> Self {
        Self(INIT)
    }
    /// Feed more bytes.
    pub fn update(&mut self, data: &[u8]) {
        // As `crc16`: two bytes per pass.
        let mut crc = self.0;
        let mut rest = data;
        while let [a, b, tail @ ..] = rest {
            crc = step(step(crc, *a), *b);
            rest = tail;
        }
        if let [last] = rest {
            crc = step(crc, *last);
        }
        self.0 = crc;
    }
    /// The CRC of everything fed so far.
    pub const fn value(&self) -> u16 {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn catalogue_check_value() {
        assert_eq!(crc16(b"123456789"), CHECK);
    }

    #[test]
    fn table_matches_rev_d_section_1_2() {
        // First row, a middle row and the last row of the table printed in Rev D §1.2.
        assert_eq!(
            TABLE[0..8],
            [0x0000, 0xC0C1, 0xC181, 0x0140, 0xC301, 0x03C0, 0x0280, 0xC241]
        );
        assert_eq!(
            TABLE[128..136],
            [0xA001, 0x60C0, 0x6180, 0xA141, 0x6300, 0xA3C1, 0xA281, 0x6240]
        );
        assert_eq!(
            TABLE[248..256],
            [0x8201, 0x42C0, 0x4380, 0x8341, 0x4100, 0x81C1, 0x8081, 0x4040]
        );
        assert_eq!(
            TABLE[168..176],
            [0xBE01, 0x7EC0, 0x7F80, 0xBF41, 0x7D00, 0xBDC1, 0xBC81, 0x7C40]
        );
    }

    #[test]
    fn rev_d_worked_examples() {
        // §1.3.1 MODBUS write request and its echo.
        assert_eq!(
            crc16(&[0xAA, 0x10, 0x01, 0x3B, 0x00, 0x02, 0x04, 0x10, 0x68, 0x09, 0xC4]),
            0x6119
        );
        assert_eq!(crc16(&[0xAA, 0x10, 0x01, 0x3B, 0x00, 0x02]), 0x2228);
        // §1.3.2 MODBUS read request and reply.
        assert_eq!(crc16(&[0xAA, 0x03, 0x00, 0x05, 0x00, 0x05]), 0x138C);
        assert_eq!(
            crc16(&[0xAA, 0x03, 0x0A, 0x97, 0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C]),
            0xC73E
        );
        // §1.3.3 temperatures request and reply.
        assert_eq!(crc16(&[0xAA, 0x1B]), 0x1B3F);
        assert_eq!(
            crc16(&[0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01]),
            0x4E0E
        );
        // The known slip of the French guide: AA 14 is 0x1F7F, not 0x1B3F.
        assert_eq!(crc16(&[0xAA, 0x14]), 0x1F7F);
    }

    #[test]
    fn incremental_equals_one_shot() {
        let data = b"TinyBMS incremental CRC";
        for split in 0..data.len() {
            let mut c = Crc16::new();
            c.update(&data[..split]);
            c.update(&data[split..]);
            assert_eq!(c.value(), crc16(data));
        }
    }
}
