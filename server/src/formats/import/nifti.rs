//! Reading NIfTI-1 single-file volumes (`.nii`, `.nii.gz`), streaming.
//!
//! The 348-byte header gives the shape (`dim`), the type (`datatype`), the voxel size
//! (`pixdim[1..=3]`, the voxel scale) and where the voxels start (`vox_offset`); either byte
//! order is read (told by `sizeof_hdr`). The voxels are then read plane by plane from the file
//! or through a gzip decoder, never whole. Index order is kept: i is x, j is y, k is z (the
//! orientation matrices are not applied). A scaling (`scl_slope`, `scl_inter`) other than the
//! identity makes the values float32, as NIfTI readers present them.

use super::convert::DType;
use super::planes::{plane_bytes, PlaneSource};
use crate::formats::FormatsError;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

const HEADER_LEN: usize = 348;

/// A NIfTI-1 file open for streaming.
pub struct NiftiInput {
    path: PathBuf,
    reader: Box<dyn Read + Send>,
    dims: [u32; 3],
    stored: DType,
    big_endian: bool,
    /// `(slope, inter)` when the values are scaled.
    scaling: Option<(f32, f32)>,
    scale: [f32; 3],
    /// The next plane the stream is at.
    next_z: u32,
}

impl std::fmt::Debug for NiftiInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NiftiInput")
            .field("path", &self.path)
            .field("dims", &self.dims)
            .field("stored", &self.stored)
            .finish_non_exhaustive()
    }
}

/// Whether `path` starts like a NIfTI-1 file (plain or gzip-compressed): `sizeof_hdr` 348 in
/// either byte order and a NIfTI-1 magic. The rest of the header is checked on opening, so an
/// unsupported one gets its own message.
pub fn sniff(path: &Path) -> bool {
    let Ok(file) = File::open(path) else {
        return false;
    };
    let (mut reader, _) = open_stream(file);
    let mut head = [0u8; HEADER_LEN];
    reader.read_exact(&mut head).is_ok()
        && (head[..4] == 348i32.to_le_bytes() || head[..4] == 348i32.to_be_bytes())
        && matches!(&head[344..348], b"n+1\0" | b"ni1\0")
}

/// Whether `path` is named as a NIfTI file (`.nii`, `.nii.gz`), whatever it holds: such a file
/// is read as NIfTI, so that one that is not gets told why rather than taken for RAW.
pub fn named(path: &Path) -> bool {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    name.ends_with(".nii") || name.ends_with(".nii.gz")
}

/// The file's bytes, through a gzip decoder when it starts with gzip's magic (whatever its
/// name says), and whether it did.
fn open_stream(file: File) -> (Box<dyn Read + Send>, bool) {
    let mut buffered = BufReader::new(file);
    let gz = {
        use std::io::BufRead;
        buffered
            .fill_buf()
            .is_ok_and(|b| b.starts_with(&[0x1f, 0x8b]))
    };
    if gz {
        (Box::new(flate2::read::MultiGzDecoder::new(buffered)), true)
    } else {
        (Box::new(buffered), false)
    }
}

/// How many times its size deflate can expand data at most: a gzip file smaller than this
/// fraction of what its header promises cannot hold it, and is refused before it is read.
const DEFLATE_MAX_RATIO: u64 = 1032;

struct Header {
    dims: [u32; 3],
    stored: DType,
    big_endian: bool,
    scaling: Option<(f32, f32)>,
    scale: [f32; 3],
    vox_offset: u64,
}

