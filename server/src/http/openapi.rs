//! `GET /openapi.json`: the API described in OpenAPI 3.1, written by hand next to the routes it
//! describes (`mod.rs`).
//!
//! The document states what the server accepts, no more and no less, so that a client generated
//! from it never sends what the server refuses: every bound, enum, pattern and required field
//! here is one the handlers check, objects whose unknown fields the server refuses say
//! `additionalProperties: false`, and the term limits come from the server's configuration.
//! `server/tests/it/api_document.rs` (and `scripts/fuzz-api.sh`, longer) hold the two together
//! with Schemathesis: schema-valid requests accepted, schema-invalid ones refused.
//!
//! What no schema can state is said in descriptions and answered with the status a client
//! expects for a resource or a state: a volume, version, brick or region that is not there is
//! 404; a `since` past the head 409; versions compacted away 410; limits of the volume's voxel
//! type (an `iso` or `k` beyond its H) 400 or 422.

use super::AppState;
use crate::icvg::ops::BinaryOp;
use crate::icvg::term::TermLimits;
use axum::extract::State;
use axum::response::{IntoResponse, Response};
use axum::Json;
use isovox_proto::batch::MAX_BATCH;
use isovox_proto::icvg::MAX_COORDINATE;
use isovox_proto::VoxelType;
use serde_json::{json, Value};

