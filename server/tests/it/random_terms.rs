//! Random ICVG terms for the property tests (icvg_laws.rs, icvg_edits.rs): primitives of every
//! kind at random placements, and the binary operators by number, so that both suites draw from
//! the same shapes. Nothing here calls the code under test.
#![allow(dead_code)]

use isovox_proto::icvg::Term;
use proptest::prelude::*;

/// A random primitive of any of the eight kinds, placed at `pos`, its extents at most about
/// `extent` voxels (each kind's sizes are fixed fractions of it, so the shapes stay comparable
/// in volume).
pub(crate) fn leaf<P>(pos: P, extent: u32) -> impl Strategy<Value = Term>
where
    P: Strategy<Value = [i64; 3]> + Clone,
{
    let e = extent.max(10);
    prop_oneof![
        (pos.clone(), prop::array::uniform3(3u32..e))
            .prop_map(|(origin, size)| Term::Cuboid { origin, size }),
        (pos.clone(), prop::array::uniform3(1u32..e * 3 / 5))
            .prop_map(|(center, radii)| Term::Ellipsoid { center, radii }),
        (pos.clone(), prop::array::uniform2(1u32..e / 2), 3u32..e).prop_map(
            |(base, radii, height)| Term::Cylinder {
                base,
                radii,
                height,
            }
        ),
        (pos.clone(), prop::array::uniform2(1u32..e / 2), 3u32..e).prop_map(
            |(base, radii, height)| Term::Cone {
                base,
                radii,
                height,
            }
        ),
        // Every radius is at least 1, the ring's too (docs/icvg.md, "Validation").
        (pos.clone(), 1u32..e * 2 / 5, 1u32..e / 4).prop_map(|(center, major, minor)| {
            Term::Torus {
                center,
                major,
                minor,
            }
        }),
        (pos.clone(), 1u32..e / 3, 0u32..e / 2).prop_map(|(center, radius, length)| {
            Term::Capsule {
                center,
                radius,
                length,
            }
        }),
        (pos.clone(), prop::array::uniform3(4u32..e * 4 / 5))
            .prop_map(|(origin, size)| Term::Prism { origin, size }),
        (pos, prop::array::uniform3(4u32..e * 4 / 5))
            .prop_map(|(origin, size)| Term::Pyramid { origin, size }),
    ]
}

/// Binary operator number `which % 12` applied to `a` and `b`, in the order of the spec's table
/// (11 is the two-sided division with threshold `s_l`).
pub(crate) fn binary(which: u8, a: Term, b: Term, s_l: f64) -> Term {
    let (a, b) = (Box::new(a), Box::new(b));
    match which % 12 {
        0 => Term::Union(a, b),
        1 => Term::Intersection(a, b),
        2 => Term::Trim(a, b),
        3 => Term::Cap(a, b),
        4 => Term::Difference(a, b),
        5 => Term::DifferenceA(a, b),
        6 => Term::DifferenceB(a, b),
        7 => Term::Add(a, b),
        8 => Term::Modulate(a, b),
        9 => Term::Product(a, b),
        10 => Term::DivideA(a, b),
        _ => Term::Divide { s_l, args: (a, b) },
    }
}
