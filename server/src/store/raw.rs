//! RAW and RAWVOX files: the plain voxel arrays volumes are imported from and exported to.
//!
//! RAW is headerless: voxels x fastest, then y, then z, u16 little endian; its shape comes from
//! the command line. RAWVOX (as 3D-Coat and Voreen read it) adds a 20-byte header of five
//! little-endian i32: the magic 0x52564F58 (bytes `XOVR`), size x, y, z, and bits per voxel.

use super::mapping::Mapping;
use super::vod2::Snapshot;
use super::StoreError;
use crate::geometry::Box3;
use crate::progress::Progress;
use isovox_proto::{BrickKey, VoxelType};
use rayon::prelude::*;
use std::fs::File;
use std::io::Write;
use std::path::Path;

/// RAWVOX magic as a little-endian i32.
pub const RAWVOX_MAGIC: i32 = 0x5256_4F58;
/// Bytes of a RAWVOX header (magic, three sizes, bits per voxel).
pub const RAWVOX_HEADER_LEN: usize = 20;

/// A RAW or RAWVOX file, mapped.
#[derive(Debug)]
pub struct RawInput {
    map: Mapping,
    data_at: usize,
    /// Size in voxels.
    pub dims: [u32; 3],
    /// The voxel type.
    pub voxel_type: VoxelType,
}

impl RawInput {
    /// Opens a RAW file (`dims` and `voxel_type` given) or a RAWVOX file (they come from its
    /// header; if given too, they must agree).
    ///
    /// # Errors
    /// The file cannot be read, a RAW file lacks `dims`, the header is malformed, or the file's
    /// size does not match its shape.
    pub fn open(
        path: &Path,
        rawvox: bool,
        dims: Option<[u32; 3]>,
        voxel_type: Option<VoxelType>,
    ) -> Result<Self, StoreError> {
        let file = File::open(path).map_err(StoreError::io_path("cannot open", path))?;
        let len = file
            .metadata()
            .map_err(StoreError::io_path("cannot stat", path))?
            .len();
        let map = Mapping::new(&file, len).map_err(StoreError::io_path("cannot map", path))?;
        let (dims, voxel_type, data_at) = if rawvox {
            let b = map.bytes();
            if b.len() < RAWVOX_HEADER_LEN {
                return Err(StoreError::BadInput(format!(
                    "{}: shorter than a RAWVOX header (20 bytes)",
                    path.display()
                )));
            }
            let field =
                |i: usize| i32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]]);
            if field(0) != RAWVOX_MAGIC {
                return Err(StoreError::BadInput(format!(
                    "{}: not a RAWVOX file (bad magic)",
                    path.display()
                )));
            }
            let mut header_dims = [0u32; 3];
            for (axis, d) in header_dims.iter_mut().enumerate() {
                *d = u32::try_from(field(1 + axis)).map_err(|_| {
                    StoreError::BadInput(format!(
                        "{}: negative size {} in the RAWVOX header",
                        path.display(),
                        field(1 + axis)
                    ))
                })?;
            }
            let bits = field(4);
            let header_type = VoxelType::from_bits(bits as u32)
                .filter(|_| bits > 0)
                .ok_or_else(|| {
                    StoreError::BadInput(format!(
                        "{}: {bits} bits per voxel (Isovox reads 8 and 16)",
                        path.display()
                    ))
                })?;
            if dims.is_some_and(|d| d != header_dims)
                || voxel_type.is_some_and(|t| t != header_type)
            {
                return Err(StoreError::BadInput(format!(
                    "{}: --dims/--type disagree with the RAWVOX header ({header_dims:?}, {header_type})",
                    path.display()
                )));
            }
            (header_dims, header_type, RAWVOX_HEADER_LEN)
        } else {
            let dims =
                dims.ok_or_else(|| StoreError::BadInput("a RAW file needs --dims X,Y,Z".into()))?;
            (dims, voxel_type.unwrap_or(VoxelType::U8), 0)
        };
        let expected = dims
            .iter()
            .try_fold(voxel_type.bytes() as u64, |acc, &d| {
                acc.checked_mul(d as u64)
            })
            .ok_or_else(|| {
                StoreError::BadInput(format!(
                    "{}: dimensions {dims:?} are too large",
                    path.display()
                ))
            })?;
        if len - data_at as u64 != expected {
            return Err(StoreError::BadInput(format!(
                "{}: {} voxel bytes, but {}x{}x{} {voxel_type} voxels need {expected}",
                path.display(),
                len - data_at as u64,
                dims[0],
                dims[1],
                dims[2]
            )));
        }
        Ok(RawInput {
            map,
            data_at,
            dims,
            voxel_type,
        })
    }

    /// The voxel bytes.
    pub fn voxels(&self) -> &[u8] {
        &self.map.bytes()[self.data_at..]
    }
}

