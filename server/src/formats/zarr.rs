//! The OME-Zarr 0.5 view (Zarr v3) of a volume.
//!
//! ```text
//! zarr.json              the group: ome.multiscales (axes z, y, x; one dataset per level with
//!                        its scale) and every array's metadata inline (consolidated_metadata),
//!                        so a client needs no listing and no further metadata request
//! {k}/zarr.json          level k as an array: shape (z, y, x) = ceil(dims / 2^k), chunks of
//!                        one brick, uint8 or uint16, fill value 0, codecs bytes + zstd
//! {k}/c/{z}/{y}/{x}      one chunk: brick (x, y, z) of level k, full size (Zarr pads edge
//!                        chunks; bricks are padded with 0 beyond the volume already)
//! ```
//!
//! A brick's voxels are x fastest, then y, then z: exactly a C-order chunk of shape
//! (b, b, b) over axes (z, y, x), u16 little endian. So a brick stored as a zstd frame is
//! already a chunk of the codec chain `bytes` (little endian) + `zstd` and goes out as it is
//! when its frame qualifies ([`super::view::frame_qualifies`]). Bricks stored otherwise (raw
//! when compression did not pay, lz4, constant) are compressed with zstd on request. A brick
//! equal to the fill value everywhere answers 404, which Zarr clients read as the fill value.
//!
//! Each attribute channel (`docs/channels.md`) is an OME-Zarr label image under `labels/`:
//!
//! ```text
//! labels/zarr.json                 {"ome": {"labels": [every channel's name]}}
//! labels/{channel}/zarr.json       the channel's multiscales (the same datasets, "type": "mode")
//!                                  and "image-label": its palette as colours, source ../../
//! labels/{channel}/{k}/...         level k of the channel, as the image's levels are
//! ```
//!
//! The root group's consolidated metadata lists these too.
//!
//! Level k's voxel i is the mean of level-0 voxels [i 2^k, (i + 1) 2^k) (the pyramid averages
//! 2x2x2 blocks). OME-Zarr places a voxel's coordinate at its centre, so level k's dataset has
//! the scale s 2^k and the translation s (2^k - 1) / 2: its voxel centres fall on the centres
//! of the level-0 blocks they average, and every level lines up with level 0.

use super::view::{level_segment, Chunk, ChunkEncoding, Document, ViewError};
use crate::store::{Snapshot, StoredBrick};
use isovox_proto::{VolumeLayout, VoxelType};
use serde_json::{json, Value};

/// The Zarr data type of a voxel type.
pub fn data_type(voxel_type: VoxelType) -> &'static str {
    match voxel_type {
        VoxelType::U8 => "uint8",
        VoxelType::U16 => "uint16",
        VoxelType::U32 => "uint32",
        VoxelType::U64 => "uint64",
    }
}

/// Level `level`'s array metadata (`{k}/zarr.json`).
pub fn array_metadata(layout: &VolumeLayout, level: u8) -> Value {
    let [x, y, z] = layout.level_dims(level);
    let b = layout.brick();
    json!({
        "zarr_format": 3,
        "node_type": "array",
        "shape": [z, y, x],
        "data_type": data_type(layout.voxel_type()),
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [b, b, b]}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": 0,
        "codecs": [
            {"name": "bytes", "configuration": {"endian": "little"}},
            {"name": "zstd", "configuration": {"level": super::view::ZSTD_LEVEL, "checksum": false}}
        ],
        "attributes": {},
        "dimension_names": ["z", "y", "x"]
    })
}

/// The group's metadata (`zarr.json`): OME-Zarr 0.5 multiscales and the consolidated metadata
/// of every level.
pub fn group_metadata(layout: &VolumeLayout, voxel_scale: [f32; 3], name: &str) -> Value {
    multiscale_group(layout, voxel_scale, name, "mean")
}

/// A multiscale image group of `layout`'s levels, downsampled by `method`.
fn multiscale_group(
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    name: &str,
    method: &str,
) -> Value {
    let levels = 0..layout.levels();
    let datasets: Vec<Value> = levels
        .clone()
        .map(|k| {
            let f = f64::from(1u32 << k);
            let [sx, sy, sz] = voxel_scale.map(|s| f64::from(s) * f);
            let [tx, ty, tz] = voxel_scale.map(|s| f64::from(s) * (f - 1.0) / 2.0);
            json!({
                "path": k.to_string(),
                "coordinateTransformations": [
                    {"type": "scale", "scale": [sz, sy, sx]},
                    {"type": "translation", "translation": [tz, ty, tx]}
                ]
            })
        })
        .collect();
    let arrays: serde_json::Map<String, Value> = levels
        .map(|k| (k.to_string(), array_metadata(layout, k)))
        .collect();
    json!({
        "zarr_format": 3,
        "node_type": "group",
        "attributes": {
            "ome": {
                "version": "0.5",
                "multiscales": [{
                    "name": name,
                    "axes": [
                        {"name": "z", "type": "space"},
                        {"name": "y", "type": "space"},
                        {"name": "x", "type": "space"}
                    ],
                    "datasets": datasets,
                    "type": method
                }]
            }
        },
        "consolidated_metadata": {"kind": "inline", "must_understand": false, "metadata": arrays}
    })
}

