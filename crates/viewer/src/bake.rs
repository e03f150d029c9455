//! The baked field in the viewer (`docs/baked.md`). After a file is opened, a background
//! thread bakes its occupancy grid (CPU) and then its baked fields (GPU, in dispatches of
//! `BAKE_CHUNK` points, so the UI keeps drawing between them): a quick one (`QUICK_FIELD`), then a
//! fine one (`FINE_FIELD`, a longer bake; docs/performance.md, "Bake time and size") that replaces
//! it. Once a field is ready, frames drawn while the view moves look samples up in it at the
//! chosen resolution and samples (the fine field with a third more coarse samples, which brings its
//! frames to the exact frame's error), or, when that does not fit the frame budget, the chosen
//! resolution with fewer samples (the ladder's two baked-only rungs), then lower rungs with the
//! chosen coarse samples, instead of decoding every sample at a much lower rung; the settled frame
//! is always exact (it decodes every sample), the reference the baked field only approximates.
//!
//! The field lives with its `GpuTriplane` (`GpuTriplane::baked`), so a field can never serve
//! another file's frames; opening another file drops this file's job, which stops its bake.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

use eframe::egui;
use lp3d_renderer::occupancy::{Occupancy, DEFAULT_RESOLUTION};
use lp3d_renderer::settings::MAX_SAMPLES;
use lp3d_renderer::{
    BakeSpec, Display, GpuBaked, GpuTriplane, Outputs, RenderSettings, Renderer, Skips, Triplane,
};

use crate::orbit::Orbit;
use crate::quality::{FrameTimes, Ladder, Rung};

/// A field the viewer bakes: points per cell edge, k (k_f in the bricks a surface crosses), and
/// the coarse samples its frames take for each coarse sample of the rung they stand in for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Field {
    pub subdivisions: u32,
    pub fine_subdivisions: u32,
    /// (numerator, denominator): a baked frame of a rung with C coarse samples takes
    /// ceil(C · n / d), so that its error matches the rung's exact frame.
    pub coarse_scale: (u32, u32),
}

/// The field baked first: `Skips::BAKED`'s (k 4, and 10 in the bricks a surface crosses), small
/// and quick to bake (docs/performance.md, "Bake time and size"); a lookup costs the same whatever
/// k, and the field's error falls with the square of the sub-cell (`docs/baked.md`). Its frames
/// take the rung's samples and stay short of the exact frame's error (docs/performance.md, "What
/// each drag frame looks like").
pub const QUICK_FIELD: Field = Field {
    subdivisions: Skips::BAKED.baked_subdivisions,
    fine_subdivisions: Skips::BAKED.baked_fine_subdivisions,
    coarse_scale: (1, 1),
};

/// The field baked next, replacing the quick one when ready: k 4 / 16, larger and slower to bake
/// (docs/performance.md, "Bake time and size"). With a third more coarse samples than the rung
/// (64+48 for 48+48) its frames are as close to exact 192+192 as the rung's exact frame on the
/// shipped encoder's triplanes (docs/performance.md, "What each drag frame looks like"): at the
/// samples a baked lookup costs what it does, the coarse pass buys the error
/// (bench/history/RESULTS.md, "More coarse samples than fine").
pub const FINE_FIELD: Field = Field { subdivisions: 4, fine_subdivisions: 16, coarse_scale: (4, 3) };

impl Field {
    /// The viewer's field a bake spec was made for (the quick one's rules for any other).
    pub fn of(spec: &BakeSpec) -> Field {
        let same =
            |f: &Field| (f.subdivisions, f.fine_subdivisions) == (spec.subdivisions, spec.fine_subdivisions);
        [QUICK_FIELD, FINE_FIELD].into_iter().find(same).unwrap_or(Field {
            subdivisions: spec.subdivisions,
            fine_subdivisions: spec.fine_subdivisions,
            coarse_scale: (1, 1),
        })
    }

