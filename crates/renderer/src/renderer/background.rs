//! The background half of `KernelChoice::Auto` on lavapipe: the fast kernel compiled on a
//! device and thread of its own while the quick kernel serves, and the marker that tells later
//! processes it is in Mesa's shader cache.

use super::*;
use crate::kernel::write_marker;
use crate::triplane::SceneBounds;

/// Starts [`compile_fast_kernel`] on its own thread.
pub(super) fn spawn_fast_kernel_compile(
    adapter: String,
    marker: Option<std::path::PathBuf>,
) -> Result<JoinHandle<Result<()>>> {
    std::thread::Builder::new()
        .name("lp3d kernel compile".into())
        .spawn(move || compile_fast_kernel(&adapter, marker.as_deref()))
        .map_err(|e| Error::Gpu(format!("starting the background kernel compile failed: {e}")))
}

/// The background half of `KernelChoice::Auto`: compiles the fast kernel on a device of its
/// own (lavapipe JIT-compiles a pipeline at its first dispatch, on the queue that runs it, so
/// compiling on the renderer's own device would stall its renders for the whole compile) with
/// one one-ray render, and the bake kernel with its decoder with a bake of a few points, which
/// leaves both compiled in Mesa's on-disk shader cache. The device is dropped before returning,
/// which flushes that cache, so the renderer's own first dispatches of them then load them
/// instead of compiling them. (With Mesa's cache disabled, those dispatches compile them again,
/// once.)
fn compile_fast_kernel(adapter: &str, marker: Option<&std::path::Path>) -> Result<()> {
    let ctx = GpuContext::headless()?;
    if ctx.adapter_info.name != adapter {
        return Err(Error::Gpu(format!(
            "the background kernel compile found adapter {:?}, not {adapter:?}",
            ctx.adapter_info.name
        )));
    }
    let renderer = Renderer::with_kernel(&ctx, KernelChoice::Fast)?;
    // The marker is written below, after the device is gone, not by this render.
    if let Ok(mut m) = renderer.marker.lock() {
        *m = None;
    }
    let mut tri = Triplane {
        planes: vec![0.0; 3 * N_CHANNELS * 2 * 2],
        height: 2,
        width: 2,
        plane_dtype: PlaneDtype::F32,
        decoder: crate::triplane::Decoder {
            w0: vec![0.0; crate::triplane::HIDDEN * N_CHANNELS],
            b0: vec![0.0; crate::triplane::HIDDEN],
            w1: vec![0.0; crate::triplane::N_OUT * crate::triplane::HIDDEN],
            // Dense everywhere, so that the bake below has bricks to decode.
            b1: [vec![20.0], vec![0.0; crate::triplane::N_OUT - 1]].concat(),
        },
        bounds: SceneBounds::default(),
        camera: None,
        occupancy: None,
        source: None,
    };
    tri.occupancy = Some(crate::Occupancy::bake(&tri, 2)?);
    let gpu = renderer.upload(&tri)?;
    let camera = Camera::lookat_pose(
        std::f64::consts::FRAC_PI_2,
        std::f64::consts::FRAC_PI_2,
        crate::camera::FFHQ_RADIUS,
        [0.0, 0.0, 0.0],
        crate::camera::FFHQ_FOCAL,
    );
    let settings = RenderSettings { resolution: 1, ..Default::default() };
    renderer.render(&gpu, &[camera], &settings, Outputs::ALL)?;
    let max_delta = settings.max_interval(tri.bounds.ray_start, tri.bounds.ray_end);
    renderer
        .bake(&gpu, crate::BakeSpec { subdivisions: 1, fine_subdivisions: 0, epsilon: 1e-4, max_delta })?;
    // Drop the device (flushing Mesa's cache writes) before the marker says it is cached.
    drop((gpu, renderer, ctx));
    if let Some(path) = marker {
        write_marker(path);
    }
    Ok(())
}

impl Renderer {
    /// Notes that `pipeline` (0: the fast render kernel, 1: the bake with its decoder) has run,
    /// so is in Mesa's shader cache; once both have, records it (once). Best effort: without the
    /// marker, the next process only takes the slower `Auto` start.
    pub(super) fn record_fast_kernel(&self, pipeline: usize) {
        self.fast_ran[pipeline].store(true, Ordering::Relaxed);
        if !self.fast_ran.iter().all(|r| r.load(Ordering::Relaxed)) {
            return;
        }
        if let Some(path) = self.marker.lock().ok().and_then(|mut m| m.take()) {
            write_marker(&path);
        }
    }
}
