//! Transition strips: what a tile carries so that it joins a coarser neighbour without cracks.
//!
//! A pure kernel over sample grids, writing into caller-owned buffers, run right after
//! [`super::mc::march`] on the same tile. Everything is in the tile's local lattice frame, as the
//! regular mesh is.
//!
//! # The seam rule across levels
//!
//! Levels share one lattice ([`super::lattice`]): lattice point j of level k+1 is lattice point
//! 2j of level k, and a tile of level k+1 covers exactly its eight children. Tiles that share a
//! point differ by at most one level (`isovox_proto::lod::balance`). Where a tile of level k
//! meets a tile of level k+1 across a face, the coarse tile keeps its mesh; the fine tile makes
//! room and fills it:
//!
//! - **Secondary positions.** The fine tile's blocks of 2x2 boundary cells start at even lattice
//!   coordinates, so its faces are taken over `[lo', hi]`, `lo'` being `lo` rounded down to even
//!   (-2 for a tile that is first on an axis, whose cells start at -1). A lattice point of face
//!   f moves inwards by [`WIDTH`] fine cells when f touches a coarser neighbour, unless it also
//!   lies on another face g beyond which that coarser tile ends: then it stays. The coarser
//!   tile across f goes on beyond g exactly when the tile across g is this tile's sibling (in
//!   the same parent; or when no tile lies across g), which a tile knows from its own position.
//!   Then every tile sharing the point sees the same coarser tile across f and moves the point
//!   alike (the 2:1 rule makes the sibling the same level); otherwise the tiles around that
//!   edge may be of either level, and only staying is safe. So a face shared with a tile of the
//!   same or a finer level keeps its place, whatever the tiles around know of each other: a
//!   tile knows its six face neighbours, never the ones across its edges. No point moves with
//!   two faces at once (when f touches a coarser tile, the tiles beyond f's edges that move
//!   with f are siblings, and a sibling is never coarser). A vertex moves by the interpolation
//!   of its edge's endpoint moves. [`tile_moves`] writes the moves as [`VertexMove`]s,
//!   "move vertex i by d when face f touches a coarser neighbour".
//! - **Strips.** For each face, one transition cell per 2x2 block of boundary cells (the 13
//!   samples of [`super::transition_table`]): its fine face is the 3x3 samples of the tile's
//!   own face plane, at their secondary positions, and its fine-face vertices *are* the regular
//!   mesh's vertices (same indices), so they move together. Its coarse face is the 2x2 lattice
//!   values of level k+1 at the block's corners, on the face plane, never moved: a face of the
//!   coarse tile's cell, cut by the same face rule, with vertices computed by the coarse tile's
//!   own formula in the coarse tile's frame and then doubled into this tile's frame (exact in
//!   f32), so they are the coarse tile's vertices bit for bit after the same world transform.
//!   The edges joining a fine corner to its coarse twin have length [`WIDTH`].
//! - **Strip ends.** Where the coarser tile's face ends on an edge of the box, the fine samples
//!   on that edge stay on the face plane, so the lateral side of the strip's last cell
//!   collapses onto the edge: three fine and two coarse samples on one line. Such a side is cut
//!   by its positions, not by the table: the line carries a segment wherever exactly one of the
//!   fine and the coarse interpolant is inside (their symmetric difference, whose intervals
//!   start and end at the side's crossings). That depends on the side's samples alone, so it
//!   is drawn identically by the strip on the other side of the edge, which meets the same
//!   coarse tile (or its same-level neighbour) with the same fine samples: the same face's
//!   strip of the tile beside, or the strip with which the tile diagonally across meets the
//!   coarse tile from its other face. Where the coarser tile goes on beyond the edge, the
//!   side is an ordinary one, shared with the strip of the sibling beside. The cells at a
//!   strip's ends are traced at run time, the others take their loops from the table; every
//!   loop is triangulated by minimum area in the cell's drawn shape (a loop lying flat on the
//!   fine face is then always triangulated without overlap), never joining two vertices of a
//!   collapsed side by a diagonal (it would lie on that side, where the strip across the edge
//!   draws too).
//! - **Drawing.** A viewer computes each tile's 6-bit mask of faces touching a coarser
//!   neighbour (`isovox_proto::lod::face_masks`), applies the moves of those faces and draws
//!   their strips (`isovox_proto::mesh::stitch`). With mask 0 a tile is its regular mesh,
//!   unchanged.
//!
//! # What a tile and a strip are
//!
//! A tile carries its regular mesh and the moves of its boundary vertices for every face that
//! can touch a coarser tile ([`tile_moves`], from `march`'s border alone: no coarser sample is
//! read), whatever its neighbours are now, so it stays one cacheable object. The strip of a face
//! is an object of its own, made only when asked ([`mesh_strip`]): a mesh whose vertices along
//! the tile's face are copies of the tile's vertices there, with their moves with that face, so
//! that applying them as a viewer applies the tile's gives the same bits, and welding joins the
//! strip to the moved tile.
//!
//! # What a caller gathers for a strip (tile.rs)
//!
//! For a tile of level k with cells `[lo, hi)` (`lo` is -1 on the volume's low faces) and
//! `coarse_frame` = the parent brick's position times the brick edge (in level-(k+1) lattice
//! units), and face f:
//!
//! - a `march` of the layer of the tile's cells along f (or of the whole tile) with the tile's
//!   frame, and `fine`, the field it meshed: level-k lattice values over the layer's cells and
//!   one point around them (for k > 0, [`super::lattice::lattice_field`] of the stored level-k
//!   voxels 2 below and 1 above). The layer's vertices on f's plane are the tile's, bit for bit.
//! - `coarse`: a field of level-(k+1) lattice values over `[c, d]` with `c = floor(lo / 2) - 1`
//!   and `d = hi / 2 + 1`, of which only f's plane across `[c, d]` is read, and beside the plane
//!   the points next to a point of the face where an edge of its cells' coarse face, or a
//!   connecting edge, is crossed (the normals of coarse and connecting vertices read those;
//!   nothing else off the plane is read, and `tile.rs` computes nothing else).
//! - `tile.faces`: the faces that can touch a coarser neighbour: those with a neighbouring tile
//!   in the grid, when level k+1 exists. The moves depend on all of them (a coarser tile across
//!   f reaches past another face g exactly when no tile, or a sibling, lies across g).

