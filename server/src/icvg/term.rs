//! CVG terms compiled for evaluation: validated, with B-boxes, evaluated over boxes of voxels.

use super::ops::{check_s_l, BinaryOp, UnaryOp};
use super::primitives::{
    constant_over, Box3, Capsule, Cone, Cuboid, Cylinder, Ellipsoid, Primitive, Prism, Pyramid,
    Torus,
};
use crate::store::Snapshot;
use isovox_proto::icvg::Term;
use isovox_proto::{BrickKey, VoxelType};
use std::sync::Arc;

/// Limits on what a term may ask for (safe defaults; a server can tighten them).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TermLimits {
    /// Deepest nesting of operators.
    pub max_depth: usize,
    /// Most nodes in one term.
    pub max_nodes: usize,
    /// Largest extension of one primitive along any axis, in voxels.
    pub max_extent: u32,
}

impl Default for TermLimits {
    fn default() -> Self {
        TermLimits {
            max_depth: 32,
            max_nodes: 256,
            max_extent: 1 << 16,
        }
    }
}

/// Why a term is refused. The message says what and where.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct TermError(pub String);

/// Finds the stored volumes a term names (`{"volume": {"name": ...}}`).
pub trait VolumeResolver {
    /// # Errors
    /// No volume of that name.
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError>;

    /// The uploaded mesh with this content hash (for `mesh` leaves).
    ///
    /// # Errors
    /// No such mesh, or no mesh store here.
    fn mesh(&self, hash: u64) -> Result<Arc<crate::voxelize::solid::TriMesh>, TermError> {
        Err(TermError(format!(
            "mesh {hash:016x}: meshes are not available here"
        )))
    }
}

/// A resolver that knows no volume.
#[derive(Debug)]
pub struct NoVolumes;

impl VolumeResolver for NoVolumes {
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        Err(TermError(format!("unknown volume {name:?} in term")))
    }
}

/// A compiled term node.
#[derive(Debug)]
pub enum Node {
    Primitive(Box<dyn Primitive>),
    /// A box `source` of another volume's level 0, moved by `shift` (world = source + shift).
    Volume {
        snap: Arc<Snapshot>,
        shift: [i64; 3],
        source: Box3,
    },
    Binary(BinaryOp, Box<CompiledTerm>, Box<CompiledTerm>),
    Unary(UnaryOp, Box<CompiledTerm>),
    /// Values sampled once into an array over `frame` (a voxelized mesh); L outside.
    Grid {
        frame: Box3,
        values: Vec<u16>,
    },
    /// Dilation (max) or erosion (min) over a cube of side `2 * radius + 1`.
    Morph {
        dilate: bool,
        radius: u32,
        arg: Box<CompiledTerm>,
    },
}

/// A term ready to evaluate, with its B-box: outside it the term is L. `None` means unbounded
/// (an operator that maps (L, L) to something else: inverse, divide, add_scalar with k > 0).
#[derive(Debug)]
pub struct CompiledTerm {
    pub node: Node,
    pub bbox: Option<Box3>,
    pub voxel_type: VoxelType,
}

fn positive(what: &str, v: u32) -> Result<(), TermError> {
    if v == 0 {
        return Err(TermError(format!("{what} must be at least 1")));
    }
    Ok(())
}

impl CompiledTerm {
    /// Validates and compiles a term for voxels of type `t`.
    ///
    /// # Errors
    /// A radius or size out of range, an extension over the limit, a tree too deep or too
    /// large, an unknown volume, a bad operator argument.
    pub fn compile(
        term: &Term,
        t: VoxelType,
        limits: &TermLimits,
        volumes: &dyn VolumeResolver,
    ) -> Result<CompiledTerm, TermError> {
        let mut nodes = 0;
        Self::build(term, t, limits, volumes, 0, &mut nodes)
    }

