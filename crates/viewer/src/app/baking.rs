//! The app's side of the baked field (`crate::bake`): starting a file's background bake, asking
//! whether its field serves a frame, and what the panel and the JSON report say about it.

use super::*;
use crate::bake::BakeState;

impl ViewerApp {
    /// Starts baking `gpu`'s field for the chosen settings; `cpu` is the triplane it was uploaded
    /// from, when its occupancy grid is still to be made.
    pub(super) fn start_bake(
        &self,
        gpu: &Arc<GpuTriplane>,
        cpu: Option<Triplane>,
        ray_range: (f32, f32),
    ) -> BakeJob {
        BakeJob::start(
            self.renderer.clone(),
            gpu.clone(),
            cpu,
            bake::bake_specs(&self.settings, ray_range, self.bake_fine),
            self.settings,
            self.egui_ctx.clone(),
        )
    }

    /// Once the view is still: when the chosen settings changed so that the file's field no
    /// longer covers them (fewer coarse samples), bakes again in the background, once per spec
    /// (a failed bake is not retried for the same settings). Exact frames meanwhile.
    pub(super) fn rebake_if_needed(&mut self) {
        let Some(l) = &self.loaded else { return };
        let Some(job) = &l.bake else { return };
        let need = bake::bake_specs(&self.settings, l.ray_range, self.bake_fine);
        let last = need.last().expect("at least the quick field");
        let covered = l.gpu.baked().is_some_and(|f| f.spec.covers(last));
        if covered || job.specs == need || job.state().running() {
            return;
        }
        // The first job made the occupancy grid (or failed to, and so will this one, saying so).
        let next = self.start_bake(&l.gpu, None, l.ray_range);
        if let Some(l) = &mut self.loaded {
            l.bake = Some(next);
        }
    }

    /// The loaded file's field can draw `key` (at its settings: the chosen ones, or a rung's): it
    /// is ready, covers the settings and can show the display (RGB, depth, weights, channels 0-2).
    pub(super) fn field_serves(&self, key: &FrameKey) -> bool {
        let Some(l) = &self.loaded else { return false };
        !self.baked_broken
            && bake::display_supported(key.display)
            && l.gpu.baked().is_some_and(|f| {
                f.spec.covers(&bake::spec_for(&key.settings, bake::Field::of(&f.spec), l.ray_range))
            })
    }

    /// The settings of a frame drawn from the loaded file's field in place of the rung `exact`
    /// (`bake::baked_settings`). A field other than the one the baked frame times were measured
    /// with (the fine one replacing the quick one) starts those times again.
    pub(super) fn baked_frame_settings(&mut self, exact: &RenderSettings) -> RenderSettings {
        let Some(field) = self.loaded.as_ref().and_then(|l| l.gpu.baked()) else { return *exact };
        if self.baked_times_field != Some(field.spec) {
            self.baked_times = FrameTimes::default();
            self.baked_times_field = Some(field.spec);
        }
        bake::baked_settings(exact, bake::Field::of(&field.spec))
    }

    /// The loaded file's bake, None without a file or with `--no-bake`.
    pub(super) fn bake_state(&self) -> Option<BakeState> {
        self.loaded.as_ref()?.bake.as_ref().map(BakeJob::state)
    }

    /// A bake of the loaded file is under way (the scripted drag waits for it).
    pub(super) fn bake_running(&self) -> bool {
        self.bake_state().is_some_and(|s| s.running())
    }

    /// The bake's state for the frame log: `BakeState::name`, `off` (`--no-bake`) or `none`.
    pub(super) fn bake_state_name(&self) -> &'static str {
        match (&self.loaded, self.bake_state()) {
            (None, _) => "none",
            (Some(_), None) => "off",
            (Some(_), Some(s)) => s.name(),
        }
    }

    /// Which field the image on screen came from, e.g. `baked field (k 4 / 10, N MiB, baked in
    /// T s)` or `exact (decoding every sample)`.
    pub(super) fn source_label(&self) -> String {
        let field = self.loaded.as_ref().and_then(|l| l.gpu.baked());
        match (self.shown, field) {
            (None, _) => "–".into(),
            (Some(s), Some(f)) if s.baked => bake::field_label(&f),
            (Some(s), None) if s.baked => "baked field".into(),
            (Some(_), _) => "exact (decoding every sample)".into(),
        }
    }

    /// The panel's line about the bake (and whether it is an error): progress, a failure, that
    /// it is off, or the ready field when the image on screen is not from it.
    pub(super) fn bake_label(&self) -> Option<(String, bool)> {
        let l = self.loaded.as_ref()?;
        let Some(state) = self.bake_state() else {
            return Some(("baking off: exact frames only".into(), false));
        };
        if let Some(progress) = state.progress_label() {
            return Some((progress, matches!(state, BakeState::Failed(_))));
        }
        let field = l.gpu.baked()?;
        if self.shown.is_some_and(|s| s.baked) {
            return None; // the "from" line names it
        }
        let use_ = if self.field_serves(&self.key()?) {
            "drawn while moving"
        } else {
            "not for this display or these settings"
        };
        Some((format!("{} ready: {use_}", bake::field_label(&field)), false))
    }

    /// The JSON report's `bake` member: the state, and the field when there is one.
    pub(super) fn bake_json(&self) -> String {
        let field = self.loaded.as_ref().and_then(|l| l.gpu.baked());
        let job = self.loaded.as_ref().and_then(|l| l.bake.as_ref());
        let error = match self.bake_state() {
            Some(BakeState::Failed(e)) => json_string(&e),
            _ => "null".into(),
        };
        let field = match &field {
            Some(f) => format!(
                "{{\"subdivisions\": {}, \"fine_subdivisions\": {}, \"epsilon\": {}, \"max_delta\": {}, \
                 \"cells\": {}, \"bricks\": {}, \"fine_bricks\": {}, \"device_bytes\": {}, \
                 \"bake_seconds\": {}}}",
                f.spec.subdivisions,
                f.spec.fine_subdivisions,
                json_number(f.spec.epsilon as f64),
                json_number(f.spec.max_delta),
                f.cells,
                f.n_bricks,
                f.n_bricks - f.n_coarse(),
                f.device_bytes(),
                json_number(f.bake_seconds)
            ),
            None => "null".into(),
        };
        format!(
            "{{\"state\": {}, \"error\": {}, \"job_seconds\": {}, \"field\": {}}}",
            json_string(self.bake_state_name()),
            error,
            job.and_then(BakeJob::seconds).map_or("null".into(), json_number),
            field
        )
    }
}
