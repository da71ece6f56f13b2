//! Voxel types and the ICVG value range.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// The scalar type of a voxel. Values are unsigned integers in `[L, H]` (`docs/icvg.md`).
///
/// Density is u8 or u16 ([`VoxelType::is_density`]); the wide types u32 and u64 hold the ids of
/// a label channel (`docs/channels.md`), which the algebra never computes with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VoxelType {
    /// 8 bits per voxel: L 0, H 255, S 127.
    U8,
    /// 16 bits per voxel, little endian: L 0, H 65535, S 32767.
    U16,
    /// 32 bits per voxel, little endian: label ids (channels only).
    U32,
    /// 64 bits per voxel, little endian: label ids (channels only).
    U64,
}

impl VoxelType {
    /// Bytes one voxel takes in memory, on disk and on the wire (u16 is little endian).
    pub const fn bytes(self) -> usize {
        match self {
            VoxelType::U8 => 1,
            VoxelType::U16 => 2,
            VoxelType::U32 => 4,
            VoxelType::U64 => 8,
        }
    }

    /// Whether density may have this type (u8, u16): the algebra's L, H and S are defined for
    /// these only.
    pub const fn is_density(self) -> bool {
        matches!(self, VoxelType::U8 | VoxelType::U16)
    }

    /// Whether values of this type need more than 16 bits (u32, u64): their streams' brick
    /// records and summaries carry 64-bit ranges (`docs/vod2.md`, revision 6).
    pub const fn is_wide(self) -> bool {
        !self.is_density()
    }

    /// The largest value of the type.
    pub const fn max_value(self) -> u64 {
        match self {
            VoxelType::U8 => u8::MAX as u64,
            VoxelType::U16 => u16::MAX as u64,
            VoxelType::U32 => u32::MAX as u64,
            VoxelType::U64 => u64::MAX,
        }
    }

    /// Bits per voxel, as VOD 1's `voxelSize` and VOD 2's header store it.
    pub const fn bits(self) -> u32 {
        self.bytes() as u32 * 8
    }

    /// The type with `bits` bits per voxel, if there is one.
    pub const fn from_bits(bits: u32) -> Option<VoxelType> {
        match bits {
            8 => Some(VoxelType::U8),
            16 => Some(VoxelType::U16),
            32 => Some(VoxelType::U32),
            64 => Some(VoxelType::U64),
            _ => None,
        }
    }

    /// L, the lowest value: empty space.
    pub const fn low(self) -> u16 {
        0
    }

    /// H, the highest density: solid. The algebra's constant, defined for the density types;
    /// a wide type (never density) answers u16's, and what needs a type's true largest value
    /// asks [`VoxelType::max_value`].
    pub const fn high(self) -> u16 {
        match self {
            VoxelType::U8 => u8::MAX as u16,
            VoxelType::U16 | VoxelType::U32 | VoxelType::U64 => u16::MAX,
        }
    }

    /// S = floor((H - L) / 2), the surface threshold: a voxel is inside when its value >= S.
    pub const fn surface(self) -> u16 {
        (self.high() - self.low()) / 2
    }

    /// The name used on the command line and in JSON.
    pub const fn name(self) -> &'static str {
        match self {
            VoxelType::U8 => "u8",
            VoxelType::U16 => "u16",
            VoxelType::U32 => "u32",
            VoxelType::U64 => "u64",
        }
    }
}

impl fmt::Display for VoxelType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for VoxelType {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "u8" => Ok(VoxelType::U8),
            "u16" => Ok(VoxelType::U16),
            "u32" => Ok(VoxelType::U32),
            "u64" => Ok(VoxelType::U64),
            other => Err(format!(
                "unknown voxel type {other:?} (expected u8 or u16; u32 and u64 for channels)"
            )),
        }
    }
}

/// Smallest and largest voxel value of a decoded brick.
pub fn min_max(bytes: &[u8], voxel_type: VoxelType) -> (u64, u64) {
    fn range<const N: usize>(bytes: &[u8], value: fn([u8; N]) -> u64) -> (u64, u64) {
        let (mut lo, mut hi) = (u64::MAX, u64::MIN);
        for c in bytes.chunks_exact(N) {
            let v = value(c.try_into().expect("chunks of N"));
            lo = lo.min(v);
            hi = hi.max(v);
        }
        (lo, hi)
    }
    match voxel_type {
        VoxelType::U8 => {
            let (mut lo, mut hi) = (u8::MAX, u8::MIN);
            for &v in bytes {
                lo = lo.min(v);
                hi = hi.max(v);
            }
            (lo as u64, hi as u64)
        }
        VoxelType::U16 => {
            let (mut lo, mut hi) = (u16::MAX, u16::MIN);
            for c in bytes.chunks_exact(2) {
                let v = u16::from_le_bytes([c[0], c[1]]);
                lo = lo.min(v);
                hi = hi.max(v);
            }
            (lo as u64, hi as u64)
        }
        VoxelType::U32 => range::<4>(bytes, |b| u32::from_le_bytes(b) as u64),
        VoxelType::U64 => range::<8>(bytes, u64::from_le_bytes),
    }
}

