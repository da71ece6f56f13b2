//! `isovox edit`: apply an ICVG edit to a VOD 2 file as a new version; and the demo scene.

use super::parse_dims;
use crate::icvg::edit::{apply_edit, CheckpointPolicy, Edit, EditOutcome};
use crate::icvg::term::{TermError, TermLimits, VolumeResolver};
use crate::store::codec::Compression;
use crate::store::{Snapshot, Vod2, Vod2Writer};
use anyhow::{bail, Context};
use clap::Args;
use isovox_proto::icvg::{EditRequest, Term};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Debug, Args)]
pub struct EditArgs {
    /// The VOD 2 file to edit.
    pub input: PathBuf,
    /// An edit request as JSON (spec/icvg.md), e.g. {"op": "difference", "term": {...}}; `-`
    /// reads it from stdin.
    pub edit: Option<PathBuf>,
    /// Operator for the shorthand primitives below.
    #[arg(long, default_value = "difference")]
    pub op: String,
    /// Shorthand: an ellipsoid CX,CY,CZ,RX,RY,RZ.
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    pub ellipsoid: Option<Vec<i64>>,
    /// Shorthand: a cuboid X,Y,Z,SX,SY,SZ.
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    pub cuboid: Option<Vec<i64>>,
}

/// Volumes named in terms are the `NAME.vod` files beside the edited one.
#[derive(Debug)]
pub struct DirVolumes {
    pub dir: PathBuf,
}

impl VolumeResolver for DirVolumes {
    /// Meshes uploaded to a server on this directory (`DIR/meshes/HASH.EXT`).
    fn mesh(&self, hash: u64) -> Result<Arc<crate::voxelize::solid::TriMesh>, TermError> {
        crate::voxelize::store::MeshStore::new(&self.dir.join("meshes"))
            .get(hash)
            .map_err(TermError)
    }

    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        if !crate::catalog::valid_name(name) {
            return Err(TermError(format!("{name:?} is not a volume name")));
        }
        let path = self.dir.join(format!("{name}.vod"));
        Vod2::open(&path).map(|v| v.head()).map_err(|e| {
            TermError(format!(
                "volume {name:?} ({}): {}",
                path.display(),
                crate::store::error_chain(&e)
            ))
        })
    }
}

fn u32s(v: &[i64], what: &str) -> anyhow::Result<[u32; 3]> {
    let mut out = [0u32; 3];
    for (o, x) in out.iter_mut().zip(v) {
        *o = u32::try_from(*x).with_context(|| format!("{what} must be non-negative, got {x}"))?;
    }
    Ok(out)
}

fn request(a: &EditArgs) -> anyhow::Result<EditRequest> {
    for (flag, values) in [("--ellipsoid", &a.ellipsoid), ("--cuboid", &a.cuboid)] {
        if values.as_ref().is_some_and(|v| v.len() != 6) {
            bail!("{flag} takes six comma-separated integers");
        }
    }
    let shorthand = match (&a.ellipsoid, &a.cuboid) {
        (Some(e), None) => Some(Term::Ellipsoid {
            center: [e[0], e[1], e[2]],
            radii: u32s(&e[3..], "ellipsoid radii")?,
        }),
        (None, Some(c)) => Some(Term::Cuboid {
            origin: [c[0], c[1], c[2]],
            size: u32s(&c[3..], "cuboid size")?,
        }),
        (None, None) => None,
        _ => bail!("give one shorthand primitive at a time"),
    };
    match (&a.edit, shorthand) {
        (Some(_), Some(_)) => bail!("give either an edit file or a shorthand primitive, not both"),
        (Some(path), None) => {
            let text = if path.as_os_str() == "-" {
                std::io::read_to_string(std::io::stdin())
                    .context("cannot read the edit from stdin")?
            } else {
                std::fs::read_to_string(path)
                    .with_context(|| format!("cannot read {}", path.display()))?
            };
            serde_json::from_str(&text)
                .with_context(|| format!("{} is not a valid edit request", path.display()))
        }
        (None, Some(term)) => Ok(EditRequest {
            op: a.op.clone(),
            term: Some(term),
            s_l: None,
            k: None,
            region: None,
        }),
        (None, None) => {
            bail!("give an edit file (JSON) or a shorthand such as --ellipsoid CX,CY,CZ,RX,RY,RZ")
        }
    }
}

