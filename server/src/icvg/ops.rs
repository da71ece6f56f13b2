//! The operators of the algebra (`docs/icvg.md`, "Operators"). D1 is the existing volume, D2
//! the operand; every result is clamped to [L, H].

use isovox_proto::VoxelType;

/// A binary operator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BinaryOp {
    /// max(D1, D2).
    Union,
    /// min(D1, D2).
    Intersection,
    /// D1 where D1 >= D2, else L.
    Trim,
    /// D1 where D1 <= D2, else L.
    Cap,
    /// Carving that keeps the source's visible surface (`docs/icvg.md`).
    Difference,
    /// max(D1 - D2, L).
    DifferenceA,
    /// max(D1 - D2, L) where D2 >= S, else D1.
    DifferenceB,
    /// min(D1 + D2, H).
    Add,
    /// min(D1 * D2, H).
    Modulate,
    /// D1 * D2 / H.
    Product,
    /// D1 / D2 where D2 > 0, else H.
    DivideA,
    /// `S_L` real in (0, 1].
    Divide(f64),
}

/// Which operand of a binary operator a voxel's attributes come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AttributesFrom {
    /// The operand with the larger density there; the left one on a tie.
    Denser,
    /// Always the left one.
    Left,
}

impl AttributesFrom {
    /// The attribute of a voxel whose operands have densities `d1`, `d2` and attributes `a1`,
    /// `a2`.
    #[inline(always)]
    pub fn pick(self, d1: u16, a1: u64, d2: u16, a2: u64) -> u64 {
        match self {
            AttributesFrom::Denser if d2 > d1 => a2,
            _ => a1,
        }
    }
}

/// What a binary operator gives where the operand is L (outside the operand's B-box).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outside {
    /// `op(D1, L) = D1`: bricks the operand does not reach are left alone.
    Identity,
    /// `op(D1, L)` is this constant whatever D1 is: such bricks become the shared constant brick.
    Constant(u16),
}

impl BinaryOp {
    /// Every binary operator but `divide` (the one with an argument of its own, `s_l`).
    pub const WITHOUT_ARGUMENTS: [BinaryOp; 11] = [
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
    ];

    /// The operator named `name` (the JSON names), with `s_l` for divide.
    ///
    /// # Errors
    /// Unknown name, or divide without `s_l` in (0, 1].
    pub fn from_name(name: &str, s_l: Option<f64>) -> Result<BinaryOp, String> {
        Ok(match name {
            "union" => BinaryOp::Union,
            "intersection" => BinaryOp::Intersection,
            "trim" => BinaryOp::Trim,
            "cap" => BinaryOp::Cap,
            "difference" => BinaryOp::Difference,
            "difference_a" => BinaryOp::DifferenceA,
            "difference_b" => BinaryOp::DifferenceB,
            "add" => BinaryOp::Add,
            "modulate" => BinaryOp::Modulate,
            "product" => BinaryOp::Product,
            "divide_a" => BinaryOp::DivideA,
            "divide" => {
                let s_l = s_l.ok_or("divide needs \"s_l\", a real in (0, 1]")?;
                check_s_l(s_l)?;
                BinaryOp::Divide(s_l)
            }
            other => return Err(format!("unknown operator {other:?}")),
        })
    }

