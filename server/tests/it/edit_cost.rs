//! Every edit's cost is bounded, against a real `isovox serve` on a 256^3 volume:
//!
//! - a mesh leaf placed at an absurd scale (500 on a 256^3 volume; vertices at 1e30 with scale
//!   1e-26) is voxelized only within the volume and applied correctly; one placed beyond the
//!   voxelizer's range (1e30 at scale 1, or an overflow to infinity) is a 422 naming the limit;
//! - `dilate` of radius 200 is applied correctly while other edits of the volume go on;
//! - an edit past `--edit-timeout` is stopped with a 422, commits nothing, and frees the writer;
//! - an edit whose client leaves is stopped (it never commits);
//! - SIGTERM during a long edit: the server exits, and the edit was stopped, not committed.
//!
//! Golden values are reasoned out by hand in each test (a placed cube's samples; a window of
//! radius 200 that holds the centre of a sphere from every voxel).

use crate::server_process;

use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::store::{build_vod2, BuildOptions, DenseGrid, Vod2};
use serde_json::{json, Value};
use server_process::ServerProcess;
use std::path::Path;
use std::time::Duration;

const TOKEN: &str = "edit-cost-0123456789abcdef";
const N: u32 = 256;
/// Far longer than anything here should take: reaching it means the server hangs.
const HANGS: Duration = Duration::from_secs(120);

/// A 256^3 u8 volume of zeros, `w.vod` in `dir`.
fn zero_volume(dir: &Path) {
    let dims = [N; 3];
    let layout = VolumeLayout::new(dims, 32, VoxelType::U8).unwrap();
    let zeros = vec![0u8; (N as usize).pow(3)];
    build_vod2(
        &dir.join("w.vod"),
        &layout,
        [1.0; 3],
        &DenseGrid::new(dims, VoxelType::U8, 32, &zeros),
        &BuildOptions::default(),
    )
    .unwrap();
}

fn serve(dir: &Path, flags: &[&str]) -> ServerProcess {
    std::fs::write(dir.join("tokens"), format!("t {TOKEN} write\n")).unwrap();
    let mut args: Vec<&std::ffi::OsStr> = vec!["--data".as_ref(), dir.as_os_str()];
    args.extend(flags.iter().map(std::ffi::OsStr::new));
    ServerProcess::start(&args, &[("ISOVOX_EDIT_RATE", "100000")])
}

fn client() -> reqwest::blocking::Client {
    isovox_server::client_tls::install_provider();
    reqwest::blocking::Client::builder()
        .timeout(HANGS)
        .build()
        .unwrap()
}

/// POSTs an edit; (status, JSON body).
fn edit(server: &ServerProcess, body: &Value) -> (u16, Value) {
    let r = client()
        .post(server.url("/v1/volumes/w/edits"))
        .bearer_auth(TOKEN)
        .json(body)
        .send()
        .unwrap();
    let status = r.status().as_u16();
    (status, r.json().unwrap_or(Value::Null))
}

fn version(server: &ServerProcess) -> u64 {
    let meta: Value = client()
        .get(server.url("/v1/volumes/w"))
        .send()
        .unwrap()
        .json()
        .unwrap();
    meta["version"].as_u64().unwrap()
}

/// Level 0 as one array (x fastest).
fn voxels(server: &ServerProcess) -> Vec<u8> {
    let r = client()
        .get(server.url("/v1/volumes/w/levels/0?format=voxels"))
        .send()
        .unwrap();
    assert_eq!(r.status(), 200);
    let bytes = r.bytes().unwrap().to_vec();
    assert_eq!(bytes.len(), (N as usize).pow(3));
    bytes
}

