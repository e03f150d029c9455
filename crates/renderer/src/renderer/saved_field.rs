//! A baked field read back to be saved (`Renderer::read_baked_values`), and one saved earlier put back
//! on the GPU (`lp3d.render.baked.load_baked` reads the file; `Renderer::attach_baked` checks every
//! array again here before it reaches the GPU).

use super::baking::field_buffer;
use super::*;
use crate::baked::atlas::FineAtlas;
use crate::baked::{BakeSpec, BrickLayout, MAX_FINE_SUBDIVISIONS, POINT_BYTES};

/// Checks a saved field before it is uploaded: `values` holds the coarse bricks' points,
/// `fine_values` a two-level field's fine ones' (empty for one level). Its numbers of coarse and
/// fine bricks.
fn check_saved_field(
    spec: &BakeSpec,
    cells: usize,
    index: &[u32],
    values: &[u16],
    fine_values: &[u16],
) -> Result<(usize, usize)> {
    let k = spec.subdivisions;
    if !(1..=crate::baked::MAX_SUBDIVISIONS).contains(&k) {
        return Err(Error::invalid("subdivisions", format!("must be in [1, 8], got {k}")));
    }
    let kf = spec.fine_subdivisions;
    if kf != 0 && !(kf > k && kf <= MAX_FINE_SUBDIVISIONS) {
        return Err(Error::invalid(
            "fine_subdivisions",
            format!("must be 0 or in (subdivisions, {MAX_FINE_SUBDIVISIONS}], got {kf}"),
        ));
    }
    if kf == 0 && !fine_values.is_empty() {
        return Err(Error::invalid("fine_values", "a one-level field (fine_subdivisions 0) has none"));
    }
    if !(spec.epsilon > 0.0 && spec.epsilon < 1.0 && spec.max_delta.is_finite() && spec.max_delta > 0.0) {
        return Err(Error::invalid("occupancy_epsilon", "must be in (0, 1), with a positive max_delta"));
    }
    if !(1..=crate::occupancy::MAX_RESOLUTION).contains(&cells) || index.len() != cells.pow(3) {
        return Err(Error::invalid(
            "index",
            format!("must be (G, G, G) with G in [1, 512], got {} entries", index.len()),
        ));
    }
    let per_brick = 4 * BrickLayout::points_per_brick(k);
    if values.len() % per_brick != 0 {
        return Err(Error::invalid("values", format!("must be (bricks, {0}, {0}, {0}, 4)", k + 1)));
    }
    let n_coarse = values.len() / per_brick;
    let per_fine = 4 * BrickLayout::points_per_brick(kf);
    if kf != 0 && fine_values.len() % per_fine != 0 {
        return Err(Error::invalid(
            "fine_values",
            format!("must be (fine bricks, {0}, {0}, {0}, 4)", kf + 1),
        ));
    }
    let n_fine = if kf == 0 { 0 } else { fine_values.len() / per_fine };
    // Every brick named by exactly one cell, each level in cell order (as a bake numbers them).
    let named: Vec<u32> = index.iter().copied().filter(|&b| b != crate::baked::EMPTY).collect();
    let coarse = named.iter().filter(|&&b| (b as usize) < n_coarse);
    let fine = named.iter().filter(|&&b| (b as usize) >= n_coarse);
    if named.len() != n_coarse + n_fine
        || coarse.enumerate().any(|(i, &b)| b as usize != i)
        || fine.enumerate().any(|(i, &b)| b as usize != n_coarse + i)
    {
        return Err(Error::invalid(
            "index",
            format!("must name bricks 0..{} once each, each level in cell order", n_coarse + n_fine),
        ));
    }
    // Finite float16 only (exponent 31 is Inf or NaN): the renderer's output stays finite.
    for (name, halves) in [("values", values), ("fine_values", fine_values)] {
        if let Some(i) = halves.iter().position(|&h| (h >> 10) & 0x1f == 0x1f) {
            return Err(Error::invalid(name, format!("NaN or Inf at flat index {i}")));
        }
    }
    Ok((n_coarse, n_fine))
}

