//! The triplane: three 32-channel planes plus the EG3D decoder that turns a sampled feature
//! into density and colour, and the scene bounds. Also its `.npz` file
//! (`docs/triplane-format.md`); the Python twin is `lp3d.triplane` / `lp3d.triplane_io`.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::npz::{self, NpyArray, NpyData};
pub use crate::occupancy::Occupancy;

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
/// Largest accepted plane side.
pub const MAX_PLANE_SIZE: usize = 2048;

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

/// What the kernels need to know about a triplane besides its data: plane size and bounds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneInfo {
    pub height: u32,
    pub width: u32,
    pub box_warp: f32,
    pub ray_start: f32,
    pub ray_end: f32,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Triplane {
    /// (3, 32, height, width) row-major, float32 values.
    pub planes: Vec<f32>,
    pub height: usize,
    pub width: usize,
    pub plane_dtype: PlaneDtype,
    pub decoder: Decoder,
    pub box_warp: f32,
    pub ray_start: f32,
    pub ray_end: f32,
    /// The input view's camera, when known.
    pub camera: Option<Camera>,
    /// A baked occupancy grid for these planes and decoder (`crate::occupancy`).
    pub occupancy: Option<Occupancy>,
    /// A short free-text provenance note.
    pub source: Option<String>,
}

