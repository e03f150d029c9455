//! How to render: the one Rust definition of the rendering settings. Names follow EG3D's
//! `rendering_kwargs` and match `lp3d.render.settings.RenderSettings` in Python and the WGSL
//! `Params` uniform (a cross-language test ties them).

use crate::error::{Error, Result};

/// Largest ray-grid side.
pub const MAX_RESOLUTION: u32 = 1024;
/// Largest coarse or fine sample count per ray (sizes of the kernel's scratch arrays;
/// must equal `MAX_SAMPLES` in `shaders/params.wgsl`).
pub const MAX_SAMPLES: u32 = 256;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderSettings {
    /// Rays per image side (EG3D's neural rendering resolution).
    pub resolution: u32,
    /// Coarse samples per ray, EG3D's S.
    pub depth_resolution: u32,
    /// Fine (importance) samples per ray, EG3D's N; 0 disables the importance pass.
    pub depth_resolution_importance: u32,
    /// Composite over white (EG3D's Shapenet setting); FFHQ uses black.
    pub white_back: bool,
    /// No coarse jitter and EG3D's `det=True` importance draw. Otherwise jittered with `seed`.
    pub deterministic: bool,
    pub seed: u32,
    /// Work the renderer may skip; the default skips nothing (exact EG3D semantics).
    pub skips: Skips,
}

/// Approximations that trade a bounded error for speed (docs/performance.md, "Exact mode's skips").
/// Zero thresholds are exact.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Skips {
    /// Stop a ray once its transmittance is below this, in the coarse pass and the composite.
    /// Contributions behind that point are weighted by less than the threshold, but stopping
    /// the coarse pass also moves the importance samples (the pdf behind the surface becomes
    /// its floor), so the error is measured (docs/performance.md, "Exact mode's skips"), not
    /// bounded by the threshold.
    pub transmittance_threshold: f32,
    /// No importance pass for rays whose coarse opacity is below this: they are composited
    /// from the coarse samples alone.
    pub empty_threshold: f32,
    /// Skip samples in the triplane's occupancy grid's empty cells (`crate::occupancy`): an
    /// interval between two such samples has opacity at most this and is taken as 0, without
    /// fetching or decoding them. Applies to the final composite, where the error has a proved
    /// bound (`docs/occupancy.md`); 0 = off.
    pub occupancy_epsilon: f32,
    /// Apply the occupancy skip to the coarse pass as well: faster, but the changed coarse
    /// weights move the importance samples, so that part of the error is measured, not bounded.
    pub occupancy_coarse: bool,
    /// Skip the decoder: look samples up in the triplane's baked field (`crate::baked`,
    /// `docs/baked.md`), decoded once at this many points per baked cell edge (`baked::baked_cells`) in the cells
    /// the occupancy skip keeps; RGB, depth and weights only. Needs `occupancy_epsilon` > 0 (the
    /// bake stores nothing where that skip takes the density as 0). 0 = off.
    pub baked_subdivisions: u32,
    /// A two-level field: the bricks a surface crosses, or that hold a colour edge under one
    /// (`baked::needs_fine`), hold this many points per cell edge instead, more than
    /// `baked_subdivisions`; the rest keep that many. The error falls with the square of the
    /// sub-cell and those bricks are where it is (`docs/baked.md`, "Two levels"). 0 = one level.
    pub baked_fine_subdivisions: u32,
}

impl Skips {
    pub const EXACT: Skips = Skips {
        transmittance_threshold: 0.0,
        empty_threshold: 0.0,
        occupancy_epsilon: 0.0,
        occupancy_coarse: false,
        baked_subdivisions: 0,
        baked_fine_subdivisions: 0,
    };

