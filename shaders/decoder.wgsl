// EG3D OSGDecoder on effective weights: h = softplus(W0 f + b0), o = W1 h + b1,
// o[0] raw density, o[1..33] features through the clamped sigmoid.

var<private> hidden: array<vec4<f32>, 16>;

// torch.nn.Softplus(beta=1, threshold=20): x above 20, else log1p(exp(x)) (torch uses log1p).
// WGSL has no log1p, and log(1 + y) loses all digits once y = exp(x) < 6e-8, turning the faint
// densities of empty space into exact zeros. Below x = -3 (y < 0.05) a series in y keeps full
// relative precision; above it, log(1 + y) is accurate to ~1e-6 relative (docs/numerics.md).
fn softplus(x: f32) -> f32 {
    if (x > 20.0) {
        return x;
    }
    let y = exp(x);
    if (x < -3.0) {
        // log1p(y) = y - y^2/2 + y^3/3 - y^4/4 + y^5/5 - ..., truncation error < y^6/6.
        return y * (1.0 - y * (0.5 - y * (1.0 / 3.0 - y * (0.25 - y * 0.2))));
    }
    return log(1.0 + y);
}

// MipNeRF's widened sigmoid, range (-0.001, 1.001).
fn clamped_sigmoid(x: f32) -> f32 {
    return (1.0 / (1.0 + exp(-x))) * 1.002 - 0.001;
}

// Hidden layer from `feat` into `hidden`.
fn decode_hidden() {
    for (var j = 0u; j < 16u; j++) {
        var h = vec4<f32>(0.0);
        for (var c = 0u; c < 4u; c++) {
            let row = (4u * j + c) * 8u;
            var acc = 0.0;
            for (var q = 0u; q < 8u; q++) {
                acc += dot(decoder.w0[row + q], feat[q]);
            }
            h[c] = softplus(acc + decoder.b0[j][c]);
        }
        hidden[j] = h;
    }
}

// Output r of the last layer (0: raw density, 1..33: feature logits).
fn decode_output(r: u32) -> f32 {
    var acc = 0.0;
    for (var q = 0u; q < 16u; q++) {
        acc += dot(decoder.w1[16u * r + q], hidden[q]);
    }
    return acc + decoder.b1[r / 4u][r % 4u];
}