/// A binary STL of `triangles`.
fn stl(triangles: &[[[f32; 3]; 3]]) -> Vec<u8> {
    let mut out = vec![0u8; 80];
    out.extend_from_slice(&(triangles.len() as u32).to_le_bytes());
    for t in triangles {
        out.extend_from_slice(&[0u8; 12]);
        for v in t {
            for c in v {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        out.extend_from_slice(&[0u8; 2]);
    }
    out
}

/// The unit cube [0, 1]^3, 12 triangles facing out.
fn unit_cube() -> Vec<[[f32; 3]; 3]> {
    let c = |x: f32, y: f32, z: f32| [x, y, z];
    let quads = [
        [c(0., 0., 0.), c(0., 0., 1.), c(0., 1., 1.), c(0., 1., 0.)],
        [c(1., 0., 0.), c(1., 1., 0.), c(1., 1., 1.), c(1., 0., 1.)],
        [c(0., 0., 0.), c(1., 0., 0.), c(1., 0., 1.), c(0., 0., 1.)],
        [c(0., 1., 0.), c(0., 1., 1.), c(1., 1., 1.), c(1., 1., 0.)],
        [c(0., 0., 0.), c(0., 1., 0.), c(1., 1., 0.), c(1., 0., 0.)],
        [c(0., 0., 1.), c(1., 0., 1.), c(1., 1., 1.), c(0., 1., 1.)],
    ];
    quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect()
}

/// The tetrahedron with corners at the origin and at `far` on each axis, facing out.
fn tetrahedron(far: f32) -> Vec<[[f32; 3]; 3]> {
    let (o, x, y, z) = (
        [0.0, 0.0, 0.0],
        [far, 0.0, 0.0],
        [0.0, far, 0.0],
        [0.0, 0.0, far],
    );
    vec![[o, y, x], [o, x, z], [o, z, y], [x, y, z]]
}

fn upload(server: &ServerProcess, triangles: &[[[f32; 3]; 3]]) -> String {
    let r = client()
        .post(server.url("/v1/meshes?format=stl"))
        .bearer_auth(TOKEN)
        .body(stl(triangles))
        .send()
        .unwrap();
    assert_eq!(r.status(), 200, "{}", r.text().unwrap_or_default());
    let answer: Value = r.json().unwrap();
    answer["hash"].as_str().unwrap().to_string()
}

fn mesh_edit(op: &str, hash: &str, offset: [f64; 3], scale: f64) -> Value {
    json!({"op": op, "term": {"mesh": {"hash": hash, "offset": offset, "scale": scale}}})
}

#[test]
fn mesh_leaves_at_absurd_scales_are_voxelized_within_the_volume_or_refused() {
    let dir = tempfile::tempdir().unwrap();
    zero_volume(dir.path());
    let server = serve(dir.path(), &[]);
    let cube = upload(&server, &unit_cube());

    // Scale 500: the cube spans [100, 600] x [-300, 200] x [-300, 200]. A voxel's 2x2x2 samples
    // sit at +0.25 and +0.75, so every sample of voxel (x, y, z) is inside exactly when
    // x >= 100, y <= 199 and z <= 199: those voxels become H (8 of 8 inside), the others stay L.
    let (status, answer) = edit(
        &server,
        &mesh_edit("union", &cube, [100.0, -300.0, -300.0], 500.0),
    );
    assert_eq!(status, 200, "{answer}");
    let v = voxels(&server);
    let n = N as usize;
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let want = if x >= 100 && y < 200 && z < 200 {
                    255
                } else {
                    0
                };
                assert_eq!(v[(z * n + y) * n + x], want, "voxel {x},{y},{z}");
            }
        }
    }

    // Vertices at 1e30, scale 1e-26: the tetrahedron x, y, z > 0, x + y + z < 1e4 holds every
    // sample of the volume (0.25 <= coordinate, sum <= 3 * 255.75 < 1e4), so the union is H
    // everywhere.
    let far = upload(&server, &tetrahedron(1e30));
    let (status, answer) = edit(&server, &mesh_edit("union", &far, [0.0; 3], 1e-26));
    assert_eq!(status, 200, "{answer}");
    assert!(voxels(&server).iter().all(|&v| v == 255));

    // The same model at scale 1 reaches 1e30: beyond the voxelizer's range, refused with the
    // limit named; as is a placement that overflows to infinity. Nothing is committed.
    let before = version(&server);
    for scale in [1.0, 1e300] {
        let (status, answer) = edit(&server, &mesh_edit("difference", &far, [0.0; 3], scale));
        assert_eq!(status, 422, "scale {scale}: {answer}");
        let detail = answer["detail"].as_str().unwrap();
        assert!(detail.contains("2^40"), "scale {scale}: {detail}");
    }
    assert_eq!(version(&server), before);
    // Carving with the far-reaching tetrahedron scaled down to cover the volume empties it
    // (difference of H by H, outside the surface band: L).
    let (status, answer) = edit(&server, &mesh_edit("difference_a", &far, [0.0; 3], 1e-26));
    assert_eq!(status, 200, "{answer}");
    assert!(voxels(&server).iter().all(|&v| v == 0));
}

