//! The cameras' paths (an orbit, a seeded random walk, or a recorded path), sampled by time,
//! and the seeded generator viewers and editors draw from.

use super::PathSpec;
use isovox_proto::api::VolumeInfo;
use std::sync::Arc;

/// A camera path from a file: one `t x y z` per line (seconds, world units), `t`
/// non-decreasing; blank lines and `#` comments are skipped. Positions between two lines are
/// interpolated linearly.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedPath {
    points: Vec<(f32, [f32; 3])>,
}

impl RecordedPath {
    /// Parses the text of a path file.
    ///
    /// # Errors
    /// A line that is not four numbers, a time before the previous one, or no point at all;
    /// the message names the line.
    pub fn parse(text: &str) -> Result<RecordedPath, String> {
        let mut points: Vec<(f32, [f32; 3])> = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let v: Vec<f32> = line
                .split_whitespace()
                .map(str::parse::<f32>)
                .collect::<Result<_, _>>()
                .map_err(|e| format!("line {}: {e}", i + 1))?;
            let [t, x, y, z] = v[..] else {
                return Err(format!(
                    "line {}: expected `t x y z`, found {} numbers",
                    i + 1,
                    v.len()
                ));
            };
            if v.iter().any(|f| !f.is_finite()) {
                return Err(format!("line {}: not a finite number", i + 1));
            }
            if points.last().is_some_and(|(last, _)| t < *last) {
                return Err(format!("line {}: time {t} before the previous one", i + 1));
            }
            points.push((t, [x, y, z]));
        }
        if points.is_empty() {
            return Err("no point in the path".into());
        }
        Ok(RecordedPath { points })
    }

    /// Seconds from the first point to the last.
    pub fn span(&self) -> f32 {
        match (self.points.first(), self.points.last()) {
            (Some(a), Some(b)) => b.0 - a.0,
            _ => 0.0,
        }
    }

    /// The position `t` seconds after the first point, looping at the end.
    pub fn at(&self, t: f32) -> [f32; 3] {
        let (first, span) = (self.points[0].0, self.span());
        if span <= 0.0 || self.points.len() == 1 {
            return self.points[0].1;
        }
        let t = first + t.rem_euclid(span);
        let i = self.points.partition_point(|(pt, _)| *pt <= t);
        if i == 0 {
            return self.points[0].1;
        }
        if i >= self.points.len() {
            return self.points[self.points.len() - 1].1;
        }
        let ((t0, a), (t1, b)) = (self.points[i - 1], self.points[i]);
        let f = if t1 > t0 { (t - t0) / (t1 - t0) } else { 0.0 };
        [0, 1, 2].map(|k| a[k] + (b[k] - a[k]) * f)
    }
}

/// A small seeded generator (SplitMix64): viewers and editors draw their own streams.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        let mut r = Rng(seed ^ 0x6a09_e667_f3bc_c909);
        r.next_u64();
        r
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in `[lo, hi)`.
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }
}

/// The volume's size in world units.
fn extent(info: &VolumeInfo) -> [f32; 3] {
    [0, 1, 2].map(|a| info.dims[a] as f32 * info.voxel_scale[a])
}

/// One camera's flight, sampled by time since its start.
#[derive(Debug, Clone)]
pub struct CameraPath(PathState);

#[derive(Debug, Clone)]
enum PathState {
    Orbit {
        centre: [f32; 2],
        radius: f32,
        height: f32,
        phase: f32,
        omega: f32,
    },
    Walk {
        pos: [f32; 3],
        heading: f32,
        climb: f32,
        speed: f32,
        min: [f32; 3],
        max: [f32; 3],
        last_t: f32,
        rng: Rng,
    },
    Recorded {
        path: Arc<RecordedPath>,
        offset: f32,
    },
}

impl CameraPath {
    /// The path `spec` over `info`'s volume for the viewer seeded `seed`.
    pub fn new(spec: &PathSpec, info: &VolumeInfo, seed: u64) -> CameraPath {
        let e = extent(info);
        let mut rng = Rng::new(seed);
        CameraPath(match spec {
            PathSpec::Orbit {
                radius,
                height,
                period_s,
            } => {
                let r = radius.unwrap_or(0.35 * e[0].min(e[2]));
                let dir = if rng.unit() < 0.5 { -1.0 } else { 1.0 };
                PathState::Orbit {
                    centre: [e[0] / 2.0, e[2] / 2.0],
                    radius: r * rng.range(0.8, 1.2),
                    height: height.unwrap_or(0.95 * e[1]),
                    phase: rng.range(0.0, std::f32::consts::TAU),
                    omega: dir * std::f32::consts::TAU / period_s.max(0.1),
                }
            }
            PathSpec::RandomWalk { speed, low, high } => {
                let lo = low.unwrap_or(0.6 * e[1]);
                let hi = high.unwrap_or(e[1]).max(lo);
                let min = [0.0, lo, 0.0];
                let max = [e[0], hi, e[2]];
                PathState::Walk {
                    pos: [0, 1, 2].map(|a| rng.range(min[a], max[a])),
                    heading: rng.range(0.0, std::f32::consts::TAU),
                    climb: 0.0,
                    speed: speed.unwrap_or(0.05 * e[0].max(e[2])),
                    min,
                    max,
                    last_t: 0.0,
                    rng,
                }
            }
            PathSpec::Recorded(path) => PathState::Recorded {
                offset: rng.range(0.0, path.span().max(0.0)),
                path: path.clone(),
            },
        })
    }

    /// The camera position `t` seconds after the start (a random walk moves forward only:
    /// earlier times return the current position).
    pub fn at(&mut self, t: f32) -> [f32; 3] {
        match &mut self.0 {
            PathState::Orbit {
                centre,
                radius,
                height,
                phase,
                omega,
            } => {
                let a = *phase + *omega * t;
                [
                    centre[0] + *radius * a.cos(),
                    *height,
                    centre[1] + *radius * a.sin(),
                ]
            }
            PathState::Walk {
                pos,
                heading,
                climb,
                speed,
                min,
                max,
                last_t,
                rng,
            } => {
                while *last_t < t {
                    let dt = (t - *last_t).min(0.05);
                    *last_t += dt;
                    // The heading and the climb rate wander; the speed stays.
                    *heading += rng.range(-4.0, 4.0) * dt;
                    *climb = (*climb + rng.range(-1.0, 1.0) * dt).clamp(-0.3, 0.3);
                    let v = [heading.cos(), *climb, heading.sin()];
                    for a in 0..3 {
                        pos[a] += v[a] * *speed * dt;
                        if pos[a] < min[a] || pos[a] > max[a] {
                            // Bounce: mirror the position and turn back.
                            pos[a] = pos[a].clamp(min[a], max[a]);
                            match a {
                                0 => *heading = std::f32::consts::PI - *heading,
                                1 => *climb = -*climb,
                                _ => *heading = -*heading,
                            }
                        }
                    }
                }
                *pos
            }
            PathState::Recorded { path, offset } => path.at(t + *offset),
        }
    }
}
