//! Saving the window as PNG, with a JSON sidecar that says where the 3D view is, so tests and
//! scripts can crop it and compare it with `lp3d_render.render` of the same camera.

use std::io::Write;
use std::path::{Path, PathBuf};

use eframe::egui;
use lp3d_renderer::atomic;

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
    // Both files are written and synced before either is renamed into place, sidecar first: if a
    // rename fails, `publish_all` removes what it already renamed, so a failure leaves neither.
    let stage = |p: &Path, bytes: &[u8]| atomic::stage(p, |f| f.write_all(bytes)).map_err(|e| e.to_string());
    let png = stage(path, &png_bytes)?;
    let json = stage(&sidecar_path(path), sidecar.as_bytes())?;
    atomic::publish_all(vec![json, png]).map_err(|e| e.to_string())?;
    Ok(path.to_path_buf())
}

/// The JSON file written next to a screenshot: the same name with the extension `.json`.
pub fn sidecar_path(path: &Path) -> PathBuf {
    path.with_extension("json")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view() -> ViewRect {
        ViewRect { x: 0, y: 0, size: 2, scale: 1, resolution: 2, yaw: 0.0, pitch: 0.0 }
    }

    #[test]
    fn saves_both_files_or_neither() {
        let dir = std::env::temp_dir().join(format!("lp3d-screenshot-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let image = egui::ColorImage::from_rgba_unmultiplied([2, 2], &[200; 16]);
        let names = || {
            let mut v: Vec<String> = std::fs::read_dir(&dir)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into())
                .collect();
            v.sort();
            v
        };
        save_screenshot(&dir.join("ok.png"), &image, &view()).unwrap();
        assert_eq!(names(), ["ok.json", "ok.png"]);
        assert!(std::fs::read_to_string(dir.join("ok.json")).unwrap().contains("\"resolution\": 2"));
        // The sidecar's place is taken by a folder: the write fails and leaves no PNG behind.
        std::fs::create_dir_all(dir.join("bad.json").join("inside")).unwrap();
        assert!(save_screenshot(&dir.join("bad.png"), &image, &view()).is_err());
        assert_eq!(names(), ["bad.json", "ok.json", "ok.png"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
