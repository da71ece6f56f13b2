//! Input voxel types, and their conversion to the volume's u8 or u16.
//!
//! u8 and u16 inputs are stored as they are. Other types (i8, i16, u32, i32, f32, f64) are
//! mapped linearly from a window `[lo, hi]` onto `[0, H]`: `round((v - lo) / (hi - lo) * H)`,
//! clamped, NaN to 0. The window is given (`--window LO,HI`) or taken from percentiles of the
//! input ([`sample_window`]), and the import says which in its output.

use crate::formats::FormatsError;
use isovox_proto::VoxelType;
use std::fmt;

/// A voxel type an input may have.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DType {
    /// Unsigned 8 bits.
    U8,
    /// Signed 8 bits.
    I8,
    /// Unsigned 16 bits.
    U16,
    /// Signed 16 bits.
    I16,
    /// Unsigned 32 bits.
    U32,
    /// Signed 32 bits.
    I32,
    /// Unsigned 64 bits (segmentations' ids; as f64, exact up to 2^53).
    U64,
    /// IEEE 754 single precision.
    F32,
    /// IEEE 754 double precision.
    F64,
}

impl DType {
    /// Bytes of one value.
    pub const fn bytes(self) -> usize {
        match self {
            DType::U8 | DType::I8 => 1,
            DType::U16 | DType::I16 => 2,
            DType::U32 | DType::I32 | DType::F32 => 4,
            DType::U64 | DType::F64 => 8,
        }
    }

    /// The volume type this input is stored as when nothing is asked: u8 and i8 as u8, every
    /// wider type as u16.
    pub fn default_target(self) -> VoxelType {
        match self {
            DType::U8 | DType::I8 => VoxelType::U8,
            _ => VoxelType::U16,
        }
    }

    /// The channel type a label map of this type is stored as: its own width for unsigned
    /// integers (u8, u16, u32, u64), the unsigned type of the same width for signed ones (a
    /// negative id is an error), u16 for floats (whole values only, as the file may hold ids in
    /// a float type; more than 65,535 ids in a float map is an error naming the value).
    pub fn label_type(self) -> VoxelType {
        match self {
            DType::U8 | DType::I8 => VoxelType::U8,
            DType::U16 | DType::I16 | DType::F32 | DType::F64 => VoxelType::U16,
            DType::U32 | DType::I32 => VoxelType::U32,
            DType::U64 => VoxelType::U64,
        }
    }

    /// The value at `i` of little-endian `bytes` as an id: exact for every integer type,
    /// `None` for a negative value or a float that is not a whole number from 0 to 2^64 - 1.
    pub fn id(self, bytes: &[u8], i: usize) -> Option<u64> {
        let at = i * self.bytes();
        let b = &bytes[at..at + self.bytes()];
        match self {
            DType::U8 => Some(u64::from(b[0])),
            DType::U16 => Some(u64::from(u16::from_le_bytes([b[0], b[1]]))),
            DType::U32 => Some(u64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))),
            DType::U64 => Some(u64::from_le_bytes(b.try_into().ok()?)),
            DType::I8 => u64::try_from(b[0] as i8).ok(),
            DType::I16 => u64::try_from(i16::from_le_bytes([b[0], b[1]])).ok(),
            DType::I32 => u64::try_from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])).ok(),
            DType::F32 | DType::F64 => {
                let v = self.value(bytes, i);
                // 2^64 itself is the first float past u64.
                ((0.0..18_446_744_073_709_551_616.0).contains(&v) && v.fract() == 0.0)
                    .then_some(v as u64)
            }
        }
    }

    /// Whether values of this type are stored without conversion as `target`.
    pub fn is(self, target: VoxelType) -> bool {
        matches!(
            (self, target),
            (DType::U8, VoxelType::U8) | (DType::U16, VoxelType::U16)
        )
    }

    /// The value at `i` of little-endian `bytes`, as f64.
    pub fn value(self, bytes: &[u8], i: usize) -> f64 {
        let at = i * self.bytes();
        let b = &bytes[at..at + self.bytes()];
        match self {
            DType::U8 => f64::from(b[0]),
            DType::I8 => f64::from(b[0] as i8),
            DType::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            DType::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            DType::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            DType::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            DType::U64 => {
                u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f64
            }
            DType::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            DType::F64 => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
        }
    }
}

impl fmt::Display for DType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            DType::U8 => "uint8",
            DType::I8 => "int8",
            DType::U16 => "uint16",
            DType::I16 => "int16",
            DType::U32 => "uint32",
            DType::I32 => "int32",
            DType::U64 => "uint64",
            DType::F32 => "float32",
            DType::F64 => "float64",
        })
    }
}

/// How input values become the volume's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Conversion {
    /// Stored as they are (u8 to u8, u16 to u16).
    Identity(VoxelType),
    /// `[lo, hi]` mapped linearly onto `[0, H]` of `target`.
    Window {
        /// The value mapped to 0.
        lo: f64,
        /// The value mapped to H.
        hi: f64,
        /// The volume's type.
        target: VoxelType,
    },
    /// Ids (a label map beside the image): each value kept exactly, never scaled; a value
    /// that is negative, not a whole number or above `target`'s largest is an error naming it.
    Labels(VoxelType),
}