#[test]
fn dilate_of_radius_200_is_applied_while_other_edits_go_on() {
    let dir = tempfile::tempdir().unwrap();
    zero_volume(dir.path());
    let server = serve(dir.path(), &[]);
    let v0 = version(&server);
    // Every voxel of the volume is within 128 voxels (per axis) of the sphere's centre, which is
    // H: the window of radius 200 around any voxel holds it, so the dilation is H everywhere.
    let dilate = json!({"op": "union", "term": {"dilate": {"radius": 200,
        "arg": {"ellipsoid": {"center": [128, 128, 128], "radii": [10, 10, 10]}}}}});
    let small: Vec<Value> = (0..6)
        .map(|i| {
            json!({"op": "union", "term": {"ellipsoid": {"center": [20 + 30 * i, 40, 40], "radii": [4, 4, 4]}}})
        })
        .collect();
    let answers = std::thread::scope(|s| {
        let big = s.spawn(|| edit(&server, &dilate));
        let others: Vec<_> = small.iter().map(|e| s.spawn(|| edit(&server, e))).collect();
        (
            big.join().unwrap(),
            others
                .into_iter()
                .map(|h| h.join().unwrap())
                .collect::<Vec<_>>(),
        )
    });
    let (status, answer) = answers.0;
    assert_eq!(status, 200, "{answer}");
    for (status, answer) in answers.1 {
        assert_eq!(status, 200, "{answer}");
    }
    assert_eq!(version(&server), v0 + 7);
    assert!(voxels(&server).iter().all(|&v| v == 255));
}

/// A dilation whose argument has no B-box (the inverse of a sphere is H far away), so the
/// filter reads its whole grown box: 656^3 voxels for the whole 256^3 volume, far more work
/// than the edit timeouts below allow.
fn heavy_edit() -> Value {
    json!({"op": "union", "term": {"dilate": {"radius": 200,
        "arg": {"inverse": {"ellipsoid": {"center": [128, 128, 128], "radii": [100, 90, 80]}}}}}})
}

fn small_edit() -> Value {
    json!({"op": "union", "term": {"ellipsoid": {"center": [40, 40, 40], "radii": [5, 5, 5]}}})
}

#[test]
fn an_edit_over_the_voxel_budget_is_refused_before_it_runs() {
    let dir = tempfile::tempdir().unwrap();
    zero_volume(dir.path());
    let server = serve(dir.path(), &[]);
    let before = version(&server);
    // 656^3 voxels read, and 656 planes of 256^2 kept, is over the default budget of 2^28.
    let (status, answer) = edit(&server, &heavy_edit());
    assert_eq!(status, 422, "{answer}");
    let detail = answer["detail"].as_str().unwrap();
    assert!(
        detail.contains("dilate of radius 200") && detail.contains("268435456"),
        "{detail}"
    );
    assert_eq!(version(&server), before);
}

#[test]
fn an_edit_past_the_deadline_is_stopped_commits_nothing_and_frees_the_writer() {
    let dir = tempfile::tempdir().unwrap();
    zero_volume(dir.path());
    let budget = (1u64 << 40).to_string();
    let server = serve(
        dir.path(),
        &["--edit-timeout", "0.3", "--max-edit-voxels", &budget],
    );
    let v0 = version(&server);
    let ((status, answer), (small_status, small_answer)) = std::thread::scope(|s| {
        let heavy = s.spawn(|| edit(&server, &heavy_edit()));
        // Sent while the heavy edit holds the writer (or just before: either order passes).
        std::thread::sleep(Duration::from_millis(100));
        let small = s.spawn(|| edit(&server, &small_edit()));
        (heavy.join().unwrap(), small.join().unwrap())
    });
    assert_eq!(status, 422, "{answer}");
    let detail = answer["detail"].as_str().unwrap();
    assert!(
        detail.contains("--edit-timeout") && detail.contains("nothing was committed"),
        "{detail}"
    );
    assert_eq!(small_status, 200, "{small_answer}");
    // Only the small edit committed.
    assert_eq!(version(&server), v0 + 1);
    assert_eq!(small_answer["previous"].as_u64(), Some(v0));
}

#[test]
fn an_edit_whose_client_leaves_is_stopped() {
    let dir = tempfile::tempdir().unwrap();
    zero_volume(dir.path());
    let budget = (1u64 << 40).to_string();
    let server = serve(
        dir.path(),
        &["--edit-timeout", "3600", "--max-edit-voxels", &budget],
    );
    let v0 = version(&server);
    isovox_server::client_tls::install_provider();
    let impatient = reqwest::blocking::Client::builder()
        .timeout(Duration::from_millis(500))
        .build()
        .unwrap();
    let gone = impatient
        .post(server.url("/v1/volumes/w/edits"))
        .bearer_auth(TOKEN)
        .json(&heavy_edit())
        .send();
    assert!(gone.is_err(), "the heavy edit answered within 0.5 s");
    drop(impatient);
    // Had the heavy edit gone on, it would hold the writer until it committed, and this edit
    // would follow it; stopped, it committed nothing, and this edit follows v0.
    let (status, answer) = edit(&server, &small_edit());
    assert_eq!(status, 200, "{answer}");
    assert_eq!(answer["previous"].as_u64(), Some(v0), "{answer}");
    assert_eq!(version(&server), v0 + 1);
}

