//! The Neuroglancer precomputed view of a volume.
//!
//! ```text
//! info                                    one scale per level, finest first: key "k", size
//!                                         ceil(dims / 2^k), resolution voxel scale * 2^k,
//!                                         voxel offset 0, chunk size = brick, raw encoding
//! {k}/{x0}-{x1}_{y0}-{y1}_{z0}-{z1}       one chunk: brick (x0 / b, y0 / b, z0 / b) of level
//!                                         k, cropped to the level's extent
//! ```
//!
//! Each attribute channel (`docs/channels.md`) is a data source of its own under
//! `{channel}/`: `{channel}/info` says `"type": "segmentation"`, uint32 values (u8, u16 and
//! u32 channels; the encoding below is defined for uint32 and uint64 only) or uint64 (u64
//! channels) and the
//! `compressed_segmentation` encoding in blocks of 8^3, and `{channel}/{k}/{range}` is the
//! channel's brick so encoded ([`super::compressed_segmentation`]): Neuroglancer opens it as a
//! segmentation layer. Its info names `segment_properties`, and
//! `{channel}/segment_properties/info` lists the channel's segments as Neuroglancer's segment
//! properties ([`segment_properties`]): the layer's segment list shows each one's size and box.
//!
//! A raw chunk is the voxels x fastest, then y, then z (little endian), as a brick is; chunks
//! at the volume's far faces are cropped (`x1 = min(x0 + b, size)`), as Neuroglancer checks the
//! byte count. A range that is not a chunk's (misaligned, wrong end) is a 400; a chunk past the
//! level's extent, a level the volume does not have, or a number spelled other than in plain
//! decimal (`+0`, `00`, `%30`: one URL per chunk) is a 404.

use super::view::{level_segment, Chunk, ChunkEncoding, Document, ViewError};
use crate::decimal::NotCanonical;
use crate::store::Snapshot;
use crate::volume::segments::SegmentInfo;
use isovox_proto::{VolumeLayout, VoxelType};
use serde_json::{json, Value};

/// The `info` document.
pub fn info(layout: &VolumeLayout, voxel_scale: [f32; 3]) -> Value {
    scales_info(layout, voxel_scale, Source::Image)
}

/// What a data source of the view holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    /// Density, raw.
    Image,
    /// An attribute channel, as uint32 labels in `compressed_segmentation`.
    Segmentation,
}

/// The `info` document of a data source of `layout`'s levels.
fn scales_info(layout: &VolumeLayout, voxel_scale: [f32; 3], source: Source) -> Value {
    let b = layout.brick();
    let scales: Vec<Value> = (0..layout.levels())
        .map(|k| {
            let f = f64::from(1u32 << k);
            json!({
                "key": k.to_string(),
                "size": layout.level_dims(k),
                "resolution": voxel_scale.map(|s| f64::from(s) * f),
                "voxel_offset": [0, 0, 0],
                "chunk_sizes": [[b, b, b]],
            })
        })
        .map(|mut scale| {
            match source {
                Source::Image => scale["encoding"] = json!("raw"),
                Source::Segmentation => {
                    scale["encoding"] = json!("compressed_segmentation");
                    scale["compressed_segmentation_block_size"] =
                        json!(super::compressed_segmentation::BLOCK);
                }
            }
            scale
        })
        .collect();
    let (kind, data_type) = match source {
        Source::Image => ("image", super::zarr::data_type(layout.voxel_type())),
        Source::Segmentation => ("segmentation", segmentation_type(layout.voxel_type())),
    };
    let mut info = json!({
        "@type": "neuroglancer_multiscale_volume",
        "type": kind,
        "data_type": data_type,
        "num_channels": 1,
        "scales": scales
    });
    if source == Source::Segmentation {
        info["segment_properties"] = json!(SEGMENT_PROPERTIES);
    }
    info
}

/// The precomputed data type of a channel's labels: the encoding is defined for uint32 and
/// uint64 only, so u8 and u16 channels are widened to uint32.
pub fn segmentation_type(voxel_type: VoxelType) -> &'static str {
    match voxel_type {
        VoxelType::U64 => "uint64",
        _ => "uint32",
    }
}

/// Where a segmentation source's segment properties are, relative to the source.
const SEGMENT_PROPERTIES: &str = "segment_properties";

/// The channel whose segment properties `path` (within the view) names:
/// `{channel}/segment_properties/info`.
pub fn segment_properties_channel(path: &str) -> Option<&str> {
    let (channel, rest) = path.split_once('/')?;
    let named = rest.strip_prefix(SEGMENT_PROPERTIES)? == "/info";
    (named && channel.starts_with(|c: char| c.is_ascii_lowercase())).then_some(channel)
}

