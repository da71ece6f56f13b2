//! Geometry the volume algebra, the edits and the generators share: boxes of voxels
//! ([`Box3`], defined with the wire types), volumes of tetrahedra, constant fields over boxes.

pub use isovox_proto::geometry::Box3;

/// The signed volume of the tetrahedron (origin, a, b, c): positive when a, b, c turn
/// counter-clockwise seen from the origin's far side. Summed over a closed, outward-wound
/// triangle mesh it is the volume the mesh encloses (the divergence theorem).
pub fn tetra_volume(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
        + a[2] * (b[0] * c[1] - b[1] * c[0]))
        / 6.0
}

/// The one value of every voxel of `b`, for a field that is `low` outside `bbox`, when that is
/// certain without sampling: `low` when `b` misses `bbox`; else `inside`'s answer for the part
/// of `b` within `bbox`, when that part is all of `b` or the answer is `low` anyway.
pub fn constant_over(
    bbox: &Box3,
    b: &Box3,
    low: u16,
    inside: impl FnOnce(&Box3) -> Option<u16>,
) -> Option<u16> {
    let within = b.intersect(bbox);
    if within.is_empty() {
        return Some(low);
    }
    let v = inside(&within)?;
    (within == *b || v == low).then_some(v)
}
