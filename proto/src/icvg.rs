//! ICVG terms and edit requests as JSON (`docs/icvg.md`, "Term JSON").
//!
//! A term is a tree: leaves are primitives placed in the world (level-0 voxel coordinates) or
//! stored volumes; inner nodes are operators. Every variant below serializes as a one-key object
//! (`{"union": [A, B]}`, `{"ellipsoid": {...}}`), exactly the grammar of the spec.

use serde::{Deserialize, Serialize};

/// A CVG term.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Term {
    /// Extension space `size` (every side > 2) starting at `origin`: L padding layer, S surface
    /// layer, H inside.
    Cuboid {
        origin: [i64; 3],
        size: [u32; 3],
    },
    /// Radii `R >= 1`; extension `2R + 1` per axis, centred on `center`.
    Ellipsoid {
        center: [i64; 3],
        radii: [u32; 3],
    },
    /// Axis +y; `base` is the centre of the bottom padding layer; extension
    /// `(2 rx + 1, height, 2 rz + 1)`.
    Cylinder {
        base: [i64; 3],
        radii: [u32; 2],
        height: u32,
    },
    /// Apex up (+y), otherwise placed like the cylinder.
    Cone {
        base: [i64; 3],
        radii: [u32; 2],
        height: u32,
    },
    /// Ring around the +y axis through `center`: `major` is the radius of the tube's centre
    /// circle, `minor` the tube's radius; extension `(2(major + minor) + 1, 2 minor + 1, ...)`.
    Torus {
        center: [i64; 3],
        major: u32,
        minor: u32,
    },
    /// A segment along +y of `length` voxels centred on `center`, swept by a ball of `radius`;
    /// extension `(2 r + 1, 2 ceil(length / 2) + 2 r + 1, 2 r + 1)`, symmetric about `center`.
    Capsule {
        center: [i64; 3],
        radius: u32,
        length: u32,
    },
    /// A wedge: the cuboid `origin`/`size` cut by the plane through its top-left and
    /// bottom-right edges (x-y cross-section a right triangle, extruded along z).
    Prism {
        origin: [i64; 3],
        size: [u32; 3],
    },
    /// A square pyramid: base the bottom of the cuboid `origin`/`size`, apex the centre of its
    /// top.
    Pyramid {
        origin: [i64; 3],
        size: [u32; 3],
    },
    /// Another stored volume's level 0, placed with its voxel (0, 0, 0) at `origin`; with
    /// `region`, only that box of it (min inclusive, max exclusive, in its own voxels), placed
    /// with the region's `min` corner at `origin`.
    Volume {
        name: String,
        origin: [i64; 3],
        #[serde(default, skip_serializing_if = "Option::is_none")]
        region: Option<Region>,
    },
    Union(Box<Term>, Box<Term>),
    Intersection(Box<Term>, Box<Term>),
    Trim(Box<Term>, Box<Term>),
    Cap(Box<Term>, Box<Term>),
    Difference(Box<Term>, Box<Term>),
    DifferenceA(Box<Term>, Box<Term>),
    DifferenceB(Box<Term>, Box<Term>),
    Add(Box<Term>, Box<Term>),
    Modulate(Box<Term>, Box<Term>),
    Product(Box<Term>, Box<Term>),
    DivideA(Box<Term>, Box<Term>),
    Divide {
        s_l: f64,
        args: (Box<Term>, Box<Term>),
    },
    Inverse(Box<Term>),
    /// Same as inverse (CVG's name).
    Complement(Box<Term>),
    AddScalar {
        k: i32,
        arg: Box<Term>,
    },
    /// An uploaded watertight mesh (`POST /v1/meshes`, named by its content hash), placed so
    /// that model point p lands at voxel `p * scale + offset`, as a density (2x2x2 samples per
    /// voxel: H inside, L outside, the fraction inside near the surface).
    Mesh {
        hash: String,
        offset: [f64; 3],
        scale: f64,
    },
    /// Grey-value dilation: the maximum over a box of `radius` voxels around each voxel (a
    /// cube of side 2 * radius + 1); on a binary volume, morphological dilation.
    Dilate {
        radius: u32,
        arg: Box<Term>,
    },
    /// Grey-value erosion: the minimum over the same box.
    Erode {
        radius: u32,
        arg: Box<Term>,
    },
}

/// A box of level-0 voxels: `min` inclusive, `max` exclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Region {
    pub min: [i64; 3],
    pub max: [i64; 3],
}

/// An edit: `op(volume, term)` for a binary operator, or a unary operator on the volume.
///
/// ```json
/// {"op": "difference", "term": {"ellipsoid": {"center": [64, 64, 64], "radii": [16, 16, 16]}}}
/// {"op": "divide", "s_l": 0.5, "term": ...}
/// {"op": "add_scalar", "k": -20, "region": {"min": [0, 0, 0], "max": [32, 32, 32]}}
/// {"op": "inverse"}
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EditRequest {
    pub op: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub term: Option<Term>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub s_l: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub k: Option<i32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<Region>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_examples_parse() {
        let t: Term = serde_json::from_str(
            r#"{"difference": [
                {"cuboid": {"origin": [0, 0, 0], "size": [40, 30, 20]}},
                {"divide": {"s_l": 0.5, "args": [
                    {"ellipsoid": {"center": [20, 15, 10], "radii": [8, 8, 8]}},
                    {"add_scalar": {"k": -20, "arg": {"inverse": {"cone": {"base": [5, 0, 5], "radii": [3, 3], "height": 9}}}}}
                ]}}
            ]}"#,
        )
        .unwrap();
        let Term::Difference(a, b) = &t else {
            panic!("not a difference: {t:?}")
        };
        assert_eq!(
            **a,
            Term::Cuboid {
                origin: [0, 0, 0],
                size: [40, 30, 20]
            }
        );
        assert!(matches!(**b, Term::Divide { s_l, .. } if s_l == 0.5));
        let back: Term = serde_json::from_str(&serde_json::to_string(&t).unwrap()).unwrap();
        assert_eq!(back, t);
        let e: EditRequest = serde_json::from_str(
            r#"{"op": "add_scalar", "k": 5, "region": {"min": [0,0,0], "max": [4,4,4]}}"#,
        )
        .unwrap();
        assert_eq!(e.k, Some(5));
        assert!(serde_json::from_str::<Term>(r#"{"blob": {}}"#).is_err());
        assert!(serde_json::from_str::<Term>(
            r#"{"cuboid": {"origin": [0,0,0], "size": [4,4,4], "x": 1}}"#
        )
        .is_err());
    }
}
