//! Saving the window as PNG, with a JSON sidecar that says where the 3D view is and how each frame
//! was rendered, plus the render itself (read back from its texture, one pixel per ray), so tests
//! and scripts can compare it with `lp3d_render.render` of the same camera and settings.

use std::io::Write;
use std::path::{Path, PathBuf};

use eframe::egui;
use lp3d_renderer::atomic;

/// The 3D view's place in the window image, in physical pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewRect {
    pub x: u32,
    pub y: u32,
    /// Side of the view in pixels (the render is scaled to fit, bilinear).
    pub size: u32,
    /// Pixels per ray: `size / resolution`.
    pub scale: f64,
    /// Rays per side of the image on screen.
    pub resolution: u32,
    pub yaw: f64,
    pub pitch: f64,
}

/// The render on screen, as its texture holds it: `size`² RGBA texels, rows top to bottom.
pub struct RenderImage {
    pub size: u32,
    pub rgba: Vec<u8>,
}

fn encode_png(width: u32, height: u32, rgba: &[u8]) -> Result<Vec<u8>, String> {
    let mut png_bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut png_bytes, width, height);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
        writer.write_image_data(rgba).map_err(|e| e.to_string())?;
    }
    Ok(png_bytes)
}

fn encode_window(image: &egui::ColorImage) -> Result<Vec<u8>, String> {
    let [w, h] = image.size;
    let rgba: Vec<u8> = image.pixels.iter().flat_map(|p| p.to_array()).collect();
    encode_png(w as u32, h as u32, &rgba)
}

/// Writes the window PNG at `path`, the render PNG at `render_path(path)`, the window during the
/// scripted drag (`drag`, if any) at `drag_path(path)` and the JSON sidecar (the view's rectangle
/// and camera, the render's file name, then `report`'s fields: a JSON object's members, without
/// braces) at `sidecar_path(path)`; all of them or none.
pub fn save_screenshot(
    path: &Path,
    image: &egui::ColorImage,
    view: &ViewRect,
    render: &RenderImage,
    drag: Option<&egui::ColorImage>,
    report: &str,
) -> Result<PathBuf, String> {
    let [w, h] = image.size;
    let window_png = encode_window(image)?;
    let drag_png = drag.map(encode_window).transpose()?;
    let render_png = encode_png(render.size, render.size, &render.rgba)?;
    let render_file = render_path(path);
    let render_name = render_file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let sidecar = format!(
        "{{\n  \"window\": [{w}, {h}],\n  \"view\": {{\"x\": {}, \"y\": {}, \"size\": {}, \"scale\": {}, \"resolution\": {}}},\n  \"yaw\": {},\n  \"pitch\": {},\n  \"render\": {}{}{}\n}}\n",
        view.x,
        view.y,
        view.size,
        view.scale,
        view.resolution,
        view.yaw,
        view.pitch,
        json_string(&render_name),
        if report.is_empty() { "" } else { ",\n  " },
        report
    );
    // All files are written and synced before any is renamed into place, sidecar first: if a
    // rename fails, `publish_all` removes what it already renamed, so a failure leaves none.
    let stage = |p: &Path, bytes: &[u8]| atomic::stage(p, |f| f.write_all(bytes)).map_err(|e| e.to_string());
    let png = stage(path, &window_png)?;
    let raw = stage(&render_file, &render_png)?;
    let drag = drag_png.map(|bytes| stage(&drag_path(path), &bytes)).transpose()?;
    let json = stage(&sidecar_path(path), sidecar.as_bytes())?;
    atomic::publish_all([Some(json), Some(raw), drag, Some(png)].into_iter().flatten().collect())
        .map_err(|e| e.to_string())?;
    Ok(path.to_path_buf())
}

/// The JSON file written next to a screenshot: the same name with the extension `.json`.
pub fn sidecar_path(path: &Path) -> PathBuf {
    path.with_extension("json")
}

/// The render written next to a screenshot, one pixel per ray: `shot.png` -> `shot.render.png`.
pub fn render_path(path: &Path) -> PathBuf {
    path.with_extension("render.png")
}

/// `s` as a JSON string literal.
pub fn json_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// The window during a scripted drag (`--drag-frames`), at its last moving frame, before the
/// release: `shot.png` -> `shot.drag.png`.
pub fn drag_path(path: &Path) -> PathBuf {
    path.with_extension("drag.png")
}

/// `v` as a JSON number (`null` when not finite, which JSON cannot hold).
pub fn json_number(v: f64) -> String {
    if v.is_finite() {
        format!("{v}")
    } else {
        "null".into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view() -> ViewRect {
        ViewRect { x: 0, y: 0, size: 2, scale: 1.0, resolution: 2, yaw: 0.0, pitch: 0.0 }
    }

    fn render() -> RenderImage {
        RenderImage { size: 1, rgba: vec![1, 2, 3, 255] }
    }

    #[test]
    fn json_helpers_escape() {
        assert_eq!(json_string("a\"b\\c\n"), "\"a\\\"b\\\\c\\u000a\"");
        assert_eq!(json_number(1.5), "1.5");
        assert_eq!(json_number(f64::NAN), "null");
    }

    #[test]
    fn saves_all_files_or_none() {
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
        save_screenshot(&dir.join("ok.png"), &image, &view(), &render(), None, "\"extra\": 1").unwrap();
        assert_eq!(names(), ["ok.json", "ok.png", "ok.render.png"]);
        save_screenshot(&dir.join("dr.png"), &image, &view(), &render(), Some(&image), "").unwrap();
        assert_eq!(
            names(),
            ["dr.drag.png", "dr.json", "dr.png", "dr.render.png", "ok.json", "ok.png", "ok.render.png"]
        );
        let sidecar = std::fs::read_to_string(dir.join("ok.json")).unwrap();
        assert!(sidecar.contains("\"resolution\": 2"), "{sidecar}");
        assert!(sidecar.contains("\"render\": \"ok.render.png\",\n  \"extra\": 1\n}"), "{sidecar}");
        // The sidecar's place is taken by a folder: the write fails and leaves no PNG behind.
        std::fs::create_dir_all(dir.join("bad.json").join("inside")).unwrap();
        assert!(save_screenshot(&dir.join("bad.png"), &image, &view(), &render(), Some(&image), "").is_err());
        assert_eq!(
            names(),
            [
                "bad.json",
                "dr.drag.png",
                "dr.json",
                "dr.png",
                "dr.render.png",
                "ok.json",
                "ok.png",
                "ok.render.png"
            ]
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
