//! Reading TIFF stacks: a multi-page file (one page per z-plane) or a folder of TIFF files
//! (their pages in file-name order, numbers compared as numbers: `z2.tif` before `z10.tif`).
//!
//! Pages are grayscale, one sample per pixel, all of one size and type (8, 16, 32 or 64 bits,
//! unsigned, signed or float), decoded one at a time by the `tiff` crate within its default
//! memory limits.

use super::convert::DType;
use super::planes::PlaneSource;
use crate::formats::FormatsError;
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use tiff::decoder::{Decoder, DecodingResult};
use tiff::ColorType;

type TiffDecoder = Decoder<BufReader<File>>;

/// A TIFF stack open for reading plane by plane.
pub struct TiffInput {
    /// Each file and its number of pages.
    files: Vec<(PathBuf, u32)>,
    dims: [u32; 3],
    dtype: DType,
    /// The file being read and its decoder, positioned at the page `next_z` is on.
    current: Option<(usize, TiffDecoder)>,
    next_z: u32,
}

impl std::fmt::Debug for TiffInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TiffInput")
            .field("files", &self.files.len())
            .field("dims", &self.dims)
            .field("dtype", &self.dtype)
            .finish_non_exhaustive()
    }
}

/// Whether `path` starts with a TIFF or BigTIFF signature.
pub fn sniff(path: &Path) -> bool {
    let mut head = [0u8; 4];
    File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok()
        && matches!(&head, b"II*\0" | b"MM\0*" | b"II+\0" | b"MM\0+")
}

fn tiff_error(path: &Path, e: tiff::TiffError) -> FormatsError {
    FormatsError::input(format!("{}: {e}", path.display()))
}

fn open_decoder(path: &Path) -> Result<TiffDecoder, FormatsError> {
    let file = File::open(path).map_err(FormatsError::io_path("cannot open", path))?;
    Decoder::new(BufReader::new(file)).map_err(|e| tiff_error(path, e))
}

/// The page's size and type, checked to be a grayscale plane.
fn page_shape(path: &Path, d: &mut TiffDecoder) -> Result<([u32; 2], DType), FormatsError> {
    let (w, h) = d.dimensions().map_err(|e| tiff_error(path, e))?;
    let color = d.colortype().map_err(|e| tiff_error(path, e))?;
    let format = d
        .find_tag_unsigned::<u16>(tiff::tags::Tag::SampleFormat)
        .map_err(|e| tiff_error(path, e))?
        .unwrap_or(1);
    let dtype = match (color, format) {
        (ColorType::Gray(8), 1) => DType::U8,
        (ColorType::Gray(8), 2) => DType::I8,
        (ColorType::Gray(16), 1) => DType::U16,
        (ColorType::Gray(16), 2) => DType::I16,
        (ColorType::Gray(32), 1) => DType::U32,
        (ColorType::Gray(32), 2) => DType::I32,
        (ColorType::Gray(32), 3) => DType::F32,
        (ColorType::Gray(64), 3) => DType::F64,
        (other, format) => {
            return Err(FormatsError::input(format!(
                "{}: pages of {other:?} (sample format {format}); Isovox imports grayscale pages of 8, 16, 32 or 64 bits",
                path.display()
            )))
        }
    };
    Ok(([w, h], dtype))
}

/// "strip" or "tile": what the page's chunks are.
fn chunk_kind(d: &TiffDecoder) -> &'static str {
    match d.get_chunk_type() {
        tiff::decoder::ChunkType::Strip => "strip",
        tiff::decoder::ChunkType::Tile => "tile",
    }
}