    fn build(
        term: &Term,
        t: VoxelType,
        limits: &TermLimits,
        volumes: &dyn VolumeResolver,
        depth: usize,
        nodes: &mut usize,
    ) -> Result<CompiledTerm, TermError> {
        *nodes += 1;
        if depth > limits.max_depth {
            return Err(TermError(format!(
                "term is nested deeper than {} levels",
                limits.max_depth
            )));
        }
        if *nodes > limits.max_nodes {
            return Err(TermError(format!(
                "term has more than {} nodes",
                limits.max_nodes
            )));
        }
        let extent = |what: &str, e: u64| -> Result<(), TermError> {
            if e > limits.max_extent as u64 {
                return Err(TermError(format!(
                    "{what} spans {e} voxels, more than the limit of {}",
                    limits.max_extent
                )));
            }
            Ok(())
        };
        let prim = |p: Box<dyn Primitive>| -> Result<CompiledTerm, TermError> {
            let b = p.bbox();
            Ok(CompiledTerm {
                bbox: Some(b),
                node: Node::Primitive(p),
                voxel_type: t,
            })
        };
        let child =
            |c: &Term, nodes: &mut usize| Self::build(c, t, limits, volumes, depth + 1, nodes);
        let binary = |op: BinaryOp,
                      a: &Term,
                      b: &Term,
                      nodes: &mut usize|
         -> Result<CompiledTerm, TermError> {
            let (a, b) = (child(a, nodes)?, child(b, nodes)?);
            let bbox = binary_bbox(op, a.bbox, b.bbox);
            Ok(CompiledTerm {
                node: Node::Binary(op, Box::new(a), Box::new(b)),
                bbox,
                voxel_type: t,
            })
        };
        match term {
            Term::Cuboid { origin, size } => {
                if size.iter().any(|&s| s <= 2) {
                    return Err(TermError(format!(
                        "cuboid size {size:?}: every side must be greater than 2"
                    )));
                }
                extent("cuboid", *size.iter().max().unwrap_or(&0) as u64)?;
                prim(Box::new(Cuboid {
                    origin: *origin,
                    size: *size,
                }))
            }
            Term::Ellipsoid { center, radii } => {
                for r in radii {
                    positive("ellipsoid radius", *r)?;
                }
                extent(
                    "ellipsoid",
                    2 * *radii.iter().max().unwrap_or(&0) as u64 + 1,
                )?;
                prim(Box::new(Ellipsoid {
                    center: *center,
                    radii: *radii,
                }))
            }
            Term::Cylinder {
                base,
                radii,
                height,
            }
            | Term::Cone {
                base,
                radii,
                height,
            } => {
                let name = if matches!(term, Term::Cone { .. }) {
                    "cone"
                } else {
                    "cylinder"
                };
                for r in radii {
                    positive(&format!("{name} radius"), *r)?;
                }
                if *height < 3 {
                    return Err(TermError(format!(
                        "{name} height must be at least 3, got {height}"
                    )));
                }
                extent(
                    name,
                    (2 * *radii.iter().max().unwrap_or(&0) as u64 + 1).max(*height as u64),
                )?;
                if name == "cone" {
                    prim(Box::new(Cone {
                        base: *base,
                        radii: *radii,
                        height: *height,
                    }))
                } else {
                    prim(Box::new(Cylinder {
                        base: *base,
                        radii: *radii,
                        height: *height,
                    }))
                }
            }
            Term::Torus {
                center,
                major,
                minor,
            } => {
                positive("torus minor radius", *minor)?;
                extent("torus", 2 * (*major as u64 + *minor as u64) + 1)?;
                prim(Box::new(Torus {
                    center: *center,
                    major: *major,
                    minor: *minor,
                }))
            }
            Term::Capsule {
                center,
                radius,
                length,
            } => {
                positive("capsule radius", *radius)?;
                extent("capsule", *length as u64 + 2 * *radius as u64 + 1)?;
                prim(Box::new(Capsule {
                    center: *center,
                    radius: *radius,
                    length: *length,
                }))
            }
            Term::Prism { origin, size } | Term::Pyramid { origin, size } => {
                let name = if matches!(term, Term::Prism { .. }) {
                    "prism"
                } else {
                    "pyramid"
                };
                if size.iter().any(|&s| s < 4) {
                    return Err(TermError(format!(
                        "{name} size {size:?}: every side must be at least 4"
                    )));
                }
                extent(name, *size.iter().max().unwrap_or(&0) as u64)?;
                if name == "prism" {
                    prim(Box::new(
                        Prism {
                            origin: *origin,
                            size: *size,
                        }
                        .solid(),
                    ))
                } else {
                    prim(Box::new(
                        Pyramid {
                            origin: *origin,
                            size: *size,
                        }
                        .solid(),
                    ))
                }
            }
            Term::Volume {
                name,
                origin,
                region,
            } => {
                let snap = volumes.resolve(name)?;
                if snap.layout().voxel_type() != t {
                    return Err(TermError(format!(
                        "volume {name:?} holds {} voxels, the edited volume {t}",
                        snap.layout().voxel_type()
                    )));
                }
                let whole = Box3::new([0; 3], snap.layout().dims().map(|d| d as i64));
                let source = match region {
                    Some(r) => {
                        let b = Box3::new(r.min, r.max);
                        if b.is_empty() || b.intersect(&whole) != b {
                            return Err(TermError(format!(
                                "region {:?}..{:?} is empty or outside volume {name:?} ({:?})",
                                r.min, r.max, whole.max
                            )));
                        }
                        b
                    }
                    None => whole,
                };
                let shift = [0, 1, 2].map(|a| origin[a] - source.min[a]);
                let bbox = Box3::new(*origin, [0, 1, 2].map(|a| source.max[a] + shift[a]));
                Ok(CompiledTerm {
                    node: Node::Volume {
                        snap,
                        shift,
                        source,
                    },
                    bbox: Some(bbox),
                    voxel_type: t,
                })
            }
            Term::Union(a, b) => binary(BinaryOp::Union, a, b, nodes),
            Term::Intersection(a, b) => binary(BinaryOp::Intersection, a, b, nodes),
            Term::Trim(a, b) => binary(BinaryOp::Trim, a, b, nodes),
            Term::Cap(a, b) => binary(BinaryOp::Cap, a, b, nodes),
            Term::Difference(a, b) => binary(BinaryOp::Difference, a, b, nodes),
            Term::DifferenceA(a, b) => binary(BinaryOp::DifferenceA, a, b, nodes),
            Term::DifferenceB(a, b) => binary(BinaryOp::DifferenceB, a, b, nodes),
            Term::Add(a, b) => binary(BinaryOp::Add, a, b, nodes),
            Term::Modulate(a, b) => binary(BinaryOp::Modulate, a, b, nodes),
            Term::Product(a, b) => binary(BinaryOp::Product, a, b, nodes),
            Term::DivideA(a, b) => binary(BinaryOp::DivideA, a, b, nodes),
            Term::Divide { s_l, args } => {
                check_s_l(*s_l).map_err(TermError)?;
                binary(BinaryOp::Divide(*s_l), &args.0, &args.1, nodes)
            }
            Term::Inverse(a) | Term::Complement(a) => {
                let a = child(a, nodes)?;
                Ok(CompiledTerm {
                    node: Node::Unary(UnaryOp::Inverse, Box::new(a)),
                    bbox: None,
                    voxel_type: t,
                })
            }
            Term::Mesh {
                hash,
                offset,
                scale,
            } => {
                let h = (hash.len() == 16)
                    .then(|| u64::from_str_radix(hash, 16).ok())
                    .flatten()
                    .ok_or_else(|| {
                        TermError(format!("mesh hash {hash:?}: 16 hex digits expected"))
                    })?;
                if !(scale.is_finite() && *scale > 0.0) || offset.iter().any(|o| !o.is_finite()) {
                    return Err(TermError(format!(
                        "mesh {hash}: scale must be positive and finite, offset finite"
                    )));
                }
                let mesh = volumes.mesh(h)?;
                let (lo, hi) = mesh
                    .bounds()
                    .ok_or_else(|| TermError(format!("mesh {hash} has no triangles")))?;
                let place = |p: [f32; 3]| -> [f64; 3] {
                    std::array::from_fn(|a| p[a] as f64 * scale + offset[a])
                };
                let (a, b) = (place(lo), place(hi));
                let min = a.map(|c| c.floor() as i64 - 1);
                let max = b.map(|c| c.ceil() as i64 + 1);
                for axis in 0..3 {
                    extent("mesh", (max[axis] - min[axis]).max(0) as u64)?;
                }
                let frame = Box3::new(min, max);
                let dims = [0, 1, 2].map(|i| (max[i] - min[i]) as usize);
                let values = crate::voxelize::density_box(&mesh, min, dims, 2, t, place);
                Ok(CompiledTerm {
                    node: Node::Grid { frame, values },
                    bbox: Some(frame),
                    voxel_type: t,
                })
            }
            Term::Dilate { radius, arg } | Term::Erode { radius, arg } => {
                let dilate = matches!(term, Term::Dilate { .. });
                positive("morphology radius", *radius)?;
                extent("morphology box", 2 * *radius as u64 + 1)?;
                let a = child(arg, nodes)?;
                // Dilation reaches `radius` beyond its argument; erosion stays inside it (the
                // minimum over a box that leaves the argument's B-box includes an L).
                let bbox = match (dilate, a.bbox) {
                    (true, Some(b)) => Some(b.grow(*radius as i64)),
                    (_, b) => b,
                };
                Ok(CompiledTerm {
                    node: Node::Morph {
                        dilate,
                        radius: *radius,
                        arg: Box::new(a),
                    },
                    bbox,
                    voxel_type: t,
                })
            }
            Term::AddScalar { k, arg } => {
                if k.unsigned_abs() > t.high() as u32 {
                    return Err(TermError(format!(
                        "add_scalar k = {k} is outside [-{h}, {h}]",
                        h = t.high()
                    )));
                }
                let a = child(arg, nodes)?;
                let bbox = if *k > 0 { None } else { a.bbox };
                Ok(CompiledTerm {
                    node: Node::Unary(UnaryOp::AddScalar(*k), Box::new(a)),
                    bbox,
                    voxel_type: t,
                })
            }
        }
    }

