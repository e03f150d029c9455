//! The bind-group and pipeline layouts every render entry point shares.

use super::*;

fn storage_entry(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

fn uniform_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// The bind-group and pipeline layouts: the render bindings (shared by every entry point) and
/// the present pass's, which adds the display texture.
pub(super) struct Layouts {
    pub(super) render: wgpu::BindGroupLayout,
    pub(super) render_pipeline_layout: wgpu::PipelineLayout,
    pub(super) present: wgpu::BindGroupLayout,
    pub(super) present_pipeline_layout: wgpu::PipelineLayout,
    /// The bake kernel's: params, planes, decoder, the bricks' cells and the values it writes.
    pub(super) bake: wgpu::BindGroupLayout,
    pub(super) bake_pipeline_layout: wgpu::PipelineLayout,
}

impl Layouts {
    pub(super) fn new(device: &wgpu::Device) -> Layouts {
        let render = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("lp3d render bindings"),
            entries: &[
                uniform_entry(0),
                storage_entry(1, true),
                storage_entry(2, true),
                uniform_entry(3),
                storage_entry(4, false),
                storage_entry(5, false),
                storage_entry(6, false),
                storage_entry(7, false),
                storage_entry(8, true),
                storage_entry(9, true),
                wgpu::BindGroupLayoutEntry {
                    binding: 10,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: false },
                        view_dimension: wgpu::TextureViewDimension::D3,
                        multisampled: false,
                    },
                    count: None,
                },
            ],
        });
        let render_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lp3d render pipeline layout"),
            bind_group_layouts: &[Some(&render)],
            immediate_size: 0,
        });
        let present = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("lp3d present bindings"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::StorageTexture {
                        access: wgpu::StorageTextureAccess::WriteOnly,
                        format: DISPLAY_FORMAT,
                        view_dimension: wgpu::TextureViewDimension::D2,
                    },
                    count: None,
                },
                uniform_entry(1),
            ],
        });
        let present_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lp3d present pipeline layout"),
            bind_group_layouts: &[Some(&render), Some(&present)],
            immediate_size: 0,
        });
        let bake = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("lp3d bake bindings"),
            entries: &[
                uniform_entry(0),
                storage_entry(2, true),
                uniform_entry(3),
                storage_entry(11, true),
                storage_entry(12, false),
            ],
        });
        let bake_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lp3d bake pipeline layout"),
            bind_group_layouts: &[Some(&bake)],
            immediate_size: 0,
        });
        Layouts {
            render,
            render_pipeline_layout,
            present,
            present_pipeline_layout,
            bake,
            bake_pipeline_layout,
        }
    }
}

/// The format of a two-level baked field's fine bricks (`baked::atlas`): a point per texel, its
/// four float16 as the field's buffer stores them.
pub(super) const FINE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;

/// A small storage buffer bound where a render uses no occupancy bits or baked field (a binding
/// needs a buffer; 16 bytes covers the largest element the kernels declare there).
pub(super) fn placeholder(device: &wgpu::Device, label: &str) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: 16,
        usage: wgpu::BufferUsages::STORAGE,
        mapped_at_creation: false,
    })
}

/// A 3D texture of `extent` texels for a two-level field's fine bricks (or, 1³, bound where a
/// render has none).
pub(super) fn fine_texture(device: &wgpu::Device, extent: [u32; 3], label: &str) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d { width: extent[0], height: extent[1], depth_or_array_layers: extent[2] },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D3,
        format: FINE_FORMAT,
        usage: wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_DST
            | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}
