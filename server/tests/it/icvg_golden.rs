//! Golden values of the ICVG algebra, computed by hand from `docs/icvg.md` (the computation of
//! each value is in the comment beside it; none is copied from the code's output).
//!
//! Value ranges: u8 L = 0, H = 255, S = floor(255 / 2) = 127; u16 L = 0, H = 65535, S = 32767.

use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::VoxelType;
use isovox_server::geometry::Box3;
use isovox_server::icvg::edit::{Edit, EditKind};
use isovox_server::icvg::ops::{BinaryOp, Outside, UnaryOp};
use isovox_server::icvg::primitives::{
    Capsule, Cone, Cuboid, Cylinder, Ellipsoid, Primitive, Prism, Pyramid, Torus,
};
use isovox_server::icvg::term::{CompiledTerm, NoVolumes, TermLimits};

const U8: VoxelType = VoxelType::U8;
const U16: VoxelType = VoxelType::U16;

fn compile(json: &str, t: VoxelType) -> CompiledTerm {
    let term: Term = serde_json::from_str(json).unwrap();
    CompiledTerm::compile(&term, t, &TermLimits::default(), &NoVolumes).unwrap()
}

fn compile_err(json: &str) -> String {
    let term: Term = serde_json::from_str(json).unwrap();
    match CompiledTerm::compile(&term, U8, &TermLimits::default(), &NoVolumes) {
        Ok(_) => panic!("{json} compiled, expected an error"),
        Err(e) => e.to_string(),
    }
}

fn edit_err(json: &str) -> String {
    let req: EditRequest = serde_json::from_str(json).unwrap();
    match Edit::from_request(&req, U8, &TermLimits::default(), &NoVolumes) {
        Ok(_) => panic!("{json} was accepted, expected an error"),
        Err(e) => e.to_string(),
    }
}

// ---------------------------------------------------------------------------------------------
// Cuboid
// ---------------------------------------------------------------------------------------------

/// Cuboid origin (10, 20, 30), size (6, 7, 8): local x in 0..=5 (last 5), y in 0..=6 (last 6),
/// z in 0..=7 (last 7). L on local 0 / B-1, else S on local 1 / B-2, else H.
fn check_cuboid(t: VoxelType, s: u16, h: u16) {
    let c = Cuboid {
        origin: [10, 20, 30],
        size: [6, 7, 8],
    };
    let json = compile(
        r#"{"cuboid": {"origin": [10, 20, 30], "size": [6, 7, 8]}}"#,
        t,
    );
    // B-box: origin .. origin + size.
    assert_eq!(c.bbox(), Box3::new([10, 20, 30], [16, 27, 38]));
    assert_eq!(json.bbox, Some(Box3::new([10, 20, 30], [16, 27, 38])));
    let o = [10i64, 20, 30];
    let cases: &[([i64; 3], u16, &str)] = &[
        ([2, 3, 3], h, "interior: no coordinate is 0, 1, B-2 or B-1"),
        (
            [3, 4, 5],
            h,
            "interior, the other corner of the H block (B-3 on every axis)",
        ),
        ([1, 3, 3], s, "x = 1: S layer"),
        ([4, 3, 3], s, "x = B-2 = 4: S layer"),
        ([2, 1, 3], s, "y = 1: bottom S layer"),
        ([2, 5, 3], s, "y = B-2 = 5: top S layer"),
        ([3, 3, 1], s, "z = 1: S layer"),
        ([3, 3, 6], s, "z = B-2 = 6: S layer"),
        ([1, 1, 1], s, "corner of the S layer"),
        ([4, 5, 6], s, "far corner of the S layer"),
        ([0, 3, 3], 0, "x = 0: padding L"),
        ([5, 3, 3], 0, "x = B-1 = 5: padding L"),
        ([2, 0, 3], 0, "y = 0: bottom padding L"),
        ([2, 6, 3], 0, "y = B-1 = 6: top padding L"),
        ([3, 3, 0], 0, "z = 0: padding L"),
        ([3, 3, 7], 0, "z = B-1 = 7: padding L"),
        ([0, 1, 1], 0, "padding wins over the S layer"),
        ([6, 3, 3], 0, "outside the extension space"),
        ([-1, 3, 3], 0, "outside the extension space"),
        ([2, 7, 3], 0, "outside the extension space"),
    ];
    for (local, want, why) in cases {
        let v = [0, 1, 2].map(|a| o[a] + local[a]);
        assert_eq!(c.sample(v, t), *want, "{t} cuboid local {local:?}: {why}");
        assert_eq!(
            json.sample(v),
            *want,
            "{t} cuboid term local {local:?}: {why}"
        );
    }
    // Counts: 6*7*8 = 336 voxels; inside the padding (4*5*6 = 120), inside the S layer
    // (2*3*4 = 24) H; so 24 H, 120 - 24 = 96 S, 336 - 120 = 216 L.
    let (mut nh, mut ns, mut nl) = (0, 0, 0);
    for z in 30..38 {
        for y in 20..27 {
            for x in 10..16 {
                match c.sample([x, y, z], t) {
                    v if v == h => nh += 1,
                    v if v == s => ns += 1,
                    0 => nl += 1,
                    v => panic!("{t} cuboid value {v} is none of L, S, H"),
                }
            }
        }
    }
    assert_eq!((nh, ns, nl), (24, 96, 216), "{t} cuboid counts (H, S, L)");
}

#[test]
fn cuboid_golden_u8() {
    check_cuboid(U8, 127, 255);
}

#[test]
fn cuboid_golden_u16() {
    check_cuboid(U16, 32767, 65535);
}

// ---------------------------------------------------------------------------------------------
// Ellipsoid
// ---------------------------------------------------------------------------------------------

/// Ellipsoid centre (10, -5, 7), radii R = (5, 3, 4):
/// body(P) = Px²/25 + Py²/9 + Pz²/16. Entries: offset T from the centre, u8 value, u16 value.
const ELLIPSOID: &[([i64; 3], u16, u16, &str)] = &[
    // T = 0: T^ = 0, body(T + T^) = 0 < 1.
    ([0, 0, 0], 255, 65535, "centre: H"),
    // T = (3,0,0): body(T + T^) = body(4,0,0) = 16/25 = 0.64 < 1.
    ([3, 0, 0], 255, 65535, "one step in from the band: H"),
    // T = (4,0,0): body(5,0,0) = 1, not < 1; body(3,0,0) = 0.36, not > 1;
    // band: body(T) = 16/25 = 0.64; 127 / 0.64 = 198.44 -> 198; 32767 / 0.64 = 51198.44 -> 51198.
    ([4, 0, 0], 198, 51198, "band inside the surface"),
    // T = (5,0,0): body(6,0,0) = 1.44; body(4,0,0) = 0.64 not > 1; band: body(T) = 1 -> S.
    ([5, 0, 0], 127, 32767, "on the surface, x axis: S"),
    ([-5, 0, 0], 127, 32767, "on the surface, -x: S (symmetric)"),
    // T = (0,3,0): body(0,4,0) = 16/9; body(0,2,0) = 4/9; band body(T) = 9/9 = 1 -> S.
    ([0, 3, 0], 127, 32767, "on the surface, y axis: S"),
    // T = (0,2,0): body(0,3,0) = 1, not < 1; body(0,1,0) = 1/9; band body(T) = 4/9:
    // 127 * 9/4 = 285.75 -> min(255, 285) = 255; 32767 * 9/4 = 73725.75 -> min(65535, ..).
    ([0, 2, 0], 255, 65535, "band value clamped to H"),
    // T = (0,0,4): body(0,0,5) = 25/16; body(0,0,3) = 9/16; band body(T) = 1 -> S.
    ([0, 0, 4], 127, 32767, "on the surface, z axis: S"),
    // T = (0,0,3): body(0,0,4) = 1 not < 1; band body(T) = 9/16 = 0.5625:
    // 127 * 16/9 = 225.78 -> 225; 32767 * 16/9 = 58252.44 -> 58252.
    ([0, 0, 3], 225, 58252, "band, z axis"),
    // T = (3,2,2): body(T) = 9/25 + 4/9 + 4/16 = (1296 + 1600 + 900) / 3600 = 3796/3600.
    // |T| = sqrt(17) = 4.1231, T^ = (0.7276, 0.4851, 0.4851);
    // T - T^ = (2.2724, 1.5149, 1.5149): body = 0.2066 + 0.2550 + 0.1434 = 0.605 (not > 1);
    // T + T^ = (3.7276, 2.4851, 2.4851): body = 0.5558 + 0.6862 + 0.3860 = 1.628 (not < 1);
    // band: 127 * 3600/3796 = 120.44 -> 120; 32767 * 3600/3796 = 31075.13 -> 31075.
    ([3, 2, 2], 120, 31075, "off-axis band voxel"),
    ([-3, -2, -2], 120, 31075, "its mirror image"),
    // T = (4,2,0): body(T) = 16/25 + 4/9 = 0.64 + 0.4444 = 1.0844 (976/900).
    // |T| = sqrt(20), T^ = (0.8944, 0.4472, 0); T - T^ = (3.1056, 1.5528, 0):
    // body = 0.3858 + 0.2679 = 0.654 (not > 1); T + T^ = (4.894, 2.447, 0): body = 1.62.
    // band: 127 * 900/976 = 117.11 -> 117; 32767 * 900/976 = 30215.47 -> 30215.
    ([4, 2, 0], 117, 30215, "band just outside the surface"),
    // T = (0,3,2): body(T) = 1 + 4/16 = 1.25; |T| = sqrt(13), T^ = (0, 0.8321, 0.5547);
    // T - T^ = (0, 2.1679, 1.4453): body = 0.5222 + 0.1306 = 0.653 (not > 1);
    // band: 127 / 1.25 = 101.6 -> 101; 32767 / 1.25 = 26213.6 -> 26213.
    ([0, 3, 2], 101, 26213, "band outside the surface, y-z plane"),
    // T = (5,3,0): |T| = sqrt(34) = 5.831, T^ = (0.8575, 0.5145, 0);
    // T - T^ = (4.1425, 2.4855, 0): body = 17.160/25 + 6.178/9 = 0.6864 + 0.6864 = 1.373 > 1.
    ([5, 3, 0], 0, 0, "exterior corner: L"),
    // T = (6,0,0): outside the extension space (x from 10-5 = 5 to 10+5 = 15).
    ([6, 0, 0], 0, 0, "outside the extension space: L"),
    ([0, -4, 0], 0, 0, "outside the extension space: L"),
];

