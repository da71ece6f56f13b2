//! Reading Neuroglancer precomputed volumes (the finest scale), local or over http.
//!
//! Unsharded chunks with `raw` encoding, or `compressed_segmentation` for segmentations (uint32
//! or uint64: Neuroglancer's label encoding), stored plain or gzip-compressed (a `.gz` file on
//! disk, `Content-Encoding: gzip` over http). One channel. A chunk row (all chunks of one z range) is
//! fetched in parallel; every chunk must have exactly the bytes its cropped extent needs.

use super::convert::DType;
use super::location::Location;
use super::planes::{plane_bytes, PlaneSource};
use crate::formats::{compressed_segmentation, FormatsError};
use rayon::prelude::*;
use serde::Deserialize;

#[derive(Debug, Deserialize)]
struct Info {
    #[serde(rename = "type")]
    kind: Option<String>,
    data_type: String,
    num_channels: u32,
    scales: Vec<Scale>,
}

#[derive(Debug, Deserialize)]
struct Scale {
    key: String,
    size: [u64; 3],
    resolution: [f64; 3],
    #[serde(default)]
    voxel_offset: [i64; 3],
    chunk_sizes: Vec<[u64; 3]>,
    encoding: String,
    compressed_segmentation_block_size: Option<[u32; 3]>,
    sharding: Option<serde_json::Value>,
}

/// How the chunks of the scale read are encoded.
#[derive(Debug, Clone, Copy)]
enum Encoding {
    /// The voxels as they are.
    Raw,
    /// Neuroglancer's `compressed_segmentation`, in blocks of this size.
    CompressedSegmentation([u32; 3]),
}

/// The finest scale of a precomputed volume.
#[derive(Debug)]
pub struct PrecomputedInput {
    location: Location,
    key: String,
    dims: [u32; 3],
    offset: [i64; 3],
    chunk: [u32; 3],
    dtype: DType,
    encoding: Encoding,
    scale: [f32; 3],
}

/// Most bytes of an `info` file.
const MAX_INFO_BYTES: u64 = 16 << 20;

fn dtype_of(name: &str) -> Option<DType> {
    Some(match name {
        "uint8" => DType::U8,
        "int8" => DType::I8,
        "uint16" => DType::U16,
        "int16" => DType::I16,
        "uint32" => DType::U32,
        "int32" => DType::I32,
        "uint64" => DType::U64,
        "float32" => DType::F32,
        "float64" => DType::F64,
        _ => return None,
    })
}