/// Neuroglancer's segment properties (`neuroglancer_segment_properties`, inline) of
/// `segments`, in the order given: a `description` (the level-0 voxel count and box, as the
/// segments list gives them) and the voxel count as a `number` property, which the segment
/// list can sort and filter by. Neuroglancer's numbers are at most 32 bits: `uint32` while every
/// count fits, `float32` (rounded) beyond.
pub fn segment_properties(segments: &[SegmentInfo]) -> Value {
    let fits = segments.iter().all(|s| s.voxels <= u64::from(u32::MAX));
    let ids: Vec<String> = segments.iter().map(|s| s.id.value.to_string()).collect();
    let descriptions: Vec<String> = segments
        .iter()
        .map(|s| {
            let [lo, hi] = s.bounds;
            format!(
                "{} voxels in [{}, {}, {}] .. [{}, {}, {}]",
                s.voxels, lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
            )
        })
        .collect();
    let voxels: Vec<Value> = segments
        .iter()
        .map(|s| {
            if fits {
                json!(s.voxels)
            } else {
                json!(s.voxels as f32)
            }
        })
        .collect();
    json!({
        "@type": "neuroglancer_segment_properties",
        "inline": {
            "ids": ids,
            "properties": [
                {"id": "description", "type": "description", "values": descriptions},
                {
                    "id": "voxels",
                    "type": "number",
                    "data_type": if fits { "uint32" } else { "float32" },
                    "description": "level-0 voxels holding the id",
                    "values": voxels
                }
            ]
        }
    })
}

/// The file name of a chunk: `{x0}-{x1}_{y0}-{y1}_{z0}-{z1}` for brick `(x, y, z)` of `level`.
pub fn chunk_name(layout: &VolumeLayout, level: u8, brick: [u32; 3]) -> String {
    let b = layout.brick();
    let extent = layout.level_dims(level);
    let r: Vec<String> = (0..3)
        .map(|a| {
            let lo = brick[a] * b;
            format!("{lo}-{}", (lo + b).min(extent[a]))
        })
        .collect();
    r.join("_")
}

/// What `path` names in the precomputed view of `snap`.
///
/// # Errors
/// See [`super::view::resolve`].
pub fn document<'s>(snap: &'s Snapshot, path: &str) -> Result<Document<'s>, ViewError> {
    // A channel's source: its name first (names start with a letter, levels are numbers).
    if let Some((first, rest)) = path.split_once('/') {
        if first.starts_with(|c: char| c.is_ascii_lowercase()) {
            let view = snap.channel_view(first).ok_or_else(|| {
                ViewError::NoSuchDocument(format!(
                    "the volume has no channel {first:?}; its channels: {:?}",
                    snap.channel_names()
                ))
            })?;
            return source_document(view, Some(view), rest, Source::Segmentation);
        }
    }
    source_document(snap, None, path, Source::Image)
}

/// What `path` names in the data source `source` of `snap` (`view`: the shared channel view
/// when `snap` is one).
fn source_document<'s>(
    snap: &'s Snapshot,
    view: Option<&'s std::sync::Arc<Snapshot>>,
    path: &str,
    source: Source,
) -> Result<Document<'s>, ViewError> {
    let layout = snap.layout();
    match path.split_once('/') {
        None if path == "info" => Ok(Document::Metadata(
            serde_json::to_vec_pretty(&scales_info(layout, snap.header().voxel_scale, source))
                .unwrap_or_default(),
        )),
        Some((level, chunk)) => {
            let level = level_segment(snap, level)?;
            let (brick, extent) = parse_chunk(layout, level, chunk)?;
            let key = layout
                .key(level, brick[0], brick[1], brick[2])
                .map_err(|e| ViewError::NoSuchDocument(e.to_string()))?;
            Ok(Document::Chunk(Chunk {
                key,
                stored: snap.stored(key)?,
                encoding: match source {
                    Source::Image => ChunkEncoding::Raw { extent },
                    Source::Segmentation => ChunkEncoding::CompressedSegmentation { extent },
                },
                view,
            }))
        }
        None => Err(ViewError::NoSuchDocument(format!(
            "{path:?} is not in the precomputed view: it has info, {{level}}/{{x0}}-{{x1}}_{{y0}}-{{y1}}_{{z0}}-{{z1}}, and {{channel}}/ (with {{channel}}/segment_properties/info) for each channel"
        ))),
    }
}

