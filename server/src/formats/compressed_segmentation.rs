//! Neuroglancer's `compressed_segmentation` encoding of a label chunk (uint32 or uint64
//! values), which Neuroglancer draws as a segmentation and tensorstore and cloud-volume decode.
//!
//! The chunk is cut into blocks of [`BLOCK`] voxels (the last ones of an axis padded to a whole
//! block); each block stores the sorted distinct values it holds (its lookup table) and, per
//! voxel, the index of its value in that table, packed in 0, 1, 2, 4, 8, 16 or 32 bits into
//! little-endian 32-bit words; a uint64 table entry takes two words, the low one first. The data
//! starts with one 64-bit header per block, x fastest: the
//! table's offset (24 bits) and the bits per index (8 bits) in the first word, the offset of the
//! packed indices in the second; offsets in 32-bit words from the start of the channel's data.
//! A precomputed chunk holds one such encoding per channel, after one u32 per channel giving
//! where it starts (in words from the chunk's start): here one channel, so the chunk is the word
//! 1 followed by the encoding. Blocks with the same table share one copy of it.
//!
//! [`decode_chunk`] reads the encoding back (the precomputed importer's segmentations, uint32
//! or uint64).
//!
//! No Rust crate implements the encoding (the PyPI `compressed-segmentation` package and
//! tensorstore are C++); this one is checked against both by the formats tests.

use std::collections::HashMap;

/// The block edge, per axis: Neuroglancer's default, and what `info` declares.
pub const BLOCK: [u32; 3] = [8, 8, 8];

/// The precomputed chunk of `values` (one channel of labels, x fastest, then y, then z) of
/// `size` voxels: uint64 when `wide`, else uint32 (every value must then fit a u32).
///
/// # Panics
/// When `values` does not hold `size` voxels: a caller's bug.
pub fn encode_chunk(values: &[u64], size: [u32; 3], wide: bool) -> Vec<u8> {
    assert_eq!(
        values.len(),
        size.iter().map(|&s| s as usize).product::<usize>(),
        "values of a {size:?} chunk"
    );
    let grid = [0, 1, 2].map(|a| size[a].div_ceil(BLOCK[a]));
    let blocks = grid.iter().map(|&g| g as usize).product::<usize>();
    // One channel: its encoding starts after the one offset word.
    let mut words: Vec<u32> = vec![1];
    let start = words.len();
    words.resize(start + 2 * blocks, 0);
    let mut tables: HashMap<Vec<u64>, u32> = HashMap::new();
    let mut block = Vec::with_capacity(BLOCK.iter().map(|&b| b as usize).product());
    let mut i = 0;
    for bz in 0..grid[2] {
        for by in 0..grid[1] {
            for bx in 0..grid[0] {
                block_values(values, size, [bx, by, bz], &mut block);
                let mut table = block.clone();
                table.sort_unstable();
                table.dedup();
                let bits = index_bits(table.len());
                let packed_at = (words.len() - start) as u32;
                pack(&block, &table, bits, &mut words);
                let table_at = match tables.get(&table) {
                    Some(&at) => at,
                    None => {
                        let at = (words.len() - start) as u32;
                        for &v in &table {
                            words.push(v as u32);
                            if wide {
                                words.push((v >> 32) as u32);
                            }
                        }
                        tables.insert(table, at);
                        at
                    }
                };
                words[start + 2 * i] = table_at | (bits << 24);
                words[start + 2 * i + 1] = packed_at;
                i += 1;
            }
        }
    }
    words.iter().flat_map(|w| w.to_le_bytes()).collect()
}

/// The values of block `b` of a chunk of `size`, x fastest, padded past the chunk's far faces
/// with the block's first value (the format lets any value of the block pad it).
fn block_values(values: &[u64], size: [u32; 3], b: [u32; 3], out: &mut Vec<u64>) {
    out.clear();
    let lo = [0, 1, 2].map(|a| b[a] * BLOCK[a]);
    let first = values[index(size, lo)];
    for z in 0..BLOCK[2] {
        for y in 0..BLOCK[1] {
            for x in 0..BLOCK[0] {
                let p = [lo[0] + x, lo[1] + y, lo[2] + z];
                let inside = (0..3).all(|a| p[a] < size[a]);
                out.push(if inside {
                    values[index(size, p)]
                } else {
                    first
                });
            }
        }
    }
}

