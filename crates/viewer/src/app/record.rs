//! What is on screen (`Shown`) and the log of rendered frames the screenshot's JSON report holds
//! (`FrameRecord`, read by `tests/view/test_viewer.py` and `bench/viewer_frames.py`).

use super::*;

/// The image on screen.
#[derive(Debug, Clone, Copy)]
pub(super) struct Shown {
    pub key: FrameKey,
    /// The resolution and samples drawn (a baked frame may take more coarse samples than its
    /// ladder rung, `bake::Field::coarse_scale`).
    pub rung: Rung,
    /// Side of the texture on screen: the rung's, or the network's output side.
    pub texture: u32,
    /// Index in the key's ladder, and the ladder's top index (a baked frame is at the top's
    /// resolution and samples).
    pub index: usize,
    pub top: usize,
    /// Drawn from the baked field (`crate::bake`) instead of decoding every sample.
    pub baked: bool,
    /// The network's image of the exact feature render (`app/superres.rs`).
    pub superres: bool,
    pub render_ms: f64,
    /// When it finished, and in which UI frame.
    pub at: Instant,
    pub ui_frame: u64,
}

impl Shown {
    /// The chosen settings, exact: a baked frame at the same quality is not final, nor the exact
    /// one while the key wants it super-resolved.
    pub fn is_final(&self) -> bool {
        self.index == self.top && !self.baked && self.superres == self.key.superres
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Phase {
    /// Rendered within the frame budget while the view was changing.
    Moving,
    /// A step up the ladder after the view stopped.
    Refining,
    /// The chosen settings.
    Final,
}

impl Phase {
    pub fn name(self) -> &'static str {
        match self {
            Phase::Moving => "moving",
            Phase::Refining => "refining",
            Phase::Final => "final",
        }
    }
}

/// One rendered frame, for the screenshot's JSON report (and `bench/viewer_frames.py`).
#[derive(Debug, Clone, Copy)]
pub(super) struct FrameRecord {
    /// Milliseconds since the app started, at the end of the render.
    pub t_ms: f64,
    pub ui_frame: u64,
    pub render_ms: f64,
    /// Time since the previous UI frame began: what the user sees as the frame time.
    pub interval_ms: f64,
    /// The resolution and samples drawn (`Shown::rung`); `index` is the ladder rung.
    pub rung: Rung,
    pub index: usize,
    pub rungs: usize,
    pub phase: Phase,
    /// A pointer button was down (a drag in progress).
    pub dragging: bool,
    /// Drawn from the baked field.
    pub baked: bool,
    /// The network's image (`rung` is then its feature render's).
    pub superres: bool,
    /// The file's bake when the frame was drawn (`BakeState::name`, or `off` / `none`).
    pub bake: &'static str,
}

impl FrameRecord {
    pub fn json(&self) -> String {
        format!(
            "{{\"t_ms\": {}, \"ui_frame\": {}, \"render_ms\": {}, \"interval_ms\": {}, \"resolution\": {}, \
             \"depth_resolution\": {}, \"depth_resolution_importance\": {}, \"rung\": {}, \"rungs\": {}, \
             \"phase\": \"{}\", \"dragging\": {}, \"baked\": {}, \"superres\": {}, \"bake\": \"{}\"}}",
            json_number(self.t_ms),
            self.ui_frame,
            json_number(self.render_ms),
            json_number(self.interval_ms),
            self.rung.resolution,
            self.rung.depth_resolution,
            self.rung.depth_resolution_importance,
            self.index,
            self.rungs,
            self.phase.name(),
            self.dragging,
            self.baked,
            self.superres,
            self.bake
        )
    }
}

impl ViewerApp {
    /// Adds `shown`, just rendered, to the screenshot's frame log.
    pub(super) fn log_frame(&mut self, shown: Shown, ladder: &Ladder, phase: Phase, dragging: bool) {
        if self.log.len() < LOG_CAP {
            self.log.push(FrameRecord {
                t_ms: shown.at.duration_since(self.started).as_secs_f64() * 1e3,
                ui_frame: shown.ui_frame,
                render_ms: shown.render_ms,
                interval_ms: self.interval_ms,
                rung: shown.rung,
                index: shown.index,
                rungs: ladder.rungs.len(),
                phase,
                dragging,
                baked: shown.baked,
                superres: shown.superres,
                bake: self.bake_state_name(),
            });
        }
    }
}
