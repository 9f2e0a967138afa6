//! How well a mask drawn from the field's 3D geometry alone would segment a run's held-out
//! views: the upper bound of a geometric objectness prior for stage 2.
//!
//! 1. The density is sampled at the centres of an `N³` grid over the unit cube the field
//!    models; a cell is occupied when its alpha over its own world size exceeds `ALPHA` (0.3).
//! 2. Up to three large planes are found among the occupied cells by RANSAC (tolerance
//!    `TOL_CELLS` (2) local cell sizes): the ground and walls.
//! 3. The occupied cells off every plane are grouped into 26-connected components; the object
//!    is the component nearest the focus (where the training axes meet, or for a forward-facing
//!    rig the point on the mean axis at the median central depth of each view), plus every
//!    component within `JOIN` (0.15) of the view camera's distance from the focus.
//! 4. Each held-out view's rendered surface points are foreground when their cell (dilated by
//!    one) is an object cell; the mask is scored against the view's exact mask.
//!
//! `cargo run --release --manifest-path experiments/Cargo.toml --bin prior3d -- CONFIG CHECKPOINT [N]`
//! (`N` 128 by default; the environment variables `ALPHA`, `TOL_CELLS` and `JOIN` change the
//! thresholds).

use rand::{Rng, SeedableRng};
use sos_core::camera::{cross, dot, normalize, sub, Vec3};
use sos_core::metrics::binary_iou;
use sos_core::segment::infer::{render_logits, FocusTarget};
use sos_experiments::{args_or_usage, open_with_head};
use sos_plugins as _;