/// Checks that every strip or tile of the current page (`page`, from 0) lies inside the file
/// of `len` bytes: the offsets are known before any is read, so one that points past the end
/// is refused when the stack is opened, by name, rather than failing a read halfway through.
fn check_chunks(path: &Path, page: u32, len: u64, d: &mut TiffDecoder) -> Result<(), FormatsError> {
    use tiff::tags::Tag;
    let kind = chunk_kind(d);
    let (offsets, counts) = match d.get_chunk_type() {
        tiff::decoder::ChunkType::Strip => (Tag::StripOffsets, Tag::StripByteCounts),
        tiff::decoder::ChunkType::Tile => (Tag::TileOffsets, Tag::TileByteCounts),
    };
    let offsets = d
        .find_tag_unsigned_vec::<u64>(offsets)
        .map_err(|e| tiff_error(path, e))?
        .unwrap_or_default();
    let counts = d
        .find_tag_unsigned_vec::<u64>(counts)
        .map_err(|e| tiff_error(path, e))?
        .unwrap_or_default();
    if offsets.len() != counts.len() {
        return Err(FormatsError::input(format!(
            "{}: page {page}: {} {kind} offsets but {} byte counts",
            path.display(),
            offsets.len(),
            counts.len()
        )));
    }
    for (i, (offset, count)) in offsets.iter().zip(&counts).enumerate() {
        if offset.checked_add(*count).is_none_or(|end| end > len) {
            return Err(FormatsError::input(format!(
                "{}: page {page}, {kind} {i}: {count} bytes at offset {offset} run past the end of the file ({len} bytes)",
                path.display()
            )));
        }
    }
    Ok(())
}

/// Pages of one file, each checked with [`check_chunks`].
fn count_pages(path: &Path) -> Result<u32, FormatsError> {
    let len = std::fs::metadata(path)
        .map_err(FormatsError::io_path("cannot stat", path))?
        .len();
    let mut d = open_decoder(path)?;
    check_chunks(path, 0, len, &mut d)?;
    let mut pages = 1u32;
    while d.more_images() {
        d.next_image()
            .map_err(|e| FormatsError::input(format!("{}: page {pages}: {e}", path.display())))?;
        check_chunks(path, pages, len, &mut d)?;
        pages += 1;
    }
    Ok(pages)
}

/// The error of a page that did not decode, naming the first of its strips or tiles that does
/// not (decoded alone, each within the decoder's limits) when one does not.
fn page_error(path: &Path, page: u32, d: &mut TiffDecoder, e: tiff::TiffError) -> FormatsError {
    let kind = chunk_kind(d);
    let chunks = match d.get_chunk_type() {
        tiff::decoder::ChunkType::Strip => d.strip_count(),
        tiff::decoder::ChunkType::Tile => d.tile_count(),
    }
    .unwrap_or(0);
    for i in 0..chunks {
        if let Err(e) = d.read_chunk(i) {
            return FormatsError::input(format!(
                "{}: page {page}, {kind} {i}: {e}",
                path.display()
            ));
        }
    }
    FormatsError::input(format!("{}: page {page}: {e}", path.display()))
}

/// `name` split into text and numbers, so that names sort as people number files.
fn natural_key(name: &str) -> Vec<(String, u128)> {
    let mut key = Vec::new();
    let mut text = String::new();
    let mut chars = name.chars().peekable();
    while let Some(c) = chars.next() {
        if c.is_ascii_digit() {
            let mut n = u128::from(c.to_digit(10).unwrap_or(0));
            while let Some(d) = chars.peek().and_then(|d| d.to_digit(10)) {
                n = n.saturating_mul(10).saturating_add(u128::from(d));
                chars.next();
            }
            key.push((std::mem::take(&mut text), n));
        } else {
            text.push(c);
        }
    }
    key.push((text, 0));
    key
}

