//! Synthetic data sets like the thesis's (its Table 2): an ellipsoid filling the volume, and a
//! terrain from a fractal Perlin-noise height map. Both are [`BrickSource`]s, so any size streams
//! into a VOD 2 file without holding the volume in memory. And the demo scene: the terrain with
//! tunnels, a crater and a few primitives, made by ICVG edits.

use crate::geometry::Box3;
use crate::icvg::primitives::{Ellipsoid, Primitive};
use crate::store::build::{build_file, build_streams_file, sibling, FileFormat};
use crate::store::{BrickSource, BuildOptions, SnapshotSource, StoreError, Vod2};
use crate::volume::{edit_file, VolumeError};
use isovox_proto::channel::ChannelInfo;
use isovox_proto::icvg::{Attributes, EditRequest, Term};
use isovox_proto::vod2::FileHeader;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use noise::{Fbm, MultiFractal, NoiseFn, Perlin};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Writes `value` at voxel `(x, y, z)` of a brick buffer.
fn put(out: &mut [u8], index: usize, value: u16, voxel_type: VoxelType) {
    isovox_proto::voxel::set_value_at(out, voxel_type, index, value.into());
}

/// The brick's voxel box at level 0 clipped to the volume, and whether the brick lies wholly
/// inside the volume.
fn clipped_brick(layout: &VolumeLayout, key: BrickKey) -> (Box3, bool) {
    let whole = Box3::of_brick(layout, key);
    let clipped = whole.intersect(&Box3::of_volume(layout));
    (clipped, clipped == whole)
}

/// The ICVG ellipsoid filling the volume: radii `(dims - 1) / 2` (at least 1), centred so that
/// its extension space `2R + 1` starts at voxel 0.
#[derive(Debug, Clone)]
pub struct EllipsoidSource {
    /// The volume's layout.
    pub layout: VolumeLayout,
    /// The ellipsoid, placed.
    pub ellipsoid: Ellipsoid,
}

impl EllipsoidSource {
    /// The ellipsoid filling `layout`'s volume.
    pub fn new(layout: VolumeLayout) -> Self {
        let radii = layout.dims().map(|d| ((d.saturating_sub(1)) / 2).max(1));
        EllipsoidSource {
            ellipsoid: Ellipsoid {
                center: radii.map(|r| r as i64),
                radii,
            },
            layout,
        }
    }
}

impl BrickSource for EllipsoidSource {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        let (Box3 { min: lo, max: hi }, _) = clipped_brick(&self.layout, key);
        let b = self.layout.brick() as usize;
        let t = self.layout.voxel_type();
        for z in lo[2]..hi[2] {
            for y in lo[1]..hi[1] {
                for x in lo[0]..hi[0] {
                    let i = (((z - lo[2]) as usize * b + (y - lo[1]) as usize) * b)
                        + (x - lo[0]) as usize;
                    put(out, i, self.ellipsoid.sample([x, y, z], t), t);
                }
            }
        }
    }

    fn constant(&self, key: BrickKey) -> Option<u64> {
        let (inside, whole) = clipped_brick(&self.layout, key);
        let t = self.layout.voxel_type();
        match self.ellipsoid.constant_over(&inside, t) {
            // A partial brick is padded with L: constant only if the inside is L too.
            Some(v) if whole || v == t.low() => Some(v.into()),
            _ => None,
        }
    }
}

/// Terrain from a fractal Perlin-noise height map over x and z (y is up): below the height the
/// ground is H, above it L, with a one-voxel band between, `floor(H * (h - y + 0.5))` clamped,
/// so marching cubes finds a smooth surface at S.
#[derive(Debug, Clone)]
pub struct WorldSource {
    /// The volume's layout.
    pub layout: VolumeLayout,
    /// Height of the ground at each (x, z) column, x fastest, in voxels.
    heights: Vec<f32>,
    /// For each brick column (bx, bz): the lowest and highest height inside it.
    column_range: Vec<(f32, f32)>,
}

impl WorldSource {
    /// A world whose hills vary between about 15% and 85% of the height, four hills across.
    pub fn new(layout: VolumeLayout, seed: u32) -> Self {
        let [dx, dy, dz] = layout.dims();
        let fbm = Fbm::<Perlin>::new(seed)
            .set_octaves(6)
            .set_frequency(4.0 / dx.max(dz) as f64)
            .set_persistence(0.5);
        let heights: Vec<f32> = (0..dz)
            .into_par_iter()
            .flat_map_iter(|z| {
                let fbm = &fbm;
                (0..dx).map(move |x| {
                    let n = fbm.get([x as f64 + 0.5, z as f64 + 0.5]);
                    let h = dy as f64 * (0.5 + 0.45 * n.clamp(-1.0, 1.0));
                    h.clamp(1.0, (dy as f64 - 2.0).max(1.0)) as f32
                })
            })
            .collect();
        let b = layout.brick();
        let g = layout.grid(0);
        let mut column_range = vec![(f32::INFINITY, f32::NEG_INFINITY); (g[0] * g[2]) as usize];
        for z in 0..dz {
            for x in 0..dx {
                let h = heights[(z * dx + x) as usize];
                let c = &mut column_range[((z / b) * g[0] + x / b) as usize];
                c.0 = c.0.min(h);
                c.1 = c.1.max(h);
            }
        }
        WorldSource {
            layout,
            heights,
            column_range,
        }
    }

