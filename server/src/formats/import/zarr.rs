//! Reading OME-Zarr images and plain Zarr arrays, v3 and v2, local or over http (`zarrs`).
//!
//! At the root there is either a group with OME `multiscales` (0.5 in `zarr.json`'s
//! `attributes.ome`, 0.4 in a v2 `.zattrs`), whose first dataset (the finest) is read and whose
//! scale becomes the voxel scale, or an array, read as it is. The last three axes are z, y, x
//! (OME-Zarr's order); any axes before them (t, c) must have size 1. Missing chunks read as the
//! fill value, as Zarr says.

use super::convert::DType;
use super::location::Location;
use super::planes::PlaneSource;
use crate::formats::FormatsError;
use serde_json::Value;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use zarrs::array::codec::ArrayToBytesCodecTraits;
use zarrs::array::{Array, BytesRepresentation, DataType};
use zarrs::array_subset::ArraySubset;
use zarrs::storage::byte_range::ByteRangeIterator;
use zarrs::storage::{
    Bytes, MaybeBytes, MaybeBytesIterator, ReadableStorageTraits, StorageError, StoreKey,
};

type ZarrArray = Array<dyn ReadableStorageTraits>;

/// Most bytes of one metadata document.
const MAX_METADATA_BYTES: u64 = 16 << 20;

/// Most bytes of one object of a Zarr store read over http (a chunk or a shard).
const MAX_OBJECT_BYTES: u64 = 1 << 30;

/// A Zarr store over http(s), read through [`Location::get`]: every object is fetched whole (a
/// byte range is cut from it), within `max_bytes`: [`MAX_METADATA_BYTES`] while the metadata is
/// read, then what one encoded chunk (or shard) of the array can take, so that neither a large
/// answer nor a gzip `Content-Encoding` expands past it.
#[derive(Debug)]
struct HttpStore {
    location: Location,
    max_bytes: AtomicU64,
}

impl HttpStore {
    fn fetch(&self, key: &StoreKey) -> Result<Option<Bytes>, StorageError> {
        self.location
            .get(key.as_str(), self.max_bytes.load(Ordering::Relaxed))
            .map(|found| found.map(Bytes::from))
            .map_err(|e| StorageError::Other(crate::store::error_chain(&e)))
    }
}

impl ReadableStorageTraits for HttpStore {
    fn get(&self, key: &StoreKey) -> Result<MaybeBytes, StorageError> {
        self.fetch(key)
    }

    fn get_partial_many<'a>(
        &'a self,
        key: &StoreKey,
        byte_ranges: ByteRangeIterator<'a>,
    ) -> Result<MaybeBytesIterator<'a>, StorageError> {
        let Some(bytes) = self.fetch(key)? else {
            return Ok(None);
        };
        let size = bytes.len() as u64;
        let parts = byte_ranges.map(move |range| {
            let (start, end) = (range.start(size), range.end(size));
            if start > end || end > size {
                return Err(StorageError::Other(format!(
                    "byte range {range} is outside an object of {size} bytes"
                )));
            }
            Ok(bytes.slice(start as usize..end as usize))
        });
        Ok(Some(Box::new(parts)))
    }

    fn size_key(&self, key: &StoreKey) -> Result<Option<u64>, StorageError> {
        Ok(self.fetch(key)?.map(|b| b.len() as u64))
    }

    fn supports_get_partial(&self) -> bool {
        false
    }
}

/// The finest level of a Zarr image.
pub struct ZarrInput {
    array: ZarrArray,
    /// Where it was found, for messages.
    name: String,
    dims: [u32; 3],
    dtype: DType,
    scale: Option<[f32; 3]>,
    depth: u32,
}

impl std::fmt::Debug for ZarrInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZarrInput")
            .field("name", &self.name)
            .field("dims", &self.dims)
            .field("dtype", &self.dtype)
            .finish_non_exhaustive()
    }
}

/// Whether `location` holds Zarr metadata at its root.
///
/// # Errors
/// The location cannot be read.
pub fn sniff(location: &Location) -> Result<bool, FormatsError> {
    for name in ["zarr.json", ".zgroup", ".zarray"] {
        if location.get(name, MAX_METADATA_BYTES)?.is_some() {
            return Ok(true);
        }
    }
    Ok(false)
}

fn json(location: &Location, name: &str) -> Result<Option<Value>, FormatsError> {
    let Some(bytes) = location.get(name, MAX_METADATA_BYTES)? else {
        return Ok(None);
    };
    serde_json::from_slice(&bytes)
        .map(Some)
        .map_err(|e| FormatsError::input(format!("{} is not JSON: {e}", location.describe(name))))
}

