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

/// Encodes the bytes of a brick of `voxel_type` with `compression`: as [`encode`], except that
/// a u32 or u64 brick compressed with zstd is stored with the palette codec when that is
/// smaller ([`palette_encode`]): a label brick holds a few distinct ids of 4 or 8 bytes each,
/// which one byte of index per voxel names.
pub fn encode_typed(
    bytes: &[u8],
    voxel_type: VoxelType,
    compression: Compression,
) -> (Codec, Vec<u8>) {
    let plain = encode(bytes, compression);
    let Compression::Zstd(level) = compression else {
        return plain;
    };
    if !voxel_type.is_wide() {
        return plain;
    }
    match palette_encode(bytes, voxel_type, level) {
        Some(p) if p.len() < plain.1.len() => (Codec::Palette, p),
        _ => plain,
    }
}

/// The palette codec's frame of a brick of `voxel_type`: a zstd frame (at `level`) of an
/// 8-byte header (u8 value width, u8 index width, u16 zero, u32 palette length k), the k
/// distinct values ascending (little endian, of the type's width), then each voxel's index in
/// them, 1, 2 or 4 bytes (the fewest that count to k). `None` when the indices would be no
/// narrower than the values.
pub fn palette_encode(bytes: &[u8], voxel_type: VoxelType, level: i32) -> Option<Vec<u8>> {
    let value = |i: usize| isovox_proto::voxel::value_at(bytes, voxel_type, i);
    let width = voxel_type.bytes();
    let n = bytes.len() / width;
    let mut palette: Vec<u64> = (0..n).map(value).collect();
    palette.sort_unstable();
    palette.dedup();
    let index_width = palette_index_width(palette.len());
    if index_width >= width {
        return None;
    }
    let mut plain = Vec::with_capacity(8 + palette.len() * width + n * index_width);
    plain.extend_from_slice(&[width as u8, index_width as u8, 0, 0]);
    plain.extend_from_slice(&(palette.len() as u32).to_le_bytes());
    for v in &palette {
        plain.extend_from_slice(&v.to_le_bytes()[..width]);
    }
    // Runs of one value are the rule: look an index up only where the value changes.
    let mut last = (u64::MAX, 0usize);
    for i in 0..n {
        let v = value(i);
        if v != last.0 || i == 0 {
            last = (v, palette.binary_search(&v).unwrap_or(0));
        }
        plain.extend_from_slice(&(last.1 as u32).to_le_bytes()[..index_width]);
    }
    zstd_compress(&plain, level)
}

/// Bytes per index into a palette of `k` values.
fn palette_index_width(k: usize) -> usize {
    match k {
        0..=256 => 1,
        257..=65_536 => 2,
        _ => 4,
    }
}

