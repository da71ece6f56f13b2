//! The one memory-mapping module: every `unsafe` block of the library lives here (the binary
//! has one more, in `allocator.rs`).
//!
//! A [`Mapping`] is a read-only, shared mapping of a file's first `len` bytes. Writers only
//! ever append past the committed length, or write the header slots with ordinary `pwrite`s
//! (read back with `pread`, never through the mapping), so no byte a live `&[u8]` points at is
//! ever changed while the mapping exists.
//!
//! A mapping taken [`with_room`](Mapping::with_room) reserves addresses past the end of the
//! file: the file's next versions, appended behind it, are seen through the same mapping
//! ([`Mapping::grown`]) instead of a new one per commit, which would cost the system call,
//! the unmapping of the old one (a TLB shootdown on every core) and a page fault for every page
//! read again. Pages past a version's length are never read.
#![allow(unsafe_code)]

use memmap2::{Mmap, MmapOptions};
use std::fs::File;
use std::io;
use std::sync::Arc;

/// A read-only view of a file's bytes.
#[derive(Debug)]
pub(crate) struct Mapping {
    /// The mapped addresses, shared by the versions seen through them.
    map: Option<Arc<Mmap>>,
    /// The bytes this view shows (at most the mapping's length).
    len: usize,
}

impl Mapping {
    /// Maps the first `len` bytes of `file` (a zero-length mapping needs no system call).
    ///
    /// # Errors
    /// The system refuses the mapping.
    pub(crate) fn new(file: &File, len: u64) -> io::Result<Mapping> {
        Mapping::with_room(file, len, 0)
    }

    /// Maps the first `len` bytes of `file` and `room` more addresses past them, for the bytes
    /// appended later ([`Mapping::grown`]).
    ///
    /// # Errors
    /// The system refuses the mapping.
    pub(crate) fn with_room(file: &File, len: u64, room: u64) -> io::Result<Mapping> {
        let too_large = || io::Error::other("file too large to map");
        let len = usize::try_from(len).map_err(|_| too_large())?;
        let reserved = usize::try_from(room)
            .ok()
            .and_then(|room| len.checked_add(room))
            .ok_or_else(too_large)?;
        if reserved == 0 {
            return Ok(Mapping { map: None, len: 0 });
        }
        // SAFETY: the mapping is read-only and shared. Isovox never modifies bytes below `len`
        // of a file it has mapped: VOD files are append-only past the committed length, and the
        // header slots are written and read with pwrite/pread, not through a mapping. Addresses
        // past the file's end are never read: `bytes` stops at `len`, and a view is only grown
        // to a length the file has reached. Another process truncating the file underneath us
        // is outside that contract (it would raise SIGBUS, as with every mmap-based reader).
        let map = unsafe { MmapOptions::new().len(reserved).map(file)? };
        #[cfg(unix)]
        {
            // Brick reads are random; do not let the kernel read ahead megabytes per fault.
            let _ = map.advise(memmap2::Advice::Random);
        }
        Ok(Mapping {
            map: Some(Arc::new(map)),
            len,
        })
    }

    /// The same mapping showing its file's first `len` bytes, when it has the room; the caller
    /// must know the file holds them (a committed length it has just written and synced, or
    /// read from a valid header slot).
    pub(crate) fn grown(&self, len: u64) -> Option<Mapping> {
        let map = self.map.as_ref()?;
        let len = usize::try_from(len).ok().filter(|&l| l <= map.len())?;
        Some(Mapping {
            map: Some(map.clone()),
            len,
        })
    }

    /// The mapped bytes.
    pub(crate) fn bytes(&self) -> &[u8] {
        self.map.as_deref().map_or(&[], |m| &m[..self.len])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn a_grown_view_sees_bytes_appended_after_the_mapping() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        let mut file = File::create(&path).unwrap();
        file.write_all(b"0123456789").unwrap();
        let read = File::open(&path).unwrap();
        let first = Mapping::with_room(&read, 10, 4096).unwrap();
        assert_eq!(first.bytes(), b"0123456789");
        file.write_all(b"abcdefghij").unwrap();
        let second = first.grown(20).unwrap();
        assert_eq!(second.bytes(), b"0123456789abcdefghij");
        // The first view still shows what it showed.
        assert_eq!(first.bytes(), b"0123456789");
        // Only as far as the room reserved; a mapping without room never grows.
        assert!(first.grown(10 + 4096).is_some());
        assert!(first.grown(10 + 4096 + 1).is_none());
        assert!(Mapping::new(&read, 10).unwrap().grown(11).is_none());
        assert!(Mapping::new(&read, 0).unwrap().grown(1).is_none());
    }
}
