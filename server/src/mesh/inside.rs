//! Which samples of a row are inside (`value >= iso`), as the bits of a word: the first pass of
//! [`super::mc_rows`], which reads every point of a tile once.
//!
//! On x86-64 a vector at a time with SSE2 (part of every x86-64 CPU; through `safe_arch`, which
//! wraps the intrinsics safely): a vector compare and a movemask make sixteen bits (u8), eight
//! (u16) or four (f32) in a few instructions, where the same loop written portably compiles to
//! a compare and a shift per value. Other targets use the portable loop, which also takes each
//! row's last few values.

/// Bits `0..values.len()` of the result: `values[i] >= t` (at most 64 values).
pub(super) fn u8_at_least(values: &[u8], t: u8) -> u64 {
    by_vectors::<16, _>(values, |v| u64::from(sixteen_u8(v, t)), |v| v >= t)
}

/// Bits `0..values.len()` of the result: `values[i] >= t` (at most 64 values).
pub(super) fn u16_at_least(values: &[u16], t: u16) -> u64 {
    by_vectors::<8, _>(values, |v| u64::from(eight_u16(v, t)), |v| v >= t)
}

/// Bits `0..values.len()` of the result: `values[i] >= iso` (at most 64 values; false for NaN).
pub(super) fn f32_at_least(values: &[f32], iso: f32) -> u64 {
    by_vectors::<4, _>(values, |v| u64::from(four_f32(v, iso)), |v| v >= iso)
}

/// The bits of a row: `vector` on each whole vector of `W` values, `inside` on the values left.
#[inline(always)]
fn by_vectors<const W: usize, T: Copy>(
    values: &[T],
    vector: impl Fn(&[T]) -> u64,
    inside: impl Fn(T) -> bool,
) -> u64 {
    let mut bits = 0;
    let mut vectors = values.chunks_exact(W);
    for (k, v) in (&mut vectors).enumerate() {
        bits |= vector(v) << (W * k);
    }
    with_tail(bits, values.len(), vectors.remainder(), inside)
}

/// The bits of a row of `len` values: `bits` of its whole vectors, followed by those of its
/// last values `rest`.
#[inline]
fn with_tail<T: Copy>(bits: u64, len: usize, rest: &[T], inside: impl Fn(T) -> bool) -> u64 {
    if rest.is_empty() {
        // A row of 64 values: no shift by 64.
        return bits;
    }
    bits | tail(rest, inside) << (len - rest.len())
}

/// Bit i: `inside(values[i])`, one value at a time.
#[inline]
fn tail<T: Copy>(values: &[T], inside: impl Fn(T) -> bool) -> u64 {
    let mut bits = 0;
    for (i, &v) in values.iter().enumerate() {
        bits |= u64::from(inside(v)) << i;
    }
    bits
}

#[cfg(target_arch = "x86_64")]
mod lanes {
    use safe_arch::{
        bitxor_m128i, cmp_eq_mask_i8_m128i, cmp_ge_mask_m128, cmp_gt_mask_i16_m128i,
        load_unaligned_m128, load_unaligned_m128i, max_u8_m128i, move_mask_i8_m128i,
        move_mask_m128, pack_i16_to_i8_m128i, set_splat_i16_m128i, set_splat_i8_m128i,
        set_splat_m128,
    };

    /// Bit i: `values[i] >= t`, for sixteen values: `max(v, t) == v`.
    #[inline]
    pub(super) fn sixteen_u8(values: &[u8], t: u8) -> u16 {
        let mut bytes = [0; 16];
        bytes.copy_from_slice(values);
        let v = load_unaligned_m128i(&bytes);
        let ge = cmp_eq_mask_i8_m128i(max_u8_m128i(v, set_splat_i8_m128i(t as i8)), v);
        move_mask_i8_m128i(ge) as u16
    }

