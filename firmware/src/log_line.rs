//! One log line being written: a bounded text with number formatting of its
//! own (no `core::fmt`, which the chip does not link: see `src/chip/panic.rs`).
//! A leaf: the words of the lines are in [`crate::text`].

use heapless::String;

/// Longest line, bytes. A line that would be longer ends in `…` (the link
/// statistics line, the longest, is under 350 bytes with every counter at its widest).
pub const LINE_MAX: usize = 384;

/// One log line being written. Never fails: text beyond [`LINE_MAX`] is cut
/// and the line ends in `…`.
#[derive(Debug, Clone, Default)]
pub struct Line {
    text: String<LINE_MAX>,
    cut: bool,
}

impl Line {
    /// An empty line.
    pub const fn new() -> Self {
        Self {
            text: String::new(),
            cut: false,
        }
    }

    /// The text so far.
    pub fn as_str(&self) -> &str {
        self.text.as_str()
    }

    /// Empties the line.
    pub fn clear(&mut self) {
        self.text.clear();
        self.cut = false;
    }

    /// Appends text.
    pub fn push(&mut self, s: &str) -> &mut Self {
        if self.cut {
            return self;
        }
        for c in s.chars() {
            // Room is kept for the `…` (3 bytes) that marks a cut line.
            if self.text.len() + c.len_utf8() > LINE_MAX - 3 {
                self.cut = true;
                let _ = self.text.push('…');
                return self;
            }
            let _ = self.text.push(c);
        }
        self
    }

    /// Appends an unsigned integer.
    pub fn uint(&mut self, v: u64) -> &mut Self {
        let mut digits = [0u8; 20];
        let mut i = digits.len();
        let mut v = v;
        loop {
            i -= 1;
            if let Some(d) = digits.get_mut(i) {
                *d = b'0' + (v % 10) as u8;
            }
            v /= 10;
            if v == 0 || i == 0 {
                break;
            }
        }
        self.push(core::str::from_utf8(digits.get(i..).unwrap_or(&[])).unwrap_or("?"))
    }

    /// Appends a signed integer.
    pub fn int(&mut self, v: i64) -> &mut Self {
        if v < 0 {
            self.push("-");
        }
        self.uint(v.unsigned_abs())
    }

    /// Appends `0xNN` (at least two upper-case hex digits).
    pub fn hex(&mut self, v: u32) -> &mut Self {
        self.push("0x");
        let mut started = false;
        for shift in (0..8).rev() {
            let nibble = ((v >> (shift * 4)) & 0xF) as usize;
            if nibble != 0 || shift < 2 || started {
                started = true;
                let c = b"0123456789ABCDEF".get(nibble).copied().unwrap_or(b'?');
                self.push(core::str::from_utf8(&[c]).unwrap_or("?"));
            }
        }
        self
    }

    /// Appends `raw · 10^-decimals` with exactly `decimals` digits after the point
    /// (`fixed(3304, 3)` → `3.304`, `fixed(-5, 1)` → `-0.5`).
    pub fn fixed(&mut self, raw: i64, decimals: u32) -> &mut Self {
        if decimals == 0 {
            return self.int(raw);
        }
        let scale = 10u64.saturating_pow(decimals);
        if raw < 0 {
            self.push("-");
        }
        let m = raw.unsigned_abs();
        self.uint(m / scale).push(".");
        let frac = m % scale;
        let mut d = scale / 10;
        while d > 0 {
            self.uint(frac / d % 10);
            d /= 10;
        }
        self
    }

    /// Appends `x` rounded half away from zero to `decimals` places; `?` when
    /// it is not a finite number or too large to print.
    pub fn real(&mut self, x: f32, decimals: u32) -> &mut Self {
        let scaled = f64::from(x) * crate::units::pow10(decimals);
        if !scaled.is_finite() || crate::units::abs(scaled) >= 9.0e15 {
            return self.push("?");
        }
        let r = crate::units::round(scaled) as i64;
        self.fixed(r, decimals)
    }

    /// Appends `x` with `decimals` places and a unit after a space (`3.304 V`).
    pub fn quantity(&mut self, x: f32, decimals: u32, unit: &str) -> &mut Self {
        self.real(x, decimals).push(" ").push(unit)
    }

    /// Appends a temperature in °C with one decimal, or `not connected`.
    pub fn celsius(&mut self, x: Option<f32>) -> &mut Self {
        match x {
            Some(v) => self.quantity(v, 1, "°C"),
            None => self.push("not connected"),
        }
    }

    /// Appends a byte string as upper-case hex, two digits a byte, no spaces.
    pub fn hex_bytes(&mut self, bytes: &[u8]) -> &mut Self {
        for &b in bytes {
            let hi = b"0123456789ABCDEF".get(usize::from(b >> 4)).copied();
            let lo = b"0123456789ABCDEF".get(usize::from(b & 0xF)).copied();
            let pair = [hi.unwrap_or(b'?'), lo.unwrap_or(b'?')];
            self.push(core::str::from_utf8(&pair).unwrap_or("??"));
        }
        self
    }

    /// Appends a duration given in seconds as people read it: `45 s`,
    /// `12 min 5 s`, `3 h 20 min`, `12 d 4 h`.
    pub fn duration_s(&mut self, s: u64) -> &mut Self {
        let (d, h, m, sec) = (s / 86_400, s / 3600 % 24, s / 60 % 60, s % 60);
        if d > 0 {
            self.uint(d).push(" d ").uint(h).push(" h")
        } else if h > 0 {
            self.uint(h).push(" h ").uint(m).push(" min")
        } else if m > 0 {
            self.uint(m).push(" min ").uint(sec).push(" s")
        } else {
            self.uint(sec).push(" s")
        }
    }
}