/// A setting from the environment variable `name`, or `default`.
fn setting(name: &str, default: f32) -> f32 {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// Alpha over a cell's world size above which the cell is occupied (`ALPHA`).
fn alpha() -> f32 {
    setting("ALPHA", 0.3)
}

/// Plane tolerance, in local cell sizes (`TOL_CELLS`).
fn tol_cells() -> f32 {
    setting("TOL_CELLS", 2.0)
}

/// Components within this share of the view camera's distance from the focus join the object
/// (`JOIN`).
fn join() -> f32 {
    setting("JOIN", 0.15)
}

/// Smallest share of the occupied cells a plane must hold.
const MIN_PLANE_SHARE: f64 = 0.1;

/// Cells of an `n³` grid within one step of cell `g` along every axis (itself included), by
/// index; `g` may lie outside the grid.
fn neighbours(n: usize, g: [i64; 3]) -> impl Iterator<Item = usize> {
    let inside = move |v: i64| (0..n as i64).contains(&v);
    (-1..=1i64).flat_map(move |dz| {
        (-1..=1i64).flat_map(move |dy| {
            (-1..=1i64).filter_map(move |dx| {
                let (x, y, z) = (g[0] + dx, g[1] + dy, g[2] + dz);
                (inside(x) && inside(y) && inside(z)).then(|| (z as usize * n + y as usize) * n + x as usize)
            })
        })
    })
}

fn main() {
    sos_benchmarks::setup();
    let args = args_or_usage(2, "prior3d CONFIG CHECKPOINT [N]");
    let n: usize = args.get(2).map_or(128, |s| s.parse().expect("N is a number"));
    let (session, head) = open_with_head(&args[0], &args[1]);
    let c = session.contraction;
    let (alpha, tol_cells, join) = (alpha(), tol_cells(), join());

    // 1. Occupied cells.
    let cells = n * n * n;
    let centre = |i: usize| -> Vec3 {
        let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
        [(x as f32 + 0.5) / n as f32, (y as f32 + 0.5) / n as f32, (z as f32 + 0.5) / n as f32]
    };
    let world: Vec<Vec3> = (0..cells).map(|i| c.from_unit(centre(i))).collect();
    // World size of a cell: the distance to the centre of its +x+y+z neighbour over √3.
    let size: Vec<f32> = (0..cells)
        .map(|i| {
            let u = centre(i);
            let v = [u[0] + 1.0 / n as f32, u[1] + 1.0 / n as f32, u[2] + 1.0 / n as f32];
            let d = sub(c.from_unit(v), world[i]);
            (dot(d, d).sqrt() / 3f32.sqrt()).max(1e-9)
        })
        .collect();
    let mut sigma = vec![0.0f32; cells];
    session.field.density(&world, &mut sigma);
    let occupied: Vec<bool> = (0..cells).map(|i| 1.0 - (-sigma[i] * size[i]).exp() > alpha).collect();
    let occ: Vec<usize> = (0..cells).filter(|&i| occupied[i]).collect();
    eprintln!("{} of {cells} cells occupied", occ.len());

    // 2. Planes.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut left = occ.clone();
    let mut on_plane = vec![false; cells];
    for k in 0..3 {
        if left.len() < 3 {
            break;
        }
        let on = |plane: &(Vec3, f32), i: usize| (dot(plane.0, world[i]) - plane.1).abs() <= tol_cells * size[i];
        let mut best: Option<(usize, (Vec3, f32))> = None;
        for _ in 0..400 {
            let [a, b, cc] = [0; 3].map(|_| world[left[rng.gen_range(0..left.len())]]);
            let nrm = cross(sub(b, a), sub(cc, a));
            if dot(nrm, nrm) < 1e-18 {
                continue;
            }
            let nrm = normalize(nrm);
            let plane = (nrm, dot(nrm, a));
            let count = (0..2000).map(|_| left[rng.gen_range(0..left.len())]).filter(|&i| on(&plane, i)).count();
            if best.is_none_or(|(m, _)| count > m) {
                best = Some((count, plane));
            }
        }
        let Some((_, plane)) = best else { break };
        let held: Vec<usize> = left.iter().copied().filter(|&i| on(&plane, i)).collect();
        if (held.len() as f64) < MIN_PLANE_SHARE * occ.len() as f64 {
            break;
        }
        eprintln!(
            "plane {k}: normal {:?}, {} cells ({:.0}%)",
            plane.0,
            held.len(),
            100.0 * held.len() as f64 / occ.len() as f64
        );
        // Every occupied cell near the plane is the plane's, even among those taken already.
        for &i in &occ {
            if on(&plane, i) {
                on_plane[i] = true;
            }
        }
        left.retain(|&i| !on_plane[i]);
    }

    // 3. Components of the cells off the planes.
    let mut comp = vec![u32::MAX; cells];
    let mut sizes = Vec::new();
    for &s in &left {
        if comp[s] != u32::MAX {
            continue;
        }
        let id = sizes.len() as u32;
        let mut stack = vec![s];
        comp[s] = id;
        let mut count = 0usize;
        while let Some(i) = stack.pop() {
            count += 1;
            let g = [(i % n) as i64, ((i / n) % n) as i64, (i / (n * n)) as i64];
            for j in neighbours(n, g) {
                if occupied[j] && !on_plane[j] && comp[j] == u32::MAX {
                    comp[j] = id;
                    stack.push(j);
                }
            }
        }
        sizes.push(count);
    }
    eprintln!("{} components off the planes; largest {:?}", sizes.len(), {
        let mut s = sizes.clone();
        s.sort_unstable_by(|a, b| b.cmp(a));
        s.truncate(6);
        s
    });

    // 4. Score the held-out views.
    let focus_target = FocusTarget::of_scene(&session.scene);
    let (mut sum, mut scored) = (0.0, 0usize);
    let tests = session.scene.test.clone();
    for &v in &tests {
        let view = &session.scene.views[v];
        let r = render_logits(&session, &head, &view.camera);
        let (w, h) = (r.rgb.width, r.rgb.height);
        let focus = focus_target.point_for(&r.depth, w, h).unwrap_or(session.scene.focus_point());
        let reach = {
            let d = sub(view.camera.origin(), focus);
            dot(d, d).sqrt() * join
        };
        // Per component, its nearest cell's distance to the focus.
        let mut nearest = vec![f32::INFINITY; sizes.len()];
        for &i in &left {
            let d = sub(world[i], focus);
            let d = dot(d, d).sqrt();
            let k = comp[i] as usize;
            nearest[k] = nearest[k].min(d);
        }
        let closest = nearest.iter().copied().fold(f32::INFINITY, f32::min);
        let chosen: Vec<bool> = nearest.iter().map(|&d| d <= closest.max(reach)).collect();
        let object = |u: Vec3| {
            neighbours(n, u.map(|v| (v * n as f32).floor() as i64))
                .any(|j| comp[j] != u32::MAX && chosen[comp[j] as usize])
        };
        let pred: Vec<bool> = r.points.iter().map(|p| p.is_some_and(|p| object(c.to_unit(p)))).collect();
        let Some(gt) = view.mask.as_ref().map(|m| m.resized_nearest(w, h)) else {
            eprintln!("{}: no exact mask", view.name);
            continue;
        };
        let gt: Vec<bool> = gt.data.iter().map(|&g| g >= 0.5).collect();
        let iou = binary_iou(&gt, &pred).expect("the mask has the view's size");
        let miou = iou.miou().unwrap_or(0.0);
        println!(
            "{}: mIoU {miou:.3} (FG {:.3}, BG {:.3}), {} components chosen",
            view.name,
            iou.fg.unwrap_or(0.0),
            iou.bg.unwrap_or(0.0),
            chosen.iter().filter(|&&c| c).count()
        );
        sum += miou;
        scored += 1;
    }
    println!("mean mIoU {:.3} over {scored} views", sum / scored.max(1) as f64);
}