use super::mc::{faces_of, BorderVertex, Field, Mesh, Scratch};
use super::transition_table::{
    chain, edge_between, edge_kind, faces, run_segments, sample_position, table, triangulate,
    EdgeKind, Table, EDGES, EDGE_SIDES, SAMPLES, SIDES,
};
use isovox_proto::mesh::{TileMesh, VertexMove};
/// How far (in fine cells) the fine face of a transition cell sits inside the coarse face.
pub const WIDTH: f32 = super::transition_table::WIDTH as f32;

/// The lateral axes (u, v) of each face's transition cells, in face-mask order (-x, +x, -y, +y,
/// -z, +z): with the face's outward normal n, (u, v, n) is right-handed, so the table's winding
/// carries over.
pub const FACE_FRAMES: [(usize, usize); 6] = [(2, 1), (1, 2), (0, 2), (2, 0), (1, 0), (0, 1)];

/// Where a tile lies and which of its faces have a neighbour: all the moves depend on.
#[derive(Debug, Clone, Copy)]
pub struct TileFaces {
    /// The lower end of the tile's cells `[lo, hi)` (as given to `march` for the whole tile).
    pub lo: [i64; 3],
    /// Their upper end.
    pub hi: [i64; 3],
    /// The frame given to `march`.
    pub frame: [i64; 3],
    /// The parent tile's frame, in level-(k+1) lattice units: the coarse neighbours' frames on
    /// every axis along their faces.
    pub coarse_frame: [i64; 3],
    /// The faces (a face mask) that can touch a coarser neighbour: those with a neighbouring
    /// tile, when a coarser level exists.
    pub faces: u8,
}

impl TileFaces {
    /// The box whose faces the moves and strips are taken over: `[lo', hi]`.
    fn box_lo(&self) -> [i64; 3] {
        self.lo.map(|c| c - c.rem_euclid(2))
    }

    /// Whether the tile is the upper child of its parent on each axis (its frame is not twice
    /// its parent's).
    fn upper_child(&self, axis: usize) -> bool {
        self.frame[axis] != 2 * self.coarse_frame[axis]
    }

    /// Whether a coarser tile across any other face reaches on beyond face `g` of the tile: no
    /// tile lies across `g` (the volume ends there), or the tile across `g` is this tile's
    /// sibling, in the same parent, so that a level-(k+1) tile across a face f covers the slot
    /// across f and `g` too.
    fn reaches_past(&self, g: usize) -> bool {
        let high = g & 1 == 1;
        self.faces >> g & 1 == 0 || high != self.upper_child(g / 2)
    }

    /// The faces a lattice point of the box on the faces `on` moves with (a face mask): face
    /// `f` when the point lies on `f` and the coarser tile across `f` reaches beyond every
    /// other face the point lies on (see the module doc). At most one of them can touch a
    /// coarser tile at a time.
    ///
    /// `reach` is the tile's [`TileFaces::reach`], which does not depend on `on`: a table of
    /// every mask takes it once.
    fn moving_faces_on(&self, on: u8, reach: u8) -> u8 {
        if on & self.faces == 0 {
            return 0;
        }
        // The faces p lies on beyond which a coarser tile across another face ends.
        let blocked = on & !reach;
        // Face f moves when no face but f itself blocks.
        match blocked.count_ones() {
            0 => on & self.faces,
            1 => on & self.faces & blocked,
            _ => 0,
        }
    }

    /// [`TileFaces::moving_faces_on`] of every face mask.
    fn moving_table(&self) -> [u8; 64] {
        let reach = self.reach();
        std::array::from_fn(|on| self.moving_faces_on(on as u8, reach))
    }

    /// The faces beyond which a coarser tile across another face reaches: the face mask of
    /// [`TileFaces::reaches_past`].
    fn reach(&self) -> u8 {
        (0..6).fold(0u8, |m, g| m | u8::from(self.reaches_past(g)) << g)
    }
}

/// The inputs of [`mesh_strip`] (see the module doc for what to gather).
#[derive(Debug, Clone, Copy)]
pub struct TransitionInput<'a> {
    /// The tile.
    pub tile: TileFaces,
    /// The tile's level-k lattice values: at least the field `march` meshed for the strip (the
    /// layer of cells along its face, or the whole tile).
    pub fine: &'a Field<'a>,
    /// Level-(k+1) lattice values, in level-(k+1) lattice units (coarse point q is fine point
    /// 2q): the face's plane, and beside it the points its crossed edges' normals read.
    pub coarse: &'a Field<'a>,
    /// The iso value.
    pub iso: f32,
}

