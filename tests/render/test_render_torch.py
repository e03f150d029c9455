"""The torch renderer twin against the float64 NumPy reference, its gradients, batching and devices.

Tolerances (float32 twin vs float64 reference): 1e-4 on features, rgb and depth, 1e-5 on weights_sum.
The scenes are chosen to be well conditioned in float32: with white-noise planes *and* a density that
swings by tens of units per texel, any float32 implementation of EG3D's algorithm (the twin and EG3D's
own code alike) drifts ~1e-4..1e-3 from float64: float32 rounding of points, features and raw densities
(~1e-5 in sigma_raw) perturbs the coarse weights, and the importance pass amplifies that into shifted
fine samples. The float64 twin agrees with the
reference to ~1e-12 on those scenes too (``test_float64_twin_matches_reference_exactly``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from lp3d.render import reference
from lp3d.render.camera import look_at_camera, stack_labels
from lp3d.render.settings import RenderSettings, SceneBounds
from lp3d.render.torch_twin import (
    rays_from_cameras,
    render_rays,
    render_torch,
    render_with_twin,
    sample_triplane,
)
from lp3d.render.triplane import TriplaneData

TOL = {"features": 1e-4, "rgb": 1e-4, "depth": 1e-4, "weights_sum": 1e-5}

CAMERA_SETS = {
    "frontal-yaw45": [look_at_camera(), look_at_camera(yaw_deg=45.0), look_at_camera(yaw_deg=-45.0)],
    "pitch25-roll": [
        look_at_camera(pitch_deg=25.0),
        look_at_camera(pitch_deg=-25.0),
        look_at_camera(yaw_deg=10.0, pitch_deg=5.0, roll_deg=30.0),
    ],
    "offcentre": [
        look_at_camera(cx=0.42, cy=0.58, focal=3.6),
        look_at_camera(yaw_deg=20.0, pitch_deg=-10.0, cx=0.55, cy=0.47),
        look_at_camera(yaw_deg=-30.0, roll_deg=-15.0, cx=0.6, cy=0.4, focal=5.0),
    ],
}


def _planes(rng: np.random.Generator, height: int, width: int, *, smooth: int | None = None) -> np.ndarray:
    """Random (3, 32, H, W) float32 planes with unit std: white noise, or noise on a ``smooth`` grid
    upsampled bicubically (texel-to-texel changes small, as in a trained triplane)."""
    if smooth is None:
        return rng.standard_normal((3, 32, height, width)).astype(np.float32)
    low = torch.from_numpy(rng.standard_normal((3, 32, smooth, smooth)))
    up = F.interpolate(low, size=(height, width), mode="bicubic", align_corners=False)
    return (up / up.std()).numpy().astype(np.float32)


def _triplane(seed: int, height: int = 32, width: int = 32, *, decoder: str = "realistic") -> TriplaneData:
    """A random triplane with effective decoder weights at EG3D's scales (w0 ~ N/sqrt(32), w1 ~ N/8).

    ``decoder="dense"``: the density row is rescaled so that raw densities inside the box spread with
    std 5 (sigma from ~1e-6 to ~15) and empty space (zero features) decodes to raw -4: opaque and
    nearly empty rays side by side, on smooth planes.
    """
    rng = np.random.default_rng(seed)
    planes = _planes(rng, height, width, smooth=6 if decoder == "dense" else None)
    w0 = (rng.standard_normal((64, 32)) / math.sqrt(32)).astype(np.float32)
    b0 = (0.1 * rng.standard_normal(64)).astype(np.float32)
    w1 = (rng.standard_normal((33, 64)) / 8).astype(np.float32)
    b1 = (0.1 * rng.standard_normal(33)).astype(np.float32)
    if decoder == "dense":
        points = rng.uniform(-0.5, 0.5, (2048, 3))
        hidden = reference.softplus(reference.sample_triplane(planes, points) @ w0.T.astype(np.float64) + b0)
        w1[0] = (w1[0] * (5.0 / np.std(hidden @ w1[0]))).astype(np.float32)
        b1[0] = np.float32(-4.0 - reference.softplus(b0.astype(np.float64)) @ w1[0])
    return TriplaneData(planes=planes, w0=w0, b0=b0, w1=w1, b1=b1)


def _torch_args(tri: TriplaneData, dtype: torch.dtype = torch.float32) -> list[torch.Tensor]:
    return [
        torch.tensor(np.asarray(getattr(tri, k)), dtype=dtype) for k in ("planes", "w0", "b0", "w1", "b1")
    ]


def _max_errors(out: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> dict[str, float]:
    assert out.keys() == ref.keys()
    for key, value in ref.items():
        assert out[key].shape == value.shape, key
    return {key: float(np.max(np.abs(out[key].astype(np.float64) - ref[key]))) for key in ref}


def _assert_parity(out: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> None:
    errors = _max_errors(out, ref)
    bad = {key: err for key, err in errors.items() if not err <= TOL[key]}
    assert not bad, f"max abs errors {errors} exceed {TOL}"


# -------------------------------------------------------------------------------- parity with reference

PARITY_CASES = {
    # id: (decoder, (H, W), cameras, R, S, N, deterministic, white_back)
    "realistic-32-frontal-yaw-12+12": ("realistic", (32, 32), "frontal-yaw45", 17, 12, 12, True, False),
    "realistic-32-pitch-roll-24+24": ("realistic", (32, 32), "pitch25-roll", 17, 24, 24, True, False),
    "realistic-64x48-offcentre-12+12": ("realistic", (64, 48), "offcentre", 17, 12, 12, True, False),
    "realistic-64-R1-24+24": ("realistic", (64, 64), "frontal-yaw45", 1, 24, 24, True, False),
    "realistic-32-jitter-12+12": ("realistic", (32, 32), "pitch25-roll", 17, 12, 12, False, False),
    "realistic-32-R1-jitter-12+12": ("realistic", (32, 32), "offcentre", 1, 12, 12, False, False),
    "dense-32-frontal-yaw-12+12": ("dense", (32, 32), "frontal-yaw45", 17, 12, 12, True, False),
    "dense-64x48-pitch-roll-jitter-24+24": ("dense", (64, 48), "pitch25-roll", 17, 24, 24, False, False),
    "dense-32-offcentre-coarse-white": ("dense", (32, 32), "offcentre", 17, 24, 0, True, True),
}


@pytest.mark.parametrize("case", list(PARITY_CASES), ids=list(PARITY_CASES))
def test_parity_with_reference(case: str) -> None:
    decoder, (height, width), camera_set, res, s, n, deterministic, white_back = PARITY_CASES[case]
    tri = _triplane(sum(map(ord, case)), height, width, decoder=decoder)
    cameras = stack_labels(CAMERA_SETS[camera_set])
    settings = {
        "resolution": res,
        "depth_resolution": s,
        "depth_resolution_importance": n,
        "white_back": white_back,
        "deterministic": deterministic,
        "seed": 1234,
    }
    ref = reference.render_reference(tri, cameras, **settings)
    out = render_with_twin(tri, cameras, **settings)
    assert all(value.dtype == np.float32 for value in out.values())
    _assert_parity(out, ref)


def test_parity_one_triplane_per_camera() -> None:
    """Planes (B, 3, 32, H, W), as in training: camera b renders triplane b."""
    tris = [_triplane(10 + b) for b in range(3)]
    cameras = stack_labels(CAMERA_SETS["frontal-yaw45"])
    settings = {"resolution": 17, "depth_resolution": 12, "depth_resolution_importance": 12}
    args = [torch.stack(parts) for parts in zip(*(_torch_args(tri) for tri in tris), strict=True)]
    out = render_torch(args[0], *(a[0] for a in args[1:]), torch.tensor(cameras), **settings)
    # The decoder is shared in training; give every triplane the first one's for the reference.
    refs = [
        reference.render_reference(
            TriplaneData(planes=tri.planes, w0=tris[0].w0, b0=tris[0].b0, w1=tris[0].w1, b1=tris[0].b1),
            cameras[b],
            **settings,
        )
        for b, tri in enumerate(tris)
    ]
    # Depth clamps are batch-wide in both, and no ray here has zero weight, so per-camera refs match.
    ref = {key: np.stack([r[key] for r in refs]) for key in refs[0]}
    _assert_parity({key: value.numpy() for key, value in out.items()}, ref)


def test_float16_planes_render_like_their_float32_values() -> None:
    tri = _triplane(3)
    half = TriplaneData(planes=tri.planes.astype(np.float16), w0=tri.w0, b0=tri.b0, w1=tri.w1, b1=tri.b1)
    settings = {"resolution": 9, "depth_resolution": 12, "depth_resolution_importance": 12}
    camera = look_at_camera(yaw_deg=15.0)
    _assert_parity(
        render_with_twin(half, camera, **settings), reference.render_reference(half, camera, **settings)
    )


def test_float64_twin_matches_reference_exactly() -> None:
    """Same algorithm, same precision: agreement to rounding, even where float32 is ill-conditioned."""
    rng = np.random.default_rng(7)
    tri = _triplane(7, decoder="dense")
    planes = _planes(rng, 32, 32)  # white noise under the dense decoder: the hard case for float32
    tri = TriplaneData(planes=planes, w0=tri.w0, b0=tri.b0, w1=tri.w1, b1=tri.b1)
    cameras = stack_labels(CAMERA_SETS["offcentre"])
    settings = {
        "resolution": 17,
        "depth_resolution": 12,
        "depth_resolution_importance": 12,
        "deterministic": False,
        "seed": 9,
    }
    ref = reference.render_reference(tri, cameras, **settings)
    out = render_torch(*_torch_args(tri, torch.float64), torch.tensor(cameras), **settings)
    errors = _max_errors({key: value.numpy() for key, value in out.items()}, ref)
    assert max(errors.values()) < 1e-9, errors


@pytest.mark.parametrize("plane", [0, 1, 2])
def test_sample_triplane_reads_eg3d_plane_axes(plane: int) -> None:
    """Hand-worked: plane p holds its column index in channel 0 and its row index in channel 1, so a
    lookup returns the texel coordinates (ix, iy) of the point's (u, v) pair, which must be EG3D's
    (x, y), (x, z), (z, x) — the quirk, with no (y, z) plane."""
    height, width, box_warp = 8, 6, 1.6
    planes = torch.zeros(1, 3, 32, height, width, dtype=torch.float64)
    planes[0, plane, 0] = torch.arange(width, dtype=torch.float64)[None, :]
    planes[0, plane, 1] = torch.arange(height, dtype=torch.float64)[:, None]
    point = torch.tensor([[[0.11, -0.23, 0.31]]], dtype=torch.float64)
    u_axis, v_axis = {0: (0, 1), 1: (0, 2), 2: (2, 0)}[plane]
    u, v = (2 / box_warp * point[0, 0, a].item() for a in (u_axis, v_axis))
    ix, iy = ((u + 1) * width - 1) / 2, ((v + 1) * height - 1) / 2  # grid_sample, align_corners=False
    features = sample_triplane(planes, point, box_warp=box_warp)[0, 0] * 3  # undo the mean over planes
    torch.testing.assert_close(features[:2], torch.tensor([ix, iy], dtype=torch.float64))
    assert torch.all(features[2:] == 0)


# ------------------------------------------------------------------------------------------- gradients


def _tiny_case(seed: int = 0) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Float64 planes (3, 32, 4, 4), decoder weights and 2 cameras, all inputs needing gradients."""
    gen = torch.Generator().manual_seed(seed)
    planes = torch.randn(3, 32, 4, 4, generator=gen, dtype=torch.float64)
    w0 = torch.randn(64, 32, generator=gen, dtype=torch.float64) / math.sqrt(32)
    b0 = 0.1 * torch.randn(64, generator=gen, dtype=torch.float64)
    w1 = torch.randn(33, 64, generator=gen, dtype=torch.float64) / 8
    b1 = 0.1 * torch.randn(33, generator=gen, dtype=torch.float64)
    w1[0] *= 4  # density strong enough that weights are far from 0 and 1
    params = [p.requires_grad_() for p in (planes, w0, b0, w1, b1)]
    cameras = torch.tensor(stack_labels([look_at_camera(yaw_deg=10.0), look_at_camera(pitch_deg=-15.0)]))
    return params, cameras


