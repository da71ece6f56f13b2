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
    /// An edit request as JSON (docs/icvg.md), e.g. {"op": "difference", "term": {...}}; `-`
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

pub(super) fn edit(a: EditArgs) -> anyhow::Result<()> {
    let req = request(&a)?;
    let outcome =
        edit_file(&a.input, &req).with_context(|| format!("cannot edit {}", a.input.display()))?;
    out!("{}", serde_json::to_string(&outcome)?)?;
    Ok(())
}