impl Conversion {
    /// The volume's type.
    pub fn target(&self) -> VoxelType {
        match *self {
            Conversion::Identity(t)
            | Conversion::Window { target: t, .. }
            | Conversion::Labels(t) => t,
        }
    }

    /// `values` (little endian, of `dtype`) as the volume's type.
    ///
    /// # Errors
    /// An identity conversion of another type (a bug: the conversion is chosen for the type).
    pub fn apply(&self, dtype: DType, values: &[u8]) -> Result<Vec<u8>, FormatsError> {
        match *self {
            Conversion::Identity(t) if dtype.is(t) => Ok(values.to_vec()),
            Conversion::Identity(t) => Err(FormatsError::Internal(format!(
                "{dtype} values cannot be stored as {t} without a window"
            ))),
            Conversion::Window { lo, hi, target } => {
                let n = values.len() / dtype.bytes();
                let high = f64::from(target.high());
                let span = hi - lo;
                let map = |i: usize| -> u16 {
                    // Multiplied before dividing: exact for integer inputs, so a value halfway
                    // between two outputs rounds up as documented.
                    let v = (dtype.value(values, i) - lo) * high / span;
                    // NaN fails both comparisons and lands on 0.
                    if v >= high {
                        target.high()
                    } else if v > 0.0 {
                        v.round() as u16
                    } else {
                        0
                    }
                };
                Ok(match target {
                    VoxelType::U8 => (0..n).map(|i| map(i) as u8).collect(),
                    _ => (0..n).flat_map(|i| map(i).to_le_bytes()).collect(),
                })
            }
            Conversion::Labels(target) => {
                let n = values.len() / dtype.bytes();
                let high = target.max_value();
                let mut out = vec![0u8; n * target.bytes()];
                for i in 0..n {
                    match dtype.id(values, i) {
                        Some(id) if id <= high => {
                            isovox_proto::voxel::set_value_at(&mut out, target, i, id);
                        }
                        _ => {
                            return Err(FormatsError::input(format!(
                                "label value {} is not an id from 0 to {high} (a {target} channel)",
                                number(dtype.value(values, i))
                            )))
                        }
                    }
                }
                Ok(out)
            }
        }
    }
}

/// `v` for a message: as Rust prints it, or in scientific notation when that would take more
/// than a handful of digits (f64's largest values print with 309 of them).
pub fn number(v: f64) -> String {
    if v.is_finite() && v != 0.0 && !(1e-6..1e15).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        v.to_string()
    }
}

/// Parses `LO,HI` (a window or a pair of percentiles).
///
/// # Errors
/// Not two finite numbers with `LO < HI` whose difference is finite too.
pub fn parse_pair(s: &str, what: &str) -> Result<(f64, f64), FormatsError> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| {
            FormatsError::BadArgument(format!("{what} {s:?}: two numbers LO,HI expected"))
        })?;
    match v.as_slice() {
        [lo, hi] if lo < hi && (hi - lo).is_finite() => Ok((*lo, *hi)),
        _ => Err(FormatsError::BadArgument(format!(
            "{what} {s:?}: two numbers LO < HI expected, whose difference is finite"
        ))),
    }
}

/// Values a percentile window is estimated from at most (evenly spaced through the input).
pub const SAMPLE_TARGET: u64 = 1 << 22;

/// Collects every `stride`-th value of an input (by position in x-fastest order), for
/// [`sample_window`].
#[derive(Debug)]
pub struct Sampler {
    stride: u64,
    next: u64,
    seen: u64,
    values: Vec<f64>,
}

impl Sampler {
    /// A sampler for an input of `total` values.
    pub fn new(total: u64) -> Self {
        Sampler {
            stride: total.div_ceil(SAMPLE_TARGET).max(1),
            next: 0,
            seen: 0,
            values: Vec::new(),
        }
    }

    /// Takes the next run of values (little endian, of `dtype`).
    pub fn take(&mut self, dtype: DType, bytes: &[u8]) {
        let n = (bytes.len() / dtype.bytes()) as u64;
        while self.next < self.seen + n {
            let v = dtype.value(bytes, (self.next - self.seen) as usize);
            if !v.is_nan() {
                self.values.push(v);
            }
            self.next += self.stride;
        }
        self.seen += n;
    }

    /// The values at percentiles `lo` and `hi` (0..100, nearest rank) of the sample, and how
    /// many values it held.
    ///
    /// # Errors
    /// The input has no number, or the two percentiles are equal values (a constant input).
    pub fn window(mut self, (lo, hi): (f64, f64)) -> Result<(f64, f64, usize), FormatsError> {
        let n = self.values.len();
        if n == 0 {
            return Err(FormatsError::input(
                "the input holds no number (all NaN): give --window LO,HI",
            ));
        }
        self.values.sort_unstable_by(f64::total_cmp);
        let rank = |p: f64| -> f64 {
            let i = ((p / 100.0) * (n - 1) as f64).round() as usize;
            self.values[i.min(n - 1)]
        };
        let (a, b) = (rank(lo), rank(hi));
        if a >= b {
            return Err(FormatsError::input(format!(
                "the {lo}th and {hi}th percentiles are both {}: give --window LO,HI",
                number(a)
            )));
        }
        if !(b - a).is_finite() {
            return Err(FormatsError::input(format!(
                "the {lo}th and {hi}th percentiles, {} and {}, are too far apart to map linearly: give --window LO,HI",
                number(a),
                number(b)
            )));
        }
        Ok((a, b, n))
    }
}

