//! `GET /openapi.json`: the API described in OpenAPI 3.1, written by hand next to the routes it
//! describes (`mod.rs`); the end-to-end tests check that every route is listed.

use axum::response::{IntoResponse, Response};
use axum::Json;
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

/// The document.
pub(super) fn document() -> Value {
    let name = path_param(
        "name",
        json!({"type": "string", "pattern": "^[A-Za-z0-9_.-]{1,128}$"}),
        "volume name",
    );
    let level = path_param(
        "level",
        json!({"type": "integer", "minimum": 0, "maximum": 255}),
        "level of detail",
    );
    let coord = |c: &str| {
        path_param(
            c,
            json!({"type": "integer", "minimum": 0, "maximum": 4294967295u64}),
            "brick coordinate at the level",
        )
    };
    let version = query_param(
        "version",
        json!({"type": "integer", "minimum": 0}),
        "read this older version",
    );
    let brick_params = json!([name, level, coord("x"), coord("y"), coord("z"), version]);
    let binary = |media: &str| json!({media: {"schema": {"type": "string", "format": "binary"}}});
    let mut doc = json!({
        "openapi": "3.1.0",
        "info": {"title": "Isovox", "version": env!("CARGO_PKG_VERSION"),
                 "description": "Large, editable volumes as brick octrees: bricks, levels and marching-cubes tiles by random access."},
        "paths": {
            "/healthz": {"get": {"summary": "liveness", "responses": {"200": {"description": "ok", "content": {"text/plain": {"schema": {"type": "string"}}}}}}},
            "/metrics": {"get": {"summary": "Prometheus metrics", "responses": {"200": {"description": "text format 0.0.4", "content": {"text/plain": {"schema": {"type": "string"}}}}}}},
            "/openapi.json": {"get": {"summary": "this document", "responses": {"200": {"description": "OpenAPI 3.1", "content": {"application/json": {"schema": {"type": "object"}}}}}}},
            "/v1/volumes": {"get": {"summary": "list volumes", "responses": {"200": {"description": "volumes", "content": {"application/json": {"schema": {"$ref": "#/components/schemas/VolumeList"}}}}}}},
            "/v1/volumes/{name}": {"get": {"summary": "volume metadata", "parameters": [name],
                "responses": merge(json!({"200": {"description": "metadata", "content": {"application/json": {"schema": {"$ref": "#/components/schemas/VolumeInfo"}}}}}), problem_responses(&["400", "404"]))}},
            "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}": {"get": {
                "summary": "one brick: raw voxels (x fastest, u16 little endian); the stored zstd frame with Accept-Encoding: zstd; an lz4 block with Accept: application/x-lz4",
                "parameters": brick_params,
                "responses": merge(json!({
                    "200": {"description": "the brick; ETag is its content hash", "content": merge(binary("application/octet-stream"), binary("application/x-lz4"))},
                    "304": {"description": "not modified (If-None-Match)"}}), problem_responses(&["400", "404", "500"]))}},
            "/v1/volumes/{name}/blobs/{hash}": {"get": {
                "summary": "a brick by content hash, immutable (Cache-Control: public, max-age=31536000, immutable)",
                "parameters": [name, path_param("hash", json!({"type": "string", "pattern": "^[0-9a-f]{16}$"}), "content hash, 16 hex digits")],
                "responses": merge(json!({
                    "200": {"description": "the brick", "content": merge(binary("application/octet-stream"), binary("application/x-lz4"))},
                    "304": {"description": "not modified"}}), problem_responses(&["400", "404", "500"]))}},
            "/v1/volumes/{name}/batch": {"post": {
                "summary": "many bricks in one response (application/x-isovox-bricks, see proto/src/batch.rs)",
                "parameters": [name],
                "requestBody": {"required": true, "content": {"application/json": {"schema": {"$ref": "#/components/schemas/BatchRequest"}}}},
                "responses": merge(json!({"200": {"description": "the bricks", "content": binary("application/x-isovox-bricks")}}), problem_responses(&["400", "404", "413", "415", "500", "503"]))}},
            "/v1/volumes/{name}/levels/{level}": {"get": {
                "summary": "a level's brick grid (JSON), or its voxels as one RAW array (format=voxels)",
                "parameters": [name, level, version,
                    query_param("region", json!({"type": "string", "pattern": "^[0-9]+(,[0-9]+){5}$"}), "MINX,MINY,MINZ,MAXX,MAXY,MAXZ, max exclusive (bricks for grid, voxels for voxels); must be non-empty and inside the level (400 otherwise)"),
                    query_param("format", json!({"type": "string", "enum": ["grid", "voxels"]}), "grid (default) or voxels")],
                "responses": merge(json!({"200": {"description": "the grid or the voxels", "content": merge(json!({"application/json": {"schema": {"$ref": "#/components/schemas/LevelGrid"}}}), binary("application/octet-stream"))}}),
                    problem_responses(&["400", "404", "413", "500", "503"]))}},
            "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}": {"get": {
                "summary": "the marching-cubes mesh of one tile, in world coordinates, with its transition data: secondary positions and one strip per face, to join tiles one level coarser without cracks (docs/mesh-encoding.md, docs/lod-meshes.md)",
                "parameters": [name, level, coord("x"), coord("y"), coord("z"), version,
                    query_param("iso", json!({"type": "number"}), "iso value, default S - 0.5"),
                    query_param("format", json!({"type": "string", "enum": ["compact", "glb"]}), "compact (default: format version 2 with the transition section, docs/mesh-encoding.md) or glb (the regular mesh as a plain glTF primitive, the transition section in a buffer view named by the mesh's extras)")],
                "responses": merge(json!({
                    "200": {"description": "the tile: its regular mesh and transition data", "content": merge(binary("application/x-isovox-mesh"), binary("model/gltf-binary"))},
                    "304": {"description": "not modified"}}), problem_responses(&["400", "404", "500", "503"]))}},
        },
        "components": {"securitySchemes": {"bearer": {"type": "http", "scheme": "bearer"}}, "schemas": {
            "Problem": {"type": "object", "required": ["type", "title", "status", "detail"],
                "properties": {"type": {"type": "string"}, "title": {"type": "string"}, "status": {"type": "integer"}, "detail": {"type": "string"},
                    "version": {"type": "integer", "description": "the current version, on a 409 from If-Match (absent on a 409 from a read-only volume)"}}},
            "LevelInfo": {"type": "object", "required": ["level", "grid", "dims"],
                "properties": {"level": {"type": "integer"}, "grid": {"$ref": "#/components/schemas/Triple"}, "dims": {"$ref": "#/components/schemas/Triple"}}},
            "Triple": {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 3, "maxItems": 3},
            "VolumeInfo": {"type": "object",
                "required": ["name", "dims", "voxel_type", "low", "high", "surface", "brick", "levels", "voxel_scale", "version"],
                "properties": {"name": {"type": "string"}, "dims": {"$ref": "#/components/schemas/Triple"},
                    "voxel_type": {"type": "string", "enum": ["u8", "u16"]}, "low": {"type": "integer"}, "high": {"type": "integer"},
                    "surface": {"type": "integer"}, "brick": {"type": "integer"},
                    "levels": {"type": "array", "items": {"$ref": "#/components/schemas/LevelInfo"}},
                    "voxel_scale": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
                    "version": {"type": "integer"}}},
            "VolumeList": {"type": "object", "required": ["volumes"], "properties": {"volumes": {"type": "array", "items": {"$ref": "#/components/schemas/VolumeInfo"}}}},
            "LevelGrid": {"type": "object", "required": ["level", "grid", "min", "max", "version", "bricks"],
                "properties": {"level": {"type": "integer"}, "grid": {"$ref": "#/components/schemas/Triple"},
                    "min": {"$ref": "#/components/schemas/Triple"}, "max": {"$ref": "#/components/schemas/Triple"}, "version": {"type": "integer"},
                    "bricks": {"type": "array", "items": {"type": "object", "required": ["hash", "min", "max"],
                        "properties": {"hash": {"type": "string"}, "min": {"type": "integer"}, "max": {"type": "integer"}}}}}},
            "BatchRequest": {"type": "object", "required": ["keys"], "additionalProperties": false,
                "properties": {"keys": {"type": "array", "maxItems": 4096,
                        "items": {"type": "array", "minItems": 4, "maxItems": 4, "items": false, "prefixItems": [
                            {"type": "integer", "minimum": 0, "maximum": 255},
                            {"type": "integer", "minimum": 0, "maximum": 4294967295u64},
                            {"type": "integer", "minimum": 0, "maximum": 4294967295u64},
                            {"type": "integer", "minimum": 0, "maximum": 4294967295u64}]}},
                    "version": {"type": ["integer", "null"], "minimum": 0, "maximum": u64::MAX}, "encoding": {"type": "string", "enum": ["raw", "stored"]}}}
        }}
    });
    let (paths, schemas) = write_side(name);
    if let Some(p) = doc["paths"].as_object_mut() {
        p.extend(paths.as_object().cloned().unwrap_or_default());
    }
    if let Some(s) = doc["components"]["schemas"].as_object_mut() {
        s.extend(schemas.as_object().cloned().unwrap_or_default());
    }
    doc
}

