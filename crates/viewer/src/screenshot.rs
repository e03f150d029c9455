//! Saving the window as PNG, with a JSON sidecar that says where the 3D view is, so tests and
//! scripts can crop it and compare it with `lp3d_render.render` of the same camera.

use std::io::Write;
use std::path::{Path, PathBuf};

use eframe::egui;

/// The 3D view's place in the window image, in physical pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewRect {
    pub x: u32,
    pub y: u32,
    /// Side of the view in pixels: `resolution * scale`.
    pub size: u32,
    /// Pixels per ray (nearest-neighbour magnification).
    pub scale: u32,
    pub resolution: u32,
    pub yaw: f64,
    pub pitch: f64,
}

pub fn save_screenshot(path: &Path, image: &egui::ColorImage, view: &ViewRect) -> Result<PathBuf, String> {
    let [w, h] = image.size;
    let rgba: Vec<u8> = image.pixels.iter().flat_map(|p| p.to_array()).collect();
    let mut png_bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut png_bytes, w as u32, h as u32);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
        writer.write_image_data(&rgba).map_err(|e| e.to_string())?;
    }
    let sidecar = format!(
        "{{\n  \"window\": [{w}, {h}],\n  \"view\": {{\"x\": {}, \"y\": {}, \"size\": {}, \"scale\": {}, \"resolution\": {}}},\n  \"yaw\": {},\n  \"pitch\": {}\n}}\n",
        view.x, view.y, view.size, view.scale, view.resolution, view.yaw, view.pitch
    );
    let write = |p: &Path, bytes: &[u8]| {
        lp3d_renderer::triplane::write_atomically(p, |f| f.write_all(bytes)).map_err(|e| e.to_string())
    };
    write(path, &png_bytes)?;
    write(&path.with_extension("json"), sidecar.as_bytes())?;
    Ok(path.to_path_buf())
}