    /// Bit i: `values[i] >= t`, for eight values: SSE2 compares u16 lanes as signed only, so
    /// both sides are shifted by 2^15 (a xor of the top bit), and `v >= t` is `!(t > v)`.
    #[inline]
    pub(super) fn eight_u16(values: &[u16], t: u16) -> u8 {
        let mut bytes = [0; 16];
        for (pair, v) in bytes.chunks_exact_mut(2).zip(values) {
            pair.copy_from_slice(&v.to_le_bytes());
        }
        let flip = set_splat_i16_m128i(i16::MIN);
        let v = bitxor_m128i(load_unaligned_m128i(&bytes), flip);
        let t = bitxor_m128i(set_splat_i16_m128i(t as i16), flip);
        let below = cmp_gt_mask_i16_m128i(t, v);
        // One byte per lane (0 or -1), the eight in the low half.
        !(move_mask_i8_m128i(pack_i16_to_i8_m128i(below, below)) as u8)
    }

    /// Bit i: `values[i] >= iso`, for four values (an ordered compare: false for NaN).
    #[inline]
    pub(super) fn four_f32(values: &[f32], iso: f32) -> u8 {
        let four = [values[0], values[1], values[2], values[3]];
        move_mask_m128(cmp_ge_mask_m128(
            load_unaligned_m128(&four),
            set_splat_m128(iso),
        )) as u8
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod lanes {
    #[inline]
    pub(super) fn sixteen_u8(values: &[u8], t: u8) -> u16 {
        super::tail(values, |v| v >= t) as u16
    }

    #[inline]
    pub(super) fn eight_u16(values: &[u16], t: u16) -> u8 {
        super::tail(values, |v| v >= t) as u8
    }

    #[inline]
    pub(super) fn four_f32(values: &[f32], iso: f32) -> u8 {
        super::tail(values, |v| v >= iso) as u8
    }
}

use lanes::{eight_u16, four_f32, sixteen_u8};

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn one_by_one<T: Copy + PartialOrd>(values: &[T], t: T) -> u64 {
        tail(values, |v| v >= t)
    }

    proptest! {
        #[test]
        fn u8_rows_match_one_by_one(values in prop::collection::vec(any::<u8>(), 0..=64), t in any::<u8>()) {
            prop_assert_eq!(u8_at_least(&values, t), one_by_one(&values, t));
        }

        #[test]
        fn u16_rows_match_one_by_one(values in prop::collection::vec(any::<u16>(), 0..=64), t in any::<u16>()) {
            prop_assert_eq!(u16_at_least(&values, t), one_by_one(&values, t));
        }

        #[test]
        fn f32_rows_match_one_by_one(values in prop::collection::vec(-1e3f32..1e3, 0..=64), iso in -1e3f32..1e3) {
            prop_assert_eq!(f32_at_least(&values, iso), one_by_one(&values, iso));
        }
    }

    #[test]
    fn extremes_of_each_type() {
        // Hand-picked: the top bit of u8 and u16 (where a signed compare would go wrong), the
        // ends of the range, and 64 values (every bit of the word).
        let bytes: Vec<u8> = (0..64).map(|i| [0, 127, 128, 255][i % 4]).collect();
        assert_eq!(u8_at_least(&bytes, 128), 0xcccc_cccc_cccc_cccc);
        assert_eq!(u8_at_least(&bytes, 0), u64::MAX);
        assert_eq!(u8_at_least(&bytes, 255), 0x8888_8888_8888_8888);
        let words: Vec<u16> = (0..64).map(|i| [0, 32767, 32768, 65535][i % 4]).collect();
        assert_eq!(u16_at_least(&words, 32768), 0xcccc_cccc_cccc_cccc);
        assert_eq!(u16_at_least(&words, 0), u64::MAX);
        assert_eq!(u16_at_least(&words, 65535), 0x8888_8888_8888_8888);
        let floats = [f32::NAN, 0.5, -0.5, 1.0, f32::INFINITY];
        assert_eq!(f32_at_least(&floats, 0.5), 0b11010);
        assert_eq!(f32_at_least(&floats, f32::NAN), 0);
    }
}
