//! The object's mesh: the field's density sampled on a regular grid, the grid nodes labelled
//! object or background by the views' masks, and the iso-surface of the object's density.
//!
//! **Iso-level.** A ray crossing one grid cell of side `h` through density `σ` is made opaque
//! by `α = 1 − exp(−σ h)`. The surface is drawn where `α = 1/2`, i.e. at `σ = ln 2 / h`: denser
//! than that, one cell of material stops more than half of the light passing through it (it
//! renders as surface at the grid's resolution); thinner, most light passes (it renders as fog).
//! A finer grid asks for a denser surface, as thinner shells then still show.
//!
//! **Which part is the object.** Every node at or above the iso-level is voted on by the views
//! that see it: it projects inside the image, and its distance from the camera is not more than
//! a tolerance ([`VISIBILITY_CELLS`] cells plus [`VISIBILITY_RELATIVE`] of the depth) behind the
//! view's rendered depth at that pixel (the depth the view's mask was decided with; an empty ray
//! counts as seeing it). It belongs to the object when most of those views' masks say
//! foreground. A node that no view sees (inside a solid, deeper than the tolerance) is voted on
//! by every view it projects into, as a visual hull: object when most of their masks say
//! foreground. Background nodes are cleared before the surface is extracted, so the object's
//! mesh is closed, also where it stood on a support.
//!
//! **Surface.** Naive Surface Nets (`fast-surface-nets`) on `iso − σ`: one vertex per grid cell
//! that the iso-surface crosses, at the mean of its edge crossings (linearly interpolated, the
//! same crossings marching cubes finds), joined into quads across every crossed edge and split
//! into triangles. The grid is padded with empty nodes so the surface closes at its faces.

use fast_surface_nets::ndshape::{RuntimeShape, Shape};
use fast_surface_nets::{surface_nets, SurfaceNetsBuffer};
use rayon::prelude::*;
use sos_core::camera::{norm, sub, Camera, Vec3};
use sos_core::plugin::RadianceField;
use sos_core::render::composite::is_hit;
use sos_core::scene::SceneExtent;

/// Visibility tolerance behind the rendered depth, in grid cells.
pub const VISIBILITY_CELLS: f32 = 2.0;
/// Visibility tolerance behind the rendered depth, as a fraction of that depth.
pub const VISIBILITY_RELATIVE: f32 = 0.02;

/// Lateral slack of the forward-facing box around the virtual camera's frustum (as the
/// field's own grid has).
const FORWARD_FACING_MARGIN: f32 = 1.15;

/// Nodes per density batch handed to the field.
const BATCH: usize = 16_384;

/// A regular grid of cubic cells: node `(x, y, z)` lies at `min + h · (x, y, z)`, stored at
/// index `x + nx (y + ny z)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    /// Position of node `(0, 0, 0)`.
    pub min: Vec3,
    /// Cell side `h`.
    pub cell: f32,
    /// Nodes along each axis.
    pub dims: [usize; 3],
}

impl Grid {
    /// The grid with `resolution` nodes along the longest side of the box `[min, max]` and
    /// cubic cells, centred in the box (shorter sides end within half a cell of its faces).
    pub fn fit(min: Vec3, max: Vec3, resolution: usize) -> Grid {
        let size = [max[0] - min[0], max[1] - min[1], max[2] - min[2]];
        let longest = size.iter().copied().fold(0.0f32, f32::max);
        let cell = longest / (resolution.max(2) - 1) as f32;
        let mut grid = Grid { min, cell, dims: [2; 3] };
        for k in 0..3 {
            let n = ((size[k] / cell) * (1.0 + 1e-5)).floor() as usize + 1;
            grid.dims[k] = n.max(2);
            grid.min[k] = min[k] + (size[k] - (grid.dims[k] - 1) as f32 * cell) / 2.0;
        }
        grid
    }

    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.dims.iter().product()
    }

    /// Whether the grid has no nodes.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Position of the node at linear index `i`.
    pub fn node(&self, i: usize) -> Vec3 {
        let [nx, ny, _] = self.dims;
        let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
        [self.min[0] + self.cell * x as f32, self.min[1] + self.cell * y as f32, self.min[2] + self.cell * z as f32]
    }

    /// The corner opposite [`Grid::min`].
    pub fn max(&self) -> Vec3 {
        [0, 1, 2].map(|k| self.min[k] + self.cell * (self.dims[k] - 1) as f32)
    }
}

