//! Brick records: a stored brick as it is in the file, read without decoding, checked against
//! its payload checksum or content hash, decoded, or served as the mapped bytes themselves.

use super::Snapshot;
use crate::store::codec;
use crate::store::region::MappedRegion;
use crate::store::StoreError;
use isovox_proto::vod2::{
    content_hash, payload_check, BrickHeader, Fields, NodeEntry, PAYLOAD_CHECK_LEN,
};
use isovox_proto::{BrickKey, FormatError, VolumeLayout};
use std::sync::Arc;

/// One stored brick as it is in the file: a constant, or a header and its payload (a slice of
/// the mapping, ready to be sent as it is).
#[derive(Debug, Clone, Copy)]
pub enum StoredBrick<'a> {
    /// Every voxel holds this value (no payload).
    Constant(u64),
    /// A brick record.
    Record {
        /// Where the record starts.
        offset: u64,
        /// Its header.
        header: BrickHeader,
        /// Its payload, a slice of the mapping.
        payload: &'a [u8],
        /// The checksum stored after the payload; `None` in records written before payload
        /// checksums.
        checksum: Option<u32>,
    },
}

/// What checking a stored payload against its checksum found (see
/// [`StoredBrick::check_payload`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PayloadCheck {
    /// The payload is what was stored (or there is none: a constant).
    Verified,
    /// The record has no checksum (written before payload checksums): only decoding it and
    /// comparing the content hash tells.
    NoChecksum,
}

impl StoredBrick<'_> {
    /// The brick's smallest and largest voxel value.
    pub fn min_max(&self) -> (u64, u64) {
        match self {
            StoredBrick::Constant(v) => (*v, *v),
            StoredBrick::Record { header, .. } => (header.min, header.max),
        }
    }

    /// The brick's content hash (for a constant, the hash of its expanded bytes).
    pub fn content_hash(&self, layout: &VolumeLayout) -> u64 {
        match self {
            StoredBrick::Constant(v) => codec::constant_hash(*v, layout),
            StoredBrick::Record { header, .. } => header.hash,
        }
    }

    /// Checks the payload against the checksum stored after it (one xxh3 pass over the stored
    /// bytes, no decoding).
    ///
    /// # Errors
    /// [`StoreError::Corrupt`]: the payload differs from what was stored.
    pub fn check_payload(&self) -> Result<PayloadCheck, StoreError> {
        match *self {
            StoredBrick::Constant(_) => Ok(PayloadCheck::Verified),
            StoredBrick::Record { checksum: None, .. } => Ok(PayloadCheck::NoChecksum),
            StoredBrick::Record {
                offset,
                payload,
                checksum: Some(stored),
                ..
            } => {
                let computed = payload_check(payload);
                if computed != stored {
                    return Err(StoreError::corrupt(
                        offset,
                        format!("a brick payload with checksum {stored:#010x}"),
                        format!("one with checksum {computed:#010x}"),
                    ));
                }
                Ok(PayloadCheck::Verified)
            }
        }
    }
}

/// Verifies a stored brick before its payload is copied or sent as it is: against its
/// checksum, or (a record without one) by decoding it and comparing the content hash.
///
/// # Errors
/// [`StoreError::Corrupt`]: the payload is not what was stored.
pub fn verify_stored(stored: &StoredBrick<'_>, layout: &VolumeLayout) -> Result<(), StoreError> {
    match stored.check_payload()? {
        PayloadCheck::Verified => Ok(()),
        PayloadCheck::NoChecksum => {
            let mut out = vec![0u8; layout.brick_bytes()];
            decode_stored(stored, layout, &mut out)
        }
    }
}

