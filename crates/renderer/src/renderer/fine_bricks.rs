//! A two-level baked field's fine bricks on the GPU (`crate::baked::atlas`): baked in passes that
//! each fit a storage binding, gathered on the host, and written into one 3D texture, which the
//! lookup reads (`baked_fine` in `shaders/params.wgsl`).

use super::baking::BakePass;
use super::layouts::fine_texture;
use super::*;
use crate::baked::atlas::FineAtlas;
use crate::baked::{BrickLayout, POINT_BYTES};

/// A two-level field's fine bricks: their texture and where each sits in it.
pub(super) struct FineBricks {
    atlas: FineAtlas,
    texture: wgpu::Texture,
    pub(super) view: wgpu::TextureView,
}

impl FineBricks {
    /// Device bytes of the texture (its unused slots included).
    pub(super) fn device_bytes(&self) -> u64 {
        self.atlas.extent().iter().map(|&e| e as u64).product::<u64>() * POINT_BYTES as u64
    }
}

impl Renderer {
    /// Decodes every point of `pass`'s bricks and returns them as float16 bits (four per point,
    /// brick after brick), baking as many bricks at a time as a storage binding holds.
    /// `progress(points done, points)`.
    pub(super) fn bake_to_host(
        &self,
        tri: &GpuTriplane,
        pass: &BakePass,
        progress: &mut dyn FnMut(usize, usize) -> bool,
    ) -> Result<Vec<u16>> {
        let per_brick = BrickLayout::points_per_brick(pass.k);
        let total = pass.cells.len() * per_brick;
        let bricks_per_pass = (self.max_binding_bytes() as usize / (per_brick * POINT_BYTES)).max(1);
        let scratch_points = per_brick * bricks_per_pass.min(pass.cells.len()).max(1);
        let scratch = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d fine bricks scratch"),
            size: (scratch_points * POINT_BYTES) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let mut out = Vec::with_capacity(total * 4);
        for cells in pass.cells.chunks(bricks_per_pass) {
            let done_before = out.len() / 4;
            let part = BakePass { cells, cells_per_axis: pass.cells_per_axis, k: pass.k };
            self.run_bake(tri, &part, 0, &scratch, &mut |done| progress(done_before + done, total))?;
            out.extend(self.read_halves(&scratch, 0, (cells.len() * per_brick * POINT_BYTES) as u64)?);
        }
        Ok(out)
    }

    /// Writes fine bricks' points (`bake_to_host`'s layout) into a new texture laid out by `atlas`.
    pub(super) fn upload_fine(&self, atlas: FineAtlas, fine_values: &[u16]) -> Result<FineBricks> {
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let extent = atlas.extent();
        let texture = fine_texture(&self.device, extent, "lp3d baked fine bricks");
        let texels = atlas.texels_from_bricks(fine_values, extent[0] as usize);
        self.queue.write_texture(
            texture.as_image_copy(),
            bytemuck::cast_slice(&texels),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(extent[0] * POINT_BYTES as u32),
                rows_per_image: Some(extent[1]),
            },
            wgpu::Extent3d { width: extent[0], height: extent[1], depth_or_array_layers: extent[2] },
        );
        if let Some(e) = pollster::block_on(oom.pop()) {
            return Err(Error::Gpu(format!("out of device memory for the fine bricks: {e}")));
        }
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        Ok(FineBricks { atlas, texture, view })
    }

    /// The first `n_bricks` fine bricks' points read back from their texture, in
    /// `bake_to_host`'s layout.
    pub(super) fn read_fine(&self, fine: &FineBricks, n_bricks: usize) -> Result<Vec<u16>> {
        let [w, h, d] = fine.atlas.extent();
        let row_bytes = (w * POINT_BYTES as u32).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT);
        let bytes = row_bytes as u64 * h as u64 * d as u64;
        let texels = self.read_back_halves(bytes, &mut |encoder, read| {
            encoder.copy_texture_to_buffer(
                fine.texture.as_image_copy(),
                wgpu::TexelCopyBufferInfo {
                    buffer: read,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(row_bytes),
                        rows_per_image: Some(h),
                    },
                },
                wgpu::Extent3d { width: w, height: h, depth_or_array_layers: d },
            )
        })?;
        Ok(fine.atlas.bricks_from_texels(&texels, row_bytes as usize / POINT_BYTES, n_bricks))
    }
}
