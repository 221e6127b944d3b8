//! How the battery's current splits between its packs, learnt from how each
//! pack's current moves with the total.
//!
//! Packs in parallel are each an open-circuit voltage E_k behind a resistance
//! R_k (cells, switch, fuse, cable) on one bus. Pack k carries
//! I_k = (V − E_k)/R_k, so when the total T changes by ΔT, pack k's current
//! changes by α_k·ΔT with α_k = G_k / ΣG (G = 1/R): its *share of a change*.
//! The rest of its current, I_k − α_k·T, is what the packs exchange because
//! their voltages differ; it moves only as their states of charge move.
//!
//! The bridges measure every I_k (the summaries) but neither R_k (the cable is
//! outside the BMS) nor the bus voltage. α_k is what can be learnt: the
//! covariance of I_k with T over a window of [`SHARE_WINDOW`] battery steps
//! (one a second), divided by T's variance. Because T = Σ I_k, the estimates
//! add up to 1. The window slides (the last [`SHARE_WINDOW`] currents of
//! every pack are kept, 0.5 KiB), and nothing before it weighs in it: a
//! start, a step taken from data of different moments, values that make no
//! sense are forgotten once they leave it; a window never spans a time
//! when a pack had no data. A window's estimate is taken only when T moved
//! enough in it to say something (its spread at least
//! [`SHARE_MIN_SPREAD_DA`]), every pack's current followed its share of T
//! within [`SHARE_MAX_RESIDUAL_DA`] and every share is one a pack can have
//! (between 0 and 1); it is then kept — through
//! long stretches at one current — until the packs in the battery change,
//! which starts learning again. While nothing is known the battery's rules
//! use the bound that needs no knowledge: a pack may take all of a change.
//!
//! The sums use it with a margin ([`share_with_margin`]): sampling moments differ between
//! bridges, and a real pack's resistance is not quite one number.

use super::summary::MAX_NODES;

/// Window of the estimate, battery steps (seconds).
pub const SHARE_WINDOW: u16 = 32;

/// The total must have moved at least this much (its weighted standard
/// deviation over the window) for an estimate, 0.1 A.
pub const SHARE_MIN_SPREAD_DA: f32 = 20.0;

/// A pack's current must follow the total this closely (the weighted
/// standard deviation of what the share does not explain) for an estimate:
/// data from different moments, a pack that does not behave like a voltage
/// behind a resistance, or values that make no sense teach nothing, 0.1 A.
pub const SHARE_MAX_RESIDUAL_DA: f32 = 5.0;

/// The two halves of a window must give shares this close to each other.
pub const SHARE_AGREE: f32 = 0.1;

/// Relative margin on a learnt share.
pub const SHARE_MARGIN: f32 = 0.25;

/// Absolute margin on a learnt share.
pub const SHARE_MARGIN_ABS: f32 = 0.05;

/// The share used by the sums for a learnt share `alpha`: with its margins,
/// at most 1.
pub fn share_with_margin(alpha: f32) -> f32 {
    (alpha * (1.0 + SHARE_MARGIN) + SHARE_MARGIN_ABS).min(1.0)
}

const N: usize = MAX_NODES as usize;

const W: usize = SHARE_WINDOW as usize;

/// The learnt shares of the packs taking part.
#[derive(Debug, Clone, PartialEq)]
pub struct Shares {
    /// Node bits of the packs the estimate is for.
    mask: u16,
    /// Samples in the window (at most [`SHARE_WINDOW`]).
    len: u16,
    /// Where the next sample goes.
    next: u16,
    /// The last currents of every pack, 0.1 A, by node.
    ring: [[i16; N]; W],
    alpha: [Option<f32>; N],
}

impl Default for Shares {
    fn default() -> Self {
        Self::new()
    }
}

impl Shares {
    /// Nothing learnt.
    pub const fn new() -> Self {
        Self {
            mask: 0,
            len: 0,
            next: 0,
            ring: [[0; N]; W],
            alpha: [None; N],
        }
    }

