// Stage: camera (lp3d.render.reference.rays_from_cameras). Rays from EG3D 25-float cameras
// (RaySampler): pixel centres, OpenCV camera axes, unit directions, depth measured along the
// direction.
// needs: params, cameras
// provides: CAMERA_FLOATS, Ray, cam_at, camera_ray

// Floats per camera in EG3D's label: cam2world 4x4 row-major (16), then the 3x3 normalised
// intrinsics (9).
const CAMERA_FLOATS: u32 = 25u;

struct Ray {
    origin: vec3<f32>,
    dir: vec3<f32>,
}

fn cam_at(cam: u32, i: u32) -> f32 {
    return cameras[cam * CAMERA_FLOATS + i];
}

fn camera_ray(cam: u32, pixel: u32) -> Ray {
    let r = params.resolution;
    let row = pixel / r;
    let col = pixel % r;
    // EG3D: arange(R) * (1/R) + 0.5/R, with x the column and y the row (row 0 at the top).
    let inv_r = 1.0 / f32(r);
    let x = f32(col) * inv_r + 0.5 * inv_r;
    let y = f32(row) * inv_r + 0.5 * inv_r;
    let fx = cam_at(cam, 16u);
    let sk = cam_at(cam, 17u);
    let cx = cam_at(cam, 18u);
    let fy = cam_at(cam, 20u);
    let cy = cam_at(cam, 21u);
    let x_lift = (x - cx + cy * sk / fy - sk * y / fy) / fx;
    let y_lift = (y - cy) / fy;
    var world = vec3<f32>(0.0);
    var origin = vec3<f32>(0.0);
    for (var i = 0u; i < 3u; i++) {
        let m0 = cam_at(cam, 4u * i);
        let m1 = cam_at(cam, 4u * i + 1u);
        let m2 = cam_at(cam, 4u * i + 2u);
        let m3 = cam_at(cam, 4u * i + 3u);
        world[i] = m0 * x_lift + m1 * y_lift + m2 + m3;
        origin[i] = m3;
    }
    let d = world - origin;
    // torch.nn.functional.normalize: v / max(|v|, 1e-12).
    return Ray(origin, d / max(length(d), 1e-12));
}
