"""Where the baked field's error comes from: the density's interpolation or the colour's, and whether
interpolating them in another space helps.

    python bench/baked_error.py [--seed 1000003] [--subdivisions 6] [--resolution 64]

One teacher head, one novel view (yaw 25, pitch 5), 48+48 samples, PSNR against exact 192+192 (GPU).
The float64 reference renderer (lp3d.render.reference.render_with) renders with samples evaluated
seven ways: decoded exactly; looked up in the field as stored (float64 values, no float16), which must
match the GPU's baked render; density looked up and colour decoded, and the reverse; the field as
lp3d-baked-field-v1 stored it (colour not premultiplied by the colour weight); and the field
interpolated in other spaces (density through asinh, plain colour as logits before the clamped
sigmoid). Then an estimate of a baked *guide*: every sample looked up, and those the field finds
significant (dense, not yet hidden) decoded exactly, with how many that takes per ray; and the same
with the samples chosen by the field's own error instead (the bricks whose lookups at their sub-cell
centres differ most from the decoder).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

import numpy as np

import lp3d_render
from lp3d.render.baked import (
    EMPTY_RAW,
    bake_reference,
    baked_lookup,
    brick_points,
    colour_weight,
    decode_brick_points,
)
from lp3d.render.camera import look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.reference import (
    decode,
    interval_alpha,
    march,
    rays_from_cameras,
    render_with,
    sample_importance,
    sample_stratified,
    sample_triplane,
)
from lp3d.render.settings import SIGMOID_MARGIN, RenderSettings
from lp3d.render.triplane import TriplaneData
from lp3d.teachers import ProceduralTeacher


def logit(rgb: np.ndarray) -> np.ndarray:
    p = np.clip((rgb + SIGMOID_MARGIN) / (1 + 2 * SIGMOID_MARGIN), 1e-12, 1 - 1e-12)
    return np.log(p) - np.log1p(-p)


def from_logit(x: np.ndarray) -> np.ndarray:
    return 1 / (1 + np.exp(-x)) * (1 + 2 * SIGMOID_MARGIN) - SIGMOID_MARGIN


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=1_000_003, help="teacher identity (default 1000003)")
    p.add_argument("--subdivisions", type=int, default=6, help="k (default 6)")
    p.add_argument("--resolution", type=int, default=64, help="rays per side (default 64)")
    args = p.parse_args(argv)
    head = ProceduralTeacher(resolution=64).sample(args.seed)
    tri, k, r = head.to_native(), args.subdivisions, args.resolution
    field = lp3d_render.bake(tri, subdivisions=k, occupancy_epsilon=1e-4)
    index, values = field.index, bake_reference(head, field.index, k)
    cam = look_at_camera(yaw_deg=25, pitch_deg=5)
    fine = {"depth_resolution": 192, "depth_resolution_importance": 192}
    ref = lp3d_render.render(tri, cam, resolution=r, **fine, outputs=["rgb"])["rgb"]
    gpu = lp3d_render.render(
        tri, cam, resolution=r, occupancy_epsilon=1e-4, baked_subdivisions=k, outputs=["rgb"]
    )["rgb"]
    planes = head.planes.astype(np.float64)

    def decoded(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        features = sample_triplane(planes, points, box_warp=head.box_warp)
        sigma, feat = decode(features, head.w0, head.b0, head.w1, head.b1)
        return sigma, feat[..., :3]

    def looked_up(points: np.ndarray, table: np.ndarray = values) -> tuple[np.ndarray, np.ndarray]:
        return baked_lookup(index, table, k, head.box_warp, points)

    def plain_lookup(points: np.ndarray, colour: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trilinear colour, not premultiplied: the lookup of a field whose points all have the same
        (high) density, so one colour weight, which the lookup divides out again."""
        opaque = np.full_like(colour[..., :1], 1e4)
        table = np.concatenate([opaque, colour * colour_weight(opaque)], axis=-1)
        return looked_up(points)[0], baked_lookup(index, table, k, head.box_warp, points)[1]

    plain = decode_brick_points(head, index, k)[1]  # the v1 field's colour
    as_asinh = values.copy()
    as_asinh[..., 0] = np.arcsinh(values[..., 0] / 10.0)

    def variant(name: str):  # noqa: ANN202
        def evaluate(o: np.ndarray, d: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            points = o[:, None, :] + t[..., None] * d[:, None, :]
            if name == "decoded":
                return decoded(points)
            if name == "field":
                return looked_up(points)
            if name == "field density, decoded colour":
                return looked_up(points)[0], decoded(points)[1]
            if name == "decoded density, field colour":
                return decoded(points)[0], looked_up(points)[1]
            if name == "field, plain colour (lp3d-baked-field-v1)":
                return plain_lookup(points, plain)
            if name == "field, plain colour as logits":
                sigma, x = plain_lookup(points, logit(plain))
                return sigma, np.where((sigma == EMPTY_RAW)[..., None], 0.0, from_logit(x))
            sigma = looked_up(points, as_asinh)[0]  # "field, density through asinh(raw / 10)"
            return np.where(sigma == EMPTY_RAW, sigma, np.sinh(sigma) * 10.0), looked_up(points)[1]

        return evaluate

    print(f"Command: `python bench/baked_error.py --seed {args.seed} --subdivisions {k} --resolution {r}`\n")
    print("| samples evaluated | PSNR vs exact 192+192 |\n|---|---|")
    print(f"| GPU baked render (float16 field) | {psnr_db(gpu, ref):.2f} |")
    names = [
        "decoded",
        "field",
        "field density, decoded colour",
        "decoded density, field colour",
        "field, plain colour (lp3d-baked-field-v1)",
        "field, plain colour as logits",
        "field, density through asinh(raw / 10)",
    ]
    settings = RenderSettings(resolution=r)
    for name in names:
        out = render_with(head, cam, settings, variant(name))["rgb"]
        print(f"| {name} | {psnr_db(out, ref):.2f} |", flush=True)

    print("\nA baked guide, decoding only the samples it finds significant (48+48):\n")
    print("| decoded where | samples decoded per ray, mean / max (of 96) | PSNR vs exact 192+192 |")
    print("|---|---|---|")
    for raw_above, t_above in ((0.0, 1e-3), (5.0, 1e-3), (10.0, 1e-3)):
        rgb, n = guided_render(head, cam, r, looked_up, decoded, dense_and_visible(raw_above, t_above))
        where = f"raw density > {raw_above:g} (or a neighbour's), transmittance > {t_above:g}"
        print(f"| {where} | {n.mean():.1f} / {n.max()} | {psnr_db(rgb, ref):.2f} |", flush=True)

    errors = brick_errors(index, k, head.box_warp, looked_up, decoded)
    print(f"\nChosen by the field's own error instead: each brick's largest error at its {k}³ sub-cell")
    print(f"centres (opacity over a {ERROR_STEP:g} step, or RGB times opacity), samples in bricks above τ")
    print("decoded while visible (transmittance > 0.001):\n")
    print("| τ | bricks above τ | samples decoded per ray, mean / max (of 96) | PSNR vs exact 192+192 |")
    print("|---|---|---|---|")
    for tau in (0.1, 0.03, 0.01, 0.001):
        chosen = errors > tau
        rgb, n = guided_render(head, cam, r, looked_up, decoded, in_bricks(index, chosen, head.box_warp))
        print(f"| {tau:g} | {chosen.mean():.0%} | {n.mean():.1f} / {n.max()} | {psnr_db(rgb, ref):.2f} |")
    return 0


#: The step over which bench/baked_error.py turns a density error into an opacity error (a coarse
#: step of 48 samples over the ray's span).
ERROR_STEP = 0.02


def brick_errors(
    index: np.ndarray, k: int, box_warp: float, looked_up: Evaluate, decoded: Evaluate
) -> np.ndarray:
    """Each brick's largest error at the centres of its k³ sub-cells (bricks,): the larger of the
    opacity difference over :data:`ERROR_STEP` and the RGB difference times the opacity."""
    g = index.shape[0]
    centres = (brick_points(index, k)[:, :k, :k, :k] + 1.0 / (g * k)) * (0.5 * box_warp)
    centres = centres.reshape(centres.shape[0], -1, 3)
    out = np.empty(centres.shape[0])
    for lo in range(0, len(out), 2000):  # bounded memory: ~2000 k³ points at a time
        points = centres[lo : lo + 2000].reshape(1, -1, 3)
        (s_true, c_true), (s_field, c_field) = decoded(points), looked_up(points)
        a_true = interval_alpha(s_true, s_true, ERROR_STEP)  # the opacity of a step at this density
        a_field = interval_alpha(s_field, s_field, ERROR_STEP)
        colour = np.abs(c_true - c_field).max(-1) * np.maximum(a_true, a_field)
        err = np.maximum(np.abs(a_true - a_field), colour)
        out[lo : lo + 2000] = err.reshape(-1, k**3).max(-1)
    return out


Evaluate = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


Select = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def near_dense(sigma_raw: np.ndarray, above: float) -> np.ndarray:
    """Where a sample of sorted rays (rays, M) or a neighbour along its ray (none past the ends) has
    a raw density above ``above``."""
    dense = sigma_raw > above
    near = dense.copy()
    near[:, 1:] |= dense[:, :-1]
    near[:, :-1] |= dense[:, 1:]
    return near


def dense_and_visible(raw_above: float, t_above: float) -> Select:
    """The guide's choice: raw density above ``raw_above`` at the sample or a neighbour along its
    ray, transmittance before it above ``t_above``."""
    return lambda points, sigma, transmittance: near_dense(sigma, raw_above) & (transmittance > t_above)


def in_bricks(index: np.ndarray, chosen: np.ndarray, box_warp: float, t_above: float = 1e-3) -> Select:
    """Samples in the ``chosen`` bricks (bricks,) while the transmittance before them is above
    ``t_above``."""
    g = index.shape[0]

    def select(points: np.ndarray, sigma: np.ndarray, transmittance: np.ndarray) -> np.ndarray:
        cell = np.clip(np.floor((points * (2.0 / box_warp) + 1.0) * (0.5 * g)), 0, g - 1).astype(np.int64)
        brick = index[cell[..., 0], cell[..., 1], cell[..., 2]]
        return (brick >= 0) & chosen[np.maximum(brick, 0)] & (transmittance > t_above)

    return select


def guided_render(
    head: TriplaneData, cam: np.ndarray, r: int, looked_up: Evaluate, decoded: Evaluate, select: Select
) -> tuple[np.ndarray, np.ndarray]:
    """48+48 with every sample looked up in the field (the coarse pass, the importance draw and a
    first composite), then the samples ``select(points, raw density, transmittance before them)``
    picks decoded exactly. An estimate of a guided kernel (which would judge the transmittance on
    the mixed values as it walks); returns the RGB image and the decoded samples per ray."""
    o, d = (a.reshape(-1, 3) for a in rays_from_cameras(np.asarray(cam)[None], r))

    def points(t: np.ndarray) -> np.ndarray:
        return o[:, None, :] + t[..., None] * d[:, None, :]

    t = sample_stratified(o.shape[0], depth_resolution=48, ray_start=head.ray_start, ray_end=head.ray_end)
    sigma, rgb = looked_up(points(t))
    t_fine = sample_importance(t, march(t, sigma, rgb).weights, 48, None)
    t = np.sort(np.concatenate([t, t_fine], axis=-1), axis=-1, kind="stable")
    sigma, rgb = looked_up(points(t))
    w = march(t, sigma, rgb).weights
    transmittance = np.concatenate([np.ones_like(w[:, :1]), 1.0 - np.cumsum(w, axis=-1)], axis=-1)
    significant = select(points(t), sigma, transmittance)
    exact_sigma, exact_rgb = decoded(points(t)[significant][:, None, :])
    sigma[significant], rgb[significant] = exact_sigma[:, 0], exact_rgb[:, 0]
    out = march(t, sigma, rgb).features.reshape(r, r, 3).transpose(2, 0, 1)
    return out, significant.sum(axis=-1)


if __name__ == "__main__":
    sys.exit(main())