def _flat_outputs(out: dict[str, torch.Tensor]) -> torch.Tensor:
    return torch.cat([out["features"].flatten(), out["depth"].flatten(), out["weights_sum"].flatten()])


GRADCHECK = {"eps": 1e-6, "atol": 1e-6, "rtol": 1e-4, "fast_mode": True}


def test_gradcheck_coarse_only() -> None:
    """The whole of ``render_torch`` (6 coarse samples) against finite differences."""
    params, cameras = _tiny_case()

    def fn(*p: torch.Tensor) -> torch.Tensor:
        out = render_torch(*p, cameras, resolution=2, depth_resolution=6, depth_resolution_importance=0)
        return _flat_outputs(out)

    assert torch.autograd.gradcheck(fn, params, **GRADCHECK)


def _fixed_fine_render(
    params: list[torch.Tensor], cameras: torch.Tensor
) -> tuple[Callable[..., torch.Tensor], torch.Tensor]:
    """6+6 render with the importance draw held fixed at the current parameters' fine depths."""
    origins, directions = rays_from_cameras(cameras, 2)
    kw = {
        "bounds": SceneBounds(box_warp=1.0, ray_start=2.25, ray_end=3.3),
        "settings": RenderSettings(depth_resolution=6, depth_resolution_importance=6),
    }
    with torch.no_grad():
        t_fine = render_rays(params[0][None], *params[1:], origins, directions, **kw)["t_fine"]

    def fn(*p: torch.Tensor) -> torch.Tensor:
        out = render_rays(p[0][None], *p[1:], origins, directions, t_fine=t_fine, **kw)
        return _flat_outputs(out)

    return fn, t_fine