    /// `k 4 / 16`.
    pub fn label(&self) -> String {
        match self.fine_subdivisions {
            0 => format!("k {}", self.subdivisions),
            fine => format!("k {} / {fine}", self.subdivisions),
        }
    }
}

/// The occupancy skip's epsilon the fields are baked for: `Skips::BAKED`'s (1e-4), invisible in an
/// 8-bit image.
pub const BAKE_EPSILON: f32 = Skips::BAKED.occupancy_epsilon;
/// Transmittance and empty-ray thresholds of a baked frame, which also skips empty cells in the
/// coarse pass: with the decoder gone, marching the samples is the cost. They make a baked frame
/// much quicker while moving its error against exact 192+192 far less than the field's own error
/// (bench/history/RESULTS.md, "Drag frames from the baked field").
pub const BAKED_THRESHOLD: f32 = 1e-3;

/// The settings of a frame drawn from `field` in place of the rung `chosen`: its resolution and
/// fine samples, the field's coarse samples for it, samples looked up instead of decoded.
pub fn baked_settings(chosen: &RenderSettings, field: Field) -> RenderSettings {
    let (n, d) = field.coarse_scale;
    RenderSettings {
        depth_resolution: (chosen.depth_resolution * n).div_ceil(d).min(MAX_SAMPLES),
        skips: Skips {
            transmittance_threshold: BAKED_THRESHOLD,
            empty_threshold: BAKED_THRESHOLD,
            occupancy_epsilon: BAKE_EPSILON,
            occupancy_coarse: true,
            baked_subdivisions: field.subdivisions,
            baked_fine_subdivisions: field.fine_subdivisions,
        },
        ..*chosen
    }
}

/// What `field` must cover to draw baked frames for the rung `settings` (`BakeSpec::covers`), for
/// a scene whose rays run from `ray_start` to `ray_end`.
pub fn spec_for(settings: &RenderSettings, field: Field, (ray_start, ray_end): (f32, f32)) -> BakeSpec {
    BakeSpec {
        subdivisions: field.subdivisions,
        fine_subdivisions: field.fine_subdivisions,
        epsilon: BAKE_EPSILON,
        max_delta: baked_settings(settings, field).max_interval(ray_start, ray_end),
    }
}

/// The specs the viewer bakes for `chosen`, in order: the quick field, then (with `fine`) the fine
/// one. Each serves every rung of the ladder with the chosen coarse samples or fewer, down to the
/// baked-only rungs' (half of them), i.e. is `spec_for` the rung with the fewest. Half the samples
/// mean intervals twice as long, so the occupancy skip keeps more cells, and the field more bricks
/// (bench/history/RESULTS.md, "A baked-only rung").
pub fn bake_specs(chosen: &RenderSettings, rays: (f32, f32), fine: bool) -> Vec<BakeSpec> {
    let ladder = Ladder::new(chosen);
    let baked_only = ladder.baked_only.clone().map(|i| ladder.rungs[i]);
    let fewest = baked_only.chain([Rung::of(chosen)]).min_by_key(|r| r.depth_resolution);
    let rung = fewest.expect("the chosen rung at least").apply(chosen);
    let fields: &[Field] = if fine { &[QUICK_FIELD, FINE_FIELD] } else { &[QUICK_FIELD] };
    fields.iter().map(|&f| spec_for(&rung, f, rays)).collect()
}

/// Whether a baked field can draw `display`: it holds density and RGB, so feature channels 3..31
/// need exact mode.
pub fn display_supported(display: Display) -> bool {
    match display {
        Display::Rgb | Display::Depth { .. } | Display::Weights => true,
        Display::Channel(c) => c < 3,
    }
}

/// While a move lasts, every this many frames is a probe (`moving_frame`): one frame of up to
/// twice the budget about once a second at ten frames a second, so a drag climbs back within a
/// second of a slow spell's end.
pub const PROBE_EVERY: u32 = 10;