/// The root group's metadata: [`group_metadata`], and when the volume has channels, the
/// `labels` groups and arrays in its consolidated metadata.
fn root_metadata(snap: &Snapshot, name: &str) -> Value {
    let mut root = group_metadata(snap.layout(), snap.header().voxel_scale, name);
    if snap.channel_views().is_empty() {
        return root;
    }
    let consolidated = &mut root["consolidated_metadata"]["metadata"];
    consolidated["labels"] = labels_metadata(snap);
    for view in snap.channel_views() {
        let channel = channel_name(view);
        let mut group = label_metadata(view);
        if let Some(arrays) = group["consolidated_metadata"]["metadata"]
            .as_object()
            .cloned()
        {
            for (k, array) in arrays {
                consolidated[format!("labels/{channel}/{k}")] = array;
            }
        }
        if let Some(g) = group.as_object_mut() {
            g.remove("consolidated_metadata");
        }
        consolidated[format!("labels/{channel}")] = group;
    }
    root
}

/// The name of the attribute channel `view` is of.
fn channel_name(view: &Snapshot) -> &str {
    channel_info(view).map_or("", |c| c.name.as_str())
}

/// The description of the attribute channel `view` is of (`None` for density's).
fn channel_info(view: &Snapshot) -> Option<&isovox_proto::channel::ChannelInfo> {
    view.header().channels.get(view.stream().wrapping_sub(1))
}

/// `labels/zarr.json`: the label images there are, one per channel.
fn labels_metadata(snap: &Snapshot) -> Value {
    let names = snap.channel_names();
    json!({
        "zarr_format": 3,
        "node_type": "group",
        "attributes": {"ome": {"version": "0.5", "labels": names}}
    })
}

/// `labels/{channel}/zarr.json`: the channel's levels (by mode) as a label image of the image
/// two levels up, its palette as the label colours.
fn label_metadata(view: &Snapshot) -> Value {
    let name = channel_name(view);
    let mut group = multiscale_group(view.layout(), view.header().voxel_scale, name, "mode");
    let palette = channel_info(view)
        .map(|c| c.palette.as_slice())
        .unwrap_or_default();
    let colors: Vec<Value> = palette
        .iter()
        .enumerate()
        .filter_map(|(value, hex)| {
            let hex = hex.strip_prefix('#').unwrap_or(hex);
            let rgb = u32::from_str_radix(hex, 16).ok().filter(|_| hex.len() == 6)?;
            Some(json!({"label-value": value, "rgba": [rgb >> 16, (rgb >> 8) & 255, rgb & 255, 255]}))
        })
        .collect();
    group["attributes"]["ome"]["image-label"] =
        json!({"version": "0.5", "colors": colors, "source": {"image": "../../"}});
    group
}

/// What `path` names in the Zarr view of `snap` (volume `name`).
///
/// # Errors
/// See [`super::view::resolve`].
pub fn document<'s>(snap: &'s Snapshot, name: &str, path: &str) -> Result<Document<'s>, ViewError> {
    if path == "zarr.json" {
        return Ok(metadata(&root_metadata(snap, name)));
    }
    if let Some(rest) = path.strip_prefix("labels/") {
        if rest == "zarr.json" && !snap.channel_views().is_empty() {
            return Ok(metadata(&labels_metadata(snap)));
        }
        let (channel, rest) = rest.split_once('/').unwrap_or((rest, ""));
        let view = snap.channel_view(channel).ok_or_else(|| {
            ViewError::NoSuchDocument(format!(
                "no label image {channel:?}: the volume's channels are {:?}",
                snap.channel_names()
            ))
        })?;
        if rest == "zarr.json" {
            return Ok(metadata(&label_metadata(view)));
        }
        return level_document(view, Some(view), rest);
    }
    level_document(snap, None, path)
}

