//! The marching-cubes kernel against its oracle: `Kernel::Rows` (rows of cells classified a word
//! at a time) must give exactly the mesh of `Kernel::Reference` (the cell-by-cell kernel it
//! replaced) on random fields: the same vertex on every crossed edge (position and normal bit
//! for bit), the same triangles with the same winding, the same border vertices, and the same
//! answers to `vertex_on_edge` (which the transition strips read). Fields of random size (rows
//! longer than one 64-bit word included), with flat regions, values equal to the iso value,
//! and meshes appended to a mesh that already holds vertices.

use crate::common::XorShift;
use isovox_server::mesh::mc::{march, BorderVertex, Field, Kernel, Mesh, Sample, Scratch};
use proptest::prelude::*;
use std::collections::HashMap;

/// How a random field's values are made.
#[derive(Debug, Clone, Copy)]
enum Values {
    /// Each sample one of 0, 1, 2, 3: values equal to integer iso values, ties everywhere.
    Levels,
    /// A constant background with a few boxes of other levels: large flat regions.
    Blobs,
    /// Uniform noise in [0, 1).
    Noise,
    /// A sphere's distance mapped to 0..=255, rounded: a smooth surface with plateaus.
    Sphere,
}

fn make_values(kind: Values, size: [usize; 3], seed: u64) -> Vec<f32> {
    let mut rng = XorShift(seed | 1);
    let count = size.iter().product::<usize>();
    match kind {
        Values::Levels => (0..count).map(|_| rng.below(4) as f32).collect(),
        Values::Noise => (0..count)
            .map(|_| (rng.next() >> 40) as f32 / (1u64 << 24) as f32)
            .collect(),
        Values::Blobs => {
            let mut v = vec![rng.below(4) as f32; count];
            for _ in 0..rng.below(5) {
                let from = size.map(|s| rng.below(s as u64) as usize);
                let to = [0, 1, 2].map(|a| from[a] + 1 + rng.below(size[a] as u64) as usize);
                let level = rng.below(4) as f32;
                for z in from[2]..to[2].min(size[2]) {
                    for y in from[1]..to[1].min(size[1]) {
                        for x in from[0]..to[0].min(size[0]) {
                            v[(z * size[1] + y) * size[0] + x] = level;
                        }
                    }
                }
            }
            v
        }
        Values::Sphere => {
            let centre = size.map(|s| rng.below(s as u64) as f32 + 0.25);
            let radius = 1.0 + rng.below(10) as f32;
            let mut v = Vec::with_capacity(count);
            for z in 0..size[2] {
                for y in 0..size[1] {
                    for x in 0..size[0] {
                        let d = [x, y, z].map(|c| c as f32);
                        let r = (0..3)
                            .map(|a| (d[a] - centre[a]).powi(2))
                            .sum::<f32>()
                            .sqrt();
                        v.push((127.5 + 40.0 * (radius - r)).round().clamp(0.0, 255.0));
                    }
                }
            }
            v
        }
    }
}

/// A random marching problem: the field's origin and size, the cells `[lo, hi)` inside it
/// (with the gradient halo), the frame, the iso value, and vertices already in the mesh.
#[derive(Debug, Clone)]
struct Case {
    origin: [i64; 3],
    size: [usize; 3],
    lo: [i64; 3],
    hi: [i64; 3],
    frame: [i64; 3],
    iso: f32,
    values: Vec<f32>,
    prefix: usize,
}

fn cases() -> impl Strategy<Value = Case> {
    let kind = prop_oneof![
        Just(Values::Levels),
        Just(Values::Blobs),
        Just(Values::Noise),
        Just(Values::Sphere),
    ];
    // Cells along x up to 140 (three words per row), fewer along y and z; zero on an axis
    // (no cell at all) now and then.
    let cells = (
        prop_oneof![0usize..3, 1usize..70, 60usize..140],
        0usize..9,
        0usize..9,
    );
    let margins = proptest::array::uniform3(0usize..3);
    let starts = proptest::array::uniform3(-5i64..5);
    (
        kind,
        cells,
        margins,
        starts,
        any::<u64>(),
        0usize..5,
        0usize..8,
    )
        .prop_map(
            |(kind, (nx, ny, nz), margin, origin, seed, iso_pick, prefix)| {
                let n = [nx, ny, nz];
                // The field covers [lo - 1, hi + 1] and `margin` more on the upper side.
                let lo = [0, 1, 2].map(|a| origin[a] + 1 + margin[a] as i64 % 2);
                let hi = [0, 1, 2].map(|a| lo[a] + n[a] as i64);
                let size = [0, 1, 2].map(|a| (hi[a] + 2 - origin[a]) as usize + margin[a]);
                let values = make_values(kind, size, seed);
                let iso = match kind {
                    // Integer iso values equal samples; half-integers do not.
                    Values::Levels | Values::Blobs => [0.5, 1.0, 1.5, 2.0, 3.0][iso_pick],
                    Values::Noise => [0.5, 0.25, 0.75, 0.1, 0.9][iso_pick],
                    Values::Sphere => [127.5, 127.0, 128.0, 100.0, 200.0][iso_pick],
                };
                let frame = [lo[0] - 3, origin[1], 7];
                Case {
                    origin,
                    size,
                    lo,
                    hi,
                    frame,
                    iso,
                    values,
                    prefix,
                }
            },
        )
}

