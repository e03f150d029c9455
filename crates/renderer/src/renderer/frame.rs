//! One render request's GPU side: validating it, splitting its cameras into dispatches that
//! fit a storage binding, allocating its buffers and bind group (`prepare`), and recording
//! each chunk's dispatches (`encode_chunk`), then checking the dispatch (`check`) and reading
//! the results back (`read_back`).

use super::*;
use crate::gpu_types::FLAG_FULL_WALK;

/// `LP3D_FULL_WALK` (`Renderer::new`): `1` walks every sample, `0` or unset ends a walk where
/// nothing left can change an output (the default); anything else is an error naming it.
pub(super) fn full_walk_from_env() -> Result<bool> {
    match std::env::var("LP3D_FULL_WALK").ok().as_deref() {
        None | Some("") | Some("0") => Ok(false),
        Some("1") => Ok(true),
        Some(other) => Err(Error::invalid("LP3D_FULL_WALK", format!("must be 0 or 1, got {other:?}"))),
    }
}

impl Renderer {
    /// Walk every sample of every ray (`true`), or end a walk once its transmittance is too small
    /// for anything left to change an output's float32 sums (`false`, the default; exact early
    /// termination, `docs/numerics.md`). The outputs are the same bits either way: this is for
    /// the tests and benchmarks that compare the two. `Renderer::new` reads `LP3D_FULL_WALK`.
    pub fn set_full_walk(&self, on: bool) {
        self.full_walk.store(on, Ordering::Relaxed);
    }

    /// How many cameras one dispatch renders: the batch is split so each dispatch's outputs
    /// (`fc` feature channels and `n_pix` pixels per camera) fit one storage binding.
    pub(super) fn cameras_per_dispatch(&self, fc: usize, n_pix: usize, n_cam: usize) -> Result<usize> {
        let max_binding = self.max_binding_bytes() as usize;
        let per_cam = (fc.max(1) * n_pix * 4).max(1);
        if per_cam > max_binding {
            return Err(Error::invalid(
                "resolution",
                format!("one image's outputs ({} MiB) exceed the device's buffer limit", per_cam >> 20),
            ));
        }
        Ok((max_binding / per_cam).clamp(1, n_cam))
    }