def test_gradcheck_with_importance_samples() -> None:
    """6+6 samples: finite differences would also move the fine samples, whose gradient EG3D stops, so
    the check holds them fixed; ``test_importance_samples_carry_no_gradient`` ties this to render_torch."""
    params, cameras = _tiny_case(1)
    fn, _ = _fixed_fine_render(params, cameras)
    assert torch.autograd.gradcheck(fn, params, **GRADCHECK)


def test_importance_samples_carry_no_gradient() -> None:
    params, cameras = _tiny_case(2)
    out = render_torch(*params, cameras, resolution=2, depth_resolution=6, depth_resolution_importance=6)
    loss = _flat_outputs(out).pow(2).sum()
    grads = torch.autograd.grad(loss, params)
    fn, _ = _fixed_fine_render(params, cameras)
    fixed_grads = torch.autograd.grad(fn(*params).pow(2).sum(), params)
    for got, want in zip(grads, fixed_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------- batching and clamping


def test_batched_equals_one_by_one() -> None:
    tris = [_triplane(20 + b) for b in range(3)]
    args = [torch.stack(parts) for parts in zip(*(_torch_args(tri) for tri in tris), strict=True)]
    planes, decoder = args[0], [a[0] for a in args[1:]]
    cameras = torch.tensor(stack_labels(CAMERA_SETS["pitch25-roll"]))
    settings = {"resolution": 9, "depth_resolution": 12, "depth_resolution_importance": 12}
    batched = render_torch(planes, *decoder, cameras, **settings)
    for b in range(3):
        single = render_torch(planes[b], *decoder, cameras[b], **settings)
        for key, value in single.items():
            torch.testing.assert_close(batched[key][b], value, rtol=0, atol=1e-6)
    # The shared-triplane path (planes (3, 32, H, W), cameras (B, 25)) gives the same as repeating it.
    shared = render_torch(planes[0], *decoder, cameras, **settings)
    repeated = render_torch(planes[:1].expand(3, -1, -1, -1, -1), *decoder, cameras, **settings)
    for key in shared:
        torch.testing.assert_close(shared[key], repeated[key], rtol=0, atol=1e-6)


def test_empty_rays_take_the_batch_max_depth() -> None:
    """W = 0 (density -1000 everywhere): EG3D's NaN depth → +inf → clamped to the largest sample depth
    of the whole batch; features -1 (or +1 with white_back); gradients finite, not NaN."""
    params, cameras = _tiny_case()
    planes, w0, b0, w1, b1 = (p.detach().float().requires_grad_() for p in params)
    with torch.no_grad():
        b1[0] = -1000.0
    settings = {"resolution": 3, "depth_resolution": 8, "depth_resolution_importance": 8}
    out = render_torch(planes, w0, b0, w1, b1, cameras, **settings)
    assert torch.all(out["weights_sum"] == 0)
    assert torch.all(out["features"] == -1)
    assert torch.all(out["depth"] == torch.tensor(3.3, dtype=torch.float32))
    out["depth"].sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in (planes, w0, b0, w1, b1))

    white = render_torch(planes, w0, b0, w1, b1, cameras, white_back=True, **settings)
    assert torch.all(white["features"] == 1)

    # Jittered, the largest sample depth differs per camera, and every empty ray gets the batch's.
    jittered = dict(settings, deterministic=False, seed=3)
    batch = render_torch(planes, w0, b0, w1, b1, cameras, **jittered)
    assert torch.unique(batch["depth"]).numel() == 1
    ref = reference.render_reference(
        TriplaneData(*(p.detach().numpy() for p in (planes, w0, b0, w1, b1))), cameras.numpy(), **jittered
    )
    np.testing.assert_allclose(batch["depth"].detach().numpy(), ref["depth"], rtol=0, atol=1e-6)