    /// The value at one voxel (the reference, voxel by voxel; [`CompiledTerm::eval`] is the fast
    /// path and must agree with it).
    pub fn sample(&self, v: [i64; 3]) -> u16 {
        let t = self.voxel_type;
        if let Some(b) = self.bbox {
            if !b.contains(v) {
                return t.low();
            }
        }
        match &self.node {
            Node::Primitive(p) => p.sample(v, t),
            Node::Volume {
                snap,
                shift,
                source,
            } => {
                let s = [0, 1, 2].map(|a| v[a] - shift[a]);
                if source.contains(s) {
                    volume_voxel(snap, s).unwrap_or(t.low())
                } else {
                    t.low()
                }
            }
            Node::Binary(op, a, b) => op.apply(a.sample(v), b.sample(v), t),
            Node::Unary(op, a) => op.apply(a.sample(v), t),
            Node::Grid { frame, values } => grid_value(frame, values, v, t),
            Node::Morph {
                dilate,
                radius,
                arg,
            } => {
                let r = *radius as i64;
                let mut best = if *dilate { t.low() } else { t.high() };
                for z in v[2] - r..=v[2] + r {
                    for y in v[1] - r..=v[1] + r {
                        for x in v[0] - r..=v[0] + r {
                            let s = arg.sample([x, y, z]);
                            best = if *dilate { best.max(s) } else { best.min(s) };
                        }
                    }
                }
                best
            }
        }
    }