fn parse_header(h: &[u8; HEADER_LEN], path: &Path) -> Result<Header, FormatsError> {
    let bad = |what: String| FormatsError::input(format!("{}: {what}", path.display()));
    let (le, be) = (
        i32::from_le_bytes([h[0], h[1], h[2], h[3]]),
        i32::from_be_bytes([h[0], h[1], h[2], h[3]]),
    );
    // NIfTI-2's magic sits at byte 4 of its 540-byte header.
    if le == 540 || be == 540 || matches!(&h[4..8], b"n+2\0" | b"ni2\0") {
        return Err(bad(
            "a NIfTI-2 header (sizeof_hdr 540); Isovox imports NIfTI-1 (.nii, .nii.gz)".into(),
        ));
    }
    let big_endian = match (le, be) {
        (348, _) => false,
        (_, 348) => true,
        _ => {
            return Err(bad(format!(
                "not a NIfTI-1 header: sizeof_hdr is {le} (348 expected) and the magic at byte 344 is \"{}\" (\"n+1\\0\" expected)",
                h[344..348].escape_ascii()
            )))
        }
    };
    match &h[344..348] {
        b"n+1\0" => {}
        b"ni1\0" => {
            return Err(bad(
                "a NIfTI-1 header/image pair (.hdr/.img); Isovox imports single .nii files".into(),
            ))
        }
        other => {
            return Err(bad(format!(
                "not a NIfTI-1 file: the magic at byte 344 is \"{}\" (\"n+1\\0\" expected)",
                other.escape_ascii()
            )))
        }
    }
    let i16_at = |o: usize| {
        let b = [h[o], h[o + 1]];
        if big_endian {
            i16::from_be_bytes(b)
        } else {
            i16::from_le_bytes(b)
        }
    };
    let f32_at = |o: usize| {
        let b = [h[o], h[o + 1], h[o + 2], h[o + 3]];
        if big_endian {
            f32::from_be_bytes(b)
        } else {
            f32::from_le_bytes(b)
        }
    };
    let ndim = i16_at(40);
    if !(1..=7).contains(&ndim) {
        return Err(bad(format!("dim[0] = {ndim}, not 1..7")));
    }
    let dim = |i: usize| {
        if i as i16 <= ndim {
            i16_at(40 + 2 * i)
        } else {
            1
        }
    };
    let mut dims = [0u32; 3];
    for (a, d) in dims.iter_mut().enumerate() {
        let v = dim(a + 1);
        *d = u32::try_from(v)
            .ok()
            .filter(|v| *v > 0)
            .ok_or_else(|| bad(format!("dim[{}] = {v}, not a positive size", a + 1)))?;
    }
    if let Some(i) = (4..=7).find(|&i| dim(i) > 1) {
        return Err(bad(format!(
            "dim[{i}] = {}: a 4D or larger image; Isovox imports one 3D volume",
            dim(i)
        )));
    }
    let datatype = i16_at(70);
    let stored = match datatype {
        2 => DType::U8,
        4 => DType::I16,
        8 => DType::I32,
        16 => DType::F32,
        64 => DType::F64,
        256 => DType::I8,
        512 => DType::U16,
        768 => DType::U32,
        1280 => DType::U64,
        other => {
            return Err(bad(format!(
                "datatype {other} is not supported (uint8, int8, uint16, int16, uint32, int32, uint64, float32, float64 are)"
            )))
        }
    };
    let vox_offset = f32_at(108);
    if !(vox_offset.is_finite() && vox_offset >= HEADER_LEN as f32 && vox_offset < 1e9) {
        return Err(bad(format!(
            "vox_offset {} is not a valid offset (348 up to 1e9)",
            super::convert::number(f64::from(vox_offset))
        )));
    }
    let (slope, inter) = (f32_at(112), f32_at(116));
    let scaling = (slope.is_finite()
        && slope != 0.0
        && (slope != 1.0 || (inter.is_finite() && inter != 0.0)))
        .then_some((slope, if inter.is_finite() { inter } else { 0.0 }));
    let scale = [f32_at(80), f32_at(84), f32_at(88)];
    Ok(Header {
        dims,
        stored,
        big_endian,
        scaling,
        scale: if scale.iter().all(|s| s.is_finite() && *s > 0.0) {
            scale
        } else {
            [1.0; 3]
        },
        vox_offset: vox_offset as u64,
    })
}