impl PrecomputedInput {
    /// Reads `info` at `location` and checks the finest scale is one this reader handles.
    ///
    /// # Errors
    /// No `info`, malformed JSON, or an unsupported volume (sharded, another encoding, several
    /// channels, an unknown data type, dimensions beyond u32).
    pub fn open(location: Location) -> Result<Self, FormatsError> {
        let bytes = location.get("info", MAX_INFO_BYTES)?.ok_or_else(|| {
            FormatsError::input(format!(
                "{}: no such file; a precomputed volume has one at its root",
                location.describe("info")
            ))
        })?;
        let where_ = location.describe("info");
        let info: Info = serde_json::from_slice(&bytes).map_err(|e| {
            FormatsError::input(format!("{where_} is not a precomputed info file: {e}"))
        })?;
        if info
            .kind
            .as_deref()
            .is_some_and(|k| k != "image" && k != "segmentation")
        {
            return Err(FormatsError::input(format!(
                "{where_}: type {:?} is not a volume (image or segmentation)",
                info.kind
            )));
        }
        if info.num_channels != 1 {
            return Err(FormatsError::input(format!(
                "{where_}: {} channels; Isovox imports one",
                info.num_channels
            )));
        }
        let dtype = dtype_of(&info.data_type).ok_or_else(|| {
            FormatsError::input(format!(
                "{where_}: data type {:?} is not supported",
                info.data_type
            ))
        })?;
        let scale = info
            .scales
            .into_iter()
            .next()
            .ok_or_else(|| FormatsError::input(format!("{where_}: no scales")))?;
        if scale.sharding.is_some() {
            return Err(FormatsError::input(format!(
                "{where_}: scale {:?} is sharded; Isovox imports unsharded chunks",
                scale.key
            )));
        }
        let encoding = match scale.encoding.as_str() {
            "raw" => Encoding::Raw,
            "compressed_segmentation" if matches!(dtype, DType::U32 | DType::U64) => {
                let block = scale.compressed_segmentation_block_size.ok_or_else(|| {
                    FormatsError::input(format!(
                        "{where_}: scale {:?} is compressed_segmentation without compressed_segmentation_block_size",
                        scale.key
                    ))
                })?;
                // Neuroglancer's blocks are a few voxels a side (8 by default): a block of
                // more than 2^24 voxels cannot be indexed by the format's 24-bit offsets.
                if block.contains(&0) || block.iter().map(|&b| u64::from(b)).product::<u64>() > 1 << 24 {
                    return Err(FormatsError::input(format!(
                        "{where_}: compressed_segmentation_block_size {block:?} is empty or too large"
                    )));
                }
                Encoding::CompressedSegmentation(block)
            }
            "compressed_segmentation" => {
                return Err(FormatsError::input(format!(
                    "{where_}: compressed_segmentation of {} values; the encoding holds uint32 or uint64",
                    info.data_type
                )))
            }
            other => {
                return Err(FormatsError::input(format!(
                    "{where_}: encoding {other:?}; Isovox imports raw chunks, and compressed_segmentation for segmentations (plain or gzip)"
                )))
            }
        };
        let chunk = scale.chunk_sizes.first().copied().ok_or_else(|| {
            FormatsError::input(format!("{where_}: scale {:?} has no chunk size", scale.key))
        })?;
        let fits = |v: u64| u32::try_from(v).ok().filter(|v| *v > 0);
        let dims = [0, 1, 2].map(|a| fits(scale.size[a]));
        let chunk = [0, 1, 2].map(|a| fits(chunk[a]));
        let (Some(dx), Some(dy), Some(dz), Some(cx), Some(cy), Some(cz)) =
            (dims[0], dims[1], dims[2], chunk[0], chunk[1], chunk[2])
        else {
            return Err(FormatsError::input(format!(
                "{where_}: size {:?} or chunk size {:?} is empty or beyond 2^32",
                scale.size, chunk
            )));
        };
        let key = super::location::contained(&scale.key).map_err(|why| {
            FormatsError::input(format!(
                "{where_}: scales[0].key {:?} leads outside the volume ({why}); Isovox reads only under the location it is given",
                scale.key
            ))
        })?;
        let key = key.to_string();
        let voxel = scale.resolution.map(|r| r as f32);
        Ok(PrecomputedInput {
            location,
            key,
            dims: [dx, dy, dz],
            offset: scale.voxel_offset,
            chunk: [cx, cy, cz],
            dtype,
            encoding,
            scale: if voxel.iter().all(|s| s.is_finite() && *s > 0.0) {
                voxel
            } else {
                [1.0; 3]
            },
        })
    }

    /// The name of the chunk at grid position `(i, j, k)`, and its extent.
    fn chunk_at(&self, i: [u32; 3]) -> (String, [u32; 3]) {
        let mut parts = Vec::with_capacity(3);
        let mut extent = [0u32; 3];
        for a in 0..3 {
            // In u64/i64: a hostile info's chunk and size near 2^32 must not overflow.
            let lo = u64::from(i[a]) * u64::from(self.chunk[a]);
            let hi = (lo + u64::from(self.chunk[a])).min(u64::from(self.dims[a]));
            extent[a] = (hi - lo) as u32;
            let o = self.offset[a];
            parts.push(format!(
                "{}-{}",
                o.saturating_add(lo as i64),
                o.saturating_add(hi as i64)
            ));
        }
        (format!("{}/{}", self.key, parts.join("_")), extent)
    }