def test_chunking_does_not_change_results() -> None:
    tri = _triplane(4)
    args = _torch_args(tri)
    cameras = torch.tensor(stack_labels(CAMERA_SETS["offcentre"]))
    settings = {
        "resolution": 7,
        "depth_resolution": 12,
        "depth_resolution_importance": 12,
        "deterministic": False,
        "seed": 5,
    }
    whole = render_torch(*args, cameras, **settings)
    chunked = render_torch(*args, cameras, ray_chunk=10, **settings)  # 3 rays per camera per chunk
    for key in whole:
        torch.testing.assert_close(chunked[key], whole[key], rtol=0, atol=1e-6)


def test_output_shapes_and_batch_axis() -> None:
    args = _torch_args(_triplane(5))
    camera = torch.tensor(look_at_camera())
    settings = {"resolution": 3, "depth_resolution": 4, "depth_resolution_importance": 2}
    expected = {"features": (32, 3, 3), "rgb": (3, 3, 3), "depth": (3, 3), "weights_sum": (3, 3)}
    single = render_torch(*args, camera, **settings)
    assert {k: tuple(v.shape) for k, v in single.items()} == expected
    for planes, cams in ((args[0], camera[None]), (args[0][None], camera), (args[0][None], camera[None])):
        out = render_torch(planes, *args[1:], cams, **settings)
        assert {k: tuple(v.shape) for k, v in out.items()} == {k: (1, *v) for k, v in expected.items()}
        torch.testing.assert_close(out["features"][0], single["features"], rtol=0, atol=0)
    torch.testing.assert_close(single["rgb"], single["features"][:3], rtol=0, atol=0)
    assert all(v.dtype == torch.float32 for v in single.values())
    as64 = render_torch(*(a.double() for a in args), camera, **settings)
    assert all(v.dtype == torch.float64 for v in as64.values())


