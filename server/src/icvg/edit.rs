//! Edits: `op(volume, term)` applied brick by brick to a stored volume, then committed.
//!
//! Only bricks that can change are visited (`docs/icvg.md`): for operators with
//! `op(D1, L) = D1` (union, the differences, add, trim) the bricks the term's B-box reaches; for
//! operators that give a constant outside the term (intersection, cap, modulate, product: L;
//! divide, divide_a: H) every brick of the region, those outside the B-box pointed at the shared
//! constant without touching a voxel; for unary operators the bricks of the region. Bricks are
//! evaluated in parallel (rayon), deduplicated, and the coarser levels recomputed only above the
//! bricks that changed, so the cost is proportional to the change, not to the volume.
//!
//! Cost: what an edit evaluates is known before it starts ([`Edit::evaluated_voxels`]: its
//! bricks, plus what its term samples besides, counted when it is compiled: mesh leaves
//! voxelized within the edit's box, morphology arguments over their grown boxes), so a server
//! refuses what is over its budget. A [`CancelToken`] is checked between bricks and inside
//! every long loop below them, so an edit past its deadline, or whose client left, stops
//! without committing anything.

use super::compile::check_k;
use super::ops::{AttributesFrom, BinaryOp, Outside, UnaryOp};
use super::term::{
    CompiledTerm, EvalError, RecordingReads, Scope, TermError, TermLimits, VolumeResolver, KEEP,
};
use crate::cancel::CancelToken;
use crate::geometry::Box3;
use crate::store::transaction::{ChangedKeys, CheckpointPolicy, Transaction, BRICKS_PER_JOB};
use crate::store::writer::Vod2Writer;
use crate::store::{BrickVoxels, Snapshot};
use isovox_proto::channel::ChannelInfo;
use isovox_proto::history::{CommitInfo, CommitKind, CommitNote, OpSummary};
use isovox_proto::icvg::{EditRequest, Overwrite, MAX_COORDINATE};
use isovox_proto::vod2::FileHeader;
use isovox_proto::voxel::{set_value_at as set_value, value_at};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// What an edit does.
#[derive(Debug)]
pub enum EditKind {
    /// `op(volume, term)`.
    Binary(BinaryOp, CompiledTerm),
    /// `op(volume)`.
    Unary(UnaryOp),
    /// `paint`: the channel `channel` takes the term's values where the term is inside (at
    /// least S), density unchanged; with [`Overwrite::Empty`] only where the channel is 0.
    Paint {
        /// The channel written.
        channel: String,
        /// Which voxels it may write.
        overwrite: Overwrite,
        /// Where, and what values.
        term: CompiledTerm,
    },
}

/// A validated edit, ready to apply.
#[derive(Debug)]
pub struct Edit {
    /// What the edit does.
    pub kind: EditKind,
    /// Where the edit applies (level-0 voxels, max exclusive); the whole volume when `None`.
    pub region: Option<Box3>,
    /// Voxels its term samples besides its evaluation brick by brick (mesh leaves voxelized,
    /// morphology arguments), counted when it was compiled.
    pub sampled: u64,
    /// What its commit records of it (its request, what it reads, who made it): filled by
    /// [`Edit::for_volume`], the author by the caller. Edits built otherwise record nothing.
    pub note: CommitNote,
}

/// What an edit changed.
#[derive(Debug, Clone, Serialize)]
pub struct EditOutcome {
    /// The version committed (or staged).
    pub version: u64,
    /// Changed bricks per level (level 0 first), as `[x, y, z]`.
    pub changed: ChangedKeys,
    /// Level-0 bricks whose voxels were evaluated.
    pub evaluated: usize,
    /// Brick records appended (new unique content).
    pub new_records: u64,
    /// Whether the commit wrote a full index checkpoint.
    pub checkpoint: bool,
    /// How long evaluating, storing and committing took, in microseconds as an edit's HTTP
    /// answer says it (`elapsed_us`).
    #[serde(rename = "elapsed_us", serialize_with = "micros")]
    pub elapsed: Duration,
    /// Whether a version was committed (`false`: the edit reaches no voxel of the volume, see
    /// [`Edit::reaches_nothing`]).
    pub committed: bool,
    /// Changed bricks of attribute channels, by channel name, per level; only channels that
    /// changed.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub channels: BTreeMap<String, ChangedKeys>,
    /// Level-0 density voxels whose value the edit changed.
    pub voxels_changed: u64,
}

fn micros<S: serde::Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_u64(d.as_micros() as u64)
}

