//! The desired set: the tiles the camera needs, and what is known about each (delivered,
//! shown, stale, a mesh tile's drawing and face mask).

use isovox_proto::mesh::TileMesh;
use isovox_proto::tile::GridBox;
use isovox_proto::{BrickKey, VolumeLayout};
use std::collections::{HashMap, HashSet};
use std::sync::Arc;

/// One tile of the desired set.
#[derive(Debug, Default)]
struct Tile {
    /// The content key of the delivered content, while it is current.
    ready: Option<u64>,
    /// `Ready` was emitted (and the tile has not left the set since).
    shown: bool,
    /// `Stale` was emitted and the new content has not been delivered yet.
    stale: bool,
    /// A mesh tile's delivered content and the face mask it was stitched with.
    drawn: Option<(Arc<TileMesh>, u8)>,
    /// A mesh tile's delivered drawing: a hash of its content key, mask and strips' content
    /// keys, while current.
    drawn_key: Option<u64>,
    /// The descent found no surface in it (with this face mask, for a mesh tile): complete
    /// without content (`ready` holds [`SKIPPED`]).
    skipped: Option<u8>,
}

/// The content key a skipped tile is complete with (no content is ever looked up by it).
pub(super) const SKIPPED: u64 = 0;

/// The desired set: the tiles the camera needs, and what is known about each.
#[derive(Debug, Default)]
pub(super) struct Desired {
    pub(super) camera: Option<[f32; 3]>,
    pub(super) camera_seq: u64,
    tiles: HashMap<BrickKey, Tile>,
    /// Mesh tiles: each desired tile's face mask in the desired set.
    masks: HashMap<BrickKey, u8>,
    /// Desired tiles without current content.
    pub(super) missing: usize,
}

impl Desired {
    /// A desired mesh tile's face mask in the desired set (0 otherwise).
    pub(super) fn mask(&self, key: BrickKey) -> u8 {
        self.masks.get(&key).copied().unwrap_or(0)
    }

    /// Whether `key` is desired.
    pub(super) fn contains(&self, key: BrickKey) -> bool {
        self.tiles.contains_key(&key)
    }

    /// Whether `key` is desired and skipped by the descent.
    pub(super) fn is_skipped(&self, key: BrickKey) -> bool {
        self.tiles.get(&key).is_some_and(|t| t.skipped.is_some())
    }

    /// Whether `key` is desired and has no current content.
    pub(super) fn needs(&self, key: BrickKey) -> bool {
        self.tiles.get(&key).is_some_and(|t| t.ready.is_none())
    }

    /// The desired tiles without current content.
    pub(super) fn without_content(&self) -> Vec<BrickKey> {
        self.tiles
            .iter()
            .filter(|(_, t)| t.ready.is_none())
            .map(|(k, _)| *k)
            .collect()
    }

    /// The desired tiles, in key order.
    pub(super) fn sorted_keys(&self) -> Vec<BrickKey> {
        let mut keys: Vec<BrickKey> = self.tiles.keys().copied().collect();
        keys.sort();
        keys
    }

    /// Makes `new` the desired set, mesh tiles with their face `masks` in it: tiles that leave
    /// it are dropped, mesh tiles whose face mask changed need drawing again. Returns the
    /// dropped tiles that had been shown, in key order.
    pub(super) fn replace(&mut self, new: Vec<BrickKey>, masks: Option<Vec<u8>>) -> Vec<BrickKey> {
        if let Some(masks) = masks {
            self.masks = new.iter().copied().zip(masks).collect();
        }
        let keep: HashSet<BrickKey> = new.iter().copied().collect();
        let mut gone: Vec<BrickKey> = self
            .tiles
            .keys()
            .filter(|k| !keep.contains(k))
            .copied()
            .collect();
        gone.sort();
        let mut dropped = Vec::new();
        for key in gone {
            let Some(t) = self.tiles.remove(&key) else {
                continue;
            };
            if t.ready.is_none() {
                self.missing -= 1;
            }
            if t.shown {
                dropped.push(key);
            }
        }
        for key in new {
            let t = self.tiles.entry(key).or_insert_with(|| {
                self.missing += 1;
                Tile::default()
            });
            // A mesh tile whose mask changed is drawn again (its tile from the cache, the
            // strips of its new faces from the cache or a request; the old drawing stays until
            // then).
            let mask = self.masks.get(&key).copied().unwrap_or(0);
            // A skipped mesh tile whose mask changed reads other strips: decided again.
            if t.skipped.is_some_and(|m| m != mask) {
                t.skipped = None;
                t.ready = None;
                self.missing += 1;
            }
            if let (Some(_), Some((_, drawn))) = (t.ready, &t.drawn) {
                if *drawn != mask {
                    t.ready = None;
                    self.missing += 1;
                }
            }
        }
        dropped
    }