    /// The one value of every voxel of `b`, when certain without sampling.
    pub fn constant_over(&self, b: &Box3) -> Option<u16> {
        let t = self.voxel_type;
        if let Some(bb) = self.bbox {
            if b.intersect(&bb).is_empty() {
                return Some(t.low());
            }
        }
        match &self.node {
            Node::Primitive(p) => constant_over(p.as_ref(), b, t),
            Node::Volume { .. } | Node::Grid { .. } => None,
            Node::Binary(op, x, y) => Some(op.apply(x.constant_over(b)?, y.constant_over(b)?, t)),
            Node::Unary(op, x) => Some(op.apply(x.constant_over(b)?, t)),
            // Constant over the box grown by the radius: the filter of a constant.
            Node::Morph { radius, arg, .. } => arg.constant_over(&b.grow(*radius as i64)),
        }
    }

    /// Evaluates the term over the box `b` into `out` (x fastest, then y, then z; one u16 per
    /// voxel). Sub-boxes whose value is certain are filled without sampling.
    ///
    /// # Errors
    /// A stored volume operand fails to read.
    pub fn eval(&self, b: &Box3, out: &mut [u16]) -> Result<(), crate::store::StoreError> {
        debug_assert_eq!(out.len() as u128, b.voxels());
        if let Some(v) = self.constant_over(b) {
            out.fill(v);
            return Ok(());
        }
        let t = self.voxel_type;
        match &self.node {
            Node::Primitive(p) => eval_primitive(p.as_ref(), t, b, b, out),
            Node::Volume {
                snap,
                shift,
                source,
            } => read_volume_box(snap, *shift, source, b, out)?,
            Node::Binary(op, x, y) => {
                x.eval(b, out)?;
                let mut other = vec![0u16; out.len()];
                y.eval(b, &mut other)?;
                for (o, d2) in out.iter_mut().zip(other) {
                    *o = op.apply(*o, d2, t);
                }
            }
            Node::Unary(op, x) => {
                x.eval(b, out)?;
                for o in out.iter_mut() {
                    *o = op.apply(*o, t);
                }
            }
            Node::Grid { frame, values } => {
                let mut i = 0;
                for z in b.min[2]..b.max[2] {
                    for y in b.min[1]..b.max[1] {
                        for x in b.min[0]..b.max[0] {
                            out[i] = grid_value(frame, values, [x, y, z], t);
                            i += 1;
                        }
                    }
                }
            }
            Node::Morph {
                dilate,
                radius,
                arg,
            } => {
                let grown = b.grow(*radius as i64);
                let mut field = vec![0u16; grown.voxels() as usize];
                arg.eval(&grown, &mut field)?;
                morph_crop(&mut field, &grown, b, *radius as usize, *dilate, out);
            }
        }
        Ok(())
    }
}