/// How a frame is drawn: a rung of the quality ladder, exact or from the baked field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Draw {
    /// Looked up in the baked field, at this rung's resolution and samples.
    Baked(usize),
    /// Exact mode at this rung (the top rung: the chosen settings).
    Ladder(usize),
}

/// The frame to draw while the view moves. From the baked field, the most expensive rung it serves
/// (`serves`: ready, covering the rung's samples, and a display it can draw: in practice the rungs
/// with the chosen coarse samples) whose predicted time (`baked_times`) fits `budget_ms`; a rung
/// not measured yet (nor any baked frame) is tried. On a `probe` frame (the first of a move and
/// every [`PROBE_EVERY`]th after it) the most expensive rung served is tried again when hoped to
/// take at most twice the budget (`FrameTimes::hopeful`), so that a slow spell that has passed
/// does not keep the rest of a drag at a lower rung. When no baked rung fits: the exact ladder's
/// `exact_rung`, as without a field.
pub fn moving_frame(
    ladder: &Ladder,
    serves: impl Fn(&Rung) -> bool,
    baked_times: &FrameTimes,
    probe: bool,
    budget_ms: f64,
    exact_rung: usize,
) -> Draw {
    let served: Vec<usize> = (0..ladder.rungs.len()).rev().filter(|&i| serves(&ladder.rungs[i])).collect();
    for (n, &i) in served.iter().enumerate() {
        let rung = &ladder.rungs[i];
        let fits = if probe && n == 0 {
            baked_times.hopeful(rung).is_none_or(|ms| ms <= 2.0 * budget_ms)
        } else {
            baked_times.predict(rung).is_none_or(|ms| ms <= budget_ms)
        };
        if fits {
            return Draw::Baked(i);
        }
    }
    Draw::Ladder(exact_rung)
}

/// Where a bake is.
#[derive(Debug, Clone, PartialEq)]
pub enum BakeState {
    /// Bounding the decoder's density over the occupancy grid's cells (CPU).
    Occupancy,
    /// Baking `field` on the GPU: points done of all (the field before it, if any, draws
    /// meanwhile).
    Baking {
        field: Field,
        done: usize,
        total: usize,
    },
    /// The last field is on the triplane (`GpuTriplane::baked`).
    Ready,
    Failed(String),
}

impl BakeState {
    /// The name the screenshot's JSON report gives it.
    pub fn name(&self) -> &'static str {
        match self {
            BakeState::Occupancy => "occupancy",
            BakeState::Baking { .. } => "baking",
            BakeState::Ready => "ready",
            BakeState::Failed(_) => "failed",
        }
    }

    pub fn running(&self) -> bool {
        matches!(self, BakeState::Occupancy | BakeState::Baking { .. })
    }

    /// `baking k 4 / 16… 43%`, for the panel (None when ready: the field's own label says it).
    pub fn progress_label(&self) -> Option<String> {
        match self {
            BakeState::Occupancy => Some("baking… occupancy grid".into()),
            BakeState::Baking { field, done, total } => Some(format!(
                "baking {}… {:.0}%",
                field.label(),
                100.0 * *done as f64 / (*total).max(1) as f64
            )),
            BakeState::Ready => None,
            BakeState::Failed(e) => Some(format!("bake failed: {e}")),
        }
    }
}

/// `baked field (k 4 / 10, N MiB, baked in T s)`: the field, its device memory and its bake time.
pub fn field_label(field: &GpuBaked) -> String {
    format!(
        "baked field ({}, {:.0} MiB, baked in {:.1} s)",
        Field::of(&field.spec).label(),
        field.device_bytes() as f64 / (1 << 20) as f64,
        field.bake_seconds
    )
}

/// A background bake of one file's fields, one after the other (`bake_specs`).
pub struct BakeJob {
    /// What it bakes, in order.
    pub specs: Vec<BakeSpec>,
    state: Arc<Mutex<BakeState>>,
    cancel: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
    /// Seconds from the start of the job (the occupancy grid included) to the field being ready.
    seconds: Arc<Mutex<Option<f64>>>,
}