impl Edit {
    /// Builds an edit from its JSON request, its term compiled to be evaluated anywhere (mesh
    /// leaves voxelized over their whole placed extent): for terms tried on no particular
    /// volume. [`Edit::for_volume`] is what servers and the command line use.
    ///
    /// # Errors
    /// An unknown operator, a missing or superfluous term, `s_l` or `k`, a bad `s_l` or `k`, a
    /// region corner beyond the coordinate limit, or a term that does not compile. A region
    /// with `max <= min` on an axis is no error: it selects nothing, and the edit changes
    /// nothing (as one whose term misses the volume).
    pub fn from_request(
        req: &EditRequest,
        t: VoxelType,
        limits: &TermLimits,
        volumes: &dyn VolumeResolver,
    ) -> Result<Edit, TermError> {
        Edit::build(req, t, limits, volumes, |_| Scope::default())
    }

    /// Builds an edit of a volume of `layout` from its JSON request: its term is compiled to be
    /// evaluated only within the edit's target (the volume, or its region within it), with
    /// what it samples besides counted against `max_voxels`, and `cancel` checked while mesh
    /// leaves are voxelized.
    ///
    /// # Errors
    /// As [`Edit::from_request`]; [`TermError::OverBudget`] past `max_voxels`;
    /// [`TermError::Stopped`] when `cancel` stops the compilation.
    pub fn for_volume(
        req: &EditRequest,
        header: &FileHeader,
        limits: &TermLimits,
        volumes: &dyn VolumeResolver,
        max_voxels: Option<u64>,
        cancel: &CancelToken,
    ) -> Result<Edit, TermError> {
        let layout = &header.layout;
        let volume = Box3::of_volume(layout);
        let reading = RecordingReads::new(volumes);
        let mut edit = Edit::build(req, layout.voxel_type(), limits, &reading, |region| Scope {
            within: Some(region.map_or(volume, |r| r.intersect(&volume))),
            max_voxels,
            cancel: cancel.clone(),
        })?;
        edit.check_channels(header)?;
        let reach = edit.reach(layout);
        let request = EditRequest {
            message: None,
            ..req.clone()
        };
        edit.note = CommitNote {
            info: CommitInfo {
                kind: Some(CommitKind::Edit),
                message: req.message.clone(),
                op: Some(OpSummary::of(req, reach)),
                ..CommitInfo::default()
            },
            request: Some(request),
            reads: reading.into_reads(),
        };
        Ok(edit)
    }

    fn build(
        req: &EditRequest,
        t: VoxelType,
        limits: &TermLimits,
        volumes: &dyn VolumeResolver,
        scope: impl FnOnce(Option<Box3>) -> Scope,
    ) -> Result<Edit, TermError> {
        let region = match req.region {
            Some(r) => {
                if r.min
                    .iter()
                    .chain(&r.max)
                    .any(|c| c.unsigned_abs() > MAX_COORDINATE as u64)
                {
                    return Err(TermError::Invalid(format!(
                        "region {:?}..{:?} reaches beyond +-{MAX_COORDINATE}, the coordinate limit",
                        r.min, r.max
                    )));
                }
                Some(r)
            }
            None => None,
        };
        // An argument the operator does not take is a mistake the caller should hear about.
        if req.s_l.is_some() && req.op != "divide" {
            return Err(TermError::Invalid(format!(
                "\"s_l\" belongs to divide, not to {:?}",
                req.op
            )));
        }
        if req.k.is_some() && req.op != "add_scalar" {
            return Err(TermError::Invalid(format!(
                "\"k\" belongs to add_scalar, not to {:?}",
                req.op
            )));
        }
        if (req.channel.is_some() || req.overwrite.is_some()) && req.op != "paint" {
            return Err(TermError::Invalid(format!(
                "\"channel\" and \"overwrite\" belong to paint, not to {:?}",
                req.op
            )));
        }
        if req.op == "paint" {
            let term = req.term.as_ref().ok_or_else(|| {
                TermError::Invalid("paint needs a \"term\": where to paint, and what".into())
            })?;
            let channel = req.channel.clone().unwrap_or_else(|| "material".into());
            if !["material", "label"].contains(&channel.as_str()) {
                return Err(TermError::Invalid(format!(
                    "paint writes \"material\" or \"label\", the attributes leaves carry; not {channel:?}"
                )));
            }
            let (term, sampled) =
                CompiledTerm::compile_in(term, t, limits, volumes, &scope(region))?;
            if !term.gives(&channel) {
                return Err(TermError::Invalid(format!(
                    "paint needs a term whose leaves carry \"{channel}\": values to paint"
                )));
            }
            return Ok(Edit {
                kind: EditKind::Paint {
                    channel,
                    overwrite: req.overwrite.unwrap_or_default(),
                    term,
                },
                region,
                sampled,
                note: CommitNote::default(),
            });
        }
        let kind = match req.op.as_str() {
            "inverse" | "complement" | "add_scalar" => {
                if req.term.is_some() {
                    return Err(TermError::Invalid(format!(
                        "{} is unary: it takes no term",
                        req.op
                    )));
                }
                if req.op == "add_scalar" {
                    let k = req
                        .k
                        .ok_or_else(|| TermError::Invalid("add_scalar needs \"k\"".into()))?;
                    check_k(k, t)?;
                    EditKind::Unary(UnaryOp::AddScalar(k))
                } else {
                    EditKind::Unary(UnaryOp::Inverse)
                }
            }
            name => {
                let op = BinaryOp::from_name(name, req.s_l).map_err(TermError::Invalid)?;
                let term = req
                    .term
                    .as_ref()
                    .ok_or_else(|| TermError::Invalid(format!("{name} needs a \"term\"")))?;
                let (term, sampled) =
                    CompiledTerm::compile_in(term, t, limits, volumes, &scope(region))?;
                return Ok(Edit {
                    kind: EditKind::Binary(op, term),
                    region,
                    sampled,
                    note: CommitNote::default(),
                });
            }
        };
        Ok(Edit {
            kind,
            region,
            sampled: 0,
            note: CommitNote::default(),
        })
    }
}