/// Reusable memory for [`mesh_strip`].
#[derive(Debug, Default)]
pub struct TransitionScratch {
    /// Transition vertices already made, four slots per point of the coarse field: on the
    /// coarse edge from that point along axis 0, 1, 2, or (slot 3) on the connecting edge of
    /// its fine twin. Each slot holds the call that wrote it and the vertex, so that the table
    /// never needs clearing between tiles.
    made: Vec<(u32, u32)>,
    /// The current call's stamp in `made`.
    stamp: u32,
    /// The number of regular vertices; transition vertices are numbered after them.
    regular: usize,
    /// The move of each regular vertex with the face whose strip is being built.
    offsets: Vec<[f32; 3]>,
    /// Whether some of `offsets` are not zero (a strip is being built).
    offsets_set: bool,
    /// One loop's vertices, drawn positions and collapsed sides.
    loop_ids: Vec<u32>,
    points: Vec<[f64; 3]>,
    lines: Vec<u8>,
    fine_inside: Vec<bool>,
    coarse_inside: Vec<bool>,
    /// One loop's triangles, as indices into it.
    tris: Vec<[usize; 3]>,
    /// [`TileFaces::moving_faces_on`] of every face mask, for the current call.
    moving: Vec<u8>,
    /// The current call's `box_lo`.
    box_lo: [i64; 3],
    /// The strip being built.
    work: Transitions,
    /// Per vertex of the strip being built (regular, then its own): its index in the strip,
    /// or `u32::MAX`.
    remap: Vec<u32>,
    /// One row of blocks of a strip: per fine column its three samples' inside flags (bits 0,
    /// 3, 6), per coarse column its two (bits 0, 2).
    fine_columns: Vec<u16>,
    coarse_columns: Vec<u16>,
}

impl TransitionScratch {
    /// The faces lattice point `p` of the box moves with ([`TileFaces::moving_faces_on`]
    /// of the faces it lies on).
    fn moving_faces(&self, p: [i64; 3], hi: [i64; 3]) -> u8 {
        self.moving[usize::from(faces_of(p, self.box_lo, hi))]
    }

    /// The vertex this call made in slot `slot` of `made`, if it made one.
    fn made_at(&self, slot: usize) -> Option<u32> {
        match self.made[slot] {
            (stamp, id) if stamp == self.stamp => Some(id),
            _ => None,
        }
    }
}

/// How far a point of face `face` moves (along the face's axis), scaled by `k`: inwards.
fn distance(face: usize, k: f32) -> f32 {
    if face & 1 == 0 {
        WIDTH * k
    } else {
        -WIDTH * k
    }
}

/// The move of a point on face `face`, scaled by `k`, as a vector.
fn displacement(face: usize, k: f32) -> [f32; 3] {
    let mut d = [0f32; 3];
    d[face / 2] = distance(face, k);
    d
}

/// A strip being built: the vertices it makes (numbered after the regular ones), their moves
/// (with every face they move with), the lattice edge each lies on, and its triangles.
#[derive(Debug, Default)]
struct Transitions {
    positions: Vec<[f32; 3]>,
    normals: Vec<[f32; 3]>,
    edges: Vec<StripEdge>,
    moves: Vec<VertexMove>,
    strip: Vec<u32>,
}

impl Transitions {
    fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.edges.clear();
        self.moves.clear();
        self.strip.clear();
    }
}

/// Where a vertex of a strip lies, for its materials: on a lattice edge, or a cone's apex.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StripEdge {
    /// On the edge between two lattice points, at `t` of the way from the first (before any
    /// move): each end is `(d, j)`, lattice point `j` of the tile's level (`d` = 0) or of the
    /// next coarser one (`d` = 1), in that level's lattice coordinates. A fine edge has two
    /// ends of the tile's level, a coarse one two of the coarser level, a connecting edge a
    /// fine corner and its coarse twin.
    Edge {
        /// The two ends.
        ends: [(u8, [i64; 3]); 2],
        /// The fraction of the way from `ends[0]` to `ends[1]`.
        t: f32,
    },
    /// The apex of a cone drawn over a loop (see `triangulate_loop`): it lies on no edge and
    /// takes the materials of the loop's vertex with this id (regular ids first, then the
    /// strip's own, as the strip is built).
    Apex(u32),
}

impl TransitionScratch {
    /// The edge of each vertex of the strip the last [`mesh_strip`] built (`n` vertices, in
    /// the strip's order) into `out` (cleared first), `march` being the `march` it was built
    /// from. A vertex whose edge is unknown (none, as built) gets `None`.
    pub fn strip_edges(&self, march: &Scratch, n: usize, out: &mut Vec<Option<StripEdge>>) {
        out.clear();
        out.resize(n, None);
        let to = |id: usize| {
            self.remap
                .get(id)
                .copied()
                .filter(|&to| to != u32::MAX && (to as usize) < n)
                .map(|to| to as usize)
        };
        // The regular vertices the strip copies lie on the face's plane: on the border of the
        // layer `march` meshed.
        for b in &march.border {
            if let Some(i) = to(b.id as usize) {
                let mut p1 = b.p0;
                p1[usize::from(b.axis)] += 1;
                out[i] = Some(StripEdge::Edge {
                    ends: [(0, b.p0), (0, p1)],
                    t: b.t,
                });
            }
        }
        for (k, edge) in self.work.edges.iter().enumerate() {
            if let Some(i) = to(self.regular + k) {
                out[i] = Some(*edge);
            }
        }
        for i in 0..n {
            if let Some(StripEdge::Apex(id)) = out[i] {
                out[i] = to(id as usize).and_then(|j| match out[j] {
                    Some(StripEdge::Apex(_)) => None,
                    other => other,
                });
            }
        }
    }
}