    /// The operator's name in terms and edit requests.
    pub fn name(self) -> &'static str {
        match self {
            BinaryOp::Union => "union",
            BinaryOp::Intersection => "intersection",
            BinaryOp::Trim => "trim",
            BinaryOp::Cap => "cap",
            BinaryOp::Difference => "difference",
            BinaryOp::DifferenceA => "difference_a",
            BinaryOp::DifferenceB => "difference_b",
            BinaryOp::Add => "add",
            BinaryOp::Modulate => "modulate",
            BinaryOp::Product => "product",
            BinaryOp::DivideA => "divide_a",
            BinaryOp::Divide(_) => "divide",
        }
    }

    /// `op(d1, d2)` for voxels of type `t`.
    #[inline(always)]
    pub fn apply(self, d1: u16, d2: u16, t: VoxelType) -> u16 {
        // In i32, which every result but a product's fits (operands are at most 65,535), so
        // that loops over voxels vectorize; products in i64.
        let (l, h, s) = (t.low() as i32, t.high() as i32, t.surface() as i32);
        let (a, b) = (d1 as i32, d2 as i32);
        let r = match self {
            BinaryOp::Union => a.max(b),
            BinaryOp::Intersection => a.min(b),
            BinaryOp::Trim => {
                if a >= b {
                    a
                } else {
                    l
                }
            }
            BinaryOp::Cap => {
                if a <= b {
                    a
                } else {
                    l
                }
            }
            BinaryOp::DifferenceA => (a - b).max(l),
            BinaryOp::DifferenceB => {
                if b >= s {
                    (a - b).max(l)
                } else {
                    a
                }
            }
            BinaryOp::Difference => {
                if a >= s && b < s {
                    (a - b).max(s)
                } else {
                    (a - b).max(l)
                }
            }
            BinaryOp::Add => (a + b).min(h),
            BinaryOp::Modulate => (i64::from(a) * i64::from(b)).min(i64::from(h)) as i32,
            BinaryOp::Product => (i64::from(a) * i64::from(b) / i64::from(h)) as i32,
            BinaryOp::DivideA => {
                if b > 0 {
                    a / b
                } else {
                    h
                }
            }
            BinaryOp::Divide(s_l) => {
                let den = b as f64 * s_l;
                if den > 0.0 {
                    (a as f64 / den).floor().min(h as f64) as i32
                } else {
                    h
                }
            }
        };
        r.clamp(l, h) as u16
    }

    /// `dst[i] = op(dst[i], operand[i])` over both slices (of equal length). The operator is
    /// chosen once and each loop is compiled for one operator, its arithmetic branch-free, so
    /// that it vectorizes; choosing it per voxel was most of an edit's own time past the
    /// term's evaluation.
    pub fn apply_in_place(self, dst: &mut [u16], operand: &[u16], t: VoxelType) {
        debug_assert_eq!(dst.len(), operand.len());
        #[inline(always)]
        fn each(dst: &mut [u16], operand: &[u16], op: impl Fn(u16, u16) -> u16) {
            for (d, &b) in dst.iter_mut().zip(operand) {
                *d = op(*d, b);
            }
        }
        use BinaryOp as B;
        match self {
            B::Union => each(dst, operand, |a, b| B::Union.apply(a, b, t)),
            B::Intersection => each(dst, operand, |a, b| B::Intersection.apply(a, b, t)),
            B::Trim => each(dst, operand, |a, b| B::Trim.apply(a, b, t)),
            B::Cap => each(dst, operand, |a, b| B::Cap.apply(a, b, t)),
            B::Difference => each(dst, operand, |a, b| B::Difference.apply(a, b, t)),
            B::DifferenceA => each(dst, operand, |a, b| B::DifferenceA.apply(a, b, t)),
            B::DifferenceB => each(dst, operand, |a, b| B::DifferenceB.apply(a, b, t)),
            B::Add => each(dst, operand, |a, b| B::Add.apply(a, b, t)),
            B::Modulate => each(dst, operand, |a, b| B::Modulate.apply(a, b, t)),
            B::Product => each(dst, operand, |a, b| B::Product.apply(a, b, t)),
            B::DivideA => each(dst, operand, |a, b| B::DivideA.apply(a, b, t)),
            B::Divide(s_l) => each(dst, operand, |a, b| B::Divide(s_l).apply(a, b, t)),
        }
    }

    /// Which operand a voxel's attributes (material, label) come from (`docs/channels.md`):
    /// CVG's rule for union and intersection (the operand with the larger density, the left
    /// on a tie), extended to `add`, whose result grows with both operands as a union's does;
    /// the left operand's for the differences (CVG's rule) and for every operator that trims,
    /// caps or scales the left operand by the right.
    pub fn attributes_from(self) -> AttributesFrom {
        match self {
            BinaryOp::Union | BinaryOp::Intersection | BinaryOp::Add => AttributesFrom::Denser,
            BinaryOp::Trim
            | BinaryOp::Cap
            | BinaryOp::Difference
            | BinaryOp::DifferenceA
            | BinaryOp::DifferenceB
            | BinaryOp::Modulate
            | BinaryOp::Product
            | BinaryOp::DivideA
            | BinaryOp::Divide(_) => AttributesFrom::Left,
        }
    }

    /// How the operator treats voxels the operand does not reach (`docs/icvg.md`).
    pub fn outside(self, t: VoxelType) -> Outside {
        match self {
            BinaryOp::Union
            | BinaryOp::Trim
            | BinaryOp::Difference
            | BinaryOp::DifferenceA
            | BinaryOp::DifferenceB
            | BinaryOp::Add => Outside::Identity,
            BinaryOp::Intersection | BinaryOp::Cap | BinaryOp::Modulate | BinaryOp::Product => {
                Outside::Constant(t.low())
            }
            BinaryOp::DivideA | BinaryOp::Divide(_) => Outside::Constant(t.high()),
        }
    }
}

