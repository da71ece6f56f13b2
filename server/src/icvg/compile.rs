//! Compiling a JSON term into a [`CompiledTerm`]: one checked constructor per leaf (each checks
//! its own arguments and the size limit) and the tree walk (depth and node limits, B-boxes of
//! operators).

use super::morph;
use super::ops::{check_s_l, BinaryOp, UnaryOp};
use super::primitives::{
    Capsule, Cone, Cuboid, Cylinder, Ellipsoid, Primitive, Prism, Pyramid, Torus,
};
use super::term::{CompiledTerm, Node, Scope, TermError, TermLimits, VolumeResolver};
use crate::geometry::Box3;
use isovox_proto::icvg::{Attributes, Term, MAX_COORDINATE};
use isovox_proto::VoxelType;

impl CompiledTerm {
    /// Validates and compiles a term for voxels of type `t`, to be evaluated anywhere (mesh
    /// leaves are voxelized over their whole placed extent).
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
        Ok(CompiledTerm::compile_in(term, t, limits, volumes, &Scope::default())?.0)
    }

    /// Validates and compiles a term to be evaluated within `scope.within`, with what it
    /// samples besides its own evaluation (mesh leaves voxelized, morphology inputs) counted
    /// against `scope.max_voxels`. Returns the term and that count.
    ///
    /// # Errors
    /// As [`CompiledTerm::compile`]; [`TermError::OverBudget`] past `scope.max_voxels`;
    /// [`TermError::Stopped`] when `scope.cancel` stops a mesh leaf's voxelization.
    pub fn compile_in(
        term: &Term,
        t: VoxelType,
        limits: &TermLimits,
        volumes: &dyn VolumeResolver,
        scope: &Scope,
    ) -> Result<(CompiledTerm, u64), TermError> {
        let mut compiler = Compiler {
            t,
            limits,
            volumes,
            scope,
            nodes: 0,
            sampled: 0,
        };
        let compiled = compiler.node(term, 0, scope.within)?;
        Ok((compiled, compiler.sampled))
    }
}

/// The tree walk: counts nodes and depth against the limits, and the voxels sampled against
/// the scope's budget.
struct Compiler<'a> {
    t: VoxelType,
    limits: &'a TermLimits,
    volumes: &'a dyn VolumeResolver,
    scope: &'a Scope,
    nodes: usize,
    sampled: u64,
}