/// What `path` names among the level arrays of `snap` (`view`: the shared channel view when
/// `snap` is one).
fn level_document<'s>(
    snap: &'s Snapshot,
    view: Option<&'s std::sync::Arc<Snapshot>>,
    path: &str,
) -> Result<Document<'s>, ViewError> {
    let layout = snap.layout();
    let mut parts = path.split('/');
    let segments: [Option<&str>; 6] = std::array::from_fn(|_| parts.next());
    match segments {
        [Some(level), Some("zarr.json"), None, ..] => Ok(metadata(&array_metadata(
            layout,
            level_segment(snap, level)?,
        ))),
        [Some(level), Some("c"), Some(z), Some(y), Some(x), None] => {
            let level = level_segment(snap, level)?;
            // One spelling per chunk (`crate::decimal`): `01` or `+1` is no chunk.
            let coord = |s: &str| crate::decimal::parse::<u32>(s).ok();
            let key = match (coord(x), coord(y), coord(z)) {
                (Some(x), Some(y), Some(z)) => layout.key(level, x, y, z).ok(),
                _ => None,
            }
            .ok_or_else(|| {
                let [gx, gy, gz] = layout.grid(level);
                let spelled_otherwise = [x, y, z].iter().any(|s| {
                    crate::decimal::parse::<u32>(s) == Err(crate::decimal::NotCanonical::OtherSpelling)
                });
                ViewError::NoSuchDocument(if spelled_otherwise {
                    format!(
                        "no chunk {z}/{y}/{x}: chunk coordinates are spelled in plain decimal, \
                         without a sign, leading zeros or escapes"
                    )
                } else {
                    format!(
                        "no chunk {z}/{y}/{x} at level {level}: its chunk grid (z, y, x) is {gz} x {gy} x {gx}"
                    )
                })
            })?;
            let stored = snap.stored(key)?;
            if matches!(stored, StoredBrick::Constant(0)) {
                return Ok(Document::Absent);
            }
            Ok(Document::Chunk(Chunk {
                key,
                stored,
                encoding: ChunkEncoding::ZstdFrame,
                view,
            }))
        }
        _ => Err(ViewError::NoSuchDocument(format!(
            "{path:?} is not in the Zarr view: it has zarr.json, {{level}}/zarr.json, {{level}}/c/{{z}}/{{y}}/{{x}}, and labels/{{channel}}/ the same for each channel"
        ))),
    }
}

fn metadata(value: &Value) -> Document<'static> {
    Document::Metadata(serde_json::to_vec_pretty(value).unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_halve_the_shape_and_double_the_scale() {
        // 197 x 77 x 141 voxels, brick 32: level 1 is ceil(/2) = 99 x 39 x 71, in (z, y, x).
        let layout = VolumeLayout::new([197, 77, 141], 32, VoxelType::U16).unwrap();
        let a = array_metadata(&layout, 1);
        assert_eq!(a["shape"], json!([71, 39, 99]));
        assert_eq!(a["data_type"], "uint16");
        assert_eq!(
            a["chunk_grid"]["configuration"]["chunk_shape"],
            json!([32, 32, 32])
        );
        let g = group_metadata(&layout, [0.5, 1.0, 2.0], "v");
        let ms = &g["attributes"]["ome"]["multiscales"][0];
        assert_eq!(g["attributes"]["ome"]["version"], "0.5");
        // Scales are (z, y, x): level 0 is (2, 1, 0.5), level 2 four times that.
        assert_eq!(
            ms["datasets"][0]["coordinateTransformations"][0]["scale"],
            json!([2.0, 1.0, 0.5])
        );
        assert_eq!(
            ms["datasets"][2]["coordinateTransformations"][0]["scale"],
            json!([8.0, 4.0, 2.0])
        );
        // Level 2's voxel 0 averages level-0 voxels 0..4, whose centre is at 1.5 voxels:
        // 1.5 times (2, 1, 0.5); level 0 needs none.
        assert_eq!(
            ms["datasets"][2]["coordinateTransformations"][1]["translation"],
            json!([3.0, 1.5, 0.75])
        );
        assert_eq!(
            ms["datasets"][0]["coordinateTransformations"][1]["translation"],
            json!([0.0, 0.0, 0.0])
        );
        // One dataset and one consolidated array per level: 197 needs levels up to one brick
        // (197 -> 99 -> 50 -> 25 <= 32): 4 levels.
        assert_eq!(ms["datasets"].as_array().unwrap().len(), 4);
        assert_eq!(
            g["consolidated_metadata"]["metadata"]["3"]["shape"],
            json!([18, 10, 25])
        );
    }
}