/// The write side (`docs/editing.md`): edits, compaction, the change feed and its catch-up.
fn write_side(name: Value) -> (Value, Value) {
    let json_body = |schema: &str| json!({"application/json": {"schema": {"$ref": format!("#/components/schemas/{schema}")}}});
    let bearer = json!([{"bearer": []}]);
    let since = query_param(
        "since",
        json!({"type": "integer", "minimum": 0}),
        "list the versions after this one",
    );
    let paths = json!({
        "/v1/volumes/{name}/edits": {"post": {
            "summary": "apply an ICVG edit (docs/icvg.md) as the next version; durable before the answer",
            "security": bearer,
            "parameters": [name, {"name": "If-Match", "in": "header", "required": false, "schema": {"type": "string"}, "description": "apply only at this version (quoted or not); 409 otherwise"}],
            "requestBody": {"required": true, "content": {"application/json": {"schema": {"type": "object", "required": ["op"], "properties": {"op": {"type": "string"}}}}}},
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
            "security": bearer,
            "parameters": [query_param("format", json!({"type": "string", "enum": ["stl", "obj", "ply", "glb"]}), "the model's format (required)")],
            "requestBody": {"required": true, "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}},
            "responses": merge(json!({"200": {"description": "the stored mesh", "content": json_body("MeshInfo")}}),
                problem_responses(&["400", "401", "403", "404", "413", "422", "500"]))}},
        "/v1/volumes/{name}/changes": {"get": {
            "summary": "the versions after `since`, oldest first, with their changed bricks per level",
            "parameters": [name, since.clone(), query_param("limit", json!({"type": "integer", "minimum": 1, "maximum": 10000}), "most versions listed (default 1000)")],
            "responses": merge(json!({"200": {"description": "the versions", "content": json_body("ChangeList")}}),
                problem_responses(&["400", "404", "410", "500"]))}},
        "/v1/volumes/{name}/events": {"get": {
            "summary": "change feed, server-sent events: hello, then one commit event per version (resync when too far behind)",
            "parameters": [name, since, {"name": "Last-Event-ID", "in": "header", "required": false, "schema": {"type": "string"}, "description": "resume after this version"}],
            "responses": merge(json!({"200": {"description": "an event stream; each event as its fields (data: JSON text)", "content": {"text/event-stream": {"schema": {
                "type": "object", "required": ["data"],
                "properties": {"event": {"type": "string", "enum": ["hello", "commit", "resync"]}, "data": {"type": "string"}, "id": {"type": "string"}}}}}}}),
                problem_responses(&["400", "404", "410"]))}},
    });
    let changed = json!({"type": "array", "items": {"type": "array", "items": {"$ref": "#/components/schemas/Triple"}}});
    let event = json!({"type": "object", "required": ["version", "timestamp_ms", "changed"],
        "properties": {"version": {"type": "integer"}, "timestamp_ms": {"type": "integer"}, "changed": changed}});
    let schemas = json!({
        "EditResponse": {"type": "object", "required": ["version", "previous", "changed", "evaluated", "new_records", "checkpoint", "elapsed_us"],
            "properties": {"version": {"type": "integer"}, "previous": {"type": "integer"}, "changed": changed,
                "evaluated": {"type": "integer"}, "new_records": {"type": "integer"}, "checkpoint": {"type": "boolean"}, "elapsed_us": {"type": "integer"}}},
        "ChangeEvent": event,
        "MeshInfo": {"type": "object", "required": ["hash", "triangles", "vertices", "min", "max"],
            "properties": {"hash": {"type": "string"}, "triangles": {"type": "integer"}, "vertices": {"type": "integer"},
                "min": {"type": "array", "items": {"type": "number"}}, "max": {"type": "array", "items": {"type": "number"}}}},
        "ChangeList": {"type": "object", "required": ["since", "head", "oldest", "more", "changes"],
            "properties": {"since": {"type": "integer"}, "head": {"type": "integer"}, "oldest": {"type": "integer"}, "more": {"type": "boolean"},
                "changes": {"type": "array", "items": {"$ref": "#/components/schemas/ChangeEvent"}}}},
        "CompactResponse": {"type": "object", "required": ["version", "bytes_before", "bytes_after", "bricks", "elapsed_us"],
            "properties": {"version": {"type": "integer"}, "bytes_before": {"type": "integer"}, "bytes_after": {"type": "integer"},
                "bricks": {"type": "integer"}, "elapsed_us": {"type": "integer"}}},
    });
    (paths, schemas)
}

pub(super) async fn openapi() -> Response {
    Json(document()).into_response()
}
