//! `isovox edit`: apply an ICVG edit to a VOD 2 file as a new version.

use anyhow::{bail, Context};
use clap::Args;
use isovox_proto::icvg::{EditRequest, Term};
use isovox_server::volume::edit_file;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub(crate) struct EditArgs {
    /// The VOD 2 file to edit.
    pub input: PathBuf,
    /// The edit request (docs/icvg.md): inline JSON when it starts with `{`, e.g.
    /// '{"op": "difference", "term": {...}}'; `-` reads it from stdin; anything else is the
    /// path of a JSON file holding it.
    pub edit: Option<String>,
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
        (Some(_), Some(_)) => {
            bail!("give either an edit (JSON or a file) or a shorthand primitive, not both")
        }
        (Some(given), None) => {
            // A path never starts with `{` in practice, and JSON text always does: so the
            // argument that `edit --help` shows (inline JSON) works as it reads.
            let (text, what) = if given.trim_start().starts_with('{') {
                (given.clone(), "the edit given".to_string())
            } else if given == "-" {
                let text = std::io::read_to_string(std::io::stdin())
                    .context("cannot read the edit from stdin")?;
                (text, "the edit read from stdin".to_string())
            } else {
                let text = std::fs::read_to_string(given)
                    .with_context(|| format!("cannot read the edit file {given}"))?;
                (text, given.clone())
            };
            serde_json::from_str(&text)
                .with_context(|| format!("{what} is not a valid edit request"))
        }
        (None, Some(term)) => Ok(EditRequest {
            op: a.op.clone(),
            term: Some(term),
            s_l: None,
            k: None,
            region: None,
            message: None,
            channel: None,
            overwrite: None,
        }),
        (None, None) => {
            bail!("give an edit (inline JSON, a JSON file or - for stdin) or a shorthand such as --ellipsoid CX,CY,CZ,RX,RY,RZ")
        }
    }
}

pub(super) fn edit(a: EditArgs) -> anyhow::Result<()> {
    let req = request(&a)?;
    let outcome =
        edit_file(&a.input, &req).with_context(|| format!("cannot edit {}", a.input.display()))?;
    if !outcome.committed {
        eprintln!(
            "the edit reaches no voxel of {}: nothing changed, no version committed (still {})",
            a.input.display(),
            outcome.version
        );
    }
    out!("{}", serde_json::to_string(&outcome)?)?;
    Ok(())
}