/// The density at which the surface is drawn on a grid of cell side `cell`: `ln 2 / cell`, one
/// cell of it half opaque (see the module documentation).
pub fn iso_level(cell: f32) -> f32 {
    std::f32::consts::LN_2 / cell
}

/// The box a scene's content lies in: the bounded box, the unbounded extent's foreground
/// sphere's box, or the forward-facing virtual camera's frustum between `near` and `far`.
pub fn extent_box(extent: &SceneExtent) -> (Vec3, Vec3) {
    match *extent {
        SceneExtent::Bounded { min, max } => (min, max),
        SceneExtent::Unbounded { center, radius } => (center.map(|c| c - radius), center.map(|c| c + radius)),
        SceneExtent::ForwardFacing { near, far, focal, width, height } => {
            let hx = FORWARD_FACING_MARGIN * far * width / (2.0 * focal);
            let hy = FORWARD_FACING_MARGIN * far * height / (2.0 * focal);
            ([-hx, -hy, -far], [hx, hy, -near])
        }
    }
}

/// The box around the object's fused points: per axis their 1st to 99th percentile (stray
/// mask pixels do not stretch it), widened on each side by a tenth of its size and a hundredth
/// of `within`'s, and cut to `within`; `None` without points.
pub fn object_box(points: &[Vec3], within: (Vec3, Vec3)) -> Option<(Vec3, Vec3)> {
    if points.is_empty() {
        return None;
    }
    let mut min = [0.0; 3];
    let mut max = [0.0; 3];
    for k in 0..3 {
        let mut v: Vec<f32> = points.iter().map(|p| p[k]).collect();
        v.sort_unstable_by(f32::total_cmp);
        let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        let (lo, hi) = (at(0.01), at(0.99));
        // A flat object still gets a slab: a hundredth of `within` on top of the tenth.
        let pad = 0.1 * (hi - lo) + 0.01 * (within.1[k] - within.0[k]);
        min[k] = (lo - pad).max(within.0[k]);
        max[k] = (hi + pad).min(within.1[k]);
        if max[k] <= min[k] {
            return None;
        }
    }
    Some((min, max))
}

/// Samples the field's density at every node; `progress` hears the nodes done. Non-finite
/// values count as empty space.
pub fn sample_density(field: &dyn RadianceField, grid: &Grid, progress: &(dyn Fn(u64) + Sync)) -> Vec<f32> {
    let mut density = vec![0.0f32; grid.len()];
    density.par_chunks_mut(BATCH).enumerate().for_each(|(b, out)| {
        let positions: Vec<Vec3> = (0..out.len()).map(|j| grid.node(b * BATCH + j)).collect();
        field.density(&positions, out);
        out.iter_mut().filter(|v| !v.is_finite()).for_each(|v| *v = 0.0);
        progress(out.len() as u64);
    });
    density
}

/// A view's segmentation and the rendered depth its mask was decided with.
#[derive(Debug, Clone)]
pub struct ViewEvidence {
    /// The view's camera.
    pub camera: Camera,
    /// Foreground flag per pixel, row-major.
    pub foreground: Vec<bool>,
    /// Rendered distance along each pixel's ray, row-major (not a hit: empty ray).
    pub depth: Vec<f32>,
}

/// Whether the point `p` belongs to the object by the vote of `views` (see the module
/// documentation); `cell` sets the visibility tolerance.
pub fn is_object(p: Vec3, views: &[ViewEvidence], cell: f32) -> bool {
    let (mut seen, mut seen_fg, mut inside, mut inside_fg) = (0usize, 0usize, 0usize, 0usize);
    for v in views {
        let Some([x, y]) = v.camera.project(p) else { continue };
        let (w, h) = (v.camera.width as f32, v.camera.height as f32);
        if !(x >= 0.0 && y >= 0.0 && x < w && y < h) {
            continue;
        }
        let i = y as usize * v.camera.width as usize + x as usize;
        let fg = usize::from(v.foreground[i]);
        inside += 1;
        inside_fg += fg;
        let depth = v.depth[i];
        let distance = norm(sub(p, v.camera.origin()));
        if !is_hit(depth) || distance <= depth * (1.0 + VISIBILITY_RELATIVE) + VISIBILITY_CELLS * cell {
            seen += 1;
            seen_fg += fg;
        }
    }
    if seen > 0 {
        2 * seen_fg > seen
    } else {
        2 * inside_fg > inside
    }
}