/// Voxels below which a box is sampled voxel by voxel rather than split further.
const SPLIT_BELOW: u128 = 512;

/// Evaluates a primitive over `b`, a sub-box of `frame` (the layout of `out`): boxes whose value
/// is certain are filled, others split in two along their longest axis until small, so only the
/// voxels near the surface are sampled one by one.
fn eval_primitive(p: &dyn Primitive, t: VoxelType, frame: &Box3, b: &Box3, out: &mut [u16]) {
    let size = [0, 1, 2].map(|a| (frame.max[a] - frame.min[a]) as usize);
    let index = |x: i64, y: i64, z: i64| {
        (((z - frame.min[2]) as usize * size[1] + (y - frame.min[1]) as usize) * size[0])
            + (x - frame.min[0]) as usize
    };
    if let Some(v) = constant_over(p, b, t) {
        for z in b.min[2]..b.max[2] {
            for y in b.min[1]..b.max[1] {
                let row = index(b.min[0], y, z);
                out[row..row + (b.max[0] - b.min[0]) as usize].fill(v);
            }
        }
        return;
    }
    if b.voxels() <= SPLIT_BELOW {
        let inside = b.intersect(&p.bbox());
        let width = (b.max[0] - b.min[0]) as usize;
        for z in b.min[2]..b.max[2] {
            for y in b.min[1]..b.max[1] {
                let row = index(b.min[0], y, z);
                let line = &mut out[row..row + width];
                let in_yz = (inside.min[1]..inside.max[1]).contains(&y)
                    && (inside.min[2]..inside.max[2]).contains(&z);
                if inside.is_empty() || !in_yz {
                    line.fill(t.low());
                    continue;
                }
                let (x0, x1) = (
                    (inside.min[0] - b.min[0]) as usize,
                    (inside.max[0] - b.min[0]) as usize,
                );
                line[..x0].fill(t.low());
                line[x1..].fill(t.low());
                p.sample_row(inside.min[0], y, z, t, &mut line[x0..x1]);
            }
        }
        return;
    }
    let axis = (0..3).max_by_key(|&a| b.max[a] - b.min[a]).unwrap_or(0);
    let mid = b.min[axis] + (b.max[axis] - b.min[axis]) / 2;
    let (mut lo, mut hi) = (*b, *b);
    lo.max[axis] = mid;
    hi.min[axis] = mid;
    eval_primitive(p, t, frame, &lo, out);
    eval_primitive(p, t, frame, &hi, out);
}

/// The B-box of a binary node from its children's (`spec/icvg.md`): union-like operators
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

/// One voxel of a volume's level 0 (None outside it).
fn volume_voxel(snap: &Snapshot, v: [i64; 3]) -> Option<u16> {
    let layout = snap.layout();
    let dims = layout.dims();
    if (0..3).any(|a| v[a] < 0 || v[a] >= dims[a] as i64) {
        return None;
    }
    let b = layout.brick() as i64;
    let key = BrickKey {
        level: 0,
        x: (v[0] / b) as u32,
        y: (v[1] / b) as u32,
        z: (v[2] / b) as u32,
    };
    let bytes = snap.read(key).ok()?;
    let i = (((v[2] % b) * b + v[1] % b) * b + v[0] % b) as usize;
    Some(match layout.voxel_type() {
        VoxelType::U8 => bytes[i] as u16,
        VoxelType::U16 => u16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]]),
    })
}

