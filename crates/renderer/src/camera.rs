//! EG3D cameras: the 25-float label (cam2world 4x4 row-major, OpenCV axes x right, y down,
//! z forward, world y-up; then 3x3 intrinsics normalised by image size), its validation, and
//! the look-at construction of EG3D's `LookAtPoseSampler` (used by the viewer).
//! The Python twin is `lp3d.render.camera`; tests tie the two.

use crate::error::{Error, Result};

/// FFHQ's normalised focal length (EG3D dataset labels).
pub const FFHQ_FOCAL: f64 = 4.2647;
/// FFHQ's average camera radius.
pub const FFHQ_RADIUS: f64 = 2.7;
/// FFHQ's look-at pivot.
pub const FFHQ_PIVOT: [f64; 3] = [0.0, 0.0, 0.2];

/// A validated 25-float EG3D camera label (stored as f32, as uploaded to the GPU).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera(pub [f32; 25]);

impl Camera {
    /// Validates one label; `field` names it in errors (e.g. `camera[3]`).
    pub fn from_label(label: &[f64], field: &str) -> Result<Camera> {
        if label.len() != 25 {
            return Err(Error::invalid(field, format!("must have 25 values, got {}", label.len())));
        }
        if let Some(i) = label.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(field, format!("contains NaN/Inf at index {i}")));
        }
        let m = |r: usize, c: usize| label[4 * r + c];
        let bottom = [m(3, 0), m(3, 1), m(3, 2), m(3, 3)];
        if (bottom[0].abs() > 1e-6)
            || (bottom[1].abs() > 1e-6)
            || (bottom[2].abs() > 1e-6)
            || ((bottom[3] - 1.0).abs() > 1e-6)
        {
            return Err(Error::invalid(
                format!("{field} cam2world"),
                format!("bottom row must be (0, 0, 0, 1), got {bottom:?}"),
            ));
        }
        let det = m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1))
            - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0))
            + m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
        if det.abs() < 1e-6 {
            return Err(Error::invalid(
                format!("{field} cam2world"),
                format!("rotation is singular (determinant {det:.3e})"),
            ));
        }
        let k = &label[16..25];
        if k[0] <= 0.0 || k[4] <= 0.0 {
            return Err(Error::invalid(
                format!("{field} focal"),
                format!("fx and fy must be > 0, got fx={} fy={}", k[0], k[4]),
            ));
        }
        if k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || k[8] != 1.0 {
            return Err(Error::invalid(
                format!("{field} intrinsics"),
                format!("rows 2-3 must be (0, fy, cy) and (0, 0, 1), got {:?}", &k[3..9]),
            ));
        }
        let mut out = [0f32; 25];
        for (i, (o, v)) in out.iter_mut().zip(label).enumerate() {
            *o = *v as f32;
            // The GPU computes in float32: a finite float64 beyond its range would become Inf
            // there and turn every ray into NaN (an empty image, no error).
            if !o.is_finite() {
                return Err(Error::invalid(
                    field,
                    format!("value {v:e} at index {i} ({}) overflows float32", element_name(i)),
                ));
            }
        }
        if out[16] == 0.0 || out[20] == 0.0 {
            return Err(Error::invalid(format!("{field} focal"), "too small for float32"));
        }
        check_ray_range(label, field)?;
        Ok(Camera(out))
    }

    /// A batch of labels, `n * 25` values row-major.
    pub fn batch_from_labels(labels: &[f64]) -> Result<Vec<Camera>> {
        if labels.is_empty() || labels.len() % 25 != 0 {
            return Err(Error::invalid(
                "camera",
                format!("must hold (25,) or (B, 25) values, got {} values", labels.len()),
            ));
        }
        labels.chunks(25).enumerate().map(|(i, c)| Camera::from_label(c, &format!("camera[{i}]"))).collect()
    }

    /// A look-at camera from geometric angles in degrees, as `lp3d.render.camera.look_at_camera`:
    /// yaw > 0 moves the camera toward +x, pitch > 0 raises it (true elevation, in (-90, 90)),
    /// roll turns it about its viewing axis (`cam2world[:3,:3] @ Rz(roll)`). Maps onto EG3D's
    /// angles as h = π/2 + yaw, v = π/2 · (1 − sin pitch).
    pub fn look_at_camera(
        yaw_deg: f64,
        pitch_deg: f64,
        roll_deg: f64,
        radius: f64,
        lookat: [f64; 3],
        focal: f64,
    ) -> Camera {
        let pitch = pitch_deg.clamp(-89.9, 89.9).to_radians();
        let h = std::f64::consts::FRAC_PI_2 + yaw_deg.to_radians();
        let v = std::f64::consts::FRAC_PI_2 * (1.0 - pitch.sin());
        let label = look_at_label(h, v, radius, lookat, focal);
        let (c, s) = (roll_deg.to_radians().cos(), roll_deg.to_radians().sin());
        let mut out = label;
        for i in 0..3 {
            // Columns right, down of the rotation, turned about the forward axis.
            let (r, d) = (label[4 * i], label[4 * i + 1]);
            out[4 * i] = c * r + s * d;
            out[4 * i + 1] = -s * r + c * d;
        }
        Camera(out.map(|v| v as f32))
    }

    /// EG3D's `LookAtPoseSampler.sample(h, v, lookat, radius)` with focal length `focal` and
    /// principal point (0.5, 0.5). `h`, `v` are EG3D's angles in radians (h = v = π/2 is
    /// frontal). The origin lies on a sphere about the world origin, not about `lookat`
    /// (EG3D's quirk).
    pub fn lookat_pose(h: f64, v: f64, radius: f64, lookat: [f64; 3], focal: f64) -> Camera {
        Camera(look_at_label(h, v, radius, lookat, focal).map(|v| v as f32))
    }
}

