//! Grey-value morphology: the maximum (dilate) or minimum (erode) over a cube window of side
//! `2r + 1`, computed so that its cost does not depend on the radius.
//!
//! The cube filter is separable: three one-dimensional passes (x, then y, then z). Each pass is
//! the van Herk / Gil-Werman running maximum: the line is cut into blocks of the window's width
//! `w`, and the maximum over any window is the larger of a suffix maximum of one block and a
//! prefix maximum of the next, so every voxel costs three comparisons whatever `r` is.
//!
//! Memory stays near the output's size: the argument is evaluated slab by slab (a few planes of
//! the input box at a time, in parallel); the x and y passes shrink each plane to the output's
//! width and depth at once, so only the planes of `output.xy x input.z` are kept for the z pass.
//!
//! Boxes: for an output box `out`, the input is `out` grown by `r`. Outside its B-box the
//! argument is L, so a dilation needs it only over the input box clipped to that B-box (L is
//! the identity of max: the rest is padding), and an erosion is L wherever its window leaves
//! the B-box (so its own B-box is the argument's shrunk by `r`, and its input lies inside the
//! argument's B-box). [`boxes`] computes both boxes; [`filter`] the values.

use super::term::{CompiledTerm, EvalError};
use crate::cancel::CancelToken;
use crate::geometry::Box3;
use rayon::prelude::*;

/// Input voxels evaluated per slab (one job): about 4 MiB of u16.
const SLAB_VOXELS: u128 = 1 << 21;

/// The output box and the input box (the argument's voxels needed) of a morphology node
/// evaluated over `b`: `None` when the node is L all over `b`.
pub fn boxes(
    b: &Box3,
    node_bbox: Option<Box3>,
    arg_bbox: Option<Box3>,
    r: u32,
    dilate: bool,
) -> Option<(Box3, Box3)> {
    let out = node_bbox.map_or(*b, |bb| b.intersect(&bb));
    if out.is_empty() {
        return None;
    }
    let mut input = out.grow(r as i64);
    if dilate {
        if let Some(a) = arg_bbox {
            input = input.intersect(&a);
        }
    }
    (!input.is_empty()).then_some((out, input))
}

/// What filtering over `out` from `input` samples and holds, in voxels: the argument's values
/// over `input`, and the planes of `out.xy` for every input z kept for the z pass.
pub fn cost(out: &Box3, input: &Box3) -> u128 {
    let (o, i) = (size(out), size(input));
    input.voxels() + (o[0] * o[1]) as u128 * i[2] as u128
}

/// The B-box of `erode(arg, r)`: the argument's shrunk by `r` (maybe empty).
pub fn eroded_bbox(arg: Box3, r: u32) -> Box3 {
    arg.grow(-(r as i64))
}

fn size(b: &Box3) -> [usize; 3] {
    [0, 1, 2].map(|a| (b.max[a] - b.min[a]).max(0) as usize)
}

/// The morphology of `arg` over `out` (x fastest), from its values over `input` (see
/// [`boxes`]; `input` within `out` grown by `r`, L assumed elsewhere).
///
/// # Errors
/// The argument fails to evaluate, or `cancel` stops the work.
pub fn filter(
    arg: &CompiledTerm,
    out: &Box3,
    input: &Box3,
    r: u32,
    dilate: bool,
    cancel: &CancelToken,
) -> Result<Vec<u16>, EvalError> {
    let low = arg.voxel_type.low();
    let (no, ni) = (size(out), size(input));
    let r = r as usize;
    // Where the input starts in each axis's padded line, which begins at out.min - r.
    let shift = [0, 1, 2].map(|a| (input.min[a] - (out.min[a] - r as i64)) as usize);
    let plane_in = ni[0] * ni[1];
    let plane_out = no[0] * no[1];
    let slab = ((SLAB_VOXELS / plane_in.max(1) as u128) as usize).clamp(1, ni[2].max(1));
    // The x and y passes, slab by slab: planes of out.xy for every input z.
    let mut planes = vec![low; plane_out * ni[2]];
    planes
        .par_chunks_mut(plane_out * slab)
        .enumerate()
        .try_for_each(|(s, chunk)| -> Result<(), EvalError> {
            cancel.check()?;
            let z0 = input.min[2] + (s * slab) as i64;
            let depth = chunk.len() / plane_out.max(1);
            let mut values = vec![0u16; plane_in * depth];
            let part = Box3::new(
                [input.min[0], input.min[1], z0],
                [input.max[0], input.max[1], z0 + depth as i64],
            );
            arg.eval(&part, &mut values)?;
            let mut line = Line::new(dilate, low);
            let mut rows = vec![low; no[0] * ni[1]];
            for (src, dst) in values.chunks(plane_in).zip(chunk.chunks_mut(plane_out)) {
                cancel.check()?;
                for (y, row) in rows.chunks_mut(no[0]).enumerate() {
                    let at = y * ni[0];
                    line.run(&src[at..at + ni[0]], shift[0], no[0], r);
                    row.copy_from_slice(line.result(no[0]));
                }
                let mut column = Vec::with_capacity(ni[1]);
                for x in 0..no[0] {
                    column.clear();
                    column.extend((0..ni[1]).map(|y| rows[y * no[0] + x]));
                    line.run(&column, shift[1], no[1], r);
                    for (y, &v) in line.result(no[1]).iter().enumerate() {
                        dst[y * no[0] + x] = v;
                    }
                }
            }
            Ok(())
        })?;
    // The z pass, a band of output rows (fixed y) at a time.
    let mut result = vec![low; plane_out * no[2]];
    let band = 16;
    for y0 in (0..no[1]).step_by(band) {
        cancel.check()?;
        let ys = y0..(y0 + band).min(no[1]);
        let bands: Vec<Vec<u16>> = ys
            .clone()
            .into_par_iter()
            .map(|y| {
                let mut line = Line::new(dilate, low);
                let mut rows = vec![low; no[0] * no[2]];
                // Row y of every plane, side by side: the columns then read a small block
                // instead of striding through all the planes once per column.
                let mut block = Vec::with_capacity(no[0] * ni[2]);
                for z in 0..ni[2] {
                    let at = z * plane_out + y * no[0];
                    block.extend_from_slice(&planes[at..at + no[0]]);
                }
                let mut column = Vec::with_capacity(ni[2]);
                for x in 0..no[0] {
                    column.clear();
                    column.extend((0..ni[2]).map(|z| block[z * no[0] + x]));
                    line.run(&column, shift[2], no[2], r);
                    for (z, &v) in line.result(no[2]).iter().enumerate() {
                        rows[z * no[0] + x] = v;
                    }
                }
                rows
            })
            .collect();
        for (y, rows) in ys.zip(bands) {
            for (z, row) in rows.chunks(no[0]).enumerate() {
                let at = z * plane_out + y * no[0];
                result[at..at + no[0]].copy_from_slice(row);
            }
        }
    }
    Ok(result)
}

