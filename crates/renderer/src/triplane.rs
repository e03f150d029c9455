//! The triplane: three 32-channel planes plus the EG3D decoder that turns a sampled feature
//! into density and colour, and the scene bounds; its `.npz` file (`docs/triplane-format.md`)
//! is `triplane/file.rs`. The Python twins are `lp3d.render.triplane` and
//! `lp3d.render.triplane_io`.

mod file;
pub mod occupancy;

pub(crate) use file::{format_error, open_regular_file};
pub use file::{OPTIONAL_KEYS, REQUIRED_KEYS};

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::npz;
pub use occupancy::Occupancy;

/// Which world axes each plane samples as (u, v): (x,y), (x,z), (z,x).
///
/// EG3D's quirk, kept on purpose: the third plane was meant to be YZ but samples (z,x), the
/// transpose of the second; world y is seen by plane 0 alone. All released EG3D checkpoints
/// were trained this way (NVlabs/eg3d#67), so reproducing it makes them render unchanged.
/// `u` indexes a plane's columns (W), `v` its rows (H). The kernel hard-codes the same
/// pairs in `shaders/triplane.wgsl::sample_triplane`.
pub const PLANE_AXES: [[usize; 2]; 3] = [[0, 1], [0, 2], [2, 0]];
/// Channels per plane.
pub const N_CHANNELS: usize = 32;
/// Decoder hidden width.
pub const HIDDEN: usize = 64;
/// Decoder outputs: raw density + 32 features.
pub const N_OUT: usize = 33;
/// Current triplane file format version.
pub const FORMAT_VERSION: i64 = 1;
/// Largest accepted plane side (H and W).
pub const MAX_PLANE_SIZE: usize = 2048;
/// Largest accepted occupancy grid side G.
pub const MAX_OCCUPANCY_RESOLUTION: usize = occupancy::MAX_RESOLUTION;
/// Longest accepted `source` text, in characters.
pub const MAX_SOURCE_CHARS: usize = 4096;
/// Largest accepted triplane file (2048 x 2048 float32 planes and a 512^3 grid are just over 2 GiB).
pub const MAX_FILE_BYTES: u64 = 3 << 30;
/// The file format's caps (`docs/triplane-format.md`, "Caps"), by name, as `lp3d_render.FILE_LIMITS`
/// exposes them; `lp3d.render.triplane_io.FILE_LIMITS` must agree (a test checks).
pub const FILE_LIMITS: [(&str, u64); 7] = [
    ("max_file_bytes", MAX_FILE_BYTES),
    ("max_entry_bytes", npz::MAX_ENTRY_BYTES),
    ("max_entries", npz::MAX_ENTRIES as u64),
    ("max_npy_header_bytes", npz::MAX_NPY_HEADER_BYTES as u64),
    ("max_plane_size", MAX_PLANE_SIZE as u64),
    ("max_occupancy_resolution", MAX_OCCUPANCY_RESOLUTION as u64),
    ("max_source_chars", MAX_SOURCE_CHARS as u64),
];

/// EG3D OSGDecoder with *effective* weights (stored weights × lr_mul / sqrt(fan_in)).
#[derive(Debug, Clone, PartialEq)]
pub struct Decoder {
    /// (64, 32) row-major.
    pub w0: Vec<f32>,
    /// (64,)
    pub b0: Vec<f32>,
    /// (33, 64) row-major.
    pub w1: Vec<f32>,
    /// (33,)
    pub b1: Vec<f32>,
}

impl Decoder {
    pub fn validate(&self) -> Result<()> {
        for (name, v, n) in [
            ("w0", &self.w0, HIDDEN * N_CHANNELS),
            ("b0", &self.b0, HIDDEN),
            ("w1", &self.w1, N_OUT * HIDDEN),
            ("b1", &self.b1, N_OUT),
        ] {
            if v.len() != n {
                return Err(Error::invalid(name, format!("expected {n} values, got {}", v.len())));
            }
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(Error::invalid(name, format!("contains NaN/Inf at flat index {i}")));
            }
        }
        Ok(())
    }
}

/// Storage precision of the planes in the file (the renderer computes in float32).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlaneDtype {
    F16,
    F32,
}

