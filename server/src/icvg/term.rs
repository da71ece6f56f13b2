//! CVG terms compiled for evaluation: validated, with B-boxes, evaluated over boxes of voxels.

use super::morph;
use super::ops::{BinaryOp, UnaryOp};
use super::primitives::Primitive;
use crate::cancel::{CancelToken, Stopped};
use crate::geometry::Box3;
use crate::store::{Snapshot, StoreError};
use isovox_proto::icvg::Attributes;
use isovox_proto::{BrickKey, VoxelType};
use std::collections::BTreeMap;
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

/// Why a term (or an edit request) is refused. The message says what and where.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TermError {
    /// Operators nested deeper than [`TermLimits::max_depth`].
    #[error("term is nested deeper than {0} levels")]
    TooDeep(usize),
    /// More nodes than [`TermLimits::max_nodes`].
    #[error("term has more than {0} nodes")]
    TooManyNodes(usize),
    /// A primitive wider than [`TermLimits::max_extent`].
    #[error("{what} spans {extent} voxels, more than the limit of {limit}")]
    TooWide {
        /// What is too wide.
        what: String,
        /// Its extension in voxels.
        extent: u64,
        /// The limit.
        limit: u32,
    },
    /// A size, radius, parameter or operator out of its range, or a missing or superfluous
    /// part of the request.
    #[error("{0}")]
    Invalid(String),
    /// A volume or mesh the term names is not there (a 404 over HTTP, as for any resource
    /// named that is not there).
    #[error("{0}")]
    Unknown(String),
    /// A volume the term names does not fit the edited one, or cannot be read.
    #[error("{0}")]
    Volume(String),
    /// A mesh the term names cannot be used or placed.
    #[error("{0}")]
    Mesh(String),
    /// Preparing the term (voxelizing a mesh leaf, filtering a morphology argument) would
    /// sample more voxels than one edit may.
    #[error("{what} would sample {voxels} voxels within the edited box; this server allows {limit} per edit (--max-edit-voxels): give a region, or split the edit")]
    OverBudget {
        /// What would sample them.
        what: String,
        /// The voxels it would sample, with those counted before it.
        voxels: u64,
        /// The limit.
        limit: u64,
    },
    /// Compiling was stopped (its deadline passed, or its client left).
    #[error(transparent)]
    Stopped(#[from] Stopped),
}

/// Why evaluating a term failed.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A stored volume operand could not be read.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The work was stopped (its deadline passed, or its client left).
    #[error(transparent)]
    Stopped(#[from] Stopped),
}

/// Where a term will be evaluated and what compiling it may spend: set by the edit that
/// compiles it ([`CompiledTerm::compile_in`]).
#[derive(Debug, Clone, Default)]
pub struct Scope {
    /// The voxels the term will be evaluated over (an edit's target: the volume, or its region
    /// within it). Mesh leaves are voxelized only there (grown by the radius of every
    /// morphology above them). `None`: anywhere, so a mesh leaf is voxelized over its whole
    /// placed extent.
    pub within: Option<Box3>,
    /// Most voxels the term may sample besides its own evaluation: mesh leaves voxelized and
    /// morphology arguments filtered over their input boxes. `None`: no limit.
    pub max_voxels: Option<u64>,
    /// Stops the compilation (a mesh leaf being voxelized).
    pub cancel: CancelToken,
}

/// Finds the stored volumes a term names (`{"volume": {"name": ...}}`).
pub trait VolumeResolver {
    /// # Errors
    /// No volume of that name.
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError>;

    /// The volume `name` at `version` (what replaying an edit reads).
    ///
    /// # Errors
    /// No volume of that name, or it no longer holds that version.
    fn resolve_at(&self, name: &str, version: u64) -> Result<Arc<Snapshot>, TermError> {
        let snap = self.resolve(name)?;
        if snap.version == version {
            return Ok(snap);
        }
        Err(TermError::Volume(format!(
            "volume {name:?} at version {version}: older versions cannot be read here"
        )))
    }

    /// The uploaded mesh with this content hash (for `mesh` leaves).
    ///
    /// # Errors
    /// No such mesh, or no mesh store here.
    fn mesh(&self, hash: u64) -> Result<Arc<crate::voxelize::solid::TriMesh>, TermError> {
        Err(TermError::Unknown(format!(
            "mesh {hash:016x}: meshes are not available here"
        )))
    }
}

/// A resolver that notes the version of every volume it finds: what an edit's commit records,
/// so that replaying the edit (an undo under it) reads the same voxels
/// ([`PinnedReads`]).
pub struct RecordingReads<'a> {
    inner: &'a dyn VolumeResolver,
    reads: std::sync::Mutex<BTreeMap<String, u64>>,
}

