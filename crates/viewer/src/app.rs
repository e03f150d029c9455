//! The egui app. Following egui's `custom3d_wgpu` pattern: GPU resources are built once on
//! eframe's wgpu device; the renderer writes straight into a storage texture that egui shows
//! (no readback), and a frame is re-rendered only when the camera or a setting changes.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use eframe::egui;
use eframe::egui_wgpu;
use lp3d_renderer::{Display, GpuContext, GpuTriplane, RenderSettings, Renderer, Triplane, DISPLAY_FORMAT};

use crate::options::ViewerOptions;
use crate::orbit::Orbit;
use crate::screenshot::{save_screenshot, ViewRect};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Rgb,
    Depth,
    Weights,
    Channel,
}

/// Everything that decides the rendered image; a change means "render again".
#[derive(Debug, Clone, Copy, PartialEq)]
struct FrameKey {
    orbit: Orbit,
    settings: RenderSettings,
    display: Display,
    generation: u64,
}

struct Loaded {
    path: PathBuf,
    gpu: GpuTriplane,
    summary: String,
    ray_range: (f32, f32),
    generation: u64,
}

/// The display texture (an `Rgba8Unorm` storage texture registered with egui).
struct Target {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    id: egui::TextureId,
    size: u32,
}

pub struct ViewerApp {
    renderer: Renderer,
    render_state: egui_wgpu::RenderState,
    loaded: Option<Loaded>,
    generation: u64,
    orbit: Orbit,
    home: Orbit,
    settings: RenderSettings,
    mode: Mode,
    channel: u32,
    target: Option<Target>,
    last: Option<FrameKey>,
    render_ms: f64,
    fps: f64,
    last_frame: Instant,
    frames_rendered: u32,
    error: Option<String>,
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
    requested: bool,
    result: Arc<Mutex<Option<Arc<egui::ColorImage>>>>,
    view: Option<ViewRect>,
}

/// What a `--screenshot` run reports back to `run`.
pub type Outcome = Arc<Mutex<Option<Result<PathBuf, String>>>>;

impl ViewerApp {
    pub fn new(
        cc: &eframe::CreationContext<'_>,
        options: &ViewerOptions,
        triplane: Option<(PathBuf, Triplane)>,
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
        let renderer = Renderer::new(&ctx).map_err(|e| e.to_string())?;
        let orbit = Orbit::new(options.yaw, options.pitch);
        let settings = RenderSettings { resolution: options.resolution, ..Default::default() };
        let mut app = ViewerApp {
            renderer,
            render_state,
            loaded: None,
            generation: 0,
            orbit,
            home: orbit,
            settings,
            mode: Mode::Rgb,
            channel: 3,
            target: None,
            last: None,
            render_ms: 0.0,
            fps: 0.0,
            last_frame: Instant::now(),
            frames_rendered: 0,
            error: None,
            path_input: String::new(),
            screenshot: None,
            status: None,
            outcome,
        };
        if let Some((path, tri)) = triplane {
            app.install(path, &tri)?;
        }
        if let Some(path) = &options.screenshot {
            app.screenshot = Some(ScreenshotJob {
                path: path.clone(),
                exit_after: true,
                frames_before: options.frames,
                requested: false,
                result: Arc::new(Mutex::new(None)),
                view: None,
            });
        }
        Ok(app)
    }

    fn install(&mut self, path: PathBuf, tri: &Triplane) -> Result<(), String> {
        // Name the file: the upload's checks (e.g. planes that overflow float32) only know the field.
        let gpu = self.renderer.upload(tri).map_err(|e| format!("{}: {e}", path.display()))?;
        self.generation += 1;
        let summary = format!(
            "{}×{} planes ({}), rays {:.2}–{:.2}{}",
            tri.height,
            tri.width,
            if tri.plane_dtype == lp3d_renderer::PlaneDtype::F16 { "float16" } else { "float32" },
            tri.ray_start,
            tri.ray_end,
            tri.source.as_deref().map(|s| format!("\n{s}")).unwrap_or_default()
        );
        self.path_input = path.display().to_string();
        self.loaded = Some(Loaded {
            path,
            gpu,
            summary,
            ray_range: (tri.ray_start, tri.ray_end),
            generation: self.generation,
        });
        self.error = None;
        Ok(())
    }

