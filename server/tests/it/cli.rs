//! The real `isovox` binary on real files.
//!
//! Proves that `generate` + `inspect --json` report the shape, version, brick counts (computed
//! here by hand), file size and ratio; that `import` of a RAW or RAWVOX file followed by `export`
//! gives back the same voxels (and each level of detail and region the independent downsampling
//! gives); that `get` writes exactly the brick sliced from the RAW, padded with L; that VOD 1
//! import and export round-trip; and that bad input (RAW without --dims, a RAW of the wrong size,
//! a missing file, an out-of-range brick, a damaged file, dimensions whose product overflows)
//! exits non-zero with an "error:" message and no panic.

// unwrap is how a test says "this must work"; clippy exempts only #[test] functions.

use isovox_proto::VoxelType;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use crate::common;
use crate::server_process;
use common::{brick_count, level_count, mixed_volume, pyramid, Grid};

fn isovox(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_isovox"))
        .args(args)
        .env_remove("ISOVOX_LOG")
        .output()
        .expect("the isovox binary runs")
}

fn show(o: &Output) -> String {
    format!(
        "status {:?}\nstderr: {}",
        o.status.code(),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Runs a command that must succeed; returns its stdout.
fn ok(args: &[&str]) -> Vec<u8> {
    let o = isovox(args);
    assert!(o.status.success(), "isovox {args:?} failed: {}", show(&o));
    o.stdout
}

/// Runs a command that must fail cleanly; returns its stderr.
fn fails(args: &[&str]) -> String {
    let o = isovox(args);
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(
        !o.status.success(),
        "isovox {args:?} succeeded but should fail"
    );
    assert!(
        !stderr.contains("panicked"),
        "isovox {args:?} panicked: {stderr}"
    );
    assert!(
        stderr.starts_with("error:"),
        "isovox {args:?}: stderr does not start with \"error:\": {stderr}"
    );
    assert!(
        stderr.trim().len() > "error:".len(),
        "isovox {args:?}: empty message"
    );
    stderr
}

fn s(p: &Path) -> &str {
    p.to_str().expect("temporary paths are UTF-8")
}

fn inspect_json(path: &Path) -> Value {
    let out = ok(&["inspect", "--json", s(path)]);
    serde_json::from_slice(&out).expect("inspect --json prints JSON")
}

/// Checks the fields `docs/cli.md` lists against what the test knows.
fn check_inspection(j: &Value, path: &Path, dims: [u32; 3], voxel_type: &str, brick: u32) {
    let bytes = if voxel_type == "u16" { 2 } else { 1 };
    assert_eq!(j["dims"], serde_json::json!(dims), "{j}");
    assert_eq!(j["voxel_type"], voxel_type, "{j}");
    assert_eq!(j["brick"], brick, "{j}");
    assert_eq!(j["version"], 1, "{j}");
    let total = brick_count(dims, brick);
    assert_eq!(j["bricks_total"], total, "{j}");
    let unique = j["bricks_unique"].as_u64().expect("bricks_unique");
    assert!(unique >= 1 && unique <= total, "{j}");
    let file_bytes = std::fs::metadata(path).unwrap().len();
    assert_eq!(j["file_bytes"], file_bytes, "{j}");
    let raw = dims.iter().map(|&d| d as u64).product::<u64>() * bytes;
    assert_eq!(j["raw_bytes"], raw, "{j}");
    let ratio = j["ratio"].as_f64().expect("ratio");
    let expected = raw as f64 / file_bytes as f64;
    assert!(
        (ratio - expected).abs() <= expected * 1e-12,
        "ratio {ratio}, expected {expected}"
    );
    // `levels` lists each level with its brick grid.
    let levels = j["levels"].as_array().expect("levels is a list");
    assert_eq!(levels.len(), level_count(dims, brick), "{j}");
    for (k, l) in levels.iter().enumerate() {
        let grid = dims.map(|d| d.div_ceil(brick << k));
        assert_eq!(l["level"], k, "{j}");
        assert_eq!(l["grid"], serde_json::json!(grid), "{j}");
        assert_eq!(l["bricks"], grid.iter().product::<u32>(), "{j}");
    }
}

#[test]
fn every_data_subcommand_parses_its_arguments() {
    // Each subcommand's help is printed, which requires its argument definitions to be valid.
    for sub in ["import", "export", "generate", "inspect", "get"] {
        let o = isovox(&[sub, "--help"]);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            !stderr.contains("panicked"),
            "isovox {sub} --help panicked: {stderr}"
        );
        assert!(
            o.status.success(),
            "isovox {sub} --help failed: {}",
            show(&o)
        );
        assert!(
            String::from_utf8_lossy(&o.stdout).contains("Usage: isovox"),
            "isovox {sub} --help"
        );
    }
}

#[test]
fn generate_ellipsoid_then_inspect_reports_the_volume() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("e.vod");
    ok(&[
        "generate",
        "ellipsoid",
        "-o",
        s(&out),
        "--dims",
        "40,24,16",
        "--brick",
        "8",
    ]);
    // By hand: grids 5x3x2 = 30, 3x2x1 = 6, 2x1x1 = 2, 1x1x1 = 1: 39 bricks in 4 levels.
    assert_eq!(brick_count([40, 24, 16], 8), 39);
    assert_eq!(level_count([40, 24, 16], 8), 4);
    let j = inspect_json(&out);
    check_inspection(&j, &out, [40, 24, 16], "u8", 8);
    assert_eq!(j["bricks_total"], 39);
    // The ellipsoid fills the volume: the centre is solid, a corner is empty.
    let centre = ok(&["get", s(&out), "0", "2", "1", "1"]);
    let corner = ok(&["get", s(&out), "0", "0", "0", "0"]);
    assert_eq!(centre.len(), 512);
    assert!(centre.contains(&255), "no solid voxel at the centre");
    assert_eq!(corner[0], 0, "the corner voxel is outside the ellipsoid");
}