def _bad_inputs() -> dict[str, tuple[str, Callable[[list[torch.Tensor], torch.Tensor], dict[str, object]]]]:
    """id → (word the message must contain, function editing the keyword arguments of render_torch)."""

    def nan_planes(a: list[torch.Tensor], c: torch.Tensor) -> dict[str, object]:
        return {"planes": a[0].clone().index_fill_(1, torch.tensor([0]), math.nan)}

    return {
        "planes-shape": ("planes", lambda a, c: {"planes": a[0][:, :16]}),
        "planes-nan": ("planes", nan_planes),
        "planes-int": ("planes", lambda a, c: {"planes": a[0].int()}),
        "planes-half": ("planes", lambda a, c: {"planes": a[0].half()}),
        "w0-shape": ("w0", lambda a, c: {"w0": a[1].T}),
        "b1-dtype": ("b1", lambda a, c: {"b1": a[4].double()}),
        "w1-inf": ("w1", lambda a, c: {"w1": a[3].clone().fill_(math.inf)}),
        "cameras-shape": ("cameras", lambda a, c: {"cameras": c[:, :16]}),
        "cameras-nan": ("cameras", lambda a, c: {"cameras": c.clone().fill_(math.nan)}),
        "cameras-focal": (
            "focal",
            lambda a, c: {"cameras": c.clone().index_fill_(1, torch.tensor([16]), 0.0)},
        ),
        "batch-mismatch": ("triplanes", lambda a, c: {"planes": a[0][None].expand(3, -1, -1, -1, -1)}),
        "ray-range": ("ray_start", lambda a, c: {"ray_start": 3.3, "ray_end": 2.25}),
        "box-warp": ("box_warp", lambda a, c: {"box_warp": 0.0}),
        "resolution": ("resolution", lambda a, c: {"resolution": 0}),
        "samples": ("depth_resolution", lambda a, c: {"depth_resolution": 3}),
        "importance": ("depth_resolution_importance", lambda a, c: {"depth_resolution_importance": 1}),
        "ray-chunk": ("ray_chunk", lambda a, c: {"ray_chunk": 0}),
    }


