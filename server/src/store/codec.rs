//! Brick payload encoding: constant, raw, an lz4 block or a zstd frame, chosen per brick.
//!
//! zstd is the default for storage: on the thesis's synthetic volumes it stores bricks about 2.5x
//! smaller than lz4 (what the compression goals need) and still decodes at over 1 GB/s per core.
//! lz4 remains for files that favour decode speed above all.

use super::StoreError;
use isovox_proto::vod2::Codec;
/// The smallest and largest value of a decoded brick (shared with the client streamer).
pub use isovox_proto::voxel::min_max;
use isovox_proto::{VolumeLayout, VoxelType};
use std::cell::RefCell;

/// How a writer compresses bricks (each brick is stored raw when compression does not shrink it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Compression {
    /// Every brick stored raw.
    None,
    /// lz4 blocks (fast to decode, larger).
    Lz4,
    /// zstd at this level (1-22; negative levels are zstd's fast modes).
    Zstd(i32),
}

impl Default for Compression {
    fn default() -> Self {
        Compression::Zstd(DEFAULT_ZSTD_LEVEL)
    }
}

/// The zstd level imports use unless told otherwise.
pub const DEFAULT_ZSTD_LEVEL: i32 = 5;

/// The zstd level of the bricks an edit writes. An edit compresses every brick it changes,
/// on every level of detail (about 15 for a small carve in a 1024^3 world), while its editor
/// waits, and compressing was the largest part of an edit's CPU. Level -1, zstd's first fast
/// level, compresses terrain bricks in about two thirds of level 3's time, a little larger, and
/// decodes them faster; `isovox-bench edits` makes more edits/s with it, at a lower latency for
/// a single editor. The frames are ordinary zstd frames. Imports and builds, written once, keep
/// the stronger default.
pub const EDIT_ZSTD_LEVEL: i32 = -1;

/// The zstd level at least of the attribute channels' bricks that imports and builds write.
/// Label and material bricks are ids: long runs of a few 16-bit values, which zstd's stronger
/// levels find much more of than the default's (a synthetic segmentation of 24-voxel cells,
/// 64^3 bricks: 1.05 MB at level 5, 0.80 MB at level 15, where Neuroglancer's
/// compressed_segmentation + gzip takes 0.85 MB; `isovox-bench channels`). Level 15
/// compresses such bricks at tens of MB/s, and most bricks of a channel are constant
/// (stored free, never compressed); decoding is as fast as at any level.
pub const CHANNEL_ZSTD_LEVEL: i32 = 15;

impl Compression {
    /// What edits compress new bricks with ([`EDIT_ZSTD_LEVEL`]).
    pub fn for_edits() -> Compression {
        Compression::Zstd(EDIT_ZSTD_LEVEL)
    }

    /// What a build compresses an attribute channel's bricks with when it compresses density
    /// with this: zstd at [`CHANNEL_ZSTD_LEVEL`] or above; lz4 and raw as asked.
    pub fn for_channels(self) -> Compression {
        match self {
            Compression::Zstd(level) => Compression::Zstd(level.max(CHANNEL_ZSTD_LEVEL)),
            other => other,
        }
    }
}

