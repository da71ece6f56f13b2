//! Compiling a JSON term into a [`CompiledTerm`]: one checked constructor per leaf (each checks
//! its own arguments and the size limit) and the tree walk (depth and node limits, B-boxes of
//! operators).

use super::ops::{check_s_l, BinaryOp, UnaryOp};
use super::primitives::{
    Capsule, Cone, Cuboid, Cylinder, Ellipsoid, Primitive, Prism, Pyramid, Torus,
};
use super::term::{CompiledTerm, Node, TermError, TermLimits, VolumeResolver};
use crate::geometry::Box3;
use isovox_proto::icvg::{Region, Term};
use isovox_proto::VoxelType;

impl CompiledTerm {
    /// Validates and compiles a term for voxels of type `t`.
    ///
    /// # Errors
    /// A radius or size out of range, an extension over the limit, a tree too deep or too
    /// large, an unknown volume or mesh, a bad operator argument.
    pub fn compile(
        term: &Term,
        t: VoxelType,
        limits: &TermLimits,
        volumes: &dyn VolumeResolver,
    ) -> Result<CompiledTerm, TermError> {
        Compiler {
            t,
            limits,
            volumes,
            nodes: 0,
        }
        .node(term, 0)
    }
}

/// The tree walk: counts nodes and depth against the limits.
struct Compiler<'a> {
    t: VoxelType,
    limits: &'a TermLimits,
    volumes: &'a dyn VolumeResolver,
    nodes: usize,
}

