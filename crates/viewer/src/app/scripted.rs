//! The scripted runs: `--drag-frames` (a synthetic drag fed into egui's input) and
//! `--screenshot` / the Save button (the window capture, the render read back, the JSON report).

use super::*;

/// How often a scripted drag waiting for the bake looks again (besides the bake's own repaints).
const BAKE_WAIT_REPAINT: Duration = Duration::from_millis(250);

/// `--drag-frames`: a synthetic left-button drag injected into egui's input, one step per UI
/// frame, so tests and benchmarks drive the same code path as a mouse.
#[derive(Debug, Clone)]
pub(super) struct DragScript {
    frames: u32,
    /// 0: waiting for the first final image (and the bake); 1..=frames: moving; frames + 1:
    /// released.
    step: u32,
    start: egui::Pos2,
    delta: egui::Vec2,
    released: Option<Instant>,
    /// Release to the refined image on screen.
    release_to_final_ms: Option<f64>,
    /// The window at the last moving frame, captured before the release (saved with the
    /// screenshot as `drag_path`), and the quality it showed.
    shot: DragShot,
}

impl DragScript {
    pub(super) fn new(frames: u32) -> DragScript {
        DragScript {
            frames,
            step: 0,
            start: egui::Pos2::ZERO,
            delta: egui::Vec2::ZERO,
            released: None,
            release_to_final_ms: None,
            shot: DragShot::default(),
        }
    }
}

#[derive(Debug, Clone, Default)]
pub(super) struct DragShot {
    requested: Option<String>,
    slot: Arc<Mutex<Option<Arc<egui::ColorImage>>>>,
    image: Option<Arc<egui::ColorImage>>,
}