impl Edit {
    /// The level-0 voxels the edit applies to: its region within the volume.
    pub fn target(&self, layout: &VolumeLayout) -> Box3 {
        let volume = Box3::of_volume(layout);
        self.region.map_or(volume, |r| r.intersect(&volume))
    }

    /// The level-0 voxels that can change: for operators with `op(D1, L) = D1` the term's B-box
    /// within the target, else the whole target.
    pub fn reach(&self, layout: &VolumeLayout) -> Box3 {
        let target = self.target(layout);
        match &self.kind {
            EditKind::Binary(op, term) => match (op.outside(layout.voxel_type()), term.bbox) {
                (Outside::Identity, Some(b)) => b.intersect(&target),
                _ => target,
            },
            // Paint writes only where its term is inside.
            EditKind::Paint { term, .. } => term.bbox.map_or(target, |b| b.intersect(&target)),
            EditKind::Unary(_) => target,
        }
    }

    /// The channels of `header` the edit can change: `paint`'s, and for an operator that takes
    /// attributes from the denser operand (union, intersection, add) every channel its term
    /// gives values. A term's attribute for a channel the volume does not have is ignored.
    pub fn channels_touched<'h>(&self, header: &'h FileHeader) -> Vec<&'h ChannelInfo> {
        header
            .channels
            .iter()
            .filter(|c| match &self.kind {
                EditKind::Paint { channel, .. } => *channel == c.name,
                EditKind::Binary(op, term) => {
                    op.attributes_from() == AttributesFrom::Denser && term.gives(&c.name)
                }
                EditKind::Unary(_) => false,
            })
            .collect()
    }

    /// Refuses what the volume `header` describes cannot take: paint of a channel it does not
    /// have, an attribute value beyond its channel's type.
    fn check_channels(&self, header: &FileHeader) -> Result<(), TermError> {
        // Whatever the volume: no channel holds more than a u64 channel does (the document
        // says so).
        if let EditKind::Binary(_, term) | EditKind::Paint { term, .. } = &self.kind {
            let high = largest_attribute(VoxelType::U64);
            for name in ["material", "label"] {
                let mut values = Vec::new();
                term.attribute_values(name, &mut values);
                if let Some(v) = values.iter().find(|&&v| v > high) {
                    return Err(TermError::Invalid(format!(
                        "\"{name}\": {v} is beyond every channel type (at most {high})"
                    )));
                }
            }
        }
        let term = match &self.kind {
            EditKind::Paint { channel, term, .. } => {
                if header.stream_named(channel).is_none() {
                    let names: Vec<&str> =
                        header.channels.iter().map(|c| c.name.as_str()).collect();
                    return Err(TermError::Invalid(format!(
                        "this volume has no channel {channel:?} to paint (its channels: {names:?})"
                    )));
                }
                term
            }
            EditKind::Binary(_, term) => term,
            EditKind::Unary(_) => return Ok(()),
        };
        for c in &header.channels {
            let mut values = Vec::new();
            term.attribute_values(&c.name, &mut values);
            let high = largest_attribute(c.voxel_type);
            if let Some(v) = values.iter().find(|&&v| v > high) {
                return Err(TermError::Invalid(format!(
                    "\"{}\": {v} is beyond the channel's type {} (at most {high})",
                    c.name, c.voxel_type
                )));
            }
        }
        Ok(())
    }

    /// Readies the edit to be evaluated brick by brick (morphology in its term filtered once
    /// over its reach): what [`stage_edit`] does first, for an edit applied by other means (a
    /// replay under an undo, [`edit_voxels`]).
    ///
    /// # Errors
    /// `cancel` stops it.
    pub fn prepare_eval(
        &mut self,
        layout: &VolumeLayout,
        cancel: &CancelToken,
    ) -> Result<(), EvalError> {
        let reach = self.reach(layout);
        if let EditKind::Binary(_, term) | EditKind::Paint { term, .. } = &mut self.kind {
            if !reach.is_empty() {
                term.materialize(&reach, cancel)?;
            }
        }
        Ok(())
    }

    /// Whether the edit can change no voxel of the volume: its reach (the region, or the term's
    /// bounds for an operator that keeps what the term leaves out) is wholly outside it. Such an
    /// edit commits nothing: an empty version would only tell every follower of the change
    /// feed about nothing.
    pub fn reaches_nothing(&self, layout: &VolumeLayout) -> bool {
        self.reach(layout).is_empty()
    }

    /// How many voxels applying the edit evaluates: the level-0 voxels of the bricks it
    /// visits, plus what its term samples besides (mesh leaves, morphology arguments): what an
    /// edit costs, for limits.
    pub fn evaluated_voxels(&self, layout: &VolumeLayout) -> u64 {
        (bricks_meeting_count(layout, &self.reach(layout)) * (layout.brick() as u64).pow(3))
            .saturating_add(self.sampled)
    }
}