/// The moves of the vertices `march` made on the tile's boundary (its `border`; `march` meshed
/// the whole tile, `[tile.lo, tile.hi)`), for the faces in `tile.faces`, appended to `out`
/// grouped by face: "move vertex i by d when face f touches a coarser neighbour". A vertex moves
/// with a face by the interpolation of its edge's endpoint moves with it.
pub fn tile_moves(tile: &TileFaces, march: &Scratch, out: &mut Vec<VertexMove>) {
    if tile.faces == 0 {
        return;
    }
    let moving = tile.moving_table();
    let box_lo = tile.box_lo();
    let same_box = box_lo == tile.lo;
    let start = out.len();
    for b in &march.border {
        // march's faces are those of [lo, hi]; the box's are the same unless it starts lower.
        let (f0, f1) = if same_box {
            (
                moving[usize::from(b.faces[0])],
                moving[usize::from(b.faces[1])],
            )
        } else {
            let mut p1 = b.p0;
            p1[b.axis as usize] += 1;
            (
                moving[usize::from(faces_of(b.p0, box_lo, tile.hi))],
                moving[usize::from(faces_of(p1, box_lo, tile.hi))],
            )
        };
        push_moves(b, f0, f1, 0x3f, out);
    }
    // Grouped by face, as the encoding writes them (stable: in border order within a face).
    out[start..].sort_by_key(|m| m.face);
}

/// The moves of border vertex `b` whose endpoints move with the faces `f0` and `f1`, for the
/// faces in `only`.
fn push_moves(b: &BorderVertex, f0: u8, f1: u8, only: u8, out: &mut Vec<VertexMove>) {
    for face in (0..6).filter(|&f| ((f0 | f1) & only) >> f & 1 == 1) {
        let k = match (f0 >> face & 1, f1 >> face & 1) {
            (1, 1) => 1.0,
            (1, _) => 1.0 - b.t,
            _ => b.t,
        };
        out.push(VertexMove {
            vertex: b.id,
            face: face as u8,
            distance: distance(face, k),
        });
    }
}

/// Builds the transition strip of face `face` of a tile into `out` (cleared first), in the
/// tile's local frame: a mesh of its own whose vertices along the tile's face are copies of the
/// tile's vertices there, with their moves with that face (`out.moves`, all of face `face`;
/// applying them gives the drawn strip, and applying them exactly as the tile's moves are
/// applied gives the tile's moved vertices bit for bit), its coarse vertices (never moved) and
/// the vertices on the edges joining them (moved too). `regular` and `march` are a `march` of
/// `input.fine` over cells that include the tile's layer of cells along `face` (the whole tile
/// or that layer alone), with `input.tile.frame`. Empty when the face cannot touch a coarser
/// tile or no surface crosses it.
///
/// # Panics
/// A field does not cover what the module doc says to gather, or the face lies off the coarse
/// lattice (an odd plane).
pub fn mesh_strip(
    input: &TransitionInput<'_>,
    face: usize,
    regular: &Mesh,
    march: &Scratch,
    out: &mut TileMesh,
    scratch: &mut TransitionScratch,
) {
    out.mesh.clear();
    out.moves.clear();
    if input.tile.faces >> face & 1 == 0 {
        return;
    }
    let mut work = std::mem::take(&mut scratch.work);
    work.clear();
    let slots = 4 * input.coarse.values.len();
    scratch.stamp = scratch.stamp.wrapping_add(1);
    if scratch.stamp == 0 || scratch.made.len() < slots {
        // First use, a larger field, or the stamp wrapped: start from a clean table.
        scratch.made.clear();
        scratch.made.resize(slots, (0, 0));
        scratch.stamp = 1;
    }
    scratch.moving.clear();
    scratch.moving.extend(input.tile.moving_table());
    scratch.box_lo = input.tile.box_lo();
    scratch.regular = regular.positions.len();
    // Zero but for the vertices of the face whose strip is being built (set and reset around
    // it), so that it needs no clearing between tiles; cleared if a call left it midway.
    if scratch.offsets_set {
        scratch.offsets.clear();
    }
    if scratch.offsets.len() < regular.positions.len() {
        scratch.offsets.resize(regular.positions.len(), [0.0; 3]);
    }
    // The moves of the face's regular vertices with this face (by position in the tile's box:
    // `march` may have meshed a layer of it only). The strip is drawn with the moves of its own
    // face only: when face f touches a coarser tile, no point of f moves with another face
    // (`moving_faces_on`).
    let tile = &input.tile;
    for b in &march.border {
        let mut p1 = b.p0;
        p1[b.axis as usize] += 1;
        let f0 = scratch.moving_faces(b.p0, tile.hi);
        let f1 = scratch.moving_faces(p1, tile.hi);
        push_moves(b, f0, f1, 1 << face, &mut work.moves);
    }
    let regular_moves = work.moves.len();
    scratch.offsets_set = true;
    for m in &work.moves {
        scratch.offsets[m.vertex as usize][face / 2] = m.distance;
    }
    strip(input, face, regular, march, &mut work, scratch);
    // The strip as an object of its own: the vertices it uses, in order of first use.
    let n = regular.positions.len();
    scratch.remap.clear();
    scratch.remap.resize(n + work.positions.len(), u32::MAX);
    for &i in &work.strip {
        let i = i as usize;
        if scratch.remap[i] == u32::MAX {
            scratch.remap[i] = out.mesh.positions.len() as u32;
            let (p, nm) = match i.checked_sub(n) {
                None => (regular.positions[i], regular.normals[i]),
                Some(t) => (work.positions[t], work.normals[t]),
            };
            out.mesh.positions.push(p);
            out.mesh.normals.push(nm);
        }
        out.mesh.indices.push(scratch.remap[i]);
    }
    for m in work.moves.iter().filter(|m| usize::from(m.face) == face) {
        let to = scratch.remap[m.vertex as usize];
        if to != u32::MAX {
            out.moves.push(VertexMove { vertex: to, ..*m });
        }
    }
    for m in &work.moves[..regular_moves] {
        scratch.offsets[m.vertex as usize] = [0.0; 3];
    }
    scratch.offsets_set = false;
    scratch.work = work;
}

