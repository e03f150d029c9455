//! A render's feature images super-resolved in the render's own command buffers
//! (`Renderer::render_with_superres`): the network's frame and readback for one request.

use super::Renderer;
use crate::error::{Error, Result};
use crate::settings::RenderSettings;
use crate::superres::{SuperRes, SuperresFrame};
use crate::triplane::N_CHANNELS;

/// Refuses a network that cannot read this render's feature images, before any GPU work.
pub(super) fn check(renderer: &Renderer, sr: &SuperRes, settings: &RenderSettings) -> Result<()> {
    if sr.device() != &renderer.device {
        return Err(Error::invalid("superres", "the network lives on another device than the renderer"));
    }
    if sr.in_channels() != N_CHANNELS {
        return Err(Error::invalid(
            "superres",
            format!(
                "the network takes {} channels; a render's feature image has {N_CHANNELS}",
                sr.in_channels()
            ),
        ));
    }
    if settings.resolution as usize != sr.input_resolution() {
        return Err(Error::invalid(
            "resolution",
            format!(
                "the super-resolution network takes {0}² feature images: render at resolution={0}, got {1}",
                sr.input_resolution(),
                settings.resolution
            ),
        ));
    }
    if settings.skips.baked_subdivisions > 0 {
        return Err(Error::invalid(
            "superres",
            "a baked field holds density and RGB only, not the feature image the network reads: \
             set baked_subdivisions=0",
        ));
    }
    Ok(())
}

/// The network's buffers for chunks of up to `images()` cameras, and where its images come back.
pub(super) struct Chain<'a> {
    sr: &'a SuperRes,
    frame: SuperresFrame,
    readback: wgpu::Buffer,
}

impl<'a> Chain<'a> {
    /// Buffers for chunks of at most `chunk` cameras (fewer when the network's frame holds fewer).
    pub(super) fn new(renderer: &Renderer, sr: &'a SuperRes, chunk: usize) -> Result<Chain<'a>> {
        let frame = sr.frame(chunk.min(sr.max_images_per_frame()).max(1))?;
        let readback = renderer.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d superres readback"),
            size: (frame.images() * Self::per_image(sr) * 4) as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(Chain { sr, frame, readback })
    }

    fn per_image(sr: &SuperRes) -> usize {
        3 * sr.output_resolution() * sr.output_resolution()
    }

    /// Cameras per chunk.
    pub(super) fn images(&self) -> usize {
        self.frame.images()
    }

    pub(super) fn floats_per_image(&self) -> usize {
        Self::per_image(self.sr)
    }

    pub(super) fn device_bytes(&self) -> u64 {
        self.frame.device_bytes() + self.readback.size()
    }

    /// Records the network on the chunk's feature images (`features`, as the render left them)
    /// and the copy of its `count` images to the readback.
    pub(super) fn record(&self, encoder: &mut wgpu::CommandEncoder, features: &wgpu::Buffer, count: usize) {
        self.sr.record(encoder, features, &self.frame);
        let bytes = (count * self.floats_per_image() * 4) as u64;
        encoder.copy_buffer_to_buffer(self.frame.output(), 0, &self.readback, 0, bytes);
    }

    /// The readback job of a chunk of `count` cameras from camera `first` into `images`.
    pub(super) fn job<'b>(
        &'b self,
        first: usize,
        count: usize,
        images: &'b mut [f32],
    ) -> (&'b wgpu::Buffer, u64, &'b mut [f32]) {
        let per = self.floats_per_image();
        (&self.readback, (count * per * 4) as u64, &mut images[first * per..(first + count) * per])
    }

    /// Refuses images the network overflowed on (validated weights can still be large enough).
    pub(super) fn check_finite(&self, images: &[f32]) -> Result<()> {
        match images.iter().position(|v| !v.is_finite()) {
            None => Ok(()),
            Some(i) => Err(Error::invalid(
                "superres",
                format!(
                    "the network overflowed float32 on image {} (its weights or the features are too large)",
                    i / self.floats_per_image()
                ),
            )),
        }
    }
}
