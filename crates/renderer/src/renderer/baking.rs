//! The baked field on the GPU (`crate::baked`, `docs/baked.md`): `Renderer::bake` decodes every
//! brick point once with the `bake_field` kernel, and a render with
//! `Skips::baked_subdivisions` > 0 binds the field and runs render_rays specialised to look
//! samples up in it (`BAKED`). The field lives with its triplane (`GpuTriplane`) and is reused
//! by every render it covers (`BakeSpec::covers`).

use std::time::Instant;

use super::fine_bricks::FineBricks;
use super::layouts::fine_texture;
use super::*;
use crate::baked::atlas::FineAtlas;
use crate::baked::{needs_fine, BakeSpec, BrickLayout, MAX_FINE_SUBDIVISIONS, POINT_BYTES};
use crate::kernel::{build_render_variant, FieldUse};

/// Points per bake dispatch: small enough that a dispatch is short on lavapipe, so a viewer
/// drawing meanwhile waits at most that long for its frame.
pub const BAKE_CHUNK: usize = 1 << 16;

/// A bake's field as it goes to the GPU: the index, the bricks (N) and the first fine one (N_c;
/// `u32::MAX` for one level), the buffer of index and coarse points, the fine bricks' texture.
pub(super) struct Levels {
    pub(super) index: Vec<u32>,
    pub(super) n_bricks: usize,
    pub(super) fine_first: u32,
    pub(super) data: wgpu::Buffer,
    pub(super) fine: Option<FineBricks>,
}

/// One level of a bake: the cells of its bricks (flat indices of the G³ grid) and their k.
pub(super) struct BakePass<'a> {
    pub(super) cells: &'a [u32],
    pub(super) cells_per_axis: usize,
    pub(super) k: u32,
}

/// The baked field's pipelines, each built on first use, and what the bake binds.
pub(super) struct BakedPipelines {
    /// render_rays looking samples up in a baked field (`BAKED`).
    lookup: OnceLock<wgpu::ComputePipeline>,
    /// The bake kernel, with the fast [0] and the quick [1] decoder, and its bindings.
    bake: [OnceLock<wgpu::ComputePipeline>; 2],
    bake_layout: wgpu::BindGroupLayout,
    bake_pipeline_layout: wgpu::PipelineLayout,
    /// Bound in place of a baked field when the render decodes, and of fine bricks when it has none.
    no_baked: wgpu::Buffer,
    no_fine: wgpu::TextureView,
}

impl BakedPipelines {
    pub(super) fn new(
        device: &wgpu::Device,
        bake_layout: wgpu::BindGroupLayout,
        bake_pipeline_layout: wgpu::PipelineLayout,
    ) -> Self {
        Self {
            lookup: OnceLock::new(),
            bake: [OnceLock::new(), OnceLock::new()],
            bake_layout,
            bake_pipeline_layout,
            no_baked: super::layouts::placeholder(device, "lp3d no baked field"),
            no_fine: fine_texture(device, [1, 1, 1], "lp3d no fine bricks")
                .create_view(&wgpu::TextureViewDescriptor::default()),
        }
    }
}

/// A baked field resident on the GPU.
pub struct GpuBaked {
    pub spec: BakeSpec,
    /// Cells per axis, G, and per cell its brick or `baked::EMPTY` (kept on the CPU too).
    pub cells: usize,
    pub index: Vec<u32>,
    pub n_bricks: usize,
    /// Two-level fields: the first fine brick's number (N_c); `u32::MAX` for one level.
    pub fine_first: u32,
    /// Seconds the bake took (brick layout, upload, kernel, wait).
    pub bake_seconds: f64,
    /// The index (G³ words), then the coarse points (two words each): `baked` in `shaders/params.wgsl`.
    pub(super) data: wgpu::Buffer,
    /// A two-level field's fine points (`baked::atlas`): `baked_fine`.
    pub(super) fine: Option<FineBricks>,
}

