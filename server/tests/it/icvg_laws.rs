//! Algebraic laws of the ICVG operators (property tests over u8 and u16 values), and the
//! agreement of the fast term evaluation (`CompiledTerm::eval` over a box, with its constant
//! shortcuts) with the voxel-by-voxel reference (`CompiledTerm::sample`) on random terms.

use isovox_proto::icvg::Term;
use isovox_proto::VoxelType;
use isovox_server::geometry::Box3;
use isovox_server::icvg::ops::{BinaryOp, UnaryOp};
use isovox_server::icvg::term::{CompiledTerm, NoVolumes, TermLimits};
use proptest::prelude::*;

use crate::random_terms;

const ALL_BINARY: [BinaryOp; 12] = [
    BinaryOp::Union,
    BinaryOp::Intersection,
    BinaryOp::Trim,
    BinaryOp::Cap,
    BinaryOp::Difference,
    BinaryOp::DifferenceA,
    BinaryOp::DifferenceB,
    BinaryOp::Add,
    BinaryOp::Modulate,
    BinaryOp::Product,
    BinaryOp::DivideA,
    BinaryOp::Divide(0.37),
];

/// A voxel value of type `t`, often one of the boundaries L, S-1, S, S+1, H-1, H.
fn value(t: VoxelType) -> impl Strategy<Value = u16> {
    let (s, h) = (t.surface(), t.high());
    prop_oneof![
        1 => Just(0u16),
        1 => Just(s - 1),
        1 => Just(s),
        1 => Just(s + 1),
        1 => Just(h - 1),
        1 => Just(h),
        6 => 0..=h,
    ]
}