    /// The ground's height at column (x, z), in voxels.
    pub fn height(&self, x: u32, z: u32) -> f32 {
        let dx = self.layout.dims()[0];
        self.heights[(z.min(self.layout.dims()[2] - 1) * dx + x.min(dx - 1)) as usize]
    }

    fn value(h: f32, y: i64, high: u16) -> u16 {
        let v = (high as f64 * (h as f64 - y as f64 + 0.5)).floor();
        v.clamp(0.0, high as f64) as u16
    }
}

impl BrickSource for WorldSource {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        let (Box3 { min: lo, max: hi }, _) = clipped_brick(&self.layout, key);
        let b = self.layout.brick() as usize;
        let t = self.layout.voxel_type();
        let dx = self.layout.dims()[0] as usize;
        for z in lo[2]..hi[2] {
            for x in lo[0]..hi[0] {
                let h = self.heights[z as usize * dx + x as usize];
                for y in lo[1]..hi[1] {
                    let i = (((z - lo[2]) as usize * b + (y - lo[1]) as usize) * b)
                        + (x - lo[0]) as usize;
                    put(out, i, Self::value(h, y, t.high()), t);
                }
            }
        }
    }

    fn constant(&self, key: BrickKey) -> Option<u64> {
        let (Box3 { min: lo, max: hi }, whole) = clipped_brick(&self.layout, key);
        let (hmin, hmax) = self.column_range[(key.z * self.layout.grid(0)[0] + key.x) as usize];
        let high = self.layout.voxel_type().high();
        // value(h, y) is L when h - y + 0.5 <= 0 and H when h - y + 0.5 >= 1.
        if lo[1] as f32 >= hmax + 0.5 {
            return Some(0);
        }
        if whole && ((hi[1] - 1) as f32) <= hmin - 0.5 {
            return Some(high.into());
        }
        None
    }
}

/// The demo world's materials, by value (0 is air).
pub mod materials {
    /// Air: no material.
    pub const AIR: u16 = 0;
    /// Bedrock, below everything.
    pub const ROCK: u16 = 1;
    /// A few voxels of soil under the surface.
    pub const SOIL: u16 = 2;
    /// The surface of gentle slopes.
    pub const GRASS: u16 = 3;
    /// The surface near the water line.
    pub const SAND: u16 = 4;
    /// A vein of ore winding through the rock.
    pub const ORE: u16 = 5;
    /// What the scene's buildings are made of.
    pub const MARBLE: u16 = 6;
    /// Their display colours, by value (the channel's palette).
    pub const PALETTE: [&str; 7] = [
        "#000000", "#77736e", "#7a5634", "#4f8a35", "#d9c58c", "#c9a227", "#e8e4dc",
    ];
}

/// The material channel of a [`WorldSource`]'s terrain: rock below, soil a few voxels deep,
/// grass on gentle slopes, sand near the water line (the lowest fifth of the hills), an ore
/// vein winding through the rock; air above the ground.
#[derive(Debug, Clone)]
pub struct WorldMaterials {
    world: WorldSource,
    water_line: f32,
}

impl WorldMaterials {
    /// The materials of `world`.
    pub fn new(world: WorldSource) -> Self {
        let dy = world.layout.dims()[1] as f32;
        WorldMaterials {
            world,
            water_line: 0.3 * dy,
        }
    }

    /// The material of voxel (x, y, z).
    pub fn material(&self, x: u32, y: u32, z: u32) -> u16 {
        use materials::*;
        let w = &self.world;
        let h = w.height(x, z);
        let depth = h - y as f32;
        if depth < -0.5 {
            return AIR;
        }
        let [dx, dy, dz] = w.layout.dims().map(|d| d as f32);
        // The vein: a tube around a curve that winds in y and z as x goes.
        let (fx, fy, fz) = (x as f32, y as f32, z as f32);
        let vy = dy * (0.3 + 0.08 * (fx * 9.0 / dx).sin());
        let vz = dz * (0.5 + 0.15 * (fx * 5.0 / dx).cos());
        if depth > 6.0 && (fy - vy).hypot(fz - vz) < dy * 0.03 {
            return ORE;
        }
        if depth > 5.0 {
            return ROCK;
        }
        if h < self.water_line + 2.0 {
            return SAND;
        }
        let slope = ((w.height(x + 1, z) - w.height(x.saturating_sub(1), z)).abs()
            + (w.height(x, z + 1) - w.height(x, z.saturating_sub(1))).abs())
            / 2.0;
        if depth < 3.0 && slope < 1.2 {
            GRASS
        } else {
            SOIL
        }
    }
}