impl<'a> RecordingReads<'a> {
    /// Finds volumes and meshes through `inner`.
    pub fn new(inner: &'a dyn VolumeResolver) -> Self {
        RecordingReads {
            inner,
            reads: std::sync::Mutex::new(BTreeMap::new()),
        }
    }

    /// The version of each volume found, by name.
    pub fn into_reads(self) -> BTreeMap<String, u64> {
        self.reads.into_inner().unwrap_or_else(|p| p.into_inner())
    }
}

impl std::fmt::Debug for RecordingReads<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecordingReads").finish_non_exhaustive()
    }
}

impl VolumeResolver for RecordingReads<'_> {
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        let snap = self.inner.resolve(name)?;
        self.reads
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(name.to_string(), snap.version);
        Ok(snap)
    }

    fn resolve_at(&self, name: &str, version: u64) -> Result<Arc<Snapshot>, TermError> {
        self.inner.resolve_at(name, version)
    }

    fn mesh(&self, hash: u64) -> Result<Arc<crate::voxelize::solid::TriMesh>, TermError> {
        self.inner.mesh(hash)
    }
}

/// A resolver that finds each volume at the version an edit's commit recorded it read: what
/// replaying the edit resolves its `volume` leaves through.
pub struct PinnedReads<'a> {
    inner: &'a dyn VolumeResolver,
    reads: &'a BTreeMap<String, u64>,
}

impl<'a> PinnedReads<'a> {
    /// `inner`'s volumes at the versions `reads` names.
    pub fn new(inner: &'a dyn VolumeResolver, reads: &'a BTreeMap<String, u64>) -> Self {
        PinnedReads { inner, reads }
    }
}

impl std::fmt::Debug for PinnedReads<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PinnedReads")
            .field("reads", self.reads)
            .finish_non_exhaustive()
    }
}

impl VolumeResolver for PinnedReads<'_> {
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        let version = self.reads.get(name).ok_or_else(|| {
            TermError::Volume(format!(
                "the edit did not record the version of volume {name:?} it read"
            ))
        })?;
        self.inner.resolve_at(name, *version)
    }

    fn resolve_at(&self, name: &str, version: u64) -> Result<Arc<Snapshot>, TermError> {
        self.inner.resolve_at(name, version)
    }

    fn mesh(&self, hash: u64) -> Result<Arc<crate::voxelize::solid::TriMesh>, TermError> {
        self.inner.mesh(hash)
    }
}

/// A resolver that knows no volume.
#[derive(Debug)]
pub struct NoVolumes;

impl VolumeResolver for NoVolumes {
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        Err(TermError::Unknown(format!(
            "unknown volume {name:?} in term"
        )))
    }
}

/// A compiled term node.
#[derive(Debug)]
pub enum Node {
    /// A primitive, placed.
    Primitive(Box<dyn Primitive>),
    /// A box `source` of another volume's level 0, moved by `shift` (world = source + shift).
    Volume {
        /// The other volume's version read.
        snap: Arc<Snapshot>,
        /// World position minus source position.
        shift: [i64; 3],
        /// The box of the other volume's voxels used.
        source: Box3,
    },
    /// A binary operator and its operands.
    Binary(BinaryOp, Box<CompiledTerm>, Box<CompiledTerm>),
    /// A unary operator and its operand.
    Unary(UnaryOp, Box<CompiledTerm>),
    /// Values sampled once into an array over `frame` (a voxelized mesh); L outside.
    Grid {
        /// The box the values cover.
        frame: Box3,
        /// The values, x fastest.
        values: Vec<u16>,
    },
    /// Dilation (max) or erosion (min) over a cube of side `2 * radius + 1`.
    Morph {
        /// Dilation when true, erosion when false.
        dilate: bool,
        /// The window is the cube of side 2 * radius + 1.
        radius: u32,
        /// The term filtered.
        arg: Box<CompiledTerm>,
    },
}

/// A term ready to evaluate, with its B-box: outside it the term is L. `None` means unbounded
/// (an operator that maps (L, L) to something else: inverse, divide, add_scalar with k > 0).
#[derive(Debug)]
pub struct CompiledTerm {
    /// The node.
    pub node: Node,
    /// The B-box (see above).
    pub bbox: Option<Box3>,
    /// The voxel type it is evaluated for.
    pub voxel_type: VoxelType,
    /// A leaf's attribute values (none for operators).
    pub attrs: Attributes,
}

/// What a term gives an attribute channel at a voxel where no leaf gives it a value: the
/// volume keeps its own there.
pub const KEEP: u64 = u64::MAX;