#[test]
fn generate_world_then_inspect_reports_the_volume() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("w.vod");
    ok(&[
        "generate",
        "world",
        "-o",
        s(&out),
        "--dims",
        "48,32,40",
        "--brick",
        "16",
        "--type",
        "u16",
        "--seed",
        "3",
    ]);
    // By hand: grids 3x2x3 = 18, 2x1x2 = 4, 1x1x1 = 1: 23 bricks in 3 levels.
    assert_eq!(brick_count([48, 32, 40], 16), 23);
    let j = inspect_json(&out);
    check_inspection(&j, &out, [48, 32, 40], "u16", 16);
    assert_eq!(j["bricks_total"], 23);
    assert_eq!(j["raw_bytes"], 48 * 32 * 40 * 2);
}

/// Writes `volume` as a RAW file.
fn write_raw(dir: &Path, name: &str, volume: &Grid, voxel_type: VoxelType) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, volume.to_bytes(voxel_type)).unwrap();
    p
}

#[test]
fn raw_import_then_export_gives_back_the_voxels() {
    let dir = tempfile::tempdir().unwrap();
    let volume = mixed_volume([37, 20, 11], VoxelType::U16, 61);
    let raw = write_raw(dir.path(), "in.raw", &volume, VoxelType::U16);
    let levels = pyramid(&volume, 8);
    for codec in ["zstd", "lz4", "none"] {
        let vod = dir.path().join(format!("{codec}.vod"));
        ok(&[
            "import",
            s(&raw),
            "-o",
            s(&vod),
            "--dims",
            "37,20,11",
            "--type",
            "u16",
            "--brick",
            "8",
            "--codec",
            codec,
        ]);
        let j = inspect_json(&vod);
        check_inspection(&j, &vod, [37, 20, 11], "u16", 8);
        let back = dir.path().join(format!("{codec}.raw"));
        ok(&["export", s(&vod), "-o", s(&back)]);
        assert!(
            std::fs::read(&back).unwrap() == volume.to_bytes(VoxelType::U16),
            "{codec}: export differs from the RAW imported"
        );
        // Level 1 as a whole, and a region of level 0.
        let l1 = dir.path().join(format!("{codec}.l1.raw"));
        ok(&["export", s(&vod), "-o", s(&l1), "--level", "1"]);
        assert!(
            std::fs::read(&l1).unwrap() == levels[1].to_bytes(VoxelType::U16),
            "{codec}: level 1 differs from the independent downsampling"
        );
        let region = dir.path().join(format!("{codec}.region.raw"));
        ok(&[
            "export",
            s(&vod),
            "-o",
            s(&region),
            "--region",
            "3,5,2,36,19,10",
        ]);
        assert!(
            std::fs::read(&region).unwrap()
                == volume.slice([3, 5, 2], [36, 19, 10], VoxelType::U16),
            "{codec}: region export differs from the slice"
        );
    }
}