impl Renderer {
    /// Attaches a field baked earlier (its `index` and each level's `values` as `read_baked_values` gave them,
    /// e.g. saved and loaded; a two-level field's fine bricks' points in `fine_values`) to `tri`
    /// without baking again. Everything is checked: the caller vouches only that it was baked
    /// from these planes and decoder.
    pub fn attach_baked(
        &self,
        tri: &GpuTriplane,
        spec: BakeSpec,
        cells: usize,
        index: Vec<u32>,
        values: &[u16],
        fine_values: &[u16],
    ) -> Result<Arc<GpuBaked>> {
        let (n_coarse, n_fine) = check_saved_field(&spec, cells, &index, values, fine_values)?;
        self.check_binding("values", "the field", (index.len() * 4 + values.len() * 2) as u64, "")?;
        let words: Vec<u32> = values.chunks(2).map(|h| h[0] as u32 | (h[1] as u32) << 16).collect();
        let (fine_first, fine, data) = match spec.fine_subdivisions {
            0 => (u32::MAX, None, field_buffer(&self.device, &index, Some(&words), words.len())),
            k_f => {
                let atlas = FineAtlas::new(n_fine, k_f, self.limits.max_texture_dimension_3d)?;
                let gpu_index = atlas.gpu_index(&index, n_coarse as u32);
                let data = field_buffer(&self.device, &gpu_index, Some(&words), words.len());
                (n_coarse as u32, Some(self.upload_fine(atlas, fine_values)?), data)
            }
        };
        let baked = Arc::new(GpuBaked {
            spec,
            cells,
            n_bricks: n_coarse + n_fine,
            fine_first,
            data,
            fine,
            index,
            bake_seconds: 0.0,
        });
        *tri.baked.lock().map_err(|_| Error::Gpu("baked field lock poisoned".into()))? = Some(baked.clone());
        Ok(baked)
    }

    /// The points of one level of a baked field, read back as float16 bits (sigma_raw, r, g, b):
    /// the coarse bricks' `n_coarse() * (k + 1)³` (all of a one-level field's), or with `fine` a
    /// two-level field's fine bricks' `(n_bricks - n_coarse()) * (k_f + 1)³`.
    pub fn read_baked_values(&self, baked: &GpuBaked, fine: bool) -> Result<Vec<u16>> {
        if fine {
            let n_fine = baked.n_bricks - baked.n_coarse();
            return baked.fine.as_ref().map_or(Ok(Vec::new()), |f| self.read_fine(f, n_fine));
        }
        let points = baked.n_coarse() * BrickLayout::points_per_brick(baked.spec.subdivisions);
        self.read_halves(&baked.data, baked.values_offset() as u64 * 4, (points * POINT_BYTES) as u64)
    }

    /// `bytes` of `buffer` from byte `offset` on, read back as float16 bits.
    pub(super) fn read_halves(&self, buffer: &wgpu::Buffer, offset: u64, bytes: u64) -> Result<Vec<u16>> {
        self.read_back_halves(bytes, &mut |encoder, read| {
            encoder.copy_buffer_to_buffer(buffer, offset, read, 0, bytes)
        })
    }

    /// `bytes` that `record` copies into a mappable buffer (from a buffer or a texture), read back
    /// as float16 bits.
    pub(super) fn read_back_halves(
        &self,
        bytes: u64,
        record: &mut dyn FnMut(&mut wgpu::CommandEncoder, &wgpu::Buffer),
    ) -> Result<Vec<u16>> {
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let read = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d baked values readback"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("lp3d baked readback") });
        record(&mut encoder, &read);
        self.queue.submit([encoder.finish()]);
        let mut words = vec![0f32; (bytes / 4) as usize];
        self.read_back(&mut [(&read, bytes, &mut words)])?;
        Ok(words
            .iter()
            .flat_map(|w| {
                let b = w.to_bits();
                [(b & 0xffff) as u16, (b >> 16) as u16]
            })
            .collect())
    }
}
