//! The egui app. Following egui's `custom3d_wgpu` pattern: GPU resources are built once on
//! eframe's wgpu device; the renderer writes straight into a storage texture that egui shows,
//! scaled to fit the view with bilinear filtering.
//!
//! Rendering follows a quality ladder (`crate::quality`): while the camera or a setting changes
//! (or a pointer button is held), each frame renders at the rung predicted to fit the frame
//! budget; once nothing has changed for `SETTLE`, one rung per UI frame refines the image up to
//! the chosen settings, where it stops: an unchanged view is never rendered again. Once the file's
//! baked field is ready (`crate::bake`, made in the background after the file opens), frames
//! drawn while the view moves look samples up in it, at the most expensive rung it serves (the
//! chosen quality first) that fits the budget; the settled image is always exact, and with a
//! super-resolution network (`--superres`) the network's image of it follows (`app/superres.rs`).

mod baking;
mod panel;
mod record;
mod scripted;
mod superres;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use eframe::egui;
use eframe::egui_wgpu;
use lp3d_renderer::{Display, GpuContext, GpuTriplane, RenderSettings, Renderer, Triplane, DISPLAY_FORMAT};

use crate::bake::{self, BakeJob, Draw};
use crate::options::ViewerOptions;
use crate::orbit::Orbit;
use crate::quality::{FrameTimes, Ladder, Rung};
use crate::screenshot::{drag_path, json_number, json_string, save_screenshot, RenderImage, ViewRect};
use record::{FrameRecord, Phase, Shown};
use scripted::DragScript;
use superres::StillSuperRes;

/// How long the view must stay unchanged (with no pointer button held) before refining.
const SETTLE: Duration = Duration::from_millis(200);
/// Rendered frames kept for the screenshot's report.
const LOG_CAP: usize = 100_000;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Rgb,
    Depth,
    Weights,
    Channel,
}

/// Everything that decides the image at the chosen quality; a change means "render again".
#[derive(Debug, Clone, Copy, PartialEq)]
struct FrameKey {
    orbit: Orbit,
    /// The chosen (final) settings; rungs derive from them.
    settings: RenderSettings,
    display: Display,
    generation: u64,
    /// The still image is super-resolved (`StillSuperRes`).
    superres: bool,
}

struct Loaded {
    path: PathBuf,
    /// Shared with its bake's thread; the baked field lives on it (`GpuTriplane::baked`).
    gpu: Arc<GpuTriplane>,
    summary: String,
    ray_range: (f32, f32),
    generation: u64,
    /// The background bake of this file's field (None with `--no-bake`); dropping it stops it.
    bake: Option<BakeJob>,
}

/// A display texture (an `Rgba8Unorm` storage texture registered with egui), one per rung size.
struct Target {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    id: egui::TextureId,
    size: u32,
}

pub struct ViewerApp {
    /// Shared with the bake threads.
    renderer: Arc<Renderer>,
    /// The network that super-resolves the still image (`--superres`).
    superres: Option<StillSuperRes>,
    render_state: egui_wgpu::RenderState,
    egui_ctx: egui::Context,
    /// Bake each opened file's field in the background (not with `--no-bake`).
    bake_enabled: bool,
    /// A baked frame failed: draw exact frames only (until another file is opened).
    baked_broken: bool,
    loaded: Option<Loaded>,
    generation: u64,
    orbit: Orbit,
    home: Orbit,
    /// The chosen (final) quality.
    settings: RenderSettings,
    mode: Mode,
    channel: u32,
    frame_budget_ms: f64,
    times: FrameTimes,
    /// Render times of baked frames (apart: they are far cheaper than exact ones of a rung).
    baked_times: FrameTimes,
    /// The field `baked_times` were measured with: a new field (the fine one replacing the quick
    /// one) starts them again.
    baked_times_field: Option<lp3d_renderer::BakeSpec>,
    /// Bake the fine field after the quick one (`--no-fine-field`: false).
    bake_fine: bool,
    /// Frames rendered since the current move started (`bake::PROBE_EVERY`); 0 when the last
    /// frame was not a moving one, so a move starts when it is 0.
    move_frames: u32,
    targets: Vec<Target>,
    shown: Option<Shown>,
    /// The key whose render failed (not retried until something changes).
    failed: Option<FrameKey>,
    last_key: Option<FrameKey>,
    last_change: Instant,
    moving: bool,
    started: Instant,
    last_ui: Instant,
    interval_ms: f64,
    log: Vec<FrameRecord>,
    /// The 3D view's square in points, from the last UI frame.
    view_rect: Option<egui::Rect>,
    drag: Option<DragScript>,
    error: Option<String>,
    render_error: Option<String>,
    path_input: String,
    screenshot: Option<ScreenshotJob>,
    status: Option<String>,
    outcome: Outcome,
}