/// A RAWVOX file: five little-endian i32 (magic 0x52564F58, x, y, z, bits), then the voxels.
fn write_rawvox(dir: &Path, name: &str, volume: &Grid, voxel_type: VoxelType) -> PathBuf {
    let p = dir.join(name);
    let mut b = Vec::new();
    for field in [
        0x5256_4F58,
        volume.dims[0] as i32,
        volume.dims[1] as i32,
        volume.dims[2] as i32,
        8 * voxel_type.bytes() as i32,
    ] {
        b.extend_from_slice(&i32::to_le_bytes(field));
    }
    assert_eq!(&b[..4], b"XOVR");
    b.extend_from_slice(&volume.to_bytes(voxel_type));
    std::fs::write(&p, b).unwrap();
    p
}

#[test]
fn rawvox_import_takes_its_shape_from_the_header() {
    let dir = tempfile::tempdir().unwrap();
    for (voxel_type, bits) in [(VoxelType::U8, 8i32), (VoxelType::U16, 16)] {
        let volume = mixed_volume([19, 7, 13], voxel_type, 62);
        let input = write_rawvox(dir.path(), "in.rawvox", &volume, voxel_type);
        let vod = dir.path().join("v.vod");
        ok(&["import", s(&input), "-o", s(&vod), "--brick", "4"]);
        let j = inspect_json(&vod);
        check_inspection(&j, &vod, [19, 7, 13], voxel_type.name(), 4);
        let back = dir.path().join("back.raw");
        ok(&["export", s(&vod), "-o", s(&back)]);
        assert!(
            std::fs::read(&back).unwrap() == volume.to_bytes(voxel_type),
            "{voxel_type}: RAWVOX voxels differ after the round trip"
        );
        // Exported as RAWVOX again: the same header and voxels.
        let again = dir.path().join("again.rawvox");
        ok(&["export", s(&vod), "-o", s(&again), "--format", "rawvox"]);
        let a = std::fs::read(&again).unwrap();
        let fields: Vec<i32> = a[..20]
            .chunks_exact(4)
            .map(|c| i32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(fields, vec![0x5256_4F58, 19, 7, 13, bits]);
        assert!(
            a == std::fs::read(&input).unwrap(),
            "{voxel_type}: RAWVOX export differs from the input"
        );
    }
}

#[test]
fn get_writes_the_brick_sliced_from_the_raw() {
    let dir = tempfile::tempdir().unwrap();
    let volume = mixed_volume([37, 20, 11], VoxelType::U16, 63);
    let raw = write_raw(dir.path(), "in.raw", &volume, VoxelType::U16);
    let vod = dir.path().join("v.vod");
    ok(&[
        "import",
        s(&raw),
        "-o",
        s(&vod),
        "--dims",
        "37,20,11",
        "--type",
        "u16",
        "--brick",
        "8",
    ]);
    let levels = pyramid(&volume, 8);
    // Level 0 grid is 5x3x2; (4, 2, 1) is the far corner, mostly L padding.
    for (l, x, y, z) in [
        (0u8, 0u32, 0u32, 0u32),
        (0, 2, 1, 0),
        (0, 4, 2, 1),
        (0, 4, 0, 0),
        (1, 2, 1, 0),
        (2, 1, 0, 0),
        (3, 0, 0, 0),
    ] {
        let args = [l, x as u8, y as u8, z as u8].map(|v| v.to_string());
        let got = ok(&["get", s(&vod), &args[0], &args[1], &args[2], &args[3]]);
        let expected =
            levels[l as usize].brick([x as usize, y as usize, z as usize], 8, VoxelType::U16);
        assert_eq!(got.len(), 8 * 8 * 8 * 2);
        assert!(got == expected, "get {l} {x} {y} {z} differs from the RAW");
    }
    let file = dir.path().join("brick.bin");
    ok(&["get", s(&vod), "0", "4", "2", "1", "-o", s(&file)]);
    assert!(std::fs::read(&file).unwrap() == levels[0].brick([4, 2, 1], 8, VoxelType::U16));
}

#[test]
fn vod1_import_and_export_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let volume = mixed_volume([30, 17, 9], VoxelType::U8, 64);
    let raw = write_raw(dir.path(), "in.raw", &volume, VoxelType::U8);
    let a = dir.path().join("a.vod1");
    ok(&[
        "import",
        s(&raw),
        "-o",
        s(&a),
        "--dims",
        "30,17,9",
        "--brick",
        "4",
        "--format",
        "vod1",
    ]);
    let a_bytes = std::fs::read(&a).unwrap();
    assert_eq!(&a_bytes[..8], &[b'.', b'V', b'O', b'D', 1, 0, 0, 0]);
    let j = inspect_json(&a);
    assert_eq!(j["dims"], serde_json::json!([30, 17, 9]), "{j}");
    assert_eq!(j["voxel_type"], "u8");
    assert_eq!(j["brick"], 4);
    assert_eq!(j["version"], 1);
    assert_eq!(j["file_bytes"], a_bytes.len());
    assert_eq!(j["raw_bytes"], 30 * 17 * 9);
    for field in ["levels", "bricks_total", "bricks_unique", "ratio"] {
        assert!(j.get(field).is_some(), "VOD 1 inspect lacks {field}: {j}");
    }
    // `get` reads VOD 1 too.
    let levels = pyramid(&volume, 4);
    for (l, x, y, z) in [
        (0u8, 0usize, 0usize, 0usize),
        (0, 7, 4, 2),
        (1, 3, 2, 1),
        (2, 1, 1, 0),
    ] {
        let args = [l as usize, x, y, z].map(|v| v.to_string());
        let got = ok(&["get", s(&a), &args[0], &args[1], &args[2], &args[3]]);
        assert!(
            got == levels[l as usize].brick([x, y, z], 4, VoxelType::U8),
            "VOD 1 get {l} {x} {y} {z}"
        );
    }
    // VOD 1 -> VOD 2 -> RAW, and VOD 2 -> VOD 1 again, byte for byte.
    let b = dir.path().join("b.vod");
    ok(&["import", s(&a), "-o", s(&b)]);
    let back = dir.path().join("back.raw");
    ok(&["export", s(&b), "-o", s(&back)]);
    assert!(std::fs::read(&back).unwrap() == volume.to_bytes(VoxelType::U8));
    let c = dir.path().join("c.vod1");
    ok(&["export", s(&b), "-o", s(&c), "--format", "vod1"]);
    assert!(
        std::fs::read(&c).unwrap() == a_bytes,
        "VOD 1 written by import and by export differ"
    );
}

