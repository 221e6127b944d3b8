//! Writes the capture corpus `host-tests/captures/*.tbms`.
//!
//! ```text
//! cargo run -p host-tests --example mkcorpus          # rewrite the .tbms files
//! BLESS=1 cargo test -p host-tests --test corpus      # then re-bless the golden files
//! ```
//!
//! The committed captures are plain text; this program only saves typing (and
//! computes CRCs). Frames quoted from Rev D §1.3 are written byte for byte as the
//! document prints them, CRC included, so they check protocol-core independently.
//! Every other frame is built from documented values and its CRC computed with
//! protocol-core's CRC-16/MODBUS (itself checked against the Rev D examples).

use std::fmt::Write as _;
use std::path::Path;

use host_tests::sim::{CurrentSensor, PackModel, SimBms, SimConfig};
use protocol_core::crc::crc16;
use protocol_core::frame::{Frame, NackCode};
use protocol_core::request::{Request, ResetOption, SettingsOption};

// ---------------------------------------------------------------------------
// Byte helpers

fn req(r: &Request) -> Vec<u8> {
    r.to_bytes().expect("valid request").to_vec()
}

fn enc(f: &Frame) -> Vec<u8> {
    let mut b = vec![0u8; 1024];
    let n = f.encode(&mut b).expect("encodable frame");
    b.truncate(n);
    b
}

/// A single-packet data frame (PL or not, as the command's layout says).
fn data(command: u8, payload: &[u8]) -> Vec<u8> {
    enc(&Frame::data(command, payload).expect("payload fits"))
}

fn ack(command: u8) -> Vec<u8> {
    enc(&Frame::Ack { command })
}

fn nack(command: u8, code: u8) -> Vec<u8> {
    enc(&Frame::Nack {
        command,
        code: NackCode::from_u8(code),
    })
}

/// `bytes` followed by their CRC (LSB first).
fn with_crc(bytes: &[u8]) -> Vec<u8> {
    let mut v = bytes.to_vec();
    v.extend_from_slice(&crc16(bytes).to_le_bytes());
    v
}

fn be_words(words: &[u16]) -> Vec<u8> {
    words.iter().flat_map(|w| w.to_be_bytes()).collect()
}

fn le_words(words: &[u16]) -> Vec<u8> {
    words.iter().flat_map(|w| w.to_le_bytes()).collect()
}

fn f32_le(x: f32) -> Vec<u8> {
    x.to_le_bytes().to_vec()
}

fn hex(bytes: &[u8]) -> String {
    tinybms_desk::capture::hex(bytes)
}

// ---------------------------------------------------------------------------
// The 14S Li-ion pack of HARDWARE-NOTES, discharging. One table, used by every
// capture that reads live data, so all replies agree with each other.

/// Cells in registers 2-15 (registers 0 and 1 unused, read 0), 0.1 mV;
/// they add up to 55.7800 V.
const CELLS_14S: [u16; 14] = [
    39843, 39851, 39838, 39846, 39840, 39829, 39855, 39842, 39837, 39848, 39844, 39833, 39850,
    39844,
];

/// Registers 0-55 of the pack.
fn live_14s() -> [u16; 56] {
    let mut r = [0u16; 56];
    r[2..16].copy_from_slice(&CELLS_14S);
    let lifetime: u32 = 12_345_678; // s, about 143 days
    r[32] = lifetime as u16;
    r[33] = (lifetime >> 16) as u16;
    r[34] = 18_000; // time left, s (5 h)
    r[35] = 0;
    r[36] = 0x1EB8; // 55.78 V: the words HARDWARE-NOTES quotes
    r[37] = 0x425F;
    let current = (-12.5f32).to_bits();
    r[38] = current as u16;
    r[39] = (current >> 16) as u16;
    r[40] = 3982; // min cell, mV (39829 / 10)
    r[41] = 3985; // max cell, mV (39855 / 10)
    r[42] = 225; // external sensor 1: 22.5 °C
    r[43] = 0x8000; // external sensor 2 not connected (-32768)
    r[44] = 37; // distance left, km
    r[45] = 48_750; // SOH 97.5 % (0.002 %)
    let soc: u32 = 78_543_210; // 78.543210 %
    r[46] = soc as u16;
    r[47] = (soc >> 16) as u16;
    r[48] = 263; // internal 26.3 °C
    r[50] = 0x93; // discharging
    r[51] = 0;
    r[52] = 0;
    r[53] = 14; // detected cells
    let speed = 18.5f32.to_bits();
    r[54] = speed as u16;
    r[55] = (speed >> 16) as u16;
    r
}

/// Registers 100-117 (statistics) of the same unit, read after a wake by UART.
fn stats_block() -> [u16; 18] {
    let mut r = [0u16; 18];
    let dist: u32 = 123_456; // 1234.56 km
    r[0] = dist as u16;
    r[1] = (dist >> 16) as u16;
    r[2] = 452; // peak discharge current 45.2 A
    r[3] = 198; // peak charge current 19.8 A
    r[4] = 312; // max cell difference 0.0312 V
    r[5] = 2; // under-voltage protections
    r[6] = 1; // over-voltage protections
    r[7] = 0;
    r[8] = 0;
    r[9] = 3; // over-heat protections
    r[11] = 187; // charging count
    r[12] = 142; // full charge count
    r[13] = u16::from_le_bytes([(-3i8) as u8, 41]); // min -3 °C, max 41 °C
    r[14] = 0x0305; // last reset POR/PDR (0x05), last wake-up UART (0x03)
    let cleared: u32 = 1_000_000;
    r[16] = cleared as u16;
    r[17] = (cleared >> 16) as u16;
    r
}