/// Labels the nodes at or above `iso`: `true` for the object's (see [`is_object`]); nodes
/// below `iso` are `false`. `progress` hears the nodes done.
pub fn label_object(
    grid: &Grid,
    density: &[f32],
    iso: f32,
    views: &[ViewEvidence],
    progress: &(dyn Fn(u64) + Sync),
) -> Vec<bool> {
    let mut object = vec![false; density.len()];
    object.par_chunks_mut(BATCH).enumerate().for_each(|(b, out)| {
        for (j, o) in out.iter_mut().enumerate() {
            let i = b * BATCH + j;
            *o = density[i] >= iso && is_object(grid.node(i), views, grid.cell);
        }
        progress(out.len() as u64);
    });
    object
}

/// A triangle mesh with unit vertex normals (pointing out of the object).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions (world).
    pub positions: Vec<Vec3>,
    /// Unit normal per vertex (zero where the density has no gradient).
    pub normals: Vec<Vec3>,
    /// Triangles as vertex indices, counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
}

impl Mesh {
    /// Signed volume enclosed (positive for a closed mesh whose faces wind outwards).
    pub fn signed_volume(&self) -> f64 {
        self.faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| self.positions[i as usize].map(f64::from));
                a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                    + a[2] * (b[0] * c[1] - b[1] * c[0])
            })
            .sum::<f64>()
            / 6.0
    }
}