/// One transition cell being built: where its samples are.
struct Cell<'a> {
    input: &'a TransitionInput<'a>,
    face: usize,
    /// The face's normal axis and plane, its lateral axes, the block's lower corner (u, v).
    axis: usize,
    plane: i64,
    ua: usize,
    va: usize,
    base: (i64, i64),
}

impl Cell<'_> {
    /// The lower point and axis of edge `e`.
    fn edge(&self, e: u8) -> ([i64; 3], usize) {
        let (u, v, direction) = EDGE_FRAME[e as usize];
        let mut p = [0i64; 3];
        p[self.axis] = self.plane;
        p[self.ua] = self.base.0 + u;
        p[self.va] = self.base.1 + v;
        (p, [self.ua, self.va, self.axis][direction])
    }
}

/// Per edge of a transition cell: its lower sample's offsets (u, v) in the block (a coarse
/// sample: its fine twin's) and its direction (0: u, 1: v, 2: the face's normal, a connecting
/// edge).
const EDGE_FRAME: [(i64, i64, usize); EDGES.len()] = {
    let mut out = [(0, 0, 0); EDGES.len()];
    let mut e = 0;
    while e < EDGES.len() {
        let (a, b) = (sample_position(EDGES[e].0), sample_position(EDGES[e].1));
        let direction = if a[0] != b[0] {
            0
        } else if a[1] != b[1] {
            1
        } else {
            2
        };
        out[e] = (a[0] as i64, a[1] as i64, direction);
        e += 1;
    }
    out
};

/// The transition cells of one face.
fn strip(
    input: &TransitionInput<'_>,
    face: usize,
    regular: &Mesh,
    march: &Scratch,
    out: &mut Transitions,
    scratch: &mut TransitionScratch,
) {
    let (lo, hi) = (input.tile.box_lo(), input.tile.hi);
    let axis = face / 2;
    let (ua, va) = FACE_FRAMES[face];
    let plane = if face % 2 == 1 {
        hi[axis]
    } else {
        input.tile.lo[axis]
    };
    assert!(
        plane.rem_euclid(2) == 0,
        "face {face} of the tile lies off the coarse lattice"
    );
    let (u0, v0) = (lo[ua], lo[va]);
    let (nu, nv) = ((hi[ua] - u0) as usize, (hi[va] - v0) as usize);
    let mut cell = Cell {
        input,
        face,
        axis,
        plane,
        ua,
        va,
        base: (u0, v0),
    };
    // Inside flags of the face's fine and coarse samples, read once.
    let iso = input.iso;
    let at = |u: i64, v: i64| {
        let mut p = [0i64; 3];
        p[axis] = plane;
        p[ua] = u0 + u;
        p[va] = v0 + v;
        p
    };
    // Read through strides: the face's first point checked against each field, then steps.
    let flags = |field: &Field<'_>, first: [i64; 3], n: (usize, usize), out: &mut Vec<bool>| {
        let mut last = first;
        last[ua] += n.0 as i64;
        last[va] += n.1 as i64;
        assert!(
            field.contains(first) && field.contains(last),
            "the field does not cover face {face}"
        );
        let stride = [1, field.size[0], field.size[0] * field.size[1]];
        let base = (0..3)
            .map(|a| (first[a] - field.origin[a]) as usize * stride[a])
            .sum::<usize>();
        let (su, sv) = (stride[ua], stride[va]);
        let values = &field.values[base..=base + n.0 * su + n.1 * sv];
        out.clear();
        for v in 0..=n.1 {
            let row = &values[v * sv..];
            if su == 1 {
                out.extend(row[..=n.0].iter().map(|&x| x >= iso));
            } else {
                out.extend((0..=n.0).map(|u| row[u * su] >= iso));
            }
        }
    };
    flags(input.fine, at(0, 0), (nu, nv), &mut scratch.fine_inside);
    let coarse_first = at(0, 0).map(|c| c.div_euclid(2));
    flags(
        input.coarse,
        coarse_first,
        (nu / 2, nv / 2),
        &mut scratch.coarse_inside,
    );
    let first = scratch.fine_inside[0];
    if scratch
        .fine_inside
        .iter()
        .chain(&scratch.coarse_inside)
        .all(|&x| x == first)
    {
        return; // every sample on the same side: no surface crosses this face
    }
    let table = table();
    let (fw, cw) = (nu + 1, nu / 2 + 1);
    // A cell's case from its three fine and two coarse columns: fine sample (i, j) is bit
    // i + 3j, coarse sample (i, j) bit 9 + i + 2j.
    let mut fine_columns = std::mem::take(&mut scratch.fine_columns);
    let mut coarse_columns = std::mem::take(&mut scratch.coarse_columns);
    for bv in (0..nv).step_by(2) {
        let (fine, coarse) = (&scratch.fine_inside, &scratch.coarse_inside);
        fine_columns.clear();
        fine_columns.extend((0..fw).map(|u| {
            (0..3).fold(0u16, |c, j| {
                c | u16::from(fine[(bv + j) * fw + u]) << (3 * j)
            })
        }));
        coarse_columns.clear();
        coarse_columns.extend((0..cw).map(|u| {
            (0..2).fold(0u16, |c, j| {
                c | u16::from(coarse[(bv / 2 + j) * cw + u]) << (2 * j)
            })
        }));
        for bu in (0..nu).step_by(2) {
            let (f, c) = (
                &fine_columns[bu..bu + 3],
                &coarse_columns[bu / 2..bu / 2 + 2],
            );
            let case = f[0] | f[1] << 1 | f[2] << 2 | (c[0] | c[1] << 1) << 9;
            if case == 0 || case == (1 << SAMPLES) - 1 {
                continue;
            }
            cell.base = (u0 + bu as i64, v0 + bv as i64);
            // The sides on the box's edges where the coarser tile's face ends, in SIDES order
            // (u = 0, u = 2, v = 0, v = 2): their fine samples stay on the face plane.
            let collapsed = [
                bu == 0 && !input.tile.reaches_past(2 * ua),
                bu + 2 == nu && !input.tile.reaches_past(2 * ua + 1),
                bv == 0 && !input.tile.reaches_past(2 * va),
                bv + 2 == nv && !input.tile.reaches_past(2 * va + 1),
            ];
            transition_cell(&cell, case, collapsed, table, regular, march, out, scratch);
        }
    }
    scratch.fine_columns = fine_columns;
    scratch.coarse_columns = coarse_columns;
}