#[test]
fn ellipsoid_golden() {
    let c = [10i64, -5, 7];
    let e = Ellipsoid {
        center: c,
        radii: [5, 3, 4],
    };
    // B-box: centre - R .. centre + R + 1 = (5, -8, 3) .. (16, -1, 12).
    assert_eq!(e.bbox(), Box3::new([5, -8, 3], [16, -1, 12]));
    let json = r#"{"ellipsoid": {"center": [10, -5, 7], "radii": [5, 3, 4]}}"#;
    let (j8, j16) = (compile(json, U8), compile(json, U16));
    assert_eq!(j8.bbox, Some(Box3::new([5, -8, 3], [16, -1, 12])));
    for (tt, want8, want16, why) in ELLIPSOID {
        let v = [0, 1, 2].map(|a| c[a] + tt[a]);
        assert_eq!(e.sample(v, U8), *want8, "u8 ellipsoid T = {tt:?}: {why}");
        assert_eq!(e.sample(v, U16), *want16, "u16 ellipsoid T = {tt:?}: {why}");
        assert_eq!(j8.sample(v), *want8, "u8 ellipsoid term T = {tt:?}: {why}");
        assert_eq!(
            j16.sample(v),
            *want16,
            "u16 ellipsoid term T = {tt:?}: {why}"
        );
    }
}

