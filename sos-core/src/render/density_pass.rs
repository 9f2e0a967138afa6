//! The density pass of a render: the field's density at the candidates, evaluated in waves so
//! that early ray termination never evaluates what lies behind a ray's termination point, and
//! which candidates the full pass needs (those before termination whose compositing weight
//! exceeds the threshold). A field with a per-sample state
//! ([`FrozenPass::density_state_dim`](crate::plugin::FrozenPass::density_state_dim), NeRF's trunk activations) hands it over for the kept
//! candidates, so that a frozen render's colour pass does not run the density network again.

use rayon::prelude::*;

use crate::plugin::field::plain;
use crate::plugin::RadianceField;
use crate::render::sampler::Samples;

/// Candidates per live ray in the first wave, doubled each wave up to [`MAX_WAVE`].
const FIRST_WAVE: usize = 8;
/// Largest wave.
const MAX_WAVE: usize = 128;
/// Most candidates in one field call, so that one call's state stays small (64 MiB for
/// NeRF's 256 floats per sample) however many rays are live.
const GROUP: usize = 1 << 16;

/// What the density pass decided, per candidate.
pub struct DensityPass {
    /// Density at each candidate; 0 where it was not evaluated (behind a ray's termination).
    pub sigma: Vec<f32>,
    /// Whether the full pass needs the candidate.
    pub keep: Vec<bool>,
    /// Optical depth of the dropped candidates between a kept candidate and the previous kept
    /// one of its ray (so that the kept samples' transmittance stays exact).
    pub skipped_before: Vec<f32>,
    /// The field's state at the kept candidates, when the field has one and it fit the budget.
    pub state: Option<KeptState>,
    /// Candidates whose density was evaluated (for profiling: early termination leaves out
    /// what lies behind each ray's termination, but not all of a ray's last wave).
    pub evaluated: usize,
}

/// The field's per-sample state at the kept candidates, in the order the waves kept them.
pub struct KeptState {
    /// `[kept, dim]`.
    pub values: Vec<f32>,
    dim: usize,
    /// Most floats `values` may hold.
    limit: usize,
    /// Per candidate, its row in `values` (`u32::MAX`: not kept).
    row_of: Vec<u32>,
}

impl KeptState {
    /// Rows of `values` for candidates `kept` (all kept by the pass).
    pub fn rows(&self, kept: &[u32]) -> Vec<u32> {
        kept.iter().map(|&i| self.row_of[i as usize]).collect()
    }

    /// Appends the state of the kept candidates `kept` (candidate, row of `group_state`), in
    /// that order; false, appending nothing, when they would exceed the budget.
    fn extend(&mut self, kept: &[(u32, u32)], group_state: &[f32]) -> bool {
        let dim = self.dim;
        let start = self.values.len();
        if start + kept.len() * dim > self.limit {
            return false;
        }
        for (j, &(i, _)) in kept.iter().enumerate() {
            self.row_of[i as usize] = (start / dim + j) as u32;
        }
        // Rows are copied in parallel: a frozen grid's state is most of what the pass writes.
        self.values.resize(start + kept.len() * dim, 0.0);
        self.values[start..].par_chunks_mut(dim).zip(kept.par_iter()).with_min_len(256).for_each(|(dst, &(_, row))| {
            dst.copy_from_slice(&group_state[row as usize * dim..][..dim]);
        });
        true
    }
}

/// Where one ray's scan stands between waves.
struct RayScan {
    /// Next candidate to evaluate.
    cursor: usize,
    /// Optical depth up to `cursor`.
    optical: f32,
    /// Optical depth of the candidates dropped since the last kept one.
    skipped: f32,
}

