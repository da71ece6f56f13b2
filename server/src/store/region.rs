//! The committed region of a VOD 2 file as its readers see it: a memory mapping, and for a
//! volume kept in an object store, what fills the mapping's holes before they are read.
//!
//! A local file is whole: [`MappedRegion::ensure`] is one predictable branch and the brick path
//! reads the mapping as it always did. A replica of a volume in an object store maps a sparse
//! local file instead (the bounded cache, [`crate::store::remote`]); every read first asks its
//! [`Fill`] to bring the bytes it is about to touch, so a range that was never fetched is never
//! read. Everything read is checksummed anyway (records, index chunks, brick headers and
//! contents), so a range read without its fill would be an error, never wrong voxels.
//!
//! (Not to be confused with a box of voxels, [`crate::geometry::Box3`].)

use super::mapping::Mapping;
use super::StoreError;
use std::fmt::Debug;
use std::sync::Arc;

/// Brings bytes of the logical file into a mapping before they are read (the storage seam: a
/// local file needs none).
pub trait Fill: Send + Sync + Debug {
    /// Makes bytes `[start, start + len)` of the mapped file hold the file's content.
    ///
    /// # Errors
    /// The bytes cannot be fetched or written (the store is unreachable, an object is missing).
    fn fill(&self, start: u64, len: u64) -> Result<(), StoreError>;
}

/// A mapped committed region and, for a sparse mirror, its filler.
#[derive(Debug)]
pub struct MappedRegion {
    map: Mapping,
    fill: Option<Arc<dyn Fill>>,
}

impl MappedRegion {
    /// A whole local file.
    pub(crate) fn whole(map: Mapping) -> MappedRegion {
        MappedRegion { map, fill: None }
    }

    /// A sparse mirror whose bytes `fill` brings on first use.
    pub(crate) fn filled(map: Mapping, fill: Arc<dyn Fill>) -> MappedRegion {
        MappedRegion {
            map,
            fill: Some(fill),
        }
    }

    /// Makes `[start, start + len)` readable (clipped to the region; past it, the readers'
    /// bounds checks answer).
    ///
    /// # Errors
    /// See [`Fill::fill`].
    #[inline]
    pub(crate) fn ensure(&self, start: u64, len: u64) -> Result<(), StoreError> {
        match &self.fill {
            None => Ok(()),
            Some(fill) => {
                let end = start.saturating_add(len).min(self.len());
                if start >= end {
                    return Ok(());
                }
                fill.fill(start, end - start)
            }
        }
    }

    /// The mapped bytes: read only ranges made readable by [`MappedRegion::ensure`] first.
    #[inline]
    pub(crate) fn bytes(&self) -> &[u8] {
        self.map.bytes()
    }

    /// The mapping of a whole local file (a mirror's has holes to fill: `None`).
    pub(crate) fn whole_mapping(&self) -> Option<&Mapping> {
        self.fill.is_none().then_some(&self.map)
    }

    /// The region's length.
    #[inline]
    pub(crate) fn len(&self) -> u64 {
        self.map.bytes().len() as u64
    }
}