impl Compiler<'_> {
    fn node(&mut self, term: &Term, depth: usize) -> Result<CompiledTerm, TermError> {
        self.nodes += 1;
        if depth > self.limits.max_depth {
            return Err(TermError::TooDeep(self.limits.max_depth));
        }
        if self.nodes > self.limits.max_nodes {
            return Err(TermError::TooManyNodes(self.limits.max_nodes));
        }
        let (t, limits) = (self.t, self.limits);
        let leaf = |p: Box<dyn Primitive>| self.leaf(Node::Primitive(p));
        match term {
            Term::Cuboid { origin, size } => Ok(leaf(Box::new(cuboid(*origin, *size, limits)?))),
            Term::Ellipsoid { center, radii } => {
                Ok(leaf(Box::new(ellipsoid(*center, *radii, limits)?)))
            }
            Term::Cylinder {
                base,
                radii,
                height,
            } => Ok(leaf(Box::new(cylinder(*base, *radii, *height, limits)?))),
            Term::Cone {
                base,
                radii,
                height,
            } => Ok(leaf(Box::new(cone(*base, *radii, *height, limits)?))),
            Term::Torus {
                center,
                major,
                minor,
            } => Ok(leaf(Box::new(torus(*center, *major, *minor, limits)?))),
            Term::Capsule {
                center,
                radius,
                length,
            } => Ok(leaf(Box::new(capsule(*center, *radius, *length, limits)?))),
            Term::Prism { origin, size } => Ok(leaf(Box::new(prism(*origin, *size, limits)?))),
            Term::Pyramid { origin, size } => Ok(leaf(Box::new(pyramid(*origin, *size, limits)?))),
            Term::Volume {
                name,
                origin,
                region,
            } => Ok(self.leaf(volume(name, *origin, region.as_ref(), t, self.volumes)?)),
            Term::Mesh {
                hash,
                offset,
                scale,
            } => Ok(self.leaf(mesh(hash, *offset, *scale, t, limits, self.volumes)?)),
            Term::Union(a, b) => self.binary(BinaryOp::Union, a, b, depth),
            Term::Intersection(a, b) => self.binary(BinaryOp::Intersection, a, b, depth),
            Term::Trim(a, b) => self.binary(BinaryOp::Trim, a, b, depth),
            Term::Cap(a, b) => self.binary(BinaryOp::Cap, a, b, depth),
            Term::Difference(a, b) => self.binary(BinaryOp::Difference, a, b, depth),
            Term::DifferenceA(a, b) => self.binary(BinaryOp::DifferenceA, a, b, depth),
            Term::DifferenceB(a, b) => self.binary(BinaryOp::DifferenceB, a, b, depth),
            Term::Add(a, b) => self.binary(BinaryOp::Add, a, b, depth),
            Term::Modulate(a, b) => self.binary(BinaryOp::Modulate, a, b, depth),
            Term::Product(a, b) => self.binary(BinaryOp::Product, a, b, depth),
            Term::DivideA(a, b) => self.binary(BinaryOp::DivideA, a, b, depth),
            Term::Divide { s_l, args } => {
                check_s_l(*s_l).map_err(TermError::Invalid)?;
                self.binary(BinaryOp::Divide(*s_l), &args.0, &args.1, depth)
            }
            Term::Inverse(a) | Term::Complement(a) => {
                let a = self.node(a, depth + 1)?;
                Ok(self.with_bbox(Node::Unary(UnaryOp::Inverse, Box::new(a)), None))
            }
            Term::Dilate { radius, arg } | Term::Erode { radius, arg } => {
                let dilate = matches!(term, Term::Dilate { .. });
                positive("morphology radius", *radius)?;
                within(limits, "morphology box", 2 * *radius as u64 + 1)?;
                let a = self.node(arg, depth + 1)?;
                // Dilation reaches `radius` beyond its argument; erosion stays inside it (the
                // minimum over a box that leaves the argument's B-box includes an L).
                let bbox = match (dilate, a.bbox) {
                    (true, Some(b)) => Some(b.grow(*radius as i64)),
                    (_, b) => b,
                };
                let node = Node::Morph {
                    dilate,
                    radius: *radius,
                    arg: Box::new(a),
                };
                Ok(self.with_bbox(node, bbox))
            }
            Term::AddScalar { k, arg } => {
                check_k(*k, t)?;
                let a = self.node(arg, depth + 1)?;
                let bbox = if *k > 0 { None } else { a.bbox };
                Ok(self.with_bbox(Node::Unary(UnaryOp::AddScalar(*k), Box::new(a)), bbox))
            }
        }
    }

    fn binary(
        &mut self,
        op: BinaryOp,
        a: &Term,
        b: &Term,
        depth: usize,
    ) -> Result<CompiledTerm, TermError> {
        let (a, b) = (self.node(a, depth + 1)?, self.node(b, depth + 1)?);
        let bbox = binary_bbox(op, a.bbox, b.bbox);
        Ok(self.with_bbox(Node::Binary(op, Box::new(a), Box::new(b)), bbox))
    }

    /// A leaf: its B-box is its extension space.
    fn leaf(&self, node: Node) -> CompiledTerm {
        let bbox = match &node {
            Node::Primitive(p) => Some(p.bbox()),
            Node::Volume { shift, source, .. } => Some(Box3::new(
                [0, 1, 2].map(|a| source.min[a] + shift[a]),
                [0, 1, 2].map(|a| source.max[a] + shift[a]),
            )),
            Node::Grid { frame, .. } => Some(*frame),
            Node::Binary(..) | Node::Unary(..) | Node::Morph { .. } => None,
        };
        self.with_bbox(node, bbox)
    }

    fn with_bbox(&self, node: Node, bbox: Option<Box3>) -> CompiledTerm {
        CompiledTerm {
            node,
            bbox,
            voxel_type: self.t,
        }
    }
}

fn positive(what: &str, v: u32) -> Result<(), TermError> {
    if v == 0 {
        return Err(TermError::Invalid(format!("{what} must be at least 1")));
    }
    Ok(())
}

/// Checks a primitive's extension against [`TermLimits::max_extent`].
fn within(limits: &TermLimits, what: &str, extent: u64) -> Result<(), TermError> {
    if extent > limits.max_extent as u64 {
        return Err(TermError::TooWide {
            what: what.to_string(),
            extent,
            limit: limits.max_extent,
        });
    }
    Ok(())
}