    /// The voxels of chunk `name` of `extent` (x fastest, little endian), decoded when the scale
    /// is compressed_segmentation; read with at most the bytes its encoding can take.
    ///
    /// # Errors
    /// The chunk is missing, cannot be read, does not decode, or holds the wrong number of
    /// bytes.
    fn chunk_voxels(&self, name: &str, extent: [u32; 3]) -> Result<Vec<u8>, FormatsError> {
        let expected =
            extent.iter().map(|&e| u64::from(e)).product::<u64>() * self.dtype.bytes() as u64;
        let wide = self.dtype == DType::U64;
        let most = match self.encoding {
            Encoding::Raw => expected,
            Encoding::CompressedSegmentation(block) => {
                compressed_segmentation::max_chunk_bytes(extent, block, wide)
            }
        };
        let [ex, ey, ez] = extent;
        let bytes = self.location.get(name, most)?.ok_or_else(|| {
            FormatsError::input(format!("{}: chunk missing", self.location.describe(name)))
        })?;
        let bytes = match self.encoding {
            Encoding::Raw => bytes,
            Encoding::CompressedSegmentation(block) => {
                let values = compressed_segmentation::decode_chunk(&bytes, extent, block, wide)
                    .map_err(|why| {
                        FormatsError::input(format!(
                            "{}: not a compressed_segmentation chunk of {ex}x{ey}x{ez} {} voxels: {why}",
                            self.location.describe(name),
                            self.dtype
                        ))
                    })?;
                if wide {
                    values.iter().flat_map(|v| v.to_le_bytes()).collect()
                } else {
                    // Each value came from one 32-bit table word.
                    values
                        .iter()
                        .flat_map(|&v| (v as u32).to_le_bytes())
                        .collect()
                }
            }
        };
        if bytes.len() as u64 != expected {
            return Err(FormatsError::input(format!(
                "{}: {} bytes, but a raw chunk of {ex}x{ey}x{ez} {} voxels has {expected} (truncated?)",
                self.location.describe(name),
                bytes.len(),
                self.dtype
            )));
        }
        Ok(bytes)
    }
}

impl PlaneSource for PrecomputedInput {
    fn dims(&self) -> [u32; 3] {
        self.dims
    }

    fn dtype(&self) -> DType {
        self.dtype
    }

    fn voxel_scale(&self) -> Option<[f32; 3]> {
        Some(self.scale)
    }

    fn depth(&self) -> u32 {
        self.chunk[2]
    }

    fn read(&mut self, z0: u32, z1: u32, out: &mut Vec<u8>) -> Result<(), FormatsError> {
        let [dx, dy, _] = self.dims;
        let vb = self.dtype.bytes();
        out.clear();
        out.resize(
            (plane_bytes(dx, dy, self.dtype) * u64::from(z1 - z0)) as usize,
            0,
        );
        let grid = [dx.div_ceil(self.chunk[0]), dy.div_ceil(self.chunk[1])];
        for k in z0 / self.chunk[2]..z1.div_ceil(self.chunk[2]) {
            let this = &*self;
            let chunks: Vec<(u32, u32, Vec<u8>, [u32; 3])> = (0..grid[0] * grid[1])
                .into_par_iter()
                .map(|n| {
                    let (i, j) = (n % grid[0], n / grid[0]);
                    let (name, extent) = this.chunk_at([i, j, k]);
                    let bytes = this.chunk_voxels(&name, extent)?;
                    Ok((i, j, bytes, extent))
                })
                .collect::<Result<_, FormatsError>>()?;
            for (i, j, bytes, [ex, ey, ez]) in chunks {
                let (x0, y0, cz0) = (
                    i * self.chunk[0],
                    j * self.chunk[1],
                    u64::from(k) * u64::from(self.chunk[2]),
                );
                for lz in 0..ez {
                    let z = cz0 + u64::from(lz);
                    if z < u64::from(z0) || z >= u64::from(z1) {
                        continue;
                    }
                    for ly in 0..ey {
                        let src = ((lz * ey + ly) * ex) as usize * vb;
                        let dst = (((z - u64::from(z0)) as usize * dy as usize
                            + (y0 + ly) as usize)
                            * dx as usize
                            + x0 as usize)
                            * vb;
                        out[dst..dst + ex as usize * vb]
                            .copy_from_slice(&bytes[src..src + ex as usize * vb]);
                    }
                }
            }
        }
        Ok(())
    }
}