thread_local! {
    static ZSTD_ENCODER: RefCell<Option<(i32, zstd::bulk::Compressor<'static>)>> = const { RefCell::new(None) };
    static ZSTD_DECODER: RefCell<Option<zstd::bulk::Decompressor<'static>>> = const { RefCell::new(None) };
}

/// Fills a decoded brick with one value.
pub fn fill_constant(out: &mut [u8], value: u64, voxel_type: VoxelType) {
    let n = voxel_type.bytes();
    if n == 1 {
        out.fill(value as u8);
        return;
    }
    let le = &value.to_le_bytes()[..n];
    for c in out.chunks_exact_mut(n) {
        c.copy_from_slice(le);
    }
}

/// The content hash of the constant brick of `value` in `layout`'s brick shape: the hash of its
/// expanded bytes, as for any other brick. Remembered per thread (most bricks of a sparse volume
/// are constant, and hashing 32 KiB for each would dominate a level listing).
pub fn constant_hash(value: u64, layout: &VolumeLayout) -> u64 {
    /// Constants remembered per thread at most (a u16 volume may hold thousands of them).
    const REMEMBERED: usize = 256;
    let key = (value, layout.brick_bytes(), layout.voxel_type().bytes());
    CONSTANT_HASHES.with(|cell| {
        if let Some(&hash) = cell.borrow().get(&key) {
            return hash;
        }
        let mut bytes = vec![0u8; layout.brick_bytes()];
        fill_constant(&mut bytes, value, layout.voxel_type());
        let hash = isovox_proto::vod2::content_hash(&bytes);
        let mut known = cell.borrow_mut();
        if known.len() < REMEMBERED {
            known.insert(key, hash);
        }
        hash
    })
}

thread_local! {
    static CONSTANT_HASHES: RefCell<std::collections::HashMap<(u64, usize, usize), u64>> =
        RefCell::default();
}

fn zstd_compress(bytes: &[u8], level: i32) -> Option<Vec<u8>> {
    ZSTD_ENCODER.with(|cell| {
        let mut slot = cell.borrow_mut();
        if slot.as_ref().is_none_or(|(l, _)| *l != level) {
            *slot = Some((level, zstd::bulk::Compressor::new(level).ok()?));
        }
        let (_, encoder) = slot.as_mut()?;
        encoder.compress(bytes).ok()
    })
}

/// Encodes bytes with `compression`, falling back to raw when that is not smaller.
/// (Constant bricks never get here: they are stored in the index.)
pub fn encode(bytes: &[u8], compression: Compression) -> (Codec, Vec<u8>) {
    let compressed = match compression {
        Compression::None => None,
        Compression::Lz4 => Some((Codec::Lz4, lz4_flex::block::compress(bytes))),
        Compression::Zstd(level) => zstd_compress(bytes, level).map(|c| (Codec::Zstd, c)),
    };
    match compressed {
        Some((codec, c)) if c.len() < bytes.len() => (codec, c),
        _ => (Codec::Raw, bytes.to_vec()),
    }
}

/// Decodes a zstd frame into `out` (a slice, or a Vec's spare capacity) with this thread's
/// decoder; the number of bytes written.
fn zstd_decode<B: zstd::zstd_safe::WriteBuf + ?Sized>(
    payload: &[u8],
    out: &mut B,
    offset: u64,
) -> Result<usize, StoreError> {
    ZSTD_DECODER
        .with(|cell| {
            let mut slot = cell.borrow_mut();
            if slot.is_none() {
                *slot = Some(zstd::bulk::Decompressor::new()?);
            }
            match slot.as_mut() {
                Some(d) => d.decompress_to_buffer(payload, out),
                None => Err(std::io::Error::other("no zstd decoder")),
            }
        })
        .map_err(|e| {
            StoreError::corrupt(
                offset,
                "a zstd frame",
                format!("one that does not decode: {e}"),
            )
        })
}

/// Decodes a stored payload of `len` decoded bytes into a new buffer. Unlike [`decode`] into a
/// zeroed one, the buffer is not cleared first: the decoder writes every byte (a 32 KiB brick's
/// clearing was a tenth of decoding it).
///
/// # Errors
/// As [`decode`]: the payload is malformed or does not decode to exactly `len` bytes. Decoding
/// never allocates beyond `len`.
pub fn decode_new(
    codec: Codec,
    payload: &[u8],
    len: usize,
    offset: u64,
) -> Result<Vec<u8>, StoreError> {
    match codec {
        Codec::Zstd => {
            let mut out = Vec::with_capacity(len);
            // Writes into the spare capacity and never past it.
            let n = zstd_decode(payload, &mut out, offset)?;
            if n != len {
                return Err(StoreError::corrupt(
                    offset,
                    format!("a zstd payload of {len} bytes"),
                    format!("{n} bytes"),
                ));
            }
            Ok(out)
        }
        Codec::Raw | Codec::Lz4 => {
            let mut out = vec![0; len];
            decode(codec, payload, &mut out, offset)?;
            Ok(out)
        }
    }
}

/// Decodes a stored payload into `out`, which has exactly the decoded size.
///
/// # Errors
/// The payload is malformed or does not decode to exactly `out.len()` bytes. Decoding never
/// writes or allocates beyond `out`.
pub fn decode(codec: Codec, payload: &[u8], out: &mut [u8], offset: u64) -> Result<(), StoreError> {
    let n = match codec {
        Codec::Raw => {
            if payload.len() == out.len() {
                out.copy_from_slice(payload);
            }
            payload.len()
        }
        Codec::Lz4 => lz4_flex::block::decompress_into(payload, out).map_err(|e| {
            StoreError::corrupt(
                offset,
                "an lz4 block",
                format!("one that does not decode: {e}"),
            )
        })?,
        Codec::Zstd => zstd_decode(payload, out, offset)?,
    };
    if n != out.len() {
        return Err(StoreError::corrupt(
            offset,
            format!("a {} payload of {} bytes", codec.name(), out.len()),
            format!("{n} bytes"),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_fill_is_little_endian() {
        let mut b = [0u8; 6];
        fill_constant(&mut b, 0x1234, VoxelType::U16);
        assert_eq!(b, [0x34, 0x12, 0x34, 0x12, 0x34, 0x12]);
        let mut b = [0u8; 16];
        fill_constant(&mut b, 0x0102_0304_0506_0708, VoxelType::U64);
        assert_eq!(b[..8], [8, 7, 6, 5, 4, 3, 2, 1]);
        assert_eq!(b[..8], b[8..]);
    }

    fn noise(n: usize) -> Vec<u8> {
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                s as u8
            })
            .collect()
    }

    #[test]
    fn channels_compress_with_zstd_at_the_channel_level_at_least() {
        assert_eq!(Compression::Zstd(5).for_channels(), Compression::Zstd(15));
        assert_eq!(Compression::Zstd(19).for_channels(), Compression::Zstd(19));
        assert_eq!(Compression::Lz4.for_channels(), Compression::Lz4);
        assert_eq!(Compression::None.for_channels(), Compression::None);
    }

    #[test]
    fn every_compression_round_trips_and_falls_back_to_raw() {
        let mut smooth = vec![0u8; 4096];
        smooth[100..900].fill(200);
        for compression in [
            Compression::Lz4,
            Compression::Zstd(3),
            Compression::Zstd(19),
        ] {
            let (c, p) = encode(&smooth, compression);
            assert_ne!(c, Codec::Raw);
            assert!(p.len() < 200, "{compression:?} gave {} bytes", p.len());
            let mut out = vec![0u8; 4096];
            decode(c, &p, &mut out, 0).unwrap();
            assert_eq!(out, smooth);
            // An xorshift sequence does not compress: stored raw.
            let n = noise(4096);
            let (c, p) = encode(&n, compression);
            assert_eq!(c, Codec::Raw);
            decode(c, &p, &mut out, 0).unwrap();
            assert_eq!(out, n);
        }
        assert_eq!(encode(&smooth, Compression::None).0, Codec::Raw);
    }

    #[test]
    fn decode_rejects_garbage_without_overrunning() {
        let mut out = vec![0u8; 64];
        assert!(decode(Codec::Lz4, &[0xff, 0xff, 0xff], &mut out, 0).is_err());
        assert!(decode(Codec::Zstd, &[0x28, 0xb5, 0x2f, 0xfd, 0, 0], &mut out, 0).is_err());
        assert!(decode(Codec::Raw, &[0; 63], &mut out, 0).is_err());
        // Valid frames of the wrong decoded size: too short, and too long for the buffer.
        for big in [32usize, 65] {
            let data = vec![1u8; big];
            assert!(decode(Codec::Lz4, &lz4_flex::block::compress(&data), &mut out, 0).is_err());
            assert!(decode(
                Codec::Zstd,
                &zstd::bulk::compress(&data, 3).unwrap(),
                &mut out,
                0
            )
            .is_err());
        }
    }

    #[test]
    fn decode_new_gives_what_decode_does_and_rejects_the_same() {
        let mut smooth = vec![0u8; 4096];
        smooth[100..900].fill(200);
        for compression in [Compression::Lz4, Compression::Zstd(3), Compression::None] {
            let (c, p) = encode(&smooth, compression);
            assert_eq!(
                decode_new(c, &p, 4096, 0).unwrap(),
                smooth,
                "{compression:?}"
            );
        }
        assert!(decode_new(Codec::Zstd, &[0x28, 0xb5, 0x2f, 0xfd, 0, 0], 64, 0).is_err());
        // Valid frames of the wrong decoded size: too short, and too long for the buffer.
        for big in [32usize, 65] {
            let frame = zstd::bulk::compress(&vec![1u8; big], 3).unwrap();
            assert!(decode_new(Codec::Zstd, &frame, 64, 0).is_err(), "{big}");
            let block = lz4_flex::block::compress(&vec![1u8; big]);
            assert!(decode_new(Codec::Lz4, &block, 64, 0).is_err(), "{big}");
        }
    }
}