/// One line's running maximum (or minimum) over windows of `2r + 1`, with its buffers.
struct Line {
    dilate: bool,
    low: u16,
    padded: Vec<u16>,
    prefix: Vec<u16>,
    suffix: Vec<u16>,
    out: Vec<u16>,
}

impl Line {
    fn new(dilate: bool, low: u16) -> Line {
        Line {
            dilate,
            low,
            padded: Vec::new(),
            prefix: Vec::new(),
            suffix: Vec::new(),
            out: Vec::new(),
        }
    }

    fn pick(&self, a: u16, b: u16) -> u16 {
        if self.dilate {
            a.max(b)
        } else {
            a.min(b)
        }
    }

    /// Filters `input` placed at `shift` in a line of `n + 2r` voxels (L elsewhere): output `k`
    /// is the pick over padded voxels `k..=k + 2r`.
    fn run(&mut self, input: &[u16], shift: usize, n: usize, r: usize) {
        let w = 2 * r + 1;
        let len = n + 2 * r;
        self.padded.clear();
        self.padded.resize(len, self.low);
        self.padded[shift..shift + input.len()].copy_from_slice(input);
        self.prefix.resize(len, 0);
        self.suffix.resize(len, 0);
        for i in 0..len {
            let v = self.padded[i];
            self.prefix[i] = if i % w == 0 {
                v
            } else {
                self.pick(self.prefix[i - 1], v)
            };
        }
        for i in (0..len).rev() {
            let v = self.padded[i];
            self.suffix[i] = if i + 1 == len || (i + 1) % w == 0 {
                v
            } else {
                self.pick(self.suffix[i + 1], v)
            };
        }
        self.out.clear();
        for k in 0..n {
            let v = self.pick(self.suffix[k], self.prefix[k + w - 1]);
            self.out.push(v);
        }
    }

    fn result(&self, n: usize) -> &[u16] {
        &self.out[..n]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The window maximum of a line by brute force.
    fn brute(padded: &[u16], n: usize, r: usize, dilate: bool) -> Vec<u16> {
        (0..n)
            .map(|k| {
                let w = &padded[k..=k + 2 * r];
                if dilate {
                    *w.iter().max().unwrap_or(&0)
                } else {
                    *w.iter().min().unwrap_or(&0)
                }
            })
            .collect()
    }

    #[test]
    fn running_filter_equals_brute_force() {
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed % 256) as u16
        };
        for r in [1usize, 2, 3, 5, 8, 13] {
            for n in [1usize, 2, 7, 16, 31, 64] {
                for dilate in [true, false] {
                    for input_len in [0, 1, n, n + 2 * r] {
                        for shift in [0, r, 2 * r] {
                            if shift + input_len > n + 2 * r {
                                continue;
                            }
                            let input: Vec<u16> = (0..input_len).map(|_| next()).collect();
                            let mut padded = vec![3u16; n + 2 * r];
                            padded[shift..shift + input_len].copy_from_slice(&input);
                            let mut line = Line::new(dilate, 3);
                            line.run(&input, shift, n, r);
                            assert_eq!(
                                line.result(n),
                                brute(&padded, n, r, dilate).as_slice(),
                                "r {r} n {n} dilate {dilate} len {input_len} shift {shift}"
                            );
                        }
                    }
                }
            }
        }
    }
}