impl GpuBaked {
    /// Device bytes: the buffer of index and coarse values, and the fine bricks' texture (its unused
    /// slots included).
    pub fn device_bytes(&self) -> u64 {
        self.data.size() + self.fine.as_ref().map_or(0, FineBricks::device_bytes)
    }

    /// Where the points start in `data`, in 4-byte words.
    pub fn values_offset(&self) -> u32 {
        self.index.len() as u32
    }

    /// Bricks at `spec.subdivisions` (all of a one-level field's), N_c.
    pub fn n_coarse(&self) -> usize {
        self.n_bricks.min(self.fine_first as usize)
    }

    /// Points of the field: the coarse bricks', then the fine ones'.
    pub fn n_points(&self) -> usize {
        let fine =
            (self.n_bricks - self.n_coarse()) * BrickLayout::points_per_brick(self.spec.fine_subdivisions);
        self.n_coarse() * BrickLayout::points_per_brick(self.spec.subdivisions) + fine
    }
}

/// The field's buffer as the kernels read it: `index`, then `n_words` words, the first of them
/// `words` (if given), the rest zeros.
pub(super) fn field_buffer(
    dev: &wgpu::Device,
    index: &[u32],
    words: Option<&[u32]>,
    n_words: usize,
) -> wgpu::Buffer {
    let mut contents = Vec::with_capacity((index.len() + n_words).max(2));
    contents.extend_from_slice(index);
    contents.extend_from_slice(words.unwrap_or_default());
    contents.resize(index.len() + n_words, 0);
    contents.resize(contents.len().max(2), 0);
    dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("lp3d baked field"),
        contents: bytemuck::cast_slice(&contents),
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
    })
}

impl GpuTriplane {
    /// The baked field this triplane holds, if any.
    pub fn baked(&self) -> Option<Arc<GpuBaked>> {
        self.baked.lock().ok().and_then(|b| b.clone())
    }
}

impl Renderer {
    /// Bakes `tri`'s field for `spec` on the GPU and keeps it with the triplane (replacing an
    /// older one). Needs the triplane's occupancy grid (`set_occupancy`).
    pub fn bake(&self, tri: &GpuTriplane, spec: BakeSpec) -> Result<Arc<GpuBaked>> {
        self.bake_with_progress(tri, spec, &mut |_, _| true)
    }