/// The iso-surface at `iso` of the density of the nodes `keep` marks (every other node counts
/// as empty), in world coordinates, inside the grid's box.
pub fn extract(grid: &Grid, density: &[f32], iso: f32, keep: &[bool]) -> Mesh {
    let [nx, ny, nz] = grid.dims;
    let padded = [nx + 2, ny + 2, nz + 2];
    let shape = RuntimeShape::<u32, 3>::new(padded.map(|n| n as u32));
    // Negative inside: `iso − σ` where kept, `iso` (empty) elsewhere and on the padding.
    let mut sdf = vec![iso; padded.iter().product()];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let i = x + nx * (y + ny * z);
                let s = if keep[i] { density[i] } else { density[i].min(iso) };
                sdf[shape.linearize([x as u32 + 1, y as u32 + 1, z as u32 + 1]) as usize] = iso - s;
            }
        }
    }
    let mut buffer = SurfaceNetsBuffer::default();
    surface_nets(&sdf, &shape, [0; 3], padded.map(|n| n as u32 - 1), &mut buffer);
    let (lo, hi) = (grid.min, grid.max());
    let positions = buffer
        .positions
        .iter()
        .map(|p| [0, 1, 2].map(|k| (grid.min[k] + grid.cell * (p[k] - 1.0)).clamp(lo[k], hi[k])))
        .collect();
    let normals = buffer
        .normals
        .iter()
        .map(|n| {
            // The gradient of `iso − σ` points away from the density: out of the object.
            let len = norm(*n);
            if len > 0.0 && len.is_finite() {
                n.map(|v| v / len)
            } else {
                [0.0; 3]
            }
        })
        .collect();
    let faces = buffer.indices.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();
    Mesh { positions, normals, faces }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ball of density 100 and radius `r` around `c`, empty elsewhere.
    fn ball(grid: &Grid, c: Vec3, r: f32) -> Vec<f32> {
        (0..grid.len()).map(|i| if norm(sub(grid.node(i), c)) < r { 100.0 } else { 0.0 }).collect()
    }

    #[test]
    fn grid_fits_inside_its_box_with_cubic_cells() {
        let g = Grid::fit([-1.0, 0.0, 2.0], [1.0, 0.5, 3.0], 41);
        assert_eq!(g.dims, [41, 11, 21]);
        assert!((g.cell - 0.05).abs() < 1e-6);
        let (lo, hi) = (g.min, g.max());
        for k in 0..3 {
            assert!(lo[k] >= [-1.0, 0.0, 2.0][k] - 1e-5 && hi[k] <= [1.0, 0.5, 3.0][k] + 1e-5, "{g:?}");
        }
        assert_eq!(g.node(g.len() - 1), hi);
        assert!((iso_level(0.05) * 0.05 - std::f32::consts::LN_2).abs() < 1e-6);
    }

    #[test]
    fn a_ball_gives_a_closed_outward_sphere() {
        let grid = Grid::fit([-1.0; 3], [1.0; 3], 41);
        let c = [0.1, -0.2, 0.05];
        let density = ball(&grid, c, 0.6);
        let mesh = extract(&grid, &density, iso_level(grid.cell), &vec![true; grid.len()]);
        assert!(mesh.faces.len() > 500, "{} faces", mesh.faces.len());
        for p in &mesh.positions {
            let r = norm(sub(*p, c));
            assert!((r - 0.6).abs() < 1.5 * grid.cell, "vertex at radius {r}");
        }
        for (p, n) in mesh.positions.iter().zip(&mesh.normals) {
            let out = sub(*p, c);
            assert!(sos_core::camera::dot(out, *n) > 0.0, "normal {n:?} at {p:?} points inwards");
        }
        let volume = mesh.signed_volume();
        let sphere = 4.0 / 3.0 * std::f64::consts::PI * 0.6f64.powi(3);
        assert!((volume - sphere).abs() < 0.15 * sphere, "volume {volume} vs {sphere}");
        // Every edge is shared by exactly two faces: the surface is closed.
        let mut edges = std::collections::HashMap::new();
        for f in &mesh.faces {
            for k in 0..3 {
                let (a, b) = (f[k].min(f[(k + 1) % 3]), f[k].max(f[(k + 1) % 3]));
                *edges.entry((a, b)).or_insert(0) += 1;
            }
        }
        assert!(edges.values().all(|&n| n == 2));
    }

    #[test]
    fn a_ball_cut_by_the_box_is_closed_on_the_box_face() {
        let grid = Grid::fit([0.0; 3], [1.0; 3], 21);
        let density = ball(&grid, [0.0, 0.5, 0.5], 0.3);
        let mesh = extract(&grid, &density, iso_level(grid.cell), &vec![true; grid.len()]);
        assert!(mesh.positions.iter().all(|p| p.iter().all(|v| (0.0..=1.0).contains(v))));
        assert!(mesh.positions.iter().any(|p| p[0] == 0.0), "no cap on the x = 0 face");
        assert!(mesh.signed_volume() > 0.0);
    }

    #[test]
    fn background_nodes_are_cleared() {
        let grid = Grid::fit([-1.0; 3], [1.0; 3], 21);
        let mut density = ball(&grid, [-0.5, 0.0, 0.0], 0.3);
        density.iter_mut().zip(ball(&grid, [0.5, 0.0, 0.0], 0.3)).for_each(|(a, b)| *a += b);
        let keep: Vec<bool> = (0..grid.len()).map(|i| grid.node(i)[0] < 0.0).collect();
        let mesh = extract(&grid, &density, iso_level(grid.cell), &keep);
        assert!(!mesh.faces.is_empty());
        assert!(mesh.positions.iter().all(|p| p[0] < 0.0), "the right ball was kept");
    }

    /// A camera on +Z looking at the origin, with a mask of the left half of the image and a
    /// wall at depth `wall` behind (or in front of) the origin.
    fn view(eye_z: f32, wall: f32, left_is_fg: bool) -> ViewEvidence {
        let camera = Camera::look_at([0.0, 0.0, eye_z], [0.0; 3], [0.0, 1.0, 0.0], 20, 20, 20.0);
        let foreground = (0..400).map(|i| (i % 20 < 10) == left_is_fg).collect();
        ViewEvidence { camera, foreground, depth: vec![wall; 400] }
    }

    #[test]
    fn votes_count_only_views_that_see_the_point() {
        let p = [-0.1, 0.0, 0.0]; // left of centre in every view below
                                  // Two views see it as foreground, one as background: object.
        let views = [view(2.0, 2.0, true), view(3.0, 3.0, true), view(2.5, 2.5, false)];
        assert!(is_object(p, &views, 0.01));
        // The background view sees it, the foreground views have a surface well in front of
        // it: only the background view votes.
        let views = [view(2.0, 1.0, true), view(3.0, 2.0, true), view(2.5, 2.5, false)];
        assert!(!is_object(p, &views, 0.01));
        // Nobody sees it: the hull vote of all three decides.
        let views = [view(2.0, 1.0, true), view(3.0, 2.0, true), view(2.5, 1.5, false)];
        assert!(is_object(p, &views, 0.01));
        // Outside every image: background.
        assert!(!is_object([50.0, 0.0, 0.0], &views, 0.01));
    }

    #[test]
    fn object_box_ignores_stray_points() {
        let mut points: Vec<Vec3> = (0..1000).map(|i| [(i % 10) as f32 * 0.1, 0.0, 1.0]).collect();
        points.push([40.0, 0.0, 1.0]);
        let (lo, hi) = object_box(&points, ([-10.0; 3], [10.0; 3])).unwrap();
        assert!(lo[0] < 0.0 && hi[0] > 0.9 && hi[0] < 1.2, "{lo:?} {hi:?}");
        assert!(object_box(&[], ([-1.0; 3], [1.0; 3])).is_none());
    }
}