/// `add_scalar`'s `k` must lie in `[-H, H]`.
pub(crate) fn check_k(k: i32, t: VoxelType) -> Result<(), TermError> {
    if k.unsigned_abs() > t.high() as u32 {
        return Err(TermError::Invalid(format!(
            "add_scalar k = {k} is outside [-{h}, {h}]",
            h = t.high()
        )));
    }
    Ok(())
}

fn cuboid(origin: [i64; 3], size: [u32; 3], limits: &TermLimits) -> Result<Cuboid, TermError> {
    if size.iter().any(|&s| s <= 2) {
        return Err(TermError::Invalid(format!(
            "cuboid size {size:?}: every side must be greater than 2"
        )));
    }
    within(limits, "cuboid", *size.iter().max().unwrap_or(&0) as u64)?;
    Ok(Cuboid { origin, size })
}

fn ellipsoid(
    center: [i64; 3],
    radii: [u32; 3],
    limits: &TermLimits,
) -> Result<Ellipsoid, TermError> {
    for r in radii {
        positive("ellipsoid radius", r)?;
    }
    within(
        limits,
        "ellipsoid",
        2 * *radii.iter().max().unwrap_or(&0) as u64 + 1,
    )?;
    Ok(Ellipsoid { center, radii })
}

/// The checks a cylinder and a cone share: positive radii, a height of at least 3.
fn axial(name: &str, radii: [u32; 2], height: u32, limits: &TermLimits) -> Result<(), TermError> {
    for r in radii {
        positive(&format!("{name} radius"), r)?;
    }
    if height < 3 {
        return Err(TermError::Invalid(format!(
            "{name} height must be at least 3, got {height}"
        )));
    }
    within(
        limits,
        name,
        (2 * *radii.iter().max().unwrap_or(&0) as u64 + 1).max(height as u64),
    )
}

fn cylinder(
    base: [i64; 3],
    radii: [u32; 2],
    height: u32,
    limits: &TermLimits,
) -> Result<Cylinder, TermError> {
    axial("cylinder", radii, height, limits)?;
    Ok(Cylinder {
        base,
        radii,
        height,
    })
}

fn cone(
    base: [i64; 3],
    radii: [u32; 2],
    height: u32,
    limits: &TermLimits,
) -> Result<Cone, TermError> {
    axial("cone", radii, height, limits)?;
    Ok(Cone {
        base,
        radii,
        height,
    })
}

fn torus(
    center: [i64; 3],
    major: u32,
    minor: u32,
    limits: &TermLimits,
) -> Result<Torus, TermError> {
    positive("torus minor radius", minor)?;
    within(limits, "torus", 2 * (major as u64 + minor as u64) + 1)?;
    Ok(Torus {
        center,
        major,
        minor,
    })
}

fn capsule(
    center: [i64; 3],
    radius: u32,
    length: u32,
    limits: &TermLimits,
) -> Result<Capsule, TermError> {
    positive("capsule radius", radius)?;
    within(limits, "capsule", length as u64 + 2 * radius as u64 + 1)?;
    Ok(Capsule {
        center,
        radius,
        length,
    })
}

/// The checks a prism and a pyramid share: every side at least 4.
fn slanted(name: &str, size: [u32; 3], limits: &TermLimits) -> Result<(), TermError> {
    if size.iter().any(|&s| s < 4) {
        return Err(TermError::Invalid(format!(
            "{name} size {size:?}: every side must be at least 4"
        )));
    }
    within(limits, name, *size.iter().max().unwrap_or(&0) as u64)
}

fn prism(
    origin: [i64; 3],
    size: [u32; 3],
    limits: &TermLimits,
) -> Result<super::primitives::CutCuboid, TermError> {
    slanted("prism", size, limits)?;
    Ok(Prism { origin, size }.solid())
}

