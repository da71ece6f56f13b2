//! Who did what: the record each commit keeps of itself (its author, message and what it did),
//! the history, tags, undo and revert, and presence (JSON of the HTTP API).
//!
//! A commit's [`CommitNote`] is stored in its commit record (VOD 2 revision 3, `docs/vod2.md`);
//! the change feed, `changes?since=N` and `history` all read it from there, so they agree.

use crate::geometry::Box3;
use crate::icvg::{EditRequest, Term};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Longest commit message, in characters.
pub const MAX_MESSAGE_CHARS: usize = 200;

/// Longest tag name, in bytes (tags are `[A-Za-z0-9._-]`, not all digits).
pub const MAX_TAG_LEN: usize = 64;

/// What a commit did, as the feed, `changes` and `history` tell it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CommitInfo {
    /// The user who made it; absent for commits made without a user (imports, older files).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub author: Option<String>,
    /// Their message, if they gave one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// `edit`, `undo`, `redo`, `revert` or `tag`; absent for commits that recorded nothing
    /// (files written before revision 3, imports, compactions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kind: Option<CommitKind>,
    /// For an edit: the operation, its leaves' kinds and the box it can change.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub op: Option<OpSummary>,
    /// For an undo or redo: the version of the edit undone or made again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<u64>,
    /// For an undo or redo: later edits applied again over the bricks it changed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replayed: Option<u64>,
    /// For a revert: the version whose content it restored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub to: Option<u64>,
    /// For a tag: its name (the version it names is `to`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tag: Option<String>,
}

/// The kinds of commit a note names.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CommitKind {
    /// An ICVG edit.
    Edit,
    /// One edit taken back, later edits over it applied again.
    Undo,
    /// An undone edit made again.
    Redo,
    /// The content of an earlier version restored.
    Revert,
    /// A name given to a version (changes no brick).
    Tag,
}

/// An edit's operation in a few words: its operator, the kinds of its term's leaves and the
/// level-0 box it can change.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OpSummary {
    /// The operator (`union`, `difference`, ..., `inverse`).
    pub op: String,
    /// The kinds of the term's leaves, each once, in the order they first appear
    /// (`ellipsoid`, `cuboid`, ..., `volume`, `mesh`).
    pub leaves: Vec<String>,
    /// The level-0 voxels it can change (min inclusive, max exclusive).
    #[serde(rename = "box")]
    pub bbox: Box3,
}

impl OpSummary {
    /// The summary of `request`, whose reach in the volume is `bbox`.
    pub fn of(request: &EditRequest, bbox: Box3) -> OpSummary {
        let mut leaves = Vec::new();
        if let Some(term) = &request.term {
            leaf_kinds(term, &mut leaves);
        }
        OpSummary {
            op: request.op.clone(),
            leaves,
            bbox,
        }
    }
}

/// Adds the kinds of `term`'s leaves not yet in `out`, in the order they appear.
fn leaf_kinds(term: &Term, out: &mut Vec<String>) {
    let mut add = |kind: &str| {
        if !out.iter().any(|k| k == kind) {
            out.push(kind.to_string());
        }
    };
    match term {
        Term::Cuboid { .. } => add("cuboid"),
        Term::Ellipsoid { .. } => add("ellipsoid"),
        Term::Cylinder { .. } => add("cylinder"),
        Term::Cone { .. } => add("cone"),
        Term::Torus { .. } => add("torus"),
        Term::Capsule { .. } => add("capsule"),
        Term::Prism { .. } => add("prism"),
        Term::Pyramid { .. } => add("pyramid"),
        Term::Volume { .. } => add("volume"),
        Term::Mesh { .. } => add("mesh"),
        Term::Union(a, b)
        | Term::Intersection(a, b)
        | Term::Trim(a, b)
        | Term::Cap(a, b)
        | Term::Difference(a, b)
        | Term::DifferenceA(a, b)
        | Term::DifferenceB(a, b)
        | Term::Add(a, b)
        | Term::Modulate(a, b)
        | Term::Product(a, b)
        | Term::DivideA(a, b)
        | Term::Divide { args: (a, b), .. } => {
            leaf_kinds(a, out);
            leaf_kinds(b, out);
        }
        Term::Inverse(a)
        | Term::Complement(a)
        | Term::AddScalar { arg: a, .. }
        | Term::Dilate { arg: a, .. }
        | Term::Erode { arg: a, .. }
        | Term::Attributed { leaf: a, .. } => leaf_kinds(a, out),
    }
}