impl Triplane {
    pub fn scene(&self) -> SceneInfo {
        SceneInfo {
            height: self.height as u32,
            width: self.width as u32,
            box_warp: self.box_warp,
            ray_start: self.ray_start,
            ray_end: self.ray_end,
        }
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
        if !(self.box_warp.is_finite() && self.box_warp > 0.0) {
            return Err(Error::invalid("box_warp", format!("must be finite and > 0, got {}", self.box_warp)));
        }
        if !(self.ray_start.is_finite() && self.ray_start >= 0.0) {
            return Err(Error::invalid(
                "ray_start",
                format!("must be finite and >= 0, got {}", self.ray_start),
            ));
        }
        if !(self.ray_end.is_finite() && self.ray_end > self.ray_start) {
            return Err(Error::invalid(
                "ray_end",
                format!("must be finite and > ray_start ({}), got {}", self.ray_start, self.ray_end),
            ));
        }
        Ok(())
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

    /// Loads a triplane `.npz` (never with pickle). Errors name the file and the key.
    pub fn load(path: impl AsRef<Path>) -> Result<Triplane> {
        let path = path.as_ref();
        let file = File::open(path).map_err(|e| Error::Io { path: path.into(), message: e.to_string() })?;
        let fmt =
            |field: &str, message: String| Error::Format { path: path.into(), field: field.into(), message };
        let arrays = npz::read_npz(BufReader::new(file)).map_err(|(k, m)| fmt(&k, m))?;
        let get = |key: &str| arrays.iter().find(|(k, _)| k == key).map(|(_, a)| a);
        const REQUIRED: [&str; 9] = [
            "planes",
            "decoder_w0",
            "decoder_b0",
            "decoder_w1",
            "decoder_b1",
            "box_warp",
            "ray_start",
            "ray_end",
            "format_version",
        ];
        const OPTIONAL: [&str; 4] = ["camera", "occupancy", "occupancy_checksum", "source"];
        for (k, _) in &arrays {
            if !REQUIRED.contains(&k.as_str()) && !OPTIONAL.contains(&k.as_str()) {
                return Err(fmt(
                    k,
                    format!("unknown key; expected {REQUIRED:?} and optionally {OPTIONAL:?}"),
                ));
            }
        }
        for k in REQUIRED {
            if get(k).is_none() {
                return Err(fmt(k, "missing".into()));
            }
        }
        let version = get("format_version").unwrap();
        match (&version.data, version.scalar_f64()) {
            (NpyData::I64(_) | NpyData::I32(_), Some(v)) if v as i64 == FORMAT_VERSION => {}
            _ => {
                return Err(fmt(
                    "format_version",
                    format!(
                        "unsupported version {:?}; this build reads version {FORMAT_VERSION}",
                        version.data
                    ),
                ))
            }
        }
        let floats = |key: &str, shape: &[usize]| -> Result<Vec<f32>> {
            let a = get(key).unwrap();
            if a.shape != shape {
                return Err(fmt(key, format!("expected shape {shape:?}, got {:?}", a.shape)));
            }
            a.to_f32().ok_or_else(|| fmt(key, format!("expected a float array, got {}", a.dtype_name())))
        };
        let scalar = |key: &str| -> Result<f32> {
            get(key)
                .unwrap()
                .scalar_f64()
                .map(|v| v as f32)
                .ok_or_else(|| fmt(key, "expected a numeric scalar".into()))
        };
        let pa = get("planes").unwrap();
        if pa.shape.len() != 4 || pa.shape[0] != 3 || pa.shape[1] != N_CHANNELS {
            return Err(fmt("planes", format!("expected shape (3, 32, H, W), got {:?}", pa.shape)));
        }
        let plane_dtype = match pa.data {
            NpyData::F16(_) => PlaneDtype::F16,
            NpyData::F32(_) => PlaneDtype::F32,
            _ => return Err(fmt("planes", format!("expected float16 or float32, got {}", pa.dtype_name()))),
        };
        let camera = match get("camera") {
            None => None,
            Some(a) => {
                let v = a
                    .to_f32()
                    .filter(|v| v.len() == 25)
                    .ok_or_else(|| fmt("camera", "expected 25 floats".into()))?;
                let v64: Vec<f64> = v.iter().map(|&x| x as f64).collect();
                Some(Camera::from_label(&v64, "camera").map_err(|e| fmt("camera", e.to_string()))?)
            }
        };
        let occupancy = match (get("occupancy"), get("occupancy_checksum")) {
            (None, None) => None,
            (Some(_), None) => {
                return Err(fmt("occupancy_checksum", "missing (required with occupancy)".into()))
            }
            (None, Some(_)) => {
                return Err(fmt("occupancy", "missing (occupancy_checksum without a grid)".into()))
            }
            (Some(a), Some(_)) => {
                let g = a.shape.first().copied().unwrap_or(0);
                if a.shape.len() != 3 || a.shape.iter().any(|&d| d != g) {
                    return Err(fmt(
                        "occupancy",
                        format!("expected a (G, G, G) grid, got shape {:?}", a.shape),
                    ));
                }
                let NpyData::F32(bound) = &a.data else {
                    return Err(fmt("occupancy", format!("expected float32, got {}", a.dtype_name())));
                };
                Some(Occupancy { resolution: g, bound: bound.clone() })
            }
        };
        let source = match get("source") {
            None => None,
            Some(NpyArray { data: NpyData::Str(s), .. }) => Some(s.clone()),
            Some(_) => return Err(fmt("source", "expected a unicode string".into())),
        };
        let tri = Triplane {
            planes: pa.to_f32().unwrap(),
            height: pa.shape[2],
            width: pa.shape[3],
            plane_dtype,
            decoder: Decoder {
                w0: floats("decoder_w0", &[HIDDEN, N_CHANNELS])?,
                b0: floats("decoder_b0", &[HIDDEN])?,
                w1: floats("decoder_w1", &[N_OUT, HIDDEN])?,
                b1: floats("decoder_b1", &[N_OUT])?,
            },
            box_warp: scalar("box_warp")?,
            ray_start: scalar("ray_start")?,
            ray_end: scalar("ray_end")?,
            camera,
            occupancy,
            source,
        };
        tri.validate().map_err(|e| match e {
            Error::InvalidInput { field, message } => fmt(&field, message),
            other => other,
        })?;
        if tri.occupancy.is_some() {
            let a = get("occupancy_checksum").unwrap();
            let stored = match (&a.data, a.shape.is_empty()) {
                (NpyData::I64(v), true) => v[0],
                _ => return Err(fmt("occupancy_checksum", "expected an int64 scalar".into())),
            };
            let actual = Occupancy::checksum(&tri) as i64;
            if stored != actual {
                return Err(fmt(
                    "occupancy_checksum",
                    format!(
                        "{stored} does not match these planes and decoder ({actual}): the grid was baked \
                         for another triplane; bake it again"
                    ),
                ));
            }
        }
        Ok(tri)
    }

    /// Writes the triplane atomically: a temporary file in the same directory, then rename.
    /// On failure nothing is left behind and an existing file is untouched.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        self.validate()?;
        let path = path.as_ref();
        let planes = match self.plane_dtype {
            PlaneDtype::F32 => NpyData::F32(self.planes.clone()),
            PlaneDtype::F16 => {
                NpyData::F16(self.planes.iter().map(|&v| half::f16::from_f32(v).to_bits()).collect())
            }
        };
        let d = &self.decoder;
        let mut arrays: Vec<(&str, NpyArray)> = vec![
            ("planes", NpyArray { shape: vec![3, N_CHANNELS, self.height, self.width], data: planes }),
            ("decoder_w0", NpyArray::f32(vec![HIDDEN, N_CHANNELS], d.w0.clone())),
            ("decoder_b0", NpyArray::f32(vec![HIDDEN], d.b0.clone())),
            ("decoder_w1", NpyArray::f32(vec![N_OUT, HIDDEN], d.w1.clone())),
            ("decoder_b1", NpyArray::f32(vec![N_OUT], d.b1.clone())),
            ("box_warp", NpyArray { shape: vec![], data: NpyData::F64(vec![self.box_warp as f64]) }),
            ("ray_start", NpyArray { shape: vec![], data: NpyData::F64(vec![self.ray_start as f64]) }),
            ("ray_end", NpyArray { shape: vec![], data: NpyData::F64(vec![self.ray_end as f64]) }),
            ("format_version", NpyArray { shape: vec![], data: NpyData::I64(vec![FORMAT_VERSION]) }),
        ];
        if let Some(c) = &self.camera {
            arrays.push(("camera", NpyArray::f32(vec![25], c.0.to_vec())));
        }
        if let Some(o) = &self.occupancy {
            let g = o.resolution;
            arrays.push(("occupancy", NpyArray::f32(vec![g, g, g], o.bound.clone())));
            let crc = Occupancy::checksum(self) as i64;
            arrays.push(("occupancy_checksum", NpyArray { shape: vec![], data: NpyData::I64(vec![crc]) }));
        }
        if let Some(s) = &self.source {
            arrays.push(("source", NpyArray { shape: vec![], data: NpyData::Str(s.clone()) }));
        }
        write_atomically(path, |file| npz::write_npz(file, &arrays))
    }
}

/// Runs `write` on a temporary sibling of `path`, then renames it into place.
pub fn write_atomically(path: &Path, write: impl FnOnce(&mut File) -> std::io::Result<()>) -> Result<()> {
    let io_err = |p: &Path, e: std::io::Error| Error::Io { path: p.into(), message: e.to_string() };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name =
        path.file_name().ok_or_else(|| Error::Io { path: path.into(), message: "not a file path".into() })?;
    let tmp = dir.join(format!(".{}.tmp-{}", name.to_string_lossy(), std::process::id()));
    let result = (|| {
        let mut file = File::create(&tmp)?;
        write(&mut file)?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(io_err(path, e));
    }
    Ok(())
}