/// The level-0 brick range `lo..=hi` per axis that meets `b` (non-empty).
fn brick_range(layout: &VolumeLayout, b: &Box3) -> ([u32; 3], [u32; 3]) {
    let e = layout.brick() as i64;
    let g = layout.grid(0);
    let lo = [0, 1, 2].map(|a| (b.min[a].max(0) / e) as u32);
    let hi = [0, 1, 2].map(|a| (((b.max[a] - 1) / e) as u32).min(g[a] - 1));
    (lo, hi)
}

fn bricks_meeting_count(layout: &VolumeLayout, b: &Box3) -> u64 {
    if b.is_empty() {
        return 0;
    }
    let (lo, hi) = brick_range(layout, b);
    (0..3).map(|a| (hi[a] - lo[a] + 1) as u64).product()
}

/// The level-0 bricks that meet `b`, z slowest.
pub fn bricks_meeting(layout: &VolumeLayout, b: &Box3) -> Vec<BrickKey> {
    if b.is_empty() {
        return Vec::new();
    }
    let (lo, hi) = brick_range(layout, b);
    let mut out = Vec::new();
    for z in lo[2]..=hi[2] {
        for y in lo[1]..=hi[1] {
            for x in lo[0]..=hi[0] {
                out.push(BrickKey { level: 0, x, y, z });
            }
        }
    }
    out
}

/// A density brick's values (density is u8 or u16: its values fit a u16).
fn to_u16(v: &BrickVoxels, layout: &VolumeLayout) -> Vec<u16> {
    match v {
        BrickVoxels::Constant(c) => vec![*c as u16; layout.brick_voxels()],
        BrickVoxels::Data(d) => match layout.voxel_type() {
            VoxelType::U8 => d.iter().map(|&x| x as u16).collect(),
            VoxelType::U16 => d
                .chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect(),
            // Never density; read as any other type, for a total match.
            t => (0..layout.brick_voxels())
                .map(|i| value_at(d, t, i) as u16)
                .collect(),
        },
    }
}

fn from_u16(values: &[u16], layout: &VolumeLayout) -> BrickVoxels {
    let t = layout.voxel_type();
    let bytes = match t {
        VoxelType::U8 => values.iter().map(|&v| v as u8).collect(),
        VoxelType::U16 => values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        _ => {
            let mut bytes = vec![0u8; values.len() * t.bytes()];
            for (i, &v) in values.iter().enumerate() {
                set_value(&mut bytes, t, i, v.into());
            }
            bytes
        }
    };
    BrickVoxels::from_bytes(bytes, t)
}

