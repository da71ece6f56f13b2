//! ICVG terms and edit requests as JSON (`docs/icvg.md`, "Term JSON").
//!
//! A term is a tree: leaves are primitives placed in the world (level-0 voxel coordinates) or
//! stored volumes; inner nodes are operators. Every variant below serializes as a one-key object
//! (`{"union": [A, B]}`, `{"ellipsoid": {...}}`), exactly the grammar of the spec.

use crate::geometry::Box3;
use serde::{Deserialize, Serialize};

/// The largest magnitude of a placed coordinate (a primitive's origin, centre or base, a volume
/// leaf's origin, a region's corners): 2^53, so every JSON client carries it exactly
/// (JavaScript's numbers included), far beyond any volume (whose dims are u32), and far from
/// overflowing the i64 arithmetic of boxes grown by any radius.
pub const MAX_COORDINATE: i64 = 1 << 53;

/// A CVG term.
///
/// Every leaf object may also carry attributes (`"material": N`, `"label": N`): values of the
/// volume's attribute channels where the leaf is what the operators keep (`docs/channels.md`).
/// In Rust a leaf with attributes is [`Term::Attributed`] around the leaf; on the wire the
/// attributes are fields of the leaf's own object.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", rename_all = "snake_case", deny_unknown_fields)]
pub enum Term {
    /// Extension space `size` (every side > 2) starting at `origin`: L padding layer, S surface
    /// layer, H inside.
    Cuboid {
        /// The first voxel of its extension space.
        origin: [i64; 3],
        /// The extension space's size (every side > 2).
        size: [u32; 3],
    },
    /// Radii `R >= 1`; extension `2R + 1` per axis, centred on `center`.
    Ellipsoid {
        /// The centre voxel.
        center: [i64; 3],
        /// The radii along x, y, z (each at least 1).
        radii: [u32; 3],
    },
    /// Axis +y; `base` is the centre of the bottom padding layer; extension
    /// `(2 rx + 1, height, 2 rz + 1)`.
    Cylinder {
        /// The centre of the bottom padding layer.
        base: [i64; 3],
        /// The radii along x and z.
        radii: [u32; 2],
        /// The height along +y (at least 3).
        height: u32,
    },
    /// Apex up (+y), otherwise placed like the cylinder.
    Cone {
        /// The centre of the bottom padding layer.
        base: [i64; 3],
        /// The base's radii along x and z.
        radii: [u32; 2],
        /// The height along +y, apex at the top (at least 3).
        height: u32,
    },
    /// Ring around the +y axis through `center`: `major` is the radius of the tube's centre
    /// circle, `minor` the tube's radius; extension `(2(major + minor) + 1, 2 minor + 1, ...)`.
    Torus {
        /// The centre of the ring.
        center: [i64; 3],
        /// The radius of the tube's centre circle (at least 1).
        major: u32,
        /// The tube's radius (at least 1).
        minor: u32,
    },
    /// A segment along +y of `length` voxels centred on `center`, swept by a ball of `radius`;
    /// extension `(2 r + 1, 2 ceil(length / 2) + 2 r + 1, 2 r + 1)`, symmetric about `center`.
    Capsule {
        /// The centre of the segment.
        center: [i64; 3],
        /// The ball's radius (at least 1).
        radius: u32,
        /// The segment's length along +y.
        length: u32,
    },
    /// A wedge: the cuboid `origin`/`size` cut by the plane through its top-left and
    /// bottom-right edges (x-y cross-section a right triangle, extruded along z).
    Prism {
        /// The first voxel of its bounding cuboid.
        origin: [i64; 3],
        /// The bounding cuboid's size (every side at least 4).
        size: [u32; 3],
    },
    /// A square pyramid: base the bottom of the cuboid `origin`/`size`, apex the centre of its
    /// top.
    Pyramid {
        /// The first voxel of its bounding cuboid.
        origin: [i64; 3],
        /// The bounding cuboid's size (every side at least 4).
        size: [u32; 3],
    },
    /// Another stored volume's level 0, placed with its voxel (0, 0, 0) at `origin`; with
    /// `region`, only that box of it (min inclusive, max exclusive, in its own voxels), placed
    /// with the region's `min` corner at `origin`.
    Volume {
        /// The other volume's name (same voxel type).
        name: String,
        /// Where its first voxel (or the region's `min`) lands.
        origin: [i64; 3],
        /// Only this box of it; all of it when absent.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        region: Option<Box3>,
    },
    /// max(D1, D2).
    Union(Box<Term>, Box<Term>),
    /// min(D1, D2).
    Intersection(Box<Term>, Box<Term>),
    /// D1 where D1 >= D2, else L.
    Trim(Box<Term>, Box<Term>),
    /// D1 where D1 <= D2, else L.
    Cap(Box<Term>, Box<Term>),
    /// Carving that keeps the source's visible surface (`docs/icvg.md`).
    Difference(Box<Term>, Box<Term>),
    /// max(D1 - D2, L).
    DifferenceA(Box<Term>, Box<Term>),
    /// max(D1 - D2, L) where D2 >= S, else D1.
    DifferenceB(Box<Term>, Box<Term>),
    /// min(D1 + D2, H).
    Add(Box<Term>, Box<Term>),
    /// min(D1 * D2, H).
    Modulate(Box<Term>, Box<Term>),
    /// D1 * D2 / H.
    Product(Box<Term>, Box<Term>),
    /// D1 / D2 where D2 > 0, else H.
    DivideA(Box<Term>, Box<Term>),
    /// D1 / (D2 * s_l) where that is positive, else H.
    Divide {
        /// The scale of the divisor, in (0, 1].
        s_l: f64,
        /// D1 and D2.
        args: (Box<Term>, Box<Term>),
    },
    /// H - D1.
    Inverse(Box<Term>),
    /// Same as inverse (CVG's name).
    Complement(Box<Term>),
    /// D1 + k, clamped to [L, H].
    AddScalar {
        /// The amount added, within +-H.
        k: i32,
        /// D1.
        arg: Box<Term>,
    },
    /// An uploaded watertight mesh (`POST /v1/meshes`, named by its content hash), placed so
    /// that model point p lands at voxel `p * scale + offset`, as a density (2x2x2 samples per
    /// voxel: H inside, L outside, the fraction inside near the surface).
    Mesh {
        /// The upload's content hash, 16 hex digits.
        hash: String,
        /// Where model point (0, 0, 0) lands, in voxels.
        offset: [f64; 3],
        /// Voxels per model unit.
        scale: f64,
    },
    /// Grey-value dilation: the maximum over a box of `radius` voxels around each voxel (a
    /// cube of side 2 * radius + 1); on a binary volume, morphological dilation.
    Dilate {
        /// The window is the cube of side 2 * radius + 1 (at least 1).
        radius: u32,
        /// The term dilated.
        arg: Box<Term>,
    },
    /// Grey-value erosion: the minimum over the same box.
    Erode {
        /// The window is the cube of side 2 * radius + 1 (at least 1).
        radius: u32,
        /// The term eroded.
        arg: Box<Term>,
    },
    /// A leaf with attribute values (written as fields of the leaf's object, never as an
    /// object of its own).
    #[serde(skip)]
    Attributed {
        /// The attributes.
        attrs: Attributes,
        /// The leaf.
        leaf: Box<Term>,
    },
}