/// One event as its two registers (Rev D §3.3).
fn event_regs(ts: u32, id: u8) -> [u16; 2] {
    [ts as u16, u16::from_le_bytes([(ts >> 16) as u8, id])]
}

/// Registers 200-297: 49 slots; a few used, the rest erased (0xFFFF) or 0.
fn events_block() -> [u16; 98] {
    let mut r = [0xFFFFu16; 98];
    let used = [
        (0x3B2810, 0x62), // Charging Started (000 example 5)
        (0x3B2950, 0x63), // Charging Done (000 example 5)
        (0x3B2A10, 0x65), // Charger Disconnected
        (0x3B3000, 0x31), // Fully Discharged Cutoff (warning)
        (0x3B3100, 0x02), // Under-Voltage Cutoff (fault)
        (0x3B3200, 0x7B), // Recovered From Under-Voltage Fault Condition
        (0x3B3300, 0x99), // an ID outside chapter 4
    ];
    for (slot, (ts, id)) in used.iter().enumerate() {
        r[2 * slot..2 * slot + 2].copy_from_slice(&event_regs(*ts, *id));
    }
    for w in &mut r[2 * 45..] {
        *w = 0; // never-written slots read 0 on some units
    }
    r
}

/// Registers 500-509 (version block).
fn version_block() -> [u16; 10] {
    [
        0x0001, // HW 1, HW changes 0
        0x0314, // FW 20; BPT = 1 high power, BCS = 1 internal HALL
        58,     // internal FW 58
        0x0502, // bootloader 2, profile 5
        0x3412, 0x7856, 0xBC9A, 0xF0DE, 0x2301, 0x6745, // serial
    ]
}

/// Settings 300-343 for 0x1D: option -> 44 values. Minimum, maximum and
/// default are the simulated BMS's (one table of the TinyBMS's settings,
/// `host-tests/src/sim/settings.rs`, Rev D §3.4's ranges), with the
/// sensor-dependent ones (304, 305, 317, 318) as a unit with the internal
/// HALL sensor reports them; the current values are this unit's own.
fn settings(option: SettingsOption) -> [u16; 44] {
    let mut r = [0u16; 44];
    if option != SettingsOption::Current {
        let config = SimConfig::default().with_current_sensor(CurrentSensor::InternalHall);
        let sim = SimBms::new(PackModel::LiFePO4_16S, config, 1);
        r.copy_from_slice(&sim.settings_values(option)[..44]);
        return r;
    }
    for (a, v) in [
        (300, 4150),
        (301, 3000),
        (303, 3900),
        (304, 1000),
        (305, 150),
        (306, 2000), // 20.00 Ah
        (307, 14),
        (308, 15),
        (310, 20),
        (311, 5),
        (312, 1000),
        (313, 0),
        (314, 2), // km
        (315, 4200),
        (316, 2800),
        (317, 60),
        (318, 20),
        (319, 60),
        (320, (-5i16) as u16),
        (321, 90),
        (322, 1000),
        (323, 0xFFFF), // "0xFFFF when data internally accepted" (Rev D)
        (328, 0xFFFF), // read back 0xFFFF on a real unit (HARDWARE-NOTES)
        (329, 0b100),  // charger restart level enabled
        (330, 0x0501), // CC/CV, discharge over-current timeout 5 s
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
        (342, 0x04), // broadcast every 1 s ...
        (343, 0x01), // ... as ASCII (see ascii_broadcast.tbms)
    ] {
        r[a - 300] = v;
    }
    r
}

/// The ASCII broadcast line of HARDWARE-NOTES (its fields after OS:155 are
/// elided there; this one stops at them).
const BROADCAST: &[u8] = b"MST:\tEXT1:----\tEXT2:----\tOS:155\r\n";

// ---------------------------------------------------------------------------
// Capture text builder

struct Cap {
    text: String,
    /// A `>` line waiting for the comments that describe it (written before it).
    pending: Option<String>,
    /// Deterministic chunking (xorshift).
    seed: u32,
}

impl Cap {
    fn new(title: &str, about: &[&str]) -> Self {
        let mut c = Cap {
            text: String::new(),
            pending: None,
            seed: 0x1234_5678,
        };
        c.c(title);
        for l in about {
            c.c(l);
        }
        c.c("Generated by `cargo run -p host-tests --example mkcorpus`; golden output in the");
        c.c(".expected.jsonl file beside it (see host-tests/README-capture.md).");
        c
    }
    fn c(&mut self, comment: &str) -> &mut Self {
        if comment.is_empty() {
            self.text.push_str("#\n");
        } else {
            let _ = writeln!(self.text, "# {comment}");
        }
        self
    }
    fn blank(&mut self) -> &mut Self {
        self.flush();
        self.text.push('\n');
        self
    }
    fn flush(&mut self) {
        if let Some(line) = self.pending.take() {
            self.text.push_str(&line);
        }
    }
    /// A request. Comments added with [`Cap::c`] right after it are written
    /// before its `>` line.
    fn tx(&mut self, bytes: &[u8], comment: &str) -> &mut Self {
        self.blank();
        if !comment.is_empty() {
            self.c(comment);
        }
        self.pending = Some(format!("> {}\n", hex(bytes)));
        self
    }
    /// Received bytes, 16 per line.
    fn rx(&mut self, bytes: &[u8], comment: &str) -> &mut Self {
        self.flush();
        if !comment.is_empty() {
            self.c(comment);
        }
        for chunk in bytes.chunks(16) {
            let _ = writeln!(self.text, "< {}", hex(chunk));
        }
        self
    }
    /// Received bytes split at pseudo-random places (1-9 bytes per line).
    fn rx_random(&mut self, bytes: &[u8], comment: &str) -> &mut Self {
        self.flush();
        if !comment.is_empty() {
            self.c(comment);
        }
        let mut rest = bytes;
        while !rest.is_empty() {
            self.seed ^= self.seed << 13;
            self.seed ^= self.seed >> 17;
            self.seed ^= self.seed << 5;
            let n = (1 + self.seed % 9) as usize;
            let (head, tail) = rest.split_at(n.min(rest.len()));
            let _ = writeln!(self.text, "< {}", hex(head));
            rest = tail;
        }
        self
    }
    /// An ASCII broadcast line, as hex, with its text in a comment.
    fn ascii(&mut self, line: &[u8]) -> &mut Self {
        self.flush();
        let shown: String = String::from_utf8_lossy(line).escape_debug().collect();
        self.c(&format!("ASCII broadcast \"{shown}\""));
        self.rx(line, "")
    }
    fn save(&mut self, dir: &Path, name: &str) {
        self.flush();
        let path = dir.join(format!("{name}.tbms"));
        std::fs::write(&path, &self.text).expect("write capture");
        println!("wrote {}", path.display());
    }
}