/// A small imported volume for the error cases.
fn small_vod(dir: &Path) -> PathBuf {
    let volume = mixed_volume([20, 12, 9], VoxelType::U8, 65);
    let raw = write_raw(dir, "small.raw", &volume, VoxelType::U8);
    let vod = dir.join("small.vod");
    ok(&[
        "import",
        s(&raw),
        "-o",
        s(&vod),
        "--dims",
        "20,12,9",
        "--brick",
        "4",
        "--codec",
        "none",
    ]);
    vod
}

#[test]
fn bad_raw_input_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("in.raw");
    std::fs::write(&raw, vec![7u8; 999]).unwrap();
    let out = dir.path().join("out.vod");
    let e = fails(&["import", s(&raw), "-o", s(&out)]);
    assert!(e.contains("--dims"), "{e}");
    let e = fails(&["import", s(&raw), "-o", s(&out), "--dims", "10,10,10"]);
    assert!(e.contains("999"), "the message names the size: {e}");
    fails(&[
        "import",
        s(&raw),
        "-o",
        s(&out),
        "--dims",
        "999,1,1",
        "--type",
        "u16",
    ]);
    assert!(!out.exists(), "a failed import leaves no output");
    let rawvox = dir.path().join("short.rawvox");
    std::fs::write(&rawvox, [0x58, 0x4F, 0x56, 0x52, 1, 0, 0, 0]).unwrap();
    fails(&["import", s(&rawvox), "-o", s(&out)]);
}

#[test]
fn missing_input_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.raw");
    let out = dir.path().join("out.vod");
    fails(&["import", s(&missing), "-o", s(&out), "--dims", "1,1,1"]);
    fails(&["inspect", s(&missing)]);
    fails(&["export", s(&missing), "-o", s(&out)]);
    fails(&["get", s(&missing), "0", "0", "0", "0"]);
}

