// Stage: march, the compositing (lp3d.render.reference.march, EG3D's MipRayMarcher2): one interval
// between consecutive sorted samples. Raw densities are averaged first, then
// softplus(x - DENSITY_SHIFT); K samples give K - 1 intervals.
// needs: softplus
// provides: DENSITY_SHIFT, TRANSMITTANCE_EPS, interval_alpha, one_minus_exp_neg, transmit

// EG3D's MipRayMarcher2 density activation: sigma = softplus(sigma_raw - 1).
const DENSITY_SHIFT: f32 = 1.0;
// EG3D's MipRayMarcher2: the transmittance is the exclusive cumprod of (1 - alpha) + 1e-10.
const TRANSMITTANCE_EPS: f32 = 1e-10;

fn interval_alpha(sigma_raw_a: f32, sigma_raw_b: f32, delta: f32) -> f32 {
    let sigma = softplus((sigma_raw_a + sigma_raw_b) * 0.5 - DENSITY_SHIFT);
    return one_minus_exp_neg(sigma * delta);
}

// 1 - exp(-x), i.e. -expm1(-x) (as the torch twin computes it). EG3D's float32 1 - exp(-x)
// cancels for small x (absolute error ~6e-8, so 100% relative below x ~ 1e-7), which leaves the
// depth of faint rays, sum(w t) / sum(w), meaningless. Below 0.1 a Taylor series keeps full
// relative precision (truncation < x^6/720); the two forms differ by at most ~6e-8 in alpha.
fn one_minus_exp_neg(x: f32) -> f32 {
    if (x < 0.1) {
        return x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x * (1.0 / 120.0)))));
    }
    return 1.0 - exp(-x);
}

// Exclusive-cumprod step of the transmittance, with EG3D's + TRANSMITTANCE_EPS.
fn transmit(t: f32, alpha: f32) -> f32 {
    return t * ((1.0 - alpha) + TRANSMITTANCE_EPS);
}
