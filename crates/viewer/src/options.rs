//! Command-line options of `lp3d-view` (also filled in by `lp3d_render.view` from Python).

use std::path::PathBuf;

pub const USAGE: &str = "\
usage: lp3d-view [options] [triplane.npz]

Interactive viewer for EG3D-format triplanes (lp3d's .npz files).
Drag to orbit, right-drag or shift-drag to pan, scroll to zoom, double-click to reset.
Drop a .npz file on the window to open it.

options:
  --screenshot PATH   render a few frames, save a PNG of the window to PATH, and exit
                      (a JSON file next to it records where the 3D view is in the image)
  --yaw DEG           initial yaw in degrees (camera toward +x for > 0) [0]
  --pitch DEG         initial pitch in degrees (camera above for > 0) [0]
  --resolution R      rays per image side [128]
  --frames N          frames to render before a screenshot [3]
  -h, --help          show this help";

#[derive(Debug, Clone, PartialEq)]
pub struct ViewerOptions {
    pub path: Option<PathBuf>,
    pub screenshot: Option<PathBuf>,
    pub yaw: f64,
    pub pitch: f64,
    pub resolution: u32,
    pub frames: u32,
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
            frames: 3,
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
                "--frames" => o.frames = integer(&value("--frames")?, "--frames")?,
                flag if flag.starts_with('-') => return Err(format!("unknown option {flag}")),
                path => {
                    if o.path.is_some() {
                        return Err("give at most one triplane file".into());
                    }
                    o.path = Some(PathBuf::from(path));
                }
            }
        }
        o.validate()?;
        Ok(o)
    }

    pub fn validate(&self) -> Result<(), String> {
        if !(-89.0..=89.0).contains(&self.pitch) {
            return Err(format!("--pitch must be in [-89, 89], got {}", self.pitch));
        }
        if !(16..=1024).contains(&self.resolution) {
            return Err(format!("--resolution must be in [16, 1024], got {}", self.resolution));
        }
        if self.frames == 0 {
            return Err("--frames must be at least 1".into());
        }
        if self.screenshot.is_some() && self.path.is_none() {
            return Err("--screenshot needs a triplane file".into());
        }
        Ok(())
    }
}

fn number(s: &str, name: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| format!("{name} must be a finite number, got '{s}'"))
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
}