fn pyramid(
    origin: [i64; 3],
    size: [u32; 3],
    limits: &TermLimits,
) -> Result<super::primitives::CutCuboid, TermError> {
    slanted("pyramid", size, limits)?;
    Ok(Pyramid { origin, size }.solid())
}

/// A box of another volume's level 0 placed at `origin`.
fn volume(
    name: &str,
    origin: [i64; 3],
    region: Option<&Region>,
    t: VoxelType,
    volumes: &dyn VolumeResolver,
) -> Result<Node, TermError> {
    let snap = volumes.resolve(name)?;
    if snap.layout().voxel_type() != t {
        return Err(TermError::Volume(format!(
            "volume {name:?} holds {} voxels, the edited volume {t}",
            snap.layout().voxel_type()
        )));
    }
    let whole = Box3::of_volume(snap.layout());
    let source = match region {
        Some(r) => {
            let b = Box3::new(r.min, r.max);
            if b.is_empty() || b.intersect(&whole) != b {
                return Err(TermError::Invalid(format!(
                    "region {:?}..{:?} is empty or outside volume {name:?} ({:?})",
                    r.min, r.max, whole.max
                )));
            }
            b
        }
        None => whole,
    };
    let shift = [0, 1, 2].map(|a| origin[a] - source.min[a]);
    Ok(Node::Volume {
        snap,
        shift,
        source,
    })
}

/// An uploaded mesh, voxelized once into a grid of densities over its placed bounds.
fn mesh(
    hash: &str,
    offset: [f64; 3],
    scale: f64,
    t: VoxelType,
    limits: &TermLimits,
    volumes: &dyn VolumeResolver,
) -> Result<Node, TermError> {
    let h = (hash.len() == 16)
        .then(|| u64::from_str_radix(hash, 16).ok())
        .flatten()
        .ok_or_else(|| TermError::Invalid(format!("mesh hash {hash:?}: 16 hex digits expected")))?;
    if !(scale.is_finite() && scale > 0.0) || offset.iter().any(|o| !o.is_finite()) {
        return Err(TermError::Invalid(format!(
            "mesh {hash}: scale must be positive and finite, offset finite"
        )));
    }
    let mesh = volumes.mesh(h)?;
    let (lo, hi) = mesh
        .bounds()
        .ok_or_else(|| TermError::Mesh(format!("mesh {hash} has no triangles")))?;
    let place =
        |p: [f32; 3]| -> [f64; 3] { std::array::from_fn(|a| p[a] as f64 * scale + offset[a]) };
    let (a, b) = (place(lo), place(hi));
    let min = a.map(|c| c.floor() as i64 - 1);
    let max = b.map(|c| c.ceil() as i64 + 1);
    for axis in 0..3 {
        within(limits, "mesh", (max[axis] - min[axis]).max(0) as u64)?;
    }
    let frame = Box3::new(min, max);
    let dims = [0, 1, 2].map(|i| (max[i] - min[i]) as usize);
    let values = crate::voxelize::density_box(&mesh, min, dims, 2, t, place);
    Ok(Node::Grid { frame, values })
}

/// The B-box of a binary node from its children's (`docs/icvg.md`): union-like operators
/// cover the hull, intersection-like the overlap, differences the left side; divide maps (L, L)
/// to H and so has none.
fn binary_bbox(op: BinaryOp, a: Option<Box3>, b: Option<Box3>) -> Option<Box3> {
    match op {
        BinaryOp::Union | BinaryOp::Add => Some(a?.hull(&b?)),
        BinaryOp::Intersection | BinaryOp::Cap | BinaryOp::Modulate | BinaryOp::Product => {
            match (a, b) {
                (Some(a), Some(b)) => Some(a.intersect(&b)),
                (Some(x), None) | (None, Some(x)) => Some(x),
                (None, None) => None,
            }
        }
        BinaryOp::Trim | BinaryOp::Difference | BinaryOp::DifferenceA | BinaryOp::DifferenceB => a,
        BinaryOp::DivideA | BinaryOp::Divide(_) => None,
    }
}