impl BakeJob {
    /// Starts baking `gpu`'s fields for `specs`, in order, on a thread of its own; each replaces
    /// the one before when ready. `cpu` is the triplane `gpu` was uploaded from when its occupancy
    /// grid is still to be made; None when it has one. Each step requests a repaint of `ctx`. Once
    /// a field is ready, one baked frame of `warm` (settings the specs cover) builds its render
    /// pipeline and touches the field off the UI thread, so that its first frame on screen takes
    /// its usual time.
    pub fn start(
        renderer: Arc<Renderer>,
        gpu: Arc<GpuTriplane>,
        cpu: Option<Triplane>,
        specs: Vec<BakeSpec>,
        warm: RenderSettings,
        ctx: egui::Context,
    ) -> BakeJob {
        let first = specs.first().map_or(QUICK_FIELD, Field::of);
        let state = Arc::new(Mutex::new(if cpu.is_some() {
            BakeState::Occupancy
        } else {
            BakeState::Baking { field: first, done: 0, total: 1 }
        }));
        let cancel = Arc::new(AtomicBool::new(false));
        let seconds = Arc::new(Mutex::new(None));
        let (t_state, t_cancel, t_seconds) = (state.clone(), cancel.clone(), seconds.clone());
        let t_specs = specs.clone();
        let handle = std::thread::Builder::new().name("lp3d-view bake".into()).spawn(move || {
            let start = Instant::now();
            let set = |s: BakeState| {
                if let Ok(mut slot) = t_state.lock() {
                    *slot = s;
                }
                ctx.request_repaint();
            };
            match bake(&renderer, &gpu, cpu, &t_specs, &warm, &t_cancel, &set) {
                Ok(()) => {
                    if let Ok(mut s) = t_seconds.lock() {
                        *s = Some(start.elapsed().as_secs_f64());
                    }
                    set(BakeState::Ready);
                }
                // Stopped: its file is no longer shown, nobody reads the state.
                Err(_) if t_cancel.load(Ordering::Relaxed) => {}
                Err(e) => set(BakeState::Failed(e)),
            }
        });
        let (handle, state) = match handle {
            Ok(h) => (Some(h), state),
            Err(e) => {
                let failed = BakeState::Failed(format!("could not start the bake thread: {e}"));
                (None, Arc::new(Mutex::new(failed)))
            }
        };
        BakeJob { specs, state, cancel, handle, seconds }
    }

    pub fn state(&self) -> BakeState {
        self.state.lock().map(|s| s.clone()).unwrap_or_else(|_| BakeState::Failed("bake state lock".into()))
    }

    /// Seconds from the job's start to the last field being ready (occupancy grid included).
    pub fn seconds(&self) -> Option<f64> {
        self.seconds.lock().ok().and_then(|s| *s)
    }