/// The content of the level-0 brick `key` after `edit` (whose target is `target`) is applied
/// to its content `old`, or `None` when the edit leaves it as it is. What replaying an edit
/// over other voxels than it first met (an undo under it) applies.
///
/// # Errors
/// Evaluating the term fails or is stopped.
pub fn edit_voxels(
    edit: &Edit,
    old: &BrickVoxels,
    layout: &VolumeLayout,
    target: &Box3,
    key: BrickKey,
) -> Result<Option<BrickVoxels>, EvalError> {
    let t = layout.voxel_type();
    let whole = Box3::of_brick(layout, key);
    let eff = whole.intersect(target);
    if eff.is_empty() || matches!(edit.kind, EditKind::Paint { .. }) {
        return Ok(None);
    }
    // Without touching voxels when the brick is wholly edited and both sides are constant.
    if eff == whole {
        let d1 = match old {
            BrickVoxels::Constant(v) => Some(*v as u16),
            BrickVoxels::Data(_) => None,
        };
        let new = match &edit.kind {
            EditKind::Binary(op, term) => match term.constant_over(&eff) {
                // The operand is L here: the operator's outside rule decides.
                Some(b) if b == t.low() => match op.outside(t) {
                    Outside::Identity => return Ok(None),
                    Outside::Constant(c) => Some(c),
                },
                Some(b) => d1.map(|a| op.apply(a, b, t)),
                None => None,
            },
            EditKind::Unary(op) => d1.map(|a| op.apply(a, t)),
            EditKind::Paint { .. } => None,
        };
        if let Some(v) = new {
            let result = BrickVoxels::Constant(v.into());
            return Ok((result != *old).then_some(result));
        }
    }
    let size = [0, 1, 2].map(|a| (eff.max[a] - eff.min[a]) as usize);
    let mut operand = Vec::new();
    if let EditKind::Binary(_, term) = &edit.kind {
        operand = vec![0u16; size[0] * size[1] * size[2]];
        term.eval(&eff, &mut operand)?;
    }
    Ok(apply_operand(edit, old, layout, &eff, &whole, &operand))
}

/// The brick `old` (whose box is `whole`) with `edit` applied over `eff`, the term's values
/// there being `operand` (x fastest; empty for a unary edit), or `None` when that changes
/// nothing.
fn apply_operand(
    edit: &Edit,
    old: &BrickVoxels,
    layout: &VolumeLayout,
    eff: &Box3,
    whole: &Box3,
    operand: &[u16],
) -> Option<BrickVoxels> {
    if matches!(edit.kind, EditKind::Paint { .. }) {
        return None;
    }
    let t = layout.voxel_type();
    let mut values = to_u16(old, layout);
    let size = [0, 1, 2].map(|a| (eff.max[a] - eff.min[a]) as usize);
    let b = layout.brick() as usize;
    let o = [0, 1, 2].map(|a| (eff.min[a] - whole.min[a]) as usize);
    let mut operand_rows = operand.chunks_exact(size[0].max(1));
    for z in 0..size[2] {
        for y in 0..size[1] {
            let row = ((o[2] + z) * b + o[1] + y) * b + o[0];
            let dst = &mut values[row..row + size[0]];
            match &edit.kind {
                EditKind::Binary(op, _) => {
                    let d2 = operand_rows.next().unwrap_or_default();
                    op.apply_in_place(dst, d2, t);
                }
                EditKind::Unary(op) => op.apply_in_place(dst, t),
                EditKind::Paint { .. } => {}
            }
        }
    }
    let result = from_u16(&values, layout);
    (result != *old).then_some(result)
}

/// The term of an edit that can change channels, and for `paint` its mode: `None` for an edit
/// that changes no channel named `channel`.
fn channel_term<'e>(
    edit: &'e Edit,
    channel: &str,
) -> Option<(&'e CompiledTerm, Option<Overwrite>)> {
    match &edit.kind {
        EditKind::Binary(op, term) if op.attributes_from() == AttributesFrom::Denser => {
            Some((term, None))
        }
        EditKind::Paint {
            channel: name,
            overwrite,
            term,
        } if name == channel => Some((term, Some(*overwrite))),
        _ => None,
    }
}