fn index(size: [u32; 3], p: [u32; 3]) -> usize {
    p[0] as usize + size[0] as usize * (p[1] as usize + size[1] as usize * p[2] as usize)
}

/// Bits per index for a table of `n` values: 0 for one value, else the smallest of 1, 2, 4, 8,
/// 16 and 32 that can count to `n`.
fn index_bits(n: usize) -> u32 {
    if n <= 1 {
        return 0;
    }
    [1, 2, 4, 8, 16, 32]
        .into_iter()
        .find(|&bits| bits == 32 || n <= 1usize << bits)
        .unwrap_or(32)
}

/// Appends the indices of `block`'s values in `table`, `bits` each, packed into words from
/// their low bits up.
fn pack(block: &[u64], table: &[u64], bits: u32, words: &mut Vec<u32>) {
    if bits == 0 {
        return;
    }
    let per_word = 32 / bits as usize;
    for group in block.chunks(per_word) {
        let mut word = 0u32;
        for (j, v) in group.iter().enumerate() {
            // The table is sorted and holds every value of the block.
            let k = table.binary_search(v).unwrap_or(0) as u32;
            word |= k << (j as u32 * bits);
        }
        words.push(word);
    }
}

/// The values of a precomputed chunk of `size` voxels (x fastest, then y, then z) in the
/// encoding with blocks of `block` voxels, one channel; `wide` for uint64 values (two words
/// per table entry, low first), else uint32. Every offset and index is checked against the
/// chunk's words: a hostile or truncated chunk is an error, never a panic or a read past it.
///
/// # Errors
/// What is wrong with the chunk, in words.
pub fn decode_chunk(
    bytes: &[u8],
    size: [u32; 3],
    block: [u32; 3],
    wide: bool,
) -> Result<Vec<u64>, String> {
    if !bytes.len().is_multiple_of(4) {
        return Err(format!("{} bytes, not whole 32-bit words", bytes.len()));
    }
    if block.contains(&0) || size.contains(&0) {
        return Err(format!("an empty block {block:?} or chunk {size:?}"));
    }
    let words: Vec<u32> = bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let word = |at: u64| -> Result<u32, String> {
        usize::try_from(at)
            .ok()
            .and_then(|at| words.get(at).copied())
            .ok_or_else(|| format!("an offset past the chunk's {} words", words.len()))
    };
    let base = u64::from(word(0)?);
    let grid = [0, 1, 2].map(|a| size[a].div_ceil(block[a]));
    let per_value = if wide { 2 } else { 1 };
    let mut out = vec![0u64; size.iter().map(|&s| s as usize).product()];
    let mut i = 0u64;
    for bz in 0..grid[2] {
        for by in 0..grid[1] {
            for bx in 0..grid[0] {
                let header = word(base + 2 * i)?;
                let packed_at = base + u64::from(word(base + 2 * i + 1)?);
                let table_at = base + u64::from(header & 0x00ff_ffff);
                let bits = header >> 24;
                if ![0, 1, 2, 4, 8, 16, 32].contains(&bits) {
                    return Err(format!("block {i}: {bits} bits per index"));
                }
                let lo = [bx * block[0], by * block[1], bz * block[2]];
                for z in lo[2]..(lo[2] + block[2]).min(size[2]) {
                    for y in lo[1]..(lo[1] + block[1]).min(size[1]) {
                        for x in lo[0]..(lo[0] + block[0]).min(size[0]) {
                            // The voxel's place in its block, x fastest.
                            let j = u64::from(x - lo[0])
                                + u64::from(block[0])
                                    * (u64::from(y - lo[1])
                                        + u64::from(block[1]) * u64::from(z - lo[2]));
                            let k = if bits == 0 {
                                0
                            } else {
                                let bit = j * u64::from(bits);
                                let w = word(packed_at + bit / 32)?;
                                (u64::from(w) >> (bit % 32)) & ((1u64 << bits) - 1)
                            };
                            let at = table_at + k * per_value;
                            let mut v = u64::from(word(at)?);
                            if wide {
                                v |= u64::from(word(at + 1)?) << 32;
                            }
                            out[index(size, [x, y, z])] = v;
                        }
                    }
                }
                i += 1;
            }
        }
    }
    Ok(out)
}