/// The brick and the voxel extent of chunk name `name` at `level`.
fn parse_chunk(
    layout: &VolumeLayout,
    level: u8,
    name: &str,
) -> Result<([u32; 3], [u32; 3]), ViewError> {
    let malformed = || {
        ViewError::NotAChunk(format!(
            "{name:?} is not a chunk name: {{x0}}-{{x1}}_{{y0}}-{{y1}}_{{z0}}-{{z1}} expected"
        ))
    };
    // One spelling per chunk (`crate::decimal`): a range spelled with a sign, a leading zero or
    // an escape names no chunk (404); one that is no numbers at all is malformed (400).
    let number = |s: &str| {
        crate::decimal::parse::<u32>(s).map_err(|e| match e {
            NotCanonical::OtherSpelling => ViewError::NoSuchDocument(format!(
                "no chunk {name:?}: its numbers are spelled in plain decimal, without a sign, \
                 leading zeros or escapes"
            )),
            NotCanonical::NotANumber => malformed(),
        })
    };
    let ranges: Vec<(u32, u32)> = name
        .split('_')
        .map(|r| {
            let (lo, hi) = r.split_once('-').ok_or_else(malformed)?;
            Ok((number(lo)?, number(hi)?))
        })
        .collect::<Result<_, ViewError>>()?;
    if ranges.len() != 3 {
        return Err(malformed());
    }
    let b = layout.brick();
    let extent = layout.level_dims(level);
    let (mut brick, mut size) = ([0u32; 3], [0u32; 3]);
    for (a, &(lo, hi)) in ranges.iter().enumerate() {
        let axis = ["x", "y", "z"][a];
        if lo >= extent[a] {
            return Err(ViewError::NoSuchDocument(format!(
                "{axis} {lo}-{hi} starts past level {level}'s extent {}",
                extent[a]
            )));
        }
        let expected_hi = (lo / b * b + b).min(extent[a]);
        if lo % b != 0 || hi != expected_hi {
            return Err(ViewError::NotAChunk(format!(
                "{axis} {lo}-{hi} is not a chunk of level {level}: chunks are {b} voxels, cropped at {}",
                extent[a]
            )));
        }
        brick[a] = lo / b;
        size[a] = hi - lo;
    }
    Ok((brick, size))
}

#[cfg(test)]
mod tests {
    use super::*;
    use isovox_proto::VoxelType;

    fn layout() -> VolumeLayout {
        VolumeLayout::new([197, 77, 141], 32, VoxelType::U8).unwrap()
    }

    #[test]
    fn info_has_one_scale_per_level() {
        let i = info(&layout(), [1.0, 2.0, 4.0]);
        let scales = i["scales"].as_array().unwrap();
        assert_eq!(scales.len(), 4);
        assert_eq!(scales[0]["size"], json!([197, 77, 141]));
        assert_eq!(scales[1]["size"], json!([99, 39, 71]));
        assert_eq!(scales[3]["resolution"], json!([8.0, 16.0, 32.0]));
        assert_eq!(scales[2]["chunk_sizes"], json!([[32, 32, 32]]));
        assert_eq!(i["data_type"], "uint8");
    }

    #[test]
    fn chunk_names_are_cropped_at_the_far_faces() {
        let l = layout();
        assert_eq!(chunk_name(&l, 0, [0, 0, 0]), "0-32_0-32_0-32");
        assert_eq!(chunk_name(&l, 0, [6, 2, 4]), "192-197_64-77_128-141");
        assert_eq!(
            parse_chunk(&l, 0, "192-197_64-77_128-141").unwrap(),
            ([6, 2, 4], [5, 13, 13])
        );
        assert_eq!(
            parse_chunk(&l, 1, "96-99_32-39_64-71").unwrap(),
            ([3, 1, 2], [3, 7, 7])
        );
    }

    #[test]
    fn misaligned_ranges_are_bad_requests_and_far_ones_not_found() {
        let l = layout();
        for bad in [
            "1-33_0-32_0-32",
            "0-31_0-32_0-32",
            "192-224_0-32_0-32",
            "0-32_0-32",
            "a-b_0-32_0-32",
            "0-32_0-32_0-32_0-32",
        ] {
            assert!(
                matches!(parse_chunk(&l, 0, bad), Err(ViewError::NotAChunk(_))),
                "{bad}"
            );
        }
        assert!(matches!(
            parse_chunk(&l, 0, "224-256_0-32_0-32"),
            Err(ViewError::NoSuchDocument(_))
        ));
        assert!(matches!(
            parse_chunk(&l, 1, "128-160_0-32_0-32"),
            Err(ViewError::NoSuchDocument(_))
        ));
        // Chunk 0-32_0-32_0-32 has one name: other spellings of its numbers name nothing.
        for other in ["+0-+32_0-32_0-32", "00-032_0-32_0-32", "0-32_0-32_0-3%32"] {
            assert!(
                matches!(parse_chunk(&l, 0, other), Err(ViewError::NoSuchDocument(_))),
                "{other}"
            );
        }
    }
}