/// The RAWVOX header for a volume.
pub fn rawvox_header(dims: [u32; 3], voxel_type: VoxelType) -> [u8; RAWVOX_HEADER_LEN] {
    let mut h = [0u8; RAWVOX_HEADER_LEN];
    let fields = [
        RAWVOX_MAGIC,
        dims[0] as i32,
        dims[1] as i32,
        dims[2] as i32,
        voxel_type.bits() as i32,
    ];
    for (i, f) in fields.iter().enumerate() {
        h[4 * i..4 * i + 4].copy_from_slice(&f.to_le_bytes());
    }
    h
}

/// Writes the voxels of `region` of `level` as RAW (x fastest), streaming one row of bricks at a
/// time: memory holds one z-slab of decoded bricks, whatever the volume's size.
///
/// # Errors
/// The region is empty or outside the level, a brick is corrupt, or writing fails.
pub fn export_raw(
    snap: &Snapshot,
    level: u8,
    region: Box3,
    out: &mut dyn Write,
    progress: &dyn Progress,
) -> Result<(), StoreError> {
    let layout = snap.layout();
    if level >= layout.levels() {
        return Err(StoreError::OutOfRange(format!(
            "level {level} out of range (volume has {} levels)",
            layout.levels()
        )));
    }
    let extent = layout.level_dims(level);
    for axis in 0..3 {
        if region.min[axis] < 0
            || region.min[axis] >= region.max[axis]
            || region.max[axis] > i64::from(extent[axis])
        {
            return Err(StoreError::BadInput(format!(
                "region {:?}..{:?} is empty or outside level {level} ({}x{}x{} voxels)",
                region.min, region.max, extent[0], extent[1], extent[2]
            )));
        }
    }
    // Within the level's extent: voxel positions of the level, as its bricks count them.
    let (min, max) = (region.min.map(|c| c as u32), region.max.map(|c| c as u32));
    let b = layout.brick();
    let vb = layout.voxel_type().bytes();
    let brick_bytes = layout.brick_bytes();
    let (bx0, bx1) = (min[0] / b, (max[0] - 1) / b);
    let (by0, by1) = (min[1] / b, (max[1] - 1) / b);
    let (bz0, bz1) = (min[2] / b, (max[2] - 1) / b);
    let (nbx, nby) = ((bx1 - bx0 + 1) as usize, (by1 - by0 + 1) as usize);
    progress.start((max[2] - min[2]) as u64);
    let row_voxels = (max[0] - min[0]) as usize;
    let mut plane = vec![0u8; row_voxels * (max[1] - min[1]) as usize * vb];
    for bz in bz0..=bz1 {
        let slab: Vec<Vec<u8>> = (0..nbx * nby)
            .into_par_iter()
            .map(|i| {
                let key = BrickKey {
                    level,
                    x: bx0 + (i % nbx) as u32,
                    y: by0 + (i / nbx) as u32,
                    z: bz,
                };
                let mut buf = vec![0u8; brick_bytes];
                snap.read_into(key, &mut buf).map(|_| buf)
            })
            .collect::<Result<_, _>>()?;
        let z_lo = min[2].max(bz * b);
        let z_hi = max[2].min((bz + 1) * b);
        for z in z_lo..z_hi {
            let lz = (z - bz * b) as usize;
            for (row, y) in (min[1]..max[1]).enumerate() {
                let (jy, ly) = (((y / b) - by0) as usize, (y % b) as usize);
                let mut x = min[0];
                while x < max[0] {
                    let (ix, lx) = (((x / b) - bx0) as usize, (x % b) as usize);
                    let n = ((b as usize - lx) as u32).min(max[0] - x) as usize;
                    let src = &slab[jy * nbx + ix]
                        [((lz * b as usize + ly) * b as usize + lx) * vb..][..n * vb];
                    let dst = (row * row_voxels + (x - min[0]) as usize) * vb;
                    plane[dst..dst + n * vb].copy_from_slice(src);
                    x += n as u32;
                }
            }
            out.write_all(&plane)
                .map_err(StoreError::io("cannot write the export"))?;
            progress.advance(1);
        }
    }
    out.flush()
        .map_err(StoreError::io("cannot write the export"))?;
    progress.finish();
    Ok(())
}