/// Percentiles asked for with `--percentiles`, checked to lie in 0..=100.
///
/// # Errors
/// Not two numbers `0 <= LO < HI <= 100`.
pub fn parse_percentiles(s: &str) -> Result<(f64, f64), FormatsError> {
    let (lo, hi) = parse_pair(s, "--percentiles")?;
    if lo < 0.0 || hi > 100.0 {
        return Err(FormatsError::BadArgument(format!(
            "--percentiles {s:?}: both must lie in 0..100"
        )));
    }
    Ok((lo, hi))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_maps_linearly_and_clamps() {
        // Window [-100, 100] onto u8: -100 -> 0, 0 -> 127.5 -> 128 (half away from zero),
        // 100 -> 255, beyond either end clamped.
        let c = Conversion::Window {
            lo: -100.0,
            hi: 100.0,
            target: VoxelType::U8,
        };
        let values: Vec<u8> = [-200i16, -100, 0, 50, 100, 300]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        assert_eq!(
            c.apply(DType::I16, &values).unwrap(),
            vec![0, 0, 128, 191, 255, 255]
        );
        // f32 onto u16, with a NaN: 0.25 of [0, 1] is 16383.75 -> 16384.
        let c = Conversion::Window {
            lo: 0.0,
            hi: 1.0,
            target: VoxelType::U16,
        };
        let values: Vec<u8> = [0.25f32, f32::NAN, 1.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        assert_eq!(
            c.apply(DType::F32, &values).unwrap(),
            [16384u16, 0, 65535]
                .iter()
                .flat_map(|v| v.to_le_bytes())
                .collect::<Vec<u8>>()
        );
    }

    #[test]
    fn identity_refuses_other_types() {
        let c = Conversion::Identity(VoxelType::U8);
        assert_eq!(c.apply(DType::U8, &[1, 2]).unwrap(), vec![1, 2]);
        assert!(c.apply(DType::I8, &[1, 2]).is_err());
    }

    #[test]
    fn percentiles_of_a_known_sample() {
        // 0..=1000 as i32: the 1st and 99th percentiles by nearest rank are 10 and 990.
        let values: Vec<u8> = (0..=1000i32).flat_map(|v| v.to_le_bytes()).collect();
        let mut s = Sampler::new(1001);
        s.take(DType::I32, &values[..400]);
        s.take(DType::I32, &values[400..]);
        assert_eq!(s.window((1.0, 99.0)).unwrap(), (10.0, 990.0, 1001));
        let mut flat = Sampler::new(3);
        flat.take(DType::F32, &[0u8; 12]);
        assert!(flat.window((1.0, 99.0)).is_err());
    }

    #[test]
    fn numbers_in_messages_stay_short() {
        assert_eq!(number(f64::MAX), "1.7976931348623157e308");
        assert_eq!(number(1e308), "1e308");
        assert_eq!(number(-3.5e20), "-3.5e20");
        assert_eq!(number(1e-300), "1e-300");
        assert_eq!(number(1234.5), "1234.5");
        assert_eq!(number(-1000.0), "-1000");
        assert_eq!(number(0.0), "0");
        assert_eq!(number(f64::INFINITY), "inf");
        // A constant input of huge values names its value briefly.
        let mut s = Sampler::new(4);
        s.take(
            DType::F64,
            &[1e308f64; 4]
                .iter()
                .flat_map(|v| v.to_le_bytes())
                .collect::<Vec<u8>>(),
        );
        let err = s.window((0.5, 99.5)).unwrap_err().to_string();
        assert!(err.contains("both 1e308"), "{err}");
        let mut s = Sampler::new(2);
        s.take(
            DType::F64,
            &[-1e308f64, 1e308]
                .iter()
                .flat_map(|v| v.to_le_bytes())
                .collect::<Vec<u8>>(),
        );
        let err = s.window((0.0, 100.0)).unwrap_err().to_string();
        assert!(err.contains("-1e308 and 1e308"), "{err}");
    }

    #[test]
    fn pairs_are_checked() {
        assert_eq!(parse_pair("-1000, 3000", "w").unwrap(), (-1000.0, 3000.0));
        for bad in [
            "1",
            "2,1",
            "1,1",
            "a,b",
            "1,2,3",
            "nan,1",
            "-1e308,1e308",
            "0,inf",
        ] {
            assert!(parse_pair(bad, "w").is_err(), "{bad}");
        }
        assert!(parse_percentiles("0.5,99.5").is_ok());
        assert!(parse_percentiles("-1,50").is_err());
    }
}