/// The id and drawn position (local frame) of the vertex on edge `e` of `cell`.
fn vertex(
    cell: &Cell<'_>,
    e: u8,
    march: &Scratch,
    out: &mut Transitions,
    scratch: &mut TransitionScratch,
) -> (u32, [f32; 3]) {
    let (p, axis) = cell.edge(e);
    match edge_kind(e) {
        EdgeKind::Fine => {
            let id = march.vertex_on_edge(p, axis).unwrap_or_else(|| {
                panic!("no regular vertex on the crossed edge {p:?} along {axis}")
            });
            (id, [0.0; 3]) // the caller reads the regular position
        }
        EdgeKind::Coarse => {
            coarse_vertex(cell.input, p.map(|c| c.div_euclid(2)), axis, out, scratch)
        }
        EdgeKind::Connecting => connecting_vertex(cell.input, p, cell.face, out, scratch),
    }
}

/// One transition cell: its loops (from the table, or traced from its faces when a side is
/// collapsed, that side by position), triangulated in the cell's drawn shape.
#[allow(clippy::too_many_arguments)]
fn transition_cell(
    cell: &Cell<'_>,
    case: u16,
    collapsed: [bool; SIDES],
    table: &Table,
    regular: &Mesh,
    march: &Scratch,
    out: &mut Transitions,
    scratch: &mut TransitionScratch,
) {
    let n_regular = regular.positions.len();
    // Every crossed edge's vertex, with its drawn position.
    let mut ids = [u32::MAX; EDGES.len()];
    let mut drawn = [[0f64; 3]; EDGES.len()];
    for e in 0..EDGES.len() as u8 {
        let (a, b) = EDGES[e as usize];
        if (case >> a & 1) == (case >> b & 1) {
            continue;
        }
        let (id, pos) = vertex(cell, e, march, out, scratch);
        let pos = if (id as usize) < n_regular {
            let (p, d) = (regular.positions[id as usize], scratch.offsets[id as usize]);
            [p[0] + d[0], p[1] + d[1], p[2] + d[2]]
        } else {
            pos
        };
        ids[e as usize] = id;
        drawn[e as usize] = pos.map(f64::from);
    }
    let traced;
    let mut traced_loops;
    let mut table_loops;
    let loops: &mut dyn Iterator<Item = &[u8]> = if collapsed.contains(&true) {
        let mut next = [u8::MAX; EDGES.len()];
        for (f, corners) in faces().iter().enumerate() {
            match f.checked_sub(5) {
                Some(side) if collapsed[side] => {
                    let line = if side < 2 { cell.va } else { cell.ua };
                    if !interval_segments(corners, side, case, &drawn, line, &mut next) {
                        run_segments(corners, case, &mut next);
                    }
                }
                _ => run_segments(corners, case, &mut next),
            }
        }
        traced = chain(&next);
        traced_loops = traced.iter().map(Vec::as_slice);
        &mut traced_loops
    } else {
        table_loops = table.loops(case);
        &mut table_loops
    };
    let collapsed_sides = (0..SIDES).fold(0u8, |m, s| m | u8::from(collapsed[s]) << s);
    for lp in loops {
        // Consecutive vertices at one position (a fine and a coarse crossing that coincide on a
        // collapsed side) are one vertex.
        scratch.loop_ids.clear();
        scratch.points.clear();
        // The lateral sides each vertex lies on (bits 0-3), and which of them are collapsed
        // (bits 4-7).
        scratch.lines.clear();
        for &e in lp {
            let p = drawn[e as usize];
            if scratch.points.last() != Some(&p) {
                scratch.loop_ids.push(ids[e as usize]);
                scratch.points.push(p);
                let on = EDGE_SIDES[e as usize];
                scratch.lines.push(on | (on & collapsed_sides) << SIDES);
            }
        }
        if scratch.points.len() > 1 && scratch.points.first() == scratch.points.last() {
            scratch.points.pop();
            scratch.loop_ids.pop();
            scratch.lines.pop();
        }
        let points = &scratch.points;
        // Two vertices of the loop at one position (a fine and a coarse crossing where the two
        // contours cross on a collapsed side) pinch it into two loops that touch there; each is
        // triangulated on its own, so that no vertex is joined to both.
        let n = points.len();
        let pinched =
            (0..n).any(|a| (a + 2..n).any(|b| points[a] == points[b] && !(a == 0 && b + 1 == n)));
        if !pinched {
            if n >= 3 {
                let shape = LoopShape {
                    ids: &scratch.loop_ids,
                    points,
                    lines: &scratch.lines,
                };
                let tris = &mut scratch.tris;
                triangulate_loop(&shape, regular, out, scratch.regular, tris);
            }
            continue;
        }
        let mut pieces: Vec<Vec<usize>> = vec![(0..n).collect()];
        let mut at = 0;
        while at < pieces.len() {
            let piece = &pieces[at];
            let twin = (0..piece.len()).find_map(|a| {
                (a + 2..piece.len())
                    .find(|&b| {
                        points[piece[a]] == points[piece[b]] && !(a == 0 && b + 1 == piece.len())
                    })
                    .map(|b| (a, b))
            });
            match twin {
                Some((a, b)) => {
                    let piece = std::mem::take(&mut pieces[at]);
                    pieces.push(piece[a..b].to_vec());
                    pieces.push(piece[b..].iter().chain(&piece[..a]).copied().collect());
                }
                None => at += 1,
            }
        }
        for piece in pieces.iter().filter(|p| p.len() >= 3) {
            let ids: Vec<u32> = piece.iter().map(|&i| scratch.loop_ids[i]).collect();
            let pts: Vec<[f64; 3]> = piece.iter().map(|&i| points[i]).collect();
            let lines: Vec<u8> = piece.iter().map(|&i| scratch.lines[i]).collect();
            let shape = LoopShape {
                ids: &ids,
                points: &pts,
                lines: &lines,
            };
            let tris = &mut scratch.tris;
            triangulate_loop(&shape, regular, out, scratch.regular, tris);
        }
    }
}