impl ViewerApp {
    /// Reads the texture on screen back (for the screenshot's render image).
    pub(super) fn read_shown(&self) -> Result<RenderImage, String> {
        let s = self.shown.ok_or("nothing rendered")?;
        let target = self.targets.iter().find(|t| t.size == s.texture).ok_or("the render texture is gone")?;
        let device = &self.render_state.device;
        let size = target.size;
        let row = size * 4;
        let padded = row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d-view render readback"),
            size: padded as u64 * size as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut encoder = device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("lp3d-view readback") });
        encoder.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &target.texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &buffer,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded),
                    rows_per_image: Some(size),
                },
            },
            wgpu::Extent3d { width: size, height: size, depth_or_array_layers: 1 },
        );
        self.render_state.queue.submit([encoder.finish()]);
        let slice = buffer.slice(..);
        let mapped = Arc::new(Mutex::new(None));
        let slot = mapped.clone();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            if let Ok(mut s) = slot.lock() {
                *s = Some(r);
            }
        });
        device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| e.to_string())?;
        match mapped.lock().ok().and_then(|mut s| s.take()) {
            Some(Ok(())) => {}
            Some(Err(e)) => return Err(format!("reading the render back failed: {e}")),
            None => return Err("reading the render back did not finish".into()),
        }
        let data = slice.get_mapped_range().map_err(|e| format!("reading the render back failed: {e}"))?;
        let mut rgba = Vec::with_capacity((row * size) as usize);
        for y in 0..size as usize {
            let offset = y * padded as usize;
            rgba.extend_from_slice(&data[offset..offset + row as usize]);
        }
        drop(data);
        buffer.unmap();
        Ok(RenderImage { size, rgba })
    }

    /// The JSON members the screenshot's sidecar gets besides the view: settings, quality, the
    /// bake, the frame log and the drag's summary.
    pub(super) fn report(&self, quality: &str) -> String {
        let s = &self.settings;
        let drag = match &self.drag {
            Some(d) => format!(
                "{{\"frames\": {}, \"points\": [{}, {}], \"release_to_final_ms\": {}, \"image\": {}, \"image_quality\": {}}}",
                d.frames,
                json_number(d.delta.x as f64),
                json_number(d.delta.y as f64),
                d.release_to_final_ms.map_or("null".into(), json_number),
                match (&d.shot.image, &self.screenshot) {
                    (Some(_), Some(job)) => json_string(
                        &drag_path(&job.path).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
                    ),
                    _ => "null".into(),
                },
                d.shot.requested.as_deref().map_or("null".into(), json_string)
            ),
            None => "null".into(),
        };
        let frames: Vec<String> = self.log.iter().map(|r| format!("    {}", r.json())).collect();
        format!(
            "\"settings\": {{\"resolution\": {}, \"depth_resolution\": {}, \"depth_resolution_importance\": {}}},\n  \
             \"quality\": {},\n  \"frame_budget_ms\": {},\n  \"adapter\": {},\n  \"bake\": {},\n  \"drag\": {},\n  \"frames\": [\n{}\n  ]",
            s.resolution,
            s.depth_resolution,
            s.depth_resolution_importance,
            json_string(quality),
            json_number(self.frame_budget_ms),
            json_string(&self.renderer_name()),
            self.bake_json(),
            drag,
            frames.join(",\n")
        )
    }

    /// Advances the scripted drag (`--drag-frames`) by one UI frame. It starts once the final
    /// image is on screen and the file's bake has ended (ready or failed), so that the drag shows
    /// what a user sees once the viewer is ready.
    pub(super) fn drive_drag(&mut self, raw: &mut egui::RawInput) {
        let settled = self.settled_final() && !self.bake_running();
        let Some(rect) = self.view_rect else { return };
        let Some(d) = &mut self.drag else { return };
        let button = |pos, pressed| egui::Event::PointerButton {
            pos,
            button: egui::PointerButton::Primary,
            pressed,
            modifiers: egui::Modifiers::NONE,
        };
        if d.step == 0 {
            if !settled {
                return;
            }
            // A quarter of the view's width to the right and a tenth down, centred on the view.
            d.delta = egui::vec2(rect.width() / 4.0, rect.width() / 10.0);
            d.start = rect.center() - d.delta / 2.0;
            raw.events.push(egui::Event::PointerMoved(d.start));
            raw.events.push(button(d.start, true));
            d.step = 1;
        } else if d.step <= d.frames {
            let pos = d.start + d.delta * (d.step as f32 / d.frames as f32);
            raw.events.push(egui::Event::PointerMoved(pos));
            d.step += 1;
        } else if d.released.is_none() && d.shot.image.is_some() {
            // Released once the window at the last moving frame is captured (drive_drag_shot).
            raw.events.push(button(d.start + d.delta, false));
            d.released = Some(Instant::now());
        }
    }

    /// With the drag's last move done and the button still down (so the moving frame stays on
    /// screen), captures the window once that frame's numbers are in the panel; the release waits
    /// for the capture.
    fn drive_drag_shot(&mut self, ctx: &egui::Context) {
        let Some(d) = &self.drag else { return };
        if d.step <= d.frames || d.released.is_some() || d.shot.image.is_some() {
            return;
        }
        ctx.request_repaint();
        if d.shot.requested.is_some() {
            let image = d.shot.slot.lock().ok().and_then(|mut s| s.take());
            if let (Some(image), Some(d)) = (image, &mut self.drag) {
                d.shot.image = Some(image);
            }
            return;
        }
        // The last move's frame is rendered in the UI frame that moved (or failed: nothing shown).
        if self.shown.is_some_and(|s| s.ui_frame >= ctx.cumulative_frame_nr()) {
            return;
        }
        let quality = self.quality_label();
        let Some(d) = &mut self.drag else { return };
        let slot = d.shot.slot.clone();
        ctx.send_viewport_cmd(egui::ViewportCommand::Screenshot(egui::ScreenshotCallback::new(
            move |image| {
                if let Ok(mut s) = slot.lock() {
                    *s = Some(image);
                }
            },
        )));
        d.shot.requested = Some(quality);
    }

    pub(super) fn drive_screenshot(&mut self, ctx: &egui::Context) {
        self.drive_drag_shot(ctx);
        if let (Some(d), Some(s)) = (&mut self.drag, &self.shown) {
            if let (Some(released), None) = (d.released, d.release_to_final_ms) {
                if s.is_final() && s.at > released && !self.moving {
                    d.release_to_final_ms = Some(s.at.duration_since(released).as_secs_f64() * 1e3);
                }
            }
        }
        let drag_done = self.drag.as_ref().is_none_or(|d| d.release_to_final_ms.is_some());
        let frame = ctx.cumulative_frame_nr();
        // The final image was rendered in an earlier UI frame, so the panel shows its numbers.
        let ready = self.settled_final() && self.shown.is_some_and(|s| s.ui_frame < frame) && drag_done;
        let Some(job) = &self.screenshot else {
            if self.drag.is_some() {
                ctx.request_repaint();
            }
            return;
        };
        if job.requested.is_none() {
            let (Some(rect), Some(shown)) = (self.view_rect, self.shown) else {
                ctx.request_repaint();
                return;
            };
            if !(ready && frame >= job.frames_before as u64) {
                // A drag waiting for the bake: its progress asks for repaints; drawing the window
                // meanwhile would only take CPU from the bake.
                let waiting = self.drag.as_ref().is_some_and(|d| d.step == 0) && self.bake_running();
                ctx.request_repaint_after(if waiting { BAKE_WAIT_REPAINT } else { Duration::ZERO });
                return;
            }
            let ppp = ctx.pixels_per_point();
            let size = (rect.width() * ppp).round() as u32;
            let view = ViewRect {
                x: (rect.min.x * ppp).round() as u32,
                y: (rect.min.y * ppp).round() as u32,
                size,
                scale: size as f64 / shown.texture as f64,
                resolution: shown.texture,
                yaw: shown.key.orbit.yaw,
                pitch: shown.key.orbit.pitch,
            };
            let quality = self.quality_label();
            let render = match self.read_shown() {
                Ok(r) => r,
                Err(e) => return self.finish_screenshot(ctx, Err(e)),
            };
            let slot = job.result.clone();
            ctx.send_viewport_cmd(egui::ViewportCommand::Screenshot(egui::ScreenshotCallback::new(
                move |image| {
                    if let Ok(mut s) = slot.lock() {
                        *s = Some(image);
                    }
                },
            )));
            if let Some(job) = &mut self.screenshot {
                job.requested = Some(Captured { view, render, quality });
            }
            ctx.request_repaint();
            return;
        }
        let image = job.result.lock().ok().and_then(|mut s| s.take());
        let Some(image) = image else {
            ctx.request_repaint();
            return;
        };
        let captured = job.requested.as_ref().expect("requested");
        let report = self.report(&captured.quality);
        let drag = self.drag.as_ref().and_then(|d| d.shot.image.as_deref());
        let result = save_screenshot(&job.path, &image, &captured.view, &captured.render, drag, &report);
        self.finish_screenshot(ctx, result);
    }

    pub(super) fn finish_screenshot(&mut self, ctx: &egui::Context, result: Result<PathBuf, String>) {
        let Some(job) = self.screenshot.take() else { return };
        match &result {
            Ok(p) => self.status = Some(format!("saved {}", p.display())),
            Err(e) => self.error = Some(e.clone()),
        }
        if job.exit_after {
            if let Ok(mut slot) = self.outcome.lock() {
                *slot = Some(result);
            }
            ctx.send_viewport_cmd(egui::ViewportCommand::Close);
        }
    }
}