/// Mirror symmetry of the ellipsoid about its centre, on all three axes.
#[test]
fn ellipsoid_is_symmetric() {
    let c = [3i64, 4, 5];
    let e = Ellipsoid {
        center: c,
        radii: [7, 5, 6],
    };
    for t in [U8, U16] {
        for z in -6..=6 {
            for y in -5..=5 {
                for x in -7..=7i64 {
                    let v = e.sample([c[0] + x, c[1] + y, c[2] + z], t);
                    for m in [[-1, 1, 1], [1, -1, 1], [1, 1, -1]] {
                        let w = e.sample([c[0] + m[0] * x, c[1] + m[1] * y, c[2] + m[2] * z], t);
                        assert_eq!(v, w, "{t} ellipsoid ({x},{y},{z}) mirrored {m:?}");
                    }
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Cylinder
// ---------------------------------------------------------------------------------------------

/// Cylinder base (5, 7, -9), radii (rx, rz) = (3, 2), height By = 6: local Vy = y - 7 in
/// 0..=5 (By-1 = 5, By-2 = 4); ebody(P) = Px²/9 + Pz²/4 with P = (x - 5, -, z + 9).
/// Entries: (dx, Vy, dz), u8 value, u16 value.
const CYLINDER: &[([i64; 3], u16, u16, &str)] = &[
    // Axis column: T = 0, T^ = 0, ebody(T - T^) = 0, ebody(T + T^) = 0 < 1.
    ([0, 0, 0], 0, 0, "Vy = 0: bottom padding L"),
    (
        [0, 1, 0],
        127,
        32767,
        "Vy = 1 and ebody(T+T^) < 1: bottom S layer",
    ),
    ([0, 2, 0], 255, 65535, "Vy = 2: H"),
    ([0, 3, 0], 255, 65535, "Vy = 3: H"),
    ([0, 4, 0], 127, 32767, "Vy = By-2 = 4: top S layer"),
    ([0, 5, 0], 0, 0, "Vy = By-1 = 5: top padding L"),
    // (1, Vy, 0): ebody(T + T^) = ebody(2,0) = 4/9 < 1.
    ([1, 0, 0], 0, 0, "bottom padding off-axis: L"),
    ([1, 2, 0], 255, 65535, "ebody(2,0) = 4/9 < 1: H"),
    ([1, 4, 0], 127, 32767, "top S layer off-axis: S"),
    ([1, 5, 0], 0, 0, "top padding off-axis: L"),
    // (3, Vy, 0): ebody(T - T^) = ebody(2,0) = 4/9 (not > 1); ebody(T + T^) = 16/9 (not < 1);
    // band: ebody(T) = 9/9 = 1 -> S.
    ([3, 2, 0], 127, 32767, "side surface on the x axis: S"),
    ([-3, 3, 0], 127, 32767, "side surface on -x: S"),
    // (2, Vy, 0): ebody(3,0) = 1 not < 1: band ebody(2,0) = 4/9: 127 * 9/4 = 285.75 -> H.
    ([2, 2, 0], 255, 65535, "band clamped to H"),
    // Same voxel column in the bottom S layer: the S rule needs ebody(T+T^) < 1, which fails,
    // so it is the band value, clamped to H.
    (
        [2, 1, 0],
        255,
        65535,
        "band voxel of the S layer: band value, not S",
    ),
    // (0, Vy, 2): ebody(0,1) = 1/4; ebody(0,3) = 9/4; band ebody(0,2) = 4/4 = 1 -> S.
    ([0, 3, 2], 127, 32767, "side surface on the z axis: S"),
    // (0, Vy, 1): ebody(0,2) = 1 not < 1; band ebody(0,1) = 1/4: 127 * 4 -> H.
    ([0, 3, 1], 255, 65535, "band clamped to H (z)"),
    // (2, Vy, 1): ebody(T) = 4/9 + 1/4 = 25/36; |T| = sqrt(5), T^ = (0.8944, 0.4472);
    // T + T^ = (2.8944, 1.4472): 0.9309 + 0.5236 = 1.4545 (not < 1);
    // T - T^ = (1.1056, 0.5528): 0.1358 + 0.0764 = 0.2122 (not > 1);
    // band: 127 * 36/25 = 182.88 -> 182; 32767 * 36/25 = 47184.48 -> 47184.
    ([2, 2, 1], 182, 47184, "band voxel of the side"),
    ([-2, 3, -1], 182, 47184, "mirror image of the band voxel"),
    (
        [2, 1, 1],
        182,
        47184,
        "band voxel in the bottom S layer keeps its band value",
    ),
    (
        [2, 4, 1],
        182,
        47184,
        "band voxel in the top S layer keeps its band value",
    ),
    // (1, Vy, 1): ebody(T+T^) with T^ = (0.7071, 0.7071): (1.7071, 1.7071): 0.3238 + 0.7286
    // = 1.052 (not < 1); band ebody(1,1) = 1/9 + 1/4 = 13/36: 127 * 36/13 = 351.7 -> H.
    ([1, 3, 1], 255, 65535, "diagonal band clamped to H"),
    // (3, Vy, 2): |T| = sqrt(13), T^ = (0.8321, 0.5547); T - T^ = (2.1679, 1.4453):
    // 4.700/9 + 2.089/4 = 0.5222 + 0.5222 = 1.044 > 1 -> L.
    ([3, 2, 2], 0, 0, "exterior corner: L"),
    ([3, 1, 2], 0, 0, "exterior corner in the S layer: L"),
    // Outside the extension space.
    ([0, 6, 0], 0, 0, "Vy = 6 = By: outside, L"),
    ([0, -1, 0], 0, 0, "Vy = -1: outside, L"),
    ([4, 3, 0], 0, 0, "dx = 4 > rx: outside, L"),
];

#[test]
fn cylinder_golden() {
    let base = [5i64, 7, -9];
    let c = Cylinder {
        base,
        radii: [3, 2],
        height: 6,
    };
    // B-box: origin = base - (rx, 0, rz) = (2, 7, -11); size (2*3+1, 6, 2*2+1) = (7, 6, 5).
    assert_eq!(c.bbox(), Box3::new([2, 7, -11], [9, 13, -6]));
    let json = r#"{"cylinder": {"base": [5, 7, -9], "radii": [3, 2], "height": 6}}"#;
    let (j8, j16) = (compile(json, U8), compile(json, U16));
    assert_eq!(j16.bbox, Some(Box3::new([2, 7, -11], [9, 13, -6])));
    for (d, want8, want16, why) in CYLINDER {
        let v = [0, 1, 2].map(|a| base[a] + d[a]);
        assert_eq!(c.sample(v, U8), *want8, "u8 cylinder {d:?}: {why}");
        assert_eq!(c.sample(v, U16), *want16, "u16 cylinder {d:?}: {why}");
        assert_eq!(j8.sample(v), *want8, "u8 cylinder term {d:?}: {why}");
        assert_eq!(j16.sample(v), *want16, "u16 cylinder term {d:?}: {why}");
    }
    // The bottom and top layers are L over the whole cross-section.
    for t in [U8, U16] {
        for z in -11..-6 {
            for x in 2..9 {
                assert_eq!(c.sample([x, 7, z], t), 0, "{t} bottom layer ({x}, 7, {z})");
                assert_eq!(c.sample([x, 12, z], t), 0, "{t} top layer ({x}, 12, {z})");
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Cone
// ---------------------------------------------------------------------------------------------

/// Cone base (10, -3, 20), radii (4, 4), height By = 9: h = 1 - Vy/8,
/// cbody(P) = (Px² + Pz²) / (4h)². Entries: (dx, Vy, dz), u8 value, u16 value.
const CONE: &[([i64; 3], u16, u16, &str)] = &[
    ([0, 0, 0], 0, 0, "Vy = 0: bottom padding L on the axis"),
    ([2, 0, 0], 0, 0, "Vy = 0: bottom padding L"),
    // Vy = 1: h = 7/8, radius 3.5, (4h)² = 12.25.
    (
        [0, 1, 0],
        127,
        32767,
        "Vy = 1, cbody(T+T^) = 0 < 1: S layer",
    ),
    // (2,1,0): cbody(3,0) = 9/12.25 = 0.735 < 1 -> S.
    (
        [2, 1, 0],
        127,
        32767,
        "Vy = 1, cbody(3,0) = 0.73 < 1: S layer",
    ),
    // (3,1,0): cbody(4,0) = 16/12.25 = 1.306 (not < 1); cbody(2,0) = 0.33 (not > 1);
    // band: cbody(3,0) = 9/12.25: 127 * 12.25/9 = 172.86 -> 172; 32767 * 12.25/9 = 44599.3.
    ([3, 1, 0], 172, 44599, "Vy = 1 band voxel: band value"),
    // (4,1,0): cbody(3,0) = 0.735 (not > 1); band cbody(4,0) = 16/12.25 = 1.306:
    // 127 * 12.25/16 = 97.23 -> 97; 32767 * 12.25/16 = 25087.2 -> 25087.
    (
        [4, 1, 0],
        97,
        25087,
        "Vy = 1 band voxel outside the surface",
    ),
    // Vy = 2: h = 6/8 = 0.75, (4h)² = 9.
    ([0, 2, 0], 255, 65535, "Vy = 2 axis: H"),
    ([1, 2, 0], 255, 65535, "cbody(2,0) = 4/9 < 1: H"),
    // (2,2,0): cbody(3,0) = 1 not < 1; band cbody(2,0) = 4/9: 285.75 -> clamped H.
    ([2, 2, 0], 255, 65535, "band clamped to H"),
    // (3,2,0): cbody(2,0) = 4/9 not > 1; cbody(4,0) = 16/9; band cbody(3,0) = 1 -> S.
    ([3, 2, 0], 127, 32767, "surface at Vy = 2: S"),
    // Vy = 4: h = 0.5, (4h)² = 4.
    // (2,4,0): cbody(1,0) = 1/4, cbody(3,0) = 9/4; band cbody(2,0) = 1 -> S.
    ([2, 4, 0], 127, 32767, "surface at Vy = 4: S"),
    // (3,4,0): cbody(2,0) = 1 not > 1; band cbody(3,0) = 9/4: 127/2.25 = 56.4 -> 56;
    // 32767/2.25 = 14563.1 -> 14563.
    ([3, 4, 0], 56, 14563, "band outside the surface at Vy = 4"),
    ([0, 4, -3], 56, 14563, "same radius along -z"),
    // (2,4,2): cbody(T) = 8/4 = 2; T - T^ = (1.293, 1.293): 3.343/4 = 0.836 (not > 1);
    // band: 127/2 = 63.5 -> 63; 32767/2 = 16383.5 -> 16383.
    ([2, 4, 2], 63, 16383, "diagonal band voxel at Vy = 4"),
    // (4,4,0): cbody(3,0) = 9/4 > 1 -> L.
    ([4, 4, 0], 0, 0, "exterior at Vy = 4: L"),
    // Vy = 7: h = 1/8, (4h)² = 1/4.
    ([0, 7, 0], 255, 65535, "axis below the apex: H"),
    // (1,7,0): cbody(0,0) = 0 (not > 1); cbody(2,0) = 16 (not < 1); band cbody(1,0) = 4:
    // 127/4 = 31.75 -> 31; 32767/4 = 8191.75 -> 8191.
    ([1, 7, 0], 31, 8191, "band beside the tip"),
    // Vy = 8 = By-1: h = 0, cbody = +inf except cbody(0) = 0 on the apex column.
    (
        [0, 8, 0],
        255,
        65535,
        "apex: cbody(T + T^) = cbody(0) = 0 < 1: H",
    ),
    // (1,8,0): cbody(T - T^) = cbody(0) = 0 (not > 1); cbody(T + T^) = inf; band S / inf = 0.
    ([1, 8, 0], 0, 0, "beside the apex: S / inf = 0"),
    ([0, 9, 0], 0, 0, "above the extension space: L"),
];

#[test]
fn cone_golden() {
    let base = [10i64, -3, 20];
    let c = Cone {
        base,
        radii: [4, 4],
        height: 9,
    };
    // B-box: origin base - (4, 0, 4) = (6, -3, 16), size (9, 9, 9).
    assert_eq!(c.bbox(), Box3::new([6, -3, 16], [15, 6, 25]));
    let json = r#"{"cone": {"base": [10, -3, 20], "radii": [4, 4], "height": 9}}"#;
    let (j8, j16) = (compile(json, U8), compile(json, U16));
    assert_eq!(j8.bbox, Some(Box3::new([6, -3, 16], [15, 6, 25])));
    for (d, want8, want16, why) in CONE {
        let v = [0, 1, 2].map(|a| base[a] + d[a]);
        assert_eq!(c.sample(v, U8), *want8, "u8 cone {d:?}: {why}");
        assert_eq!(c.sample(v, U16), *want16, "u16 cone {d:?}: {why}");
        assert_eq!(j8.sample(v), *want8, "u8 cone term {d:?}: {why}");
        assert_eq!(j16.sample(v), *want16, "u16 cone term {d:?}: {why}");
    }
    // Bottom layer all L.
    for t in [U8, U16] {
        for z in 16..25 {
            for x in 6..15 {
                assert_eq!(
                    c.sample([x, -3, z], t),
                    0,
                    "{t} bottom layer ({x}, -3, {z})"
                );
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Primitives beyond the papers: the documented contract.
// ---------------------------------------------------------------------------------------------

/// Checks, over the B-box grown by 2 voxels, the contract of a curved primitive given `inside`,
/// the signed distance of a voxel centre inside the surface (negative outside):
/// - more than one voxel inside: exactly H; more than one voxel outside: exactly L;
/// - inside or on the surface: visible (>= S); outside: invisible (< S).
///
/// Returns the number of visible voxels.
fn check_curved_contract(
    p: &dyn Primitive,
    t: VoxelType,
    what: &str,
    inside: impl Fn([f64; 3]) -> f64,
) -> u64 {
    let (s, h) = (t.surface(), t.high());
    let b = p.bbox();
    let mut visible = 0;
    let (mut saw_band, mut saw_h, mut saw_l) = (false, false, false);
    for z in b.min[2] - 2..b.max[2] + 2 {
        for y in b.min[1] - 2..b.max[1] + 2 {
            for x in b.min[0] - 2..b.max[0] + 2 {
                let v = p.sample([x, y, z], t);
                let d = inside([x as f64, y as f64, z as f64]);
                if d > 1.0 + 1e-9 {
                    assert_eq!(v, h, "{t} {what} ({x},{y},{z}) depth {d}: H");
                    saw_h = true;
                } else if d < -1.0 - 1e-9 {
                    assert_eq!(v, 0, "{t} {what} ({x},{y},{z}) depth {d}: L");
                    saw_l = true;
                } else {
                    saw_band = true;
                }
                // (Centres exactly on a curved surface are left out: whether the rounded body
                // lands on 1 or just above it is up to the floating-point evaluation.)
                if d >= 1e-9 {
                    assert!(
                        v >= s,
                        "{t} {what} ({x},{y},{z}) depth {d}: visible, got {v}"
                    );
                } else if d <= -1e-9 {
                    assert!(
                        v < s,
                        "{t} {what} ({x},{y},{z}) depth {d}: invisible, got {v}"
                    );
                }
                if v >= s {
                    visible += 1;
                    assert!(
                        b.contains([x, y, z]),
                        "{what} visible voxel outside its B-box"
                    );
                }
            }
        }
    }
    assert!(saw_band && saw_h && saw_l, "{what}: test shape too small");
    visible
}

fn within(count: u64, analytic: f64, tolerance: f64) -> bool {
    ((count as f64 - analytic) / analytic).abs() <= tolerance
}

#[test]
fn torus_contract() {
    let c = [4i64, -3, 9];
    let (major, minor) = (12u32, 8u32);
    let torus = Torus {
        center: c,
        major,
        minor,
    };
    // Documented extension (2(major + minor) + 1, 2 minor + 1, 2(major + minor) + 1) centred on
    // `center`: (4 - 20, -3 - 8, 9 - 20) .. (4 + 21, -3 + 9, 9 + 21).
    assert_eq!(torus.bbox(), Box3::new([-16, -11, -11], [25, 6, 30]));
    let term = compile(
        r#"{"torus": {"center": [4, -3, 9], "major": 12, "minor": 8}}"#,
        U8,
    );
    assert_eq!(term.bbox, Some(torus.bbox()));
    // Distance of a point from the tube's centre circle (radius 12 in the y = -3 plane).
    let depth = |v: [f64; 3]| {
        let (x, y, z) = (v[0] - 4.0, v[1] + 3.0, v[2] - 9.0);
        let ring = (x * x + z * z).sqrt() - major as f64;
        minor as f64 - (ring * ring + y * y).sqrt()
    };
    for t in [U8, U16] {
        let visible = check_curved_contract(&torus, t, "torus", depth);
        // Analytic volume 2 pi² R r² = 2 * 9.8696 * 12 * 64 = 15159.7.
        assert!(
            within(
                visible,
                2.0 * std::f64::consts::PI.powi(2) * 12.0 * 64.0,
                0.03
            ),
            "{t} torus visible voxels {visible}"
        );
        // Anchors: the tube's centre circle is H, the hole's centre is L (12 > 8 + 1).
        assert_eq!(torus.sample([4 + 12, -3, 9], t), t.high());
        assert_eq!(torus.sample([4, -3, 9 - 12], t), t.high());
        assert_eq!(torus.sample([4, -3, 9], t), 0);
        // On the outer equator (distance exactly 8 from the circle): body 1, so S.
        assert_eq!(torus.sample([4 + 20, -3, 9], t), t.surface());
        assert_eq!(torus.sample([4 + 12, -3 + 8, 9], t), t.surface());
    }
    // A fat torus whose hole is closed (minor > major): the same contract holds (no volume
    // check: the tube overlaps itself).
    let fat = Torus {
        center: [0, 0, 0],
        major: 3,
        minor: 5,
    };
    assert_eq!(fat.bbox(), Box3::new([-8, -5, -8], [9, 6, 9]));
    for t in [U8, U16] {
        check_curved_contract(&fat, t, "fat torus", |v: [f64; 3]| {
            let ring = (v[0] * v[0] + v[2] * v[2]).sqrt() - 3.0;
            5.0 - (ring * ring + v[1] * v[1]).sqrt()
        });
    }
    // Symmetry: mirror in x, y, z about the centre. (Only mirrors: they flip signs, which f64
    // evaluates exactly; a swap of axes reorders sums, and a voxel whose body is exactly 1 in
    // exact arithmetic may then round to either side of 1.)
    for z in -20..=20i64 {
        for y in -8..=8i64 {
            for x in -20..=20i64 {
                let v = torus.sample([c[0] + x, c[1] + y, c[2] + z], U16);
                for w in [[-x, y, z], [x, -y, z], [x, y, -z]] {
                    let m = torus.sample([c[0] + w[0], c[1] + w[1], c[2] + w[2]], U16);
                    assert_eq!(v, m, "torus ({x},{y},{z}) vs {w:?}");
                }
            }
        }
    }
}

/// A capsule of `length` along +y centred on `center`: the segment from -length/2 to +length/2.
fn capsule_depth(center: [i64; 3], radius: u32, length: u32) -> impl Fn([f64; 3]) -> f64 {
    move |v: [f64; 3]| {
        let half = length as f64 / 2.0;
        let (x, y, z) = (
            v[0] - center[0] as f64,
            v[1] - center[1] as f64,
            v[2] - center[2] as f64,
        );
        let dy = (y.abs() - half).max(0.0);
        radius as f64 - (x * x + dy * dy + z * z).sqrt()
    }
}

#[test]
fn capsule_contract_even_length() {
    let c = [-7i64, 2, 5];
    let cap = Capsule {
        center: c,
        radius: 8,
        length: 10,
    };
    // Documented extension (2r + 1, length + 2r + 1, 2r + 1) = (17, 27, 17), centred:
    // x -7 - 8 .. -7 + 9, y 2 - 5 - 8 .. 2 + 5 + 9, z 5 - 8 .. 5 + 9.
    assert_eq!(cap.bbox(), Box3::new([-15, -11, -3], [2, 16, 14]));
    let term = compile(
        r#"{"capsule": {"center": [-7, 2, 5], "radius": 8, "length": 10}}"#,
        U16,
    );
    assert_eq!(term.bbox, Some(cap.bbox()));
    for t in [U8, U16] {
        let visible = check_curved_contract(&cap, t, "capsule", capsule_depth(c, 8, 10));
        // Analytic: pi r² length + 4/3 pi r³ = 2010.6 + 2144.7 = 4155.3.
        let pi = std::f64::consts::PI;
        assert!(
            within(visible, pi * 64.0 * 10.0 + 4.0 / 3.0 * pi * 512.0, 0.03),
            "{t} capsule visible voxels {visible}"
        );
        // The segment is H; the cap's tip (distance 8 from the segment's end) is S.
        assert_eq!(cap.sample([-7, 2 + 5, 5], t), t.high());
        assert_eq!(cap.sample([-7, 2 - 5, 5], t), t.high());
        assert_eq!(cap.sample([-7, 2 + 5 + 8, 5], t), t.surface());
        assert_eq!(cap.sample([-7, 2 - 5 - 8, 5], t), t.surface());
        assert_eq!(cap.sample([-7 + 8, 2, 5], t), t.surface());
    }
    capsule_symmetry(&cap);
}

/// With an odd length the segment ends at +-length/2 = +-2.5: the shape is still symmetric
/// about the centre voxel, and so must be its values. Hand checks on the axis (r = 8):
/// - offset (0, +-10, 0): distance 10 - 2.5 = 7.5; one step out (8.5) is outside, so not H; one
///   step in (6.5) is inside, so not L: band, body 7.5² / 64 = 0.8789:
///   floor(127 / 0.8789) = floor(144.50) = 144; floor(32767 * 64 / 56.25) = floor(37281.56) = 37281.
/// - offset (0, +-11, 0): distance 8.5; one step in (7.5 < 8) is inside, so not L; one step out
///   (9.5) not H: band, body 72.25 / 64: floor(127 * 64 / 72.25) = floor(112.50) = 112;
///   floor(32767 * 64 / 72.25) = floor(29025.45) = 29025.
/// - offset (-2, +-11, -2): distance sqrt(2² + 8.5² + 2²) = sqrt(80.25) = 8.958; one step in
///   (7.958) inside, one step out (9.958) outside: band, floor(32767 * 64 / 80.25) =
///   floor(26131.9) = 26131 (u16).
#[test]
fn capsule_contract_odd_length() {
    let c = [0i64, 0, 0];
    let cap = Capsule {
        center: c,
        radius: 8,
        length: 5,
    };
    // Documented extension (2r + 1, 2 ceil(5/2) + 2r + 1, 2r + 1) = (17, 23, 17), centred:
    // y from -3 - 8 = -11 to 3 + 8 = 11.
    assert_eq!(cap.bbox(), Box3::new([-8, -11, -8], [9, 12, 9]));
    for t in [U8, U16] {
        check_curved_contract(&cap, t, "capsule (odd length)", capsule_depth(c, 8, 5));
    }
    for y in [10, -10] {
        assert_eq!(cap.sample([0, y, 0], U8), 144, "u8 (0, {y}, 0)");
        assert_eq!(cap.sample([0, y, 0], U16), 37281, "u16 (0, {y}, 0)");
    }
    for y in [11, -11] {
        assert_eq!(cap.sample([0, y, 0], U8), 112, "u8 (0, {y}, 0)");
        assert_eq!(cap.sample([0, y, 0], U16), 29025, "u16 (0, {y}, 0)");
        assert_eq!(cap.sample([-2, y, -2], U16), 26131, "u16 (-2, {y}, -2)");
    }
    capsule_symmetry(&cap);
}

fn capsule_symmetry(cap: &Capsule) {
    let c = cap.center;
    let (r, half) = (cap.radius as i64, cap.length as i64 / 2 + 1);
    for z in -r - 1..=r + 1 {
        for y in -half - r - 1..=half + r + 1 {
            for x in -r - 1..=r + 1 {
                let v = cap.sample([c[0] + x, c[1] + y, c[2] + z], U16);
                // Mirrors only (see the torus).
                for w in [[-x, y, z], [x, -y, z], [x, y, -z]] {
                    let m = cap.sample([c[0] + w[0], c[1] + w[1], c[2] + w[2]], U16);
                    assert_eq!(
                        v, m,
                        "capsule {cap:?}: offset ({x},{y},{z}) = {v} but mirror {w:?} = {m}"
                    );
                }
            }
        }
    }
}

/// Checks a polytope (a cuboid `size` at `origin` cut by planes) against its contract. `planes`
/// gives, for a local position, the integer plane functions E_i (inside where E_i <= 0) and
/// their norms: the signed distance inside face i is -E_i / norm_i.
fn check_polytope_contract(
    p: &dyn Primitive,
    origin: [i64; 3],
    size: [u32; 3],
    what: &str,
    planes: &dyn Fn([i64; 3]) -> Vec<(i64, f64)>,
) {
    let b = Box3::new(origin, [0, 1, 2].map(|a| origin[a] + size[a] as i64));
    assert_eq!(p.bbox(), b, "{what}: B-box is the cuboid's");
    let last = size.map(|s| s as i64 - 1);
    for t in [U8, U16] {
        let (s, h) = (t.surface(), t.high());
        let (mut saw_h, mut saw_band, mut saw_on) = (false, false, false);
        for z in b.min[2] - 2..b.max[2] + 2 {
            for y in b.min[1] - 2..b.max[1] + 2 {
                for x in b.min[0] - 2..b.max[0] + 2 {
                    let v = p.sample([x, y, z], t);
                    let l = [x - origin[0], y - origin[1], z - origin[2]];
                    let at = format!("{t} {what} local {l:?} = {v}");
                    if (0..3).any(|a| l[a] < 0 || l[a] > last[a]) {
                        assert_eq!(v, 0, "{at}: outside the extension space, L");
                        continue;
                    }
                    if (0..3).any(|a| l[a] == 0 || l[a] == last[a]) {
                        assert_eq!(v, 0, "{at}: padding layer, L");
                        continue;
                    }
                    let faces = planes(l);
                    let depth = faces
                        .iter()
                        .map(|&(e, n)| -(e as f64) / n)
                        .fold(f64::INFINITY, f64::min);
                    let on_plane = faces.iter().any(|&(e, _)| e == 0);
                    let inside = faces.iter().all(|&(e, _)| e <= 0);
                    let s_layer = (0..3).any(|a| l[a] == 1 || l[a] == last[a] - 1);
                    if depth < -1.0 - 1e-9 {
                        assert_eq!(v, 0, "{at}: over one voxel outside a slanted face, L");
                    } else if depth > 1.0 + 1e-9 {
                        let want = if s_layer { s } else { h };
                        assert_eq!(v, want, "{at}: deep inside, the cuboid's value");
                        saw_h |= !s_layer;
                    } else {
                        saw_band = true;
                    }
                    // Visible exactly when inside every face (voxel centres on a face count as
                    // inside: there the body is exactly 1 and the value S).
                    if inside {
                        assert!(v >= s, "{at}: inside, must be visible");
                    } else {
                        assert!(v < s, "{at}: outside, must be invisible");
                    }
                    if on_plane && inside {
                        saw_on = true;
                        assert_eq!(v, s, "{at}: centre on a slanted face: body 1, value S");
                    }
                }
            }
        }
        assert!(saw_h && saw_band && saw_on, "{what}: test shape too small");
    }
}

#[test]
fn prism_contract() {
    // Size (12, 9, 6): the S layers are at local 1 and B-2, so w = 12 - 3 = 9, h = 9 - 3 = 6.
    // The slanted face runs through (x, y) = (1, 1 + h) = (1, 7) and (1 + w, 1) = (10, 1);
    // outward normal (h, w) = (6, 9): E = 6 (x - 1) + 9 (y - 7), inside where E <= 0,
    // distance -E / sqrt(36 + 81). Centres on the face: (1,7), (4,5), (7,3), (10,1).
    let origin = [3, -2, 7];
    let size = [12, 9, 6];
    let prism = Prism { origin, size };
    let term = compile(
        r#"{"prism": {"origin": [3, -2, 7], "size": [12, 9, 6]}}"#,
        U8,
    );
    assert_eq!(term.bbox, Some(Box3::new([3, -2, 7], [15, 7, 13])));
    let planes = |l: [i64; 3]| vec![(6 * (l[0] - 1) + 9 * (l[1] - 7), 117f64.sqrt())];
    check_polytope_contract(&prism, origin, size, "prism", &planes);
    // Extruded along z: the interior slices z = 2 .. B-3 are equal; mirror symmetric in z.
    for t in [U8, U16] {
        for y in -2..7 {
            for x in 3..15 {
                // Bz = 6: interior slices are local z = 2 and 3.
                let v = prism.sample([x, y, 7 + 2], t);
                assert_eq!(
                    prism.sample([x, y, 7 + 3], t),
                    v,
                    "{t} prism slices at ({x},{y})"
                );
                for dz in 0..6 {
                    assert_eq!(
                        prism.sample([x, y, 7 + dz], t),
                        prism.sample([x, y, 7 + 5 - dz], t),
                        "{t} prism mirror in z at ({x},{y}), dz {dz}"
                    );
                }
            }
        }
    }
}

#[test]
fn prism_square_is_symmetric_across_its_face() {
    // w = h: swapping local x and y maps the wedge onto itself.
    let origin = [0, 0, 0];
    let prism = Prism {
        origin,
        size: [14, 14, 5],
    };
    let planes = |l: [i64; 3]| vec![((l[0] - 1) + (l[1] - 12), 2f64.sqrt())];
    check_polytope_contract(&prism, origin, [14, 14, 5], "square prism", &planes);
    for t in [U8, U16] {
        for z in 0..5 {
            for y in 0..14 {
                for x in 0..14 {
                    assert_eq!(
                        prism.sample([x, y, z], t),
                        prism.sample([y, x, z], t),
                        "{t} square prism ({x},{y},{z}) vs ({y},{x},{z})"
                    );
                }
            }
        }
    }
}

#[test]
fn pyramid_contract() {
    // Size (11, 9, 11): w = 8, h = 6, d = 8; base on the bottom S layer (y = 1), apex at the
    // centre of the top S layer: (1 + 4, 1 + 6, 1 + 4) = (5, 7, 5). Face +x through the apex
    // and the base edge x = 9: E = h (x - 5) + (w/2) (y - 7) = 6 (x - 5) + 4 (y - 7), norm
    // sqrt(36 + 16); likewise -x: -6 (x - 5) + 4 (y - 7); +z, -z with z.
    // Centres on the +x face: (5,7), (7,4), (9,1).
    let origin = [-4, 6, 2];
    let size = [11, 9, 11];
    let pyr = Pyramid { origin, size };
    let term = compile(
        r#"{"pyramid": {"origin": [-4, 6, 2], "size": [11, 9, 11]}}"#,
        U16,
    );
    assert_eq!(term.bbox, Some(Box3::new([-4, 6, 2], [7, 15, 13])));
    let n = 52f64.sqrt();
    let planes = |l: [i64; 3]| {
        vec![
            (6 * (l[0] - 5) + 4 * (l[1] - 7), n),
            (-6 * (l[0] - 5) + 4 * (l[1] - 7), n),
            (6 * (l[2] - 5) + 4 * (l[1] - 7), n),
            (-6 * (l[2] - 5) + 4 * (l[1] - 7), n),
        ]
    };
    check_polytope_contract(&pyr, origin, size, "pyramid", &planes);
    // Symmetry: mirror in x and in z about the apex column, and the swap of x and z.
    for t in [U8, U16] {
        for lz in 0..11i64 {
            for ly in 0..9i64 {
                for lx in 0..11i64 {
                    let v = pyr.sample([-4 + lx, 6 + ly, 2 + lz], t);
                    for m in [[10 - lx, ly, lz], [lx, ly, 10 - lz], [lz, ly, lx]] {
                        let w = pyr.sample([-4 + m[0], 6 + m[1], 2 + m[2]], t);
                        assert_eq!(v, w, "{t} pyramid local ({lx},{ly},{lz}) vs {m:?}");
                    }
                }
            }
        }
        // The apex voxel (on all four faces) is S; straight below it, 2 voxels down, deep
        // inside: distance to the +x face = -(0 + 4 * (-2)) / sqrt(52) = 1.11 > 1 -> H.
        assert_eq!(pyr.sample([-4 + 5, 6 + 7, 2 + 5], t), t.surface());
        assert_eq!(pyr.sample([-4 + 5, 6 + 5, 2 + 5], t), t.high());
    }
}

/// The visible volume of a large ellipsoid is close to 4/3 pi R1 R2 R3.
#[test]
fn ellipsoid_visible_volume() {
    let e = Ellipsoid {
        center: [0, 0, 0],
        radii: [12, 9, 10],
    };
    let mut visible = 0u64;
    for z in -10..=10 {
        for y in -9..=9 {
            for x in -12..=12 {
                visible += (e.sample([x, y, z], U8) >= 127) as u64;
            }
        }
    }
    // 4/3 pi 12 * 9 * 10 = 4523.9.
    let analytic = 4.0 / 3.0 * std::f64::consts::PI * 1080.0;
    assert!(within(visible, analytic, 0.02), "{visible} vs {analytic}");
}

// ---------------------------------------------------------------------------------------------
// Operators
// ---------------------------------------------------------------------------------------------

/// The 16 pairs over {L, S-1, S, H}, D1 major: (L,L), (L,S-1), (L,S), (L,H), (S-1,L), ...
fn pairs(t: VoxelType) -> Vec<(u16, u16)> {
    let v = [0, t.surface() - 1, t.surface(), t.high()];
    v.iter()
        .flat_map(|&a| v.iter().map(move |&b| (a, b)))
        .collect()
}

fn table(op: BinaryOp, t: VoxelType) -> Vec<u16> {
    pairs(t).iter().map(|&(a, b)| op.apply(a, b, t)).collect()
}

// Rows below are (D1 = L | S-1 | S | H) x (D2 = L, S-1, S, H).

#[test]
fn union_intersection_trim_cap_tables() {
    // union = max.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Union, U8), vec![
        0, 126, 127, 255,
        126, 126, 127, 255,
        127, 127, 127, 255,
        255, 255, 255, 255,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Union, U16), vec![
        0, 32766, 32767, 65535,
        32766, 32766, 32767, 65535,
        32767, 32767, 32767, 65535,
        65535, 65535, 65535, 65535,
    ]);
    // intersection = min.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Intersection, U8), vec![
        0, 0, 0, 0,
        0, 126, 126, 126,
        0, 126, 127, 127,
        0, 126, 127, 255,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Intersection, U16), vec![
        0, 0, 0, 0,
        0, 32766, 32766, 32766,
        0, 32766, 32767, 32767,
        0, 32766, 32767, 65535,
    ]);
    // trim: D1 if D1 >= D2 else L. (S-1, S): 126 < 127 -> L; (S, S-1) -> 127.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Trim, U8), vec![
        0, 0, 0, 0,
        126, 126, 0, 0,
        127, 127, 127, 0,
        255, 255, 255, 255,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Trim, U16), vec![
        0, 0, 0, 0,
        32766, 32766, 0, 0,
        32767, 32767, 32767, 0,
        65535, 65535, 65535, 65535,
    ]);
    // cap: D1 if D1 <= D2 else L. (L, x) = L always; (H, x) = H only for x = H.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Cap, U8), vec![
        0, 0, 0, 0,
        0, 126, 126, 126,
        0, 0, 127, 127,
        0, 0, 0, 255,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Cap, U16), vec![
        0, 0, 0, 0,
        0, 32766, 32766, 32766,
        0, 0, 32767, 32767,
        0, 0, 0, 65535,
    ]);
}

#[test]
fn difference_tables() {
    // difference_a = max(D1 - D2, L): (S, S-1) = 1; (H, S-1) = 255 - 126 = 129;
    // (H, S) = 128; u16 (H, S-1) = 65535 - 32766 = 32769; (H, S) = 32768.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::DifferenceA, U8), vec![
        0, 0, 0, 0,
        126, 0, 0, 0,
        127, 1, 0, 0,
        255, 129, 128, 0,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::DifferenceA, U16), vec![
        0, 0, 0, 0,
        32766, 0, 0, 0,
        32767, 1, 0, 0,
        65535, 32769, 32768, 0,
    ]);
    // difference_b = max(D1 - D2, L) if D2 >= S, else D1: with D2 in {L, S-1} it is D1;
    // (H, S) = 128; (H, H) = 0; (S, S) = 0.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::DifferenceB, U8), vec![
        0, 0, 0, 0,
        126, 126, 0, 0,
        127, 127, 0, 0,
        255, 255, 128, 0,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::DifferenceB, U16), vec![
        0, 0, 0, 0,
        32766, 32766, 0, 0,
        32767, 32767, 0, 0,
        65535, 65535, 32768, 0,
    ]);
    // difference = max(D1 - D2, S) if D1 >= S and D2 < S, else max(D1 - D2, L):
    // (S-1, L): D1 < S -> 126; (S, L): max(127, 127) = 127; (S, S-1): max(1, 127) = 127;
    // (S, S): D2 >= S -> max(0, 0) = 0; (H, L) = 255; (H, S-1): max(129, 127) = 129;
    // (H, S): 128; (H, H): 0. u16: (S, S-1): max(1, 32767) = 32767; (H, S-1): 32769.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Difference, U8), vec![
        0, 0, 0, 0,
        126, 0, 0, 0,
        127, 127, 0, 0,
        255, 129, 128, 0,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Difference, U16), vec![
        0, 0, 0, 0,
        32766, 0, 0, 0,
        32767, 32767, 0, 0,
        65535, 32769, 32768, 0,
    ]);
    // Where the S bound bites: u8 (200, 100): D1 >= S, D2 < S: max(100, 127) = 127, while
    // difference_a gives 100 and difference_b gives D1 = 200.
    assert_eq!(BinaryOp::Difference.apply(200, 100, U8), 127);
    assert_eq!(BinaryOp::DifferenceA.apply(200, 100, U8), 100);
    assert_eq!(BinaryOp::DifferenceB.apply(200, 100, U8), 200);
    // u16 (50000, 20000): max(30000, 32767) = 32767; (50000, 10000): max(40000, 32767).
    assert_eq!(BinaryOp::Difference.apply(50000, 20000, U16), 32767);
    assert_eq!(BinaryOp::Difference.apply(50000, 10000, U16), 40000);
}