/// A level-0 brick of every stream `edit` can change, after it: density (`None` when
/// unchanged) and each of `channels` (their old contents `values`, in the same order). The
/// term is evaluated once for density and the first channel, not once per stream.
///
/// # Errors
/// Evaluating the term fails or is stopped.
#[allow(clippy::too_many_arguments)]
pub fn edit_streams(
    edit: &Edit,
    density: &BrickVoxels,
    channels: &[&ChannelInfo],
    values: &[BrickVoxels],
    layout: &VolumeLayout,
    target: &Box3,
    key: BrickKey,
) -> Result<(Option<BrickVoxels>, Vec<Option<BrickVoxels>>), EvalError> {
    let whole = Box3::of_brick(layout, key);
    let eff = whole.intersect(target);
    let unchanged = vec![None; channels.len()];
    let term = match &edit.kind {
        EditKind::Binary(_, term) | EditKind::Paint { term, .. } => term,
        EditKind::Unary(_) => {
            return Ok((edit_voxels(edit, density, layout, target, key)?, unchanged))
        }
    };
    if eff.is_empty()
        || term.bbox.is_some_and(|b| b.intersect(&eff).is_empty())
        || channels.is_empty()
    {
        return Ok((edit_voxels(edit, density, layout, target, key)?, unchanged));
    }
    let size = [0, 1, 2].map(|a| (eff.max[a] - eff.min[a]) as usize);
    let n = size[0] * size[1] * size[2];
    let mut operand = Vec::new();
    let mut out = Vec::with_capacity(channels.len());
    for (channel, old) in channels.iter().zip(values) {
        let Some((term, paint)) = channel_term(edit, &channel.name) else {
            out.push(None);
            continue;
        };
        let (mut term_density, mut term_values) = (vec![0u16; n], vec![KEEP; n]);
        term.eval_channel(&eff, &channel.name, &mut term_density, &mut term_values)?;
        out.push(take_values(
            density,
            old,
            layout,
            channel,
            &eff,
            &whole,
            paint,
            &term_density,
            &term_values,
        ));
        if operand.is_empty() {
            operand = term_density;
        }
    }
    if operand.is_empty() {
        return Ok((edit_voxels(edit, density, layout, target, key)?, out));
    }
    Ok((
        apply_operand(edit, density, layout, &eff, &whole, &operand),
        out,
    ))
}

/// The content of the level-0 brick `key` of the channel `channel` after `edit` (whose target
/// is `target`) is applied where the volume's density was `density` and the channel's values
/// `values`, or `None` when the edit leaves it as it is. `layout` is density's. Where the edit
/// takes attributes from the denser operand, a voxel whose term is denser than the volume was
/// takes the term's value; `paint` writes where its term is inside (at least S), only over 0
/// with [`Overwrite::Empty`]. Values the term gives beyond the channel's type saturate.
///
/// # Errors
/// Evaluating the term fails or is stopped.
#[allow(clippy::too_many_arguments)]
pub fn channel_voxels(
    edit: &Edit,
    density: &BrickVoxels,
    values: &BrickVoxels,
    layout: &VolumeLayout,
    channel: &ChannelInfo,
    target: &Box3,
    key: BrickKey,
) -> Result<Option<BrickVoxels>, EvalError> {
    let whole = Box3::of_brick(layout, key);
    let eff = whole.intersect(target);
    let Some((term, paint)) = channel_term(edit, &channel.name) else {
        return Ok(None);
    };
    if eff.is_empty() || term.bbox.is_some_and(|b| b.intersect(&eff).is_empty()) {
        return Ok(None);
    }
    let size = [0, 1, 2].map(|a| (eff.max[a] - eff.min[a]) as usize);
    let n = size[0] * size[1] * size[2];
    let (mut term_density, mut term_values) = (vec![0u16; n], vec![KEEP; n]);
    term.eval_channel(&eff, &channel.name, &mut term_density, &mut term_values)?;
    Ok(take_values(
        density,
        values,
        layout,
        channel,
        &eff,
        &whole,
        paint,
        &term_density,
        &term_values,
    ))
}

/// The channel brick `values` after the term's `term_density` and `term_values` over `eff`
/// are taken where CVG's rule (or `paint`'s mode) says; `None` when nothing changes. Works on
/// the bricks' bytes: only the voxels the term reaches are read, and the channel brick is
/// copied only once a value changes.
#[allow(clippy::too_many_arguments)]
fn take_values(
    density: &BrickVoxels,
    values: &BrickVoxels,
    layout: &VolumeLayout,
    channel: &ChannelInfo,
    eff: &Box3,
    whole: &Box3,
    paint: Option<Overwrite>,
    term_density: &[u16],
    term_values: &[u64],
) -> Option<BrickVoxels> {
    let size = [0, 1, 2].map(|a| (eff.max[a] - eff.min[a]) as usize);
    if size.contains(&0) {
        return None;
    }
    let (density_type, channel_type) = (layout.voxel_type(), channel.voxel_type);
    let (surface, high) = (density_type.surface(), largest_attribute(channel_type));
    let b = layout.brick() as usize;
    let o = [0, 1, 2].map(|a| (eff.min[a] - whole.min[a]) as usize);
    // The channel's bytes, made on the first change.
    let mut new: Option<Vec<u8>> = None;
    let rows = term_density
        .chunks_exact(size[0])
        .zip(term_values.chunks_exact(size[0]));
    for (r, (densities, term_row)) in rows.enumerate() {
        // Rows the term gives nothing to (the corners of a ball's bounding box) are skipped
        // whole.
        if term_row.iter().all(|&v| v == KEEP) {
            continue;
        }
        let (y, z) = (r % size[1], r / size[1]);
        let row = ((o[2] + z) * b + o[1] + y) * b + o[0];
        for (x, (&d, &v)) in densities.iter().zip(term_row).enumerate() {
            if v == KEEP {
                continue;
            }
            let at = row + x;
            let current = match &new {
                Some(bytes) => value_at(bytes, channel_type, at),
                None => voxel_of(values, channel_type, at),
            };
            let takes = match paint {
                None => u64::from(d) > voxel_of(density, density_type, at),
                Some(Overwrite::All) => d >= surface,
                Some(Overwrite::Empty) => d >= surface && current == 0,
            };
            let value = v.min(high);
            if takes && value != current {
                let bytes = new.get_or_insert_with(|| {
                    values
                        .clone()
                        .into_bytes(layout.brick_voxels(), channel_type)
                });
                set_value(bytes, channel_type, at, value);
            }
        }
    }
    new.map(|bytes| BrickVoxels::from_bytes(bytes, channel_type))
}