impl Compiler<'_> {
    /// Counts `voxels` sampled by `what` against the budget, before they are sampled.
    fn spend(&mut self, what: impl FnOnce() -> String, voxels: u128) -> Result<(), TermError> {
        let voxels = u64::try_from(voxels).unwrap_or(u64::MAX);
        self.sampled = self.sampled.saturating_add(voxels);
        match self.scope.max_voxels {
            Some(limit) if self.sampled > limit => Err(TermError::OverBudget {
                what: what(),
                voxels: self.sampled,
                limit,
            }),
            _ => Ok(()),
        }
    }

    /// Compiles `term`, to be evaluated within `within` (anywhere when `None`).
    fn node(
        &mut self,
        term: &Term,
        depth: usize,
        within: Option<Box3>,
    ) -> Result<CompiledTerm, TermError> {
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
            } => {
                let node = self.mesh(hash, *offset, *scale, within)?;
                Ok(self.leaf(node))
            }
            Term::Union(a, b) => self.binary(BinaryOp::Union, a, b, depth, within),
            Term::Intersection(a, b) => self.binary(BinaryOp::Intersection, a, b, depth, within),
            Term::Trim(a, b) => self.binary(BinaryOp::Trim, a, b, depth, within),
            Term::Cap(a, b) => self.binary(BinaryOp::Cap, a, b, depth, within),
            Term::Difference(a, b) => self.binary(BinaryOp::Difference, a, b, depth, within),
            Term::DifferenceA(a, b) => self.binary(BinaryOp::DifferenceA, a, b, depth, within),
            Term::DifferenceB(a, b) => self.binary(BinaryOp::DifferenceB, a, b, depth, within),
            Term::Add(a, b) => self.binary(BinaryOp::Add, a, b, depth, within),
            Term::Modulate(a, b) => self.binary(BinaryOp::Modulate, a, b, depth, within),
            Term::Product(a, b) => self.binary(BinaryOp::Product, a, b, depth, within),
            Term::DivideA(a, b) => self.binary(BinaryOp::DivideA, a, b, depth, within),
            Term::Divide { s_l, args } => {
                check_s_l(*s_l).map_err(TermError::Invalid)?;
                self.binary(BinaryOp::Divide(*s_l), &args.0, &args.1, depth, within)
            }
            Term::Inverse(a) | Term::Complement(a) => {
                let a = self.node(a, depth + 1, within)?;
                Ok(self.with_bbox(Node::Unary(UnaryOp::Inverse, Box::new(a)), None))
            }
            Term::Dilate { radius, arg } | Term::Erode { radius, arg } => {
                let dilate = matches!(term, Term::Dilate { .. });
                positive("morphology radius", *radius)?;
                within_limit(limits, "morphology box", 2 * *radius as u64 + 1)?;
                let r = *radius as i64;
                let a = self.node(arg, depth + 1, within.map(|w| w.grow(r)))?;
                // Dilation reaches `radius` beyond its argument; erosion stays `radius` inside
                // it (the minimum over a window that leaves the argument's B-box includes an L).
                let bbox = match (dilate, a.bbox) {
                    (true, Some(b)) => Some(b.grow(r)),
                    (false, Some(b)) => Some(morph::eroded_bbox(b, *radius)),
                    (_, None) => None,
                };
                // Filtering reads the argument over the evaluated box grown by the radius.
                if let Some(w) = within {
                    if let Some((out, input)) = morph::boxes(&w, bbox, a.bbox, *radius, dilate) {
                        let name = if dilate { "dilate" } else { "erode" };
                        let cost = morph::cost(&out, &input);
                        self.spend(|| format!("{name} of radius {radius}"), cost)?;
                    }
                }
                let node = Node::Morph {
                    dilate,
                    radius: *radius,
                    arg: Box::new(a),
                };
                Ok(self.with_bbox(node, bbox))
            }
            Term::Attributed { attrs, leaf } => {
                let mut leaf = self.node(leaf, depth, within)?;
                leaf.attrs = *attrs;
                Ok(leaf)
            }
            Term::AddScalar { k, arg } => {
                check_k(*k, t)?;
                let a = self.node(arg, depth + 1, within)?;
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
        within: Option<Box3>,
    ) -> Result<CompiledTerm, TermError> {
        let a = self.node(a, depth + 1, within)?;
        let b = self.node(b, depth + 1, within)?;
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

    /// An uploaded mesh placed at `offset` and `scale` (model point `p` lands on voxel
    /// coordinate `p * scale + offset`), voxelized once into a grid of densities over its placed
    /// bounds within `within`: the term is never evaluated elsewhere, so however far the model
    /// reaches, the grid is no larger than the evaluated box.
    fn mesh(
        &mut self,
        hash: &str,
        offset: [f64; 3],
        scale: f64,
        within: Option<Box3>,
    ) -> Result<Node, TermError> {
        let h = (hash.len() == 16)
            .then(|| u64::from_str_radix(hash, 16).ok())
            .flatten()
            .ok_or_else(|| {
                TermError::Invalid(format!("mesh hash {hash:?}: 16 hex digits expected"))
            })?;
        if !(scale.is_finite() && scale > 0.0) || offset.iter().any(|o| !o.is_finite()) {
            return Err(TermError::Invalid(format!(
                "mesh {hash}: scale must be positive and finite, offset finite"
            )));
        }
        let mesh = self.volumes.mesh(h)?;
        let (lo, hi) = mesh
            .bounds()
            .ok_or_else(|| TermError::Mesh(format!("mesh {hash} has no triangles")))?;
        let place =
            |p: [f32; 3]| -> [f64; 3] { std::array::from_fn(|a| p[a] as f64 * scale + offset[a]) };
        let (a, b) = (place(lo), place(hi));
        if let Some(c) = a
            .iter()
            .chain(&b)
            .find(|c| !c.is_finite() || c.abs() > MAX_PLACED)
        {
            return Err(TermError::Mesh(format!(
                "mesh {hash} placed with scale {scale} and offset {offset:?} reaches the coordinate {c:e}; a placed mesh must lie within +-2^40 voxels ({MAX_PLACED:e})"
            )));
        }
        let whole = Box3::new(
            a.map(|c| c.floor() as i64 - 1),
            b.map(|c| c.ceil() as i64 + 1),
        );
        let frame = match within {
            Some(w) => whole.intersect(&w),
            None => {
                for axis in 0..3 {
                    within_limit(
                        self.limits,
                        "mesh",
                        (whole.max[axis] - whole.min[axis]) as u64,
                    )?;
                }
                whole
            }
        };
        if frame.is_empty() {
            return Ok(Node::Grid {
                frame,
                values: Vec::new(),
            });
        }
        self.spend(|| format!("mesh {hash} at scale {scale}"), frame.voxels())?;
        let dims = [0, 1, 2].map(|i| (frame.max[i] - frame.min[i]) as usize);
        let values = crate::voxelize::density_box(
            &mesh,
            frame.min,
            dims,
            2,
            self.t,
            place,
            &self.scope.cancel,
        )?;
        Ok(Node::Grid { frame, values })
    }

    fn with_bbox(&self, node: Node, bbox: Option<Box3>) -> CompiledTerm {
        CompiledTerm {
            node,
            bbox,
            voxel_type: self.t,
            attrs: Attributes::default(),
        }
    }
}