struct ScreenshotJob {
    path: PathBuf,
    /// Exit after saving (the `--screenshot` mode) or keep running (the Save button).
    exit_after: bool,
    frames_before: u32,
    requested: Option<Captured>,
    result: Arc<Mutex<Option<Arc<egui::ColorImage>>>>,
}

/// What was on screen when the window capture was requested.
struct Captured {
    view: ViewRect,
    render: RenderImage,
    quality: String,
}

/// What a `--screenshot` run reports back to `run`.
pub type Outcome = Arc<Mutex<Option<Result<PathBuf, String>>>>;

impl ViewerApp {
    pub fn new(
        cc: &eframe::CreationContext<'_>,
        options: &ViewerOptions,
        triplane: Option<(PathBuf, Triplane)>,
        superres: Option<(PathBuf, lp3d_renderer::SuperresWeights)>,
        outcome: Outcome,
    ) -> Result<ViewerApp, String> {
        let render_state = cc
            .wgpu_render_state
            .clone()
            .ok_or("eframe did not create a wgpu device (the viewer needs the wgpu renderer)")?;
        let ctx = GpuContext::from_device(
            render_state.device.clone(),
            render_state.queue.clone(),
            render_state.adapter.get_info(),
        );
        let renderer = Arc::new(Renderer::new(&ctx).map_err(|e| e.to_string())?);
        let superres = superres.map(|(path, w)| StillSuperRes::new(&ctx, &path, &w)).transpose()?;
        let orbit = Orbit::new(options.yaw, options.pitch);
        let now = Instant::now();
        let mut app = ViewerApp {
            renderer,
            superres,
            render_state,
            egui_ctx: cc.egui_ctx.clone(),
            bake_enabled: options.bakes(),
            baked_broken: false,
            loaded: None,
            generation: 0,
            orbit,
            home: orbit,
            settings: options.settings(),
            mode: Mode::Rgb,
            channel: 3,
            frame_budget_ms: options.frame_budget_ms,
            times: FrameTimes::default(),
            baked_times: FrameTimes::default(),
            baked_times_field: None,
            bake_fine: options.fine_field,
            move_frames: 0,
            targets: Vec::new(),
            shown: None,
            failed: None,
            last_key: None,
            last_change: now,
            moving: false,
            started: now,
            last_ui: now,
            interval_ms: 0.0,
            log: Vec::new(),
            view_rect: None,
            drag: None,
            error: None,
            render_error: None,
            path_input: String::new(),
            screenshot: None,
            status: None,
            outcome,
        };
        if let Some((path, tri)) = triplane {
            app.install(path, tri)?;
        }
        if let Some(path) = &options.screenshot {
            app.screenshot = Some(ScreenshotJob {
                path: path.clone(),
                exit_after: true,
                frames_before: options.frames,
                requested: None,
                result: Arc::new(Mutex::new(None)),
            });
        }
        if options.drag_frames > 0 {
            app.drag = Some(DragScript::new(options.drag_frames));
        }
        Ok(app)
    }

    fn install(&mut self, path: PathBuf, tri: Triplane) -> Result<(), String> {
        // Name the file: the upload's checks (e.g. planes that overflow float32) only know the field.
        let gpu = Arc::new(self.renderer.upload(&tri).map_err(|e| format!("{}: {e}", path.display()))?);
        self.generation += 1;
        let summary = format!(
            "{}×{} planes ({}), rays {:.2}–{:.2}{}",
            tri.height,
            tri.width,
            if tri.plane_dtype == lp3d_renderer::PlaneDtype::F16 { "float16" } else { "float32" },
            tri.bounds.ray_start,
            tri.bounds.ray_end,
            tri.source.as_deref().map(|s| format!("\n{s}")).unwrap_or_default()
        );
        self.path_input = path.display().to_string();
        let ray_range = (tri.bounds.ray_start, tri.bounds.ray_end);
        // A file may bring its occupancy grid (uploaded with it): then the job needs no triplane.
        let cpu = (!gpu.has_occupancy()).then_some(tri);
        let bake = self.bake_enabled.then(|| self.start_bake(&gpu, cpu, ray_range));
        // Replacing the old file drops its bake job, which stops it; its field goes with its
        // GpuTriplane, so no frame of this file can use it.
        self.loaded = Some(Loaded { path, gpu, summary, ray_range, generation: self.generation, bake });
        self.baked_times = FrameTimes::default();
        self.baked_broken = false;
        self.error = None;
        Ok(())
    }