#[test]
fn errors_name_the_file_once_and_signatures_as_text() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.vod");
    let (m, raw, glb) = (
        s(&missing),
        dir.path().join("out.raw"),
        dir.path().join("out.glb"),
    );
    for args in [
        vec!["inspect", m],
        vec!["get", m, "0", "0", "0", "0"],
        vec!["export", m, "-o", s(&raw)],
        vec!["mesh", m, "-o", s(&glb)],
        vec!["compact", m],
    ] {
        let e = fails(&args);
        assert_eq!(e.matches(m).count(), 1, "{args:?} names the file once: {e}");
        assert!(e.contains("No such file"), "{args:?}: {e}");
    }
    // A file that is not VOD 2 at all: its signature is printed as text, escapes for the bytes
    // that are not printable, as the format's documentation writes it (".VOD").
    let vod = small_vod(dir.path());
    let mut b = std::fs::read(&vod).unwrap();
    b[..4].copy_from_slice(b"PK\x03\x04");
    let zip = dir.path().join("zip.vod");
    std::fs::write(&zip, &b).unwrap();
    for args in [
        vec!["get", s(&zip), "0", "0", "0", "0"],
        vec!["mesh", s(&zip), "-o", s(&glb)],
    ] {
        let e = fails(&args);
        assert!(
            e.contains(r#"bad signature: expected ".VOD", found "PK\x03\x04""#),
            "{args:?}: {e}"
        );
        assert_eq!(e.matches(s(&zip)).count(), 1, "{args:?}: {e}");
    }
}

#[test]
fn get_outside_the_volume_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let vod = small_vod(dir.path());
    // Level 0 grid is 5x3x3; there are 4 levels.
    ok(&["get", s(&vod), "0", "4", "2", "2"]);
    fails(&["get", s(&vod), "0", "5", "0", "0"]);
    fails(&["get", s(&vod), "0", "0", "3", "0"]);
    fails(&["get", s(&vod), "1", "0", "0", "2"]);
    fails(&["get", s(&vod), "4", "0", "0", "0"]);
    fails(&[
        "export",
        s(&vod),
        "-o",
        s(&dir.path().join("x.raw")),
        "--level",
        "4",
    ]);
}

#[test]
fn damaged_files_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let vod = small_vod(dir.path());
    let good = std::fs::read(&vod).unwrap();
    let damaged = dir.path().join("damaged.vod");
    let out = dir.path().join("out.raw");

    // A flipped byte in the file header (covered by its checksum).
    let mut b = good.clone();
    b[20] ^= 0x01;
    std::fs::write(&damaged, &b).unwrap();
    fails(&["inspect", s(&damaged)]);
    fails(&["get", s(&damaged), "0", "0", "0", "0"]);
    fails(&["export", s(&damaged), "-o", s(&out)]);

    // Cut short: both slots name more bytes than the file has.
    std::fs::write(&damaged, &good[..good.len() - 1]).unwrap();
    fails(&["inspect", s(&damaged)]);
    std::fs::write(&damaged, &good[..100]).unwrap();
    fails(&["inspect", s(&damaged)]);

    // A flipped voxel in a stored (raw) brick: that brick and the export fail, others work.
    let snap = isovox_server::store::Vod2::open(&vod).unwrap().head();
    let key = snap.layout().key(0, 4, 1, 1).unwrap();
    let payload_at = match snap.stored(key).unwrap() {
        isovox_server::store::StoredBrick::Record { offset, .. } => offset as usize + 24,
        isovox_server::store::StoredBrick::Constant(_) => panic!("brick (4,1,1) is noise"),
    };
    let mut b = good.clone();
    b[payload_at + 10] ^= 0x40;
    std::fs::write(&damaged, &b).unwrap();
    let e = fails(&["get", s(&damaged), "0", "4", "1", "1"]);
    assert!(e.contains("hash"), "the message names the problem: {e}");
    fails(&["export", s(&damaged), "-o", s(&out)]);
    ok(&["get", s(&damaged), "0", "0", "0", "0"]);

    // Not a VOD file at all.
    std::fs::write(&damaged, b"hello, this is not a volume").unwrap();
    fails(&["inspect", s(&damaged)]);
    // A VOD 1 file cut short.
    let vod1 = dir.path().join("v.vod1");
    ok(&["export", s(&vod), "-o", s(&vod1), "--format", "vod1"]);
    let v1 = std::fs::read(&vod1).unwrap();
    std::fs::write(&damaged, &v1[..v1.len() / 2]).unwrap();
    fails(&["inspect", s(&damaged)]);
    fails(&["get", s(&damaged), "0", "0", "0", "0"]);
    fails(&["import", s(&damaged), "-o", s(&dir.path().join("y.vod"))]);
}