/// The finest dataset's path and its scale (x, y, z) from OME `multiscales`, if any.
fn finest_dataset(
    multiscales: &Value,
    where_: &str,
) -> Result<(String, Option<[f32; 3]>), FormatsError> {
    let ms = multiscales
        .get(0)
        .ok_or_else(|| FormatsError::input(format!("{where_}: multiscales is empty")))?;
    let dataset = ms
        .get("datasets")
        .and_then(|d| d.get(0))
        .ok_or_else(|| FormatsError::input(format!("{where_}: multiscales[0] has no datasets")))?;
    let path = dataset
        .get("path")
        .and_then(Value::as_str)
        .ok_or_else(|| FormatsError::input(format!("{where_}: datasets[0] has no path")))?;
    // The dataset's scale, times the multiscale's own scale when it has one.
    let scale_of = |v: Option<&Value>| -> Option<Vec<f64>> {
        v?.as_array()?
            .iter()
            .find(|t| t.get("type").and_then(Value::as_str) == Some("scale"))?
            .get("scale")?
            .as_array()?
            .iter()
            .map(Value::as_f64)
            .collect()
    };
    let mut scale = scale_of(dataset.get("coordinateTransformations"));
    if let (Some(s), Some(outer)) = (&mut scale, scale_of(ms.get("coordinateTransformations"))) {
        if outer.len() == s.len() {
            s.iter_mut().zip(outer).for_each(|(a, b)| *a *= b);
        }
    }
    let scale = scale.filter(|s| s.len() >= 3).map(|s| {
        let n = s.len();
        [s[n - 1] as f32, s[n - 2] as f32, s[n - 3] as f32]
    });
    let path = super::location::contained(path).map_err(|why| {
        FormatsError::input(format!(
            "{where_}: datasets[0].path {path:?} leads outside the image ({why}); Isovox reads only under the location it is given"
        ))
    })?;
    Ok((
        path.to_string(),
        scale.filter(|s| s.iter().all(|v| v.is_finite() && *v > 0.0)),
    ))
}

fn zarr_error(context: String) -> impl FnOnce(String) -> FormatsError {
    move |detail| FormatsError::Zarr { context, detail }
}

impl ZarrInput {
    /// Opens the image or array at `location`.
    ///
    /// # Errors
    /// No Zarr metadata there, malformed metadata, an unsupported data type, codec or shape.
    pub fn open(location: &Location) -> Result<Self, FormatsError> {
        super::codecs::install();
        // Find the array: an OME group's finest dataset, or the root itself.
        let (path, scale) = if let Some(group) = json(location, "zarr.json")? {
            let where_ = location.describe("zarr.json");
            match group.get("node_type").and_then(Value::as_str) {
                Some("array") => (String::new(), None),
                Some("group") => {
                    let attrs = group.get("attributes");
                    let ms = attrs
                        .and_then(|a| a.get("ome"))
                        .and_then(|o| o.get("multiscales"))
                        .or_else(|| attrs.and_then(|a| a.get("multiscales")))
                        .ok_or_else(|| {
                            FormatsError::input(format!(
                                "{where_}: a group without OME multiscales; name one of its arrays"
                            ))
                        })?;
                    let (p, s) = finest_dataset(ms, &where_)?;
                    (p, s)
                }
                other => {
                    return Err(FormatsError::input(format!(
                        "{where_}: node_type {other:?} is neither array nor group"
                    )))
                }
            }
        } else if json(location, ".zarray")?.is_some() {
            (String::new(), None)
        } else if json(location, ".zgroup")?.is_some() {
            let where_ = location.describe(".zattrs");
            let attrs = json(location, ".zattrs")?.ok_or_else(|| {
                FormatsError::input(format!(
                    "{where_}: missing; a v2 group needs OME multiscales there"
                ))
            })?;
            let ms = attrs.get("multiscales").ok_or_else(|| {
                FormatsError::input(format!(
                    "{where_}: no multiscales; name one of the group's arrays"
                ))
            })?;
            finest_dataset(ms, &where_)?
        } else {
            return Err(FormatsError::input(format!(
                "{}: no zarr.json, .zarray or .zgroup: not a Zarr array or group",
                location.as_str()
            )));
        };
        let name = if path.is_empty() {
            location.as_str()
        } else {
            format!("{}/{path}", location.as_str())
        };
        let mut http = None;
        let store: Arc<dyn ReadableStorageTraits> = match location {
            Location::Local(p) => {
                Arc::new(zarrs::filesystem::FilesystemStore::new(p).map_err(|e| {
                    zarr_error(format!("cannot open {}", p.display()))(e.to_string())
                })?)
            }
            Location::Http { .. } => {
                let store = Arc::new(HttpStore {
                    location: location.clone(),
                    max_bytes: AtomicU64::new(MAX_METADATA_BYTES),
                });
                http = Some(store.clone());
                store
            }
        };
        let array: ZarrArray = Array::open(store, &format!("/{path}")).map_err(|e| {
            zarr_error(format!("cannot open the array {name}"))(crate::store::error_chain(&e))
        })?;
        if let Some(store) = http {
            let encoded = array
                .chunk_array_representation(&vec![0; array.dimensionality()])
                .ok()
                .and_then(|r| array.codecs().encoded_representation(&r).ok());
            let bound = match encoded {
                Some(BytesRepresentation::FixedSize(n) | BytesRepresentation::BoundedSize(n)) => {
                    n.min(MAX_OBJECT_BYTES)
                }
                _ => MAX_OBJECT_BYTES,
            };
            store.max_bytes.store(bound, Ordering::Relaxed);
        }
        let dtype = match array.data_type() {
            DataType::UInt8 => DType::U8,
            DataType::Int8 => DType::I8,
            DataType::UInt16 => DType::U16,
            DataType::Int16 => DType::I16,
            DataType::UInt32 => DType::U32,
            DataType::Int32 => DType::I32,
            DataType::UInt64 => DType::U64,
            DataType::Float32 => DType::F32,
            DataType::Float64 => DType::F64,
            other => {
                return Err(FormatsError::input(format!(
                    "{name}: data type {other} is not supported (uint8, int8, uint16, int16, uint32, int32, uint64, float32, float64 are)"
                )))
            }
        };
        let shape = array.shape().to_vec();
        let n = shape.len();
        if n < 3 {
            return Err(FormatsError::input(format!(
                "{name}: {n} dimensions; a volume needs three (z, y, x)"
            )));
        }
        if let Some(i) = (0..n - 3).find(|&i| shape[i] != 1) {
            return Err(FormatsError::input(format!(
                "{name}: axis {i} has size {} (a time or channel axis); Isovox imports one 3D volume",
                shape[i]
            )));
        }
        let fit = |v: u64| u32::try_from(v).ok().filter(|v| *v > 0);
        let (Some(x), Some(y), Some(z)) = (fit(shape[n - 1]), fit(shape[n - 2]), fit(shape[n - 3]))
        else {
            return Err(FormatsError::input(format!(
                "{name}: shape {shape:?} has an empty axis or one beyond 2^32"
            )));
        };
        let depth = array
            .chunk_shape(&vec![0; n])
            .ok()
            .and_then(|c| u32::try_from(c[n - 3].get()).ok())
            .unwrap_or(1);
        Ok(ZarrInput {
            array,
            name,
            dims: [x, y, z],
            dtype,
            scale,
            depth,
        })
    }
}