/// Value `i` of little-endian voxels of `voxel_type`. One fixed-size read per type: it is
/// called per voxel (segment summaries, label chunks, palettes).
#[inline]
pub fn value_at(bytes: &[u8], voxel_type: VoxelType, i: usize) -> u64 {
    fn read<const N: usize>(bytes: &[u8], i: usize) -> u64 {
        let mut b = [0u8; 8];
        b[..N].copy_from_slice(&bytes[i * N..(i + 1) * N]);
        u64::from_le_bytes(b)
    }
    match voxel_type {
        VoxelType::U8 => u64::from(bytes[i]),
        VoxelType::U16 => read::<2>(bytes, i),
        VoxelType::U32 => read::<4>(bytes, i),
        VoxelType::U64 => read::<8>(bytes, i),
    }
}

/// Writes `value` (at most the type's largest) as voxel `i` of little-endian voxels.
#[inline]
pub fn set_value_at(bytes: &mut [u8], voxel_type: VoxelType, i: usize, value: u64) {
    fn write<const N: usize>(bytes: &mut [u8], i: usize, value: u64) {
        bytes[i * N..(i + 1) * N].copy_from_slice(&value.to_le_bytes()[..N]);
    }
    match voxel_type {
        VoxelType::U8 => bytes[i] = value as u8,
        VoxelType::U16 => write::<2>(bytes, i, value),
        VoxelType::U32 => write::<4>(bytes, i, value),
        VoxelType::U64 => write::<8>(bytes, i, value),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn min_max_of_both_types() {
        assert_eq!(min_max(&[5, 3, 9, 7], VoxelType::U8), (3, 9));
        // u16 little endian: 0x0102 = 258, 0x0001 = 256, 0x00ff = 255.
        assert_eq!(min_max(&[2, 1, 0, 1, 0xff, 0], VoxelType::U16), (255, 258));
        // u32: 0x01000000 = 16777216, 7; u64: 2^63 + 1 and 5.
        assert_eq!(
            min_max(&[0, 0, 0, 1, 7, 0, 0, 0], VoxelType::U32),
            (7, 16_777_216)
        );
        let mut b = vec![1, 0, 0, 0, 0, 0, 0, 0x80];
        b.extend([5, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(min_max(&b, VoxelType::U64), (5, (1 << 63) + 1));
    }

    #[test]
    fn values_read_and_written_little_endian() {
        let mut b = vec![0u8; 16];
        set_value_at(&mut b, VoxelType::U64, 1, u64::MAX - 1);
        assert_eq!(b[8..], [0xfe, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff]);
        assert_eq!(value_at(&b, VoxelType::U64, 1), u64::MAX - 1);
        set_value_at(&mut b, VoxelType::U32, 1, 0x0102_0304);
        assert_eq!(b[4..8], [4, 3, 2, 1]);
        assert_eq!(value_at(&b, VoxelType::U16, 2), 0x0304);
    }

    #[test]
    fn range_table_matches_the_spec() {
        // docs/icvg.md: u8 0/255/127, u16 0/65535/32767.
        assert_eq!(
            (
                VoxelType::U8.low(),
                VoxelType::U8.high(),
                VoxelType::U8.surface()
            ),
            (0, 255, 127)
        );
        assert_eq!(
            (
                VoxelType::U16.low(),
                VoxelType::U16.high(),
                VoxelType::U16.surface()
            ),
            (0, 65535, 32767)
        );
    }

    #[test]
    fn bits_round_trip() {
        for t in [
            VoxelType::U8,
            VoxelType::U16,
            VoxelType::U32,
            VoxelType::U64,
        ] {
            assert_eq!(VoxelType::from_bits(t.bits()), Some(t));
            assert_eq!(t.name().parse::<VoxelType>(), Ok(t));
        }
        assert_eq!(VoxelType::from_bits(24), None);
        assert!("f32".parse::<VoxelType>().is_err());
    }
}
