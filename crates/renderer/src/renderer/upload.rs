//! Triplanes onto the GPU: `Renderer::upload` (planes channel-last, float16 kept packed, the
//! decoder uniform), the float32 range check that makes a finite triplane render finite, and
//! the occupancy grid's bits for a threshold.

use super::*;

impl GpuTriplane {
    pub fn scene(&self) -> SceneInfo {
        self.scene
    }

    /// Whether the planes are stored as float16 on the device.
    pub fn half_planes(&self) -> bool {
        self.half
    }

    pub fn has_occupancy(&self) -> bool {
        self.occupancy.lock().map(|o| o.is_some()).unwrap_or(false)
    }

    /// Bytes of device memory this triplane holds: planes, decoder, occupancy bits and baked field.
    pub fn device_bytes(&self) -> u64 {
        let bits = self
            .occupancy
            .lock()
            .ok()
            .and_then(|o| o.as_ref().and_then(|o| o.bits.as_ref().map(|(_, b)| b.size())))
            .unwrap_or(0);
        let baked = self.baked().map_or(0, |b| b.device_bytes());
        self.planes.size() + self.decoder.size() + bits + baked
    }
}

/// Float32's largest value, in float64.
const F32_MAX: f64 = f32::MAX as f64;

/// Refuses a triplane whose finite values could overflow float32 inside the kernel: planes
/// near float32's maximum (3e38) or decoder weights large enough to push the decoder's sums
/// past it would render NaN everywhere — a black image and no error.
///
/// The bound follows `shaders/triplane.wgsl` and `shaders/decoder.wgsl` exactly, in float64:
/// with `P = max |planes|`, every partial sum of the feature accumulation (3 planes x 4
/// bilinear taps, weights summing to 1 per plane) is at most `3P`, and the averaged feature
/// `f` at most `P`; every partial sum of a hidden pre-activation `z_j = w0_j . f + b0_j` is at
/// most `Z_j = sum_k |w0_jk| P + |b0_j|`, so `softplus(z_j) <= Z_j + 1`; every partial sum of
/// an output `o_k = w1_k . h + b1_k` is at most `O_k = sum_j |w1_kj| (Z_j + 1) + |b1_k|`. The
/// ray marcher adds two raw densities before halving them, so it needs `2 O_0`. Colours go
/// through a sigmoid and densities through softplus and `1 - exp(-x)`, which are finite for
/// any finite argument. If all of these stay below float32's maximum (with a margin far above
/// float32's rounding of at most 65-term sums), no intermediate value can be Inf or NaN: a
/// proof for every camera and setting, checked once per upload (one pass over the planes)
/// and covering every path, the viewer's `render_to_texture` included, whose results never
/// come back to the CPU. Real triplanes sit ~30 orders of magnitude below the limit.
fn check_decoder_range(tri: &Triplane) -> Result<()> {
    let p = tri.planes.iter().fold(0f64, |m, &v| m.max((v as f64).abs()));
    let d = &tri.decoder;
    let n_in = N_CHANNELS;
    let n_hidden = d.b0.len();
    let hidden: Vec<f64> = (0..n_hidden)
        .map(|j| {
            let row = &d.w0[j * n_in..(j + 1) * n_in];
            row.iter().map(|&w| (w as f64).abs() * p).sum::<f64>() + (d.b0[j] as f64).abs()
        })
        .collect();
    let mut worst = 3.0 * p;
    for (k, b) in d.b1.iter().enumerate() {
        let row = &d.w1[k * n_hidden..(k + 1) * n_hidden];
        let o: f64 = row.iter().zip(&hidden).map(|(&w, &z)| (w as f64).abs() * (z + 1.0)).sum::<f64>()
            + (*b as f64).abs();
        worst = worst.max(if k == 0 { 2.0 * o } else { o });
    }
    worst = hidden.iter().fold(worst, |m, &z| m.max(z));
    // Written so that a NaN bound (impossible for finite inputs) would also be refused.
    if !matches!((worst * 1.001).partial_cmp(&F32_MAX), Some(std::cmp::Ordering::Less)) {
        return Err(Error::invalid(
            "planes",
            format!(
                "the triplane's values overflow float32 in the decoder: planes up to {p:.3e} with \
                 these decoder weights reach {worst:.3e}, beyond float32's maximum {F32_MAX:.3e}"
            ),
        ));
    }
    Ok(())
}

impl Renderer {
    /// The largest buffer one storage binding of this device can hold, in bytes.
    pub(super) fn max_binding_bytes(&self) -> u64 {
        self.limits.max_storage_buffer_binding_size.min(self.limits.max_buffer_size)
    }

    /// An `InvalidInput` error naming `field` when `bytes` (of `what`) exceed one storage
    /// binding; `hint` says what to change.
    pub(super) fn check_binding(&self, field: &str, what: &str, bytes: u64, hint: &str) -> Result<()> {
        let max = self.max_binding_bytes();
        if bytes <= max {
            return Ok(());
        }
        Err(Error::invalid(
            field,
            format!(
                "{what} ({} MiB) exceeds this device's storage buffer limit ({} MiB){hint}",
                bytes >> 20,
                max >> 20
            ),
        ))
    }