/// The most bytes a chunk of `size` voxels in blocks of `block` can take: the offset word,
/// two header words per block, 32 bits of index per padded voxel and a table entry per padded
/// voxel (two words each for uint64). What a reader allows before it reads one.
pub fn max_chunk_bytes(size: [u32; 3], block: [u32; 3], wide: bool) -> u64 {
    let grid = [0, 1, 2].map(|a| u64::from(size[a].div_ceil(block[a].max(1))));
    let blocks = grid.iter().product::<u64>();
    let padded = blocks * block.iter().map(|&b| u64::from(b)).product::<u64>();
    4 * (1 + 2 * blocks + padded * if wide { 3 } else { 2 })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(bytes: &[u8]) -> Vec<u32> {
        bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    }

    #[test]
    fn one_value_takes_no_index_bits() {
        // A 2x2x2 chunk of 7s: one block (padded with 7), no packed words, table [7].
        // Words: channel offset 1; header: table at 2 (after the 2 header words), 0 bits;
        // indices at 2 (none); the table.
        let w = words(&encode_chunk(&[7; 8], [2, 2, 2], false));
        assert_eq!(w, vec![1, 2, 2, 7]);
    }

    #[test]
    fn two_values_pack_one_bit_each_x_fastest() {
        // A 8x1x1 chunk 5 9 5 5 9 9 9 5 in one 8x8x8 block: table [5, 9], 1 bit each. The
        // block's 512 voxels are 8 given then padding with the first value (5, index 0): 16
        // words of indices, the first 0b0111_0010 (bits 1, 4, 5, 6 set), the rest 0.
        let w = words(&encode_chunk(&[5, 9, 5, 5, 9, 9, 9, 5], [8, 1, 1], false));
        assert_eq!(w[0], 1);
        // Header: the table after the 16 index words, at 2 + 16 = 18; 1 bit; indices at 2.
        assert_eq!(w[1], 18 | (1 << 24));
        assert_eq!(w[2], 2);
        assert_eq!(w[3], 0b0111_0010);
        assert!(w[4..19].iter().all(|&x| x == 0));
        assert_eq!(&w[19..], &[5, 9]);
    }

    #[test]
    fn blocks_with_the_same_values_share_one_table() {
        // 16x8x8: two blocks, both all 3: two headers, one table. Block 0's (empty) indices
        // and its table start at word 4 of the channel (after the 4 header words); block 1's
        // empty indices start where the words then end (5), its table is block 0's.
        let w = words(&encode_chunk(&vec![3; 16 * 64], [16, 8, 8], false));
        assert_eq!(w, vec![1, 4, 4, 4, 5, 3]);
    }

    #[test]
    fn uint64_tables_take_two_words_low_first() {
        // The 8x1x1 chunk of the one-bit test with 2^40 + 5 and 9: the same header and indices
        // (table [9, 2^40 + 5] sorted, so 2^40 + 5 is index 1), then the table as (lo, hi)
        // pairs: 9, 0, 5, 256. The padding repeats the first value, index 1 here: every bit of
        // the index words past the 8 given voxels is set.
        let big = (1u64 << 40) + 5;
        let w = words(&encode_chunk(
            &[big, 9, big, big, 9, 9, 9, big],
            [8, 1, 1],
            true,
        ));
        assert_eq!(w[1], 18 | (1 << 24));
        assert_eq!(w[3], 0xffff_ff00 | 0b1000_1101);
        assert!(w[4..19].iter().all(|&x| x == u32::MAX));
        assert_eq!(&w[19..], &[9, 0, 5, 256]);
        let back = decode_chunk(
            &w.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<_>>(),
            [8, 1, 1],
            BLOCK,
            true,
        )
        .unwrap();
        assert_eq!(back, [big, 9, big, big, 9, 9, 9, big]);
    }

    #[test]
    fn decoding_reads_hand_made_chunks() {
        // The chunks of the tests above, from their hand-written words.
        let bytes = |w: &[u32]| w.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        assert_eq!(
            decode_chunk(&bytes(&[1, 2, 2, 7]), [2, 2, 2], BLOCK, false),
            Ok(vec![7; 8])
        );
        let mut w = vec![1, 18 | (1 << 24), 2, 0b0111_0010];
        w.extend([0; 15]);
        w.extend([5, 9]);
        assert_eq!(
            decode_chunk(&bytes(&w), [8, 1, 1], BLOCK, false),
            Ok(vec![5, 9, 5, 5, 9, 9, 9, 5])
        );
        // uint64: a table entry is two words, low first; one block of 2x1x1 in blocks of
        // 2x1x1, values 2^40 + 3 and 1, 1 bit each: indices 1, 0 (table sorted: [1, 2^40+3]).
        let w = [1, 3 | (1 << 24), 2, 0b01, 1, 0, 3, 1 << 8];
        assert_eq!(
            decode_chunk(&bytes(&w), [2, 1, 1], [2, 1, 1], true),
            Ok(vec![(1 << 40) + 3, 1])
        );
    }

    #[test]
    fn decoding_gives_back_what_encoding_made() {
        // A chunk that is not whole blocks, with many values per block.
        let size = [13, 9, 17];
        let values: Vec<u64> = (0..13 * 9 * 17).map(|i: u64| (i * 7919) % 300).collect();
        let chunk = encode_chunk(&values, size, false);
        assert!(chunk.len() as u64 <= max_chunk_bytes(size, BLOCK, false));
        let back = decode_chunk(&chunk, size, BLOCK, false).unwrap();
        assert_eq!(back, values);
        let wide: Vec<u64> = values.iter().map(|v| v << 35 | v).collect();
        let chunk = encode_chunk(&wide, size, true);
        assert!(chunk.len() as u64 <= max_chunk_bytes(size, BLOCK, true));
        assert_eq!(decode_chunk(&chunk, size, BLOCK, true).unwrap(), wide);
    }

    #[test]
    fn hostile_chunks_are_errors() {
        let bytes = |w: &[u32]| w.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        let cases: [(&[u8], &str); 5] = [
            (&[1, 0, 0], "whole"),
            (&[], "past"),
            (&bytes(&[1, 2, 2]), "past"),
            (&bytes(&[1, 0x00ff_ffff, 2, 7]), "past"),
            (&bytes(&[1, 2 | (3 << 24), 2, 7]), "3 bits"),
        ];
        for (chunk, words) in cases {
            let e = decode_chunk(chunk, [2, 2, 2], BLOCK, false).unwrap_err();
            assert!(e.contains(words), "{e}");
        }
        // An index word past the end: 1 bit per index, indices at word 1000.
        let e = decode_chunk(
            &bytes(&[1, 2 | (1 << 24), 1000, 7, 9]),
            [2, 2, 2],
            BLOCK,
            false,
        )
        .unwrap_err();
        assert!(e.contains("past"), "{e}");
    }

    #[test]
    fn index_bits_are_the_allowed_widths() {
        let cases = [
            (1, 0),
            (2, 1),
            (3, 2),
            (4, 2),
            (5, 4),
            (16, 4),
            (17, 8),
            (256, 8),
        ];
        for (n, bits) in cases {
            assert_eq!(index_bits(n), bits, "{n} values");
        }
        assert_eq!(index_bits(257), 16);
        assert_eq!(index_bits(65537), 32);
    }
}