/// Decodes a palette frame ([`palette_encode`]) into `out`, checking every field against
/// `out`'s size: a frame that decodes to more than the largest well-formed one is refused
/// without being decoded further.
fn palette_decode(payload: &[u8], out: &mut [u8], offset: u64) -> Result<(), StoreError> {
    let bad = |detail: String| StoreError::corrupt(offset, "a palette frame", detail);
    let header = |plain: &[u8]| -> Option<(usize, usize, usize)> {
        let h = plain.get(..8)?;
        let k = u32::from_le_bytes([h[4], h[5], h[6], h[7]]) as usize;
        Some((h[0] as usize, h[1] as usize, k))
    };
    // The largest well-formed frame: a palette of one value per voxel (the brick's bytes) and
    // 4-byte indices for voxels of 4 bytes or more (the brick's bytes again).
    let mut plain = Vec::with_capacity(8 + 2 * out.len());
    zstd_decode(payload, &mut plain, offset)?;
    let (width, index_width, k) =
        header(&plain).ok_or_else(|| bad("one shorter than its header".into()))?;
    if !matches!(width, 4 | 8) || !out.len().is_multiple_of(width) {
        return Err(bad(format!(
            "values of {width} bytes in a brick of {} bytes",
            out.len()
        )));
    }
    let n = out.len() / width;
    if k == 0 || k > n || index_width != palette_index_width(k) {
        return Err(bad(format!(
            "{k} values with indices of {index_width} bytes for {n} voxels"
        )));
    }
    let (values, indices) = plain[8..]
        .split_at_checked(k * width)
        .ok_or_else(|| bad(format!("a palette of {k} values cut short")))?;
    if indices.len() != n * index_width {
        return Err(bad(format!(
            "{} bytes of indices for {n} voxels of {index_width}",
            indices.len()
        )));
    }
    for (i, dst) in out.chunks_exact_mut(width).enumerate() {
        let mut at = [0u8; 4];
        at[..index_width].copy_from_slice(&indices[i * index_width..(i + 1) * index_width]);
        let at = u32::from_le_bytes(at) as usize;
        let v = values
            .get(at * width..(at + 1) * width)
            .ok_or_else(|| bad(format!("index {at} past its {k} values")))?;
        dst.copy_from_slice(v);
    }
    Ok(())
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
        Codec::Raw | Codec::Lz4 | Codec::Palette => {
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
        Codec::Palette => {
            palette_decode(payload, out, offset)?;
            out.len()
        }
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

    /// A u64 brick of `n` voxels cycling through `ids` in runs of `run`.
    fn labels(n: usize, ids: &[u64], run: usize) -> Vec<u8> {
        (0..n)
            .flat_map(|i| ids[i / run % ids.len()].to_le_bytes())
            .collect()
    }

    #[test]
    fn a_palette_frame_is_laid_out_as_documented_and_decodes_back() {
        // Voxels 7, 7, 2^40, 7 (u64): palette [7, 2^40], one-byte indices 0 0 1 0.
        let bytes = labels(4, &[7, 7, 1 << 40, 7], 1);
        let frame = palette_encode(&bytes, VoxelType::U64, 3).unwrap();
        let plain = zstd::bulk::decompress(&frame, 1 << 10).unwrap();
        let mut want = vec![8, 1, 0, 0, 2, 0, 0, 0];
        want.extend(7u64.to_le_bytes());
        want.extend((1u64 << 40).to_le_bytes());
        want.extend([0, 0, 1, 0]);
        assert_eq!(plain, want);
        let mut out = vec![0u8; bytes.len()];
        decode(Codec::Palette, &frame, &mut out, 0).unwrap();
        assert_eq!(out, bytes);
        // 300 distinct u32 values: two-byte indices; u32 with 70,000 would need four, as wide
        // as the values: no palette.
        let many: Vec<u8> = (0..4096u32)
            .flat_map(|i| (i % 300 * 1000).to_le_bytes())
            .collect();
        let frame = palette_encode(&many, VoxelType::U32, 3).unwrap();
        assert_eq!(zstd::bulk::decompress(&frame, 1 << 20).unwrap()[1], 2);
        assert_eq!(
            decode_new(Codec::Palette, &frame, many.len(), 0).unwrap(),
            many
        );
        let wide: Vec<u8> = (0..70_000u32).flat_map(u32::to_le_bytes).collect();
        assert_eq!(palette_encode(&wide, VoxelType::U32, 3), None);
    }

    #[test]
    fn label_bricks_take_the_palette_codec_where_it_is_smaller() {
        let bytes = labels(32 * 32 * 32, &[(1 << 50) + 3, 9, (1 << 33) + 1], 700);
        let (codec, payload) = encode_typed(&bytes, VoxelType::U64, Compression::Zstd(15));
        assert_eq!(codec, Codec::Palette);
        assert!(payload.len() < encode(&bytes, Compression::Zstd(15)).1.len());
        assert_eq!(decode_new(codec, &payload, bytes.len(), 0).unwrap(), bytes);
        // u8 and u16 streams never do (revision-5 readers read them); nor lz4.
        let narrow: Vec<u8> = bytes.chunks_exact(4).map(|c| c[0]).collect();
        assert_ne!(
            encode_typed(&narrow, VoxelType::U16, Compression::Zstd(15)).0,
            Codec::Palette
        );
        assert_eq!(
            encode_typed(&bytes, VoxelType::U64, Compression::Lz4).0,
            Codec::Lz4
        );
    }

    #[test]
    fn damaged_palette_frames_are_errors() {
        let frame = |plain: &[u8]| zstd::bulk::compress(plain, 1).unwrap();
        let mut out = vec![0u8; 32];
        // Four u64 voxels: an index past the palette, a palette longer than the brick, a width
        // that is not the codec's, indices cut short, a frame past the largest well-formed one.
        let mut past = vec![8, 1, 0, 0, 1, 0, 0, 0];
        past.extend(5u64.to_le_bytes());
        past.extend([0, 0, 1, 0]);
        let mut long = vec![8, 1, 0, 0, 5, 0, 0, 0];
        long.extend([0u8; 5 * 8 + 4]);
        let mut two = vec![2, 1, 0, 0, 1, 0, 0, 0];
        two.extend([0u8; 2 + 16]);
        let mut short = vec![8, 1, 0, 0, 1, 0, 0, 0];
        short.extend(5u64.to_le_bytes());
        short.extend([0, 0, 0]);
        let huge = vec![0u8; 1 << 16];
        for (what, plain) in [
            ("past", past),
            ("long", long),
            ("two", two),
            ("short", short),
            ("huge", huge),
        ] {
            let e = decode(Codec::Palette, &frame(&plain), &mut out, 77).unwrap_err();
            assert!(matches!(e, StoreError::Corrupt { .. }), "{what}: {e}");
        }
    }

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