    fn open(&mut self, path: &Path) {
        match Triplane::load(path) {
            Ok(tri) => {
                if let Err(e) = self.install(path.to_path_buf(), tri) {
                    self.error = Some(e);
                }
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    fn display(&self) -> Display {
        match self.mode {
            Mode::Rgb => Display::Rgb,
            Mode::Depth => {
                let (near, far) = self.loaded.as_ref().map(|l| l.ray_range).unwrap_or((2.25, 3.3));
                Display::Depth { near, far }
            }
            Mode::Weights => Display::Weights,
            Mode::Channel => Display::Channel(self.channel),
        }
    }

    fn key(&self) -> Option<FrameKey> {
        let generation = self.loaded.as_ref()?.generation;
        let (orbit, settings, display, superres) =
            (self.orbit, self.settings, self.display(), self.superres_on());
        Some(FrameKey { orbit, settings, display, generation, superres })
    }

    /// The final image of the current view is on screen and nothing is changing.
    fn settled_final(&self) -> bool {
        !self.moving && self.shown.is_some_and(|s| s.is_final() && Some(s.key) == self.key())
    }

    /// The texture for `size` rays per side (made on first use); textures of sizes not in
    /// `keep` are released.
    fn target_for(&mut self, size: u32, keep: &[u32]) -> usize {
        let device = &self.render_state.device;
        let mut egui_renderer = self.render_state.renderer.write();
        self.targets.retain(|t| {
            let kept = t.size == size || keep.contains(&t.size);
            if !kept {
                egui_renderer.free_texture(&t.id);
            }
            kept
        });
        if let Some(i) = self.targets.iter().position(|t| t.size == size) {
            return i;
        }
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some(&format!("lp3d-view display {size}²")),
            size: wgpu::Extent3d { width: size, height: size, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DISPLAY_FORMAT,
            usage: wgpu::TextureUsages::STORAGE_BINDING
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        // Bilinear: the render is scaled to fit the view, usually larger than the render. Where it
        // is shown 1:1 (the square snapped to whole pixels), each pixel centre falls on a texel
        // centre and bilinear filtering returns the texel exactly, as nearest would.
        let id = egui_renderer.register_native_texture(device, &view, wgpu::FilterMode::Linear);
        self.targets.push(Target { texture, view, id, size });
        self.targets.len() - 1
    }

    /// One step of the quality ladder: renders at most one frame.
    fn step(&mut self, ctx: &egui::Context, pointer_down: bool) {
        let Some(key) = self.key() else { return };
        let now = Instant::now();
        if self.last_key != Some(key) {
            self.last_key = Some(key);
            self.last_change = now;
        }
        let since_change = now.duration_since(self.last_change);
        self.moving = pointer_down || since_change < SETTLE;
        if !self.moving {
            self.rebake_if_needed();
        }
        let ladder = Ladder::new(&self.settings);
        let shown = self.shown.filter(|s| s.key == key);
        // The exact image is up: super-resolve it (a failure turns the network off).
        let exact_top = shown.is_some_and(|s| !s.baked && !s.superres && s.index == ladder.top());
        if key.superres && exact_top && !self.moving {
            self.render_superres(ctx, key, &ladder);
            ctx.request_repaint();
            return;
        }
        let next = match shown {
            None if self.moving => Some(self.moving_frame(&key, &ladder)),
            None => Some(Draw::Ladder(ladder.interactive(&self.times, self.frame_budget_ms))),
            // A baked frame is about as good as the exact one of its rung: refine from the next
            // exact rung.
            Some(s) if !self.moving && (s.baked || s.index < ladder.top()) => {
                Some(Draw::Ladder(ladder.next_exact(s.index)))
            }
            Some(_) => None,
        };
        match next {
            Some(frame) if self.failed != Some(key) => {
                self.render(ctx, key, &ladder, frame, pointer_down);
                // Another UI frame: the panel shows this frame's numbers, refinement goes on.
                ctx.request_repaint();
            }
            _ if self.moving && !pointer_down => ctx.request_repaint_after(SETTLE - since_change),
            _ => {}
        }
    }

    /// How to draw `key` while the view moves: from the baked field at the largest rung it serves
    /// that fits the budget (`bake::moving_frame`), else the exact ladder's interactive rung.
    fn moving_frame(&self, key: &FrameKey, ladder: &Ladder) -> Draw {
        let exact = ladder.interactive(&self.times, self.frame_budget_ms);
        // The first frame of a move is a probe too: `move_frames` is 0 until a move's first frame.
        let probe = self.move_frames % bake::PROBE_EVERY == 0;
        let serves =
            |rung: &Rung| self.field_serves(&FrameKey { settings: rung.apply(&key.settings), ..*key });
        bake::moving_frame(ladder, serves, &self.baked_times, probe, self.frame_budget_ms, exact)
    }

    fn render(&mut self, ctx: &egui::Context, key: FrameKey, ladder: &Ladder, frame: Draw, dragging: bool) {
        let (index, baked) = match frame {
            Draw::Baked(i) => (i, true),
            Draw::Ladder(i) => (i, false),
        };
        let rung = ladder.rungs[index];
        let exact = rung.apply(&key.settings);
        let settings = if baked { self.baked_frame_settings(&exact) } else { exact };
        let sizes: Vec<u32> = ladder.rungs.iter().map(|r| r.resolution).collect();
        let t = self.target_for(settings.resolution, &sizes);
        let Some(loaded) = self.loaded.as_ref() else { return };
        let start = Instant::now();
        let result = self.renderer.render_to_texture(
            &loaded.gpu,
            &key.orbit.camera(),
            &settings,
            key.display,
            &self.targets[t].view,
        );
        // Wait for the GPU so the shown time is the render's, not just its submission.
        let _ = self.render_state.device.poll(wgpu::PollType::wait_indefinitely());
        let end = Instant::now();
        let render_ms = end.duration_since(start).as_secs_f64() * 1e3;
        match result {
            Ok(()) => {
                let times = if baked { &mut self.baked_times } else { &mut self.times };
                times.record(rung, render_ms);
                let top = ladder.top();
                let ui_frame = ctx.cumulative_frame_nr();
                // What was drawn: a baked frame may take more coarse samples than its rung.
                let drawn = Rung::of(&settings);
                let texture = settings.resolution;
                let superres = false;
                let shown = Shown {
                    key,
                    rung: drawn,
                    texture,
                    index,
                    top,
                    baked,
                    superres,
                    render_ms,
                    at: end,
                    ui_frame,
                };
                let phase = if shown.is_final() {
                    Phase::Final
                } else if self.moving {
                    Phase::Moving
                } else {
                    Phase::Refining
                };
                self.shown = Some(shown);
                self.move_frames = if phase == Phase::Moving { self.move_frames + 1 } else { 0 };
                self.failed = None;
                self.render_error = None;
                self.log_frame(shown, ladder, phase, dragging);
            }
            // A baked frame that fails leaves exact frames (the next step draws one).
            Err(e) if baked => {
                self.shown = None;
                self.baked_broken = true;
                self.render_error = Some(format!("a baked frame failed, drawing exact frames only: {e}"));
            }
            Err(e) => {
                self.shown = None;
                self.failed = Some(key);
                self.render_error = Some(e.to_string());
            }
        }
    }
}

impl eframe::App for ViewerApp {
    /// The panels' colour: they are drawn unfilled over it.
    fn clear_color(&self, visuals: &egui::Visuals) -> [f32; 4] {
        visuals.panel_fill.to_normalized_gamma_f32()
    }

    fn raw_input_hook(&mut self, _ctx: &egui::Context, raw_input: &mut egui::RawInput) {
        self.drive_drag(raw_input);
    }

    fn logic(&mut self, ctx: &egui::Context, _frame: &mut eframe::Frame) {
        let dropped: Vec<PathBuf> =
            ctx.input(|i| i.raw.dropped_files.iter().map(|f| f.path().to_path_buf()).collect());
        if let Some(path) = dropped.first() {
            self.open(path);
        }
    }

    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let now = Instant::now();
        self.interval_ms = now.duration_since(self.last_ui).as_secs_f64() * 1e3;
        self.last_ui = now;
        self.panels(ui);
        self.drive_screenshot(ui.ctx());
    }
}

impl Drop for ViewerApp {
    /// Stops the open file's bake and waits for its thread (at most one dispatch), so that no
    /// GPU work outlives the window.
    fn drop(&mut self) {
        if let Some(job) = self.loaded.as_mut().and_then(|l| l.bake.take()) {
            job.stop_and_wait();
        }
    }
}
