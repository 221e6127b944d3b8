//! Numbers with units: a register's raw value and its physical value, exact
//! decimals, rounding without `libm`. Shared by the host link (JSON), the log
//! text and the bridge's configuration record.

use protocol_core::registers::Register;
use protocol_core::settings::SettingId;

/// 10^k for k = 0..=9, exact in f64 (what `10f64.powi(k)` gives).
const POW10: [f64; 10] = [1.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9];

/// 10^k (k up to 9; 1e9 beyond).
pub fn pow10(k: u32) -> f64 {
    POW10.get(k as usize).copied().unwrap_or(1e9)
}

/// |x| (`f64::abs`, which `core` lacks).
pub fn abs(x: f64) -> f64 {
    if x < 0.0 {
        -x
    } else {
        x
    }
}

/// `x` rounded half away from zero to an integer (`f64::round`, which `core`
/// lacks). Exact: for |x| < 2^52, `x - trunc(x)` is representable.
pub fn round(x: f64) -> f64 {
    if !x.is_finite() || abs(x) >= 4_503_599_627_370_496.0 {
        return x;
    }
    let t = x as i64 as f64;
    let d = x - t;
    if d >= 0.5 {
        t + 1.0
    } else if d <= -0.5 {
        t - 1.0
    } else {
        t
    }
}

/// A decimal number `n * 10^-k`, printed exactly as `serde_json` (through `ryu`'s
/// shortest representation) prints the f64 nearest to it, which is that decimal
/// itself while `|n| < 2^53`: `3.3125`, `50.0`, `0.0`, `-10.5`, `1e-6`. Written
/// as raw JSON (`serialize_bytes`, serde-json-core's way to emit a number it did
/// not format) so that no float formatting code is linked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Dec {
    /// Digits.
    pub n: i64,
    /// Decimals.
    pub k: u32,
}

impl Dec {
    /// The value as f64 (`n as f64 / 10^k`, what replay computes).
    pub fn as_f64(self) -> f64 {
        self.n as f64 / pow10(self.k)
    }
}

/// Largest |n| printed exactly (2^53: every integer up to it is an f64).
pub const EXACT: i64 = 1 << 53;

/// `x` rounded half away from zero to `decimals`, `None` (JSON `null`) when not
/// finite: replay's `rounded`. Values too large to print exactly (|x| ≥ 2^53 /
/// 10^decimals, e.g. a corrupt f32 of 1e30) are `None` too: there replay prints
/// ryu's digits of the f64, which only a float formatter could reproduce.
pub fn rounded(x: f64, decimals: u32) -> Option<Dec> {
    if !x.is_finite() {
        return None;
    }
    let r = round(x * pow10(decimals));
    if abs(r) >= EXACT as f64 {
        return None;
    }
    Some(Dec {
        n: r as i64,
        k: decimals,
    })
}

/// Fixed-point value `raw * 10^-decimals`, printed exactly at that resolution:
/// replay's `fixed` (raw 33125 at 4 decimals → `3.3125`).
pub fn fixed(raw: i64, decimals: u32) -> Option<Dec> {
    (raw.unsigned_abs() < EXACT as u64).then_some(Dec {
        n: raw,
        k: decimals,
    })
}

/// A register's scale as an integer step and a number of decimals:
/// `scale = step * 10^-decimals` (0.001 → (1, 3), 0.002 → (2, 3), 1.0 → (1, 0)).
pub fn scale_parts(r: &Register) -> (i64, u32) {
    let scale = f64::from(r.scale);
    for k in 0..=6u32 {
        let m = scale * pow10(k);
        let step = round(m);
        if step >= 1.0 && abs(m - step) < 1e-6 * m {
            return (step as i64, k);
        }
    }
    (1, 0)
}

/// A setting's raw value in its physical unit ([`Register::unit`]).
pub fn physical(id: SettingId, raw: i32) -> Option<Dec> {
    let (step, k) = id.register().map(scale_parts).unwrap_or((1, 0));
    fixed(i64::from(raw).saturating_mul(step), k)
}

/// Relative nudge away from zero before rounding a physical value to raw: the
/// host writes a decimal, and one exactly on a half step (`4.0005` V, `1.005`
/// Ah) becomes an f64 an ulp or so below the tie (`4000.4999999999995`), which
/// would round towards zero. 1e-12 is far above that error (≈ 1e-16 relative)
/// and far below any difference a decimal of up to 12 significant digits makes.
const TIE_NUDGE: f64 = 1e-12;

/// The raw value nearest to a physical value (a decimal exactly on a half step
/// rounds away from zero), `None` when there is none in `i32` (not finite, too
/// large).
pub fn raw_from_physical(id: SettingId, value: f64) -> Option<i32> {
    let (step, k) = id.register().map(scale_parts).unwrap_or((1, 0));
    let x = value * pow10(k) / step as f64;
    let raw = round(x + x * TIE_NUDGE);
    if raw.is_finite() && raw >= f64::from(i32::MIN) && raw <= f64::from(i32::MAX) {
        Some(raw as i32)
    } else {
        None
    }
}