#[test]
fn arithmetic_tables() {
    // add = min(D1 + D2, H): (S-1, S-1) = 252, (S-1, S) = 253, (S, S) = 254;
    // u16: 65532, 65533, 65534.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Add, U8), vec![
        0, 126, 127, 255,
        126, 252, 253, 255,
        127, 253, 254, 255,
        255, 255, 255, 255,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Add, U16), vec![
        0, 32766, 32767, 65535,
        32766, 65532, 65533, 65535,
        32767, 65533, 65534, 65535,
        65535, 65535, 65535, 65535,
    ]);
    // modulate = min(D1 * D2, H): 0 when either is L, else at least 126 * 126 > H -> H.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Modulate, U8), vec![
        0, 0, 0, 0,
        0, 255, 255, 255,
        0, 255, 255, 255,
        0, 255, 255, 255,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Modulate, U16), vec![
        0, 0, 0, 0,
        0, 65535, 65535, 65535,
        0, 65535, 65535, 65535,
        0, 65535, 65535, 65535,
    ]);
    // Small values multiply exactly: 3 * 5 = 15; 15 * 17 = 255; 16 * 16 = 256 -> 255.
    assert_eq!(BinaryOp::Modulate.apply(3, 5, U8), 15);
    assert_eq!(BinaryOp::Modulate.apply(15, 17, U8), 255);
    assert_eq!(BinaryOp::Modulate.apply(16, 16, U8), 255);
    assert_eq!(BinaryOp::Modulate.apply(255, 257, U16), 65535);
    assert_eq!(BinaryOp::Modulate.apply(255, 256, U16), 65280);
    // product = D1 * D2 / H, floored: 126 * 126 / 255 = 15876 / 255 = 62.26 -> 62;
    // 126 * 127 / 255 = 16002 / 255 = 62.75 -> 62; 127 * 127 / 255 = 16129 / 255 = 63.25 -> 63;
    // x * H / H = x.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Product, U8), vec![
        0, 0, 0, 0,
        0, 62, 62, 126,
        0, 62, 63, 127,
        0, 126, 127, 255,
    ]);
    // u16: 32766² = 1073610756 = 16382 * 65535 + 16386 -> 16382;
    // 32766 * 32767 = 1073643522 = 16382 * 65535 + 49152 -> 16382;
    // 32767² = 1073676289 = 16383 * 65535 + 16384 -> 16383.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Product, U16), vec![
        0, 0, 0, 0,
        0, 16382, 16382, 32766,
        0, 16382, 16383, 32767,
        0, 32766, 32767, 65535,
    ]);
    // divide_a = D1 / D2 (integer) if D2 > 0, else H: 126/126 = 1, 126/127 = 0, 127/126 = 1,
    // 255/126 = 2.02 -> 2, 255/127 = 2.008 -> 2; u16 65535/32766 = 2.00006 -> 2.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::DivideA, U8), vec![
        255, 0, 0, 0,
        255, 1, 0, 0,
        255, 1, 1, 0,
        255, 2, 2, 1,
    ]);
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::DivideA, U16), vec![
        65535, 0, 0, 0,
        65535, 1, 0, 0,
        65535, 1, 1, 0,
        65535, 2, 2, 1,
    ]);
    // divide(0.5) = floor(D1 / (D2 * 0.5)) if D2 * 0.5 > 0, else H:
    // 126/63 = 2; 126/63.5 = 1.98 -> 1; 126/127.5 = 0.99 -> 0; 127/63 = 2.02 -> 2;
    // 127/63.5 = 2; 127/127.5 -> 0; 255/63 = 4.05 -> 4; 255/63.5 = 4.02 -> 4; 255/127.5 = 2.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Divide(0.5), U8), vec![
        255, 0, 0, 0,
        255, 2, 1, 0,
        255, 2, 2, 0,
        255, 4, 4, 2,
    ]);
    // u16: 32766/16383 = 2; 32766/16383.5 = 1.99994 -> 1; 32766/32767.5 -> 0;
    // 32767/16383 = 2.00006 -> 2; 32767/16383.5 = 2; 65535/16383 = 4.0002 -> 4;
    // 65535/16383.5 = 4.00006 -> 4; 65535/32767.5 = 2.
    #[rustfmt::skip]
    assert_eq!(table(BinaryOp::Divide(0.5), U16), vec![
        65535, 0, 0, 0,
        65535, 2, 1, 0,
        65535, 2, 2, 0,
        65535, 4, 4, 2,
    ]);
    // Clamping and other S_L: 255 / (1 * 0.25) = 1020 -> H; 3 / (2 * 0.25) = 6;
    // 200 / (100 * 1.0) = 2; 65535 / (1 * 0.5) = 131070 -> H; 100 / (3 * 0.75) = 44.4 -> 44.
    assert_eq!(BinaryOp::Divide(0.25).apply(255, 1, U8), 255);
    assert_eq!(BinaryOp::Divide(0.25).apply(3, 2, U8), 6);
    assert_eq!(BinaryOp::Divide(1.0).apply(200, 100, U8), 2);
    assert_eq!(BinaryOp::Divide(0.5).apply(65535, 1, U16), 65535);
    assert_eq!(BinaryOp::Divide(0.75).apply(100, 3, U8), 44);
}