/// Runs the density pass: rays stop once their transmittance falls below `early_stop` (0: no
/// termination, every candidate in one wave) and candidates are kept when their compositing
/// weight exceeds `min_weight` (0: every candidate before termination). The kept candidates'
/// state is kept, in `buffer` (emptied first; its memory is reused), when the field has one
/// and it takes at most `state_budget` bytes.
pub fn density_pass(
    field: &dyn RadianceField,
    candidates: &Samples,
    early_stop: f32,
    min_weight: f32,
    state_budget: usize,
    mut buffer: Vec<f32>,
) -> DensityPass {
    let n = candidates.len();
    let dim = plain::density_state_dim(field);
    let limit = state_budget / std::mem::size_of::<f32>();
    let mut state = (dim > 0 && n > 0 && limit >= dim).then(|| {
        // Reserved, not touched: pages are only committed as rows arrive. A buffer too small
        // is replaced rather than grown (growing would copy its old contents), with room for
        // later passes over up to twice as many candidates.
        let need = (n * dim).min(limit);
        buffer.clear();
        if buffer.capacity() < need {
            buffer = Vec::with_capacity((2 * n * dim).min(limit));
        }
        KeptState { values: buffer, dim, limit, row_of: vec![u32::MAX; n] }
    });
    let mut pass = DensityPass {
        sigma: vec![0.0; n],
        keep: vec![false; n],
        skipped_before: vec![0.0; n],
        state: None,
        evaluated: 0,
    };
    // Optical depth at which the transmittance reaches `early_stop`.
    let stop_at = stop_depth(early_stop);
    let end_of = |r: usize| ray_end(candidates, r);
    let mut rays: Vec<RayScan> = (0..candidates.n_rays())
        .map(|r| RayScan { cursor: candidates.ray_start[r] as usize, optical: 0.0, skipped: 0.0 })
        .collect();
    let mut live: Vec<usize> = (0..rays.len()).filter(|&r| rays[r].cursor < end_of(r)).collect();
    let mut wave = if early_stop > 0.0 { FIRST_WAVE } else { usize::MAX };
    let (mut idx, mut positions, mut values, mut group_state) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    while !live.is_empty() {
        let mut first = 0;
        while first < live.len() {
            // The next group of live rays, each with its whole wave.
            idx.clear();
            let mut last = first;
            while last < live.len() {
                let r = live[last];
                let stop = rays[r].cursor.saturating_add(wave).min(end_of(r));
                if !idx.is_empty() && idx.len() + (stop - rays[r].cursor) > GROUP {
                    break;
                }
                idx.extend(rays[r].cursor as u32..stop as u32);
                last += 1;
            }
            pass.evaluated += idx.len();
            positions.clear();
            positions.extend(idx.iter().map(|&i| candidates.positions[i as usize]));
            values.clear();
            values.resize(idx.len(), 0.0);
            if state.is_some() {
                group_state.resize(idx.len() * dim, 0.0);
                plain::density_with_state(field, &positions, &mut values, &mut group_state);
            } else {
                field.density(&positions, &mut values);
            }
            // Scan each ray's wave in order, as compositing will.
            let scan = WaveScan { group: &live[first..last], wave, stop_at, min_weight, values: &values, candidates };
            let state_fits = match state.as_mut() {
                Some(s) => scan.with_state(&mut rays, &mut pass, s, &group_state),
                None => {
                    scan.parallel(&mut rays, &mut pass, None);
                    true
                }
            };
            if !state_fits {
                // Over budget: the colour pass evaluates the whole network instead.
                state = None;
            }
            first = last;
        }
        live.retain(|&r| rays[r].cursor < end_of(r) && rays[r].optical <= stop_at);
        wave = wave.saturating_mul(2).min(MAX_WAVE);
    }
    pass.state = state;
    pass
}

/// Optical depth past which a ray terminates: where its transmittance falls below `early_stop`
/// (0: never).
pub fn stop_depth(early_stop: f32) -> f32 {
    if early_stop > 0.0 {
        -early_stop.ln()
    } else {
        f32::INFINITY
    }
}

/// How many of one ray's samples, in order, come before it terminates by the pass's rule: each
/// while the optical depth before it is at most `-ln early_stop`. A render that evaluated every
/// candidate keeps these, and so keeps what the pass would have.
pub fn samples_before_termination(sigma: &[f32], delta: &[f32], early_stop: f32) -> usize {
    let stop_at = stop_depth(early_stop);
    let mut optical = 0.0f32;
    for (n, (&sigma, &delta)) in sigma.iter().zip(delta).enumerate() {
        if optical > stop_at {
            return n;
        }
        optical += sigma * delta;
    }
    sigma.len()
}

/// One past ray `r`'s last candidate.
fn ray_end(candidates: &Samples, r: usize) -> usize {
    candidates.ray_start[r + 1] as usize
}

