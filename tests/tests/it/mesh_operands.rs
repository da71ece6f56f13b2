//! Meshes as edit operands over HTTP: upload a watertight model once (kept by content hash),
//! then union it into a volume at an offset and scale; every voxel is checked against the
//! placement computed by hand. Bad uploads and bad references are refused with clear errors.

use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::http::auth::Tokens;
use isovox_server::http::{run, AppState, ServerConfig};
use isovox_server::store::{build_vod2, BuildOptions, DenseGrid};

const TOKEN: &str = "0123456789abcdef0123";

/// A binary STL of the axis-aligned cube [0, side]^3 (12 triangles, outward facing), without
/// `skip` (a face index 0..6) when given.
fn cube_stl(side: f32, skip: Option<usize>) -> Vec<u8> {
    let c = |x: f32, y: f32, z: f32| [x * side, y * side, z * side];
    // Faces as quads (counter-clockwise seen from outside): -x, +x, -y, +y, -z, +z.
    let quads = [
        [c(0., 0., 0.), c(0., 0., 1.), c(0., 1., 1.), c(0., 1., 0.)],
        [c(1., 0., 0.), c(1., 1., 0.), c(1., 1., 1.), c(1., 0., 1.)],
        [c(0., 0., 0.), c(1., 0., 0.), c(1., 0., 1.), c(0., 0., 1.)],
        [c(0., 1., 0.), c(0., 1., 1.), c(1., 1., 1.), c(1., 1., 0.)],
        [c(0., 0., 0.), c(0., 1., 0.), c(1., 1., 0.), c(1., 0., 0.)],
        [c(0., 0., 1.), c(1., 0., 1.), c(1., 1., 1.), c(0., 1., 1.)],
    ];
    let mut tris = Vec::new();
    for (i, q) in quads.iter().enumerate() {
        if Some(i) != skip {
            tris.push([q[0], q[1], q[2]]);
            tris.push([q[0], q[2], q[3]]);
        }
    }
    binary_stl(&tris)
}

/// A binary STL of these triangles (normals left zero, as readers recompute them).
fn binary_stl(tris: &[[[f32; 3]; 3]]) -> Vec<u8> {
    let mut out = vec![0u8; 80];
    out.extend_from_slice(&(tris.len() as u32).to_le_bytes());
    for t in tris {
        out.extend_from_slice(&[0u8; 12]);
        for v in t {
            for x in v {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        out.extend_from_slice(&[0u8; 2]);
    }
    out
}

#[tokio::test]
async fn an_uploaded_mesh_is_unioned_into_a_volume_where_placed() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [48u32, 40, 44];
    let layout = VolumeLayout::new(dims, 16, VoxelType::U8).unwrap();
    let zeros = vec![0u8; dims.iter().map(|&d| d as usize).product()];
    build_vod2(
        &dir.path().join("w.vod"),
        &layout,
        [1.0; 3],
        &DenseGrid::new(dims, VoxelType::U8, 16, &zeros),
        &BuildOptions::default(),
    )
    .unwrap();
    let config = ServerConfig {
        tokens: Tokens::parse(&format!("t {TOKEN} write")).unwrap(),
        mesh_dir: Some(dir.path().join("meshes")),
        ..ServerConfig::default()
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    let state = AppState::with_config(Catalog::open_dir(dir.path()).unwrap(), config);
    tokio::spawn(run(listener, state, std::future::pending()));
    // Linked with the server, reqwest's rustls needs a crypto provider installed.
    isovox_server::client_tls::install_provider();
    let c = reqwest::Client::new();

    // Upload: needs a token and a format; a cube missing a face is refused.
    let stl = cube_stl(10.0, None);
    let r = c
        .post(format!("{base}/v1/meshes?format=stl"))
        .body(stl.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 401);
    // `query` is "" or "?format=...".
    let upload = |query: &str, body: Vec<u8>| {
        c.post(format!("{base}/v1/meshes{query}"))
            .bearer_auth(TOKEN)
            .body(body)
            .send()
    };
    let detail = |r: reqwest::Response| async move {
        let problem: serde_json::Value = serde_json::from_slice(&r.bytes().await.unwrap()).unwrap();
        problem["detail"].as_str().unwrap().to_string()
    };
    let r = upload("", stl.clone()).await.unwrap();
    assert_eq!(r.status().as_u16(), 400);
    let r = upload("?format=stl", cube_stl(10.0, Some(3)))
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 422);
    let d = detail(r).await;
    assert!(d.contains("watertight"), "{d}");
    // A tetrahedron whose four points lie on a line: each edge is used twice, as in a closed
    // surface, but its triangles have zero area and enclose nothing.
    let p = |t: f32| [t, 2.0 * t, 3.0 * t];
    let line = [p(0.0), p(1.0), p(2.0), p(3.0)];
    let tetra =
        [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]].map(|t: [usize; 3]| t.map(|i| line[i]));
    let r = upload("?format=stl", binary_stl(&tetra)).await.unwrap();
    assert_eq!(r.status().as_u16(), 422);
    let d = detail(r).await;
    assert!(
        d.contains("not watertight") && d.contains("no volume"),
        "{d}"
    );
    // The format is one of the four, as written (the document's enum).
    let r = upload("?format=STL", stl.clone()).await.unwrap();
    assert_eq!(r.status().as_u16(), 400);
    let r = upload("?format=stl", stl.clone()).await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let info: serde_json::Value = serde_json::from_slice(&r.bytes().await.unwrap()).unwrap();
    assert_eq!(info["triangles"], 12);
    let hash = info["hash"].as_str().unwrap().to_string();
    assert_eq!(hash.len(), 16);

    // A mesh that was never uploaded is not there: 404, as any resource named that is not
    // there (not a 500, and not a 422: the request itself is well formed).
    let edit = |hash: &str| {
        format!(
            r#"{{"op": "union", "term": {{"mesh": {{"hash": "{hash}", "offset": [5, 6, 7], "scale": 1.5}}}}}}"#
        )
    };
    let r = c
        .post(format!("{base}/v1/volumes/w/edits"))
        .bearer_auth(TOKEN)
        .header("content-type", "application/json")
        .body(edit("00000000000000ff"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 404);
    let problem: serde_json::Value = serde_json::from_slice(&r.bytes().await.unwrap()).unwrap();
    assert!(
        problem["detail"]
            .as_str()
            .unwrap()
            .contains("00000000000000ff"),
        "{problem}"
    );

    let r = c
        .post(format!("{base}/v1/volumes/w/edits"))
        .bearer_auth(TOKEN)
        .header("content-type", "application/json")
        .body(edit(&hash))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200, "{}", r.text().await.unwrap());
    let voxels = c
        .get(format!("{base}/v1/volumes/w/levels/0?format=voxels"))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    // The cube [0, 10]^3 scaled by 1.5 and moved by (5, 6, 7) spans [5, 20] x [6, 21] x [7, 22]:
    // its faces fall on voxel boundaries, so each voxel is wholly in (H) or out (L).
    let inside = |v: u32, lo: u32| (lo..lo + 15).contains(&v);
    let mut expected_inside = 0;
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let i = ((z * dims[1] + y) * dims[0] + x) as usize;
                let want = if inside(x, 5) && inside(y, 6) && inside(z, 7) {
                    expected_inside += 1;
                    255
                } else {
                    0
                };
                assert_eq!(voxels[i], want, "voxel ({x}, {y}, {z})");
            }
        }
    }
    assert_eq!(expected_inside, 15 * 15 * 15);
}