    fn open(&mut self, path: &Path) {
        match Triplane::load(path) {
            Ok(tri) => {
                if let Err(e) = self.install(path.to_path_buf(), &tri) {
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

    fn ensure_target(&mut self) {
        let size = self.settings.resolution;
        if self.target.as_ref().is_some_and(|t| t.size == size) {
            return;
        }
        let device = &self.render_state.device;
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("lp3d-view display"),
            size: wgpu::Extent3d { width: size, height: size, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DISPLAY_FORMAT,
            usage: wgpu::TextureUsages::STORAGE_BINDING | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let mut egui_renderer = self.render_state.renderer.write();
        let id = match self.target.take() {
            Some(old) => {
                egui_renderer.update_egui_texture_from_wgpu_texture(
                    device,
                    &view,
                    wgpu::FilterMode::Nearest,
                    old.id,
                );
                old.texture.destroy();
                old.id
            }
            None => egui_renderer.register_native_texture(device, &view, wgpu::FilterMode::Nearest),
        };
        self.target = Some(Target { texture, view, id, size });
    }

    /// Re-renders when the frame key changed.
    fn render_if_needed(&mut self) {
        let Some(generation) = self.loaded.as_ref().map(|l| l.generation) else { return };
        let key =
            FrameKey { orbit: self.orbit, settings: self.settings, display: self.display(), generation };
        if self.last == Some(key) && self.target.as_ref().is_some_and(|t| t.size == self.settings.resolution)
        {
            return;
        }
        self.ensure_target();
        let (Some(target), Some(loaded)) = (self.target.as_ref(), self.loaded.as_ref()) else { return };
        let start = Instant::now();
        let result = self.renderer.render_to_texture(
            &loaded.gpu,
            &self.orbit.camera(),
            &self.settings,
            key.display,
            &target.view,
        );
        // Wait for the GPU so the shown time is the render's, not just its submission.
        let _ = self.render_state.device.poll(wgpu::PollType::wait_indefinitely());
        self.render_ms = start.elapsed().as_secs_f64() * 1e3;
        match result {
            Ok(()) => {
                self.last = Some(key);
                self.frames_rendered += 1;
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    fn controls(&mut self, ui: &mut egui::Ui) {
        ui.heading("lp3d-view");
        ui.horizontal(|ui| {
            ui.add(
                egui::TextEdit::singleline(&mut self.path_input)
                    .hint_text("triplane.npz")
                    .desired_width(150.0),
            );
            if ui.button("Open").clicked() {
                let path = PathBuf::from(self.path_input.trim());
                self.open(&path);
            }
        });
        match &self.loaded {
            Some(l) => {
                ui.label(egui::RichText::new(l.path.display().to_string()).strong());
                ui.label(&l.summary);
            }
            None => {
                ui.label("Open or drop a triplane .npz file.");
            }
        }
        ui.separator();
        ui.label("Rendering");
        ui.add(egui::Slider::new(&mut self.settings.resolution, 16..=512).text("resolution"));
        ui.add(egui::Slider::new(&mut self.settings.depth_resolution, 4..=192).text("coarse samples"));
        ui.add(
            egui::Slider::new(&mut self.settings.depth_resolution_importance, 0..=192).text("fine samples"),
        );
        ui.separator();
        ui.label("Show");
        ui.horizontal_wrapped(|ui| {
            ui.selectable_value(&mut self.mode, Mode::Rgb, "RGB");
            ui.selectable_value(&mut self.mode, Mode::Depth, "depth");
            ui.selectable_value(&mut self.mode, Mode::Weights, "weights");
            ui.selectable_value(&mut self.mode, Mode::Channel, "channel");
        });
        if self.mode == Mode::Channel {
            ui.add(egui::Slider::new(&mut self.channel, 0..=31).text("feature channel"));
        }
        ui.separator();
        ui.label(format!(
            "yaw {:+.1}°  pitch {:+.1}°  zoom {:.2}×",
            self.orbit.yaw, self.orbit.pitch, self.orbit.zoom
        ));
        ui.horizontal(|ui| {
            if ui.button("Reset view").clicked() {
                self.orbit = self.home;
            }
            if ui.button("Save screenshot").clicked() {
                let path = self
                    .loaded
                    .as_ref()
                    .map(|l| l.path.with_extension("view.png"))
                    .unwrap_or_else(|| PathBuf::from("lp3d-view.png"));
                self.screenshot = Some(ScreenshotJob {
                    path,
                    exit_after: false,
                    frames_before: 0,
                    requested: false,
                    result: Arc::new(Mutex::new(None)),
                    view: None,
                });
            }
        });
        ui.separator();
        ui.label(format!("render {:.1} ms  ·  {:.0} FPS", self.render_ms, self.fps));
        ui.label(egui::RichText::new(self.renderer_name()).small());
        if let Some(s) = &self.status {
            ui.label(s);
        }
        if let Some(e) = &self.error {
            ui.colored_label(egui::Color32::from_rgb(255, 110, 110), e);
        }
        ui.add_space(8.0);
        ui.label(
            egui::RichText::new("drag: orbit · right/shift-drag: pan · scroll: zoom · double-click: reset")
                .small(),
        );
    }

    fn renderer_name(&self) -> String {
        let info = self.render_state.adapter.get_info();
        format!("{} ({:?})", info.name, info.backend)
    }

    fn view(&mut self, ui: &mut egui::Ui) {
        let Some(target) = &self.target else {
            ui.centered_and_justified(|ui| ui.label("no triplane loaded"));
            return;
        };
        // Integer magnification in physical pixels, so one ray is an exact block of pixels.
        let ppp = ui.ctx().pixels_per_point();
        let avail = ui.available_size() * ppp;
        let scale = ((avail.x.min(avail.y) / target.size as f32).floor() as u32).max(1);
        let size = egui::vec2((target.size * scale) as f32, (target.size * scale) as f32) / ppp;
        let image = egui::Image::new((target.id, size)).sense(egui::Sense::click_and_drag());
        let response = ui.add(image);
        let shift = ui.input(|i| i.modifiers.shift);
        let delta = response.drag_delta() / size.x;
        if response.dragged_by(egui::PointerButton::Secondary) || (shift && response.dragged()) {
            self.orbit.pan_by(-delta.x as f64, -delta.y as f64);
        } else if response.dragged_by(egui::PointerButton::Primary) {
            self.orbit.rotate(delta.x as f64, delta.y as f64);
        }
        if response.double_clicked() {
            self.orbit = self.home;
        }
        if response.hovered() {
            let scroll = ui.input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                self.orbit.zoom_by(scroll as f64);
            }
        }
        let r = response.rect;
        if let Some(job) = &mut self.screenshot {
            job.view = Some(ViewRect {
                x: (r.min.x * ppp).round() as u32,
                y: (r.min.y * ppp).round() as u32,
                size: target.size * scale,
                scale,
                resolution: target.size,
                yaw: self.orbit.yaw,
                pitch: self.orbit.pitch,
            });
        }
    }

    fn drive_screenshot(&mut self, ctx: &egui::Context) {
        let Some(job) = &mut self.screenshot else { return };
        if !job.requested {
            // `frames_before` UI frames, at least one of them with a finished render.
            let frames = ctx.cumulative_frame_nr();
            if self.frames_rendered >= 1 && frames >= job.frames_before as u64 && job.view.is_some() {
                let slot = job.result.clone();
                ctx.send_viewport_cmd(egui::ViewportCommand::Screenshot(egui::ScreenshotCallback::new(
                    move |image| {
                        if let Ok(mut s) = slot.lock() {
                            *s = Some(image);
                        }
                    },
                )));
                job.requested = true;
            }
            ctx.request_repaint();
            return;
        }
        let image = job.result.lock().ok().and_then(|mut s| s.take());
        let Some(image) = image else {
            ctx.request_repaint();
            return;
        };
        let result = save_screenshot(&job.path, &image, job.view.as_ref().expect("view rect"));
        let exit = job.exit_after;
        match &result {
            Ok(p) => self.status = Some(format!("saved {}", p.display())),
            Err(e) => self.error = Some(e.clone()),
        }
        self.screenshot = None;
        if exit {
            if let Ok(mut slot) = self.outcome.lock() {
                *slot = Some(result);
            }
            ctx.send_viewport_cmd(egui::ViewportCommand::Close);
        }
    }
}

impl eframe::App for ViewerApp {
    fn logic(&mut self, ctx: &egui::Context, _frame: &mut eframe::Frame) {
        let dropped: Vec<PathBuf> =
            ctx.input(|i| i.raw.dropped_files.iter().map(|f| f.path().to_path_buf()).collect());
        if let Some(path) = dropped.first() {
            self.open(path);
        }
        let now = Instant::now();
        let dt = now.duration_since(self.last_frame).as_secs_f64();
        self.last_frame = now;
        if dt > 0.0 {
            self.fps = 0.9 * self.fps + 0.1 / dt;
        }
        self.render_if_needed();
        self.drive_screenshot(ctx);
    }

    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        egui::Panel::left("controls").resizable(false).exact_size(260.0).show(ui, |ui| self.controls(ui));
        egui::CentralPanel::default().show(ui, |ui| self.view(ui));
    }
}