impl Snapshot {
    /// The stored form of the brick behind an entry, without decoding it.
    ///
    /// # Errors
    /// The brick header or its payload bounds are invalid.
    pub fn stored_entry(&self, entry: NodeEntry) -> Result<StoredBrick<'_>, StoreError> {
        match entry {
            NodeEntry::Constant(v) => Ok(StoredBrick::Constant(v)),
            NodeEntry::Stored(offset) => stored_record(&self.map, self.layout(), offset),
        }
    }

    /// The stored form of a brick, without decoding it.
    ///
    /// # Errors
    /// See [`Snapshot::entry`] and [`Snapshot::stored_entry`].
    pub fn stored(&self, key: BrickKey) -> Result<StoredBrick<'_>, StoreError> {
        self.stored_entry(self.entry(key)?)
    }

    /// Decodes a brick into `out` (exactly one brick's bytes) and checks its content hash.
    ///
    /// # Errors
    /// See [`Snapshot::stored`]; also a payload that does not decode or does not match its hash.
    pub fn read_into(&self, key: BrickKey, out: &mut [u8]) -> Result<(), StoreError> {
        let stored = self.stored(key)?;
        decode_stored(&stored, self.layout(), out)
    }

    /// A brick's voxels: a constant as it is stored, anything else decoded (and checked).
    ///
    /// # Errors
    /// See [`Snapshot::read_into`].
    pub fn voxels(&self, key: BrickKey) -> Result<crate::store::BrickVoxels, StoreError> {
        Ok(match self.stored(key)? {
            StoredBrick::Constant(v) => crate::store::BrickVoxels::Constant(v),
            record => crate::store::BrickVoxels::Data(decode_stored_new(&record, self.layout())?),
        })
    }

    /// Decodes a brick into a new buffer.
    ///
    /// # Errors
    /// See [`Snapshot::read_into`].
    pub fn read(&self, key: BrickKey) -> Result<Vec<u8>, StoreError> {
        let mut out = vec![0u8; self.layout().brick_bytes()];
        self.read_into(key, &mut out)?;
        Ok(out)
    }
}

/// The brick record at `offset` of the mapped bytes `mapped`: its header checked, its payload
/// and (in a checked record) the payload's checksum bounds-checked, nothing decoded.
pub(super) fn stored_record<'m>(
    map: &'m MappedRegion,
    layout: &VolumeLayout,
    offset: u64,
) -> Result<StoredBrick<'m>, StoreError> {
    // A record is its header, its payload and (checked records) the payload's checksum, in a
    // row: filled in one go when they share a page, which they mostly do.
    let header_len = BrickHeader::len_for(layout.voxel_type());
    map.ensure(offset, header_len as u64)?;
    let fields = Fields::new("brick record", map.bytes(), 0);
    let at = usize::try_from(offset).map_err(|_| {
        FormatError::invalid(
            "brick record",
            format!("offset {offset} is not addressable"),
        )
    })?;
    let header = BrickHeader::decode(fields.slice(at, header_len)?, offset, layout)?;
    let start = at + header_len;
    let tail = if header.checked { PAYLOAD_CHECK_LEN } else { 0 };
    map.ensure(start as u64, (header.stored_len as usize + tail) as u64)?;
    let payload = fields.slice(start, header.stored_len as usize)?;
    let checksum = match header.checked {
        false => None,
        true => {
            let check = fields.slice(start + payload.len(), PAYLOAD_CHECK_LEN)?;
            Some(u32::from_le_bytes([check[0], check[1], check[2], check[3]]))
        }
    };
    Ok(StoredBrick::Record {
        offset,
        header,
        payload,
        checksum,
    })
}

/// A range of a mapping that keeps the mapping alive: lets a response carry mapped bytes
/// without copying them.
#[derive(Debug)]
struct MappedRange {
    map: Arc<MappedRegion>,
    start: usize,
    end: usize,
}

impl AsRef<[u8]> for MappedRange {
    fn as_ref(&self) -> &[u8] {
        &self.map.bytes()[self.start..self.end]
    }
}