/// Attribute values a leaf gives the volume's channels where it wins (CVG's rule).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Attributes {
    /// The value for a `material` channel.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<u64>,
    /// The value for a `label` channel.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label: Option<u64>,
}

impl Attributes {
    /// The value for the channel named `channel`, if this leaf gives one.
    pub fn get(&self, channel: &str) -> Option<u64> {
        match channel {
            "material" => self.material,
            "label" => self.label,
            _ => None,
        }
    }

    fn is_empty(&self) -> bool {
        self.material.is_none() && self.label.is_none()
    }
}

/// The names of the leaves, which may carry attributes.
pub const LEAVES: [&str; 10] = [
    "cuboid",
    "ellipsoid",
    "cylinder",
    "cone",
    "torus",
    "capsule",
    "prism",
    "pyramid",
    "volume",
    "mesh",
];

impl Serialize for Term {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::Error;
        let Term::Attributed { attrs, leaf } = self else {
            return Term::serialize(self, s);
        };
        // The leaf's object with the attributes as fields of its own.
        let mut value = serde_json::to_value(&**leaf).map_err(S::Error::custom)?;
        let inner = value
            .as_object_mut()
            .and_then(|o| o.values_mut().next())
            .and_then(|v| v.as_object_mut())
            .ok_or_else(|| S::Error::custom("attributes on a term that is not a leaf"))?;
        for (name, v) in [("material", attrs.material), ("label", attrs.label)] {
            if let Some(v) = v {
                inner.insert(name.into(), v.into());
            }
        }
        value.serialize(s)
    }
}