    /// The baked field as the viewer's moving frames and `lp3d orbit --baked` use it
    /// (`docs/baked.md`; sizes in docs/performance.md, "Bake time and size"): two levels, k = 10
    /// in the bricks a surface crosses (or a colour edge under one) and 4 elsewhere (the coarse
    /// ones within lavapipe's 128 MiB storage binding, where a uniform k = 8 is not), closer to
    /// exact mode than a uniform k = 6 at the same frame time; the occupancy skip at 1e-4 per
    /// interval. `lp3d.render.settings.BAKED` is the same (a test).
    pub const BAKED: Skips =
        Skips { occupancy_epsilon: 1e-4, baked_subdivisions: 4, baked_fine_subdivisions: 10, ..Skips::EXACT };

    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("transmittance_threshold", self.transmittance_threshold),
            ("empty_threshold", self.empty_threshold),
            ("occupancy_epsilon", self.occupancy_epsilon),
        ] {
            if !(v.is_finite() && (0.0..1.0).contains(&v)) {
                return Err(Error::invalid(name, format!("must be in [0, 1), got {v}")));
            }
        }
        if self.occupancy_coarse && self.occupancy_epsilon == 0.0 {
            return Err(Error::invalid("occupancy_coarse", "needs occupancy_epsilon > 0"));
        }
        let k = self.baked_subdivisions;
        if k > crate::baked::MAX_SUBDIVISIONS {
            return Err(Error::invalid(
                "baked_subdivisions",
                format!("must be in [0, {}], got {k}", crate::baked::MAX_SUBDIVISIONS),
            ));
        }
        if k > 0 && self.occupancy_epsilon == 0.0 {
            return Err(Error::invalid("baked_subdivisions", "needs occupancy_epsilon > 0"));
        }
        let fine = self.baked_fine_subdivisions;
        if fine != 0 && !(k > 0 && fine > k && fine <= crate::baked::MAX_FINE_SUBDIVISIONS) {
            return Err(Error::invalid(
                "baked_fine_subdivisions",
                format!(
                    "must be 0 or in (baked_subdivisions, {}] with baked_subdivisions > 0, got {fine} \
                     (baked_subdivisions {k})",
                    crate::baked::MAX_FINE_SUBDIVISIONS
                ),
            ));
        }
        Ok(())
    }
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            resolution: 128,
            depth_resolution: 48,
            depth_resolution_importance: 48,
            white_back: false,
            deterministic: true,
            seed: 0,
            skips: Skips::EXACT,
        }
    }
}

impl RenderSettings {
    /// The longest interval between consecutive samples, coarse or merged (every merged
    /// interval lies inside a coarse one): one linspace step, two with jitter, plus float32
    /// rounding of the depths.
    pub fn max_interval(&self, ray_start: f32, ray_end: f32) -> f64 {
        let step = (ray_end as f64 - ray_start as f64) / (self.depth_resolution.max(2) - 1) as f64;
        let steps = if self.deterministic { 1.0 } else { 2.0 };
        let ulps = 8.0 * f32::EPSILON as f64 * (ray_start.abs().max(ray_end.abs()) as f64);
        steps * step * (1.0 + 1e-6) + ulps
    }

    pub fn validate(&self) -> Result<()> {
        if !(1..=MAX_RESOLUTION).contains(&self.resolution) {
            return Err(Error::invalid(
                "resolution",
                format!("must be in [1, {MAX_RESOLUTION}], got {}", self.resolution),
            ));
        }
        let n = self.depth_resolution_importance;
        // sample_pdf needs S - 3 >= 1 bins.
        let min_s = if n > 0 { 4 } else { 2 };
        if !(min_s..=MAX_SAMPLES).contains(&self.depth_resolution) {
            return Err(Error::invalid(
                "depth_resolution",
                format!(
                    "must be in [{min_s}, {MAX_SAMPLES}] (importance sampling needs at least 4), got {}",
                    self.depth_resolution
                ),
            ));
        }
        if n != 0 && !(2..=MAX_SAMPLES).contains(&n) {
            return Err(Error::invalid(
                "depth_resolution_importance",
                format!("must be 0 (no importance pass) or in [2, {MAX_SAMPLES}], got {n}"),
            ));
        }
        self.skips.validate()
    }
}

/// Which outputs to compute. Features need all 32 decoder colour rows; RGB needs 3;
/// depth and weights sum need only the density row.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Outputs {
    pub features: bool,
    pub rgb: bool,
    pub depth: bool,
    pub weights_sum: bool,
}

impl Outputs {
    pub const ALL: Outputs = Outputs { features: true, rgb: true, depth: true, weights_sum: true };
    pub const NAMES: [&'static str; 4] = ["features", "rgb", "depth", "weights_sum"];

    /// Parses output names such as `["rgb", "depth"]`.
    pub fn from_names<S: AsRef<str>>(names: &[S]) -> Result<Self> {
        let mut out = Outputs { features: false, rgb: false, depth: false, weights_sum: false };
        for name in names {
            match name.as_ref() {
                "features" => out.features = true,
                "rgb" => out.rgb = true,
                "depth" => out.depth = true,
                "weights_sum" => out.weights_sum = true,
                other => {
                    return Err(Error::invalid(
                        "outputs",
                        format!("unknown output '{other}', expected some of {:?}", Self::NAMES),
                    ))
                }
            }
        }
        if !(out.features || out.rgb || out.depth || out.weights_sum) {
            return Err(Error::invalid("outputs", "must name at least one output"));
        }
        Ok(out)
    }

    /// Decoder feature channels the kernel must compute.
    pub fn feature_channels(&self) -> u32 {
        if self.features {
            32
        } else if self.rgb {
            3
        } else {
            0
        }
    }
}

/// What the viewer shows: one render output mapped to colour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Display {
    Rgb,
    /// Depth as a ramp, near (bright) to far (dark); rays with weights sum < 0.5 are black.
    Depth {
        near: f32,
        far: f32,
    },
    Weights,
    /// One of the 32 feature channels, [-1, 1] mapped to black..white.
    Channel(u32),
}