/// One loop (or a piece of a pinched one) of a transition cell: its vertices, their drawn
/// positions, and the lateral sides each lies on (bits 0-3: the sides, bits 4-7: those of them
/// collapsed).
struct LoopShape<'a> {
    ids: &'a [u32],
    points: &'a [[f64; 3]],
    lines: &'a [u8],
}

/// Triangulates one loop of a transition cell into the strip of `face`: by minimum area, never
/// joining two vertices of one collapsed side by a diagonal (it would lie on that line, where
/// the strip across the edge draws too). A loop that passes a lateral side twice (a tube
/// through it) could get a diagonal across that side, and the next cell of the strip, whose
/// loop passes it twice too, the same one: four triangles on one edge. Such a loop is drawn as
/// a cone from a new vertex at its centroid instead, which lies inside the cell (the loop does
/// not lie on one side), so that no edge of it lies on a side but the loop's own.
fn triangulate_loop(
    shape: &LoopShape<'_>,
    regular: &Mesh,
    out: &mut Transitions,
    n_regular: usize,
    tris: &mut Vec<[usize; 3]>,
) {
    let (ids, points, lines) = (shape.ids, shape.points, shape.lines);
    let n = points.len();
    let refused = |i: usize, j: usize| (lines[i] & lines[j]) >> SIDES != 0;
    tris.clear();
    triangulate(points, 1e-12, refused, tris);
    let on_side = |i: usize, j: usize| {
        let edge = j == (i + 1) % n || i == (j + 1) % n;
        !edge && lines[i] & lines[j] & 0xf != 0
    };
    let across_a_side = tris
        .iter()
        .any(|t| on_side(t[0], t[1]) || on_side(t[1], t[2]) || on_side(t[2], t[0]));
    if !across_a_side {
        for t in tris.iter() {
            out.strip.extend(t.map(|i| ids[i]));
        }
        return;
    }
    let mut centre = [0f64; 3];
    let mut normal = [0f32; 3];
    for (&id, p) in ids.iter().zip(points) {
        for a in 0..3 {
            centre[a] += p[a] / n as f64;
        }
        let nm = match (id as usize).checked_sub(n_regular) {
            None => regular.normals[id as usize],
            Some(t) => out.normals[t],
        };
        for a in 0..3 {
            normal[a] += nm[a];
        }
    }
    let len = (normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]).sqrt();
    let normal = if len > 0.0 {
        normal.map(|c| c / len)
    } else {
        [0.0; 3]
    };
    // The apex belongs to this strip alone, drawn only with its face's moves: it is stored at
    // its drawn position, with no move.
    let apex = (n_regular + out.positions.len()) as u32;
    out.positions.push(centre.map(|c| c as f32));
    out.normals.push(normal);
    out.edges.push(StripEdge::Apex(ids[0]));
    for i in 0..n {
        out.strip.extend([ids[i], ids[(i + 1) % n], apex]);
    }
}