impl ZarrInput {
    /// ", chunk KEY" for the first chunk of `subset` that does not decode, to name it in the
    /// error of a read that failed (zarrs's errors do not say which chunk); each is decoded
    /// alone, within its size, so looking costs at most one chunk at a time.
    fn failing_chunk(&self, subset: &ArraySubset) -> String {
        let Ok(Some(chunks)) = self.array.chunks_in_array_subset(subset) else {
            return String::new();
        };
        for indices in &chunks.indices() {
            if self.array.retrieve_chunk(&indices).is_err() {
                return format!(", chunk {}", self.array.chunk_key(&indices).as_str());
            }
        }
        String::new()
    }
}

impl PlaneSource for ZarrInput {
    fn dims(&self) -> [u32; 3] {
        self.dims
    }

    fn dtype(&self) -> DType {
        self.dtype
    }

    fn voxel_scale(&self) -> Option<[f32; 3]> {
        self.scale
    }

    fn depth(&self) -> u32 {
        self.depth
    }

    fn read(&mut self, z0: u32, z1: u32, out: &mut Vec<u8>) -> Result<(), FormatsError> {
        let n = self.array.shape().len();
        let mut ranges = vec![0..1u64; n - 3];
        ranges.push(u64::from(z0)..u64::from(z1));
        ranges.push(0..u64::from(self.dims[1]));
        ranges.push(0..u64::from(self.dims[0]));
        let subset = ArraySubset::new_with_ranges(&ranges);
        let fail = |e: zarrs::array::ArrayError| FormatsError::Zarr {
            context: format!(
                "{}: cannot read planes {z0}..{z1}{}",
                self.name,
                self.failing_chunk(&subset)
            ),
            detail: crate::store::error_chain(&e),
        };
        macro_rules! elements {
            ($t:ty) => {{
                let v = self
                    .array
                    .retrieve_array_subset_elements::<$t>(&subset)
                    .map_err(fail)?;
                out.clear();
                out.extend(v.iter().flat_map(|x| x.to_le_bytes()));
            }};
        }
        match self.dtype {
            DType::U8 => elements!(u8),
            DType::I8 => elements!(i8),
            DType::U16 => elements!(u16),
            DType::I16 => elements!(i16),
            DType::U32 => elements!(u32),
            DType::I32 => elements!(i32),
            DType::U64 => elements!(u64),
            DType::F32 => elements!(f32),
            DType::F64 => elements!(f64),
        }
        Ok(())
    }
}