impl NiftiInput {
    /// Opens `path` and reads up to the first voxel.
    ///
    /// # Errors
    /// Not a NIfTI-1 single file, an unsupported type or shape, or a read failure.
    pub fn open(path: &Path) -> Result<Self, FormatsError> {
        let file = File::open(path).map_err(FormatsError::io_path("cannot open", path))?;
        let len = file
            .metadata()
            .map_err(FormatsError::io_path("cannot stat", path))?
            .len();
        let (mut reader, gzip) = open_stream(file);
        let mut head = [0u8; HEADER_LEN];
        if let Err(e) = reader.read_exact(&mut head) {
            return Err(FormatsError::input(
                if e.kind() == std::io::ErrorKind::UnexpectedEof {
                    format!(
                        "{}: shorter than a NIfTI-1 header (348 bytes{})",
                        path.display(),
                        if gzip { " once decompressed" } else { "" }
                    )
                } else {
                    format!("{}: cannot decompress: {e}", path.display())
                },
            ));
        }
        let h = parse_header(&head, path)?;
        // The file's size is known before a voxel is read: one too small for what the header
        // promises is refused at once, not after reading (and building from) all it has.
        let [x, y, z] = h.dims;
        let needed = h.vox_offset + plane_bytes(x, y, h.stored) * u64::from(z);
        if !gzip && len < needed {
            return Err(FormatsError::input(format!(
                "{}: truncated: the header promises {x} x {y} x {z} {} voxels from byte {} \
                 ({needed} bytes), but the file has {len} bytes",
                path.display(),
                h.stored,
                h.vox_offset
            )));
        }
        if gzip && len.saturating_mul(DEFLATE_MAX_RATIO) < needed {
            return Err(FormatsError::input(format!(
                "{}: the header promises {x} x {y} x {z} {} voxels ({needed} bytes), more than {len} bytes of gzip can hold (deflate expands at most {DEFLATE_MAX_RATIO}-fold)",
                path.display(),
                h.stored
            )));
        }
        // Skip the extensions up to the voxels.
        let skip = h.vox_offset - HEADER_LEN as u64;
        let skipped = std::io::copy(&mut (&mut reader).take(skip), &mut std::io::sink())
            .map_err(FormatsError::io_path("cannot read", path))?;
        if skipped != skip {
            return Err(FormatsError::input(format!(
                "{}: ends before its voxels start (vox_offset {})",
                path.display(),
                h.vox_offset
            )));
        }
        Ok(NiftiInput {
            path: path.to_path_buf(),
            reader,
            dims: h.dims,
            stored: h.stored,
            big_endian: h.big_endian,
            scaling: h.scaling,
            scale: h.scale,
            next_z: 0,
        })
    }
}

impl PlaneSource for NiftiInput {
    fn dims(&self) -> [u32; 3] {
        self.dims
    }

    fn dtype(&self) -> DType {
        if self.scaling.is_some() {
            DType::F32
        } else {
            self.stored
        }
    }

    fn voxel_scale(&self) -> Option<[f32; 3]> {
        Some(self.scale)
    }

    fn read(&mut self, z0: u32, z1: u32, out: &mut Vec<u8>) -> Result<(), FormatsError> {
        if z0 != self.next_z {
            return Err(FormatsError::Internal(format!(
                "NIfTI planes are read in order ({} next, {z0} asked)",
                self.next_z
            )));
        }
        let [x, y, _] = self.dims;
        let n = plane_bytes(x, y, self.stored) * u64::from(z1 - z0);
        out.clear();
        // Grown as the bytes arrive rather than sized from the header first: a compressed
        // stream that ends early costs what it held.
        let got = (&mut self.reader)
            .take(n)
            .read_to_end(out)
            .map_err(FormatsError::io_path("cannot read", &self.path))?;
        if (got as u64) < n {
            return Err(FormatsError::input(format!(
                "{}: truncated: the voxels end before plane {z1} of {}",
                self.path.display(),
                self.dims[2]
            )));
        }
        self.next_z = z1;
        let width = self.stored.bytes();
        if self.big_endian && width > 1 {
            for v in out.chunks_exact_mut(width) {
                v.reverse();
            }
        }
        if let Some((slope, inter)) = self.scaling {
            let values = std::mem::take(out);
            let count = values.len() / width;
            out.reserve(count * 4);
            for i in 0..count {
                let v = self.stored.value(&values, i);
                out.extend_from_slice(&((v as f32) * slope + inter).to_le_bytes());
            }
        }
        Ok(())
    }
}