/// Marches `case` with `kernel` into a mesh that already holds `case.prefix` vertices.
fn run(case: &Case, kernel: Kernel) -> (Mesh, Scratch) {
    let field = Field {
        origin: case.origin,
        size: case.size,
        values: &case.values,
    };
    let mut mesh = Mesh::default();
    for i in 0..case.prefix {
        mesh.positions.push([i as f32, -1.0, -1.0]);
        mesh.normals.push([1.0, 0.0, 0.0]);
    }
    let mut scratch = Scratch::new(kernel);
    march(
        &field,
        case.lo,
        case.frame,
        case.hi,
        case.iso,
        &mut mesh,
        &mut scratch,
    );
    (mesh, scratch)
}

/// A triangle rotated so that its least index comes first (same winding).
fn canonical(t: [u32; 3]) -> [u32; 3] {
    let first = (0..3).min_by_key(|&i| t[i]).unwrap_or(0);
    [t[first], t[(first + 1) % 3], t[(first + 2) % 3]]
}

fn bits(v: [f32; 3]) -> [u32; 3] {
    v.map(f32::to_bits)
}

fn check_same_mesh(case: &Case) -> Result<(), TestCaseError> {
    let (old, old_scratch) = run(case, Kernel::Reference);
    let (new, new_scratch) = run(case, Kernel::Rows);
    prop_assert_eq!(new.positions.len(), old.positions.len());
    prop_assert_eq!(new.normals.len(), new.positions.len());
    prop_assert_eq!(new.indices.len(), old.indices.len());
    // The vertices already in the mesh stay where they were.
    prop_assert_eq!(&new.positions[..case.prefix], &old.positions[..case.prefix]);
    // Every grid edge from a point of [lo - 1, hi + 1]: the same answer from both kernels, and
    // the same vertex; the pairs name every vertex once.
    let mut new_of_old: HashMap<u32, u32> = (0..case.prefix as u32).map(|i| (i, i)).collect();
    for z in case.lo[2] - 1..=case.hi[2] + 1 {
        for y in case.lo[1] - 1..=case.hi[1] + 1 {
            for x in case.lo[0] - 1..=case.hi[0] + 1 {
                for axis in 0..3 {
                    let p = [x, y, z];
                    let (o, n) = (
                        old_scratch.vertex_on_edge(p, axis),
                        new_scratch.vertex_on_edge(p, axis),
                    );
                    prop_assert_eq!(o.is_some(), n.is_some(), "edge {:?} along {}", p, axis);
                    if let (Some(o), Some(n)) = (o, n) {
                        let (o, n) = (o as usize, n as usize);
                        prop_assert_eq!(bits(new.positions[n]), bits(old.positions[o]));
                        prop_assert_eq!(bits(new.normals[n]), bits(old.normals[o]));
                        prop_assert!(new_of_old.insert(o as u32, n as u32).is_none());
                    }
                }
            }
        }
    }
    prop_assert_eq!(new_of_old.len(), old.positions.len());
    // The same triangles, wound the same way.
    let mut want: Vec<[u32; 3]> = old
        .indices
        .chunks_exact(3)
        .map(|t| canonical([t[0], t[1], t[2]].map(|i| new_of_old[&i])))
        .collect();
    let mut got: Vec<[u32; 3]> = new
        .indices
        .chunks_exact(3)
        .map(|t| canonical([t[0], t[1], t[2]]))
        .collect();
    want.sort_unstable();
    got.sort_unstable();
    prop_assert_eq!(got, want);
    // The same border vertices.
    let key = |b: &BorderVertex| (b.p0, b.axis);
    let mut want: Vec<BorderVertex> = old_scratch
        .border
        .iter()
        .map(|b| BorderVertex {
            id: new_of_old[&b.id],
            ..*b
        })
        .collect();
    let mut got = new_scratch.border.clone();
    want.sort_by_key(key);
    got.sort_by_key(key);
    prop_assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(&want) {
        prop_assert_eq!((g.id, g.p0, g.axis, g.faces), (w.id, w.p0, w.axis, w.faces));
        prop_assert_eq!(g.t.to_bits(), w.t.to_bits());
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    #[test]
    fn rows_kernel_gives_the_reference_mesh(case in cases()) {
        check_same_mesh(&case)?;
    }
}

/// A field with every sample equal to the iso value: all inside, no surface.
#[test]
fn samples_equal_to_the_iso_value_are_inside() {
    let values = vec![2.0f32; 8 * 8 * 8];
    let field = Field {
        origin: [0; 3],
        size: [8; 3],
        values: &values,
    };
    for kernel in [Kernel::Rows, Kernel::Reference] {
        let mut mesh = Mesh::default();
        let mut scratch = Scratch::new(kernel);
        march(&field, [1; 3], [0; 3], [6; 3], 2.0, &mut mesh, &mut scratch);
        assert!(
            mesh.positions.is_empty() && mesh.indices.is_empty(),
            "{kernel:?}"
        );
    }
}

/// After `forget`, no edge has a vertex, whichever kernel marched.
#[test]
fn forget_drops_the_vertices_of_the_last_march() {
    let mut values = vec![0f32; 6 * 6 * 6];
    values[(3 * 6 + 3) * 6 + 3] = 1.0;
    let field = Field {
        origin: [0; 3],
        size: [6; 3],
        values: &values,
    };
    for kernel in [Kernel::Rows, Kernel::Reference] {
        let mut mesh = Mesh::default();
        let mut scratch = Scratch::new(kernel);
        march(&field, [1; 3], [0; 3], [4; 3], 0.5, &mut mesh, &mut scratch);
        // The single inside sample at (3, 3, 3): six crossed edges around it.
        assert_eq!(mesh.positions.len(), 6, "{kernel:?}");
        assert!(scratch.vertex_on_edge([3, 3, 3], 0).is_some());
        assert!(scratch.vertex_on_edge([2, 3, 3], 0).is_some());
        assert!(scratch.vertex_on_edge([3, 3, 2], 2).is_some());
        assert!(scratch.vertex_on_edge([3, 3, 3], 1).is_some());
        assert!(scratch.vertex_on_edge([1, 1, 1], 0).is_none());
        scratch.forget();
        assert!(scratch.vertex_on_edge([3, 3, 3], 0).is_none(), "{kernel:?}");
        assert!(scratch.border.is_empty());
    }
}

/// Marches `values` (integer voxels, or their f32 copy) with `kernel`.
fn march_samples<S: Sample>(
    case: &Case,
    values: &[S],
    iso: f32,
    kernel: Kernel,
) -> (Mesh, Scratch) {
    let field = Field {
        origin: case.origin,
        size: case.size,
        values,
    };
    let (mut mesh, mut scratch) = (Mesh::default(), Scratch::new(kernel));
    march(
        &field,
        case.lo,
        case.frame,
        case.hi,
        iso,
        &mut mesh,
        &mut scratch,
    );
    (mesh, scratch)
}

/// The same mesh, bit for bit and in the same order: vertices, triangles, border vertices.
fn check_identical(a: &(Mesh, Scratch), b: &(Mesh, Scratch)) -> Result<(), TestCaseError> {
    let positions = |m: &Mesh| m.positions.iter().map(|&p| bits(p)).collect::<Vec<_>>();
    let normals = |m: &Mesh| m.normals.iter().map(|&n| bits(n)).collect::<Vec<_>>();
    prop_assert_eq!(positions(&a.0), positions(&b.0));
    prop_assert_eq!(normals(&a.0), normals(&b.0));
    prop_assert_eq!(&a.0.indices, &b.0.indices);
    let border = |s: &Scratch| {
        s.border
            .iter()
            .map(|v| (v.id, v.p0, v.axis, v.t.to_bits(), v.faces))
            .collect::<Vec<_>>()
    };
    prop_assert_eq!(border(&a.1), border(&b.1));
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    /// Level-0 tiles march their voxels as stored (u8, u16) instead of a copy in f32: the
    /// same fields as integers give the same meshes as their f32 values, for every iso value
    /// (between samples, on them, below and above every voxel, NaN).
    #[test]
    fn integer_samples_give_the_f32_mesh(
        case in cases(),
        iso in prop_oneof![-2.0f32..300.0, Just(0.0f32), Just(255.0), Just(255.5), Just(f32::NAN), 60000.0f32..70000.0],
        use_case_iso in any::<bool>(),
    ) {
        // The field as integers 0..=255 (noise in [0, 1) spread over them).
        let spread = case.values.iter().any(|v| v.fract() != 0.0);
        let bytes: Vec<u8> = case
            .values
            .iter()
            .map(|&v| if spread { (v * 255.0).round() } else { v } as u8)
            .collect();
        let iso = match (use_case_iso, spread) {
            (true, true) => case.iso * 255.0,
            (true, false) => case.iso,
            (false, _) => iso,
        };
        for kernel in [Kernel::Rows, Kernel::Reference] {
            let floats: Vec<f32> = bytes.iter().map(|&v| f32::from(v)).collect();
            check_identical(
                &march_samples(&case, &bytes, iso, kernel),
                &march_samples(&case, &floats, iso, kernel),
            )?;
            // As u16 voxels spread over the whole range (257 v), and the iso value with them.
            let words: Vec<u16> = bytes.iter().map(|&v| u16::from(v) * 257).collect();
            let floats: Vec<f32> = words.iter().map(|&v| f32::from(v)).collect();
            let iso = if iso.is_nan() { iso } else { iso * 257.0 };
            check_identical(
                &march_samples(&case, &words, iso, kernel),
                &march_samples(&case, &floats, iso, kernel),
            )?;
        }
    }
}
