//! The desired set: the tiles the camera needs, and what is known about each (delivered,
//! shown, stale, a mesh tile's drawing and face mask).

use super::FastMap;
use isovox_proto::mesh::TileMesh;
use isovox_proto::tile::GridBox;
use isovox_proto::{BrickKey, VolumeLayout};
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
    tiles: FastMap<BrickKey, Tile>,
    /// The desired tiles sorted by key, each with its face mask (mesh tiles; 0 for bricks): what
    /// `replace` was last given. A camera move is merged with it as two sorted lists, without
    /// hashing the tiles that stayed.
    selection: Vec<(BrickKey, u8)>,
    /// Desired tiles without current content.
    pub(super) missing: usize,
}

impl Desired {
    /// A desired mesh tile's face mask in the desired set (0 otherwise).
    pub(super) fn mask(&self, key: BrickKey) -> u8 {
        self.selection
            .binary_search_by_key(&key, |&(k, _)| k)
            .map_or(0, |i| self.selection[i].1)
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

    /// The desired tiles, in key order.
    pub(super) fn sorted_keys(&self) -> Vec<BrickKey> {
        // The selection holds the same keys as `tiles`, already sorted.
        self.selection.iter().map(|&(k, _)| k).collect()
    }

    /// The desired tiles without current content, in no particular order (read off the tiles
    /// themselves, without a lookup per key).
    pub(super) fn needing(&self) -> Vec<BrickKey> {
        let mut keys = Vec::with_capacity(self.missing);
        keys.extend(
            self.tiles
                .iter()
                .filter(|(_, t)| t.ready.is_none())
                .map(|(&k, _)| k),
        );
        keys
    }

    /// Makes `new` the desired set, mesh tiles with their face `masks` in it: tiles that leave
    /// it are dropped, mesh tiles whose face mask changed need drawing again. Returns the
    /// dropped tiles that had been shown, in key order.
    pub(super) fn replace(&mut self, new: Vec<BrickKey>, masks: Option<Vec<u8>>) -> Vec<BrickKey> {
        let mut new: Vec<(BrickKey, u8)> = match masks {
            Some(masks) => new.into_iter().zip(masks).collect(),
            None => new.into_iter().map(|k| (k, 0)).collect(),
        };
        // The selections come sorted (`select_tiles`, `lod::stitched_tiles`); sorted here
        // otherwise, each key with its own mask.
        if !new.windows(2).all(|w| w[0].0 < w[1].0) {
            new.sort_unstable_by_key(|&(k, _)| k);
            new.dedup_by_key(|&mut (k, _)| k);
        }
        if new == self.selection {
            return Vec::new();
        }
        let (gone, came) = sorted_changes(&self.selection, &new);
        self.selection = new;
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
        for (key, mask) in came {
            let t = self.tiles.entry(key).or_insert_with(|| {
                self.missing += 1;
                Tile::default()
            });
            // A skipped mesh tile whose mask changed reads other strips: decided again.
            if t.skipped.is_some_and(|m| m != mask) {
                t.skipped = None;
                t.ready = None;
                self.missing += 1;
            }
            // A drawn mesh tile whose mask changed is drawn again (its tile from the cache, the
            // strips of its new faces from the cache or a request; the old drawing stays until
            // then).
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

/// Between two selections sorted by key: the keys of `old` missing from `new` (gone), and the
/// tiles of `new` that are not in `old` or have another mask there (came), in key order.
fn sorted_changes(
    old: &[(BrickKey, u8)],
    new: &[(BrickKey, u8)],
) -> (Vec<BrickKey>, Vec<(BrickKey, u8)>) {
    let (mut gone, mut came) = (Vec::new(), Vec::new());
    let (mut i, mut j) = (0, 0);
    loop {
        match (old.get(i), new.get(j)) {
            (Some(a), Some(b)) if a.0 == b.0 => {
                if a.1 != b.1 {
                    came.push(*b);
                }
                i += 1;
                j += 1;
            }
            (Some(a), Some(b)) if a.0 < b.0 => {
                gone.push(a.0);
                i += 1;
            }
            (Some(a), None) => {
                gone.push(a.0);
                i += 1;
            }
            (_, Some(b)) => {
                came.push(*b);
                j += 1;
            }
            (None, None) => break,
        }
    }
    (gone, came)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k(level: u8, x: u32) -> BrickKey {
        BrickKey {
            level,
            x,
            y: 0,
            z: 0,
        }
    }

    #[test]
    fn the_difference_of_two_sorted_selections_by_hand() {
        let old = [(k(0, 1), 0), (k(0, 2), 0), (k(0, 5), 0), (k(1, 0), 3)];
        let new = [(k(0, 2), 0), (k(0, 3), 0), (k(1, 0), 3), (k(2, 0), 0)];
        assert_eq!(
            sorted_changes(&old, &new),
            (vec![k(0, 1), k(0, 5)], vec![(k(0, 3), 0), (k(2, 0), 0)])
        );
        assert_eq!(sorted_changes(&[], &new), (vec![], new.to_vec()));
        assert_eq!(
            sorted_changes(&old, &[]),
            (old.iter().map(|&(k, _)| k).collect(), vec![])
        );
        // A tile that stays with another face mask comes again, with its new mask.
        let remasked = [(k(0, 1), 0), (k(0, 2), 5), (k(0, 5), 0), (k(1, 0), 3)];
        assert_eq!(
            sorted_changes(&old, &remasked),
            (vec![], vec![(k(0, 2), 5)])
        );
    }

    #[test]
    fn a_new_selection_drops_what_left_and_counts_what_came() {
        let mut d = Desired::default();
        assert!(d.replace(vec![k(0, 1), k(0, 2)], None).is_empty());
        assert_eq!(d.missing, 2);
        assert_eq!(d.deliver(k(0, 1), 7), Some(true));
        // Unsorted on purpose: sorted before the merge.
        let dropped = d.replace(vec![k(0, 3), k(0, 2)], None);
        // k(0, 1) had been shown: dropped; k(0, 2) stays missing, k(0, 3) came.
        assert_eq!(dropped, vec![k(0, 1)]);
        assert_eq!(d.missing, 2);
        assert_eq!(d.sorted_keys(), vec![k(0, 2), k(0, 3)]);
        // The same selection again changes nothing.
        assert!(d.replace(vec![k(0, 2), k(0, 3)], None).is_empty());
        assert_eq!(d.missing, 2);
    }
}
