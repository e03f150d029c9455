//! The still image super-resolved (`--superres`): once the exact image of an RGB view is up, its
//! feature image at the network's input side is rendered and super-resolved in one command stream
//! (`Renderer::render_with_superres`), and the network's image replaces it on screen. Moving
//! frames stay raw: on a CPU adapter the network costs more than a drag frame's budget
//! (`docs/performance.md`, "The viewer").

use lp3d_renderer::{Outputs, SuperRes, SuperresKernels, SuperresWeights};

use super::*;

/// A model package's network on the viewer's device, and whether the user has it on.
pub(super) struct StillSuperRes {
    net: SuperRes,
    /// The panel's checkbox (on at start).
    pub enabled: bool,
    /// The weights file, for the panel.
    pub file: String,
}

impl StillSuperRes {
    pub(super) fn new(
        ctx: &GpuContext,
        path: &Path,
        weights: &SuperresWeights,
    ) -> Result<StillSuperRes, String> {
        let kernels = SuperresKernels::new(&ctx.device).map_err(|e| e.to_string())?;
        let net =
            SuperRes::new(ctx, Arc::new(kernels), weights).map_err(|e| format!("{}: {e}", path.display()))?;
        let file = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        Ok(StillSuperRes { net, enabled: true, file })
    }

    /// `64² to 256²` (egui's default font has no arrow).
    pub(super) fn sides(&self) -> String {
        format!("{}² to {}²", self.net.input_resolution(), self.net.output_resolution())
    }
}

impl ViewerApp {
    /// Whether the still image of the current view gets super-resolved: a network is loaded and
    /// on, and the view shows RGB (the network makes colour only).
    pub(super) fn superres_on(&self) -> bool {
        self.superres.as_ref().is_some_and(|s| s.enabled) && self.mode == Mode::Rgb
    }

    /// Renders the feature image of `key` at the network's input side with the chosen samples,
    /// super-resolves it and shows the result (one frame, logged as the final one).
    pub(super) fn render_superres(&mut self, ctx: &egui::Context, key: FrameKey, ladder: &Ladder) {
        let (Some(sr), Some(loaded)) = (self.superres.as_ref(), self.loaded.as_ref()) else { return };
        let settings = RenderSettings { resolution: sr.net.input_resolution() as u32, ..key.settings };
        let side = sr.net.output_resolution() as u32;
        let start = Instant::now();
        let none = Outputs { features: false, rgb: false, depth: false, weights_sum: false };
        let result = self.renderer.render_with_superres(
            &loaded.gpu,
            &[key.orbit.camera()],
            &settings,
            none,
            Some(&sr.net),
        );
        let image = match result {
            Ok((_, Some(image))) => image,
            Ok((_, None)) => unreachable!("render_with_superres returns the network's image"),
            Err(e) => {
                // The exact image stays, as this view's final one without the network.
                if let Some(sr) = self.superres.as_mut() {
                    sr.enabled = false;
                }
                if let Some(s) = self.shown.as_mut() {
                    s.key.superres = false;
                }
                self.render_error = Some(format!("super-resolving the still image failed (turned off): {e}"));
                return;
            }
        };
        let sizes: Vec<u32> = ladder.rungs.iter().map(|r| r.resolution).collect();
        let t = self.target_for(side, &sizes);
        self.render_state.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.targets[t].texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            &rgba8(&image, side as usize),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(side * 4),
                rows_per_image: Some(side),
            },
            wgpu::Extent3d { width: side, height: side, depth_or_array_layers: 1 },
        );
        self.render_state.queue.submit([]);
        let end = Instant::now();
        let render_ms = end.duration_since(start).as_secs_f64() * 1e3;
        let drawn = Rung::of(&settings);
        let top = ladder.top();
        let ui_frame = ctx.cumulative_frame_nr();
        let shown = Shown {
            key,
            rung: drawn,
            texture: side,
            index: top,
            top,
            baked: false,
            superres: true,
            render_ms,
            at: end,
            ui_frame,
        };
        self.shown = Some(shown);
        self.move_frames = 0;
        self.render_error = None;
        self.log_frame(shown, ladder, Phase::Final, false);
    }
}

/// The network's planar image (3, side, side), values in [-1, 1], as RGBA8 rows, mapped as the
/// present kernel maps a raw render (`shaders/present.wgsl`, `to_unit`).
fn rgba8(image: &[f32], side: usize) -> Vec<u8> {
    let n = side * side;
    let unit = |v: f32| (((v + 1.0) * 0.5).clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    let mut out = Vec::with_capacity(4 * n);
    for p in 0..n {
        out.extend_from_slice(&[unit(image[p]), unit(image[n + p]), unit(image[2 * n + p]), 255]);
    }
    out
}
