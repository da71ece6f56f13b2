//! Inputs as streams of z-planes, and the one brick source every import builds from.
//!
//! Each input format implements [`PlaneSource`]: its voxels a range of z-planes at a time, in
//! their own type. [`SlabSource`] turns that into the [`BrickSource`] the pyramid build asks,
//! holding one slab (the `brick` planes of one row of bricks) converted to u8 or u16: the build
//! asks for level-0 bricks one z-row at a time, so memory holds one slab of the input whatever
//! its size.

use super::convert::{Conversion, DType};
use crate::formats::FormatsError;
use crate::store::{BrickSource, DenseGrid};
use isovox_proto::{BrickKey, VolumeLayout};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, RwLock};

/// An input's voxels, read a range of z-planes at a time.
pub trait PlaneSource: Send {
    /// Voxels per axis: x, y, z.
    fn dims(&self) -> [u32; 3];
    /// The type of the values [`PlaneSource::read`] returns.
    fn dtype(&self) -> DType;
    /// World size of one voxel (x, y, z), when the input records it.
    fn voxel_scale(&self) -> Option<[f32; 3]>;
    /// Planes best read together (a chunk's depth); reads start at multiples of it.
    fn depth(&self) -> u32 {
        1
    }
    /// Replaces `out` with planes `z0..z1`: x fastest, then y, then z, each value little
    /// endian. Calls come in increasing `z0`.
    ///
    /// # Errors
    /// The input cannot be read or is malformed there.
    fn read(&mut self, z0: u32, z1: u32, out: &mut Vec<u8>) -> Result<(), FormatsError>;
}

/// Most bytes one slab may take (input and converted): an input whose planes are so large that
/// one row of bricks exceeds it is refused instead of exhausting memory.
pub const MAX_SLAB_BYTES: u64 = 8 << 30;

/// Reads a source in runs of whole planes, aligned to its preferred depth, and hands out any
/// range inside the run held.
pub struct PlaneRuns {
    source: Box<dyn PlaneSource>,
    held: (u32, u32),
    buf: Vec<u8>,
}

impl std::fmt::Debug for PlaneRuns {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PlaneRuns")
            .field("held", &self.held)
            .finish_non_exhaustive()
    }
}

impl PlaneRuns {
    /// Runs of `source`'s planes.
    pub fn new(source: Box<dyn PlaneSource>) -> Self {
        PlaneRuns {
            source,
            held: (0, 0),
            buf: Vec::new(),
        }
    }

    /// The source read.
    pub fn source(&self) -> &dyn PlaneSource {
        &*self.source
    }

    /// Planes `z0..z1` (inside the volume), little endian.
    ///
    /// # Errors
    /// What the source fails with.
    pub fn planes(&mut self, z0: u32, z1: u32) -> Result<&[u8], FormatsError> {
        let [x, y, z] = self.source.dims();
        if z0 < self.held.0 || z1 > self.held.1 {
            let depth = self.source.depth().max(1);
            let start = z0 / depth * depth;
            let end = z1.div_ceil(depth).saturating_mul(depth).min(z);
            self.source.read(start, end, &mut self.buf)?;
            let expected = plane_bytes(x, y, self.source.dtype()) * u64::from(end - start);
            if self.buf.len() as u64 != expected {
                return Err(FormatsError::Internal(format!(
                    "planes {start}..{end} came as {} bytes, {expected} expected",
                    self.buf.len()
                )));
            }
            self.held = (start, end);
        }
        let plane = plane_bytes(x, y, self.source.dtype()) as usize;
        let from = (z0 - self.held.0) as usize * plane;
        let to = (z1 - self.held.0) as usize * plane;
        Ok(&self.buf[from..to])
    }
}

/// Bytes of one plane of `x` by `y` values of `dtype`.
pub fn plane_bytes(x: u32, y: u32, dtype: DType) -> u64 {
    u64::from(x) * u64::from(y) * dtype.bytes() as u64
}

/// The level-0 bricks of an import, made from one slab of converted planes at a time.
pub struct SlabSource {
    layout: VolumeLayout,
    conversion: Conversion,
    reader: Mutex<PlaneRuns>,
    /// The brick row (z) held, and its planes converted to the volume's type.
    slab: RwLock<(Option<u32>, Vec<u8>)>,
    /// The first read that failed; once set, bricks are left empty (the build is discarded).
    error: Mutex<Option<FormatsError>>,
    failed: AtomicBool,
}