impl<'de> Deserialize<'de> for Term {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let mut value = serde_json::Value::deserialize(d)?;
        // A leaf's object may carry attributes: take them out, read the leaf, wrap it.
        let mut attrs = Attributes::default();
        if let Some(obj) = value.as_object_mut() {
            if let (1, Some((name, serde_json::Value::Object(fields)))) =
                (obj.len(), obj.iter_mut().next())
            {
                if LEAVES.contains(&name.as_str()) {
                    for (field, slot) in [
                        ("material", &mut attrs.material),
                        ("label", &mut attrs.label),
                    ] {
                        if let Some(v) = fields.remove(field) {
                            *slot = Some(v.as_u64().ok_or_else(|| {
                                D::Error::custom(format!(
                                    "\"{field}\" of a {name} must be an unsigned integer, not {v}"
                                ))
                            })?);
                        }
                    }
                }
            }
        }
        let leaf = Term::deserialize(value).map_err(D::Error::custom)?;
        Ok(if attrs.is_empty() {
            leaf
        } else {
            Term::Attributed {
                attrs,
                leaf: Box::new(leaf),
            }
        })
    }
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
    /// The operator: a binary operator's name, or `inverse`, `complement`, `add_scalar`.
    pub op: String,
    /// The operand of a binary operator.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub term: Option<Term>,
    /// `divide`'s divisor scale.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub s_l: Option<f64>,
    /// `add_scalar`'s amount.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub k: Option<i32>,
    /// Where the edit applies; the whole volume when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<Box3>,
    /// Why, in a few words (at most 200 characters): the history and the change feed show it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// `paint`'s channel (default `material`): the channel written where the term is inside.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub channel: Option<String>,
    /// `paint`'s mode: overwrite every value (default), or only where the channel is 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub overwrite: Option<Overwrite>,
}

/// Which voxels `paint` writes, as the two brush modes of segmentation tools.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Overwrite {
    /// Every voxel inside the term.
    #[default]
    All,
    /// Only voxels whose value is 0 (unlabelled): what others painted stays.
    Empty,
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

    #[test]
    fn leaves_carry_attributes_as_fields_of_their_own() {
        let json = r#"{"union": [
            {"cuboid": {"origin": [0,0,0], "size": [4,4,4], "material": 3}},
            {"ellipsoid": {"center": [1,2,3], "radii": [2,2,2], "label": 70000, "material": 1}}
        ]}"#;
        let t: Term = serde_json::from_str(json).unwrap();
        let Term::Union(a, b) = &t else {
            panic!("not a union: {t:?}")
        };
        let Term::Attributed { attrs, leaf } = &**a else {
            panic!("no attributes: {a:?}")
        };
        assert_eq!(
            (*attrs, &**leaf),
            (
                Attributes {
                    material: Some(3),
                    label: None
                },
                &Term::Cuboid {
                    origin: [0, 0, 0],
                    size: [4, 4, 4]
                }
            )
        );
        assert!(
            matches!(&**b, Term::Attributed { attrs, .. } if attrs.label == Some(70000) && attrs.material == Some(1))
        );
        // Written back as fields of the leaf, and read again the same.
        let text = serde_json::to_string(&t).unwrap();
        assert!(
            text.contains(r#""size":[4,4,4],"material":3"#) || text.contains(r#""material":3"#),
            "{text}"
        );
        assert_eq!(serde_json::from_str::<Term>(&text).unwrap(), t);
        // Attributes belong to leaves, and are unsigned integers.
        for bad in [
            r#"{"dilate": {"radius": 1, "arg": {"cuboid": {"origin": [0,0,0], "size": [4,4,4]}}, "material": 2}}"#,
            r#"{"cuboid": {"origin": [0,0,0], "size": [4,4,4], "material": -1}}"#,
            r#"{"cuboid": {"origin": [0,0,0], "size": [4,4,4], "material": "rock"}}"#,
            r#"{"cuboid": {"origin": [0,0,0], "size": [4,4,4], "colour": 2}}"#,
        ] {
            assert!(serde_json::from_str::<Term>(bad).is_err(), "{bad}");
        }
    }
}
