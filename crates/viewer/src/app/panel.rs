//! The viewer's window contents: the side panel of controls (`controls`) and the 3D view
//! (`view`), with the labels they show.

use super::*;

impl ViewerApp {
    /// What is on screen, e.g. `64² · 12+12 (moving)`, `128² · 48+48 (moving, baked)` or
    /// `128² · 48+48 (final)`.
    pub(super) fn quality_label(&self) -> String {
        match &self.shown {
            None => "nothing rendered yet".into(),
            Some(s) if s.superres => format!("{}² super-resolved from {} (final)", s.texture, s.rung.label()),
            Some(s) if s.is_final() => format!("{} (final)", s.rung.label()),
            Some(s) if s.baked && self.moving => format!("{} (moving, baked)", s.rung.label()),
            Some(s) if s.baked => format!("{} (baked, refining)", s.rung.label()),
            Some(s) if self.moving => format!("{} (moving)", s.rung.label()),
            Some(s) => {
                let (step, steps) = Ladder::new(&s.key.settings).exact_step(s.index);
                format!("{} (refining, step {step} of {steps})", s.rung.label())
            }
        }
    }

    // Long because: egui is immediate mode; the side panel's widgets are written in the order
    // they appear, one or two lines each, and splitting them would split the panel's reading order.
    pub(super) fn controls(&mut self, ui: &mut egui::Ui) {
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
        ui.label("Final quality");
        // `Edits`: a command-line value outside a slider's range stays until the slider is moved.
        let edits = egui::SliderClamping::Edits;
        ui.add(egui::Slider::new(&mut self.settings.resolution, 16..=512).clamping(edits).text("resolution"));
        ui.add(
            egui::Slider::new(&mut self.settings.depth_resolution, 4..=192)
                .clamping(edits)
                .text("coarse samples"),
        );
        ui.add(
            egui::Slider::new(&mut self.settings.depth_resolution_importance, 0..=192)
                .clamping(edits)
                .text("fine samples"),
        );
        // The importance pass needs at least 2 fine samples (0 turns it off).
        if self.settings.depth_resolution_importance == 1 {
            self.settings.depth_resolution_importance = 2;
        }
        ui.add(
            egui::Slider::new(&mut self.frame_budget_ms, 10.0..=2000.0)
                .logarithmic(true)
                .clamping(edits)
                .text("budget (ms)"),
        )
        .on_hover_text(
            "While the view changes, render at the quality predicted to take at most this per frame",
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
                    requested: None,
                    result: Arc::new(Mutex::new(None)),
                });
            }
        });
        ui.separator();
        ui.label(egui::RichText::new(format!("on screen: {}", self.quality_label())).strong());
        ui.label(format!("from: {}", self.source_label()));
        match &self.shown {
            Some(s) => {
                // Render time of the image on screen (GPU work included), and the rate it allows.
                ui.label(format!("render {:.1} ms  ·  {:.1} FPS", s.render_ms, 1e3 / s.render_ms.max(1e-3)));
            }
            None => {
                ui.label("render –");
            }
        }
        if let Some((line, failed)) = self.bake_label() {
            let text = egui::RichText::new(line);
            ui.label(if failed { text.color(egui::Color32::from_rgb(255, 110, 110)) } else { text });
        }
        match self.superres.as_mut() {
            Some(sr) => {
                let text = format!("super-resolve the still image ({})", sr.sides());
                ui.checkbox(&mut sr.enabled, text).on_hover_text(format!(
                    "{}: once the view stops, the exact feature image at the network's input side, \
                     super-resolved; moving frames are the raw volume render",
                    sr.file
                ));
                ui.label(egui::RichText::new("moving frames: raw volume render").small());
            }
            None => {
                ui.label(egui::RichText::new("raw volume render (no super-resolution: --superres)").small());
            }
        }
        ui.label(egui::RichText::new(self.renderer_name()).small());
        if let Some(s) = &self.status {
            ui.label(s);
        }
        for e in [&self.error, &self.render_error].into_iter().flatten() {
            ui.colored_label(egui::Color32::from_rgb(255, 110, 110), e);
        }
        ui.add_space(8.0);
        ui.label(egui::RichText::new("drag: orbit · right/shift-drag: pan").small());
        ui.label(egui::RichText::new("scroll: zoom · double-click: reset").small());
    }

    pub(super) fn renderer_name(&self) -> String {
        let info = self.render_state.adapter.get_info();
        format!("{} ({:?})", info.name, info.backend)
    }

    /// The side panel and the view, drawn unfilled over the window cleared to their colour
    /// (`clear_color`), so that lavapipe shades each pixel under the image once, not twice.
    pub(super) fn panels(&mut self, ui: &mut egui::Ui) {
        let side = egui::Frame::side_top_panel(ui.style()).fill(egui::Color32::TRANSPARENT);
        let central = egui::Frame::central_panel(ui.style()).fill(egui::Color32::TRANSPARENT);
        egui::Panel::left("controls")
            .frame(side)
            .resizable(false)
            .exact_size(260.0)
            .show(ui, |ui| self.controls(ui));
        egui::CentralPanel::default().frame(central).show(ui, |ui| self.view(ui));
    }

    pub(super) fn view(&mut self, ui: &mut egui::Ui) {
        if self.loaded.is_none() {
            ui.centered_and_justified(|ui| ui.label("no triplane loaded"));
            return;
        }
        let ppp = ui.ctx().pixels_per_point();
        let (area, response) = ui.allocate_exact_size(ui.available_size(), egui::Sense::click_and_drag());
        // The render scaled to fit (bilinear), centred, its corner on a whole pixel.
        let side_px = (area.width().min(area.height()) * ppp).floor().max(1.0);
        let corner = (area.center().to_vec2() * ppp - egui::Vec2::splat(side_px / 2.0)).round() / ppp;
        let rect = egui::Rect::from_min_size(corner.to_pos2(), egui::Vec2::splat(side_px / ppp));
        self.view_rect = Some(rect);

        let shift = ui.input(|i| i.modifiers.shift);
        let delta = response.drag_delta() / rect.width();
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
        let pointer_down = ui.input(|i| i.pointer.any_down());
        self.step(ui.ctx(), pointer_down);

        let shown = self.shown.and_then(|s| Some((s, self.targets.iter().find(|t| t.size == s.texture)?)));
        match shown {
            Some((_, target)) => {
                egui::Image::new((target.id, rect.size())).paint_at(ui, rect);
            }
            None => {
                ui.painter().text(
                    rect.center(),
                    egui::Align2::CENTER_CENTER,
                    "no image",
                    egui::FontId::proportional(14.0),
                    ui.visuals().text_color(),
                );
            }
        }
    }
}