#[test]
fn dimensions_whose_voxel_count_overflows_are_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.vod");
    let raw = dir.path().join("in.raw");
    std::fs::write(&raw, b"abc").unwrap();
    fails(&[
        "import",
        s(&raw),
        "-o",
        s(&out),
        "--dims",
        "4294967295,4294967295,4294967295",
    ]);
    // The same through a RAWVOX header: 2^31 - 1 voxels per side.
    let rawvox = dir.path().join("huge.rawvox");
    let mut b = Vec::new();
    for f in [0x5256_4F58, i32::MAX, i32::MAX, i32::MAX, 8] {
        b.extend_from_slice(&i32::to_le_bytes(f));
    }
    b.extend_from_slice(b"abc");
    std::fs::write(&rawvox, b).unwrap();
    fails(&["import", s(&rawvox), "-o", s(&out)]);
}

#[test]
fn output_to_a_reader_that_has_gone_ends_quietly() {
    // `isovox inspect f.vod | head -1` used to panic when `head` had exited before the next
    // line was written. Here the reader is gone before the first: every write fails.
    let dir = tempfile::tempdir().unwrap();
    let vod = small_vod(dir.path());
    let f = s(&vod);
    for args in [
        vec!["inspect", f],
        vec!["inspect", "--json", f],
        vec!["check", f],
        vec!["check", "--json", f],
        vec!["get", f, "0", "0", "0", "0"],
    ] {
        for _ in 0..3 {
            let mut child = Command::new(env!("CARGO_BIN_EXE_isovox"))
                .args(&args)
                .env_remove("ISOVOX_LOG")
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap();
            drop(child.stdout.take());
            let o = child.wait_with_output().unwrap();
            let stderr = String::from_utf8_lossy(&o.stderr);
            assert!(!stderr.contains("panicked"), "isovox {args:?}: {stderr}");
            assert!(stderr.is_empty(), "isovox {args:?}: {stderr}");
            assert!(o.status.success(), "isovox {args:?}: {}", show(&o));
        }
    }
}

/// `isovox mesh --camera` writes one stitched mesh: a GLB with one plain primitive (no extras),
/// tiles of several levels joined by their transition strips, closed once equal positions are
/// welded (every edge in exactly two triangles, once each way).
#[test]
fn mesh_with_a_camera_writes_one_closed_stitched_glb() {
    let dir = tempfile::tempdir().unwrap();
    let vod = dir.path().join("w.vod");
    ok(&[
        "generate",
        "world",
        "-o",
        s(&vod),
        "--dims",
        "96,64,96",
        "--brick",
        "8",
        "--seed",
        "5",
    ]);
    let glb = dir.path().join("w.glb");
    ok(&[
        "mesh",
        s(&vod),
        "-o",
        s(&glb),
        "--camera",
        "0,64,0",
        "--radii",
        "16,32,64",
    ]);
    let bytes = std::fs::read(&glb).unwrap();
    let gltf = gltf::Gltf::from_slice(&bytes).unwrap();
    let doc = &gltf.document;
    assert_eq!(doc.meshes().count(), 1);
    let mesh = doc.meshes().next().unwrap();
    let json_len = u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]) as usize;
    let json: Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
    assert!(
        json["meshes"][0].get("extras").is_none(),
        "a stitched GLB is a plain mesh"
    );
    assert_eq!(mesh.primitives().count(), 1);
    let prim = mesh.primitives().next().unwrap();
    let blob = gltf.blob.as_deref().unwrap();
    let reader = prim.reader(|_| Some(blob));
    let positions: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
    let indices: Vec<u32> = reader.read_indices().unwrap().into_u32().collect();
    assert!(indices.len() > 3000, "{} indices", indices.len());
    // Welded here by bits, independently of the server's weld.
    let mut ids = std::collections::HashMap::new();
    let id: Vec<usize> = positions
        .iter()
        .map(|p| {
            let n = ids.len();
            *ids.entry(p.map(f32::to_bits)).or_insert(n)
        })
        .collect();
    let mut edges = std::collections::HashMap::new();
    for t in indices.chunks_exact(3) {
        let v = [0, 1, 2].map(|k| id[t[k] as usize]);
        assert!(
            v[0] != v[1] && v[1] != v[2] && v[0] != v[2],
            "a degenerate triangle"
        );
        for k in 0..3 {
            *edges.entry((v[k], v[(k + 1) % 3])).or_insert(0u32) += 1;
        }
    }
    let open = edges
        .iter()
        .filter(|(&(a, b), &n)| n != 1 || edges.get(&(b, a)) != Some(&1))
        .count();
    assert_eq!(open, 0, "open or repeated edges in the stitched mesh");
}