/// What the scan decides for one candidate of a ray's wave, given the ray's optical depth so
/// far: its density is kept, and it is kept or skipped.
#[inline]
fn scan_candidate(ray: &mut RayScan, sigma: f32, delta: f32, min_weight: f32) -> (bool, f32) {
    let tau = sigma * delta;
    // Without a threshold every candidate is kept: its weight (two exponentials) is not needed.
    let keep = min_weight <= 0.0 || -(-tau).exp_m1() * (-ray.optical).exp() > min_weight;
    let skipped = if keep {
        std::mem::take(&mut ray.skipped)
    } else {
        ray.skipped += tau;
        0.0
    };
    ray.optical += tau;
    (keep, skipped)
}

/// One group's waves, scanned as compositing will: each ray in order.
#[derive(Clone, Copy)]
struct WaveScan<'a> {
    /// The group's live rays, ascending.
    group: &'a [usize],
    wave: usize,
    /// Optical depth at which a ray terminates.
    stop_at: f32,
    min_weight: f32,
    /// The group's densities, ray after ray.
    values: &'a [f32],
    candidates: &'a Samples,
}

impl WaveScan<'_> {
    /// The scan: rays are independent, so they are scanned in parallel, each in order, with the
    /// same arithmetic as one after another. With `kept`, each kept candidate and its row of
    /// the group's values are appended to it, ray after ray.
    fn parallel(&self, rays: &mut [RayScan], pass: &mut DensityPass, mut kept: Option<&mut Vec<(u32, u32)>>) {
        let WaveScan { group, wave, stop_at, min_weight, values, candidates } = *self;
        // Each group ray's wave: (ray, first candidate, first row in `values`, length).
        let mut spans = Vec::with_capacity(group.len());
        let mut rows = 0;
        for &r in group {
            let cursor = rays[r].cursor;
            let len = cursor.saturating_add(wave).min(ray_end(candidates, r)) - cursor;
            spans.push((r, cursor, rows, len));
            rows += len;
        }
        // Per row: whether it was scanned, whether it is kept, and the optical depth skipped
        // before it. Each ray gets its own rows and its own scan state (the group's rays ascend).
        let mut decided = vec![(false, false, 0.0f32); rows];
        let mut pieces = Vec::with_capacity(spans.len());
        let (mut rest, mut rest_rays, mut first_ray) = (&mut decided[..], &mut rays[..], 0);
        for &(r, cursor, row, len) in &spans {
            let (part, tail) = std::mem::take(&mut rest).split_at_mut(len);
            rest = tail;
            let (ray, tail) = std::mem::take(&mut rest_rays)[r - first_ray..]
                .split_first_mut()
                .expect("a group's rays lie in the batch, ascending");
            rest_rays = tail;
            first_ray = r + 1;
            pieces.push((ray, part, cursor, row));
        }
        pieces.par_iter_mut().with_min_len(64).for_each(|(ray, part, cursor, row)| {
            for (k, out) in part.iter_mut().enumerate() {
                if ray.optical > stop_at {
                    break;
                }
                let (keep, skipped) = scan_candidate(ray, values[*row + k], candidates.delta[*cursor + k], min_weight);
                *out = (true, keep, skipped);
            }
        });
        drop(pieces);
        for (r, cursor, row, len) in spans {
            for k in 0..len {
                let (scanned, keep, skipped) = decided[row + k];
                if !scanned {
                    break;
                }
                pass.sigma[cursor + k] = values[row + k];
                pass.keep[cursor + k] = keep;
                if keep {
                    pass.skipped_before[cursor + k] = skipped;
                    if let Some(kept) = kept.as_mut() {
                        kept.push(((cursor + k) as u32, (row + k) as u32));
                    }
                }
            }
            rays[r].cursor = cursor + len;
        }
    }

    /// The scan when the field's state is kept for the kept candidates, appended ray after
    /// ray. Returns whether the state still fits its budget.
    fn with_state(
        &self,
        rays: &mut [RayScan],
        pass: &mut DensityPass,
        state: &mut KeptState,
        group_state: &[f32],
    ) -> bool {
        let mut kept = Vec::new();
        self.parallel(rays, pass, Some(&mut kept));
        state.extend(&kept, group_state)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Vec3;
    use crate::plugin::FieldTape;

    /// Density `10·x` clamped at 0; its state is the position itself (3 floats).
    struct Ramp {
        with_state: bool,
    }

    impl RadianceField for Ramp {
        fn density(&self, positions: &[Vec3], density: &mut [f32]) {
            for (p, d) in positions.iter().zip(density) {
                *d = (10.0 * p[0]).max(0.0);
            }
        }
        fn forward(&self, _: &[Vec3], _: &[Vec3], _: &mut [f32], _: &mut [[f32; 3]], _: bool) -> FieldTape {
            unreachable!("the density pass only reads density")
        }
        fn backward(&mut self, _: &[Vec3], _: &[Vec3], _: FieldTape, _: &[f32], _: &[[f32; 3]]) {}
        fn step(&mut self, _: f32) {}
        fn seg_input_dim(&self) -> usize {
            0
        }
        fn seg_input(&self, _: &[Vec3], _: &mut [f32]) {}
        fn save_state(&self) -> Vec<u8> {
            Vec::new()
        }
        fn load_state(&mut self, _: &[u8]) -> Result<(), crate::error::StateError> {
            Ok(())
        }
        fn num_parameters(&self) -> usize {
            0
        }
        fn parameters(&self) -> Vec<f32> {
            Vec::new()
        }
        fn set_parameters(&mut self, _: &[f32]) -> Result<(), crate::error::StateError> {
            Ok(())
        }
        fn gradients(&self) -> Vec<f32> {
            Vec::new()
        }
        fn gradients_finite(&self) -> bool {
            true
        }
        fn discard_gradients(&mut self) {}
        fn frozen_pass(&self) -> Option<&dyn crate::plugin::field::FrozenPass> {
            Some(self)
        }
    }

    impl crate::plugin::field::FrozenPass for Ramp {
        fn density_state_dim(&self) -> usize {
            if self.with_state {
                3
            } else {
                0
            }
        }
        fn density_with_state(&self, positions: &[Vec3], density: &mut [f32], state: &mut [f32]) {
            self.density(positions, density);
            for (p, s) in positions.iter().zip(state.chunks_exact_mut(3)) {
                s.copy_from_slice(p);
            }
        }
    }

    /// Rays of different lengths along +x from x = -1, in steps of 0.01.
    fn candidates() -> Samples {
        let mut s = Samples { ray_start: vec![0], ..Default::default() };
        for (r, len) in [0usize, 300, 17, 150, 1, 260].into_iter().enumerate() {
            for k in 0..len {
                let x = -1.0 + 0.01 * k as f32;
                s.t.push(k as f32);
                s.delta.push(0.01);
                s.positions.push([x, r as f32, 0.0]);
                s.directions.push([1.0, 0.0, 0.0]);
            }
            s.ray_start.push(s.t.len() as u32);
        }
        s
    }

    /// The waves decide what one scan over all densities decides, and the state of every
    /// kept candidate is its own.
    #[test]
    fn waves_match_one_scan_and_keep_each_candidates_state() {
        let c = candidates();
        let mut all = vec![0.0; c.len()];
        Ramp { with_state: false }.density(&c.positions, &mut all);
        for (early_stop, min_weight) in [(1e-4, 1e-3), (1e-2, 0.0), (0.0, 1e-3), (1e-4, 0.0)] {
            let pass = density_pass(&Ramp { with_state: true }, &c, early_stop, min_weight, usize::MAX, Vec::new());
            let stop_at = if early_stop > 0.0 { -f32::ln(early_stop) } else { f32::INFINITY };
            let (mut kept, mut terminated) = (0, 0);
            for r in 0..c.n_rays() {
                let mut optical = 0.0f32;
                let mut skipped = 0.0f32;
                for i in c.range(r) {
                    if optical > stop_at {
                        terminated += 1;
                        assert!(!pass.keep[i]);
                        continue;
                    }
                    assert_eq!(pass.sigma[i], all[i]);
                    let tau = all[i] * c.delta[i];
                    let w = -(-tau).exp_m1() * (-optical).exp();
                    assert_eq!(pass.keep[i], min_weight <= 0.0 || w > min_weight);
                    if pass.keep[i] {
                        kept += 1;
                        assert_eq!(pass.skipped_before[i], skipped);
                        skipped = 0.0;
                    } else {
                        skipped += tau;
                    }
                    optical += tau;
                }
            }
            assert!(kept > 100, "{kept} kept");
            assert_eq!(terminated > 0, early_stop > 0.0, "{terminated} candidates behind termination");
            let state = pass.state.as_ref().expect("within budget");
            let kept_ids: Vec<u32> = (0..c.len() as u32).filter(|&i| pass.keep[i as usize]).collect();
            let rows = state.rows(&kept_ids);
            assert_eq!(state.values.len(), 3 * kept_ids.len());
            for (&i, &row) in kept_ids.iter().zip(&rows) {
                assert_eq!(&state.values[3 * row as usize..][..3], &c.positions[i as usize][..]);
            }
            // A state one row over its budget is dropped; the decisions stay.
            let tight =
                density_pass(&Ramp { with_state: true }, &c, early_stop, min_weight, 4 * (3 * kept - 1), Vec::new());
            assert!(tight.state.is_none());
            assert_eq!((tight.keep, tight.sigma), (pass.keep.clone(), pass.sigma.clone()));
            let plain = density_pass(&Ramp { with_state: false }, &c, early_stop, min_weight, usize::MAX, Vec::new());
            assert!(plain.state.is_none());
            assert_same_decisions(&plain, &pass);
        }
    }

    fn assert_same_decisions(a: &DensityPass, b: &DensityPass) {
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(a.keep, b.keep);
        assert_eq!(bits(&a.sigma), bits(&b.sigma));
        assert_eq!(bits(&a.skipped_before), bits(&b.skipped_before));
        assert_eq!(a.evaluated, b.evaluated);
    }

    /// Without a state the rays of a group are scanned in parallel: with thousands of rays of
    /// every length, the decisions equal those of the one-ray-after-another scan bit for bit.
    #[test]
    fn the_parallel_scan_decides_as_the_serial_one() {
        let mut c = Samples { ray_start: vec![0], ..Default::default() };
        for r in 0..3000usize {
            let len = (r * 7919) % 230;
            for k in 0..len {
                c.t.push(k as f32);
                c.delta.push(0.002 + 0.001 * (r % 5) as f32);
                c.positions.push([-0.5 + 0.007 * k as f32 + 0.001 * (r % 13) as f32, 0.0, 0.0]);
                c.directions.push([1.0, 0.0, 0.0]);
            }
            c.ray_start.push(c.t.len() as u32);
        }
        for (early_stop, min_weight) in [(1e-4, 1e-3), (1e-2, 0.0), (0.0, 1e-3)] {
            let serial = density_pass(&Ramp { with_state: true }, &c, early_stop, min_weight, usize::MAX, Vec::new());
            let parallel =
                density_pass(&Ramp { with_state: false }, &c, early_stop, min_weight, usize::MAX, Vec::new());
            assert!(serial.state.is_some() && parallel.state.is_none());
            assert!(parallel.keep.iter().any(|&k| k) && parallel.keep.iter().any(|&k| !k));
            assert_same_decisions(&parallel, &serial);
        }
    }

    /// Rays longer than a group, and more rays than one group holds, are evaluated in full.
    #[test]
    fn groups_split_large_waves() {
        let mut c = Samples { ray_start: vec![0], ..Default::default() };
        for len in [GROUP + 5, 3, GROUP / 2, GROUP / 2 + 1] {
            for k in 0..len {
                c.t.push(k as f32);
                c.delta.push(1e-6);
                c.positions.push([1.0, 0.0, 0.0]);
                c.directions.push([1.0, 0.0, 0.0]);
            }
            c.ray_start.push(c.t.len() as u32);
        }
        let pass = density_pass(&Ramp { with_state: true }, &c, 0.0, 0.0, usize::MAX, Vec::new());
        assert_eq!(pass.evaluated, c.len());
        assert!(pass.sigma.iter().all(|&s| s == 10.0));
        assert!(pass.keep.iter().all(|&k| k));
        assert_eq!(pass.state.expect("within budget").values.len(), 3 * c.len());
    }
}