/// How far from the origin a placed mesh may reach, in voxels: the voxelizer's fixed-point
/// coordinates (16 fractional bits, times 2 for supersampling, relative to a grid that may
/// itself start this far out) then stay well inside i64, differences included.
const MAX_PLACED: f64 = (1u64 << 40) as f64;

fn positive(what: &str, v: u32) -> Result<(), TermError> {
    if v == 0 {
        return Err(TermError::Invalid(format!("{what} must be at least 1")));
    }
    Ok(())
}

/// Checks that a placed position lies within [`MAX_COORDINATE`] on every axis.
fn placed(what: &str, p: [i64; 3]) -> Result<[i64; 3], TermError> {
    if p.iter().any(|c| c.unsigned_abs() > MAX_COORDINATE as u64) {
        return Err(TermError::Invalid(format!(
            "{what} {p:?} is beyond +-{MAX_COORDINATE}, the coordinate limit"
        )));
    }
    Ok(p)
}

/// The largest torus radius, major and minor alike: a quarter of the extension limit, so the
/// torus's extension `2 (major + minor) + 1` stays within it whatever the other one is (one
/// bound per field is what an API schema can state; 16,383 by default).
pub fn max_torus_radius(limits: &TermLimits) -> u32 {
    (limits.max_extent / 2 - 1) / 2
}

/// The largest capsule radius: as a torus radius (see [`max_torus_radius`]).
pub fn max_capsule_radius(limits: &TermLimits) -> u32 {
    max_torus_radius(limits)
}

/// The longest capsule segment: half the extension limit (32,768 by default), so
/// `length + 2 radius + 1` stays within it.
pub fn max_capsule_length(limits: &TermLimits) -> u32 {
    limits.max_extent / 2
}

/// Checks that `v` is at most `max`.
fn at_most(what: &str, v: u32, max: u32) -> Result<(), TermError> {
    if v > max {
        return Err(TermError::Invalid(format!(
            "{what} {v} is over the limit of {max}"
        )));
    }
    Ok(())
}

/// Checks a primitive's extension against [`TermLimits::max_extent`].
fn within_limit(limits: &TermLimits, what: &str, extent: u64) -> Result<(), TermError> {
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
    within_limit(limits, "cuboid", *size.iter().max().unwrap_or(&0) as u64)?;
    Ok(Cuboid {
        origin: placed("cuboid origin", origin)?,
        size,
    })
}

fn ellipsoid(
    center: [i64; 3],
    radii: [u32; 3],
    limits: &TermLimits,
) -> Result<Ellipsoid, TermError> {
    for r in radii {
        positive("ellipsoid radius", r)?;
    }
    within_limit(
        limits,
        "ellipsoid",
        2 * *radii.iter().max().unwrap_or(&0) as u64 + 1,
    )?;
    Ok(Ellipsoid {
        center: placed("ellipsoid center", center)?,
        radii,
    })
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
    within_limit(
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
        base: placed("cylinder base", base)?,
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
        base: placed("cone base", base)?,
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
    positive("torus major radius", major)?;
    positive("torus minor radius", minor)?;
    at_most("torus major radius", major, max_torus_radius(limits))?;
    at_most("torus minor radius", minor, max_torus_radius(limits))?;
    Ok(Torus {
        center: placed("torus center", center)?,
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
    at_most("capsule radius", radius, max_capsule_radius(limits))?;
    at_most("capsule length", length, max_capsule_length(limits))?;
    Ok(Capsule {
        center: placed("capsule center", center)?,
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
    within_limit(limits, name, *size.iter().max().unwrap_or(&0) as u64)
}

fn prism(
    origin: [i64; 3],
    size: [u32; 3],
    limits: &TermLimits,
) -> Result<super::primitives::CutCuboid, TermError> {
    slanted("prism", size, limits)?;
    let origin = placed("prism origin", origin)?;
    Ok(Prism { origin, size }.solid())
}

fn pyramid(
    origin: [i64; 3],
    size: [u32; 3],
    limits: &TermLimits,
) -> Result<super::primitives::CutCuboid, TermError> {
    slanted("pyramid", size, limits)?;
    let origin = placed("pyramid origin", origin)?;
    Ok(Pyramid { origin, size }.solid())
}

/// A box of another volume's level 0 placed at `origin`.
fn volume(
    name: &str,
    origin: [i64; 3],
    region: Option<&Box3>,
    t: VoxelType,
    volumes: &dyn VolumeResolver,
) -> Result<Node, TermError> {
    let origin = placed("volume origin", origin)?;
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
            let b = *r;
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