/// What label index `i` holds, for error messages.
fn element_name(i: usize) -> String {
    match i {
        0..=15 => format!("cam2world[{}][{}]", i / 4, i % 4),
        16 => "fx".into(),
        17 => "skew".into(),
        18 => "cx".into(),
        20 => "fy".into(),
        21 => "cy".into(),
        _ => format!("intrinsics[{}][{}]", (i - 16) / 3, (i - 16) % 3),
    }
}

/// Largest magnitude a ray's unnormalised direction may reach. The kernel normalises it with
/// `length()`, whose squared sum must stay below float32's maximum (3.4e38); 1e18 leaves room
/// for the three terms and rounding.
const MAX_RAY_DIRECTION: f64 = 1e18;

/// Rejects a label whose ray construction (`shaders/camera.wgsl::camera_ray`) would leave
/// float32's range for some pixel: huge rotation entries or a focal length so small that the
/// lifted pixel coordinates overflow. Each term is bounded over pixel centres in [0, 1]² in
/// float64, so the check is exact arithmetic on a bound, not a sample of pixels.
fn check_ray_range(label: &[f64], field: &str) -> Result<()> {
    let (fx, sk, cx, fy, cy) = (label[16], label[17], label[18], label[20], label[21]);
    // x_lift = (x - cx + cy sk / fy - sk y / fy) / fx, y_lift = (y - cy) / fy, x, y in [0, 1].
    let terms = [cy.abs() * sk.abs(), cy.abs() * sk.abs() / fy, sk.abs() / fy];
    let x_lift = (1.0 + cx.abs() + terms[1] + terms[2]) / fx;
    let y_lift = (1.0 + cy.abs()) / fy;
    let mut dir2 = 0.0;
    for r in 0..3 {
        let row = &label[4 * r..4 * r + 4];
        let d = row[0].abs() * x_lift + row[1].abs() * y_lift + row[2].abs();
        // world = d + origin must stay finite in float32 too.
        if !below(d + row[3].abs(), f32::MAX as f64 / 2.0) {
            return Err(Error::invalid(
                field,
                format!("rays overflow float32 (cam2world row {r} or the focal length is out of range)"),
            ));
        }
        dir2 += d * d;
    }
    if terms.iter().any(|&t| !below(t, MAX_RAY_DIRECTION)) || !below(dir2.sqrt(), MAX_RAY_DIRECTION) {
        return Err(Error::invalid(
            field,
            format!(
                "ray directions reach {:.3e}, beyond float32's range (rotation entries too large or \
                 focal length too small)",
                dir2.sqrt().max(terms[1]).max(terms[2])
            ),
        ));
    }
    Ok(())
}

/// `x < limit`, with NaN (a bound of `0 * Inf`) counting as out of range.
fn below(x: f64, limit: f64) -> bool {
    x < limit
}

