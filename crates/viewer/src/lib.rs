//! `lp3d-view`: an egui/eframe viewer for EG3D-format triplanes. It renders with the same
//! `lp3d-renderer` kernels as Python and the tests, on eframe's wgpu device. A library (so tests
//! and the Python module can start it) plus a thin `main.rs`.

mod app;
mod bake;
mod options;
mod orbit;
mod quality;
mod screenshot;

use std::sync::{Arc, Mutex};

pub use options::{ViewerOptions, USAGE};
pub use orbit::Orbit;

use eframe::egui_wgpu::{WgpuSetup, WgpuSetupCreateNew};
use lp3d_renderer::{SuperresWeights, Triplane};

/// Opens the viewer window and blocks until it is closed. In `--screenshot` mode, renders until
/// the final quality is on screen (after the scripted drag of `--drag-frames`, if any), saves the
/// window PNG, the render PNG and a JSON sidecar, and returns. Must run on the main thread.
pub fn run(options: ViewerOptions) -> Result<(), String> {
    options.validate()?;
    // Load before opening a window, so a bad file is a clear error and a non-zero exit.
    let triplane = match &options.path {
        Some(p) => Some((p.clone(), Triplane::load(p).map_err(|e| e.to_string())?)),
        None => None,
    };
    let superres = match &options.superres {
        Some(p) => Some((p.clone(), SuperresWeights::load(p).map_err(|e| e.to_string())?)),
        None => None,
    };
    let outcome: app::Outcome = Arc::new(Mutex::new(None));
    let native = eframe::NativeOptions {
        viewport: eframe::egui::ViewportBuilder::default()
            .with_title("lp3d-view")
            .with_inner_size([920.0, 700.0]),
        renderer: eframe::Renderer::Wgpu,
        // Dithering adds noise math to every pixel egui paints (lavapipe shades them on the CPU), for
        // banding that an 8-bit render upscaled does not show. With the unfilled panels (app/panel.rs) it
        // shortens each drag frame (bench/history/RESULTS.md, "The window's own time").
        dithering: false,
        wgpu_options: eframe::WgpuConfiguration { wgpu_setup: device_setup(), ..Default::default() },
        ..Default::default()
    };
    let app_outcome = outcome.clone();
    let opts = options.clone();
    eframe::run_native(
        "lp3d-view",
        native,
        Box::new(move |cc| {
            let app = app::ViewerApp::new(cc, &opts, triplane, superres, app_outcome)?;
            Ok(Box::new(app))
        }),
    )
    .map_err(|e| format!("could not open the viewer window: {e}"))?;
    if options.screenshot.is_some() {
        return match outcome.lock().ok().and_then(|mut o| o.take()) {
            Some(Ok(_)) => Ok(()),
            Some(Err(e)) => Err(format!("saving the screenshot failed: {e}")),
            None => Err("the window closed before the screenshot was taken".into()),
        };
    }
    Ok(())
}

/// eframe's wgpu device, asking for what the adapter offers (as `GpuContext::headless` does), so
/// that planes and baked fields may use buffers beyond WebGPU's default limits where the adapter
/// allows them.
fn device_setup() -> WgpuSetup {
    let mut setup = WgpuSetupCreateNew::without_display_handle();
    setup.device_descriptor = Arc::new(|adapter| wgpu::DeviceDescriptor {
        label: Some("lp3d-view device"),
        required_limits: adapter.limits(),
        ..Default::default()
    });
    WgpuSetup::CreateNew(setup)
}