impl CompiledTerm {
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
            Node::Primitive(p) => p.constant_over(b, t),
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
    pub fn eval(&self, b: &Box3, out: &mut [u16]) -> Result<(), EvalError> {
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
                op.apply_in_place(out, &other, t);
            }
            Node::Unary(op, x) => {
                x.eval(b, out)?;
                op.apply_in_place(out, t);
            }
            Node::Grid { frame, values } => copy_grid(frame, values, b, t.low(), out),
            Node::Morph {
                dilate,
                radius,
                arg,
            } => match morph::boxes(b, self.bbox, arg.bbox, *radius, *dilate) {
                None => out.fill(t.low()),
                Some((part, input)) => {
                    let values =
                        morph::filter(arg, &part, &input, *radius, *dilate, &CancelToken::never())?;
                    copy_grid(&part, &values, b, t.low(), out);
                }
            },
        }
        Ok(())
    }

    /// Whether a leaf of the term gives channel `channel` values: its own attribute, or a
    /// stored volume leaf whose volume has that channel. A term that gives none leaves the
    /// channel as it is.
    pub fn gives(&self, channel: &str) -> bool {
        if self.attrs.get(channel).is_some() {
            return true;
        }
        match &self.node {
            Node::Primitive(_) | Node::Grid { .. } => false,
            Node::Volume { snap, .. } => snap.header().stream_named(channel).is_some(),
            Node::Binary(_, x, y) => x.gives(channel) || y.gives(channel),
            Node::Unary(_, x) => x.gives(channel),
            Node::Morph { arg, .. } => arg.uniform(channel).is_some(),
        }
    }

    /// The one value every leaf of the term gives `channel`, if they all give the same (what
    /// a morphology of the term gives: the filter moves the surface, not the names on it).
    fn uniform(&self, channel: &str) -> Option<u64> {
        if let Some(v) = self.attrs.get(channel) {
            return Some(v);
        }
        match &self.node {
            Node::Primitive(_) | Node::Grid { .. } | Node::Volume { .. } => None,
            Node::Binary(_, x, y) => {
                let v = x.uniform(channel)?;
                (y.uniform(channel)? == v).then_some(v)
            }
            Node::Unary(_, x) => x.uniform(channel),
            Node::Morph { arg, .. } => arg.uniform(channel),
        }
    }

    /// Evaluates the term over `b` into `out` as [`CompiledTerm::eval`] does, and the values
    /// it gives the channel `channel` into `values` ([`KEEP`] where none): leaves give their
    /// attribute (a stored volume leaf without one, its volume's channel), operators pick
    /// each voxel's from one operand by [`BinaryOp::attributes_from`]. Where the term is L
    /// (empty) it gives none, whatever its operands gave: so a voxel's value never depends on
    /// how the evaluated box was cut.
    ///
    /// # Errors
    /// A stored volume operand fails to read.
    pub fn eval_channel(
        &self,
        b: &Box3,
        channel: &str,
        out: &mut [u16],
        values: &mut [u64],
    ) -> Result<(), EvalError> {
        debug_assert_eq!(out.len(), values.len());
        let outside = self.bbox.is_some_and(|bb| b.intersect(&bb).is_empty());
        if outside || !self.gives(channel) {
            values.fill(KEEP);
            return self.eval(b, out);
        }
        if let Some(v) = self.attrs.get(channel) {
            self.eval(b, out)?;
            values.fill(v);
            keep_where_empty(out, values);
            return Ok(());
        }
        match &self.node {
            Node::Binary(op, x, y) => {
                x.eval_channel(b, channel, out, values)?;
                let mut other = vec![0u16; out.len()];
                let mut other_values = vec![KEEP; out.len()];
                y.eval_channel(b, channel, &mut other, &mut other_values)?;
                let from = op.attributes_from();
                for i in 0..out.len() {
                    values[i] = from.pick(out[i], values[i], other[i], other_values[i]);
                }
                op.apply_in_place(out, &other, self.voxel_type);
            }
            Node::Unary(op, x) => {
                x.eval_channel(b, channel, out, values)?;
                op.apply_in_place(out, self.voxel_type);
            }
            Node::Volume {
                snap,
                shift,
                source,
            } => {
                self.eval(b, out)?;
                match snap.channel(channel) {
                    Some(view) => {
                        let mut read = vec![0u16; out.len()];
                        read_volume_box(&view, *shift, source, b, &mut read)?;
                        for (v, r) in values.iter_mut().zip(read) {
                            *v = r as u64;
                        }
                    }
                    None => values.fill(KEEP),
                }
            }
            Node::Morph { arg, .. } => {
                self.eval(b, out)?;
                values.fill(arg.uniform(channel).unwrap_or(KEEP));
            }
            Node::Primitive(_) | Node::Grid { .. } => {
                self.eval(b, out)?;
                values.fill(KEEP);
            }
        }
        keep_where_empty(out, values);
        Ok(())
    }

    /// Every attribute value a leaf of the term names for `channel` (for checking them
    /// against the channel's type before an edit runs).
    pub fn attribute_values(&self, channel: &str, out: &mut Vec<u64>) {
        out.extend(self.attrs.get(channel));
        match &self.node {
            Node::Binary(_, x, y) => {
                x.attribute_values(channel, out);
                y.attribute_values(channel, out);
            }
            Node::Unary(_, x) => x.attribute_values(channel, out),
            Node::Morph { arg, .. } => arg.attribute_values(channel, out),
            Node::Primitive(_) | Node::Grid { .. } | Node::Volume { .. } => {}
        }
    }

    /// Replaces every morphology node by a grid of its values over the part of `b` it reaches
    /// (computed once, with `cancel` checked as it goes), so that evaluating the term brick by
    /// brick over `b` reads them instead of filtering each brick's grown box again. Evaluating
    /// outside `b` afterwards gives L where a morphology node was.
    ///
    /// # Errors
    /// An argument fails to evaluate, or `cancel` stops the work.
    pub fn materialize(&mut self, b: &Box3, cancel: &CancelToken) -> Result<(), EvalError> {
        let grid = match &mut self.node {
            Node::Primitive(_) | Node::Volume { .. } | Node::Grid { .. } => return Ok(()),
            Node::Binary(_, x, y) => {
                x.materialize(b, cancel)?;
                return y.materialize(b, cancel);
            }
            Node::Unary(_, x) => return x.materialize(b, cancel),
            Node::Morph {
                dilate,
                radius,
                arg,
            } => match morph::boxes(b, self.bbox, arg.bbox, *radius, *dilate) {
                None => (Box3::new([0; 3], [0; 3]), Vec::new()),
                Some((part, input)) => {
                    arg.materialize(&input, cancel)?;
                    let values = morph::filter(arg, &part, &input, *radius, *dilate, cancel)?;
                    (part, values)
                }
            },
        };
        self.bbox = Some(grid.0);
        self.node = Node::Grid {
            frame: grid.0,
            values: grid.1,
        };
        Ok(())
    }
}