/// Checks divide's `S_L`.
///
/// # Errors
/// Not a real in (0, 1].
pub fn check_s_l(s_l: f64) -> Result<(), String> {
    if s_l.is_finite() && s_l > 0.0 && s_l <= 1.0 {
        Ok(())
    } else {
        Err(format!("s_l must be a real in (0, 1], got {s_l}"))
    }
}

/// A unary operator.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UnaryOp {
    /// `H - D1` (CVG's complement).
    Inverse,
    /// `clamp(D1 + k)`.
    AddScalar(i32),
}

impl UnaryOp {
    /// [`UnaryOp::apply`] to every voxel of `dst`, the operator chosen once (see
    /// [`BinaryOp::apply_in_place`]).
    pub fn apply_in_place(self, dst: &mut [u16], t: VoxelType) {
        match self {
            UnaryOp::Inverse => dst
                .iter_mut()
                .for_each(|d| *d = UnaryOp::Inverse.apply(*d, t)),
            UnaryOp::AddScalar(k) => {
                let op = UnaryOp::AddScalar(k);
                dst.iter_mut().for_each(|d| *d = op.apply(*d, t));
            }
        }
    }

    /// The operator applied to one voxel value.
    #[inline(always)]
    pub fn apply(self, d1: u16, t: VoxelType) -> u16 {
        match self {
            UnaryOp::Inverse => t.high() - d1.min(t.high()),
            UnaryOp::AddScalar(k) => {
                (d1 as i64 + k as i64).clamp(t.low() as i64, t.high() as i64) as u16
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use BinaryOp::*;

    const U8: VoxelType = VoxelType::U8;

    /// (D1, D2) pairs at the boundaries L=0, S-1=126, S=127, H=255, and one in the middle.
    const CASES: [(u16, u16); 10] = [
        (0, 0),
        (0, 255),
        (255, 0),
        (255, 255),
        (127, 126),
        (126, 127),
        (127, 127),
        (200, 100),
        (100, 200),
        (126, 126),
    ];

    fn table(op: BinaryOp) -> Vec<u16> {
        CASES.iter().map(|&(a, b)| op.apply(a, b, U8)).collect()
    }

    // Each expected row is worked out by hand from the table in docs/icvg.md.
    #[test]
    fn union_intersection_trim_cap() {
        assert_eq!(
            table(Union),
            vec![0, 255, 255, 255, 127, 127, 127, 200, 200, 126]
        );
        assert_eq!(
            table(Intersection),
            vec![0, 0, 0, 255, 126, 126, 127, 100, 100, 126]
        );
        // trim: D1 if D1 >= D2 else L
        assert_eq!(table(Trim), vec![0, 0, 255, 255, 127, 0, 127, 200, 0, 126]);
        // cap: D1 if D1 <= D2 else L
        assert_eq!(table(Cap), vec![0, 0, 0, 255, 0, 126, 127, 0, 100, 126]);
    }

    #[test]
    fn differences() {
        // difference_a: max(D1 - D2, L)
        assert_eq!(table(DifferenceA), vec![0, 0, 255, 0, 1, 0, 0, 100, 0, 0]);
        // difference_b: max(D1 - D2, L) if D2 >= S else D1
        assert_eq!(
            table(DifferenceB),
            vec![0, 0, 255, 0, 127, 0, 0, 200, 0, 126]
        );
        // difference: max(D1 - D2, S) if D1 >= S and D2 < S, else max(D1 - D2, L).
        // (127,126): 127>=S, 126<S -> max(1, 127) = 127; (255,0): max(255,127) = 255;
        // (200,100): max(100,127) = 127; (126,126): D1 < S -> max(0, 0) = 0.
        assert_eq!(table(Difference), vec![0, 0, 255, 0, 127, 0, 0, 127, 0, 0]);
    }

    #[test]
    fn arithmetic() {
        assert_eq!(
            table(Add),
            vec![0, 255, 255, 255, 253, 253, 254, 255, 255, 252]
        );
        // modulate: min(D1 * D2, H)
        assert_eq!(
            table(Modulate),
            vec![0, 0, 0, 255, 255, 255, 255, 255, 255, 255]
        );
        // product: D1 * D2 / H, floored: 127*126/255 = 62.75 -> 62; 127*127/255 = 63.25 -> 63;
        // 200*100/255 = 78.4 -> 78; 126*126/255 = 62.26 -> 62.
        assert_eq!(table(Product), vec![0, 0, 0, 255, 62, 62, 63, 78, 78, 62]);
        // divide_a: D1 / D2 if D2 > 0 else H: 127/126 = 1; 126/127 = 0; 200/100 = 2.
        assert_eq!(table(DivideA), vec![255, 0, 255, 1, 1, 0, 1, 2, 0, 1]);
        // divide, S_L = 0.5: D1 / (D2 * 0.5): 255/127.5 = 2; 127/63 = 2.01 -> 2; 126/63.5 = 1.98 -> 1;
        // 127/63.5 = 2; 200/50 = 4; 100/100 = 1; 126/63 = 2.
        assert_eq!(table(Divide(0.5)), vec![255, 0, 255, 2, 2, 1, 2, 4, 1, 2]);
    }

    #[test]
    fn u16_boundaries() {
        let t = VoxelType::U16;
        assert_eq!(Add.apply(40000, 40000, t), 65535);
        assert_eq!(Difference.apply(40000, 100, t), 39900);
        assert_eq!(Difference.apply(32768, 32766, t), 32767); // D1 >= S, D2 < S: floor at S
        assert_eq!(Product.apply(65535, 32767, t), 32767);
        // Products past i32 (65,535^2 > 2^31), and sums and differences at the extremes.
        assert_eq!(Product.apply(65535, 65535, t), 65535);
        assert_eq!(Product.apply(65535, 40000, t), 40000);
        assert_eq!(Modulate.apply(65535, 65535, t), 65535);
        assert_eq!(Modulate.apply(300, 200, t), 60000);
        assert_eq!(Add.apply(65535, 65535, t), 65535);
        assert_eq!(DifferenceA.apply(0, 65535, t), 0);
        assert_eq!(Difference.apply(65535, 0, t), 65535);
        assert_eq!(DivideA.apply(65535, 1, t), 65535);
        assert_eq!(Divide(1.0).apply(65535, 2, t), 32767);
        assert_eq!(UnaryOp::Inverse.apply(0, t), 65535);
        assert_eq!(UnaryOp::AddScalar(-70000).apply(5, t), 0);
    }

    #[test]
    fn unary() {
        assert_eq!(UnaryOp::Inverse.apply(0, U8), 255);
        assert_eq!(UnaryOp::Inverse.apply(127, U8), 128);
        assert_eq!(UnaryOp::AddScalar(-20).apply(10, U8), 0);
        assert_eq!(UnaryOp::AddScalar(20).apply(250, U8), 255);
        assert_eq!(UnaryOp::AddScalar(5).apply(100, U8), 105);
    }

    /// Every binary operator, divide with `s_l`.
    fn every_binary_op(s_l: f64) -> [BinaryOp; 12] {
        [
            Union,
            Intersection,
            Trim,
            Cap,
            Difference,
            DifferenceA,
            DifferenceB,
            Add,
            Modulate,
            Product,
            DivideA,
            Divide(s_l),
        ]
    }

    #[test]
    fn outside_classification_matches_apply() {
        // op(D1, L) for every D1 must be what outside() says.
        for op in every_binary_op(0.25) {
            for d1 in 0..=255u16 {
                let got = op.apply(d1, 0, U8);
                match op.outside(U8) {
                    Outside::Identity => assert_eq!(got, d1, "{op:?}({d1}, L)"),
                    Outside::Constant(c) => assert_eq!(got, c, "{op:?}({d1}, L)"),
                }
            }
        }
    }

    /// The loops over slices give what the operator gives voxel by voxel, for every operator,
    /// both voxel types, values spread over the whole range (boundaries included).
    #[test]
    fn apply_in_place_is_apply_on_every_voxel() {
        for t in [VoxelType::U8, VoxelType::U16] {
            let h = u32::from(t.high());
            // A deterministic spread: every boundary, then a pseudo-random walk.
            let mut x = 0x9e37_79b9u32;
            let mut next = || {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                (x % (h + 1)) as u16
            };
            let s = t.surface();
            let edges = [0, 1, s - 1, s, s + 1, t.high() - 1, t.high()];
            let a: Vec<u16> = edges
                .iter()
                .copied()
                .chain((0..200).map(|_| next()))
                .collect();
            let b: Vec<u16> = edges
                .iter()
                .rev()
                .copied()
                .chain((0..200).map(|_| next()))
                .collect();
            for op in every_binary_op(0.3) {
                let mut got = a.clone();
                op.apply_in_place(&mut got, &b, t);
                let want: Vec<u16> = a.iter().zip(&b).map(|(&x, &y)| op.apply(x, y, t)).collect();
                assert_eq!(got, want, "{op:?} on {t:?}");
            }
            for op in [
                UnaryOp::Inverse,
                UnaryOp::AddScalar(-300),
                UnaryOp::AddScalar(70),
            ] {
                let mut got = a.clone();
                op.apply_in_place(&mut got, t);
                let want: Vec<u16> = a.iter().map(|&x| op.apply(x, t)).collect();
                assert_eq!(got, want, "{op:?} on {t:?}");
            }
        }
    }
}