    /// One battery step: the packs taking part (node number, current in
    /// 0.1 A), and whether a pack may conduct without data. Learning starts
    /// again when the packs taking part change. While a pack may conduct
    /// without data (its current is in nobody's sum) learning pauses and what
    /// was learnt is kept: the same packs still conduct (a pack known to be
    /// open changes the packs taking part).
    pub fn update(&mut self, taking_part: &[(u8, i16)], unknown: bool) {
        if unknown {
            // The window starts again afterwards: one across the gap would
            // compare currents of minutes apart.
            self.len = 0;
            self.next = 0;
            return;
        }
        let mut mask = 0u16;
        for (node, _) in taking_part {
            if let Some(bit) = node.checked_sub(1).filter(|b| usize::from(*b) < N) {
                mask |= 1 << bit;
            }
        }
        if mask != self.mask || mask.count_ones() < 2 {
            *self = Self::new();
            self.mask = mask;
            if mask.count_ones() < 2 {
                return;
            }
        }
        let mut sample = [0i16; N];
        for (node, current) in taking_part {
            if let Some(slot) = node
                .checked_sub(1)
                .and_then(|b| sample.get_mut(usize::from(b)))
            {
                *slot = *current;
            }
        }
        if let Some(slot) = self.ring.get_mut(usize::from(self.next)) {
            *slot = sample;
        }
        self.next = (self.next + 1) % SHARE_WINDOW;
        self.len = (self.len + 1).min(SHARE_WINDOW);
        if self.len >= SHARE_WINDOW {
            self.learn();
        }
    }

    /// The window's shares, if it says enough: the whole window and each of
    /// its halves must fit, and the halves agree within [`SHARE_AGREE`] — so
    /// a single step, or one sample taken while some bridges had reported a
    /// change and others not yet, never teaches on its own.
    fn learn(&mut self) {
        let ordered = |from: usize, to: usize| {
            (from..to).filter_map(|i| self.ring.get((usize::from(self.next) + i) % W))
        };
        let (Some(all), Some(first), Some(second)) = (
            fit(ordered(0, W), self.mask),
            fit(ordered(0, W / 2), self.mask),
            fit(ordered(W / 2, W), self.mask),
        ) else {
            return;
        };
        let agree = first.iter().zip(&second).all(|(a, b)| match (a, b) {
            (Some(a), Some(b)) => (a - b).abs() <= SHARE_AGREE,
            (None, None) => true,
            _ => false,
        });
        if agree {
            self.alpha = all;
        }
    }

    /// Node `node`'s learnt share of a change of the total (no margin), if
    /// it takes part and enough is known.
    pub fn of(&self, node: u8) -> Option<f32> {
        let bit = node.checked_sub(1)?;
        if self.mask & (1u16.checked_shl(u32::from(bit))?) == 0 {
            return None;
        }
        *self.alpha.get(usize::from(bit))?
    }
}

/// The shares that explain `rows` (oldest first, currents by node), if the
/// total moved enough, every pack's current follows its share within
/// [`SHARE_MAX_RESIDUAL_DA`] and every share is one a pack can have
/// (0 < α < 1).
fn fit<'a>(
    rows: impl Iterator<Item = &'a [i16; N]> + Clone,
    mask: u16,
) -> Option<[Option<f32>; N]> {
    // Sums of differences from the first sample (no cancellation in f32).
    let first = *rows.clone().next()?;
    let base: i32 = first.iter().map(|x| i32::from(*x)).sum();
    let (mut n, mut st, mut stt) = (0.0f32, 0.0f32, 0.0f32);
    let (mut si, mut sii, mut sit) = ([0.0f32; N], [0.0f32; N], [0.0f32; N]);
    for row in rows {
        let t = (row.iter().map(|x| i32::from(*x)).sum::<i32>() - base) as f32;
        n += 1.0;
        st += t;
        stt += t * t;
        for (k, x) in row.iter().enumerate() {
            if let (Some(x0), Some(a), Some(b), Some(c)) =
                (first.get(k), si.get_mut(k), sii.get_mut(k), sit.get_mut(k))
            {
                let y = f32::from(*x) - f32::from(*x0);
                *a += y;
                *b += y * y;
                *c += y * t;
            }
        }
    }
    let mean_t = st / n;
    let var_t = stt / n - mean_t * mean_t;
    if var_t < SHARE_MIN_SPREAD_DA * SHARE_MIN_SPREAD_DA {
        return None;
    }
    let mut alpha = [None; N];
    let residual = SHARE_MAX_RESIDUAL_DA * SHARE_MAX_RESIDUAL_DA;
    for (k, a) in alpha.iter_mut().enumerate() {
        if mask & (1 << k) == 0 {
            continue;
        }
        let (si, sii, sit) = (si.get(k)?, sii.get(k)?, sit.get(k)?);
        let mean_i = si / n;
        let var_i = sii / n - mean_i * mean_i;
        let cov = sit / n - mean_i * mean_t;
        let share = cov / var_t;
        if var_i - cov * share > residual || !(share > 0.0 && share < 1.0) {
            return None;
        }
        *a = Some(share);
    }
    Some(alpha)
}