#[test]
fn unary_tables() {
    let inv = |d: u16, t: VoxelType| UnaryOp::Inverse.apply(d, t);
    // inverse = H - D1: 255 - 126 = 129; 255 - 127 = 128.
    assert_eq!([0, 126, 127, 255].map(|d| inv(d, U8)), [255, 129, 128, 0]);
    assert_eq!(
        [0, 32766, 32767, 65535].map(|d| inv(d, U16)),
        [65535, 32769, 32768, 0]
    );
    // add_scalar(5): 0 + 5, 126 + 5, 127 + 5, 255 + 5 = 260 -> clamped 255.
    let add = |k: i32, d: u16, t: VoxelType| UnaryOp::AddScalar(k).apply(d, t);
    assert_eq!(
        [0, 126, 127, 255].map(|d| add(5, d, U8)),
        [5, 131, 132, 255]
    );
    // add_scalar(-127): 0 - 127 -> 0; 126 - 127 -> 0; 127 - 127 = 0; 255 - 127 = 128.
    assert_eq!([0, 126, 127, 255].map(|d| add(-127, d, U8)), [0, 0, 0, 128]);
    // u16 add_scalar(-32767): 0, 0, 0, 32768; add_scalar(40000): 40000, 72766 -> H, ...
    assert_eq!(
        [0, 32766, 32767, 65535].map(|d| add(-32767, d, U16)),
        [0, 0, 0, 32768]
    );
    assert_eq!(
        [0, 32766, 32767, 65535].map(|d| add(40000, d, U16)),
        [40000, 65535, 65535, 65535]
    );
    // add_scalar(0) is the identity.
    assert_eq!(
        [0, 126, 127, 255].map(|d| add(0, d, U8)),
        [0, 126, 127, 255]
    );
}