impl BrickSource for WorldMaterials {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        let (Box3 { min: lo, max: hi }, _) = clipped_brick(&self.world.layout, key);
        let b = self.world.layout.brick() as usize;
        for z in lo[2]..hi[2] {
            for y in lo[1]..hi[1] {
                for x in lo[0]..hi[0] {
                    let i = (((z - lo[2]) as usize * b + (y - lo[1]) as usize) * b)
                        + (x - lo[0]) as usize;
                    out[i] = self.material(x as u32, y as u32, z as u32) as u8;
                }
            }
        }
    }

    fn constant(&self, key: BrickKey) -> Option<u64> {
        // Air above the ground is air; the rest is worth looking at.
        (self.world.constant(key) == Some(0)).then_some(materials::AIR.into())
    }
}

/// The header of a demo world of `layout`: density and a `material` channel.
///
/// # Errors
/// None for the demo's palette; the signature is [`FileHeader::with_channels`]'s.
pub fn world_header(layout: &VolumeLayout) -> Result<FileHeader, StoreError> {
    let material = ChannelInfo {
        palette: materials::PALETTE.iter().map(|c| c.to_string()).collect(),
        ..ChannelInfo::new("material", VoxelType::U8)
    };
    Ok(FileHeader::with_channels(
        layout.clone(),
        [1.0; 3],
        vec![material],
    )?)
}

/// The edits that turn a generated world of `dims` into the demo scene: tunnels carved through
/// the terrain, a crater, and a few primitives standing on it.
pub fn scene_edits(dims: [u32; 3]) -> Vec<EditRequest> {
    let [x, y, z] = dims.map(|d| d as i64);
    let r = |v: i64| v.max(2) as u32;
    // What the scene builds is marble (ignored by a volume without a material channel).
    let marble = |leaf: Term| Term::Attributed {
        attrs: Attributes {
            material: Some(u64::from(materials::MARBLE)),
            label: None,
        },
        leaf: Box::new(leaf),
    };
    let edit = |op: &str, term: Term| EditRequest {
        op: op.into(),
        term: Some(term),
        s_l: None,
        k: None,
        region: None,
        message: None,
        channel: None,
        overwrite: None,
    };
    vec![
        // Two tunnels along x and one along z, at two thirds of the terrain's mean height.
        edit(
            "difference",
            Term::Ellipsoid {
                center: [x / 2, y * 2 / 5, z / 3],
                radii: [r(x * 9 / 20), r(y / 14), r(y / 14)],
            },
        ),
        edit(
            "difference",
            Term::Ellipsoid {
                center: [x / 2, y / 3, z * 2 / 3],
                radii: [r(x * 9 / 20), r(y / 12), r(y / 12)],
            },
        ),
        edit(
            "difference",
            Term::Ellipsoid {
                center: [x / 3, y * 3 / 10, z / 2],
                radii: [r(y / 16), r(y / 16), r(z * 9 / 20)],
            },
        ),
        // A crater.
        edit(
            "difference",
            Term::Ellipsoid {
                center: [x * 3 / 4, y * 3 / 5, z / 4],
                radii: [r(x / 10), r(y / 6), r(z / 10)],
            },
        ),
        // A ring, a pyramid and a tower.
        edit(
            "union",
            marble(Term::Torus {
                center: [x / 4, y * 4 / 5, z * 3 / 4],
                major: r(x / 12),
                minor: r(y / 30),
            }),
        ),
        edit(
            "union",
            marble(Term::Pyramid {
                origin: [x * 3 / 5, y / 3, z * 3 / 5],
                size: [r(x / 8), r(y / 2), r(z / 8)],
            }),
        ),
        edit(
            "union",
            marble(Term::Cylinder {
                base: [x / 8, y / 5, z / 8],
                radii: [r(x / 40), r(z / 40)],
                height: r(y * 7 / 10),
            }),
        ),
        edit(
            "union",
            marble(Term::Cone {
                base: [x / 8, y * 9 / 10 - r(y / 5) as i64, z / 8],
                radii: [r(x / 25), r(z / 25)],
                height: r(y / 5),
            }),
        ),
    ]
}