#[test]
fn sigterm_during_a_long_edit_stops_it_and_the_server_exits() {
    let dir = tempfile::tempdir().unwrap();
    zero_volume(dir.path());
    let budget = (1u64 << 40).to_string();
    let mut server = serve(
        dir.path(),
        &[
            "--edit-timeout",
            "3600",
            "--max-edit-voxels",
            &budget,
            "--shutdown-grace",
            "1",
        ],
    );
    let v0 = version(&server);
    let url = server.url("/v1/volumes/w/edits");
    let answer = std::thread::scope(|s| {
        let heavy = s.spawn(|| {
            client()
                .post(&url)
                .bearer_auth(TOKEN)
                .json(&heavy_edit())
                .send()
                .map(|r| r.status().as_u16())
        });
        // Let the edit start.
        std::thread::sleep(Duration::from_millis(500));
        let status = server.terminate(HANGS);
        assert!(
            status.is_some_and(|s| s.success()),
            "the server did not exit cleanly after SIGTERM: {status:?}\n{}",
            server.log_tail(20)
        );
        heavy.join().unwrap()
    });
    // Its connection was closed at the end of the grace (or it was answered 503).
    assert!(matches!(answer, Err(_) | Ok(503)), "{answer:?}");
    // Had the edit gone on, the server would have waited for it and committed it.
    assert_eq!(
        Vod2::open(&dir.path().join("w.vod"))
            .unwrap()
            .head()
            .version,
        v0
    );
}

/// Resolves every mesh hash to one model (and no volume).
struct OneMesh(std::sync::Arc<isovox_server::voxelize::solid::TriMesh>);

impl isovox_server::icvg::term::VolumeResolver for OneMesh {
    fn resolve(
        &self,
        name: &str,
    ) -> Result<std::sync::Arc<isovox_server::store::Snapshot>, isovox_server::icvg::term::TermError>
    {
        Err(isovox_server::icvg::term::TermError::Volume(format!(
            "no volume {name:?}"
        )))
    }

    fn mesh(
        &self,
        _: u64,
    ) -> Result<
        std::sync::Arc<isovox_server::voxelize::solid::TriMesh>,
        isovox_server::icvg::term::TermError,
    > {
        Ok(self.0.clone())
    }
}

fn tri_mesh(triangles: &[[[f32; 3]; 3]]) -> isovox_server::voxelize::solid::TriMesh {
    isovox_server::voxelize::solid::TriMesh {
        positions: triangles.iter().flatten().copied().collect(),
        triangles: (0..triangles.len() as u32)
            .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
            .collect(),
    }
}

/// A mesh leaf compiled for a box (as an edit compiles it) has, over that box, the values of
/// the whole model's voxelization (compiled for anywhere): parity counts the surfaces beyond
/// the box. Boxes cut through the placed models and reach past them.
#[test]
fn a_mesh_leaf_voxelized_within_a_box_equals_the_whole_model_cut_to_it() {
    use isovox_server::geometry::Box3;
    use isovox_server::icvg::term::{CompiledTerm, Scope, TermLimits};
    let term = |offset: [f64; 3], scale: f64| isovox_proto::icvg::Term::Mesh {
        hash: "00000000000000aa".into(),
        offset,
        scale,
    };
    for (model, offset, scale) in [
        (unit_cube(), [-5.3, 2.7, -11.9], 37.3),
        (tetrahedron(1000.0), [-3.1, -20.45, 1.9], 0.061),
    ] {
        let meshes = OneMesh(std::sync::Arc::new(tri_mesh(&model)));
        let whole = CompiledTerm::compile(
            &term(offset, scale),
            VoxelType::U8,
            &TermLimits::default(),
            &meshes,
        )
        .unwrap();
        for within in [
            Box3::new([0, 0, 0], [20, 24, 18]),
            Box3::new([-9, 5, -3], [7, 31, 40]),
            Box3::new([10, 10, 10], [60, 60, 60]),
        ] {
            let scope = Scope {
                within: Some(within),
                ..Scope::default()
            };
            let (clipped, sampled) = CompiledTerm::compile_in(
                &term(offset, scale),
                VoxelType::U8,
                &TermLimits::default(),
                &meshes,
                &scope,
            )
            .unwrap();
            assert!(sampled as u128 <= within.voxels());
            let n = within.voxels() as usize;
            let (mut a, mut b) = (vec![0u16; n], vec![0u16; n]);
            whole.eval(&within, &mut a).unwrap();
            clipped.eval(&within, &mut b).unwrap();
            assert_eq!(a, b, "{offset:?} x {scale} within {within:?}");
            assert!(a.contains(&255) && a.contains(&0), "{within:?}");
        }
    }
}