fn problem_responses(codes: &[&str]) -> Value {
    let mut m = serde_json::Map::new();
    for c in codes {
        m.insert(
            (*c).to_string(),
            json!({"description": "problem details (RFC 9457)", "content": {"application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}}}),
        );
    }
    Value::Object(m)
}

fn merge(mut a: Value, b: Value) -> Value {
    if let (Some(a), Value::Object(b)) = (a.as_object_mut(), b) {
        a.extend(b);
    }
    a
}

fn path_param(name: &str, schema: Value, description: &str) -> Value {
    json!({"name": name, "in": "path", "required": true, "schema": schema, "description": description})
}

fn query_param(name: &str, schema: Value, description: &str) -> Value {
    json!({"name": name, "in": "query", "required": false, "schema": schema, "description": description})
}

/// An integer in `min..=max`.
fn int(min: i64, max: u64) -> Value {
    json!({"type": "integer", "minimum": min, "maximum": max})
}

/// An array of exactly `n` items of `item`.
fn tuple(n: usize, item: Value) -> Value {
    json!({"type": "array", "items": item, "minItems": n, "maxItems": n})
}

/// An object with exactly these properties, `required` among them; others are refused.
fn closed(required: &[&str], properties: Value) -> Value {
    json!({"type": "object", "required": required, "additionalProperties": false, "properties": properties})
}

/// A reference to a schema of `components`.
fn schema_ref(name: &str) -> Value {
    json!({"$ref": format!("#/components/schemas/{name}")})
}

/// A volume's name, as the catalog names files (`catalog.rs`).
fn volume_name() -> Value {
    json!({"type": "string", "pattern": "^[A-Za-z0-9_.-]{1,128}$"})
}

/// A content hash, 16 lower-case hex digits.
fn content_hash() -> Value {
    json!({"type": "string", "pattern": "^[0-9a-f]{16}$"})
}

/// A version number (any u64).
/// Optional fields may be null, as absent (what a client with None or null for "not given"
/// sends).
fn nullable(schema: Value) -> Value {
    json!({"anyOf": [schema, {"type": "null"}]})
}

fn version_number() -> Value {
    int(0, u64::MAX)
}

/// A tag's name (`volume/history.rs`, `valid_tag`).
fn tag_name() -> Value {
    json!({"type": "string", "pattern": format!("^(?![0-9]+$)[A-Za-z0-9._-]{{1,{}}}$", isovox_proto::history::MAX_TAG_LEN)})
}

/// The field's formats (`views.rs`, `docs/formats.md`): each view, live and pinned.
fn view_paths(name: Value) -> Value {
    let version = path_param(
        "version",
        int(1, u64::MAX),
        "the version this form is pinned to",
    );
    let mut paths = serde_json::Map::new();
    for (segment, what, path_doc) in [
        ("zarr", "the OME-Zarr 0.5 (Zarr v3) view", "zarr.json, {level}/zarr.json or {level}/c/{z}/{y}/{x} (a chunk of zeros is 404: the fill value)"),
        ("precomputed", "the Neuroglancer precomputed view", "info or {level}/{x0}-{x1}_{y0}-{y1}_{z0}-{z1} (400 when the range is not a chunk's); a channel's source under {channel}/, with {channel}/segment_properties/info"),
    ] {
        let path = path_param("path", json!({"type": "string"}), path_doc);
        let content = json!({"application/json": {"schema": {"type": "object"}},
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}});
        paths.insert(format!("/v1/volumes/{{name}}/{segment}/{{path}}"), json!({"get": {
            "summary": format!("{what} of the newest version (Cache-Control: public, max-age=1; a strong ETag; Content-Location names the pinned form)"),
            "parameters": [name.clone(), path],
            "responses": merge(json!({"200": {"description": "a metadata document or a chunk", "content": content.clone()},
                "304": {"description": "not modified (If-None-Match)"}}), problem_responses(&["400", "404", "500"]))}}));
        let path = path_param("path", json!({"type": "string"}), path_doc);
        paths.insert(format!("/v1/volumes/{{name}}/versions/{{version}}/{segment}/{{path}}"), json!({"get": {
            "summary": format!("{what} of one version, immutable (Cache-Control: public, max-age=31536000, immutable)"),
            "parameters": [name.clone(), version.clone(), path],
            "responses": merge(json!({"200": {"description": "a metadata document or a chunk", "content": content},
                "304": {"description": "not modified (If-None-Match)"}}), problem_responses(&["400", "404", "410", "500"]))}}));
    }
    Value::Object(paths)
}

/// The document, for a server whose edit terms are bounded by `limits`.
pub(super) fn document(limits: &TermLimits) -> Value {
    let name = path_param("name", volume_name(), "volume name");
    let level = path_param("level", int(0, u8::MAX.into()), "level of detail");
    let coord = |c: &str| {
        path_param(
            c,
            int(0, u32::MAX.into()),
            "brick coordinate at the level (404 beyond its grid)",
        )
    };
    let version = query_param(
        "version",
        json!({"anyOf": [version_number(), tag_name()]}),
        "read this older version, by number or tag (404 when the file does not hold it)",
    );
    let channel = query_param(
        "channel",
        json!({"type": "string", "pattern": "^[A-Za-z0-9_]{1,32}$"}),
        "read this attribute channel (the volume metadata lists them) instead of density; 404 when the volume has none of that name",
    );
    let mesh_channel = query_param(
        "channel",
        json!({"type": "string", "pattern": "^[A-Za-z0-9_]{1,32}$"}),
        "per-vertex materials from this u8 attribute channel (docs/channels.md, docs/mesh-encoding.md): the same mesh, plus each vertex's two materials and their weight (compact: flags bit 1 and a material section; glb: the attributes _MATERIAL and _MATERIAL_WEIGHT); density or absent: the mesh alone, as without it; 404 when the volume has no channel of that name, 422 when it is not u8",
    );
    let brick_params = json!([
        name,
        level,
        coord("x"),
        coord("y"),
        coord("z"),
        version,
        channel
    ]);
    let binary = |media: &str| json!({media: {"schema": {"type": "string", "format": "binary"}}});
    let mut doc = json!({
        "openapi": "3.1.0",
        "info": {"title": "Isovox", "version": env!("CARGO_PKG_VERSION"),
                 "description": "Large, editable volumes as brick octrees: bricks, levels and marching-cubes tiles by random access."},
        "paths": {
            "/healthz": {"get": {"summary": "liveness", "responses": {"200": {"description": "ok", "content": {"text/plain": {"schema": {"type": "string"}}}}}}},
            "/metrics": {"get": {"summary": "Prometheus metrics", "responses": {"200": {"description": "text format 0.0.4", "content": {"text/plain": {"schema": {"type": "string"}}}}}}},
            "/openapi.json": {"get": {"summary": "this document", "responses": {"200": {"description": "OpenAPI 3.1", "content": {"application/json": {"schema": {"type": "object"}}}}}}},
            "/v1/auth": {"get": {"summary": "who the bearer is and how a page signs in (open to all)",
                "responses": merge(json!({"200": {"description": "user (null without a bearer), write, admin, private_reads, oidc (issuer and client_id, or null)", "content": {"application/json": {"schema": {"type": "object"}}}}}), problem_responses(&["401"]))}},
            "/v1/volumes": {"get": {"summary": "list volumes", "responses": {"200": {"description": "volumes", "content": {"application/json": {"schema": schema_ref("VolumeList")}}}}}},
            "/v1/volumes/{name}": {"get": {"summary": "volume metadata", "parameters": [name],
                "responses": merge(json!({"200": {"description": "metadata", "content": {"application/json": {"schema": schema_ref("VolumeInfo")}}}}), problem_responses(&["400", "404"]))}},
            "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}": {"get": {
                "summary": "one brick: raw voxels (x fastest, u16 little endian); the stored zstd frame with Accept-Encoding: zstd; an lz4 block with Accept: application/x-lz4",
                "parameters": brick_params,
                "responses": merge(json!({
                    "200": {"description": "the brick; ETag is its content hash", "content": merge(binary("application/octet-stream"), binary("application/x-lz4"))},
                    "304": {"description": "not modified (If-None-Match)"}}), problem_responses(&["400", "404", "500"]))}},
            "/v1/volumes/{name}/blobs/{hash}": {"get": {
                "summary": "a brick by content hash, immutable (Cache-Control: public, max-age=31536000, immutable)",
                "parameters": [name, path_param("hash", content_hash(), "content hash, 16 hex digits"), channel],
                "responses": merge(json!({
                    "200": {"description": "the brick", "content": merge(binary("application/octet-stream"), binary("application/x-lz4"))},
                    "304": {"description": "not modified"}}), problem_responses(&["400", "404", "500"]))}},
            "/v1/volumes/{name}/batch": {"post": {
                "summary": "many bricks in one response (application/x-isovox-bricks, see proto/src/batch.rs)",
                "description": "Raw answers carry at most 64 MiB of voxels: 2,048 bricks of 32^3 u8 voxels, 1,024 of u16 (413 beyond); stored answers take up to 4,096 bricks of any size.",
                "parameters": [name, channel],
                "requestBody": {"required": true, "content": {"application/json": {"schema": schema_ref("BatchRequest")}}},
                "responses": merge(json!({"200": {"description": "the bricks", "content": binary("application/x-isovox-bricks")}}), problem_responses(&["400", "404", "413", "415", "500", "503"]))}},
            "/v1/volumes/{name}/levels/{level}": {"get": {
                "summary": "a level's brick grid (JSON), or its voxels as one RAW array (format=voxels); a strong ETag, Cache-Control: no-cache (public, max-age=31536000, immutable with ?version=N)",
                "parameters": [name, level, version, channel,
                    query_param("region", json!({"type": "string", "pattern": "^[0-9]{1,10}(,[0-9]{1,10}){5}$"}),
                        "MINX,MINY,MINZ,MAXX,MAXY,MAXZ, max exclusive: in bricks for the grid, in voxels for format=voxels. An axis with MAX <= MIN selects nothing (an empty answer); a coordinate beyond the level is 404"),
                    query_param("format", json!({"type": "string", "enum": ["grid", "voxels"]}), "grid (default) or voxels (at most 64 MiB: 413 beyond)")],
                "responses": merge(json!({"200": {"description": "the grid or the voxels", "content": merge(json!({"application/json": {"schema": schema_ref("LevelGrid")}}), binary("application/octet-stream"))},
                    "304": {"description": "not modified (If-None-Match)"}}),
                    problem_responses(&["400", "404", "413", "500", "503"]))}},
            "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}": {"get": {
                "summary": "the marching-cubes mesh of one tile, in world coordinates, with its moves (secondary positions) for the faces that touch a tile one level coarser (docs/mesh-encoding.md, docs/lod-meshes.md); a strong ETag, Cache-Control: no-cache (public, max-age=31536000, immutable with ?version=N)",
                "parameters": [name, level, coord("x"), coord("y"), coord("z"), version,
                    query_param("iso", json!({"type": "number", "minimum": 0, "maximum": u16::MAX}),
                        "iso value, default S - 0.5; within the volume's [L, H] (0..255 for u8 voxels, 0..65535 for u16: 400 beyond)"),
                    query_param("format", json!({"type": "string", "enum": ["compact", "glb"]}), "compact (default: format version 3, the regular mesh and its moves, docs/mesh-encoding.md) or glb (the regular mesh as a plain glTF primitive, the moves in a buffer view named by the mesh's extras)"),
                    mesh_channel.clone()],
                "responses": merge(json!({
                    "200": {"description": "the tile: its regular mesh and moves", "content": merge(binary("application/x-isovox-mesh"), binary("model/gltf-binary"))},
                    "304": {"description": "not modified"}}), problem_responses(&["400", "404", "422", "500", "503"]))}},
            "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}/strips/{face}": {"get": {
                "summary": "the transition strip of one face of a mesh tile: a plain mesh, in world coordinates at its drawn positions, drawn with the tile (its moves of that face applied) where that face touches a tile one level coarser (docs/lod-meshes.md); empty for a face that can never touch one (the volume's boundary, the coarsest level); a strong ETag, Cache-Control as the tile's",
                "parameters": [name, level, coord("x"), coord("y"), coord("z"),
                    json!({"name": "face", "in": "path", "required": true, "schema": {"type": "string", "enum": ["-x", "+x", "-y", "+y", "-z", "+z"]}, "description": "the face: -x, +x, -y, +y, -z or +z (400 for anything else)"}),
                    version,
                    query_param("iso", json!({"type": "number", "minimum": 0, "maximum": u16::MAX}),
                        "iso value, as for the tile"),
                    query_param("format", json!({"type": "string", "enum": ["compact", "glb"]}), "compact (default: format version 1, a plain mesh) or glb (a plain glTF mesh)"),
                    mesh_channel],
                "responses": merge(json!({
                    "200": {"description": "the strip", "content": merge(binary("application/x-isovox-mesh"), binary("model/gltf-binary"))},
                    "304": {"description": "not modified"}}), problem_responses(&["400", "404", "422", "500", "503"]))}},
        },
        "components": {"securitySchemes": {"bearer": {"type": "http", "scheme": "bearer"}}, "schemas": {
            "Problem": {"type": "object", "required": ["type", "title", "status", "detail"],
                "properties": {"type": {"type": "string"}, "title": {"type": "string"}, "status": {"type": "integer"}, "detail": {"type": "string"},
                    "version": {"type": "integer", "description": "the current version, on a 409 from If-Match (absent on a 409 from a read-only volume)"}}},
            "LevelInfo": {"type": "object", "required": ["level", "grid", "dims"],
                "properties": {"level": {"type": "integer"}, "grid": schema_ref("Triple"), "dims": schema_ref("Triple")}},
            "Triple": tuple(3, json!({"type": "integer", "minimum": 0})),
            "VolumeInfo": {"type": "object",
                "required": ["name", "dims", "voxel_type", "low", "high", "surface", "brick", "levels", "voxel_scale", "version"],
                "properties": {"name": {"type": "string"}, "dims": schema_ref("Triple"),
                    "voxel_type": {"type": "string", "enum": ["u8", "u16"]}, "low": {"type": "integer"}, "high": {"type": "integer"},
                    "surface": {"type": "integer"}, "brick": {"type": "integer"},
                    "levels": {"type": "array", "items": schema_ref("LevelInfo")},
                    "voxel_scale": tuple(3, json!({"type": "number"})),
                    "version": {"type": "integer"},
                    "channels": {"type": "array", "items": schema_ref("ChannelInfo")}}},
            "ChannelInfo": {"type": "object", "required": ["name", "type"],
                "description": "an attribute channel beside density (docs/channels.md): categorical values per voxel, levels by mode",
                "properties": {"name": {"type": "string"}, "type": {"type": "string", "enum": ["u8", "u16"]},
                    "palette": {"type": "array", "items": {"type": "string", "pattern": "^#[0-9A-Fa-f]{6}$"}},
                    "sparse": {"type": "boolean"}}},
            "VolumeList": {"type": "object", "required": ["volumes"], "properties": {"volumes": {"type": "array", "items": schema_ref("VolumeInfo")}}},
            "LevelGrid": {"type": "object", "required": ["level", "grid", "min", "max", "version", "bricks"],
                "properties": {"level": {"type": "integer"}, "grid": schema_ref("Triple"),
                    "min": schema_ref("Triple"), "max": schema_ref("Triple"), "version": {"type": "integer"},
                    "bricks": {"type": "array", "items": {"type": "object", "required": ["hash", "min", "max"],
                        "properties": {"hash": {"type": "string"}, "min": {"type": "integer"}, "max": {"type": "integer"}}}}}},
            "BatchRequest": closed(&["keys"], json!({
                "keys": {"type": "array", "maxItems": MAX_BATCH,
                    "items": {"type": "array", "minItems": 4, "maxItems": 4, "items": false, "prefixItems": [
                        int(0, u8::MAX.into()), int(0, u32::MAX.into()), int(0, u32::MAX.into()), int(0, u32::MAX.into())]}},
                "version": {"type": ["integer", "null"], "minimum": 0, "maximum": u64::MAX},
                "encoding": {"type": "string", "enum": ["raw", "stored"]}})),
        }}
    });
    let (paths, schemas) = write_side(name.clone(), limits);
    let (segment_paths, segment_schemas) = segments(name.clone(), version.clone());
    if let Some(p) = doc["paths"].as_object_mut() {
        p.extend(paths.as_object().cloned().unwrap_or_default());
        p.extend(segment_paths.as_object().cloned().unwrap_or_default());
        p.extend(view_paths(name).as_object().cloned().unwrap_or_default());
    }
    if let Some(s) = doc["components"]["schemas"].as_object_mut() {
        s.extend(schemas.as_object().cloned().unwrap_or_default());
        s.extend(segment_schemas.as_object().cloned().unwrap_or_default());
    }
    doc
}

/// The segments of categorical channels (`docs/channels.md`, "Segments"): their list and one
/// segment's mesh.
fn segments(name: Value, version: Value) -> (Value, Value) {
    use crate::volume::segments::{MAX_MESH_VOXELS, MAX_SCAN_VOXELS, MAX_SEGMENTS};
    let channel = path_param(
        "channel",
        json!({"type": "string", "pattern": "^[A-Za-z0-9_]{1,32}$", "not": {"const": "density"}}),
        "an attribute channel of the volume (404 naming the channels it has when it has none of that name); density is not categorical (422)",
    );
    let version = merge(
        version,
        json!({"description": format!("list this older version, by number or tag (404 when the file does not hold it): the segments are kept for the newest version, so an older one is a scan, for volumes of at most {MAX_SCAN_VOXELS} voxels (409 beyond)")}),
    );
    let binary = |media: &str| json!({media: {"schema": {"type": "string", "format": "binary"}}});
    let paths = json!({
        "/v1/volumes/{name}/channels/{channel}/segments": {"get": {
            "summary": "a categorical channel's non-zero values (segmentation ids, materials in use), ascending, each with its level-0 voxel count and bounding box; kept per commit, not scanned per request (the first request for a channel builds its index)",
            "parameters": [name, channel, version,
                query_param("after", version_number(), "list the ids after this one (the previous page's next)"),
                query_param("limit", int(1, MAX_SEGMENTS as u64), "segments per page, default 1000")],
            "responses": merge(json!({"200": {"description": "one page of segments, with the version it describes", "content": {"application/json": {"schema": schema_ref("SegmentList")}}}}),
                problem_responses(&["400", "404", "409", "422", "500", "503"]))}},
        "/v1/volumes/{name}/channels/{channel}/segments/{id}/mesh": {"get": {
            "summary": "the closed mesh of the voxels of a channel whose value is id, at a level of the channel's mode pyramid: marching cubes on the indicator (1 where the value is id, iso 0.5) over the segment's box padded by a voxel of zeros, in world coordinates (level-0 voxel units times the voxel scale); Isovox-Version names the version meshed",
            "parameters": [name, channel,
                path_param("id", int(0, u64::MAX), "the segment's id (404 when the channel holds no voxel of it, 0 or a value beyond its type included)"),
                version,
                query_param("level", int(0, u8::MAX.into()), "the level marched, default 0 (404 beyond the channel's pyramid)"),
                query_param("format", json!({"type": "string", "enum": ["compact", "glb"]}), "compact (default: format version 1, a plain mesh, docs/mesh-encoding.md) or glb (a plain glTF mesh)")],
            "responses": merge(json!({"200": {"description": format!("the mesh; 413 when the segment's box holds more than {MAX_MESH_VOXELS} voxels at that level (the detail names a level that fits)"),
                    "headers": {"Isovox-Version": {"description": "the version meshed", "schema": {"type": "integer"}}},
                    "content": merge(binary("application/x-isovox-mesh"), binary("model/gltf-binary"))}}),
                problem_responses(&["400", "404", "409", "413", "422", "500", "503"]))}},
    });
    let triple = schema_ref("Triple");
    let schemas = json!({
        "SegmentList": {"type": "object", "required": ["version", "channel", "total", "segments"],
            "properties": {"version": {"type": "integer"}, "channel": {"type": "string"},
                "total": {"type": "integer", "description": "segments at that version, on every page"},
                "next": {"type": "integer", "description": "when more follow: the after of the next page; absent on the last page"},
                "segments": {"type": "array", "items": {"type": "object", "required": ["id", "voxels", "box"],
                    "properties": {"id": {"type": "integer", "minimum": 1}, "voxels": {"type": "integer", "minimum": 1},
                        "box": {"type": "array", "items": triple, "minItems": 2, "maxItems": 2,
                            "description": "[[x0, y0, z0], [x1, y1, z1]], level-0 voxels, max exclusive"}}}}}},
    });
    (paths, schemas)
}

/// The write side (`docs/editing.md`): edits, compaction, the change feed and its catch-up.
fn write_side(name: Value, limits: &TermLimits) -> (Value, Value) {
    let json_body = |schema: &str| json!({"application/json": {"schema": schema_ref(schema)}});
    let bearer = json!([{"bearer": []}]);
    let since = query_param(
        "since",
        version_number(),
        "list the versions after this one (409 when it is after the head, 410 when compacted away)",
    );
    let paths = json!({
        "/v1/volumes/{name}/edits": {"post": {
            "summary": "apply an ICVG edit (docs/icvg.md) as the next version; durable before the answer",
            "security": bearer,
            "parameters": [name, {"name": "If-Match", "in": "header", "required": false,
                "schema": {"type": "string", "pattern": "^(\\*|[0-9]{1,20}|(W/)?\"[0-9]{1,20}\")$"},
                "description": "apply only at this version (N, \"N\" or W/\"N\"; 409 otherwise), or * for whatever version is current"}],
            "requestBody": {"required": true, "content": json_body("EditRequest")},
            "responses": merge(json!({"200": {"description": "the new version and the changed bricks", "content": json_body("EditResponse")}}),
                problem_responses(&["400", "401", "403", "404", "409", "413", "415", "422", "429", "500", "503"]))}},
        "/v1/volumes/{name}/compact": {"post": {
            "summary": "rewrite the volume's file with only the head version",
            "security": bearer,
            "parameters": [name],
            "responses": merge(json!({"200": {"description": "what compaction did", "content": json_body("CompactResponse")}}),
                problem_responses(&["400", "401", "403", "404", "409", "500", "503"]))}},
        "/v1/meshes": {"post": {
            "summary": "keep a watertight model (the file's bytes) by its content hash, for mesh leaves of edit terms",
            "description": "422 when the bytes are not a model of the given format, or the model is not watertight (the schema cannot say what a valid model is).",
            "security": bearer,
            "parameters": [{"name": "format", "in": "query", "required": true,
                "schema": {"type": "string", "enum": crate::voxelize::store::FORMATS}, "description": "the model's file format"}],
            "requestBody": {"required": true, "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}},
            "responses": merge(json!({"200": {"description": "the stored mesh", "content": json_body("MeshInfo")}}),
                problem_responses(&["400", "401", "403", "404", "413", "422", "500"]))}},
        "/v1/volumes/{name}/changes": {"get": {
            "summary": "the versions after `since`, oldest first, with their changed bricks per level",
            "parameters": [name, since.clone(), query_param("limit", int(1, crate::volume::MAX_CHANGES as u64), "most versions listed (default 1000)")],
            "responses": merge(json!({"200": {"description": "the versions", "content": json_body("ChangeList")}}),
                problem_responses(&["400", "404", "409", "410", "500"]))}},
        "/v1/volumes/{name}/events": {"get": {
            "summary": "change feed, server-sent events: hello, then one commit event per version (resync when too far behind)",
            "parameters": [name, since, {"name": "Last-Event-ID", "in": "header", "required": false,
                "schema": {"type": "string", "pattern": "^[0-9]{0,20}$"},
                "description": "resume after this version (empty: no event seen yet)"}],
            "responses": merge(json!({"200": {"description": "an event stream; each event as its fields (data: JSON text)", "content": {"text/event-stream": {"schema": {
                "type": "object", "required": ["data"],
                "properties": {"event": {"type": "string", "enum": ["hello", "commit", "resync", "presence"]}, "data": {"type": "string"}, "id": {"type": "string"}}}}}}}),
                problem_responses(&["400", "404", "409", "410"]))}},
        "/v1/volumes/{name}/history": {"get": {
            "summary": "commits newest first: version, time, author, message, kind, operation and box, bricks changed",
            "parameters": [name, query_param("before", version_number(), "list the commits before this version"),
                query_param("limit", int(1, crate::volume::history::MAX_HISTORY as u64), "most commits listed (default 100)")],
            "responses": merge(json!({"200": {"description": "the commits", "content": json_body("HistoryList")}}),
                problem_responses(&["400", "404", "500"]))}},
        "/v1/volumes/{name}/tags": {"get": {
            "summary": "every tag and the version it names",
            "parameters": [name],
            "responses": merge(json!({"200": {"description": "the tags", "content": json_body("TagList")}}),
                problem_responses(&["400", "404", "500"]))}},
        "/v1/volumes/{name}/tags/{tag}": {"put": {
            "summary": "name a version (a commit that changes no brick); setting a tag again moves it",
            "security": bearer,
            "parameters": [name, path_param("tag", tag_name(), "the tag")],
            "requestBody": {"required": true, "content": json_body("TagRequest")},
            "responses": merge(json!({"200": {"description": "the tag's commit", "content": json_body("EditResponse")}}),
                problem_responses(&["400", "401", "403", "404", "409", "413", "415", "429", "500", "503"]))}},
        "/v1/volumes/{name}/undo": {"post": {
            "summary": "take back the edit of a version (or make an undone one again), later edits over it applied again",
            "security": bearer,
            "parameters": [name],
            "requestBody": {"required": true, "content": json_body("UndoRequest")},
            "responses": merge(json!({"200": {"description": "the new version", "content": json_body("EditResponse")}}),
                problem_responses(&["400", "401", "403", "404", "409", "410", "413", "415", "422", "429", "500", "503"]))}},
        "/v1/volumes/{name}/revert": {"post": {
            "summary": "a new version whose content is an earlier version's",
            "security": bearer,
            "parameters": [name],
            "requestBody": {"required": true, "content": json_body("RevertRequest")},
            "responses": merge(json!({"200": {"description": "the new version", "content": json_body("EditResponse")}}),
                problem_responses(&["400", "401", "403", "404", "409", "410", "413", "415", "429", "500", "503"]))}},
        "/v1/volumes/{name}/presence": {
            "post": {
                "summary": "where the user is (read role enough; a few a second at most): sent to the change feed's subscribers, never stored",
                "security": bearer,
                "parameters": [name],
                "requestBody": {"required": true, "content": json_body("PresenceRequest")},
                "responses": merge(json!({"204": {"description": "announced"}}),
                    problem_responses(&["400", "401", "403", "404", "413", "415", "429"]))},
            "get": {
                "summary": "who is present now",
                "parameters": [name],
                "responses": merge(json!({"200": {"description": "the users present", "content": json_body("PresenceList")}}),
                    problem_responses(&["400", "404"]))}},
    });
    let changed =
        json!({"type": "array", "items": {"type": "array", "items": schema_ref("Triple")}});
    let bound = crate::volume::presence::MAX_COORDINATE;
    let coordinate = json!({"type": "number", "minimum": -bound, "maximum": bound});
    let brick_now = json!({"type": "object", "required": ["hash", "min", "max"],
        "properties": {"hash": {"type": "string"}, "min": {"type": "integer"}, "max": {"type": "integer"}}});
    let event = json!({"type": "object", "required": ["version", "timestamp_ms", "changed"],
        "properties": {"version": {"type": "integer"}, "timestamp_ms": {"type": "integer"}, "changed": changed,
            "bricks": {"type": "array", "description": "what each brick of changed holds now, in its order (absent past 4096 changed bricks)",
                "items": {"type": "array", "items": brick_now}}}});
    let mut schemas = json!({
        "EditResponse": {"type": "object", "required": ["version", "previous", "changed", "evaluated", "new_records", "checkpoint", "elapsed_us", "committed"],
            "properties": {"version": {"type": "integer"}, "previous": {"type": "integer"}, "changed": changed,
                "evaluated": {"type": "integer"}, "new_records": {"type": "integer"}, "checkpoint": {"type": "boolean"}, "elapsed_us": {"type": "integer"},
                "committed": {"type": "boolean", "description": "false for an edit that reaches no voxel of the volume: nothing committed, version is the current one"},
                "voxels_changed": {"type": "integer", "description": "for an edit: level-0 voxels whose density it changed (or would, in a dry run)"},
                "channels": {"type": "object", "description": "changed bricks of attribute channels, by channel, per level", "additionalProperties": changed}}},
        "ChangeEvent": event,
        "HistoryList": {"type": "object", "required": ["head", "oldest", "commits", "more"],
            "properties": {"head": {"type": "integer"}, "oldest": {"type": "integer"}, "more": {"type": "boolean"},
                "commits": {"type": "array", "items": {"type": "object", "required": ["version", "timestamp_ms", "bricks_changed"]}}}},
        "TagList": {"type": "object", "required": ["tags"],
            "properties": {"tags": {"type": "array", "items": {"type": "object", "required": ["tag", "version", "set_at"]}}}},
        "TagRequest": closed(&["version"], json!({"version": version_number()})),
        "UndoRequest": closed(&["version"], json!({"version": version_number(),
            "message": {"type": "string", "maxLength": isovox_proto::history::MAX_MESSAGE_CHARS}})),
        "RevertRequest": closed(&["to"], json!({"to": version_number(),
            "message": {"type": "string", "maxLength": isovox_proto::history::MAX_MESSAGE_CHARS}})),
        "PresenceRequest": closed(&["position"], json!({"position": tuple(3, coordinate.clone()),
            "looking": nullable(tuple(3, coordinate)),
            "label": nullable(json!({"type": "string", "maxLength": crate::volume::presence::MAX_LABEL_CHARS}))})),
        "PresenceList": {"type": "object", "required": ["present"],
            "properties": {"present": {"type": "array", "items": {"type": "object", "required": ["user", "position", "at_ms"]}}}},
        "MeshInfo": {"type": "object", "required": ["hash", "triangles", "vertices", "min", "max"],
            "properties": {"hash": {"type": "string"}, "triangles": {"type": "integer"}, "vertices": {"type": "integer"},
                "min": tuple(3, json!({"type": "number"})), "max": tuple(3, json!({"type": "number"}))}},
        "ChangeList": {"type": "object", "required": ["since", "head", "oldest", "more", "changes"],
            "properties": {"since": {"type": "integer"}, "head": {"type": "integer"}, "oldest": {"type": "integer"}, "more": {"type": "boolean"},
                "changes": {"type": "array", "items": schema_ref("ChangeEvent")}}},
        "CompactResponse": {"type": "object", "required": ["version", "bytes_before", "bytes_after", "bricks", "elapsed_us"],
            "properties": {"version": {"type": "integer"}, "bytes_before": {"type": "integer"}, "bytes_after": {"type": "integer"},
                "bricks": {"type": "integer"}, "elapsed_us": {"type": "integer"}}},
    });
    if let Some(s) = schemas.as_object_mut() {
        s.extend(
            term_schemas(limits)
                .as_object()
                .cloned()
                .unwrap_or_default(),
        );
    }
    (paths, schemas)
}

/// The edit request and the ICVG term grammar (`proto/src/icvg.rs`, `docs/icvg.md`), with the
/// bounds `icvg/compile.rs` checks.
fn term_schemas(limits: &TermLimits) -> Value {
    let extent = limits.max_extent as u64;
    // A radius r spans 2r + 1 voxels.
    let radius = int(1, (extent - 1) / 2);
    let point = tuple(3, int(-MAX_COORDINATE, MAX_COORDINATE as u64));
    let s_l = json!({"type": "number", "exclusiveMinimum": 0, "maximum": 1});
    let k = int(-i64::from(u16::MAX), u16::MAX.into());
    let term = schema_ref("Term");
    let two_terms = tuple(2, term.clone());
    let mut leaves = vec![
        (
            "cuboid",
            closed(
                &["origin", "size"],
                json!({"origin": point, "size": tuple(3, int(3, extent))}),
            ),
        ),
        (
            "ellipsoid",
            closed(
                &["center", "radii"],
                json!({"center": point, "radii": tuple(3, radius.clone())}),
            ),
        ),
        (
            "torus",
            closed(
                &["center", "major", "minor"],
                json!({"center": point,
            "major": int(1, crate::icvg::compile::max_torus_radius(limits).into()),
            "minor": int(1, crate::icvg::compile::max_torus_radius(limits).into())}),
            ),
        ),
        (
            "capsule",
            closed(
                &["center", "radius", "length"],
                json!({"center": point,
            "radius": int(1, crate::icvg::compile::max_capsule_radius(limits).into()),
            "length": int(0, crate::icvg::compile::max_capsule_length(limits).into())}),
            ),
        ),
        (
            "volume",
            closed(
                &["name", "origin"],
                json!({"name": volume_name(), "origin": point,
            "region": {"anyOf": [schema_ref("Region"), {"type": "null"}]}}),
            ),
        ),
        (
            "mesh",
            closed(
                &["hash", "offset", "scale"],
                json!({"hash": content_hash(),
            "offset": tuple(3, json!({"type": "number"})), "scale": {"type": "number", "exclusiveMinimum": 0}}),
            ),
        ),
        (
            "divide",
            closed(&["s_l", "args"], json!({"s_l": s_l, "args": two_terms})),
        ),
        (
            "add_scalar",
            closed(&["k", "arg"], json!({"k": k, "arg": term})),
        ),
        ("inverse", term.clone()),
        ("complement", term.clone()),
    ];
    for axial in ["cylinder", "cone"] {
        leaves.push((
            axial,
            closed(
                &["base", "radii", "height"],
                json!({"base": point, "radii": tuple(2, radius.clone()), "height": int(3, extent)}),
            ),
        ));
    }
    for slanted in ["prism", "pyramid"] {
        leaves.push((
            slanted,
            closed(
                &["origin", "size"],
                json!({"origin": point, "size": tuple(3, int(4, extent))}),
            ),
        ));
    }
    for morph in ["dilate", "erode"] {
        leaves.push((
            morph,
            closed(
                &["radius", "arg"],
                json!({"radius": radius.clone(), "arg": term}),
            ),
        ));
    }
    let binary_ops = BinaryOp::WITHOUT_ARGUMENTS.map(BinaryOp::name);
    for op in binary_ops {
        leaves.push((op, two_terms.clone()));
    }
    // A leaf's object may carry attribute values (docs/channels.md).
    let attribute = int(0, crate::icvg::edit::largest_attribute(VoxelType::U64));
    for (key, schema) in &mut leaves {
        if isovox_proto::icvg::LEAVES.contains(key) {
            if let Some(props) = schema.get_mut("properties").and_then(Value::as_object_mut) {
                props.insert("material".into(), attribute.clone());
                props.insert("label".into(), attribute.clone());
            }
        }
    }
    let term_kinds: Vec<Value> = leaves
        .into_iter()
        .map(|(key, schema)| closed(&[key], json!({key: schema})))
        .collect();
    let region = closed(&["min", "max"], json!({"min": point, "max": point}));
    // A field an operator does not take may only be null or absent.
    let absent = json!({"type": "null"});
    let edit = |op: Value, required: &[&str], term: &Value, s_l: &Value, k: &Value| {
        closed(
            required,
            json!({"op": op, "term": term, "s_l": s_l, "k": k, "region": nullable(schema_ref("Region")),
                "message": nullable(json!({"type": "string", "maxLength": isovox_proto::history::MAX_MESSAGE_CHARS})),
                "channel": absent, "overwrite": absent}),
        )
    };
    // paint takes a channel and a mode besides (docs/channels.md).
    let mut paint = merge(
        edit(
            json!({"const": "paint"}),
            &["op", "term"],
            &term,
            &absent,
            &absent,
        ),
        json!({"description": "paint: the channel takes the term's attribute values where the term is inside; density unchanged"}),
    );
    if let Some(props) = paint.get_mut("properties").and_then(Value::as_object_mut) {
        let channel = json!({"type": "string", "enum": ["material", "label"]});
        props.insert("channel".into(), nullable(channel));
        let overwrite = json!({"type": "string", "enum": ["all", "empty"]});
        props.insert("overwrite".into(), nullable(overwrite));
    }
    json!({
        "Term": {"description": "an ICVG term (docs/icvg.md): one key naming a primitive, a stored volume, an uploaded mesh or an operator",
            "oneOf": term_kinds},
        "Region": merge(region, json!({"description": "level-0 voxels, min inclusive, max exclusive; an axis with max <= min selects nothing"})),
        "EditRequest": {"description": format!("op(volume, term) for a binary operator, or a unary operator on the volume; within region when given. Limits no schema states (422 beyond): at most {} nodes nested at most {} deep, k within the volume's H, edits evaluating at most --max-edit-voxels voxels", limits.max_nodes, limits.max_depth),
            "oneOf": [
                edit(json!({"type": "string", "enum": binary_ops}), &["op", "term"], &term, &absent, &absent),
                edit(json!({"const": "divide"}), &["op", "s_l", "term"], &term, &s_l, &absent),
                edit(json!({"type": "string", "enum": ["inverse", "complement"]}), &["op"], &absent, &absent, &absent),
                edit(json!({"const": "add_scalar"}), &["op", "k"], &absent, &absent, &k),
                paint,
            ]},
    })
}

pub(super) async fn openapi(State(state): State<AppState>) -> Response {
    Json(document(&state.config.term_limits)).into_response()
}