/// Builds the demo scene into `output`: the world from `world`, the [`scene_edits`] applied,
/// then the file rebuilt from the final level 0, so the result is version 1 with no history and
/// no garbage.
///
/// # Errors
/// A build, an edit or the rebuild fails.
pub fn build_scene(
    output: &Path,
    layout: &VolumeLayout,
    world: &dyn BrickSource,
    options: &BuildOptions,
) -> Result<(), VolumeError> {
    let work = sibling(output, ".isovox-scene");
    build_file(&work, layout, [1.0; 3], world, options, FileFormat::Vod2)?;
    for request in scene_edits(layout.dims()) {
        edit_file(&work, &request)?;
    }
    let edited = Vod2::open(&work)?;
    let source = SnapshotSource::new(edited.head());
    build_file(output, layout, [1.0; 3], &source, options, FileFormat::Vod2)?;
    source.finish()?;
    drop(edited);
    let _ = std::fs::remove_file(&work);
    Ok(())
}

/// [`build_scene`] of a world with a material channel: the terrain's [`WorldMaterials`], which
/// the scene's carving reveals and its buildings (marble) add to.
///
/// # Errors
/// A build, an edit or the rebuild fails.
pub fn build_scene_with_materials(
    output: &Path,
    world: &WorldSource,
    options: &BuildOptions,
) -> Result<(), VolumeError> {
    let layout = &world.layout;
    let header = world_header(layout)?;
    let work = sibling(output, ".isovox-scene");
    let materials = WorldMaterials::new(world.clone());
    build_streams_file(&work, header.clone(), &[world, &materials], options)?;
    for request in scene_edits(layout.dims()) {
        edit_file(&work, &request)?;
    }
    let edited = Vod2::open(&work)?;
    let head = edited.head();
    let sources: Vec<SnapshotSource> = std::iter::once(head.clone())
        .chain(head.channel_views().iter().cloned())
        .map(SnapshotSource::new)
        .collect();
    let refs: Vec<&dyn BrickSource> = sources.iter().map(|s| s as &dyn BrickSource).collect();
    build_streams_file(output, header, &refs, options)?;
    for source in sources {
        source.finish()?;
    }
    drop((head, edited));
    let _ = std::fs::remove_file(&work);
    Ok(())
}

/// The name of the volume `isovox serve` generates on first start.
pub const DEMO_NAME: &str = "demo";

/// Generates the demo world as `dir/demo.vod`: a 512 x 256 x 512 terrain with tunnels, a crater
/// and a few primitives carved and added by ICVG edits, with a material channel (brick 32; a few
/// seconds, about 2.4 MB).
/// Returns the file's path.
///
/// # Errors
/// The directory cannot be created, or the build fails.
pub fn build_demo(dir: &Path, options: &BuildOptions) -> Result<PathBuf, VolumeError> {
    std::fs::create_dir_all(dir).map_err(|e| {
        VolumeError::Store(StoreError::Io {
            context: format!("cannot create the data directory {}", dir.display()),
            source: e,
        })
    })?;
    let path = dir.join(format!("{DEMO_NAME}.vod"));
    let layout = VolumeLayout::new([512, 256, 512], 32, VoxelType::U8).map_err(StoreError::from)?;
    build_scene_with_materials(&path, &WorldSource::new(layout, 1), options)?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_constant_shortcut(source: &dyn BrickSource, layout: &VolumeLayout) -> usize {
        let g = layout.grid(0);
        let mut decided = 0;
        for z in 0..g[2] {
            for y in 0..g[1] {
                for x in 0..g[0] {
                    let key = BrickKey { level: 0, x, y, z };
                    if let Some(v) = source.constant(key) {
                        decided += 1;
                        let mut out = vec![0u8; layout.brick_bytes()];
                        source.fill(key, &mut out);
                        let mut expect = vec![0u8; layout.brick_bytes()];
                        crate::store::codec::fill_constant(&mut expect, v, layout.voxel_type());
                        assert_eq!(out, expect, "brick {key} is not the constant {v}");
                    }
                }
            }
        }
        decided
    }

    #[test]
    fn world_shortcut_is_exact() {
        let layout = VolumeLayout::new([70, 60, 50], 8, VoxelType::U8).unwrap();
        let w = WorldSource::new(layout.clone(), 7);
        assert!(check_constant_shortcut(&w, &layout) > 100);
    }

    #[test]
    fn ellipsoid_shortcut_is_exact() {
        let layout = VolumeLayout::new([61, 50, 43], 8, VoxelType::U16).unwrap();
        let e = EllipsoidSource::new(layout.clone());
        assert!(check_constant_shortcut(&e, &layout) > 20);
    }

    #[test]
    fn world_band_values() {
        // h = 10.25: y = 10 -> floor(255 * 0.75) = 191; y = 11 -> floor(255 * -0.25) -> 0;
        // y = 9 -> 255 * 1.75 clamps to 255.
        assert_eq!(WorldSource::value(10.25, 10, 255), 191);
        assert_eq!(WorldSource::value(10.25, 11, 255), 0);
        assert_eq!(WorldSource::value(10.25, 9, 255), 255);
    }
}