/// EG3D FFHQ's scene bounds (``rendering_kwargs``), as given (float64): [`SceneBounds::default`]
/// and the defaults of Python's ``Triplane(...)``, exposed as ``lp3d_render.DEFAULT_*``;
/// ``lp3d.render.settings.DEFAULT_*`` must agree (tests/render/test_render_api.py checks).
pub const DEFAULT_BOX_WARP: f64 = 1.0;
pub const DEFAULT_RAY_START: f64 = 2.25;
pub const DEFAULT_RAY_END: f64 = 3.3;

/// Where a triplane's scene is: the cube `[-box_warp/2, box_warp/2]^3` its planes span and the
/// depth range `[ray_start, ray_end]` sampled along every ray, in the renderer's precision
/// (float32). The Python twin is `lp3d.render.settings.SceneBounds`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneBounds {
    pub box_warp: f32,
    pub ray_start: f32,
    pub ray_end: f32,
}

impl Default for SceneBounds {
    /// EG3D FFHQ's bounds ([`DEFAULT_BOX_WARP`], [`DEFAULT_RAY_START`], [`DEFAULT_RAY_END`]).
    fn default() -> Self {
        SceneBounds {
            box_warp: DEFAULT_BOX_WARP as f32,
            ray_start: DEFAULT_RAY_START as f32,
            ray_end: DEFAULT_RAY_END as f32,
        }
    }
}

impl SceneBounds {
    /// The bounds from values as given (a file's float64, a Python float), checked as given and
    /// as the renderer uses them (float32), so a value that overflows float32 (`ray_end = 1e300`)
    /// or collapses in it is an error here and in Python (`SceneBounds.problem`) alike. Errors are
    /// [`Error::InvalidInput`] naming the field (`box_warp`, `ray_start` or `ray_end`).
    pub fn new(box_warp: f64, ray_start: f64, ray_end: f64) -> Result<SceneBounds> {
        let (b32, s32, e32) = (box_warp as f32, ray_start as f32, ray_end as f32);
        for (key, v, v32) in
            [("box_warp", box_warp, b32), ("ray_start", ray_start, s32), ("ray_end", ray_end, e32)]
        {
            if v.is_finite() && !v32.is_finite() {
                return Err(Error::invalid(
                    key,
                    format!("{v:e} is not finite as float32 (the renderer's precision)"),
                ));
            }
        }
        if !(box_warp.is_finite() && box_warp > 0.0 && b32 > 0.0) {
            return Err(Error::invalid(
                "box_warp",
                format!("must be finite and > 0 (also as float32), got {box_warp:e}"),
            ));
        }
        if !(ray_start.is_finite() && ray_start >= 0.0 && s32 >= 0.0) {
            return Err(Error::invalid(
                "ray_start",
                format!("must be finite and >= 0 (also as float32), got {ray_start:e}"),
            ));
        }
        if !(ray_end.is_finite() && ray_end > ray_start && e32 > s32) {
            return Err(Error::invalid(
                "ray_end",
                format!("must be finite and > ray_start ({ray_start:e}) (also as float32), got {ray_end:e}"),
            ));
        }
        Ok(SceneBounds { box_warp: b32, ray_start: s32, ray_end: e32 })
    }

    /// The checks of [`SceneBounds::new`] on these (float32) values.
    pub fn validate(&self) -> Result<()> {
        SceneBounds::new(self.box_warp.into(), self.ray_start.into(), self.ray_end.into()).map(|_| ())
    }
}

/// What the kernels need to know about a triplane besides its data: plane size and bounds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneInfo {
    pub height: u32,
    pub width: u32,
    pub bounds: SceneBounds,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Triplane {
    /// (3, 32, height, width) row-major, float32 values.
    pub planes: Vec<f32>,
    pub height: usize,
    pub width: usize,
    pub plane_dtype: PlaneDtype,
    pub decoder: Decoder,
    pub bounds: SceneBounds,
    /// The input view's camera, when known.
    pub camera: Option<Camera>,
    /// A baked occupancy grid for these planes and decoder (`crate::occupancy`).
    pub occupancy: Option<Occupancy>,
    /// A short free-text provenance note.
    pub source: Option<String>,
}