/// The largest value a term's attribute may give a channel of `voxel_type`: the type's
/// largest, except for u64, whose largest value is the evaluator's mark for "no attribute"
/// ([`KEEP`]), so an edit writes ids up to 2^64 - 2.
pub fn largest_attribute(voxel_type: VoxelType) -> u64 {
    voxel_type.max_value().min(KEEP - 1)
}

/// Voxel `at` of a brick of `voxel_type`.
fn voxel_of(brick: &BrickVoxels, voxel_type: VoxelType, at: usize) -> u64 {
    match brick {
        BrickVoxels::Constant(c) => *c,
        BrickVoxels::Data(bytes) => value_at(bytes, voxel_type, at),
    }
}

/// Applies `edit` to the version `snap` of the file `writer` appends to, and commits the result
/// as the next version. `snap` must be the writer's head. `cancel` is checked until the commit
/// starts (see [`stage_edit`]); a stopped edit commits nothing.
///
/// # Errors
/// Reading a brick fails, `cancel` stops the evaluation, or writing the commit fails (the head
/// is then unchanged).
pub fn apply_edit(
    writer: &mut Vod2Writer,
    snap: &Snapshot,
    edit: &mut Edit,
    policy: CheckpointPolicy,
    cancel: &CancelToken,
) -> Result<EditOutcome, EvalError> {
    let start = Instant::now();
    if edit.reaches_nothing(snap.layout()) {
        return Ok(EditOutcome {
            version: snap.version,
            changed: vec![Vec::new(); usize::from(snap.layout().levels())],
            evaluated: 0,
            new_records: 0,
            checkpoint: false,
            elapsed: start.elapsed(),
            committed: false,
            channels: BTreeMap::new(),
            voxels_changed: 0,
        });
    }
    let mut outcome = stage_edit(writer, snap, edit, policy, cancel)?;
    writer.sync()?;
    outcome.elapsed = start.elapsed();
    Ok(outcome)
}

/// Applies `edit` to the version `snap` and stages the result as the next version, not yet
/// durable (the writer's next sync makes it so, with every other version staged until then).
/// `snap` must be the writer's newest version, staged or durable. Morphology in the term is
/// filtered once over the edit's reach first (the term keeps those values). `cancel` is checked
/// until the bricks are evaluated: a stopped edit has appended nothing.
///
/// # Errors
/// Reading a brick fails, `cancel` stops the evaluation, or appending fails: what was appended
/// is then still in the writer (roll it back to a savepoint taken before, or drop it).
pub fn stage_edit(
    writer: &mut Vod2Writer,
    snap: &Snapshot,
    edit: &mut Edit,
    policy: CheckpointPolicy,
    cancel: &CancelToken,
) -> Result<EditOutcome, EvalError> {
    let start = Instant::now();
    let layout = snap.layout();
    let target = edit.target(layout);
    let reach = edit.reach(layout);
    edit.prepare_eval(layout, cancel)?;
    let edit = &*edit;
    let keys = bricks_meeting(layout, &reach);
    // A few bricks stage fastest on this thread (see BRICKS_PER_JOB: the loops then never
    // split); more, on a worker of the rayon pool, so that the loops' jobs are shared out
    // without this thread handing over and waiting for each.
    let few = keys.len() < 2 * BRICKS_PER_JOB;
    let mut stage = || stage_bricks(writer, snap, edit, &target, &keys, policy, cancel, start);
    if few {
        stage()
    } else {
        rayon::scope(|_| {
            // The worker stages the pyramid too, reading from the store: with the edit's bound
            // on store waits, as this thread has it (`bound_store_waits`).
            let _bounded = crate::store::remote::bound_store_waits(cancel.deadline());
            stage()
        })
    }
}