impl TiffInput {
    /// Opens a multi-page TIFF file or a folder of TIFF files.
    ///
    /// # Errors
    /// No TIFF file, a file that does not decode, pages of another kind than grayscale, or
    /// pages of different sizes or types.
    pub fn open(path: &Path) -> Result<Self, FormatsError> {
        let paths: Vec<PathBuf> = if path.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(path)
                .map_err(FormatsError::io_path("cannot list", path))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.extension().and_then(|e| e.to_str()).is_some_and(|e| {
                        e.eq_ignore_ascii_case("tif") || e.eq_ignore_ascii_case("tiff")
                    })
                })
                .collect();
            found.sort_by_cached_key(|p| {
                natural_key(
                    &p.file_name()
                        .map(|n| n.to_string_lossy().into_owned())
                        .unwrap_or_default(),
                )
            });
            found
        } else {
            vec![path.to_path_buf()]
        };
        let first = paths.first().ok_or_else(|| {
            FormatsError::input(format!("{}: no .tif or .tiff file in it", path.display()))
        })?;
        let ([w, h], dtype) = page_shape(first, &mut open_decoder(first)?)?;
        let mut files = Vec::with_capacity(paths.len());
        let mut depth = 0u32;
        for p in paths {
            let pages = count_pages(&p)?;
            depth = depth.checked_add(pages).ok_or_else(|| {
                FormatsError::input(format!("{}: more than 2^32 pages", path.display()))
            })?;
            files.push((p, pages));
        }
        Ok(TiffInput {
            files,
            dims: [w, h, depth],
            dtype,
            current: None,
            next_z: 0,
        })
    }

    /// Moves the decoder to the page of plane `next_z`.
    fn advance(&mut self) -> Result<(), FormatsError> {
        let (mut file, mut first) = (0usize, 0u32);
        while first + self.files[file].1 <= self.next_z {
            first += self.files[file].1;
            file += 1;
        }
        match &mut self.current {
            Some((f, d)) if *f == file => {
                let path = &self.files[file].0;
                if !d.more_images() {
                    return Err(FormatsError::input(format!(
                        "{}: has fewer pages than when it was counted",
                        path.display()
                    )));
                }
                d.next_image().map_err(|e| tiff_error(path, e))
            }
            _ => {
                let d = open_decoder(&self.files[file].0)?;
                self.current = Some((file, d));
                Ok(())
            }
        }
    }
}

impl PlaneSource for TiffInput {
    fn dims(&self) -> [u32; 3] {
        self.dims
    }

    fn dtype(&self) -> DType {
        self.dtype
    }

    fn voxel_scale(&self) -> Option<[f32; 3]> {
        None
    }

    fn read(&mut self, z0: u32, z1: u32, out: &mut Vec<u8>) -> Result<(), FormatsError> {
        if z0 != self.next_z {
            return Err(FormatsError::Internal(format!(
                "TIFF pages are read in order ({} next, {z0} asked)",
                self.next_z
            )));
        }
        out.clear();
        for _ in z0..z1 {
            if self.next_z > 0 || self.current.is_none() {
                self.advance()?;
            }
            let Some((file, decoder)) = &mut self.current else {
                return Err(FormatsError::Internal("no TIFF page open".into()));
            };
            let page = self.next_z - self.files[..*file].iter().map(|f| f.1).sum::<u32>();
            let path = &self.files[*file].0;
            let (size, dtype) = page_shape(path, decoder)?;
            if size != [self.dims[0], self.dims[1]] || dtype != self.dtype {
                return Err(FormatsError::input(format!(
                    "{}: a page of {}x{} {dtype} in a stack of {}x{} {}",
                    path.display(),
                    size[0],
                    size[1],
                    self.dims[0],
                    self.dims[1],
                    self.dtype
                )));
            }
            let image = match decoder.read_image() {
                Ok(image) => image,
                Err(e) => return Err(page_error(path, page, decoder, e)),
            };
            match image {
                DecodingResult::U8(v) => out.extend_from_slice(&v),
                DecodingResult::I8(v) => out.extend(v.iter().map(|x| *x as u8)),
                DecodingResult::U16(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
                DecodingResult::I16(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
                DecodingResult::U32(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
                DecodingResult::I32(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
                DecodingResult::F32(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
                DecodingResult::F64(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
                other => {
                    return Err(FormatsError::input(format!(
                        "{}: decoded as {other:?}, not the page type",
                        path.display()
                    )))
                }
            }
            self.next_z += 1;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::natural_key;

    #[test]
    fn names_sort_by_their_numbers() {
        let mut names = vec!["z10.tif", "z2.tif", "z1.tif", "a.tif", "z02b.tif"];
        names.sort_by_key(|n| natural_key(n));
        assert_eq!(
            names,
            vec!["a.tif", "z1.tif", "z2.tif", "z02b.tif", "z10.tif"]
        );
    }
}