/// A leaf names no attribute where it is L (empty): there it gives [`KEEP`], so that what a
/// voxel gets never depends on how the evaluated box was cut into bricks.
fn keep_where_empty(density: &[u16], values: &mut [u64]) {
    for (v, &d) in values.iter_mut().zip(density) {
        if d == 0 {
            *v = KEEP;
        }
    }
}

/// Copies the values of `frame` (x fastest) into `out` over `b`, L where `b` leaves `frame`.
fn copy_grid(frame: &Box3, values: &[u16], b: &Box3, low: u16, out: &mut [u16]) {
    let inside = b.intersect(frame);
    if inside != *b {
        out.fill(low);
    }
    if inside.is_empty() {
        return;
    }
    let (nf, nb) = (size(frame), size(b));
    let width = (inside.max[0] - inside.min[0]) as usize;
    for z in inside.min[2]..inside.max[2] {
        for y in inside.min[1]..inside.max[1] {
            let from = (((z - frame.min[2]) as usize * nf[1] + (y - frame.min[1]) as usize)
                * nf[0])
                + (inside.min[0] - frame.min[0]) as usize;
            let to = (((z - b.min[2]) as usize * nb[1] + (y - b.min[1]) as usize) * nb[0])
                + (inside.min[0] - b.min[0]) as usize;
            out[to..to + width].copy_from_slice(&values[from..from + width]);
        }
    }
}

fn size(b: &Box3) -> [usize; 3] {
    [0, 1, 2].map(|a| (b.max[a] - b.min[a]).max(0) as usize)
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
    if let Some(v) = p.constant_over(b, t) {
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
    // Density: its values fit a u16.
    Some(isovox_proto::voxel::value_at(&bytes, layout.voxel_type(), i) as u16)
}

/// Copies the voxels of world box `b` from the box `source` of a volume moved by `origin`
/// (world = source voxel + origin; L elsewhere).
fn read_volume_box(
    snap: &Snapshot,
    origin: [i64; 3],
    source: &Box3,
    b: &Box3,
    out: &mut [u16],
) -> Result<(), StoreError> {
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
                                // Density: u16 (its values fit a u16).
                                t => isovox_proto::voxel::value_at(&buf, t, i) as u16,
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

/// A value of a sampled array over `frame`, L outside it.
fn grid_value(frame: &Box3, values: &[u16], v: [i64; 3], t: VoxelType) -> u16 {
    if !frame.contains(v) {
        return t.low();
    }
    let n = [0, 1, 2].map(|a| (frame.max[a] - frame.min[a]) as usize);
    let [x, y, z] = [0, 1, 2].map(|a| (v[a] - frame.min[a]) as usize);
    values[(z * n[1] + y) * n[0] + x]
}