/// A voxel type and three values of it.
fn typed() -> impl Strategy<Value = (VoxelType, u16, u16, u16)> {
    prop_oneof![Just(VoxelType::U8), Just(VoxelType::U16)]
        .prop_flat_map(|t| (Just(t), value(t), value(t), value(t)))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn union_and_intersection_laws((t, a, b, c) in typed()) {
        for op in [BinaryOp::Union, BinaryOp::Intersection] {
            let f = |x, y| op.apply(x, y, t);
            prop_assert_eq!(f(a, b), f(b, a), "{:?} commutative", op);
            prop_assert_eq!(f(f(a, b), c), f(a, f(b, c)), "{:?} associative", op);
            prop_assert_eq!(f(a, a), a, "{:?} idempotent", op);
        }
        // Union is the larger, intersection the smaller.
        prop_assert_eq!(BinaryOp::Union.apply(a, b, t), a.max(b));
        prop_assert_eq!(BinaryOp::Intersection.apply(a, b, t), a.min(b));
    }

    #[test]
    fn identities_with_l_and_h((t, d, _, _) in typed()) {
        let (l, h) = (t.low(), t.high());
        for op in [BinaryOp::Difference, BinaryOp::DifferenceA, BinaryOp::DifferenceB] {
            prop_assert_eq!(op.apply(d, l, t), d, "{:?}(D, L) = D", op);
        }
        prop_assert_eq!(BinaryOp::Union.apply(d, l, t), d, "union with L");
        prop_assert_eq!(BinaryOp::Union.apply(l, d, t), d, "union with L (left)");
        prop_assert_eq!(BinaryOp::Intersection.apply(d, h, t), d, "intersection with H");
        prop_assert_eq!(BinaryOp::Intersection.apply(d, l, t), l, "intersection with L");
        prop_assert_eq!(BinaryOp::Add.apply(d, l, t), d, "add L");
        prop_assert_eq!(BinaryOp::Trim.apply(d, l, t), d, "trim with L");
        prop_assert_eq!(BinaryOp::Trim.apply(d, d, t), d, "trim(D, D)");
        prop_assert_eq!(BinaryOp::Cap.apply(d, d, t), d, "cap(D, D)");
        prop_assert_eq!(BinaryOp::Product.apply(d, h, t), d, "product with H");
        prop_assert_eq!(BinaryOp::Cap.apply(d, l, t), l, "cap with L");
        prop_assert_eq!(BinaryOp::Modulate.apply(d, l, t), l, "modulate with L");
        prop_assert_eq!(BinaryOp::DivideA.apply(d, l, t), h, "divide_a by L");
        prop_assert_eq!(BinaryOp::Divide(0.5).apply(d, l, t), h, "divide by L");
    }

    #[test]
    fn inverse_is_an_involution((t, d, _, _) in typed()) {
        let inv = |x| UnaryOp::Inverse.apply(x, t);
        prop_assert_eq!(inv(inv(d)), d);
        prop_assert_eq!(inv(d) as u32 + d as u32, t.high() as u32);
    }

    #[test]
    fn add_is_commutative((t, a, b, _) in typed()) {
        prop_assert_eq!(BinaryOp::Add.apply(a, b, t), BinaryOp::Add.apply(b, a, t));
        prop_assert_eq!(BinaryOp::Modulate.apply(a, b, t), BinaryOp::Modulate.apply(b, a, t));
        prop_assert_eq!(BinaryOp::Product.apply(a, b, t), BinaryOp::Product.apply(b, a, t));
    }

    #[test]
    fn add_scalar_round_trip((t, d, _, _) in typed(), k in -65535i32..=65535) {
        let h = t.high() as i32;
        let k = k.clamp(-h, h);
        let up = UnaryOp::AddScalar(k).apply(d, t);
        let sum = d as i32 + k;
        if (0..=h).contains(&sum) {
            // No clamping: add_scalar(-k) undoes add_scalar(k).
            prop_assert_eq!(up as i32, sum);
            prop_assert_eq!(UnaryOp::AddScalar(-k).apply(up, t), d);
        } else {
            prop_assert_eq!(up as i32, sum.clamp(0, h), "clamped to [L, H]");
        }
    }

    /// Every operator's result is in [L, H]; the differences never add material; a union never
    /// removes any.
    #[test]
    fn results_in_range_and_monotone((t, a, b, _) in typed()) {
        for op in ALL_BINARY {
            let r = op.apply(a, b, t);
            prop_assert!(r <= t.high(), "{:?}({}, {}) = {} > H", op, a, b, r);
        }
        for op in [BinaryOp::Difference, BinaryOp::DifferenceA, BinaryOp::DifferenceB] {
            prop_assert!(op.apply(a, b, t) <= a, "{:?} adds material", op);
        }
        prop_assert!(BinaryOp::Union.apply(a, b, t) >= a);
        prop_assert!(BinaryOp::Union.apply(a, b, t) >= b);
    }
}

// ---------------------------------------------------------------------------------------------
// Terms: eval over a box equals sample voxel by voxel.
// ---------------------------------------------------------------------------------------------

fn pos() -> impl Strategy<Value = [i64; 3]> + Clone {
    prop::array::uniform3(-8i64..24)
}

/// A random primitive (all eight kinds), about a box's size.
fn leaf() -> impl Strategy<Value = Term> {
    random_terms::leaf(pos(), 12)
}

/// Random trees of depth <= 3 over random primitives and every operator.
fn term() -> impl Strategy<Value = Term> {
    leaf().prop_recursive(3, 15, 2, |inner| {
        prop_oneof![
            4 => (0u8..12, inner.clone(), inner.clone(), 1u32..=100)
                .prop_map(|(w, a, b, s)| random_terms::binary(w, a, b, s as f64 / 100.0)),
            1 => inner.clone().prop_map(|a| Term::Inverse(Box::new(a))),
            1 => inner.clone().prop_map(|a| Term::Complement(Box::new(a))),
            1 => (-255i32..=255, inner).prop_map(|(k, a)| Term::AddScalar { k, arg: Box::new(a) }),
        ]
    })
}