    /// [`Renderer::bake`] in dispatches of [`BAKE_CHUNK`] points, each waited for, calling
    /// `progress(points done, points)` after each; returning false stops the bake (an error
    /// naming it). Other work on the device (a viewer's frames) runs between the dispatches. A
    /// two-level field bakes every brick coarse first, reads their values back to find the ones
    /// a surface crosses or that hold a colour edge under one (`baked::needs_fine`), then bakes
    /// those fine (`points` counts every brick as fine until then).
    pub fn bake_with_progress(
        &self,
        tri: &GpuTriplane,
        spec: BakeSpec,
        progress: &mut dyn FnMut(usize, usize) -> bool,
    ) -> Result<Arc<GpuBaked>> {
        let start = Instant::now();
        if !(spec.epsilon > 0.0 && spec.epsilon < 1.0 && spec.max_delta > 0.0) {
            return Err(Error::invalid(
                "occupancy_epsilon",
                format!("a bake needs epsilon in (0, 1), got {}", spec.epsilon),
            ));
        }
        let fine_k = spec.fine_subdivisions;
        if fine_k != 0 && !(fine_k > spec.subdivisions && fine_k <= MAX_FINE_SUBDIVISIONS) {
            return Err(Error::invalid(
                "fine_subdivisions",
                format!("must be 0 or in (subdivisions, {MAX_FINE_SUBDIVISIONS}], got {fine_k}"),
            ));
        }
        let grid = {
            let slot = tri.occupancy.lock().map_err(|_| Error::Gpu("occupancy lock poisoned".into()))?;
            let Some(occ) = slot.as_ref() else {
                return Err(Error::invalid(
                    "baked_subdivisions",
                    "this triplane has no occupancy grid: bake one first (Occupancy::bake)",
                ));
            };
            occ.grid.clone()
        };
        let layout = BrickLayout::new(&grid, &spec, tri.scene.bounds.box_warp)?;
        let per_brick = BrickLayout::points_per_brick(spec.subdivisions);
        let n_points = layout.brick_cells.len() * per_brick;
        let value_bytes = (n_points * POINT_BYTES + layout.index.len() * 4) as u64;
        self.check_binding(
            "baked_subdivisions",
            "the baked field",
            value_bytes,
            ": use fewer subdivisions or a larger occupancy_epsilon",
        )?;
        let index_words = layout.index.len() as u32;
        let data = field_buffer(&self.device, &layout.index, None, n_points * 2);
        let pass =
            BakePass { cells: &layout.brick_cells, cells_per_axis: layout.cells, k: spec.subdivisions };
        // Until the fine bricks are known, a two-level bake counts every brick as fine: its total
        // only falls, so the share done only rises.
        let at_most = n_points
            + (fine_k > 0) as usize * layout.brick_cells.len() * BrickLayout::points_per_brick(fine_k);
        self.run_bake(tri, &pass, index_words, &data, &mut |done| progress(done, at_most))?;
        if fine_k == 0 {
            let levels = Levels {
                index: layout.index,
                n_bricks: layout.brick_cells.len(),
                fine_first: u32::MAX,
                data,
                fine: None,
            };
            return self.keep_baked(tri, spec, layout.cells, levels, start);
        }

        let one_level = GpuBaked {
            spec: BakeSpec { fine_subdivisions: 0, ..spec },
            cells: layout.cells,
            index: layout.index.clone(),
            n_bricks: layout.brick_cells.len(),
            fine_first: u32::MAX,
            bake_seconds: 0.0,
            data,
            fine: None,
        };
        self.bake_second_level(tri, spec, &layout, one_level, &mut |done, fine_points| {
            progress(n_points + done, n_points + fine_points)
        })
        .and_then(|levels| self.keep_baked(tri, spec, layout.cells, levels, start))
    }

    /// A two-level field's second level: reads the coarse bake `one_level` back, finds the bricks a
    /// surface crosses or that hold a colour edge under one (`baked::needs_fine`), keeps the other
    /// bricks' coarse points in a new buffer and bakes those at `spec.fine_subdivisions` into a texture (`baked::atlas`).
    /// `progress(fine points done, fine points)`.
    fn bake_second_level(
        &self,
        tri: &GpuTriplane,
        spec: BakeSpec,
        layout: &BrickLayout,
        one_level: GpuBaked,
        progress: &mut dyn FnMut(usize, usize) -> bool,
    ) -> Result<Levels> {
        let per_brick = BrickLayout::points_per_brick(spec.subdivisions);
        let halves = self.read_baked_values(&one_level, false)?;
        drop(one_level);
        let is_fine: Vec<bool> = halves
            .chunks(4 * per_brick)
            .map(|brick| {
                needs_fine(
                    brick.chunks(4).map(|p| std::array::from_fn(|c| half::f16::from_bits(p[c]).to_f32())),
                )
            })
            .collect();
        let two = layout.two_level(&is_fine);
        let n_coarse = two.coarse_bricks.len();
        let atlas = FineAtlas::new(
            two.fine_cells.len(),
            spec.fine_subdivisions,
            self.limits.max_texture_dimension_3d,
        )?;
        let coarse_words: Vec<u32> = two
            .coarse_bricks
            .iter()
            .flat_map(|&b| {
                let at = b as usize * per_brick * 4;
                halves[at..at + per_brick * 4].chunks(2).map(|h| h[0] as u32 | (h[1] as u32) << 16)
            })
            .collect();
        drop(halves);
        let gpu_index = atlas.gpu_index(&two.index, n_coarse as u32);
        let data = field_buffer(&self.device, &gpu_index, Some(&coarse_words), coarse_words.len());
        let pass =
            BakePass { cells: &two.fine_cells, cells_per_axis: layout.cells, k: spec.fine_subdivisions };
        let fine_values = self.bake_to_host(tri, &pass, progress)?;
        let fine = self.upload_fine(atlas, &fine_values)?;
        Ok(Levels {
            n_bricks: n_coarse + two.fine_cells.len(),
            fine_first: n_coarse as u32,
            index: two.index,
            data,
            fine: Some(fine),
        })
    }