/// Runs `isovox edit` with `stdin` as its standard input; must succeed; returns the JSON it
/// prints and its stderr.
fn edit_json(args: &[&str], stdin: Option<&str>) -> (Value, String) {
    use std::io::Write;
    let mut child = Command::new(env!("CARGO_BIN_EXE_isovox"))
        .args(args)
        .env_remove("ISOVOX_LOG")
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut input = child.stdin.take().unwrap();
    input.write_all(stdin.unwrap_or("").as_bytes()).unwrap();
    drop(input);
    let o = child.wait_with_output().unwrap();
    assert!(o.status.success(), "isovox {args:?} failed: {}", show(&o));
    let json = serde_json::from_slice(&o.stdout).unwrap_or_else(|e| {
        panic!("{e}: {}", String::from_utf8_lossy(&o.stdout));
    });
    (json, String::from_utf8_lossy(&o.stderr).into_owned())
}

/// `isovox edit FILE '{...}'`, as `edit --help` shows it, takes the JSON inline; a path to a
/// JSON file and `-` (stdin) work too. The JSON printed names the time `elapsed_us`, as the
/// HTTP answer does.
#[test]
fn edit_takes_inline_json_a_file_or_stdin() {
    let dir = tempfile::tempdir().unwrap();
    let vod = small_vod(dir.path());
    let body = r#"{"op": "union", "term": {"cuboid": {"origin": [0, 0, 0], "size": [4, 4, 4]}}}"#;
    let (j, _) = edit_json(&["edit", s(&vod), body], None);
    assert_eq!(j["version"], 2, "{j}");
    assert_eq!(j["committed"], true, "{j}");
    assert!(
        j["elapsed_us"].is_u64() && j.get("elapsed").is_none(),
        "{j}"
    );
    let file = dir.path().join("edit.json");
    std::fs::write(&file, body).unwrap();
    let (j, _) = edit_json(&["edit", s(&vod), s(&file)], None);
    assert_eq!(j["version"], 3, "{j}");
    let (j, _) = edit_json(&["edit", s(&vod), "-"], Some(body));
    assert_eq!(j["version"], 4, "{j}");
    assert_eq!(inspect_json(&vod)["version"], 4);

    let help = String::from_utf8(ok(&["edit", "--help"])).unwrap();
    assert!(help.contains("inline JSON"), "{help}");
    let missing = dir.path().join("missing.json");
    let e = fails(&["edit", s(&vod), s(&missing)]);
    assert!(
        e.contains("cannot read the edit file") && e.contains("missing.json"),
        "{e}"
    );
    let e = fails(&["edit", s(&vod), "{\"op\": \"union\""]);
    assert!(e.contains("not a valid edit request"), "{e}");
    assert_eq!(
        inspect_json(&vod)["version"],
        4,
        "failed edits commit nothing"
    );
}

/// An edit wholly outside the volume (20 x 12 x 9 voxels) commits nothing: the file is not
/// touched, the JSON names the current version with `"committed": false`, stderr says why.
#[test]
fn an_edit_outside_the_volume_commits_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let vod = small_vod(dir.path());
    let before = std::fs::read(&vod).unwrap();
    let (j, stderr) = edit_json(
        &["edit", s(&vod), "--op", "union", "--cuboid", "24,0,0,4,4,4"],
        None,
    );
    assert_eq!(j["committed"], false, "{j}");
    assert_eq!(j["version"], 1, "{j}");
    assert_eq!(j["evaluated"], 0, "{j}");
    assert!(stderr.contains("nothing changed"), "{stderr}");
    assert!(
        std::fs::read(&vod).unwrap() == before,
        "the file is untouched"
    );
    assert_eq!(inspect_json(&vod)["version"], 1);
}