/// The segments of a collapsed side (its corners counter-clockwise from outside; all on one
/// line along axis `line`): one per interval of the line where exactly one of the fine and the
/// coarse interpolant is inside, from the crossing where the side's run enters to the one
/// where it leaves. Returns false (writing nothing) if the crossings do not pair that way,
/// which only coinciding crossings can cause.
fn interval_segments(
    corners: &[u8],
    side: usize,
    case: u16,
    drawn: &[[f64; 3]; EDGES.len()],
    line: usize,
    next: &mut [u8; EDGES.len()],
) -> bool {
    let inside = |s: u8| case >> s & 1 == 1;
    // The canonical coordinate along the side: v on the sides u = 0, 2; u on the others.
    let along = usize::from(side < 2);
    // (position along the line, rank for ties, edge, enters the side's runs)
    let mut events: Vec<(f64, u8, u8, bool)> = Vec::with_capacity(5);
    let k = corners.len();
    for i in 0..k {
        let (a, b) = (corners[i], corners[(i + 1) % k]);
        if inside(a) == inside(b) {
            continue;
        }
        let e = edge_between(a, b);
        // Connecting edges sit at the line's ends: the one at the lower end first, the one at
        // the upper end last; at equal positions a fine crossing before a coarse one.
        let rank = match edge_kind(e) {
            EdgeKind::Connecting if sample_position(EDGES[e as usize].0)[along] == 0 => 0,
            EdgeKind::Connecting => 3,
            EdgeKind::Fine => 1,
            EdgeKind::Coarse => 2,
        };
        events.push((drawn[e as usize][line], rank, e, inside(b)));
    }
    events.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
    let pairs: Vec<(u8, u8)> = events
        .chunks_exact(2)
        .filter_map(|p| match (p[0].3, p[1].3) {
            (true, false) => Some((p[0].2, p[1].2)),
            (false, true) => Some((p[1].2, p[0].2)),
            _ => None,
        })
        .collect();
    if pairs.len() * 2 != events.len() {
        return false;
    }
    for (enter, leave) in pairs {
        next[enter as usize] = leave;
    }
    true
}

/// The vertex on the coarse lattice edge from `q0` along `axis`: computed as the coarse tile's
/// `march` computes it, in the coarse tile's frame, then doubled into this tile's frame.
fn coarse_vertex(
    input: &TransitionInput<'_>,
    q0: [i64; 3],
    axis: usize,
    out: &mut Transitions,
    scratch: &mut TransitionScratch,
) -> (u32, [f32; 3]) {
    let slot = 4 * input.coarse.index(q0) + axis;
    if let Some(id) = scratch.made_at(slot) {
        return (id, out.positions[(id as usize) - scratch.regular]);
    }
    let (t, normal) = input.coarse.crossing(q0, axis, input.iso);
    let (cf, f) = (input.tile.coarse_frame, input.tile.frame);
    let mut pos = [0f32; 3];
    for b in 0..3 {
        pos[b] = if b == axis {
            // The coarse tile's local coordinate, as march writes it...
            let local = (q0[b] - cf[b]) as f32 + t;
            // ...in this tile's frame: 2 local + (2 cf - f). Exact: 2 cf - f is 0 or minus a
            // brick, and the sum is no larger than 2 local.
            let offset = (2 * cf[b] - f[b]) as f32;
            let here = 2.0 * local + offset;
            debug_assert_eq!(here - offset, 2.0 * local, "inexact frame change");
            here
        } else {
            (2 * q0[b] - f[b]) as f32
        };
    }
    let mut q1 = q0;
    q1[axis] += 1;
    let edge = StripEdge::Edge {
        ends: [(1, q0), (1, q1)],
        t,
    };
    let id = push_vertex(out, scratch, pos, normal, edge);
    scratch.made[slot] = (scratch.stamp, id);
    (id, pos)
}

/// The vertex on the edge joining fine corner `p` (at its secondary position) to its coarse
/// twin (at `p`, never moved), with its move; the position returned is the drawn one.
fn connecting_vertex(
    input: &TransitionInput<'_>,
    p: [i64; 3],
    face: usize,
    out: &mut Transitions,
    scratch: &mut TransitionScratch,
) -> (u32, [f32; 3]) {
    let primary = [0, 1, 2].map(|b| (p[b] - input.tile.frame[b]) as f32);
    let q = p.map(|c| c.div_euclid(2));
    let (vf, vc) = (input.fine.value(p), input.coarse.value(q));
    let s = (input.iso - vf) / (vc - vf);
    // It moves with each face its fine corner moves with; drawn in this strip with the moves
    // of this strip's face.
    let moving = scratch.moving_faces(p, input.tile.hi);
    let drawn = if moving >> face & 1 == 1 {
        let d = displacement(face, 1.0 - s);
        [0, 1, 2].map(|b| primary[b] + d[b])
    } else {
        primary
    };
    let slot = 4 * input.coarse.index(q) + 3;
    if let Some(id) = scratch.made_at(slot) {
        return (id, drawn);
    }
    // Normals: fine gradient per fine cell, coarse per coarse cell (two fine cells).
    let gf = input.fine.outward_gradient(p);
    let gc = input.coarse.outward_gradient(q).map(|c| c * 0.5);
    let g = [0, 1, 2].map(|k| gf[k] + s * (gc[k] - gf[k]));
    let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
    let normal = if len > 0.0 {
        g.map(|c| c / len)
    } else {
        // Flat: along the edge, from the inside end to the outside one.
        let mut d = [0f32; 3];
        let outward = if face % 2 == 1 { 1.0 } else { -1.0 };
        d[face / 2] = if vc >= input.iso { -outward } else { outward };
        d
    };
    let edge = StripEdge::Edge {
        ends: [(0, p), (1, q)],
        t: s,
    };
    let id = push_vertex(out, scratch, primary, normal, edge);
    for f in (0..6).filter(|&f| moving >> f & 1 == 1) {
        out.moves.push(VertexMove {
            vertex: id,
            face: f as u8,
            distance: distance(f, 1.0 - s),
        });
    }
    scratch.made[slot] = (scratch.stamp, id);
    (id, drawn)
}

/// Appends a transition vertex; its index follows the regular vertices and the transition
/// vertices before it.
fn push_vertex(
    out: &mut Transitions,
    scratch: &TransitionScratch,
    pos: [f32; 3],
    normal: [f32; 3],
    edge: StripEdge,
) -> u32 {
    let id = (scratch.regular + out.positions.len()) as u32;
    out.positions.push(pos);
    out.normals.push(normal);
    out.edges.push(edge);
    id
}