/// What a commit record keeps of its commit (VOD 2 revision 3): what [`CommitInfo`] tells,
/// and for an edit what replaying it needs.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CommitNote {
    /// What the commit did.
    #[serde(flatten)]
    pub info: CommitInfo,
    /// For an edit: its request, applied again when an earlier edit under it is undone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub request: Option<EditRequest>,
    /// For an edit whose term reads other volumes (`volume` leaves): the version of each it
    /// read, so that replaying it reads the same voxels.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub reads: BTreeMap<String, u64>,
}

/// One entry of `GET /v1/volumes/{name}/history`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct HistoryEntry {
    /// The version the commit made.
    pub version: u64,
    /// When (Unix milliseconds).
    pub timestamp_ms: u64,
    /// Who, and what.
    #[serde(flatten)]
    pub info: CommitInfo,
    /// Bricks whose content it changed, over every level.
    pub bricks_changed: u64,
    /// For an edit: whether it is undone now (by an undo, or a revert to a version before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub undone: Option<bool>,
}

/// `GET /v1/volumes/{name}/history?before=V&limit=N`: commits newest first.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct HistoryList {
    /// The current version.
    pub head: u64,
    /// The oldest version the file holds.
    pub oldest: u64,
    /// The commits, newest first.
    pub commits: Vec<HistoryEntry>,
    /// Older commits exist: ask again with `before` the last version listed.
    pub more: bool,
}

/// `PUT /v1/volumes/{name}/tags/{tag}`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TagRequest {
    /// The version the tag names.
    pub version: u64,
}

/// One tag.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Tag {
    /// Its name.
    pub tag: String,
    /// The version it names.
    pub version: u64,
    /// Who set it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub author: Option<String>,
    /// The version of the commit that set it.
    pub set_at: u64,
}

/// `GET /v1/volumes/{name}/tags`: every tag, by name.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TagList {
    /// The tags, sorted by name.
    pub tags: Vec<Tag>,
}

/// `POST /v1/volumes/{name}/undo`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UndoRequest {
    /// The version whose commit is taken back: an edit (undo), or an undo (redo of its edit).
    pub version: u64,
    /// A message for the new commit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
}

/// `POST /v1/volumes/{name}/revert`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RevertRequest {
    /// The version whose content the new version has.
    pub to: u64,
    /// A message for the new commit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
}

/// `POST /v1/volumes/{name}/presence`: where the user is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PresenceRequest {
    /// The camera's position, in level-0 voxels.
    pub position: [f64; 3],
    /// Where it looks (a point or a direction, as the client likes), in level-0 voxels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub looking: Option<[f64; 3]>,
    /// A short label shown beside the cursor (at most 64 characters).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label: Option<String>,
}

/// One user present on a volume, as `presence` events and `GET .../presence` tell it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Presence {
    /// The user.
    pub user: String,
    /// Where they are.
    pub position: [f64; 3],
    /// Where they look.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub looking: Option<[f64; 3]>,
    /// Their label.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label: Option<String>,
    /// When they said so last (Unix milliseconds).
    pub at_ms: u64,
    /// `true` on the event that says the user left (silent for too long).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub gone: bool,
}

/// `GET /v1/volumes/{name}/presence`: who is there now.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PresenceList {
    /// Users heard from within the last seconds, by name.
    pub present: Vec<Presence>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn leaves_are_listed_once_in_order() {
        let request: EditRequest = serde_json::from_str(
            r#"{"op": "union", "term": {"difference": [
                {"ellipsoid": {"center": [1, 2, 3], "radii": [4, 4, 4]}},
                {"union": [{"cuboid": {"origin": [0, 0, 0], "size": [4, 4, 4]}},
                           {"ellipsoid": {"center": [9, 9, 9], "radii": [2, 2, 2]}}]}]}}"#,
        )
        .unwrap();
        let bbox = Box3 {
            min: [0; 3],
            max: [8; 3],
        };
        let s = OpSummary::of(&request, bbox);
        assert_eq!(s.op, "union");
        assert_eq!(s.leaves, ["ellipsoid", "cuboid"]);
    }

    #[test]
    fn a_note_round_trips_and_the_info_is_flat() {
        let note = CommitNote {
            info: CommitInfo {
                author: Some("alice".into()),
                kind: Some(CommitKind::Undo),
                target: Some(7),
                replayed: Some(2),
                ..CommitInfo::default()
            },
            ..CommitNote::default()
        };
        let json = serde_json::to_value(&note).unwrap();
        assert_eq!(json["author"], "alice");
        assert_eq!(json["kind"], "undo");
        assert_eq!(json["target"], 7);
        assert!(json.get("message").is_none());
        let back: CommitNote = serde_json::from_value(json).unwrap();
        assert_eq!(back, note);
    }
}
