//! The viewer's camera: an EG3D look-at orbit (the renderer's `Camera::look_at_camera`, the same camera as
//! `lp3d.render.camera.look_at_camera`), plus zoom as focal length and pan as principal point, so the
//! scene stays inside the triplane's [ray_start, ray_end] depth range.

use lp3d_renderer::camera::{Camera, FFHQ_FOCAL, FFHQ_PIVOT, FFHQ_RADIUS};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orbit {
    pub yaw: f64,
    pub pitch: f64,
    /// Focal length multiplier (1 = FFHQ's 4.2647).
    pub zoom: f64,
    /// Principal-point shift in normalised image units.
    pub pan: [f64; 2],
}

impl Orbit {
    pub fn new(yaw: f64, pitch: f64) -> Orbit {
        Orbit { yaw, pitch, zoom: 1.0, pan: [0.0, 0.0] }
    }

    pub fn camera(&self) -> Camera {
        let mut c = Camera::look_at_camera(
            self.yaw,
            self.pitch,
            0.0,
            FFHQ_RADIUS,
            FFHQ_PIVOT,
            FFHQ_FOCAL * self.zoom,
        );
        c.0[18] = (0.5 + self.pan[0]) as f32;
        c.0[21] = (0.5 + self.pan[1]) as f32;
        c
    }

    /// Mouse drag in image fractions: horizontal orbits yaw, vertical pitch.
    pub fn rotate(&mut self, dx: f64, dy: f64) {
        self.yaw = (self.yaw - 120.0 * dx).rem_euclid(360.0);
        if self.yaw > 180.0 {
            self.yaw -= 360.0;
        }
        self.pitch = (self.pitch + 90.0 * dy).clamp(-85.0, 85.0);
    }

    pub fn pan_by(&mut self, dx: f64, dy: f64) {
        self.pan[0] = (self.pan[0] + dx).clamp(-2.0, 2.0);
        self.pan[1] = (self.pan[1] + dy).clamp(-2.0, 2.0);
    }

    pub fn zoom_by(&mut self, scroll: f64) {
        self.zoom = (self.zoom * (scroll / 400.0).exp()).clamp(0.2, 8.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_orbit_is_the_frontal_look_at_camera() {
        let c = Orbit::new(0.0, 0.0).camera();
        let expect = Camera::look_at_camera(0.0, 0.0, 0.0, FFHQ_RADIUS, FFHQ_PIVOT, FFHQ_FOCAL);
        assert_eq!(c, expect);
        let mut o = Orbit::new(170.0, 0.0);
        o.rotate(-0.25, 2.0);
        assert!((o.yaw - (-160.0)).abs() < 1e-9 && o.pitch == 85.0);
    }
}