/// Applies one edit request to the file at `path` and commits it.
///
/// # Errors
/// The file does not open, the edit is invalid, or the commit fails.
pub fn edit_file(path: &Path, req: &EditRequest) -> anyhow::Result<EditOutcome> {
    let vod = Vod2::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let snap = vod.head();
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let edit = Edit::from_request(
        req,
        snap.layout().voxel_type(),
        &TermLimits::default(),
        &DirVolumes { dir },
    )
    .map_err(|e| anyhow::anyhow!("invalid edit: {e}"))?;
    let mut writer = Vod2Writer::open_append(path, Compression::default())?;
    Ok(apply_edit(
        &mut writer,
        &snap,
        &edit,
        CheckpointPolicy::default(),
    )?)
}

pub fn edit(a: EditArgs) -> anyhow::Result<()> {
    let req = request(&a)?;
    let outcome = edit_file(&a.input, &req)?;
    println!("{}", serde_json::to_string(&outcome)?);
    Ok(())
}

/// The edits that turn a generated world of `dims` into the demo scene: tunnels carved through
/// the terrain, a crater, and a few primitives standing on it.
pub fn scene_edits(dims: [u32; 3]) -> Vec<EditRequest> {
    let [x, y, z] = dims.map(|d| d as i64);
    let r = |v: i64| v.max(2) as u32;
    let edit = |op: &str, term: Term| EditRequest {
        op: op.into(),
        term: Some(term),
        s_l: None,
        k: None,
        region: None,
    };
    vec![
        // Two tunnels along x and one along z, at two thirds of the terrain's mean height.
        edit(
            "difference",
            Term::Ellipsoid {
                center: [x / 2, y * 2 / 5, z / 3],
                radii: [r(x * 9 / 20), r(y / 14), r(y / 14)],
            },
        ),
        edit(
            "difference",
            Term::Ellipsoid {
                center: [x / 2, y / 3, z * 2 / 3],
                radii: [r(x * 9 / 20), r(y / 12), r(y / 12)],
            },
        ),
        edit(
            "difference",
            Term::Ellipsoid {
                center: [x / 3, y * 3 / 10, z / 2],
                radii: [r(y / 16), r(y / 16), r(z * 9 / 20)],
            },
        ),
        // A crater.
        edit(
            "difference",
            Term::Ellipsoid {
                center: [x * 3 / 4, y * 3 / 5, z / 4],
                radii: [r(x / 10), r(y / 6), r(z / 10)],
            },
        ),
        // A ring, a pyramid and a tower.
        edit(
            "union",
            Term::Torus {
                center: [x / 4, y * 4 / 5, z * 3 / 4],
                major: r(x / 12),
                minor: r(y / 30),
            },
        ),
        edit(
            "union",
            Term::Pyramid {
                origin: [x * 3 / 5, y / 3, z * 3 / 5],
                size: [r(x / 8), r(y / 2), r(z / 8)],
            },
        ),
        edit(
            "union",
            Term::Cylinder {
                base: [x / 8, y / 5, z / 8],
                radii: [r(x / 40), r(z / 40)],
                height: r(y * 7 / 10),
            },
        ),
        edit(
            "union",
            Term::Cone {
                base: [x / 8, y * 9 / 10 - r(y / 5) as i64, z / 8],
                radii: [r(x / 25), r(z / 25)],
                height: r(y / 5),
            },
        ),
    ]
}

#[derive(Debug, Args)]
pub struct SceneArgs {
    #[arg(long, value_parser = parse_dims)]
    pub dims: [u32; 3],
}