impl std::fmt::Debug for SlabSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SlabSource")
            .field("layout", &self.layout)
            .field("conversion", &self.conversion)
            .finish_non_exhaustive()
    }
}

impl SlabSource {
    /// A source for `layout` (whose dims are the input's) reading `input` and converting its
    /// values with `conversion`.
    ///
    /// # Errors
    /// One slab would take more than [`MAX_SLAB_BYTES`].
    pub fn new(
        layout: VolumeLayout,
        input: Box<dyn PlaneSource>,
        conversion: Conversion,
    ) -> Result<Self, FormatsError> {
        let [x, y, _] = layout.dims();
        let per_plane = plane_bytes(x, y, input.dtype()) + plane_bytes(x, y, DType::U16);
        let depth = u64::from(layout.brick().max(input.depth()));
        if per_plane.saturating_mul(depth) > MAX_SLAB_BYTES {
            return Err(FormatsError::input(format!(
                "one slab of {x} x {y} x {depth} voxels would take more than {} GiB; use a smaller --brick",
                MAX_SLAB_BYTES >> 30
            )));
        }
        Ok(SlabSource {
            layout,
            conversion,
            reader: Mutex::new(PlaneRuns::new(input)),
            slab: RwLock::new((None, Vec::new())),
            error: Mutex::new(None),
            failed: AtomicBool::new(false),
        })
    }

    /// # Errors
    /// The first read that failed during the build.
    pub fn finish(self) -> Result<(), FormatsError> {
        match self.error.into_inner() {
            Ok(None) => Ok(()),
            Ok(Some(e)) => Err(e),
            Err(_) => Err(FormatsError::Internal("a reader thread panicked".into())),
        }
    }

    fn fail(&self, e: FormatsError) {
        self.failed.store(true, Ordering::Release);
        if let Ok(mut first) = self.error.lock() {
            first.get_or_insert(e);
        }
    }

    /// Loads brick row `bz` unless it is held.
    fn load(&self, bz: u32) -> Result<(), FormatsError> {
        let mut reader = self
            .reader
            .lock()
            .map_err(|_| FormatsError::Internal("a reader thread panicked".into()))?;
        if self.slab.read().map(|s| s.0 == Some(bz)).unwrap_or(false) {
            return Ok(());
        }
        let b = self.layout.brick();
        let [_, _, dz] = self.layout.dims();
        let (z0, z1) = (bz * b, (bz + 1).saturating_mul(b).min(dz));
        let dtype = reader.source().dtype();
        let converted = self.conversion.apply(dtype, reader.planes(z0, z1)?)?;
        let mut slab = self
            .slab
            .write()
            .map_err(|_| FormatsError::Internal("a reader thread panicked".into()))?;
        *slab = (Some(bz), converted);
        Ok(())
    }
}

impl BrickSource for SlabSource {
    fn failed(&self) -> bool {
        self.failed.load(Ordering::Acquire)
    }

    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        if self.failed.load(Ordering::Acquire) {
            return;
        }
        let copy = |slab: &(Option<u32>, Vec<u8>), out: &mut [u8]| -> bool {
            if slab.0 != Some(key.z) {
                return false;
            }
            let [x, y, _] = self.layout.dims();
            let planes = (slab.1.len()
                / (x as usize * y as usize * self.layout.voxel_type().bytes()))
                as u32;
            let grid = DenseGrid::new(
                [x, y, planes],
                self.layout.voxel_type(),
                self.layout.brick(),
                &slab.1,
            );
            grid.fill(BrickKey { z: 0, ..key }, out);
            true
        };
        if let Ok(slab) = self.slab.read() {
            if copy(&slab, out) {
                return;
            }
        }
        if let Err(e) = self.load(key.z) {
            self.fail(e);
            return;
        }
        match self.slab.read() {
            Ok(slab) if copy(&slab, out) => {}
            _ => self.fail(FormatsError::Internal(format!(
                "brick row {} was not held after loading it",
                key.z
            ))),
        }
    }
}