impl Snapshot {
    /// The payload of a brick record of this snapshot (from [`Snapshot::stored`]), verified,
    /// as bytes to send as they are: checked against the checksum stored after it, or, in a
    /// record written before payload checksums, decoded and checked against its content hash
    /// the first time and then remembered by `verified` (see
    /// [`DecodedBricks::verify_payload`]). Payloads up to [`SHARE_PAYLOADS_FROM`] are copied,
    /// larger ones are shared slices of the mapping (no copy; the mapping lives as long as the
    /// bytes do).
    ///
    /// [`DecodedBricks::verify_payload`]: crate::store::decoded::DecodedBricks::verify_payload
    ///
    /// # Errors
    /// [`StoreError::Corrupt`]: the payload is not what was stored. [`StoreError::Internal`]:
    /// a constant (no payload), or a record read from another snapshot's mapping.
    pub fn verified_payload(
        &self,
        stored: &StoredBrick<'_>,
        verified: &crate::store::decoded::DecodedBricks,
    ) -> Result<bytes::Bytes, StoreError> {
        let StoredBrick::Record {
            offset,
            payload,
            header,
            ..
        } = *stored
        else {
            return Err(StoreError::Internal(
                "a constant brick has no payload to send".into(),
            ));
        };
        let mapped = self.map.bytes();
        let start = offset as usize + header.header_len();
        let end = start + payload.len();
        // The bytes checked must be the bytes sent: the payload is this mapping's slice.
        if mapped.get(start..end).map(<[u8]>::as_ptr) != Some(payload.as_ptr()) {
            return Err(StoreError::Internal(format!(
                "the brick record at {offset} was not read from this snapshot's mapping"
            )));
        }
        verified.verify_payload(stored, self.layout())?;
        if end - start < SHARE_PAYLOADS_FROM {
            return Ok(bytes::Bytes::copy_from_slice(payload));
        }
        Ok(bytes::Bytes::from_owner(MappedRange {
            map: self.map.clone(),
            start,
            end,
        }))
    }
}

/// Payloads from this size on are served as shared slices of the mapping; smaller ones are
/// copied. Sharing costs an allocation and two updates of the mapping's reference count, which
/// every core serving bricks touches; for a typical lz4 brick (a few hundred bytes) the copy is
/// cheaper.
pub const SHARE_PAYLOADS_FROM: usize = 4096;

/// A version's level 0 as the source of a build (same brick size): rebuilding a file from its
/// head drops every older version and all garbage.
#[derive(Debug)]
pub struct SnapshotSource {
    snap: Arc<Snapshot>,
    errors: crate::store::pyramid::FirstError,
}

impl SnapshotSource {
    /// A source reading `snap`'s level 0.
    pub fn new(snap: Arc<Snapshot>) -> Self {
        SnapshotSource {
            snap,
            errors: Default::default(),
        }
    }

    /// # Errors
    /// The first brick that failed to read during the build.
    pub fn finish(self) -> Result<(), StoreError> {
        self.errors.finish()
    }
}

impl crate::store::BrickSource for SnapshotSource {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        if let Err(e) = self.snap.read_into(key, out) {
            self.errors.record(e);
        }
    }

    fn constant(&self, key: BrickKey) -> Option<u64> {
        match self.snap.entry(key) {
            Ok(NodeEntry::Constant(v)) => Some(v),
            _ => None,
        }
    }
}

/// Decodes a stored brick into `out` and verifies it against its content hash.
///
/// # Errors
/// The payload does not decode, or decodes to bytes whose hash differs from the header's.
pub fn decode_stored(
    stored: &StoredBrick<'_>,
    layout: &VolumeLayout,
    out: &mut [u8],
) -> Result<(), StoreError> {
    match *stored {
        StoredBrick::Constant(v) => codec::fill_constant(out, v, layout.voxel_type()),
        StoredBrick::Record {
            offset,
            header,
            payload,
            ..
        } => {
            codec::decode(header.codec, payload, out, offset)?;
            check_content(out, header.hash, offset)?;
        }
    }
    Ok(())
}

/// A stored brick's voxels in a new buffer, verified against its content hash
/// ([`decode_stored`] into a buffer it makes).
///
/// # Errors
/// As [`decode_stored`].
pub fn decode_stored_new(
    stored: &StoredBrick<'_>,
    layout: &VolumeLayout,
) -> Result<Vec<u8>, StoreError> {
    match *stored {
        StoredBrick::Constant(_) => {
            let mut out = vec![0; layout.brick_bytes()];
            decode_stored(stored, layout, &mut out)?;
            Ok(out)
        }
        StoredBrick::Record {
            offset,
            header,
            payload,
            ..
        } => {
            let out = codec::decode_new(header.codec, payload, layout.brick_bytes(), offset)?;
            check_content(&out, header.hash, offset)?;
            Ok(out)
        }
    }
}

/// Whether decoded bytes have the content hash their record's header gives.
fn check_content(decoded: &[u8], expected: u64, offset: u64) -> Result<(), StoreError> {
    let hash = content_hash(decoded);
    if hash != expected {
        return Err(StoreError::corrupt(
            offset,
            format!("content hash {expected:#018x}"),
            format!("{hash:#018x}"),
        ));
    }
    Ok(())
}