    /// Tile `key` has content `content` delivered. Whether it is shown for the first time;
    /// `None` when it is not desired.
    pub(super) fn deliver(&mut self, key: BrickKey, content: u64) -> Option<bool> {
        let t = self.tiles.get_mut(&key)?;
        if t.ready.is_none() {
            self.missing -= 1;
        }
        t.ready = Some(content);
        t.stale = false;
        t.skipped = None;
        let first = !t.shown;
        t.shown = true;
        Some(first)
    }

    /// Whether drawing `drawn_key` of mesh tile `key` (content `content`) is the one delivered
    /// (a mask that changed and changed back): the tile's content is then current again.
    /// `None` when it is not desired.
    pub(super) fn redrawn(&mut self, key: BrickKey, content: u64, drawn_key: u64) -> Option<bool> {
        let t = self.tiles.get_mut(&key)?;
        if t.drawn_key == Some(drawn_key) && t.ready.is_none() && t.shown && !t.stale {
            t.ready = Some(content);
            self.missing -= 1;
            return Some(true);
        }
        Some(false)
    }

    /// Mesh tile `key` is drawn from `tile` with face mask `mask` (drawing `drawn_key`).
    pub(super) fn set_drawn(
        &mut self,
        key: BrickKey,
        tile: Arc<TileMesh>,
        mask: u8,
        drawn_key: u64,
    ) {
        if let Some(t) = self.tiles.get_mut(&key) {
            t.drawn = Some((tile, mask));
            t.drawn_key = Some(drawn_key);
        }
    }

    /// Tile `key` needs new content (an edit changed what it reads). When it is shown, it is
    /// stale: whether it just became so; `None` when it is not desired or not shown.
    pub(super) fn invalidate(&mut self, key: BrickKey) -> Option<bool> {
        let t = self.tiles.get_mut(&key)?;
        let mut stale = None;
        if t.shown {
            stale = Some(!t.stale);
            t.stale = true;
        }
        if t.ready.take().is_some() {
            self.missing += 1;
        }
        t.skipped = None;
        stale
    }

    /// Desired tile `key` has no surface (the descent says so): complete without content.
    /// Whether it had been shown (it is then no longer: the caller reports it dropped).
    pub(super) fn skip(&mut self, key: BrickKey) -> bool {
        let mask = self.mask(key);
        let Some(t) = self.tiles.get_mut(&key) else {
            return false;
        };
        if t.ready.is_none() {
            self.missing -= 1;
        }
        t.ready = Some(SKIPPED);
        t.skipped = Some(mask);
        t.stale = false;
        t.drawn = None;
        t.drawn_key = None;
        std::mem::take(&mut t.shown)
    }

    /// The bricks a desired mesh tile's drawing reads: its own, and those of the strips of the
    /// faces in its mask.
    pub(super) fn drawing_reads(&self, layout: &VolumeLayout, key: BrickKey) -> Vec<(u8, GridBox)> {
        let mask = self.mask(key);
        let mut reads = isovox_proto::tile::mesh_tile_reads(layout, key);
        for face in (0..6).filter(|f| mask >> f & 1 == 1) {
            reads.extend(isovox_proto::tile::strip_reads(layout, key, face));
        }
        reads
    }

    /// The desired mesh tiles that read bricks of `level` (theirs, or their strips'), with the
    /// bricks their drawings read.
    pub(super) fn readers(
        &self,
        layout: &VolumeLayout,
        level: u8,
    ) -> Vec<(BrickKey, Vec<(u8, GridBox)>)> {
        self.tiles
            .keys()
            .filter(|t| t.level == level || t.level + 1 == level)
            .map(|&t| (t, self.drawing_reads(layout, t)))
            .collect()
    }
}