/// The float64 label of [`Camera::lookat_pose`].
fn look_at_label(h: f64, v: f64, radius: f64, lookat: [f64; 3], focal: f64) -> [f64; 25] {
    let theta = h;
    let v = v.clamp(1e-5, std::f64::consts::PI - 1e-5);
    let phi = (1.0 - 2.0 * v / std::f64::consts::PI).acos();
    let origin = [
        radius * phi.sin() * (std::f64::consts::PI - theta).cos(),
        radius * phi.cos(),
        radius * phi.sin() * (std::f64::consts::PI - theta).sin(),
    ];
    let forward = normalize(sub(lookat, origin));
    // create_cam2world_matrix: right = -normalize(cross(up, forward)), up' = normalize(cross(forward, right)).
    let r = cross([0.0, 1.0, 0.0], forward);
    let right = normalize([-r[0], -r[1], -r[2]]);
    let up = normalize(cross(forward, right));
    let mut label = [0f64; 25];
    for i in 0..3 {
        label[4 * i] = right[i];
        label[4 * i + 1] = up[i];
        label[4 * i + 2] = forward[i];
        label[4 * i + 3] = origin[i];
    }
    label[15] = 1.0;
    label[16..25].copy_from_slice(&[focal, 0.0, 0.5, 0.0, focal, 0.5, 0.0, 0.0, 1.0]);
    label
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt().max(1e-12);
    [a[0] / n, a[1] / n, a[2] / n]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frontal_look_at_matches_eg3d_sanity_numbers() {
        // docs/eg3d-rendering.md §13: camera at (0, 0, 2.7), right (1,0,0), up' (0,-1,0), forward (0,0,-1).
        let c = Camera::lookat_pose(
            std::f64::consts::FRAC_PI_2,
            std::f64::consts::FRAC_PI_2,
            2.7,
            [0.0; 3],
            FFHQ_FOCAL,
        )
        .0;
        let expect = [1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 2.7, 0.0, 0.0, 0.0, 1.0];
        for i in 0..16 {
            assert!((c[i] as f64 - expect[i]).abs() < 1e-6, "index {i}: {} vs {}", c[i], expect[i]);
        }
        assert!((c[16] as f64 - FFHQ_FOCAL).abs() < 1e-6);
        Camera::from_label(&c.map(f64::from), "camera").unwrap();
    }

    #[test]
    fn validation_names_the_field() {
        let good = Camera::lookat_pose(1.2, 1.4, 2.7, [0.0; 3], 4.26).0.map(f64::from);
        let mut bad = good;
        bad[20] = 0.0;
        let e = Camera::from_label(&bad, "camera").unwrap_err().to_string();
        assert!(e.contains("focal"), "{e}");
        let mut bad = good;
        bad[5] = f64::NAN;
        assert!(Camera::from_label(&bad, "camera").unwrap_err().to_string().contains("NaN"));
        let mut bad = good;
        for i in 0..3 {
            bad[4 * i] = 0.0;
        }
        assert!(Camera::from_label(&bad, "camera").unwrap_err().to_string().contains("singular"));
        assert!(Camera::batch_from_labels(&good[..24]).unwrap_err().to_string().contains("camera"));
    }

    #[test]
    fn values_beyond_float32_are_refused() {
        let good = Camera::lookat_pose(1.2, 1.4, 2.7, [0.0; 3], 4.26).0.map(f64::from);
        // Finite in float64, Inf in float32: rendered an empty image before.
        let mut bad = good;
        bad[3] = 1e300;
        let e = Camera::batch_from_labels(&bad).unwrap_err().to_string();
        assert!(
            e.starts_with("camera[0]:") && e.contains("index 3") && e.contains("overflows float32"),
            "{e}"
        );
        // Finite in float32, but the ray directions' squared length overflows it.
        let mut bad = good;
        bad[0] = 1e20;
        assert!(Camera::from_label(&bad, "camera").unwrap_err().to_string().contains("ray directions"));
        let mut bad = good;
        bad[16] = 1e-30;
        assert!(Camera::from_label(&bad, "camera").unwrap_err().to_string().contains("ray directions"));
        // A translation near float32's maximum: world points overflow.
        let mut bad = good;
        bad[7] = 3e38;
        assert!(Camera::from_label(&bad, "camera").unwrap_err().to_string().contains("overflow"));
        // Far but representable cameras are fine.
        let mut far = good;
        far[11] = 1e30;
        Camera::from_label(&far, "camera").unwrap();
    }
}