fn main() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("captures");
    std::fs::create_dir_all(&dir).expect("create captures/");
    let live = live_14s();

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Rev D §1.3 worked examples, byte for byte (CRCs as printed in the document).",
        &[],
    );
    c.tx(
        &[
            0xAA, 0x10, 0x01, 0x3B, 0x00, 0x02, 0x04, 0x10, 0x68, 0x09, 0xC4, 0x19, 0x61,
        ],
        "§1.3.1 MODBUS write: 315 (over-voltage cutoff) = 4200 mV, 316 (under-voltage) = 2500 mV",
    );
    c.rx(
        &[0xAA, 0x10, 0x01, 0x3B, 0x00, 0x02, 0x28, 0x22],
        "§1.3.1 reply: echo of address 0x013B and count 2",
    );
    c.tx(
        &[0xAA, 0x03, 0x00, 0x05, 0x00, 0x05, 0x8C, 0x13],
        "§1.3.2 MODBUS read of 5 registers from address 5 (the document says \"cells 5 to 9\";",
    );
    c.c("in the register map they are cells 6-10: register 0 is cell 1). Without register 53");
    c.c("the cell numbering is unknown, so replay reports voltages by register address.");
    c.rx(
        &[
            0xAA, 0x03, 0x0A, 0x97, 0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C, 0x3E,
            0xC7,
        ],
        "§1.3.2 reply: 3.872, 3.872, 3.870, 3.870, 3.870 V",
    );
    c.tx(&[0xAA, 0x1B, 0x3F, 0x1B], "§1.3.3 read temperatures");
    c.rx(
        &[
            0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4E,
        ],
        "§1.3.3 reply: internal 27.8 °C, external #1 27.6 °C, external #2 27.8 °C",
    );
    c.save(&dir, "rev_d_examples");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Examples of the French reference guide (000), with CRCs computed (the guide prints",
        &["[CRC] placeholders)."],
    );
    c.tx(
        &req(&Request::read_registers_native(5, 5).unwrap()),
        "000 §4 0x07: read 5 registers from 5, native (little-endian words)",
    );
    c.rx(
        &data(
            0x07,
            &[0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C, 0x97],
        ),
        "000 §4 reply: the same five cells as Rev D §1.3.2",
    );
    for (raw, what) in [(0x91u8, "Charging"), (0x93, "Discharging"), (0x9B, "Fault")] {
        c.tx(
            &req(&Request::ReadOnlineStatus),
            "000 example 4: online status",
        );
        c.rx(
            &data(0x18, &[raw, 0x00]),
            &format!("status 0x{raw:02X} = {what}"),
        );
    }
    c.tx(
        &req(&Request::ReadNewestEvents),
        "000 example 5: newest events",
    );
    c.c("The guide shows three 4-byte CAN-style messages; on the UART the same data is one frame");
    c.c("(Rev D §1.1.9): BMS timestamp 0x003B2A00, then 0x3B2810 Charging Started and");
    c.c("0x3B2950 Charging Done.");
    c.rx(
        &data(
            0x11,
            &[
                0x00, 0x2A, 0x3B, 0x00, 0x10, 0x28, 0x3B, 0x62, 0x50, 0x29, 0x3B, 0x63,
            ],
        ),
        "",
    );
    c.tx(&req(&Request::ReadSoc), "000 example 6: SOC");
    c.rx(
        &data(0x1A, &[0x00, 0x24, 0xF4, 0x01]),
        "bytes 00 24 F4 01 = 0x01F42400 = 32777216 = 32.777216 % (the guide's \"32.8 %\" is a slip)",
    );
    c.tx(
        &req(&Request::ResetClear(ResetOption::ClearStatistics)),
        "000 example 7: clear statistics",
    );
    c.rx(&ack(0x02), "ACK");
    c.tx(
        &req(&Request::ReadExtendedVersion),
        "000 example 8: extended version (PL corrected to 7, see doc_slips.tbms)",
    );
    c.rx(
        &data(0x1F, &[0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05]),
        "HW 1, HW changes 0, FW 20, internal FW 58, bootloader 2, register map 5",
    );
    c.save(&dir, "guide_examples");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Known slips of the documents (spec/README.md), as a BMS would see them.",
        &[],
    );
    c.tx(
        &[0xAA, 0x14, 0x3F, 0x1B],
        "000 §3 gives the 0x14 request as AA 14 3F 1B; 3F 1B is the CRC of AA 1B: the request fails",
    );
    c.c("its CRC check, and the BMS refuses it with NACK 0x01 (CRC error, Rev D §1.1.1).");
    c.rx(&nack(0x14, 0x01), "");
    c.tx(
        &[0xAA, 0x14, 0x7F, 0x1F],
        "the correct request: CRC(AA 14) = 0x1F7F",
    );
    c.rx(&data(0x14, &f32_le(55.78)), "55.78 V");
    c.tx(
        &req(&Request::ReadExtendedVersion),
        "000 example 8 as printed:",
    );
    c.c("AA 1F 08 01 00 14 3A 00 02 05 + CRC: PL says 8 but only 7 data bytes follow. Taken");
    c.c("literally the frame is one byte short, so the silence after it makes it `truncated`.");
    c.rx(
        &with_crc(&[0xAA, 0x1F, 0x08, 0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05]),
        "",
    );
    c.tx(&req(&Request::ReadExtendedVersion), "");
    c.rx(
        &with_crc(&[0xAA, 0x1F, 0x07, 0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05]),
        "the same reply with PL = 7: decodes as the guide describes",
    );
    c.tx(&req(&Request::ReadExtendedVersion), "");
    c.rx(
        &with_crc(&[
            0xAA, 0x1F, 0x08, 0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05, 0x00,
        ]),
        "PL = 8 with an 8th byte: accepted, the extra byte is ignored",
    );
    c.tx(
        &req(&Request::read_settings(SettingsOption::Current, 30).unwrap()),
        "000 lists 323-324 as SOH and 328-329 as SOC; Rev D has one register each, and 329",
    );
    c.c("is the configuration-flags bitmap: state_of_health = 323, state_of_charge = 328,");
    c.c("configuration_flags = 329.");
    c.rx(
        &data(0x1D, &le_words(&settings(SettingsOption::Current)[..30])),
        "",
    );
    c.save(&dir, "doc_slips");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "A full 0x03 read of registers 0-55 from a 14S Li-ion pack (HARDWARE-NOTES): registers",
        &[
            "0 and 1 read 0, the 14 cells sit in registers 2-15, register 53 = 14, registers 36/37 =",
            "0x1EB8, 0x425F = 55.78 V, external sensor 2 disconnected (0x8000). Other values are",
            "documented-range values for a pack discharging at 12.5 A: current -12.5 A, SOC",
            "78.543210 %, SOH 97.5 %, internal 26.3 °C, ext #1 22.5 °C, 18.5 km/h, 37 km, 5 h left.",
        ],
    );
    c.tx(
        &req(&Request::read_registers(0, 56).unwrap()),
        "0x03 read 56 registers from 0",
    );
    c.rx(
        &data(0x03, &be_words(&live)),
        "PL 0x70 = 112 bytes, big-endian words",
    );
    c.save(&dir, "live_snapshot_14s");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "The dedicated read commands 0x14-0x20 (Rev D §1.1.11-§1.1.23) on the same 14S pack.",
        &[],
    );
    c.tx(&req(&Request::ReadPackVoltage), "0x14 pack voltage (f32)");
    c.rx(&data(0x14, &f32_le(f32::from_bits(0x425F_1EB8))), "55.78 V");
    c.tx(&req(&Request::ReadPackCurrent), "0x15 pack current (f32)");
    c.rx(&data(0x15, &f32_le(-12.5)), "-12.5 A");
    c.tx(
        &req(&Request::ReadMaxCellVoltage),
        "0x16 max cell voltage (mV)",
    );
    c.rx(&data(0x16, &le_words(&[3985])), "3.985 V");
    c.tx(
        &req(&Request::ReadMinCellVoltage),
        "0x17 min cell voltage (mV)",
    );
    c.rx(&data(0x17, &le_words(&[3982])), "3.982 V");
    c.tx(&req(&Request::ReadOnlineStatus), "0x18 online status");
    c.rx(&data(0x18, &le_words(&[0x93])), "0x93 discharging");
    c.tx(&req(&Request::ReadOnlineStatus), "0x18 again");
    c.rx(
        &data(0x18, &le_words(&[0x55])),
        "0x55: not in Rev D's list, reported as unknown_0x55",
    );
    c.tx(
        &req(&Request::ReadLifetime),
        "0x19 lifetime counter (u32, s)",
    );
    c.rx(&data(0x19, &12_345_678u32.to_le_bytes()), "12345678 s");
    c.tx(&req(&Request::ReadSoc), "0x1A SOC (u32, 0.000001 %)");
    c.rx(&data(0x1A, &78_543_210u32.to_le_bytes()), "78.543210 %");
    c.tx(
        &req(&Request::ReadTemperatures),
        "0x1B temperatures (i16, 0.1 °C)",
    );
    c.rx(
        &data(0x1B, &le_words(&[263, 225, 0x8000])),
        "internal 26.3 °C, external #1 22.5 °C, external #2 not connected (-32768)",
    );
    c.tx(
        &req(&Request::ReadCellVoltages),
        "0x1C cell voltages (0.1 mV)",
    );
    c.rx(&data(0x1C, &le_words(&CELLS_14S)), "the 14 cells");
    c.tx(&req(&Request::ReadVersion), "0x1E version");
    c.rx(
        &data(0x1E, &[0x01, 0x00, 0x14, 0x3A, 0x00]),
        "HW 1, HW changes 0, FW 20, internal FW 58 (as 000 example 8)",
    );
    c.tx(&req(&Request::ReadExtendedVersion), "0x1F extended version");
    c.rx(
        &data(0x1F, &[0x01, 0x00, 0x14, 0x3A, 0x00, 0x02, 0x05]),
        "... bootloader 2, register map 5",
    );
    c.tx(
        &req(&Request::ReadSpeedDistanceTime),
        "0x20 speed (f32 km/h), distance left (u32 km), time left (u32 s)",
    );
    let mut p = f32_le(18.5);
    p.extend_from_slice(&37u32.to_le_bytes());
    p.extend_from_slice(&18_000u32.to_le_bytes());
    c.rx(&data(0x20, &p), "18.5 km/h, 37 km, 18000 s");
    c.save(&dir, "dedicated_reads");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Native reads 0x07 and 0x09 (little-endian), partial register sets.",
        &[],
    );
    c.tx(
        &req(&Request::read_registers_native(32, 24).unwrap()),
        "0x07 read 32-55: every live value except the cells (no registers 0-15)",
    );
    c.rx(&data(0x07, &le_words(&live[32..56])), "");
    c.tx(
        &req(&Request::read_individual(&[36, 37, 38, 39, 46, 47, 50, 53, 43]).unwrap()),
        "0x09 read 36, 37, 38, 39, 46, 47, 50, 53, 43: voltage, current, SOC, status, cell count, ext #2",
    );
    let mut p = Vec::new();
    for a in [36u16, 37, 38, 39, 46, 47, 50, 53, 43] {
        p.extend_from_slice(&a.to_le_bytes());
        p.extend_from_slice(&live[a as usize].to_le_bytes());
    }
    c.rx(
        &data(0x09, &p),
        "reply: ADDR_L ADDR_H DATA_L DATA_H per register (HARDWARE-NOTES)",
    );
    c.tx(
        &req(&Request::read_individual(&[36, 38]).unwrap()),
        "0x09 read 36 and 38, the low words of voltage and current: half a value is not decoded",
    );
    let mut p = Vec::new();
    for a in [36u16, 38] {
        p.extend_from_slice(&a.to_le_bytes());
        p.extend_from_slice(&live[a as usize].to_le_bytes());
    }
    c.rx(&data(0x09, &p), "");
    c.tx(
        &req(&Request::read_individual(&[40, 41]).unwrap()),
        "0x09 whose address echo differs from the request: echo_mismatch",
    );
    c.rx(&data(0x09, &[40, 0, 0x8E, 0x0F, 42, 0, 0x91, 0x0F]), "");
    c.tx(
        &req(&Request::read_individual(&[14, 15, 53]).unwrap()),
        "0x09 of two cell registers and 53: cells need all of 0-15, so voltages by register",
    );
    let mut p = Vec::new();
    for a in [14u16, 15, 53] {
        p.extend_from_slice(&a.to_le_bytes());
        p.extend_from_slice(&live[a as usize].to_le_bytes());
    }
    c.rx(&data(0x09, &p), "");
    c.save(&dir, "native_reads");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Multi-packet native replies: PL bit 7 set = more packets (bits 0-5 = packet ID), the",
        &["last packet has bit 7 clear and bits 0-5 = its size (HARDWARE-NOTES \"Framing\")."],
    );
    c.tx(
        &req(&Request::read_registers_native(0, 45).unwrap()),
        "0x07 read 45 registers from 0 (90 bytes): as seen on a real unit, a first packet",
    );
    c.c("with PL = 0x82 (63 bytes) and a last packet of 27 bytes.");
    let payload = le_words(&live[..45]);
    let mut first = vec![0xAA, 0x07, 0x82];
    first.extend_from_slice(&payload[..63]);
    c.rx(&with_crc(&first), "packet 0x82: 63 bytes");
    let mut last = vec![0xAA, 0x07, 27];
    last.extend_from_slice(&payload[63..]);
    c.rx(&with_crc(&last), "last packet: 27 bytes");
    c.tx(
        &req(&Request::read_registers_native(200, 98).unwrap()),
        "0x07 read of the whole event log 200-297 (196 bytes = 63 + 63 + 63 + 7)",
    );
    c.rx(
        &data(0x07, &le_words(&events_block())),
        "packets with IDs 1, 2, 3 (PL 0x81, 0x82, 0x83), then the last one (PL 7)",
    );
    c.tx(
        &req(&Request::ReadAllEvents),
        "0x12 all events: 20 events = 4 + 80 bytes = 63 + 21",
    );
    let mut p = 0x003B_4000u32.to_le_bytes().to_vec();
    let ids = [
        0x61u8, 0x64, 0x62, 0x63, 0x65, 0x61, 0x64, 0x62, 0x38, 0x65, 0x61, 0x05, 0x77, 0x64, 0x62,
        0x63, 0x65, 0x0B, 0x66, 0x67,
    ];
    for (i, id) in ids.iter().enumerate() {
        let ts = 0x003B_0000u32 + 0x100 * i as u32;
        p.extend_from_slice(&ts.to_le_bytes()[..3]);
        p.push(*id);
    }
    c.rx(&data(0x12, &p), "");
    c.save(&dir, "multi_packet");

    // -----------------------------------------------------------------------
    let mut c = Cap::new("Broken multi-packet replies: never a partial value.", &[]);
    let payload: Vec<u8> = le_words(&events_block());
    let all = data(0x07, &payload); // 68 + 68 + 68 + 12 bytes
    let (p1, p2, p3, p4) = (&all[..68], &all[68..136], &all[136..204], &all[204..]);
    c.tx(
        &req(&Request::read_registers_native(200, 98).unwrap()),
        "0x07 read 200-297, the second packet lost: packet_out_of_order (ID 3 after ID 1);",
    );
    c.c("the reassembly restarts at ID 3 and the last packet ends it with 70 of the 196 bytes");
    c.c("the request implies: packet_missing. No partial value is returned.");
    c.rx(p1, "packet ID 1")
        .rx(p3, "packet ID 3")
        .rx(p4, "last packet");
    c.tx(
        &req(&Request::read_registers_native(200, 98).unwrap()),
        "the same read, packets 1 and 2 swapped: every restart is out of order, and the",
    );
    c.c("last reassembly (from ID 3) is short: packet_missing.");
    c.rx(p2, "packet ID 2")
        .rx(p1, "packet ID 1")
        .rx(p3, "packet ID 3")
        .rx(p4, "last packet");
    c.tx(
        &req(&Request::read_registers_native(200, 98).unwrap()),
        "the same read, cut off after two packets: the silence ends it (incomplete_packets)",
    );
    c.rx(p1, "packet ID 1").rx(p2, "packet ID 2");
    c.tx(
        &req(&Request::read_registers_native(200, 98).unwrap()),
        "the same read, the packet before the last lost: IDs are consecutive (1, 2) but the",
    );
    c.c("length (133 bytes) does not match the request -> packet_missing.");
    c.rx(p1, "packet ID 1")
        .rx(p2, "packet ID 2")
        .rx(p4, "last packet");
    c.tx(
        &req(&Request::read_registers_native(200, 98).unwrap()),
        "and finally the complete reply",
    );
    c.rx(&all, "");
    c.save(&dir, "multi_packet_errors");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Writes: 0x0B and 0x0D answered by ACK, 0x10 by its echo; refusals.",
        &[],
    );
    c.tx(
        &req(&Request::write_registers_native(315, &[4200, 2500]).unwrap()),
        "0x0B write block, native: 315 = 4200 mV, 316 = 2500 mV (PL = 2 + 2n = 6, HARDWARE-NOTES)",
    );
    c.rx(&ack(0x0B), "ACK 0x0B");
    c.tx(
        &req(&Request::write_individual(&[(300, 4150), (342, 0x0004)]).unwrap()),
        "0x0D write individual: 300 = 4150 mV, 342 = 0x0004 (broadcast every 1 s)",
    );
    c.rx(&ack(0x0D), "ACK 0x0D");
    c.tx(
        &req(&Request::write_registers(306, &[2000, 14]).unwrap()),
        "0x10 write 306 = 2000 (20.00 Ah), 307 = 14 cells",
    );
    c.rx(
        &data(0x10, &[0x01, 0x32, 0x00, 0x02]),
        "echo: address 306, 2 registers",
    );
    c.tx(
        &with_crc(&[0xAA, 0x10, 0x01, 0x90, 0x00, 0x01, 0x02, 0x00, 0x01]),
        "0x10 write to register 400, outside 300-399: refused by Request::parse (not_writable);",
    );
    c.c("a real unit answered such a write AA 00 10 00 (NACK, command error; HARDWARE-NOTES).");
    c.rx(&nack(0x10, 0x00), "");
    c.tx(
        &req(&Request::write_individual(&[(315, 5000)]).unwrap()),
        "0x0D write 315 = 5000 mV, above Rev D's 4500: the BMS refuses it",
    );
    c.rx(&nack(0x0D, 0x00), "NACK 0x00 command error");
    c.tx(
        &req(&Request::write_registers(315, &[4200]).unwrap()),
        "0x10 write whose echo names another address: echo_mismatch",
    );
    c.rx(&data(0x10, &[0x01, 0x3C, 0x00, 0x01]), "");
    c.save(&dir, "writes");

    // -----------------------------------------------------------------------
    let mut c = Cap::new("0x02 reset / clear, every option (Rev D §1.1.8).", &[]);
    c.tx(
        &req(&Request::ResetClear(ResetOption::ClearEvents)),
        "option 0x01: clear events",
    );
    c.rx(&ack(0x02), "ACK");
    c.tx(
        &req(&Request::ResetClear(ResetOption::ClearStatistics)),
        "option 0x02: clear statistics",
    );
    c.rx(&ack(0x02), "ACK");
    c.tx(
        &with_crc(&[0xAA, 0x02, 0x03]),
        "option 0x03 does not exist: Request::parse refuses it (malformed), the BMS NACKs it",
    );
    c.rx(&nack(0x02, 0x00), "");
    c.tx(
        &req(&Request::ResetClear(ResetOption::ResetBms)),
        "option 0x05: reset the BMS. Its ACK may never come (HARDWARE-NOTES): silence, so",
    );
    c.c("replay reports no_response with expected_silence.");
    c.tx(
        &req(&Request::ReadOnlineStatus),
        "the first command after the restart is answered",
    );
    c.rx(&data(0x18, &le_words(&[0x97])), "idle");
    c.save(&dir, "reset_clear");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "0x1D read settings, every option, registers 300-343 (Rev D §1.1.20, §3.4).",
        &["Min / max are Rev D's ranges; the sensor-dependent ones as this unit reports them."],
    );
    for (opt, what) in [
        (SettingsOption::Min, "min"),
        (SettingsOption::Max, "max"),
        (SettingsOption::Default, "default"),
        (SettingsOption::Current, "current"),
    ] {
        c.tx(
            &req(&Request::read_settings(opt, 44).unwrap()),
            &format!("option 0x{:02X} ({what}), 44 registers", opt.to_u8()),
        );
        c.rx(&data(0x1D, &le_words(&settings(opt))), "");
    }
    c.save(&dir, "settings");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Register blocks of chapter 3 read with 0x03: statistics, event log, version.",
        &[],
    );
    c.tx(
        &req(&Request::read_registers(100, 18).unwrap()),
        "statistics 100-117",
    );
    c.rx(&data(0x03, &be_words(&stats_block())), "");
    c.tx(
        &req(&Request::read_registers(200, 98).unwrap()),
        "event log 200-297 (49 slots)",
    );
    c.rx(
        &data(0x03, &be_words(&events_block())),
        "7 events; erased slots (0xFFFF) and never-written ones (0) are left out",
    );
    c.tx(
        &req(&Request::read_registers(500, 10).unwrap()),
        "version 500-509",
    );
    c.rx(&data(0x03, &be_words(&version_block())), "");
    c.tx(
        &req(&Request::read_registers(300, 44).unwrap()),
        "settings 300-343 through 0x03 (current values)",
    );
    c.rx(
        &data(0x03, &be_words(&settings(SettingsOption::Current))),
        "",
    );
    c.save(&dir, "register_blocks");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "NACKs (Rev D §1.1.1: 0x00 command error, 0x01 CRC error) and an unknown code.",
        &[],
    );
    c.tx(
        &req(&Request::read_registers(600, 4).unwrap()),
        "0x03 read of 600-603, past the register map: NACK 0x00",
    );
    c.rx(&nack(0x03, 0x00), "");
    c.tx(
        &req(&Request::ReadCellVoltages),
        "0x1C answered with NACK 0x01 (CRC error)",
    );
    c.rx(&nack(0x1C, 0x01), "");
    c.tx(
        &req(&Request::ReadLifetime),
        "0x19 answered with NACK 0x07: not a Rev D code",
    );
    c.rx(&nack(0x19, 0x07), "");
    c.tx(
        &req(&Request::read_settings(SettingsOption::Max, 1).unwrap()),
        "0x1D NACK 0x00",
    );
    c.rx(&nack(0x1D, 0x00), "");
    c.save(&dir, "nacks");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Bad CRCs: the frame is an error, decoding resumes right after.",
        &[],
    );
    let mut bad = vec![
        0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4F,
    ];
    c.tx(&req(&Request::ReadTemperatures), "");
    c.rx(
        &bad,
        "Rev D §1.3.3 reply with the CRC's high byte changed (0x4E -> 0x4F)",
    );
    c.tx(&req(&Request::ReadTemperatures), "asked again");
    bad[10] = 0x4E;
    c.rx(&bad, "the good reply");
    c.tx(&req(&Request::read_registers(0, 56).unwrap()), "");
    let mut frame = data(0x03, &be_words(&live));
    frame[40] ^= 0x04; // one bit flipped inside the payload
    c.rx(
        &frame,
        "the live snapshot with one payload bit flipped: crc_mismatch, no values",
    );
    c.tx(&req(&Request::ReadPackCurrent), "");
    let mut f = data(0x15, &f32_le(-12.5));
    f[5] ^= 0x80;
    c.rx(
        &f,
        "0x15 with the float's sign bit flipped (41 instead of C1): without the CRC it would read +12.5 A",
    );
    c.tx(
        &req(&Request::write_individual(&[(300, 4150)]).unwrap()),
        "",
    );
    let mut a = ack(0x0D);
    a[4] ^= 0x01;
    c.rx(
        &a,
        "an ACK with a bad CRC: frame_type ack, cmd of the outstanding request",
    );
    c.save(&dir, "bad_crc");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "A corrupt frame containing the start of a good one: only the corrupt frame's",
        &["preamble is dropped, the rest is scanned again and the good frame is found."],
    );
    let good = [
        0xAA, 0x03, 0x0A, 0x97, 0x40, 0x97, 0x40, 0x97, 0x2C, 0x97, 0x2C, 0x97, 0x2C, 0x3E, 0xC7,
    ];
    c.tx(
        &[0xAA, 0x03, 0x00, 0x05, 0x00, 0x05, 0x8C, 0x13],
        "Rev D §1.3.2 request",
    );
    c.rx(&good[..6], "the reply starts, and is cut after 6 bytes ...");
    c.rx(&good, "... by a complete copy (Rev D §1.3.2 reply)");
    c.tx(&[0xAA, 0x1B, 0x3F, 0x1B], "Rev D §1.3.3 request");
    c.rx(
        &[0xAA, 0x1B, 0x06, 0x16, 0x01],
        "a cut temperature reply whose remaining bytes are taken from the next frame ...",
    );
    c.rx(
        &[
            0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4E,
        ],
        "... the good one",
    );
    c.tx(
        &req(&Request::read_registers(36, 2).unwrap()),
        "0x03 read 36-37",
    );
    c.rx(
        &[0xAA, 0x03, 0x7F],
        "a header with an impossible (odd) PL 0x7F: bad_length, then the real reply",
    );
    c.rx(&data(0x03, &be_words(&live[36..38])), "");
    c.save(&dir, "corrupt_frame_with_good_inside");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "ASCII broadcast lines (register 343 = ASCII, 342 != 0) between and around frames",
        &["(HARDWARE-NOTES). They are skipped and counted in skipped_bytes."],
    );
    c.blank();
    c.ascii(BROADCAST);
    c.tx(&req(&Request::ReadPackVoltage), "");
    c.ascii(BROADCAST);
    c.rx(&data(0x14, &f32_le(55.78)), "55.78 V");
    c.ascii(BROADCAST);
    c.tx(&req(&Request::ReadTemperatures), "");
    c.rx(
        &[
            0xAA, 0x1B, 0x06, 0x16, 0x01, 0x14, 0x01, 0x16, 0x01, 0x0E, 0x4E,
        ],
        "Rev D §1.3.3 reply, directly followed by a broadcast line",
    );
    c.ascii(b"MST:\t\r\n");
    c.ascii(BROADCAST);
    c.tx(
        &req(&Request::read_registers(0, 56).unwrap()),
        "live snapshot",
    );
    let mut mixed = BROADCAST.to_vec();
    mixed.extend_from_slice(&data(0x03, &be_words(&live)));
    mixed.extend_from_slice(BROADCAST);
    c.rx_random(&mixed, "broadcast + reply + broadcast, in random chunks");
    c.save(&dir, "ascii_broadcast");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Random chunking: the replies of live_snapshot_14s and dedicated_reads split at",
        &["arbitrary places across `<` lines (1-9 bytes each); frames span lines."],
    );
    c.tx(&req(&Request::read_registers(0, 56).unwrap()), "");
    c.rx_random(&data(0x03, &be_words(&live)), "");
    c.tx(&req(&Request::ReadTemperatures), "");
    c.rx_random(&data(0x1B, &le_words(&[263, 225, 0x8000])), "");
    c.tx(&req(&Request::ReadCellVoltages), "");
    c.rx_random(&data(0x1C, &le_words(&CELLS_14S)), "");
    c.tx(&req(&Request::read_registers_native(0, 45).unwrap()), "");
    c.rx_random(&data(0x07, &le_words(&live[..45])), "multi-packet, chunked");
    c.tx(
        &req(&Request::write_individual(&[(300, 4150)]).unwrap()),
        "",
    );
    c.rx_random(&ack(0x0D), "");
    c.save(&dir, "random_chunking");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "A sleeping BMS (Rev D §1.3 note, HARDWARE-NOTES \"Sleep\"): the first command wakes it",
        &["and gets no answer; the same command sent again is answered."],
    );
    c.tx(&req(&Request::ReadPackVoltage), "first try: no answer");
    c.tx(
        &req(&Request::ReadPackVoltage),
        "second try, after the timeout",
    );
    c.rx(&data(0x14, &f32_le(55.78)), "55.78 V");
    c.tx(
        &req(&Request::read_registers(100, 18).unwrap()),
        "statistics: register 114's high byte is 0x03, \"UART communication detected\"",
    );
    c.rx(&data(0x03, &be_words(&stats_block())), "");
    c.save(&dir, "sleeping_bms");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Frames nobody asked for, duplicates, and replies of the wrong kind.",
        &[],
    );
    c.rx(
        &data(0x14, &f32_le(55.78)),
        "a 0x14 reply before any request: unsolicited, decoded from the frame alone",
    );
    c.tx(
        &req(&Request::ReadSoc),
        "an awake BMS sent the same request twice answers twice (HARDWARE-NOTES)",
    );
    c.rx(&data(0x1A, &78_543_210u32.to_le_bytes()), "the answer");
    c.rx(
        &data(0x1A, &78_543_210u32.to_le_bytes()),
        "the second answer: duplicate",
    );
    c.tx(&req(&Request::ReadTemperatures), "");
    c.rx(
        &data(0x14, &f32_le(55.78)),
        "a 0x14 reply while 0x1B is outstanding: unsolicited",
    );
    c.rx(
        &data(0x1B, &le_words(&[263, 225, 0x8000])),
        "then the real answer",
    );
    c.tx(&req(&Request::ReadLifetime), "");
    c.rx(
        &data(0x03, &be_words(&live[36..38])),
        "a 0x03 block while 0x19 is outstanding: addresses unknown, raw words only",
    );
    c.rx(&data(0x19, &12_345_678u32.to_le_bytes()), "");
    c.tx(&req(&Request::read_registers(40, 2).unwrap()), "");
    c.rx(&ack(0x03), "an ACK to a read: unexpected_kind");
    c.tx(&req(&Request::write_individual(&[(332, 5)]).unwrap()), "");
    c.rx(
        &data(0x1D, &le_words(&[4150, 3000])),
        "a 0x1D reply while a write is outstanding",
    );
    c.rx(&ack(0x0D), "");
    c.rx(&ack(0x0B), "an ACK for another command");
    c.save(&dir, "unsolicited_and_duplicates");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Replies that frame correctly but do not fit the request; a reply cut by the end of file.",
        &[],
    );
    c.tx(
        &req(&Request::read_registers(5, 5).unwrap()),
        "5 registers asked ...",
    );
    c.rx(
        &data(0x03, &be_words(&[38720, 38720, 38700, 38700])),
        "... 4 returned: length_mismatch",
    );
    c.tx(&req(&Request::read_registers_native(36, 2).unwrap()), "");
    c.rx(
        &data(0x07, &le_words(&[0x1EB8])),
        "1 of 2 registers: packet_missing (the decoder knows the request; a short native reply and a lost packet look alike)",
    );
    c.tx(&req(&Request::ReadTemperatures), "");
    c.rx(
        &[0xAA, 0x1B, 0x04, 0x16, 0x01, 0x14, 0x01],
        "PL 4 is impossible for 0x1B (always 6): bad_length; the rest is skipped",
    );
    c.tx(&req(&Request::ReadPackVoltage), "");
    c.rx(
        &data(0x14, &f32_le(55.78))[..5],
        "the file ends inside the reply: truncated",
    );
    c.save(&dir, "response_errors");

    // -----------------------------------------------------------------------
    let mut c = Cap::new(
        "Requests that do not parse (each an error line; frames of their command follow",
        &["without the unsolicited flag), and noise bytes that are no frame at all."],
    );
    c.tx(
        &[0xAA, 0x13, 0x00, 0x00],
        "0x13 is no command: unknown_command",
    );
    c.tx(&[0x55, 0x14, 0x7F, 0x1F], "no preamble");
    c.tx(&[0xAA, 0x03, 0x00, 0x05, 0x00], "cut short: truncated");
    c.tx(
        &[0xAA, 0x14, 0x7F, 0x1F, 0x00],
        "one byte too many: trailing_bytes",
    );
    c.tx(
        &with_crc(&[0xAA, 0x03, 0x00, 0x00, 0x00, 0x80]),
        "0x03 of 128 registers (max 127): too_many_registers",
    );
    c.rx(&nack(0x03, 0x00), "the BMS refuses it");
    c.tx(&req(&Request::ReadPackVoltage), "");
    c.rx(
        &[0x00, 0xFF, 0x13, 0x37, 0xAA, 0x42, 0xAA, 0x02],
        "line noise, including preambles followed by bytes no reply starts with",
    );
    c.rx(&data(0x14, &f32_le(55.78)), "then the reply");
    c.save(&dir, "bad_requests_and_noise");
}