impl Triplane {
    /// CRC-32 of the planes (float32 values, `(3, 32, H, W)` order, little-endian) and the
    /// decoder (w0, b0, w1, b1 as float32): stored beside the grid in the `.npz` so a grid
    /// baked for other planes or weights is detected on load.
    pub fn occupancy_checksum(&self) -> u32 {
        let mut h = crc32fast::Hasher::new();
        for part in [&self.planes, &self.decoder.w0, &self.decoder.b0, &self.decoder.w1, &self.decoder.b1] {
            for chunk in part.chunks(4096) {
                let bytes: Vec<u8> = chunk.iter().flat_map(|v| v.to_le_bytes()).collect();
                h.update(&bytes);
            }
        }
        h.finalize()
    }

    pub fn scene(&self) -> SceneInfo {
        SceneInfo { height: self.height as u32, width: self.width as u32, bounds: self.bounds }
    }

    pub fn validate(&self) -> Result<()> {
        if self.height < 2 || self.width < 2 || self.height > MAX_PLANE_SIZE || self.width > MAX_PLANE_SIZE {
            return Err(Error::invalid(
                "planes",
                format!("H and W must be in [2, {MAX_PLANE_SIZE}], got {}x{}", self.height, self.width),
            ));
        }
        if self.planes.len() != 3 * N_CHANNELS * self.height * self.width {
            return Err(Error::invalid("planes", "data length does not match (3, 32, H, W)"));
        }
        if let Some(i) = self.planes.iter().position(|x| !x.is_finite()) {
            return Err(Error::invalid("planes", format!("contains NaN/Inf at flat index {i}")));
        }
        self.decoder.validate()?;
        if let Some(o) = &self.occupancy {
            o.validate()?;
        }
        self.bounds.validate()
    }

    /// Planes re-laid channel-last, (3, H, W, 32): one texel's 32 channels are contiguous,
    /// so the kernel reads a tap as 8 vec4 loads.
    pub fn planes_channel_last(&self) -> Vec<f32> {
        let (h, w) = (self.height, self.width);
        let mut out = vec![0f32; self.planes.len()];
        for p in 0..3 {
            for c in 0..N_CHANNELS {
                let src = &self.planes[(p * N_CHANNELS + c) * h * w..][..h * w];
                for (i, &v) in src.iter().enumerate() {
                    out[(p * h * w + i) * N_CHANNELS + c] = v;
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(r: Result<SceneBounds>) -> String {
        match r {
            Err(Error::InvalidInput { field, .. }) => field,
            other => panic!("expected InvalidInput, got {other:?}"),
        }
    }

    #[test]
    fn scene_bounds_default_is_ffhq_and_valid() {
        let b = SceneBounds::default();
        assert_eq!((b.box_warp, b.ray_start, b.ray_end), (1.0, 2.25, 3.3));
        b.validate().unwrap();
        assert_eq!(SceneBounds::new(DEFAULT_BOX_WARP, DEFAULT_RAY_START, DEFAULT_RAY_END).unwrap(), b);
    }

    #[test]
    fn scene_bounds_are_checked_as_given_and_as_float32() {
        assert_eq!(field(SceneBounds::new(0.0, 2.25, 3.3)), "box_warp");
        assert_eq!(field(SceneBounds::new(1e-50, 2.25, 3.3)), "box_warp"); // 0 as float32
        assert_eq!(field(SceneBounds::new(1.0, -1e-50, 3.3)), "ray_start"); // -0 as float32
        assert_eq!(field(SceneBounds::new(1.0, 2.25, 1e300)), "ray_end"); // overflows float32
        assert_eq!(field(SceneBounds::new(1.0, 1.0, 1.0 + 1e-12)), "ray_end"); // equal as float32
        assert_eq!(field(SceneBounds::new(1.0, 3.0, 2.0)), "ray_end");
        let bad = SceneBounds { ray_end: f32::NAN, ..SceneBounds::default() };
        assert!(matches!(bad.validate(), Err(Error::InvalidInput { field, .. }) if field == "ray_end"));
    }
}
