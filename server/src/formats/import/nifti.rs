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
    let mut reader = open_stream(file, path);
    let mut head = [0u8; HEADER_LEN];
    reader.read_exact(&mut head).is_ok()
        && (head[..4] == 348i32.to_le_bytes() || head[..4] == 348i32.to_be_bytes())
        && matches!(&head[344..348], b"n+1\0" | b"ni1\0")
}

fn open_stream(file: File, path: &Path) -> Box<dyn Read + Send> {
    let mut buffered = BufReader::new(file);
    let gz = {
        use std::io::BufRead;
        buffered
            .fill_buf()
            .is_ok_and(|b| b.starts_with(&[0x1f, 0x8b]))
    };
    if gz || path.extension().is_some_and(|e| e == "gz") {
        Box::new(flate2::read::MultiGzDecoder::new(buffered))
    } else {
        Box::new(buffered)
    }
}

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
    let big_endian = match (
        i32::from_le_bytes([h[0], h[1], h[2], h[3]]),
        i32::from_be_bytes([h[0], h[1], h[2], h[3]]),
    ) {
        (348, _) => false,
        (_, 348) => true,
        _ => return Err(bad("not a NIfTI-1 file (sizeof_hdr is not 348)".into())),
    };
    match &h[344..348] {
        b"n+1\0" => {}
        b"ni1\0" => {
            return Err(bad(
                "a NIfTI-1 header/image pair (.hdr/.img); Isovox imports single .nii files".into(),
            ))
        }
        _ => return Err(bad("not a NIfTI-1 file (no n+1 magic)".into())),
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
        other => {
            return Err(bad(format!(
                "datatype {other} is not supported (uint8, int8, uint16, int16, uint32, int32, float32, float64 are)"
            )))
        }
    };
    let vox_offset = f32_at(108);
    if !(vox_offset.is_finite() && vox_offset >= HEADER_LEN as f32 && vox_offset < 1e9) {
        return Err(bad(format!(
            "vox_offset {vox_offset} is not a valid offset"
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
        let mut reader = open_stream(file, path);
        let mut head = [0u8; HEADER_LEN];
        reader.read_exact(&mut head).map_err(|_| {
            FormatsError::input(format!(
                "{}: shorter than a NIfTI-1 header (348 bytes)",
                path.display()
            ))
        })?;
        let h = parse_header(&head, path)?;
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
        let n = (plane_bytes(x, y, self.stored) * u64::from(z1 - z0)) as usize;
        out.clear();
        out.resize(n, 0);
        self.reader.read_exact(out).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                FormatsError::input(format!(
                    "{}: truncated: the voxels end before plane {z1} of {}",
                    self.path.display(),
                    self.dims[2]
                ))
            } else {
                FormatsError::io_path("cannot read", &self.path)(e)
            }
        })?;
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