    /// Stops the bake and waits for its thread (at most one dispatch, or the occupancy grid).
    pub fn stop_and_wait(mut self) {
        self.cancel.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

impl Drop for BakeJob {
    /// Stops the bake without waiting: its thread ends after the dispatch under way.
    fn drop(&mut self) {
        self.cancel.store(true, Ordering::Relaxed);
    }
}

/// The job's work: the occupancy grid (when `cpu` is given), then each field and a warm-up frame
/// from it. A field that fails after an earlier one is ready leaves the earlier one drawing.
fn bake(
    renderer: &Renderer,
    gpu: &GpuTriplane,
    cpu: Option<Triplane>,
    specs: &[BakeSpec],
    warm: &RenderSettings,
    cancel: &AtomicBool,
    set: &dyn Fn(BakeState),
) -> Result<(), String> {
    if let Some(tri) = cpu {
        let grid = Occupancy::bake(&tri, DEFAULT_RESOLUTION).map_err(|e| e.to_string())?;
        drop(tri);
        if cancel.load(Ordering::Relaxed) {
            return Err("stopped".into());
        }
        renderer.set_occupancy(gpu, grid).map_err(|e| format!("{e} (exact frames only)"))?;
    }
    let rgb = Outputs { features: false, rgb: true, depth: false, weights_sum: false };
    for (i, &spec) in specs.iter().enumerate() {
        let field = Field::of(&spec);
        // What the panel says if this one fails: the field before it still draws.
        let fallback = match i {
            0 => " (exact frames only)".to_string(),
            _ => format!(" (frames from the {} field)", Field::of(&specs[i - 1]).label()),
        };
        let failed = |e: String| format!("{}: {e}{fallback}", field.label());
        set(BakeState::Baking { field, done: 0, total: 1 });
        let mut progress = |done: usize, total: usize| {
            set(BakeState::Baking { field, done, total });
            !cancel.load(Ordering::Relaxed)
        };
        renderer.bake_with_progress(gpu, spec, &mut progress).map_err(|e| failed(e.to_string()))?;
        renderer
            .render(gpu, &[Orbit::new(0.0, 0.0).camera()], &baked_settings(warm, field), rgb)
            .map_err(|e| failed(format!("its first frame failed: {e}")))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_moving_frame_is_the_largest_baked_rung_that_fits_else_the_exact_ladder() {
        use Draw::{Baked, Ladder as Exact};
        let chosen = RenderSettings { resolution: 128, depth_resolution: 48, ..Default::default() };
        let ladder = Ladder::new(&chosen);
        // 32² · 12+12, 64² · 12+12, 64² · 48+48, 128² · 24+24 and 36+24 (baked only), 128² ·
        // 48+48: the viewer's fields, baked for 24 coarse samples, serve the last four.
        let specs = bake_specs(&chosen, (2.25, 3.3), true);
        for (spec, field) in specs.iter().zip([QUICK_FIELD, FINE_FIELD]) {
            let serves = |r: &Rung| spec.covers(&spec_for(&r.apply(&chosen), field, (2.25, 3.3)));
            assert_eq!(
                (0..6).map(|i| serves(&ladder.rungs[i])).collect::<Vec<_>>(),
                [false, false, true, true, true, true]
            );
        }
        let (field, quick) = (specs[0], QUICK_FIELD);
        let serves = |r: &Rung| field.covers(&spec_for(&r.apply(&chosen), quick, (2.25, 3.3)));
        let none = |_: &Rung| false;
        let mut t = FrameTimes::default();
        // No field (or one that does not cover the settings or the display): the exact ladder.
        assert_eq!(moving_frame(&ladder, none, &t, true, 100.0, 1), Exact(1));
        // A field: the top rung, tried before any measurement, kept while it fits.
        let top = ladder.top();
        assert_eq!(moving_frame(&ladder, serves, &t, false, 100.0, 1), Baked(top));
        t.record(ladder.rungs[top], 60.0);
        assert_eq!(moving_frame(&ladder, serves, &t, false, 100.0, 1), Baked(top));
        // One slow frame does not move it; two of three over the budget (150 ms) do: the full
        // resolution with 36+24 samples, predicted at 0.625 of the cost, 94 ms.
        t.record(ladder.rungs[top], 150.0);
        assert_eq!(moving_frame(&ladder, serves, &t, false, 100.0, 1), Baked(top));
        t.record(ladder.rungs[top], 150.0);
        assert_eq!(moving_frame(&ladder, serves, &t, false, 100.0, 1), Baked(4));
        // Over it too (measured at 120 ms): 128² · 24+24, predicted at 96 ms.
        t.record(ladder.rungs[4], 120.0);
        assert_eq!(moving_frame(&ladder, serves, &t, false, 100.0, 1), Baked(3));
        // Over that as well: the next rung the field serves, 64² · 48+48, predicted at 70 ms (half
        // the cost of 128² · 24+24, measured at 140 ms).
        t.record(ladder.rungs[3], 140.0);
        assert_eq!(moving_frame(&ladder, serves, &t, false, 100.0, 1), Baked(2));
        // A probe (the first frame of a move, then every PROBE_EVERY) tries the top again when
        // within twice the budget.
        assert_eq!(moving_frame(&ladder, serves, &t, true, 100.0, 1), Baked(top));
        assert_eq!(moving_frame(&ladder, serves, &t, true, 70.0, 1), Baked(2));
        // A drag whose first frame was slow (400 ms) goes down to 64² · 48+48; once frames there
        // say the machine is fast again (30 ms: the top at about 120), a probe tries the top.
        let mut slow_start = FrameTimes::default();
        slow_start.record(ladder.rungs[top], 400.0);
        assert_eq!(moving_frame(&ladder, serves, &slow_start, true, 100.0, 1), Baked(2));
        slow_start.record(ladder.rungs[2], 30.0);
        assert_eq!(moving_frame(&ladder, serves, &slow_start, false, 100.0, 1), Baked(2));
        assert_eq!(moving_frame(&ladder, serves, &slow_start, true, 100.0, 1), Baked(top));
        // No baked rung fits: the exact ladder's rung.
        assert_eq!(moving_frame(&ladder, serves, &t, false, 40.0, 0), Exact(0));
        assert_eq!(moving_frame(&ladder, serves, &t, true, 40.0, 0), Exact(0));
    }

    #[test]
    fn baked_frames_use_the_chosen_quality_and_a_field_that_covers_them() {
        let chosen = RenderSettings { resolution: 128, depth_resolution: 48, ..Default::default() };
        let s = baked_settings(&chosen, QUICK_FIELD);
        assert_eq!((s.resolution, s.depth_resolution, s.depth_resolution_importance), (128, 48, 48));
        assert_eq!(
            (s.skips.baked_subdivisions, s.skips.baked_fine_subdivisions, s.skips.occupancy_epsilon),
            (4, 10, BAKE_EPSILON)
        );
        s.validate().unwrap();
        // The fine field's frames take a third more coarse samples (FINE_FIELD's coarse_scale).
        let f = baked_settings(&chosen, FINE_FIELD);
        assert_eq!((f.resolution, f.depth_resolution, f.depth_resolution_importance), (128, 64, 48));
        assert_eq!((f.skips.baked_subdivisions, f.skips.baked_fine_subdivisions), (4, 16));
        f.validate().unwrap();
        let most = RenderSettings { depth_resolution: MAX_SAMPLES, ..chosen };
        assert_eq!(baked_settings(&most, FINE_FIELD).depth_resolution, MAX_SAMPLES);
        assert_eq!(chosen.skips, Skips::EXACT, "the chosen (final) settings stay exact");
        let rays = (2.25, 3.3);
        let specs = bake_specs(&chosen, rays, true);
        assert_eq!(specs.len(), 2);
        assert_eq!(bake_specs(&chosen, rays, false), specs[..1]);
        for (spec, field) in specs.iter().zip([QUICK_FIELD, FINE_FIELD]) {
            assert_eq!(Field::of(spec), field);
            assert!(spec.covers(&spec_for(&chosen, field, rays)));
            // Each field also serves half the chosen coarse samples (the cheapest baked-only rung).
            let half = RenderSettings { depth_resolution: 24, depth_resolution_importance: 24, ..chosen };
            assert_eq!(*spec, spec_for(&half, field, rays));
            // More coarse samples: shorter intervals, covered; fewer than half: a new bake.
            let more = RenderSettings { depth_resolution: 64, ..chosen };
            let fewer = RenderSettings { depth_resolution: 12, ..chosen };
            assert!(spec.covers(&spec_for(&more, field, rays)));
            assert!(!spec.covers(&spec_for(&fewer, field, rays)));
            assert!(spec_for(&fewer, field, rays).covers(spec));
        }
        // A field serves only its own frames.
        assert!(!specs[0].covers(&spec_for(&chosen, FINE_FIELD, rays)));
        assert!(!specs[1].covers(&spec_for(&chosen, QUICK_FIELD, rays)));
    }

    #[test]
    fn feature_channels_past_rgb_need_exact_mode() {
        let shown = [
            Display::Rgb,
            Display::Weights,
            Display::Depth { near: 2.0, far: 3.0 },
            Display::Channel(0),
            Display::Channel(2),
        ];
        assert!(shown.into_iter().all(display_supported));
        assert!(!display_supported(Display::Channel(3)));
        assert!(!display_supported(Display::Channel(31)));
    }

    /// A small triplane of pseudo-random planes and decoder, with an occupancy grid that says
    /// every cell is occupied: every cell gets a brick, so its bake takes many dispatches.
    fn noise_triplane() -> Triplane {
        let mut state = 12345u32;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            (state as f32 / u32::MAX as f32) * 2.0 - 1.0
        };
        let (h, w) = (16, 16);
        let planes = (0..3 * 32 * h * w).map(|_| next()).collect();
        let decoder = lp3d_renderer::Decoder {
            w0: (0..64 * 32).map(|_| next() * 0.3).collect(),
            b0: (0..64).map(|_| next() * 0.1).collect(),
            w1: (0..33 * 64).map(|_| next() * 0.2).collect(),
            b1: (0..33).map(|_| next() * 0.1).collect(),
        };
        let g = 32;
        Triplane {
            planes,
            height: h,
            width: w,
            plane_dtype: lp3d_renderer::PlaneDtype::F32,
            decoder,
            bounds: lp3d_renderer::SceneBounds::default(),
            camera: None,
            occupancy: Some(Occupancy { resolution: g, bound: vec![100.0; g * g * g] }),
            source: None,
        }
    }

    #[test]
    fn a_stopped_bake_leaves_no_field_on_its_triplane() {
        let ctx = lp3d_renderer::GpuContext::headless().expect("a GPU adapter (lavapipe in CI)");
        // The quick kernel only: no background compile of the fast one.
        let renderer = Arc::new(Renderer::with_kernel(&ctx, lp3d_renderer::KernelChoice::Quick).unwrap());
        let tri = noise_triplane();
        let rays = (tri.bounds.ray_start, tri.bounds.ray_end);
        let gpu = Arc::new(renderer.upload(&tri).unwrap());
        assert!(gpu.has_occupancy(), "uploaded with its grid: the job needs no triplane");
        let settings = RenderSettings { resolution: 8, depth_resolution: 48, ..Default::default() };
        let spec = spec_for(&settings, QUICK_FIELD, rays);
        let job = BakeJob::start(renderer, gpu.clone(), None, vec![spec], settings, egui::Context::default());
        // Stop it once its first dispatches are done (as opening another file does).
        let start = Instant::now();
        let (done, total) = loop {
            match job.state() {
                BakeState::Baking { done, total, .. } if done > 0 => break (done, total),
                BakeState::Failed(e) => panic!("the bake failed: {e}"),
                s => assert!(start.elapsed().as_secs() < 120, "no progress: {s:?}"),
            }
            std::thread::sleep(std::time::Duration::from_millis(5));
        };
        assert!(total >= 4 * lp3d_renderer::renderer::BAKE_CHUNK && done < total / 2, "{done} of {total}");
        let state = job.state.clone();
        job.stop_and_wait();
        assert!(gpu.baked().is_none(), "a stopped bake must not leave a field");
        assert!(state.lock().unwrap().running(), "not ready, not failed: stopped");
    }

    #[test]
    fn progress_and_field_labels() {
        let baking = |done, total| BakeState::Baking { field: FINE_FIELD, done, total };
        assert_eq!(baking(43, 100).progress_label().unwrap(), "baking k 4 / 16… 43%");
        assert_eq!(BakeState::Ready.progress_label(), None);
        assert!(BakeState::Failed("out of memory".into())
            .progress_label()
            .unwrap()
            .contains("out of memory"));
        assert!(BakeState::Occupancy.running() && !BakeState::Ready.running());
        assert_eq!(baking(0, 0).name(), "baking");
    }
}
