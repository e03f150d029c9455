//! Command-line options of `lp3d-view` (also filled in by `lp3d_render.view` from Python).

use std::path::{Path, PathBuf};

use lp3d_renderer::RenderSettings;

use crate::screenshot::{drag_path, render_path, sidecar_path};

pub const USAGE: &str = "\
usage: lp3d-view [options] [triplane.npz]

Interactive viewer for EG3D-format triplanes (lp3d's .npz files).
Drag to orbit, right-drag or shift-drag to pan, scroll to zoom, double-click to reset.
Drop a .npz file on the window to open it.

options:
  --screenshot PATH   once the final quality is on screen, save a PNG of the window to PATH
                      (.png), the render itself to PATH with .render.png (one pixel per ray) and
                      a JSON sidecar, PATH with .json (where the 3D view is in the window, the
                      camera, each rendered frame's time and quality), and exit; none of them
                      may be the triplane file
  --yaw DEG           initial yaw in degrees (camera toward +x for > 0) [0]
  --pitch DEG         initial pitch in degrees (camera above for > 0) [0]
  --resolution R      rays per image side of the final image [128]
  --samples C+F       coarse + fine samples per ray of the final image (EG3D's depth_resolution
                      + depth_resolution_importance; C alone skips the importance pass) [48+48]
  --frame-budget-ms MS  while the camera moves, render at the quality predicted to take at most
                      MS per frame; when it stops, refine to the final quality [100]
  --no-bake           do not bake: by default the file's baked field (decoded once into a grid)
                      is made in the background after it opens, and once ready draws the frames
                      while the camera moves at the final quality, when they fit the budget; the
                      still image is always exact. A --screenshot run without --drag-frames does
                      not bake (it shows no moving frame)
  --no-fine-field     bake only the quick field (k 4 / 10: smaller, quicker to bake): by default
                      a fine one (k 4 / 16: larger, slower to bake) follows and replaces it, whose
                      moving frames are as close to the exact image as the still one
  --superres FILE     super-resolve the still image with the network of a model package's
                      weights file (MODEL.superres.npz): once the exact image is up, its feature
                      image at the network's input side is rendered and super-resolved (64² to
                      256² for lp3d's shipped model); moving frames stay raw. lp3d view picks the
                      shipped model's for a file lifted by it
  --no-superres       show the raw volume render only (lp3d view: do not pick the shipped model's)
  --frames N          UI frames before a screenshot; it waits for the final quality too [3]
  --drag-frames N     with --screenshot: once the final image is up and the bake has ended
                      (ready or failed), drag the view to orbit
                      (synthetic pointer events, a quarter of the view's width to the right and a
                      tenth down) over N UI frames, save the window at the last moving frame (PATH
                      with .drag.png), release, wait for the refined image, then save; the JSON
                      sidecar records every frame's render time and quality, whether it came from
                      the baked field, and the bake [0]
  -h, --help          show this help";

#[derive(Debug, Clone, PartialEq)]
pub struct ViewerOptions {
    pub path: Option<PathBuf>,
    pub screenshot: Option<PathBuf>,
    pub yaw: f64,
    pub pitch: f64,
    pub resolution: u32,
    pub depth_resolution: u32,
    pub depth_resolution_importance: u32,
    pub frame_budget_ms: f64,
    pub frames: u32,
    pub drag_frames: u32,
    /// Bake the file's field in the background for the moving frames (`--no-bake`: false).
    pub bake: bool,
    /// After the quick field, bake the fine one (`--no-fine-field`: false).
    pub fine_field: bool,
    /// A super-resolution weights file for the still image (`--superres`).
    pub superres: Option<PathBuf>,
    /// `--no-superres`: none, and none picked for the file by `lp3d view`.
    pub no_superres: bool,
    pub help: bool,
}

impl Default for ViewerOptions {
    fn default() -> Self {
        ViewerOptions {
            path: None,
            screenshot: None,
            yaw: 0.0,
            pitch: 0.0,
            resolution: 128,
            depth_resolution: 48,
            depth_resolution_importance: 48,
            frame_budget_ms: 100.0,
            frames: 3,
            drag_frames: 0,
            bake: true,
            fine_field: true,
            superres: None,
            no_superres: false,
            help: false,
        }
    }
}

impl ViewerOptions {
    pub fn from_args(args: impl IntoIterator<Item = String>) -> Result<ViewerOptions, String> {
        let mut o = ViewerOptions::default();
        let mut args = args.into_iter();
        while let Some(arg) = args.next() {
            let mut value = |name: &str| args.next().ok_or_else(|| format!("{name} needs a value"));
            match arg.as_str() {
                "-h" | "--help" => o.help = true,
                "--screenshot" => o.screenshot = Some(PathBuf::from(value("--screenshot")?)),
                "--yaw" => o.yaw = number(&value("--yaw")?, "--yaw")?,
                "--pitch" => o.pitch = number(&value("--pitch")?, "--pitch")?,
                "--resolution" => o.resolution = integer(&value("--resolution")?, "--resolution")?,
                "--samples" => {
                    (o.depth_resolution, o.depth_resolution_importance) = samples(&value("--samples")?)?
                }
                "--frame-budget-ms" => {
                    o.frame_budget_ms = number(&value("--frame-budget-ms")?, "--frame-budget-ms")?
                }
                "--frames" => o.frames = integer(&value("--frames")?, "--frames")?,
                "--drag-frames" => o.drag_frames = integer(&value("--drag-frames")?, "--drag-frames")?,
                "--no-bake" => o.bake = false,
                "--no-fine-field" => o.fine_field = false,
                "--superres" => o.superres = Some(PathBuf::from(value("--superres")?)),
                "--no-superres" => o.no_superres = true,
                flag if flag.starts_with('-') => return Err(format!("unknown option {flag}")),
                path => {
                    if o.path.is_some() {
                        return Err("give at most one triplane file".into());
                    }
                    o.path = Some(PathBuf::from(path));
                }
            }
        }
        o.validate_flags()?;
        Ok(o)
    }

    /// Every check: the flags ([`Self::validate_flags`]) and the files they name
    /// ([`Self::check_outputs`]).
    pub fn validate(&self) -> Result<(), String> {
        self.validate_flags()?;
        self.check_outputs()
    }

    /// The flags' values and combinations: a usage error (`from_args` runs these; exit status 2).
    pub fn validate_flags(&self) -> Result<(), String> {
        if !(-89.0..=89.0).contains(&self.pitch) {
            return Err(format!("--pitch must be in [-89, 89], got {}", self.pitch));
        }
        if !(16..=1024).contains(&self.resolution) {
            return Err(format!("--resolution must be in [16, 1024], got {}", self.resolution));
        }
        let settings = self.settings();
        if let Err(e) = settings.validate() {
            return Err(format!(
                "--samples {}+{}: {e}",
                self.depth_resolution, self.depth_resolution_importance
            ));
        }
        if !(self.frame_budget_ms.is_finite() && (1.0..=60_000.0).contains(&self.frame_budget_ms)) {
            return Err(format!("--frame-budget-ms must be in [1, 60000], got {}", self.frame_budget_ms));
        }
        if self.frames == 0 {
            return Err("--frames must be at least 1".into());
        }
        if self.drag_frames > 10_000 {
            return Err(format!("--drag-frames must be at most 10000, got {}", self.drag_frames));
        }
        if self.drag_frames > 0 && self.screenshot.is_none() {
            return Err("--drag-frames needs --screenshot (it drives a scripted drag, then saves)".into());
        }
        if self.screenshot.is_some() && self.path.is_none() {
            return Err("--screenshot needs a triplane file".into());
        }
        if self.superres.is_some() && self.no_superres {
            return Err("give --superres FILE or --no-superres, not both".into());
        }
        Ok(())
    }

    /// The screenshot's files against the file system and the input: a runtime error (exit
    /// status 1), checked before the window opens.
    pub fn check_outputs(&self) -> Result<(), String> {
        if let (Some(shot), Some(input)) = (&self.screenshot, &self.path) {
            check_screenshot_paths(input, "triplane file", shot, self.drag_frames > 0)?;
            if let Some(weights) = &self.superres {
                check_screenshot_paths(weights, "super-resolution file", shot, self.drag_frames > 0)?;
            }
        }
        Ok(())
    }

    /// Whether the viewer bakes each file's field: asked for, and some frame can use it (a
    /// `--screenshot` run without a drag draws only the still, exact image).
    pub fn bakes(&self) -> bool {
        self.bake && (self.screenshot.is_none() || self.drag_frames > 0)
    }

    /// The final-quality render settings these options choose.
    pub fn settings(&self) -> RenderSettings {
        RenderSettings {
            resolution: self.resolution,
            depth_resolution: self.depth_resolution,
            depth_resolution_importance: self.depth_resolution_importance,
            ..Default::default()
        }
    }
}

/// A screenshot writes a PNG of the window, its JSON sidecar and the render itself as a PNG (and
/// with a scripted drag, `drag`, the window during the drag as another PNG). Refused here, before
/// any window opens: any of them being the triplane file or another of them (by name, link or
/// relative path), a name that is not `.png`, a folder in their place, a missing folder.
fn check_screenshot_paths(input: &Path, input_kind: &str, shot: &Path, drag: bool) -> Result<(), String> {
    let s = shot.display();
    let mut outputs = vec![
        ("screenshot", shot.to_path_buf()),
        ("JSON sidecar", sidecar_path(shot)),
        ("render image", render_path(shot)),
    ];
    if drag {
        outputs.push(("drag image", drag_path(shot)));
    }
    let input_id = file_id(input);
    let ids: Vec<FileId> = outputs.iter().map(|(_, p)| file_id(p)).collect();
    for ((what, p), id) in outputs.iter().zip(&ids) {
        if *id == input_id {
            return Err(if *what == "screenshot" {
                format!("--screenshot {s} is the {input_kind} {}: it would be replaced", input.display())
            } else {
                format!(
                    "--screenshot {s}: its {what} {} is the {input_kind} {}: it would be replaced",
                    p.display(),
                    input.display()
                )
            });
        }
    }
    for (i, a) in ids.iter().enumerate() {
        if let Some(j) = ids[i + 1..].iter().position(|b| b == a) {
            let (what_a, what_b) = (outputs[i].0, outputs[i + 1 + j].0);
            return Err(format!(
                "--screenshot {s}: its {what_b} {} would replace its {what_a}; give a .png file name",
                outputs[i + 1 + j].1.display()
            ));
        }
    }
    let is_png = shot.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !is_png {
        return Err(format!("--screenshot {s}: the screenshot is a PNG image; give a .png file name"));
    }
    for (_, p) in &outputs {
        if p.is_dir() {
            return Err(format!("--screenshot {s}: {} is a folder", p.display()));
        }
    }
    let folder = folder_of(shot);
    if !folder.is_dir() {
        return Err(format!("--screenshot {s}: folder {} does not exist", folder.display()));
    }
    Ok(())
}

fn folder_of(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// What identifies the file a path names: device and inode where it exists (symlinks, hard links
/// and relative paths to one file agree), else the path with its folder resolved.
#[derive(Debug, PartialEq)]
enum FileId {
    #[cfg(unix)]
    Inode(u64, u64),
    Path(PathBuf),
}

fn file_id(path: &Path) -> FileId {
    #[cfg(unix)]
    if let Ok(meta) = std::fs::metadata(path) {
        use std::os::unix::fs::MetadataExt;
        return FileId::Inode(meta.dev(), meta.ino());
    }
    if let Ok(full) = path.canonicalize() {
        return FileId::Path(full);
    }
    let resolved = match (folder_of(path).canonicalize(), path.file_name()) {
        (Ok(dir), Some(name)) => dir.join(name),
        _ => path.to_path_buf(),
    };
    FileId::Path(resolved)
}

fn number(s: &str, name: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| format!("{name} must be a finite number, got '{s}'"))
}

/// `48+48` -> (48, 48); `64` -> (64, 0), no importance pass (as `lp3d render --samples`).
fn samples(s: &str) -> Result<(u32, u32), String> {
    let bad = || format!("--samples must be COARSE+FINE such as 48+48, or COARSE alone, got '{s}'");
    let parts: Vec<&str> = s.split('+').collect();
    let parse = |p: &str| p.trim().parse::<u32>().map_err(|_| bad());
    match parts.as_slice() {
        [c] => Ok((parse(c)?, 0)),
        [c, f] => Ok((parse(c)?, parse(f)?)),
        _ => Err(bad()),
    }
}

fn integer(s: &str, name: &str) -> Result<u32, String> {
    s.parse::<u32>().map_err(|_| format!("{name} must be a non-negative integer, got '{s}'"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<ViewerOptions, String> {
        ViewerOptions::from_args(args.iter().map(|s| s.to_string()))
    }

    #[test]
    fn parses_and_validates() {
        let o = parse(&["--yaw", "30", "--pitch", "-10", "--screenshot", "s.png", "t.npz"]).unwrap();
        assert_eq!((o.yaw, o.pitch), (30.0, -10.0));
        assert_eq!(o.path.as_deref(), Some(std::path::Path::new("t.npz")));
        assert!(parse(&["--yaw"]).unwrap_err().contains("--yaw needs a value"));
        assert!(parse(&["--pitch", "95", "t.npz"]).unwrap_err().contains("--pitch"));
        assert!(parse(&["--resolution", "abc"]).unwrap_err().contains("--resolution"));
        assert!(parse(&["--bogus"]).unwrap_err().contains("unknown option"));
        assert!(parse(&["--screenshot", "s.png"]).unwrap_err().contains("needs a triplane"));
        assert!(parse(&["a.npz", "b.npz"]).unwrap_err().contains("at most one"));
    }

    #[test]
    fn quality_and_drag_options() {
        let o = parse(&["--samples", "24+12", "--frame-budget-ms", "50", "t.npz"]).unwrap();
        assert_eq!((o.depth_resolution, o.depth_resolution_importance, o.frame_budget_ms), (24, 12, 50.0));
        assert_eq!(parse(&["--samples", "64", "t.npz"]).unwrap().depth_resolution_importance, 0);
        let d = ViewerOptions::default();
        assert_eq!((d.depth_resolution, d.depth_resolution_importance, d.frame_budget_ms), (48, 48, 100.0));
        for bad in ["48+", "a+b", "1+2+3", ""] {
            assert!(parse(&["--samples", bad, "t.npz"]).unwrap_err().contains("--samples"), "{bad}");
        }
        // The renderer's own limits, named after the option.
        assert!(parse(&["--samples", "3+8", "t.npz"]).unwrap_err().contains("depth_resolution"));
        assert!(parse(&["--samples", "48+1", "t.npz"]).unwrap_err().contains("--samples 48+1"));
        for bad in ["0", "-5", "nan", "inf", "1e9"] {
            assert!(parse(&["--frame-budget-ms", bad, "t.npz"]).unwrap_err().contains("--frame-budget-ms"));
        }
        assert!(parse(&["--drag-frames", "5", "t.npz"]).unwrap_err().contains("needs --screenshot"));
        assert!(parse(&["--drag-frames", "x"]).unwrap_err().contains("--drag-frames"));
        let o = parse(&["--drag-frames", "5", "--screenshot", "s.png", "t.npz"]).unwrap();
        assert_eq!(o.drag_frames, 5);
        assert!(o.bake && o.bakes());
        assert!(o.fine_field && !parse(&["--no-fine-field", "t.npz"]).unwrap().fine_field);
        assert!(!parse(&["--no-bake", "--drag-frames", "5", "--screenshot", "s.png", "t.npz"])
            .unwrap()
            .bakes());
        assert!(!parse(&["--screenshot", "s.png", "t.npz"]).unwrap().bakes(), "no moving frame to bake for");
        assert!(parse(&["t.npz"]).unwrap().bakes());
    }

    #[test]
    fn screenshot_outputs_never_alias_the_input_or_each_other() {
        let dir = std::env::temp_dir().join(format!("lp3d-view-options-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("folder.png")).unwrap();
        let input = dir.join("v.npz");
        std::fs::write(&input, b"a triplane").unwrap();
        let p = |name: &str| dir.join(name).to_string_lossy().into_owned();
        let input_s = p("v.npz");
        // Flags that parse; the files they name are checked by `check_outputs` (and `validate`).
        let err = |shot: &str, input: &str| {
            parse(&["--screenshot", shot, input]).unwrap().check_outputs().unwrap_err()
        };
        assert!(err(&input_s, &input_s).contains("would be replaced"));
        // The same file by another spelling, through a symlink, and through a hard link.
        let dotted = format!("{}/./v.npz", dir.display());
        assert!(err(&dotted, &input_s).contains("would be replaced"));
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink(&input, dir.join("link.png")).unwrap();
            assert!(err(&p("link.png"), &input_s).contains("would be replaced"));
            std::fs::hard_link(&input, dir.join("hard.png")).unwrap();
            assert!(err(&p("hard.png"), &input_s).contains("would be replaced"));
        }
        // The sidecar of v.png is v.json: a triplane named v.json would be replaced by it.
        std::fs::write(dir.join("v.json"), b"a triplane").unwrap();
        assert!(err(&p("v.png"), &p("v.json")).contains("sidecar"));
        assert!(err(&p("out.json"), &input_s).contains("sidecar"));
        // With a scripted drag, the drag image of d.png is d.drag.png.
        std::fs::write(dir.join("d.drag.png"), b"a triplane").unwrap();
        let drag_err = |shot: &str, input: &str| {
            parse(&["--drag-frames", "3", "--screenshot", shot, input]).unwrap().check_outputs().unwrap_err()
        };
        assert!(drag_err(&p("d.png"), &p("d.drag.png")).contains("drag image"));
        parse(&["--screenshot", &p("d.png"), &p("d.drag.png")]).unwrap().check_outputs().unwrap();
        // The render image of v.png is v.render.png: a triplane of that name would be replaced.
        std::fs::write(dir.join("w.render.png"), b"a triplane").unwrap();
        assert!(err(&p("w.png"), &p("w.render.png")).contains("render image"));
        std::fs::create_dir_all(dir.join("r.render.png")).unwrap();
        assert!(err(&p("r.png"), &input_s).contains("is a folder"));
        assert!(err(&p("out.jpg"), &input_s).contains(".png"));
        assert!(err(&p("folder.png"), &input_s).contains("is a folder"));
        assert!(err(&p("missing/s.png"), &input_s).contains("does not exist"));
        parse(&["--screenshot", &p("ok.png"), &input_s]).unwrap().validate().unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