    /// Uploads a validated triplane, with its occupancy grid if it has one. Float16 planes
    /// stay float16 on the device (packed pairs, unpacked to float32 in the kernel).
    pub fn upload(&self, tri: &Triplane) -> Result<GpuTriplane> {
        tri.validate()?;
        check_decoder_range(tri)?;
        let half = tri.plane_dtype == PlaneDtype::F16;
        let planes: Vec<u32> = if half {
            // Channel 2i in the low half, 2i + 1 in the high half (WGSL unpack2x16float).
            tri.planes_channel_last()
                .chunks_exact(2)
                .map(|p| {
                    let lo = half::f16::from_f32(p[0]).to_bits() as u32;
                    let hi = half::f16::from_f32(p[1]).to_bits() as u32;
                    lo | (hi << 16)
                })
                .collect()
        } else {
            tri.planes_channel_last().into_iter().map(f32::to_bits).collect()
        };
        debug_assert_eq!(planes.len() % (N_CHANNELS / 2), 0);
        let bytes = (planes.len() * 4) as u64;
        self.check_binding("planes", "the triplane", bytes, "")?;
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let planes = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d planes (3, H, W, 32)"),
            contents: bytemuck::cast_slice(&planes),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let decoder = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d decoder weights"),
            contents: bytemuck::bytes_of(&DecoderUniform::from_decoder(&tri.decoder)),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("uploading the triplane failed: {e}")));
        }
        let occupancy = tri.occupancy.clone().map(|grid| GpuOccupancy { grid: Arc::new(grid), bits: None });
        Ok(GpuTriplane {
            planes,
            decoder,
            scene: tri.scene(),
            half,
            occupancy: Mutex::new(occupancy),
            baked: Mutex::new(None),
        })
    }

    /// Attaches (or replaces) an uploaded triplane's occupancy grid, e.g. one baked after
    /// upload with `Occupancy::bake`. The caller vouches that it was baked for these planes.
    pub fn set_occupancy(&self, tri: &GpuTriplane, grid: Occupancy) -> Result<()> {
        grid.validate()?;
        let mut slot = tri.occupancy.lock().map_err(|_| Error::Gpu("occupancy lock poisoned".into()))?;
        *slot = Some(GpuOccupancy { grid: Arc::new(grid), bits: None });
        // A baked field was made from the old grid's cells.
        *tri.baked.lock().map_err(|_| Error::Gpu("baked field lock poisoned".into()))? = None;
        Ok(())
    }

    /// The occupancy bits for `settings` (grid resolution and buffer), or `None` when the skip
    /// is off. Cached per triplane for the last threshold.
    pub(super) fn occupancy_bits(
        &self,
        tri: &GpuTriplane,
        settings: &RenderSettings,
    ) -> Result<Option<(u32, wgpu::Buffer)>> {
        let eps = settings.skips.occupancy_epsilon;
        if eps <= 0.0 {
            return Ok(None);
        }
        let mut slot = tri.occupancy.lock().map_err(|_| Error::Gpu("occupancy lock poisoned".into()))?;
        let Some(occ) = slot.as_mut() else {
            return Err(Error::invalid(
                "occupancy_epsilon",
                "this triplane has no occupancy grid: bake one first (Occupancy::bake)",
            ));
        };
        let max_delta = settings.max_interval(tri.scene.bounds.ray_start, tri.scene.bounds.ray_end);
        let threshold = Occupancy::raw_threshold(eps as f64, max_delta);
        if occ.bits.as_ref().map(|(t, _)| *t) != Some(threshold) {
            let buf = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("lp3d occupancy bits"),
                contents: bytemuck::cast_slice(&occ.grid.bits(threshold)),
                usage: wgpu::BufferUsages::STORAGE,
            });
            occ.bits = Some((threshold, buf));
        }
        Ok(occ.bits.as_ref().map(|(_, b)| (occ.grid.resolution as u32, b.clone())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::triplane::SceneBounds;
    use crate::triplane::{Decoder, HIDDEN, N_OUT};

    /// Constant planes and a decoder of constant weights: every bound term is known exactly.
    fn constant(plane: f32, weight: f32) -> Triplane {
        Triplane {
            planes: vec![plane; 3 * N_CHANNELS * 2 * 2],
            height: 2,
            width: 2,
            plane_dtype: PlaneDtype::F32,
            decoder: Decoder {
                w0: vec![weight; HIDDEN * N_CHANNELS],
                b0: vec![0.0; HIDDEN],
                w1: vec![weight; N_OUT * HIDDEN],
                b1: vec![0.0; N_OUT],
            },
            bounds: SceneBounds::default(),
            camera: None,
            occupancy: None,
            source: None,
        }
    }

    #[test]
    fn decoder_range_refuses_planes_that_overflow_float32() {
        // The case: finite planes of 3e38 rendered NaN (the 3-plane sum alone is Inf).
        let e = check_decoder_range(&constant(3e38, 0.1)).unwrap_err().to_string();
        assert!(e.starts_with("planes:") && e.contains("overflow float32"), "{e}");
        // Moderate planes, huge weights: the hidden layer's sums overflow.
        assert!(check_decoder_range(&constant(1.0, 1e37)).is_err());
        // z = 32 * 1e17 * 1e-1 = 3.2e17; o = 64 * 0.1 * (z + 1) = 2.05e17; fine.
        check_decoder_range(&constant(1e17, 0.1)).unwrap();
        // The density's midpoint sum 2 * o_0 is the binding term: o_0 = 64 w (32 w P + 1).
        let w = 1e6f32;
        let p = (f32::MAX as f64 / 2.0 / (64.0 * w as f64 * 32.0 * w as f64)) as f32;
        check_decoder_range(&constant(p * 0.99, w)).unwrap();
        assert!(check_decoder_range(&constant(p * 1.01, w)).is_err());
    }
}