/// `export` says what it wrote: the file, version, level, voxels and bytes (for a 20 x 12 x 9
/// u8 volume: 2160 bytes; RAWVOX adds its 20-byte header; level 1 is 10 x 6 x 5).
#[test]
fn export_says_what_it_wrote() {
    let dir = tempfile::tempdir().unwrap();
    let vod = small_vod(dir.path());
    let text = |args: &[&str]| String::from_utf8(ok(args)).unwrap();
    let raw = dir.path().join("out.raw");
    let said = text(&["export", s(&vod), "-o", s(&raw)]);
    assert!(said.starts_with(s(&raw)), "{said}");
    assert!(
        said.contains("RAW of version 1, level 0")
            && said.contains("(20 x 12 x 9)")
            && said.contains(": 2160 bytes"),
        "{said}"
    );
    let rawvox = dir.path().join("out.rawvox");
    let said = text(&[
        "export",
        s(&vod),
        "-o",
        s(&rawvox),
        "--format",
        "rawvox",
        "--level",
        "1",
    ]);
    assert!(
        said.contains("RAWVOX of version 1, level 1")
            && said.contains("(10 x 6 x 5)")
            && said.contains(": 320 bytes"),
        "{said}"
    );
    let region = dir.path().join("region.raw");
    let said = text(&[
        "export",
        s(&vod),
        "-o",
        s(&region),
        "--region",
        "1,2,3,5,6,7",
    ]);
    assert!(
        said.contains("voxels 1,2,3..5,6,7 (4 x 4 x 4): 64 bytes"),
        "{said}"
    );
    let vod1 = dir.path().join("out.vod1");
    let said = text(&["export", s(&vod), "-o", s(&vod1), "--format", "vod1"]);
    let bytes = std::fs::metadata(&vod1).unwrap().len();
    assert!(
        said.contains("VOD 1 of version 1") && said.contains(&format!(": {bytes} bytes")),
        "{said}"
    );
}

/// The text `--help` gives the argument whose line starts with `spec` (`<LEVEL>`,
/// `--type <VOXEL_TYPE>`): on that line after it, or (clap's layout for long help) on the next.
fn help_of(help: &str, spec: &str) -> String {
    let lines: Vec<&str> = help.lines().collect();
    let at = lines
        .iter()
        .position(|l| {
            let l = l.trim_start();
            l.starts_with(spec)
                || l.split_once(", ")
                    .is_some_and(|(_, long)| long.starts_with(spec))
        })
        .unwrap_or_else(|| panic!("no {spec:?} in {help}"));
    let rest = lines[at].trim_start();
    let rest = rest[rest.find(spec).unwrap() + spec.len()..].trim();
    if rest.is_empty() {
        lines
            .get(at + 1)
            .map(|l| l.trim())
            .unwrap_or_default()
            .to_string()
    } else {
        rest.to_string()
    }
}

/// The arguments that had no help text have one in `--help`.
#[test]
fn arguments_have_help_text() {
    let help = |sub: &str| String::from_utf8(ok(&[sub, "--help"])).unwrap();
    let cases: [(&str, &str, &str); 9] = [
        ("get", "<LEVEL>", "Level of detail"),
        ("get", "<X>", "The brick's x"),
        ("get", "<Y>", "The brick's y"),
        ("get", "<Z>", "The brick's z"),
        ("voxelize", "--output <OUTPUT>", "Output VOD 2 file"),
        ("voxelize", "--type <VOXEL_TYPE>", "Voxel type"),
        ("voxelize", "--brick <BRICK>", "Brick edge"),
        (
            "voxelize",
            "--fill <FILL>",
            "How a voxel's value is decided",
        ),
        ("generate", "--type <VOXEL_TYPE>", "Voxel type"),
    ];
    for (sub, spec, text) in cases {
        let said = help_of(&help(sub), spec);
        assert!(said.starts_with(text), "{sub} {spec}: {said:?}");
    }
}

/// `serve` on a port that is taken fails before it creates anything: no data directory, demo
/// world or token file left behind.
#[test]
fn serve_on_a_port_in_use_leaves_nothing_behind() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let o = Command::new(env!("CARGO_BIN_EXE_isovox"))
        .args(["serve", "--data", s(&data), "--addr", &addr])
        .env_remove("ISOVOX_LOG")
        .env_remove("ISOVOX_TOKEN_FILE")
        .env_remove("ISOVOX_WRITE_TOKEN")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "served on a taken port: {stderr}");
    assert!(stderr.contains("cannot listen on"), "{stderr}");
    assert!(!data.exists(), "{} was created", data.display());
    drop(taken);
}

/// `serve --data` naming a directory that does not exist (a typo) says that it created one,
/// naming it, rather than serving a fresh demo world in silence.
#[test]
fn serve_says_when_it_creates_a_data_directory() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("typo");
    let mut server =
        server_process::ServerProcess::start(&["--data".as_ref(), data.as_os_str()], &[]);
    let log = server.stop();
    assert!(
        log.contains("created a new, empty data directory") && log.contains("typo"),
        "{log}"
    );
    assert!(data.join("demo.vod").exists());
    // A second start on the same directory says nothing of the kind.
    let mut again =
        server_process::ServerProcess::start(&["--data".as_ref(), data.as_os_str()], &[]);
    let log = again.stop();
    assert!(!log.contains("created a new"), "{log}");
}