/// The spec's classification of op(D1, L): identity for union, the differences, add, trim;
/// the constant L for intersection, cap, modulate, product; H for divide and divide_a.
#[test]
fn outside_classification() {
    for t in [U8, U16] {
        for op in [
            BinaryOp::Union,
            BinaryOp::Difference,
            BinaryOp::DifferenceA,
            BinaryOp::DifferenceB,
            BinaryOp::Add,
            BinaryOp::Trim,
        ] {
            assert_eq!(op.outside(t), Outside::Identity, "{op:?}");
        }
        for op in [
            BinaryOp::Intersection,
            BinaryOp::Cap,
            BinaryOp::Modulate,
            BinaryOp::Product,
        ] {
            assert_eq!(op.outside(t), Outside::Constant(0), "{op:?}");
        }
        for op in [BinaryOp::DivideA, BinaryOp::Divide(0.3)] {
            assert_eq!(op.outside(t), Outside::Constant(t.high()), "{op:?}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Terms: B-boxes and composition
// ---------------------------------------------------------------------------------------------

const A: &str = r#"{"cuboid": {"origin": [0, 0, 0], "size": [10, 10, 10]}}"#;
const B: &str = r#"{"ellipsoid": {"center": [12, 5, 5], "radii": [4, 3, 2]}}"#;

fn pair(op: &str) -> String {
    format!(r#"{{"{op}": [{A}, {B}]}}"#)
}

#[test]
fn term_bboxes() {
    // A: [0,0,0]..[10,10,10]; B: [8,2,3]..[17,9,8].
    let hull = Some(Box3::new([0, 0, 0], [17, 10, 10]));
    let overlap = Some(Box3::new([8, 2, 3], [10, 9, 8]));
    let left = Some(Box3::new([0, 0, 0], [10, 10, 10]));
    for (op, want) in [
        ("union", hull),
        ("add", hull),
        ("intersection", overlap),
        ("cap", overlap),
        ("modulate", overlap),
        ("product", overlap),
        ("difference", left),
        ("difference_a", left),
        ("difference_b", left),
        ("trim", left),
        ("divide_a", None),
    ] {
        assert_eq!(compile(&pair(op), U8).bbox, want, "{op}");
    }
    let divide = format!(r#"{{"divide": {{"s_l": 0.5, "args": [{A}, {B}]}}}}"#);
    assert_eq!(compile(&divide, U8).bbox, None, "divide maps (L, L) to H");
    assert_eq!(compile(&format!(r#"{{"inverse": {A}}}"#), U8).bbox, None);
    assert_eq!(compile(&format!(r#"{{"complement": {A}}}"#), U8).bbox, None);
    let up = format!(r#"{{"add_scalar": {{"k": 3, "arg": {A}}}}}"#);
    assert_eq!(compile(&up, U8).bbox, None, "add_scalar k > 0 lifts L");
    let down = format!(r#"{{"add_scalar": {{"k": -3, "arg": {A}}}}}"#);
    assert_eq!(compile(&down, U8).bbox, left, "add_scalar k < 0 keeps L");
}

#[test]
fn term_values_compose() {
    // At (9, 5, 5): A local (9,5,5): x = B-1 = 9 -> L. B: T = (-3, 0, 0), body(-4,0,0) = 1
    // (not < 1), body(-2,0,0) = 4/16; band body(T) = 9/16: 127 * 16/9 = 225.8 -> 225.
    // At (5, 5, 5): A interior -> H = 255; B outside its box -> L.
    // At (8, 5, 5): A local x = 8 = B-2 -> S = 127; B: T = (-4,0,0), band body 1 -> 127.
    // At (12, 5, 5): A outside -> L; B centre -> H.
    let at = [[9, 5, 5], [5, 5, 5], [8, 5, 5], [12, 5, 5]];
    let want: [(&str, [u16; 4]); 7] = [
        ("union", [225, 255, 127, 255]),
        ("intersection", [0, 0, 127, 0]),
        // difference: (L, 225): D1 < S -> max(-225, 0) = 0; (H, L) = 255;
        // (S, S): D2 >= S -> 0; (L, H) -> 0.
        ("difference", [0, 255, 0, 0]),
        // add: 225, 255, 254, 255.
        ("add", [225, 255, 254, 255]),
        // trim: (0, 225) -> L; (255, 0) -> 255; (127, 127) -> 127; (0, 255) -> L.
        ("trim", [0, 255, 127, 0]),
        // product: 0; 0; 127 * 127 / 255 = 63; 0.
        ("product", [0, 0, 63, 0]),
        // divide_a: 0 / 225 = 0; (255, 0) -> H; 127 / 127 = 1; 0 / 255 = 0.
        ("divide_a", [0, 255, 1, 0]),
    ];
    for (op, values) in want {
        let term = compile(&pair(op), U8);
        for (v, w) in at.iter().zip(values) {
            assert_eq!(term.sample(*v), w, "{op} at {v:?}");
        }
    }
    // inverse(A) at (5,5,5) = 255 - 255 = 0; far away = 255 - 0 = 255;
    // add_scalar(-20, A) at (8,5,5) = 127 - 20 = 107; complement = inverse.
    let inv = compile(&format!(r#"{{"inverse": {A}}}"#), U8);
    assert_eq!(inv.sample([5, 5, 5]), 0);
    assert_eq!(inv.sample([100, -50, 7]), 255);
    let comp = compile(&format!(r#"{{"complement": {A}}}"#), U16);
    assert_eq!(comp.sample([8, 5, 5]), 65535 - 32767);
    let sub = compile(
        &format!(r#"{{"add_scalar": {{"k": -20, "arg": {A}}}}}"#),
        U8,
    );
    assert_eq!(sub.sample([8, 5, 5]), 107);
    // divide(0.5) at (8,5,5): 127 / (127 * 0.5) = 2; far away (L, L) -> H.
    let div = compile(
        &format!(r#"{{"divide": {{"s_l": 0.5, "args": [{A}, {B}]}}}}"#),
        U8,
    );
    assert_eq!(div.sample([8, 5, 5]), 2);
    assert_eq!(div.sample([-40, 0, 0]), 255);
}

// ---------------------------------------------------------------------------------------------
// Term JSON: the spec's examples parse, bad terms are refused with a message naming the problem.
// ---------------------------------------------------------------------------------------------

fn parse(json: &str) -> Term {
    serde_json::from_str(json).unwrap_or_else(|e| panic!("{json}: {e}"))
}

#[test]
fn spec_leaf_examples_parse() {
    assert_eq!(
        parse(r#"{"cuboid":    {"origin": [1, 2, 3], "size": [4, 5, 6]}}"#),
        Term::Cuboid {
            origin: [1, 2, 3],
            size: [4, 5, 6]
        }
    );
    assert_eq!(
        parse(r#"{"ellipsoid": {"center": [-1, 2, 3], "radii": [4, 5, 6]}}"#),
        Term::Ellipsoid {
            center: [-1, 2, 3],
            radii: [4, 5, 6]
        }
    );
    assert_eq!(
        parse(r#"{"cylinder":  {"base": [1, 2, 3], "radii": [4, 5], "height": 6}}"#),
        Term::Cylinder {
            base: [1, 2, 3],
            radii: [4, 5],
            height: 6
        }
    );
    assert_eq!(
        parse(r#"{"cone":      {"base": [1, 2, 3], "radii": [4, 5], "height": 6}}"#),
        Term::Cone {
            base: [1, 2, 3],
            radii: [4, 5],
            height: 6
        }
    );
    assert_eq!(
        parse(r#"{"volume":    {"name": "other", "origin": [1, 2, 3]}}"#),
        Term::Volume {
            name: "other".into(),
            origin: [1, 2, 3],
            region: None
        }
    );
    assert_eq!(
        parse(r#"{"torus": {"center": [1, 2, 3], "major": 6, "minor": 2}}"#),
        Term::Torus {
            center: [1, 2, 3],
            major: 6,
            minor: 2
        }
    );
    assert_eq!(
        parse(r#"{"capsule": {"center": [1, 2, 3], "radius": 2, "length": 5}}"#),
        Term::Capsule {
            center: [1, 2, 3],
            radius: 2,
            length: 5
        }
    );
    assert_eq!(
        parse(r#"{"prism": {"origin": [1, 2, 3], "size": [4, 5, 6]}}"#),
        Term::Prism {
            origin: [1, 2, 3],
            size: [4, 5, 6]
        }
    );
    assert_eq!(
        parse(r#"{"pyramid": {"origin": [1, 2, 3], "size": [4, 5, 6]}}"#),
        Term::Pyramid {
            origin: [1, 2, 3],
            size: [4, 5, 6]
        }
    );
}

#[test]
fn spec_inner_node_examples_parse() {
    let a = || Box::new(parse(A));
    let b = || Box::new(parse(B));
    let binary: [(&str, Term); 11] = [
        ("union", Term::Union(a(), b())),
        ("intersection", Term::Intersection(a(), b())),
        ("trim", Term::Trim(a(), b())),
        ("cap", Term::Cap(a(), b())),
        ("difference", Term::Difference(a(), b())),
        ("difference_a", Term::DifferenceA(a(), b())),
        ("difference_b", Term::DifferenceB(a(), b())),
        ("add", Term::Add(a(), b())),
        ("modulate", Term::Modulate(a(), b())),
        ("product", Term::Product(a(), b())),
        ("divide_a", Term::DivideA(a(), b())),
    ];
    for (name, want) in binary {
        let term = parse(&pair(name));
        assert_eq!(term, want, "{name}");
        // Serializes back to the same one-key object.
        let back: serde_json::Value = serde_json::to_value(&term).unwrap();
        assert!(back.get(name).is_some(), "{name} serializes as {back}");
        CompiledTerm::compile(&term, U8, &TermLimits::default(), &NoVolumes).unwrap();
    }
    assert_eq!(
        parse(&format!(
            r#"{{"divide": {{"s_l": 0.5, "args": [{A}, {B}]}}}}"#
        )),
        Term::Divide {
            s_l: 0.5,
            args: (a(), b())
        }
    );
    assert_eq!(parse(&format!(r#"{{"inverse": {A}}}"#)), Term::Inverse(a()));
    assert_eq!(
        parse(&format!(r#"{{"complement": {A}}}"#)),
        Term::Complement(a())
    );
    assert_eq!(
        parse(&format!(r#"{{"add_scalar": {{"k": -20, "arg": {A}}}}}"#)),
        Term::AddScalar { k: -20, arg: a() }
    );
}

#[test]
fn spec_edit_request_examples_parse() {
    let t = r#"{"ellipsoid": {"center": [64, 64, 64], "radii": [16, 16, 16]}}"#;
    let req: EditRequest =
        serde_json::from_str(&format!(r#"{{"op": "difference", "term": {t}}}"#)).unwrap();
    assert_eq!(req.op, "difference");
    assert_eq!(req.term, Some(parse(t)));
    assert_eq!((req.s_l, req.k, req.region), (None, None, None));
    let edit = Edit::from_request(&req, U8, &TermLimits::default(), &NoVolumes).unwrap();
    assert!(matches!(
        edit.kind,
        EditKind::Binary(BinaryOp::Difference, _)
    ));
    assert_eq!(edit.region, None);

    let req: EditRequest =
        serde_json::from_str(&format!(r#"{{"op": "divide", "s_l": 0.5, "term": {t}}}"#)).unwrap();
    assert_eq!(req.s_l, Some(0.5));
    let edit = Edit::from_request(&req, U16, &TermLimits::default(), &NoVolumes).unwrap();
    assert!(matches!(edit.kind, EditKind::Binary(BinaryOp::Divide(s), _) if s == 0.5));

    let req: EditRequest = serde_json::from_str(r#"{"op": "inverse"}"#).unwrap();
    let edit = Edit::from_request(&req, U8, &TermLimits::default(), &NoVolumes).unwrap();
    assert!(matches!(edit.kind, EditKind::Unary(UnaryOp::Inverse)));

    let req: EditRequest = serde_json::from_str(
        r#"{"op": "add_scalar", "k": 5, "region": {"min": [0, 1, 2], "max": [32, 33, 34]}}"#,
    )
    .unwrap();
    assert_eq!(
        req.region,
        Some(Box3 {
            min: [0, 1, 2],
            max: [32, 33, 34]
        })
    );
    let edit = Edit::from_request(&req, U8, &TermLimits::default(), &NoVolumes).unwrap();
    assert!(matches!(edit.kind, EditKind::Unary(UnaryOp::AddScalar(5))));
    assert_eq!(edit.region, Some(Box3::new([0, 1, 2], [32, 33, 34])));

    let req: EditRequest = serde_json::from_str(
        r#"{"op": "add_scalar", "k": -20, "region": {"min": [0, 0, 0], "max": [32, 32, 32]}}"#,
    )
    .unwrap();
    let edit = Edit::from_request(&req, U8, &TermLimits::default(), &NoVolumes).unwrap();
    assert!(matches!(
        edit.kind,
        EditKind::Unary(UnaryOp::AddScalar(-20))
    ));

    // Every binary operator name is accepted as an edit.
    for name in [
        "union",
        "intersection",
        "trim",
        "cap",
        "difference",
        "difference_a",
        "difference_b",
        "add",
        "modulate",
        "product",
        "divide_a",
    ] {
        let req: EditRequest =
            serde_json::from_str(&format!(r#"{{"op": "{name}", "term": {t}}}"#)).unwrap();
        let edit = Edit::from_request(&req, U8, &TermLimits::default(), &NoVolumes).unwrap();
        match edit.kind {
            EditKind::Binary(op, _) => assert_eq!(op.name(), name),
            other => panic!("{name} gave {other:?}"),
        }
    }
}

#[test]
fn unknown_operator_is_refused() {
    // In a term: serde names the unknown variant.
    let e = serde_json::from_str::<Term>(&format!(r#"{{"blend": [{A}, {B}]}}"#))
        .unwrap_err()
        .to_string();
    assert!(e.contains("blend"), "{e}");
    let e = serde_json::from_str::<Term>(r#"{"sphere": {"center": [0, 0, 0], "radius": 3}}"#)
        .unwrap_err()
        .to_string();
    assert!(e.contains("sphere"), "{e}");
    // In an edit.
    let e = edit_err(&format!(r#"{{"op": "blend", "term": {A}}}"#));
    assert!(e.contains("blend") && e.contains("operator"), "{e}");
    // A unary edit given a term, a binary edit without one.
    let e = edit_err(&format!(r#"{{"op": "inverse", "term": {A}}}"#));
    assert!(e.contains("inverse") && e.contains("term"), "{e}");
    let e = edit_err(r#"{"op": "union"}"#);
    assert!(e.contains("union") && e.contains("term"), "{e}");
    let e = edit_err(r#"{"op": "add_scalar"}"#);
    assert!(e.contains("add_scalar") && e.contains('k'), "{e}");
}

#[test]
fn zero_radius_is_refused() {
    for (json, what) in [
        (
            r#"{"ellipsoid": {"center": [0, 0, 0], "radii": [3, 0, 3]}}"#,
            "ellipsoid radius",
        ),
        (
            r#"{"cylinder": {"base": [0, 0, 0], "radii": [0, 2], "height": 5}}"#,
            "cylinder radius",
        ),
        (
            r#"{"cone": {"base": [0, 0, 0], "radii": [2, 0], "height": 5}}"#,
            "cone radius",
        ),
        (
            r#"{"torus": {"center": [0, 0, 0], "major": 4, "minor": 0}}"#,
            "torus minor radius",
        ),
        // Every radius of 0 is refused, the ring's too (a ring of radius 0 is a ball).
        (
            r#"{"torus": {"center": [0, 0, 0], "major": 0, "minor": 4}}"#,
            "torus major radius",
        ),
        (
            r#"{"capsule": {"center": [0, 0, 0], "radius": 0, "length": 4}}"#,
            "capsule radius",
        ),
    ] {
        let e = compile_err(json);
        assert!(e.contains(what), "{json}: {e}");
    }
    // Radius 1 is fine.
    compile(
        r#"{"ellipsoid": {"center": [0, 0, 0], "radii": [1, 1, 1]}}"#,
        U8,
    );
}

#[test]
fn thin_cuboid_is_refused() {
    for size in [[2, 5, 5], [5, 2, 5], [5, 5, 2], [0, 5, 5], [1, 1, 1]] {
        let e = compile_err(&format!(
            r#"{{"cuboid": {{"origin": [0, 0, 0], "size": {size:?}}}}}"#
        ));
        assert!(
            e.contains("cuboid") && e.contains("greater than 2"),
            "{size:?}: {e}"
        );
    }
    // Side 3 is the smallest: L, S, L.
    let c = compile(
        r#"{"cuboid": {"origin": [0, 0, 0], "size": [3, 3, 3]}}"#,
        U8,
    );
    assert_eq!(c.sample([1, 1, 1]), 127);
    assert_eq!(c.sample([0, 1, 1]), 0);
}

/// `{"inverse": ... {"inverse": leaf}}` with `depth` operators.
fn nested(depth: usize) -> Term {
    let mut t = parse(A);
    for _ in 0..depth {
        t = Term::Inverse(Box::new(t));
    }
    t
}

#[test]
fn too_deep_is_refused() {
    let limits = TermLimits::default();
    assert_eq!(limits.max_depth, 32);
    // 32 nested operators are allowed; 33 are not.
    CompiledTerm::compile(&nested(32), U8, &limits, &NoVolumes).unwrap();
    let e = CompiledTerm::compile(&nested(33), U8, &limits, &NoVolumes)
        .unwrap_err()
        .to_string();
    assert!(e.contains("deeper") && e.contains("32"), "{e}");
    // The same through JSON and an edit request (the edit's term is the root).
    let json = serde_json::to_string(&nested(33)).unwrap();
    let e = edit_err(&format!(r#"{{"op": "union", "term": {json}}}"#));
    assert!(e.contains("deeper"), "{e}");
    // A deep chain of binary nodes: union(union(... leaf ..., B), B), 33 levels.
    let mut t = parse(A);
    for _ in 0..33 {
        t = Term::Union(Box::new(t), Box::new(parse(B)));
    }
    let e = CompiledTerm::compile(&t, U8, &limits, &NoVolumes)
        .unwrap_err()
        .to_string();
    assert!(e.contains("deeper"), "{e}");
}

#[test]
fn s_l_out_of_range_is_refused() {
    for s_l in ["0", "0.0", "-0.5", "1.5", "2", "1e300"] {
        let e = compile_err(&format!(
            r#"{{"divide": {{"s_l": {s_l}, "args": [{A}, {B}]}}}}"#
        ));
        assert!(e.contains("s_l") && e.contains("(0, 1]"), "s_l {s_l}: {e}");
        let e = edit_err(&format!(r#"{{"op": "divide", "s_l": {s_l}, "term": {A}}}"#));
        assert!(e.contains("s_l"), "edit s_l {s_l}: {e}");
    }
    let e = edit_err(&format!(r#"{{"op": "divide", "term": {A}}}"#));
    assert!(e.contains("s_l"), "divide without s_l: {e}");
    // The boundaries that are allowed: 1, and anything just above 0.
    for s_l in ["1", "1.0", "0.000001"] {
        compile(
            &format!(r#"{{"divide": {{"s_l": {s_l}, "args": [{A}, {B}]}}}}"#),
            U8,
        );
    }
}

/// The edit examples of docs/icvg.md parse and build.
#[test]
fn docs_edit_examples_parse() {
    for json in [
        r#"{"op": "difference", "term": {"ellipsoid": {"center": [256, 100, 256], "radii": [16, 16, 16]}}}"#,
        r#"{"op": "union", "term": {"cuboid": {"origin": [10, 0, 10], "size": [40, 30, 40]}},
            "region": {"min": [0, 0, 0], "max": [32, 64, 64]}}"#,
        r#"{"op": "divide", "s_l": 0.5, "term": {"cuboid": {"origin": [0, 0, 0], "size": [8, 8, 8]}}}"#,
        r#"{"op": "inverse", "region": {"min": [0, 0, 0], "max": [64, 64, 64]}}"#,
        r#"{"op": "add_scalar", "k": -20}"#,
        r#"{"op": "complement"}"#,
    ] {
        let req: EditRequest = serde_json::from_str(json).unwrap_or_else(|e| panic!("{json}: {e}"));
        Edit::from_request(&req, U16, &TermLimits::default(), &NoVolumes)
            .unwrap_or_else(|e| panic!("{json}: {e}"));
    }
}

/// The other refusals docs/icvg.md lists, each with a message naming the problem.
#[test]
fn other_validation_errors() {
    let cases = [
        (
            r#"{"cylinder": {"base": [0, 0, 0], "radii": [2, 2], "height": 2}}"#,
            "height",
        ),
        (
            r#"{"cone": {"base": [0, 0, 0], "radii": [2, 2], "height": 2}}"#,
            "height",
        ),
        (
            r#"{"prism": {"origin": [0, 0, 0], "size": [3, 5, 5]}}"#,
            "prism",
        ),
        (
            r#"{"pyramid": {"origin": [0, 0, 0], "size": [5, 5, 3]}}"#,
            "pyramid",
        ),
        (
            r#"{"cuboid": {"origin": [0, 0, 0], "size": [65537, 5, 5]}}"#,
            "limit",
        ),
        (
            r#"{"ellipsoid": {"center": [0, 0, 0], "radii": [32768, 1, 1]}}"#,
            "limit",
        ),
        (
            r#"{"add_scalar": {"k": 256, "arg": {"cuboid": {"origin": [0, 0, 0], "size": [3, 3, 3]}}}}"#,
            "k = 256",
        ),
        (
            r#"{"volume": {"name": "nowhere", "origin": [0, 0, 0]}}"#,
            "nowhere",
        ),
    ];
    for (json, what) in cases {
        let e = compile_err(json);
        assert!(e.contains(what), "{json}: {e}");
    }
    // Extension 65536 is the limit itself: allowed (2 * 32767 + 1 = 65535 too).
    compile(
        r#"{"cuboid": {"origin": [0, 0, 0], "size": [65536, 3, 3]}}"#,
        U8,
    );
    // More than 256 nodes: a balanced tree of 2^8 = 256 leaves has 511 nodes, depth 8.
    let mut level: Vec<Term> = (0..256).map(|_| parse(A)).collect();
    while level.len() > 1 {
        level = level
            .chunks(2)
            .map(|p| Term::Union(Box::new(p[0].clone()), Box::new(p[1].clone())))
            .collect();
    }
    let e = CompiledTerm::compile(&level[0], U8, &TermLimits::default(), &NoVolumes)
        .unwrap_err()
        .to_string();
    assert!(e.contains("256 nodes"), "{e}");
    // k beyond +-H in an edit; u16 accepts what u8 refuses.
    let e = edit_err(r#"{"op": "add_scalar", "k": -256}"#);
    assert!(e.contains("k = -256"), "{e}");
    let req: EditRequest = serde_json::from_str(r#"{"op": "add_scalar", "k": -256}"#).unwrap();
    Edit::from_request(&req, U16, &TermLimits::default(), &NoVolumes).unwrap();
    // Unknown fields, and arguments the operator does not take.
    assert!(serde_json::from_str::<Term>(
        r#"{"cuboid": {"origin": [0, 0, 0], "size": [4, 4, 4], "colour": 1}}"#
    )
    .is_err());
    let e = edit_err(&format!(r#"{{"op": "union", "s_l": 0.5, "term": {A}}}"#));
    assert!(e.contains("s_l") && e.contains("divide"), "{e}");
    let e = edit_err(r#"{"op": "inverse", "k": 3}"#);
    assert!(e.contains("\"k\"") && e.contains("add_scalar"), "{e}");
    // Coordinates beyond +-2^53, in a term or a region; 2^53 itself is fine.
    let e = edit_err(
        r#"{"op": "inverse", "region": {"min": [0, 0, 0], "max": [9007199254740993, 1, 1]}}"#,
    );
    assert!(e.contains("coordinate limit"), "{e}");
    let e = edit_err(
        r#"{"op": "union", "term": {"ellipsoid": {"center": [0, -9007199254740993, 0], "radii": [3, 3, 3]}}}"#,
    );
    assert!(
        e.contains("ellipsoid center") && e.contains("coordinate limit"),
        "{e}"
    );
    compile(
        r#"{"cuboid": {"origin": [9007199254740992, 0, -9007199254740992], "size": [4, 4, 4]}}"#,
        U8,
    );
    // A region with max <= min on an axis selects nothing: accepted, evaluating no voxel.
    let layout = isovox_proto::VolumeLayout::new([64, 64, 64], 16, U8).unwrap();
    for region in [r#"[4, 0, 4]"#, r#"[-4, 64, 64]"#] {
        let req: EditRequest = serde_json::from_str(&format!(
            r#"{{"op": "inverse", "region": {{"min": [0, 0, 0], "max": {region}}}}}"#
        ))
        .unwrap();
        let edit = Edit::from_request(&req, U8, &TermLimits::default(), &NoVolumes).unwrap();
        assert_eq!(edit.evaluated_voxels(&layout), 0, "max {region}");
    }
}

#[test]
fn torus_and_capsule_fields_are_bounded_one_by_one() {
    // A quarter of the 65,536-voxel extension limit per radius, half of it for the length:
    // then the extension stays within the limit whatever the other field is.
    for (json, ok) in [
        (
            r#"{"torus": {"center": [0, 0, 0], "major": 16383, "minor": 16383}}"#,
            true,
        ),
        (
            r#"{"torus": {"center": [0, 0, 0], "major": 16384, "minor": 1}}"#,
            false,
        ),
        (
            r#"{"torus": {"center": [0, 0, 0], "major": 1, "minor": 16384}}"#,
            false,
        ),
        (
            r#"{"capsule": {"center": [0, 0, 0], "radius": 16383, "length": 32768}}"#,
            true,
        ),
        (
            r#"{"capsule": {"center": [0, 0, 0], "radius": 16384, "length": 0}}"#,
            false,
        ),
        (
            r#"{"capsule": {"center": [0, 0, 0], "radius": 1, "length": 32769}}"#,
            false,
        ),
    ] {
        if ok {
            compile(json, U8);
        } else {
            let e = compile_err(json);
            assert!(e.contains("over the limit"), "{json}: {e}");
        }
    }
}
