//! Everything a random world is, drawn from its seed in a fixed order: the rig, the object,
//! the cameras, the surroundings sized around them, the materials (with the hard cases), the
//! distractors and the light.

use sos_core::camera::{normalize, Vec3};

use super::super::Rig;
use super::composition::{compose, Composition};
use super::distractors::{self, Region};
use super::draw::{stream, Aspect, Draw};
use super::environment::{self, Environment};
use super::framing::Framing;
use super::palette::{material, HardCase};
use super::rigs::{capture, draw_focal, Capture};
use super::world::{Part, RandomWorld};

/// The rigs `rig = "random"` draws from.
pub const RIGS: [Rig; 5] = [Rig::ObjectCentric, Rig::ForwardFacing, Rig::Unbounded, Rig::Hemisphere, Rig::Grazing];

/// A random world and its cameras.
#[derive(Debug, Clone)]
pub struct Blueprint {
    /// The rig (never [`Rig::Random`]).
    pub rig: Rig,
    /// The world to trace.
    pub world: RandomWorld,
    /// Cameras and novel-view path.
    pub capture: Capture,
    /// The foreground object.
    pub composition: Composition,
    /// Centre of the object's bounding box (the cameras' aim).
    pub centre: Vec3,
    /// The colour hard case drawn.
    pub hard_case: HardCase,
    /// Number of distractors placed.
    pub distractors: usize,
}

/// The box holding `points`.
fn bounds(points: impl Iterator<Item = Vec3>) -> [Vec3; 2] {
    let mut b = [[f32::INFINITY; 3], [f32::NEG_INFINITY; 3]];
    for p in points {
        for k in 0..3 {
            b[0][k] = b[0][k].min(p[k]);
            b[1][k] = b[1][k].max(p[k]);
        }
    }
    b
}

/// Draws world `seed` for `rig`, with `views` cameras of `width` x `height` and `path_views`
/// novel-view cameras.
pub fn draw(seed: u64, rig: Rig, views: usize, width: u32, height: u32, path_views: usize) -> Blueprint {
    let rig = match rig {
        Rig::Random => RIGS[stream(seed, Aspect::Rig).below(RIGS.len())],
        r => r,
    };
    let composition = compose(&mut stream(seed, Aspect::Composition));
    let [lo, hi] = composition.aabb();
    let centre = [0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k]));
    let radius = 0.5 * (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f32>().sqrt();

    let mut rng = stream(seed, Aspect::Cameras);
    let focal = draw_focal(width, &mut rng);
    let framing = Framing { outline: composition.silhouette(), centre, radius, width, height, focal };
    let capture = capture(rig, views, path_views, &framing, &mut rng);

    // Every camera position the world must make room for: the views, the novel-view path, and
    // for the forward-facing grid a rectangle twice its size (the LLFF spiral stays inside).
    let mut eyes: Vec<Vec3> = capture.cameras.iter().chain(&capture.path).map(|c| c.origin()).collect();
    if rig == Rig::ForwardFacing {
        let origins: Vec<Vec3> = capture.cameras.iter().map(|c| c.origin()).collect();
        let [glo, ghi] = bounds(origins.iter().copied());
        let mid = [0, 1, 2].map(|k| 0.5 * (glo[k] + ghi[k]));
        eyes.extend(origins.iter().map(|o| [0, 1, 2].map(|k| mid[k] + 2.0 * (o[k] - mid[k]))));
    }
    let reach = eyes.iter().map(|o| (o[0] * o[0] + o[2] * o[2]).sqrt()).fold(0.0, f32::max);

    let mut rng = stream(seed, Aspect::Environment);
    let (environment, towers) = if rig == Rig::Unbounded {
        environment::open(reach, &mut rng)
    } else {
        let content = bounds(eyes.iter().copied().chain([lo, hi]));
        (environment::room(content, &mut rng), Vec::new())
    };

    let mut rng = stream(seed, Aspect::Materials);
    let hard_case = HardCase::draw(&mut rng);
    let backdrop = match &environment {
        // Camouflage copies the floor (always in view, under the object) or a wall.
        Environment::Room { faces, .. } => faces[if rng.chance(0.65) { 2 } else { [0, 1, 4, 5][rng.below(4)] }],
        Environment::Open { ground, .. } => *ground,
    };
    let ground = *environment.ground();
    let mut parts: Vec<Part> = composition
        .parts
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let size = (s.top() - s.bottom()).max(s.footprint()).clamp(0.15, 0.6);
            let m = if i == 0 && composition.pedestal {
                // Pedestals and plinths keep ordinary colours.
                material([1.0, 0.6, 1.0, 1.0], size, &[0, 1, 2], &mut rng).at(s.centre())
            } else if hard_case == HardCase::Camouflage {
                // Same texture frame as the surface it copies, so the patterns line up.
                hard_case.material(&ground, &backdrop, size, &mut rng)
            } else {
                hard_case.material(&ground, &backdrop, size, &mut rng).at(s.centre())
            };
            Part::new(*s, m, true)
        })
        .collect();

    let mut rng = stream(seed, Aspect::Distractors);
    let count = rng.below(6);
    let mut hull = eyes.clone();
    for s in &composition.parts {
        let [a, b] = s.aabb();
        hull.extend((0..8).map(|k| [0, 1, 2].map(|i| if k >> i & 1 == 1 { b[i] } else { a[i] })));
    }
    let region = match &environment {
        Environment::Room { min, max, .. } => Region::Floor { min: *min, max: *max },
        Environment::Open { .. } => Region::Disk { radius: 2.2 * reach + 1.0 },
    };
    let placed = distractors::place(count, region, &hull, &mut rng);
    for s in &placed {
        let size = (s.top() - s.bottom()).max(s.footprint()).clamp(0.15, 0.6);
        let m = material([1.0, 1.0, 1.0, 1.0], size, &[0, 1, 2], &mut rng).at(s.centre());
        parts.push(Part::new(*s, m, false));
    }
    parts.extend(towers.into_iter().map(|(s, m)| Part::new(s, m, false)));

    let mut rng = stream(seed, Aspect::Light);
    let (a, e) = (rng.angle(), rng.range(35.0f32, 70.0).to_radians());
    let light = normalize([e.cos() * a.sin(), e.sin(), e.cos() * a.cos()]);
    let ambient = rng.range(0.3, 0.5);
    let diffuse = rng.range(0.55, 0.8);
    let world = RandomWorld { parts, environment, light, ambient, diffuse };
    Blueprint { rig, world, capture, composition, centre, hard_case, distractors: placed.len() }
}

impl Blueprint {
    /// A few lines for humans: rig, object, hard case, distractors, surroundings.
    pub fn describe(&self) -> String {
        format!(
            "{}\n{}\nhard case: {}; {} distractor(s); {}",
            self.capture.summary,
            self.composition.describe(),
            self.hard_case.name(),
            self.distractors,
            self.world.environment.describe()
        )
    }
}
