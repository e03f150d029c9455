// EG3D OSGDecoder on effective weights: h = softplus(W0 f + b0), o = W1 h + b1,
// o[0] raw density, o[1..33] features through the clamped sigmoid.

var<private> hidden: array<vec4<f32>, 16>;

// torch.nn.Softplus(beta=1, threshold=20).
fn softplus(x: f32) -> f32 {
    return select(log(1.0 + exp(x)), x, x > 20.0);
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