@pytest.mark.parametrize("case", list(_bad_inputs()))
def test_invalid_inputs_raise_clear_errors(case: str) -> None:
    word, edit = _bad_inputs()[case]
    args = _torch_args(_triplane(6, 8, 8))
    cameras = torch.tensor(stack_labels(CAMERA_SETS["frontal-yaw45"][:2]))
    kwargs: dict[str, object] = dict(zip(("planes", "w0", "b0", "w1", "b1"), args, strict=True))
    kwargs.update(cameras=cameras, resolution=2, depth_resolution=4, depth_resolution_importance=2)
    kwargs.update(edit(args, cameras))
    positional = [kwargs.pop(k) for k in ("planes", "w0", "b0", "w1", "b1", "cameras")]
    with pytest.raises(ValueError, match=word):
        render_torch(*positional, **kwargs)  # type: ignore[arg-type]


def test_non_tensor_inputs_raise_type_errors() -> None:
    args = _torch_args(_triplane(6, 8, 8))
    with pytest.raises(TypeError, match="planes"):
        render_torch(args[0].numpy(), *args[1:], torch.tensor(look_at_camera()))  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="triplane"):
        render_with_twin(object(), look_at_camera())  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------------- CUDA


@pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device (CI has none; the one GPU-only test)"
)
def test_cuda_matches_cpu_and_reference() -> None:
    tri = _triplane(8, 64, 48, decoder="dense")
    cameras = stack_labels(CAMERA_SETS["pitch25-roll"])
    settings = {
        "resolution": 17,
        "depth_resolution": 24,
        "depth_resolution_importance": 24,
        "deterministic": False,
        "seed": 11,
    }
    ref = reference.render_reference(tri, cameras, **settings)
    _assert_parity(render_with_twin(tri, cameras, device="cuda", **settings), ref)

    cpu_args = [a.requires_grad_() for a in _torch_args(tri)]
    cuda_args = [a.detach().cuda().requires_grad_() for a in cpu_args]
    grads = []
    for args, cams in ((cpu_args, torch.tensor(cameras)), (cuda_args, torch.tensor(cameras).cuda())):
        out = render_torch(*args, cams, **settings)
        assert all(v.device == args[0].device for v in out.values())
        (out["rgb"].square().mean() + out["depth"].mean()).backward()
        grads.append([a.grad.cpu() for a in args])
    # Sums run in another order on the GPU (atomics, scans), so compare relative to each gradient's scale.
    for got, want in zip(grads[1], grads[0], strict=True):
        torch.testing.assert_close(got, want, rtol=1e-3, atol=1e-4 * want.abs().max().item())