    /// Records a finished bake with its triplane.
    fn keep_baked(
        &self,
        tri: &GpuTriplane,
        spec: BakeSpec,
        cells: usize,
        levels: Levels,
        start: Instant,
    ) -> Result<Arc<GpuBaked>> {
        let baked = Arc::new(GpuBaked {
            spec,
            cells,
            index: levels.index,
            n_bricks: levels.n_bricks,
            fine_first: levels.fine_first,
            bake_seconds: start.elapsed().as_secs_f64(),
            data: levels.data,
            fine: levels.fine,
        });
        *tri.baked.lock().map_err(|_| Error::Gpu("baked field lock poisoned".into()))? = Some(baked.clone());
        Ok(baked)
    }

    /// Decodes every point of `pass`'s bricks into `data`, from word `values_offset` on, in
    /// dispatches of [`BAKE_CHUNK`] points; `progress(points done)` after each (false stops).
    // Long because: one error scope covers every buffer and dispatch of the pass, so that a
    // device that runs out reports it once, as the bake's error.
    pub(super) fn run_bake(
        &self,
        tri: &GpuTriplane,
        pass: &BakePass,
        values_offset: u32,
        data: &wgpu::Buffer,
        progress: &mut dyn FnMut(usize) -> bool,
    ) -> Result<()> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let dev = &self.device;
        let n_points = pass.cells.len() * BrickLayout::points_per_brick(pass.k);
        let padded: &[u32] = if pass.cells.is_empty() { &[0] } else { pass.cells };
        let cells_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d bake cells"),
            contents: bytemuck::cast_slice(padded),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let mut params = Params::new(&tri.scene, &RenderSettings::default(), 3, 1);
        if tri.half {
            params.flags |= FLAG_HALF_PLANES;
        }
        params.baked_cells = pass.cells_per_axis as u32;
        params.baked_subdivisions = pass.k;
        params.baked_values_offset = values_offset;
        let params_buf = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d bake params"),
            size: std::mem::size_of::<Params>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let group = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("lp3d bake bind group"),
            layout: &self.baked.bake_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: params_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: tri.planes.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: tri.decoder.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 11, resource: cells_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 12, resource: data.as_entire_binding() },
            ],
        });
        if let Some(e) = pollster::block_on(oom.pop()) {
            return Err(Error::Gpu(format!("out of device memory allocating the baked field: {e}")));
        }
        let kernel = self.decoding_kernel();
        let mut done = 0;
        while done < n_points {
            let count = BAKE_CHUNK.min(n_points - done);
            params.camera_offset = done as u32;
            self.queue.write_buffer(&params_buf, 0, bytemuck::bytes_of(&params));
            let groups = count.div_ceil(WORKGROUP as usize) as u32;
            let gx = groups.min(self.limits.max_compute_workgroups_per_dimension);
            let gy = groups.div_ceil(gx);
            let mut encoder =
                dev.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("lp3d bake") });
            {
                let mut cpass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("lp3d bake pass"),
                    timestamp_writes: None,
                });
                cpass.set_pipeline(self.bake_pipeline(kernel));
                cpass.set_bind_group(0, &group, &[]);
                cpass.dispatch_workgroups(gx, gy, 1);
            }
            self.queue.submit([encoder.finish()]);
            self.device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| Error::Gpu(format!("waiting for the bake failed: {e}")))?;
            done += count;
            if !progress(done) {
                let _ = pollster::block_on(scope.pop());
                return Err(Error::invalid("bake", "stopped before it finished"));
            }
        }
        self.check(scope, "baking the field")?;
        if kernel == Kernel::Fast {
            self.record_fast_kernel(1);
        }
        Ok(())
    }

    /// The baked field a render with `settings` uses: the triplane's, when it covers them, else
    /// a new bake; `None` when the settings do not ask for one.
    pub(super) fn baked_for(
        &self,
        tri: &GpuTriplane,
        settings: &RenderSettings,
    ) -> Result<Option<Arc<GpuBaked>>> {
        let k = settings.skips.baked_subdivisions;
        if k == 0 {
            return Ok(None);
        }
        let need = BakeSpec {
            subdivisions: k,
            fine_subdivisions: settings.skips.baked_fine_subdivisions,
            epsilon: settings.skips.occupancy_epsilon,
            max_delta: settings.max_interval(tri.scene.bounds.ray_start, tri.scene.bounds.ray_end),
        };
        if let Some(b) = tri.baked().filter(|b| b.spec.covers(&need)) {
            return Ok(Some(b));
        }
        self.bake(tri, need).map(Some)
    }

    /// render_rays with the baked lookup (`BAKED`), built on first use; the rolled decoder,
    /// which this pipeline never runs, keeps its compile short.
    pub(super) fn baked_pipeline(&self) -> &wgpu::ComputePipeline {
        self.baked.lookup.get_or_init(|| {
            build_render_variant(
                &self.device,
                &self.module,
                &self.pipeline_layout,
                Kernel::Quick,
                FieldUse::Lookup,
            )
        })
    }

    /// The kernel exact renders use now (`Renderer::render_pipeline`, which takes a finished
    /// background compile): the bake kernel uses its decoder (`bake_pipeline`).
    fn decoding_kernel(&self) -> Kernel {
        let quick = self.quick_pipeline.as_ref().is_some_and(|q| std::ptr::eq(q, self.render_pipeline()));
        if quick {
            Kernel::Quick
        } else {
            Kernel::Fast
        }
    }

    /// The bake kernel with `kernel`'s decoder (`decoding_kernel`: that of the kernel the exact
    /// renders use when a bake pass starts), built on first use. On lavapipe the unrolled decoder
    /// bakes quicker (docs/performance.md, "Bake time and size"), and
    /// `KernelChoice::Auto`'s background compile has compiled it by the time the fast kernel
    /// serves; until then the rolled one, whose compile is short.
    fn bake_pipeline(&self, kernel: Kernel) -> &wgpu::ComputePipeline {
        self.baked.bake[(kernel == Kernel::Quick) as usize].get_or_init(|| {
            let rolled = if kernel == Kernel::Quick { 1.0 } else { 0.0 };
            self.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(match kernel {
                    Kernel::Fast => "lp3d bake_field (fast kernel's decoder)",
                    Kernel::Quick => "lp3d bake_field (quick kernel's decoder)",
                }),
                layout: Some(&self.baked.bake_pipeline_layout),
                module: &self.module,
                entry_point: Some(shaders::BAKE_ENTRY),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &[("ROLLED_DECODER", rolled)],
                    ..Default::default()
                },
                cache: None,
            })
        })
    }

    /// What is bound at the baked field's bindings (9, 10): the field's buffer and its fine
    /// bricks' texture, or placeholders.
    pub(super) fn baked_binding<'a>(
        &'a self,
        baked: Option<&'a GpuBaked>,
    ) -> (&'a wgpu::Buffer, &'a wgpu::TextureView) {
        let fine = baked.and_then(|b| b.fine.as_ref()).map_or(&self.baked.no_fine, |f| &f.view);
        (baked.map_or(&self.baked.no_baked, |b| &b.data), fine)
    }
}
