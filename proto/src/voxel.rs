//! Voxel types and the ICVG value range.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// The scalar type of a voxel. Values are unsigned integers in `[L, H]` (`docs/icvg.md`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VoxelType {
    /// 8 bits per voxel: L 0, H 255, S 127.
    U8,
    /// 16 bits per voxel, little endian: L 0, H 65535, S 32767.
    U16,
}

impl VoxelType {
    /// Bytes one voxel takes in memory, on disk and on the wire (u16 is little endian).
    pub const fn bytes(self) -> usize {
        match self {
            VoxelType::U8 => 1,
            VoxelType::U16 => 2,
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
            _ => None,
        }
    }

    /// L, the lowest value: empty space.
    pub const fn low(self) -> u16 {
        0
    }

    /// H, the highest value: solid.
    pub const fn high(self) -> u16 {
        match self {
            VoxelType::U8 => u8::MAX as u16,
            VoxelType::U16 => u16::MAX,
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
            other => Err(format!("unknown voxel type {other:?} (expected u8 or u16)")),
        }
    }
}

/// Smallest and largest voxel value of a decoded brick.
pub fn min_max(bytes: &[u8], voxel_type: VoxelType) -> (u16, u16) {
    match voxel_type {
        VoxelType::U8 => {
            let (mut lo, mut hi) = (u8::MAX, u8::MIN);
            for &v in bytes {
                lo = lo.min(v);
                hi = hi.max(v);
            }
            (lo as u16, hi as u16)
        }
        VoxelType::U16 => {
            let (mut lo, mut hi) = (u16::MAX, u16::MIN);
            for c in bytes.chunks_exact(2) {
                let v = u16::from_le_bytes([c[0], c[1]]);
                lo = lo.min(v);
                hi = hi.max(v);
            }
            (lo, hi)
        }
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
        for t in [VoxelType::U8, VoxelType::U16] {
            assert_eq!(VoxelType::from_bits(t.bits()), Some(t));
            assert_eq!(t.name().parse::<VoxelType>(), Ok(t));
        }
        assert_eq!(VoxelType::from_bits(32), None);
        assert!("f32".parse::<VoxelType>().is_err());
    }
}
