// MipRayMarcher2: one interval between consecutive sorted samples.
// Raw densities are averaged first, then softplus(x - 1); K samples give K - 1 intervals.

fn interval_alpha(sigma_raw_a: f32, sigma_raw_b: f32, delta: f32) -> f32 {
    let sigma = softplus((sigma_raw_a + sigma_raw_b) * 0.5 - 1.0);
    return 1.0 - exp(-(sigma * delta));
}

// Exclusive-cumprod step of the transmittance, with EG3D's + 1e-10.
fn transmit(t: f32, alpha: f32) -> f32 {
    return t * ((1.0 - alpha) + 1e-10);
}