    /// Validates a render request and allocates its buffers and bind group.
    // Long because: every buffer of a frame is made inside one out-of-memory error scope, so
    // that a device that runs out reports it once, as this frame's error.
    pub(super) fn prepare(
        &self,
        tri: &GpuTriplane,
        cameras: &[Camera],
        settings: &RenderSettings,
        outputs: Outputs,
    ) -> Result<Frame> {
        settings.validate()?;
        if cameras.is_empty() || cameras.len() > MAX_CAMERAS {
            return Err(Error::invalid(
                "camera",
                format!("batch size must be in [1, {MAX_CAMERAS}], got {}", cameras.len()),
            ));
        }
        let n_cam = cameras.len();
        let r = settings.resolution as usize;
        let n_pix = r * r;
        let fc = outputs.feature_channels() as usize;
        let mut params = Params::new(&tri.scene, settings, fc as u32, n_cam as u32);
        if tri.half {
            params.flags |= FLAG_HALF_PLANES;
        }
        if self.full_walk.load(Ordering::Relaxed) {
            params.flags |= FLAG_FULL_WALK;
        }
        let occupancy = self.occupancy_bits(tri, settings)?;
        if let Some((g, _)) = &occupancy {
            params.occupancy_resolution = *g;
        }
        if settings.skips.baked_subdivisions > 0 && fc == N_CHANNELS {
            return Err(Error::invalid(
                "outputs",
                "a baked field holds density and RGB only: ask for rgb, depth or weights_sum, or \
                 render without baked_subdivisions for the 32 features",
            ));
        }
        let baked = self.baked_for(tri, settings)?;
        if let Some(b) = &baked {
            params.baked_subdivisions = b.spec.subdivisions;
            params.baked_cells = b.cells as u32;
            params.baked_values_offset = b.values_offset();
            params.baked_fine_subdivisions = b.spec.fine_subdivisions;
        }
        let (baked_buffer, baked_fine) = self.baked_binding(baked.as_deref());

        let chunk = self.cameras_per_dispatch(fc, n_pix, n_cam)?;

        let oom_scope = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let dev = &self.device;
        let storage = |label: &str, size: usize| {
            dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (size.max(1) * 4) as u64,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        let labels: Vec<f32> = cameras.iter().flat_map(|c| c.0).collect();
        let camera_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d cameras (B, 25)"),
            contents: bytemuck::cast_slice(&labels),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let params_buf = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d params"),
            size: std::mem::size_of::<Params>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bounds_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d depth bounds"),
            contents: bytemuck::cast_slice(&[f32::INFINITY.to_bits(), 0u32]),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let features = storage("lp3d features out", chunk * fc * n_pix);
        let depth = storage("lp3d depth out", chunk * n_pix);
        let weights_sum = storage("lp3d weights_sum out", chunk * n_pix);
        let bind_group = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("lp3d render bind group"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: params_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: camera_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: tri.planes.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: tri.decoder.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: features.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 5, resource: depth.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 6, resource: weights_sum.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 7, resource: bounds_buf.as_entire_binding() },
                wgpu::BindGroupEntry {
                    binding: 8,
                    resource: occupancy.as_ref().map_or(&self.no_occupancy, |(_, b)| b).as_entire_binding(),
                },
                wgpu::BindGroupEntry { binding: 9, resource: baked_buffer.as_entire_binding() },
                wgpu::BindGroupEntry {
                    binding: 10,
                    resource: wgpu::BindingResource::TextureView(baked_fine),
                },
            ],
        });
        let bytes = [&camera_buf, &params_buf, &bounds_buf, &features, &depth, &weights_sum]
            .iter()
            .map(|b| b.size())
            .sum();
        if let Some(e) = pollster::block_on(oom_scope.pop()) {
            return Err(Error::Gpu(format!("out of device memory allocating render buffers: {e}")));
        }
        Ok(Frame {
            params,
            params_buf,
            bind_group,
            features,
            depth,
            weights_sum,
            n_cam,
            n_pix,
            fc,
            chunk,
            bytes,
        })
    }

    /// Records the dispatches for cameras `first..first + count` of a prepared frame (the
    /// batch-global depth bounds pass runs with the first chunk).
    pub(super) fn encode_chunk(&self, frame: &mut Frame, first: usize, count: usize) -> wgpu::CommandEncoder {
        frame.params.camera_offset = first as u32;
        self.queue.write_buffer(&frame.params_buf, 0, bytemuck::bytes_of(&frame.params));
        let groups_x = (frame.n_pix as u32).div_ceil(WORKGROUP);
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("lp3d render") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("lp3d render pass"),
                timestamp_writes: None,
            });
            pass.set_bind_group(0, &frame.bind_group, &[]);
            if first == 0 {
                // Batch-global depth range first: render_rays clamps against it.
                pass.set_pipeline(&self.bounds_pipeline);
                if frame.params.flags & FLAG_JITTER != 0 {
                    pass.dispatch_workgroups(groups_x, frame.n_cam as u32, 1);
                } else {
                    // Every ray has the same coarse depths: the shader reads the first one's.
                    pass.dispatch_workgroups(1, 1, 1);
                }
            }
            if frame.params.baked_subdivisions > 0 {
                pass.set_pipeline(self.baked_pipeline());
            } else {
                pass.set_pipeline(self.render_pipeline());
            }
            pass.dispatch_workgroups(groups_x, count as u32, 1);
        }
        encoder
    }
}

impl Renderer {
    /// Pops a validation scope and reports any error wgpu raised meanwhile.
    pub(super) fn check(&self, scope: wgpu::ErrorScopeGuard, what: &str) -> Result<()> {
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("{what} failed: {e}")));
        }
        if let Some(e) = self.uncaptured.lock().ok().and_then(|mut s| s.take()) {
            return Err(Error::Gpu(e));
        }
        Ok(())
    }

    /// Maps readback buffers and copies `bytes` of each into its destination.
    pub(super) fn read_back(&self, jobs: &mut [(&wgpu::Buffer, u64, &mut [f32])]) -> Result<()> {
        let status = Arc::new(Mutex::new(Vec::new()));
        for (buf, bytes, _) in jobs.iter() {
            let status = status.clone();
            buf.map_async(wgpu::MapMode::Read, 0..*bytes, move |r| {
                if let Ok(mut s) = status.lock() {
                    s.push(r.map_err(|e| e.to_string()));
                }
            });
        }
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| Error::Gpu(format!("waiting for the GPU failed: {e}")))?;
        if let Some(Err(e)) = status.lock().ok().and_then(|s| s.iter().find(|r| r.is_err()).cloned()) {
            return Err(Error::Gpu(format!("reading results back failed: {e}")));
        }
        for (buf, bytes, dst) in jobs.iter_mut() {
            {
                let view = buf
                    .get_mapped_range(0..*bytes)
                    .map_err(|e| Error::Gpu(format!("mapping results failed: {e}")))?;
                dst.copy_from_slice(bytemuck::cast_slice(&view));
            }
            buf.unmap();
        }
        Ok(())
    }
}