fn a_box() -> impl Strategy<Value = Box3> {
    (
        prop::array::uniform3(-14i64..32),
        prop::array::uniform3(1i64..15),
    )
        .prop_map(|(min, size)| Box3::new(min, [0, 1, 2].map(|a| min[a] + size[a])))
}

fn check_eval(term: &Term, t: VoxelType, b: &Box3) -> Result<(), TestCaseError> {
    let c = CompiledTerm::compile(term, t, &TermLimits::default(), &NoVolumes).unwrap();
    let mut out = vec![0u16; b.voxels() as usize];
    c.eval(b, &mut out).unwrap();
    let mut i = 0;
    for z in b.min[2]..b.max[2] {
        for y in b.min[1]..b.max[1] {
            for x in b.min[0]..b.max[0] {
                let want = c.sample([x, y, z]);
                prop_assert_eq!(
                    out[i],
                    want,
                    "{} eval at ({},{},{}) of {:?} over {:?}",
                    t,
                    x,
                    y,
                    z,
                    term,
                    b
                );
                prop_assert!(want <= t.high());
                // Outside the B-box the term is L.
                if let Some(bb) = c.bbox {
                    if !bb.contains([x, y, z]) {
                        prop_assert_eq!(want, 0, "{:?} outside its B-box {:?}", term, bb);
                    }
                }
                i += 1;
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn eval_equals_sample(term in term(), u16s in any::<bool>(), b in a_box()) {
        let t = if u16s { VoxelType::U16 } else { VoxelType::U8 };
        check_eval(&term, t, &b)?;
    }

    /// A single primitive over boxes that straddle it, so that the constant shortcuts of
    /// `eval` (whole sub-boxes inside or outside) are exercised at their edges.
    #[test]
    fn eval_equals_sample_on_primitives(term in leaf(), u16s in any::<bool>(), b in a_box()) {
        let t = if u16s { VoxelType::U16 } else { VoxelType::U8 };
        check_eval(&term, t, &b)?;
    }
}

/// Boxes well inside and well outside large primitives (where the constant shortcuts decide
/// whole boxes without sampling) agree with sampling.
#[test]
fn eval_shortcuts_on_large_primitives() {
    let terms = [
        r#"{"ellipsoid": {"center": [40, 30, 35], "radii": [33, 25, 29]}}"#,
        r#"{"cuboid": {"origin": [-3, 5, 7], "size": [30, 21, 17]}}"#,
        r#"{"cylinder": {"base": [10, -4, 3], "radii": [17, 12], "height": 30}}"#,
        r#"{"cone": {"base": [10, -4, 3], "radii": [17, 12], "height": 30}}"#,
        r#"{"union": [{"ellipsoid": {"center": [0, 0, 0], "radii": [20, 20, 20]}},
                      {"inverse": {"cuboid": {"origin": [-5, -5, -5], "size": [10, 10, 10]}}}]}"#,
        r#"{"difference": [{"cuboid": {"origin": [-30, -30, -30], "size": [60, 60, 60]}},
                           {"ellipsoid": {"center": [0, 0, 0], "radii": [20, 20, 20]}}]}"#,
    ];
    let mut decided = 0;
    for json in terms {
        let term: Term = serde_json::from_str(json).unwrap();
        for t in [VoxelType::U8, VoxelType::U16] {
            let c = CompiledTerm::compile(&term, t, &TermLimits::default(), &NoVolumes).unwrap();
            for z in (-32..48).step_by(8) {
                for y in (-32..48).step_by(8) {
                    for x in (-32..48).step_by(8) {
                        let b = Box3::new([x, y, z], [x + 8, y + 8, z + 8]);
                        if c.constant_over(&b).is_some() {
                            decided += 1;
                        }
                        check_eval(&term, t, &b).unwrap();
                    }
                }
            }
        }
    }
    // The shortcuts did fire (otherwise this test checks nothing about them).
    assert!(decided > 500, "{decided} boxes decided without sampling");
}