/// Copies the voxels of world box `b` from the box `source` of a volume moved by `origin`
/// (world = source voxel + origin; L elsewhere).
fn read_volume_box(
    snap: &Snapshot,
    origin: [i64; 3],
    source: &Box3,
    b: &Box3,
    out: &mut [u16],
) -> Result<(), crate::store::StoreError> {
    let layout = snap.layout();
    let edge = layout.brick() as i64;
    let vt = layout.voxel_type();
    out.fill(0);
    let local = Box3::new(
        [0, 1, 2].map(|a| b.min[a] - origin[a]),
        [0, 1, 2].map(|a| b.max[a] - origin[a]),
    )
    .intersect(source);
    if local.is_empty() {
        return Ok(());
    }
    let size = [0, 1, 2].map(|a| (b.max[a] - b.min[a]) as usize);
    let mut buf = vec![0u8; layout.brick_bytes()];
    for bz in local.min[2] / edge..=(local.max[2] - 1) / edge {
        for by in local.min[1] / edge..=(local.max[1] - 1) / edge {
            for bx in local.min[0] / edge..=(local.max[0] - 1) / edge {
                snap.read_into(
                    BrickKey {
                        level: 0,
                        x: bx as u32,
                        y: by as u32,
                        z: bz as u32,
                    },
                    &mut buf,
                )?;
                let brick = Box3::new(
                    [bx * edge, by * edge, bz * edge],
                    [(bx + 1) * edge, (by + 1) * edge, (bz + 1) * edge],
                )
                .intersect(&local);
                for z in brick.min[2]..brick.max[2] {
                    for y in brick.min[1]..brick.max[1] {
                        for x in brick.min[0]..brick.max[0] {
                            let i = (((z - bz * edge) * edge + y - by * edge) * edge + x
                                - bx * edge) as usize;
                            let v = match vt {
                                VoxelType::U8 => buf[i] as u16,
                                VoxelType::U16 => u16::from_le_bytes([buf[2 * i], buf[2 * i + 1]]),
                            };
                            let o = [
                                x + origin[0] - b.min[0],
                                y + origin[1] - b.min[1],
                                z + origin[2] - b.min[2],
                            ]
                            .map(|c| c as usize);
                            out[(o[2] * size[1] + o[1]) * size[0] + o[0]] = v;
                        }
                    }
                }
            }
        }
    }
    Ok(())
}

/// Separable grey-value morphology: the max (dilate) or min (erode) over a cube of side
/// `2r + 1`, as three one-dimensional passes (x, then y, then z) over `field` (the values of
/// `grown`, which is `b` grown by `r`), written for the voxels of `b` into `out`.
fn morph_crop(field: &mut [u16], grown: &Box3, b: &Box3, r: usize, dilate: bool, out: &mut [u16]) {
    let n = [0, 1, 2].map(|a| (grown.max[a] - grown.min[a]) as usize);
    let pick = |a: u16, c: u16| if dilate { a.max(c) } else { a.min(c) };
    let stride = [1, n[0], n[0] * n[1]];
    let mut line = Vec::new();
    for axis in 0..3 {
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        for j in 0..n[v] {
            for i in 0..n[u] {
                let base = i * stride[u] + j * stride[v];
                line.clear();
                line.extend((0..n[axis]).map(|k| field[base + k * stride[axis]]));
                for k in 0..n[axis] {
                    let lo = k.saturating_sub(r);
                    let hi = (k + r).min(n[axis] - 1);
                    let mut best = line[lo];
                    for &x in &line[lo + 1..=hi] {
                        best = pick(best, x);
                    }
                    field[base + k * stride[axis]] = best;
                }
            }
        }
    }
    let size = [0, 1, 2].map(|a| (b.max[a] - b.min[a]) as usize);
    for z in 0..size[2] {
        for y in 0..size[1] {
            let from = ((z + r) * n[1] + y + r) * n[0] + r;
            let to = (z * size[1] + y) * size[0];
            out[to..to + size[0]].copy_from_slice(&field[from..from + size[0]]);
        }
    }
}

/// A value of a sampled array over `frame`, L outside it.
fn grid_value(frame: &Box3, values: &[u16], v: [i64; 3], t: VoxelType) -> u16 {
    if !frame.contains(v) {
        return t.low();
    }
    let n = [0, 1, 2].map(|a| (frame.max[a] - frame.min[a]) as usize);
    let [x, y, z] = [0, 1, 2].map(|a| (v[a] - frame.min[a]) as usize);
    values[(z * n[1] + y) * n[0] + x]
}