/// Evaluates `edit` over the level-0 bricks `keys`, recomputes the levels above and stages
/// the result (see [`stage_edit`], which began at `start`).
#[allow(clippy::too_many_arguments)]
fn stage_bricks(
    writer: &mut Vod2Writer,
    snap: &Snapshot,
    edit: &Edit,
    target: &Box3,
    keys: &[BrickKey],
    policy: CheckpointPolicy,
    cancel: &CancelToken,
    start: Instant,
) -> Result<EditOutcome, EvalError> {
    // The channels the edit can change, read and written with density in one pass over the
    // bricks: the term is evaluated once for all of them (CVG's rule compares the operands'
    // densities, so a channel's values come from the voxels before the edit).
    let touched = edit.channels_touched(snap.header());
    let views: Vec<_> = touched
        .iter()
        .filter_map(|c| snap.channel(&c.name))
        .collect();
    type BrickResult = (BrickKey, Option<BrickVoxels>, Vec<Option<BrickVoxels>>, u64);
    let layout = snap.layout();
    let results: Vec<BrickResult> = keys
        .par_iter()
        .with_min_len(BRICKS_PER_JOB)
        .map(|&key| {
            cancel.check()?;
            // On the rayon pool too, reading a brick from an object store gives up at the
            // edit's deadline (`bound_store_waits` says why).
            let _bounded = crate::store::remote::bound_store_waits(cancel.deadline());
            if Box3::of_brick(layout, key).intersect(target).is_empty() {
                return Ok((key, None, vec![None; views.len()], 0));
            }
            let density = snap.voxels(key)?;
            let (new, channels) = if views.is_empty() {
                (
                    edit_voxels(edit, &density, layout, target, key)?,
                    Vec::new(),
                )
            } else {
                let values = views
                    .iter()
                    .map(|v| v.voxels(key))
                    .collect::<Result<Vec<_>, _>>()?;
                edit_streams(edit, &density, &touched, &values, layout, target, key)?
            };
            let changed = new
                .as_ref()
                .map_or(0, |new| voxels_differing(&density, new, layout));
            Ok((key, new, channels, changed))
        })
        .collect::<Result<_, EvalError>>()?;
    let evaluated = results.len();
    let voxels_changed = results.iter().map(|r| r.3).sum();
    let mut level0 = Vec::new();
    let mut channels: Vec<Vec<(BrickKey, BrickVoxels)>> = vec![Vec::new(); views.len()];
    for (key, density, streams, _) in results {
        if let Some(d) = density {
            level0.push((key, d));
        }
        for (i, c) in streams.into_iter().enumerate() {
            if let Some(c) = c {
                channels[i].push((key, c));
            }
        }
    }
    let channels: Vec<_> = views.into_iter().zip(channels).collect();
    let mut transaction = Transaction::on(writer, snap);
    if edit.note.info.kind.is_some() {
        transaction.set_note(note_bytes(&edit.note));
    }
    // Nothing outside the edit's reach changed: the levels above recompute only what lies over it.
    let reach = edit.reach(layout);
    transaction.update_level0(level0, &reach)?;
    for (view, changed) in channels {
        transaction.update_channel_level0(&view, changed, &reach)?;
    }
    let staged = transaction.stage(policy)?;
    let channels = channel_names(snap.header(), staged.channels_changed);
    Ok(EditOutcome {
        committed: true,
        version: staged.slot.version,
        changed: staged.changed,
        evaluated,
        new_records: staged.new_records,
        checkpoint: staged.checkpoint,
        elapsed: start.elapsed(),
        channels,
        voxels_changed,
    })
}

/// How many voxels of a brick differ between `old` and `new`.
fn voxels_differing(old: &BrickVoxels, new: &BrickVoxels, layout: &VolumeLayout) -> u64 {
    match (old, new) {
        (BrickVoxels::Constant(a), BrickVoxels::Constant(b)) => {
            if a == b {
                0
            } else {
                layout.brick_voxels() as u64
            }
        }
        _ => {
            let (a, b) = (to_u16(old, layout), to_u16(new, layout));
            a.iter().zip(&b).filter(|(x, y)| x != y).count() as u64
        }
    }
}

/// Changed channel bricks by stream, keyed by the channels' names instead.
pub fn channel_names(
    header: &FileHeader,
    by_stream: BTreeMap<usize, ChangedKeys>,
) -> BTreeMap<String, ChangedKeys> {
    by_stream
        .into_iter()
        .filter_map(|(stream, keys)| {
            let name = header.channels.get(stream.checked_sub(1)?)?.name.clone();
            Some((name, keys))
        })
        .collect()
}

/// A commit note as the commit record stores it (JSON).
pub fn note_bytes(note: &CommitNote) -> Vec<u8> {
    // Serializing plain data to a Vec cannot fail.
    serde_json::to_vec(note).unwrap_or_default()
}
