//! The one memory-mapping module: every `unsafe` block of the library lives here (the binary
//! has one more, in `allocator.rs`).
//!
//! A [`Mapping`] is a read-only, shared mapping of a file's first `len` bytes, taken at open.
//! Writers only ever append past the mapped length, or write the header slots with ordinary
//! `pwrite`s (read back with `pread`, never through the mapping), so no byte a live `&[u8]`
//! points at is ever changed while the mapping exists.
#![allow(unsafe_code)]

use memmap2::{Mmap, MmapOptions};
use std::fs::File;
use std::io;

/// A read-only view of a file's bytes.
#[derive(Debug)]
pub(crate) struct Mapping {
    map: Option<Mmap>,
}

impl Mapping {
    /// Maps the first `len` bytes of `file` (a zero-length mapping needs no system call).
    ///
    /// # Errors
    /// The system refuses the mapping.
    pub(crate) fn new(file: &File, len: u64) -> io::Result<Mapping> {
        if len == 0 {
            return Ok(Mapping { map: None });
        }
        let len = usize::try_from(len).map_err(|_| io::Error::other("file too large to map"))?;
        // SAFETY: the mapping is read-only and shared. Isovox never modifies bytes below `len`
        // of a file it has mapped: VOD files are append-only past the committed length, and the
        // header slots are written and read with pwrite/pread, not through a mapping. Another
        // process truncating the file underneath us is outside that contract (it would raise
        // SIGBUS, as with every mmap-based reader).
        let map = unsafe { MmapOptions::new().len(len).map(file)? };
        #[cfg(unix)]
        {
            // Brick reads are random; do not let the kernel read ahead megabytes per fault.
            let _ = map.advise(memmap2::Advice::Random);
        }
        Ok(Mapping { map: Some(map) })
    }

    /// The mapped bytes.
    pub(crate) fn bytes(&self) -> &[u8] {
        self.map.as_deref().unwrap_or(&[])
    }
}
