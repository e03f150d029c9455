"""Check lp3d's EG3D path against NVlabs/eg3d's own source, end to end, and print one table.

    python scripts/eg3d_check.py --eg3d-source /path/to/eg3d/eg3d [--work DIR] [--device cpu]
                                 [--resolution 128] [--seed 0] [--table docs/eg3d-check.md]

EG3D is not a dependency of lp3d and its source is not copied here: the script imports it at run time
from ``--eg3d-source`` (NVlabs/eg3d's ``eg3d/`` folder, the one holding ``training/``, ``torch_utils/``,
``dnnlib/``, ``legacy.py`` and ``camera_utils.py``; the repository root is accepted too). No pretrained
weights are needed. Every step is a subprocess; EG3D's source is on ``sys.path`` only in the two EG3D
steps, never in lp3d's (lp3d's loader puts it there while unpickling, as it does for users).

1. ``build`` (EG3D's process): EG3D's ``TriPlaneGenerator`` with the FFHQ 512-128 settings of its
   ``train.py --cfg=ffhq --gen_pose_cond=True`` (``SuperresolutionHybrid8XDC``, 256² triplanes,
   neural rendering resolution 128), random weights (``torch.manual_seed(--seed)``), and its
   ``DualDiscriminator``, pickled as ``training/training_loop.py`` writes a network snapshot: a dict
   with ``training_set_kwargs``, ``G``, ``D``, ``G_ema`` and ``augment_pipe`` (None), each module a
   ``deepcopy(...).eval().requires_grad_(False).cpu()``.
2. ``eg3d-reference`` (EG3D's process): loads the pickle with EG3D's ``legacy.load_network_pkl``;
   draws z as ``gen_samples.py``/``gen_videos.py`` do and maps it with each script's conditioning
   camera (truncation 0.7, cutoff 14); the backbone's planes (``noise_mode="const"``); then
   ``G_ema.synthesis`` at ``--resolution``² with the generator's own 48+48 samples from a camera
   off the frontal view, with its renderer's two random draws (the coarse jitter's
   ``torch.rand_like`` and ``sample_pdf(det=False)``) switched to the deterministic mode from
   outside; a hook on the super-resolution module records the feature image it is given. Also
   EG3D's super-resolution of that feature image with the paper's constant w = 1.
3. ``lp3d-compare`` (lp3d's process): ``EG3DTeacher.from_pickle(..., eg3d_source=...)``; its ws and
   planes against EG3D's; ``lp3d_render`` and the torch twin on EG3D's planes against EG3D's render
   (rgb, features, depth); the teacher's super-resolution against EG3D's, given the same w and
   feature image.
4. For each training configuration, ``tiny`` (lp3d's default, the CPU recipe with its cached
   synthetic dataset, here of 8 identities in the work folder) and ``tiny-paper`` (the paper recipe
   that ``lt`` and ``full`` use, at the same size):

   * ``train``: ``python -m lp3d.train --config C --teacher eg3d --teacher-pkl G.pkl
     --eg3d-source SRC --max-steps 2``; the checkpoint must record the teacher's pickle and source;
   * ``eval``: ``lp3d eval RUN --teacher-pkl G.pkl --eg3d-source SRC`` (2 identities, no
     baseline);
   * ``export``: ``lp3d export RUN -o model-C.onnx`` (its own onnxruntime check);
   * ``encode``: ``lp3d encode`` of EG3D's super-resolved image with that model.

Each step is timed; a failed step is reported with the end of its log (all logs are in
``WORK/logs/``) and the steps that need it are skipped. The table (markdown) is printed and, with
``--table FILE``, written into FILE between ``<!-- eg3d-check:begin -->`` and
``<!-- eg3d-check:end -->`` (the rest of FILE is kept; the write is atomic). Exit status 0 when every
check passed, 1 when one failed, 2 for a usage error.

Work folder: ``--work DIR`` (new or empty; kept afterwards), else a temporary folder removed at the
end. It needs about 0.5 GB (the pickle alone is ~380 MB). Most of its time is the two train and
eval steps; each step has a time limit (``--step-timeout``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: What must exist in EG3D's source folder for this check (relative to its ``eg3d/`` folder).
EG3D_FILES = (
    "training/triplane.py",
    "training/dual_discriminator.py",
    "training/superresolution.py",
    "training/volumetric_rendering/renderer.py",
    "torch_utils/persistence.py",
    "dnnlib/__init__.py",
    "legacy.py",
    "camera_utils.py",
)
#: EG3D's top-level packages; none may be importable from its source in lp3d's processes.
EG3D_PACKAGES = ("torch_utils", "dnnlib", "training")

SECTION_BEGIN = "<!-- eg3d-check:begin -->"
SECTION_END = "<!-- eg3d-check:end -->"

#: Pass thresholds (max abs difference). Renders: the repository's WGSL/twin parity tolerance
#: (tests/render/test_render_parity.py); the others compare the same float32 arithmetic in two processes.
TOL_WS = 1e-5
TOL_PLANES = 1e-4
TOL_RENDER = 1e-4
TOL_SR = 1e-4

#: The generator's settings: EG3D's train.py for ``--cfg=ffhq --gen_pose_cond=True`` (EG3D's README
#: FFHQ command) with train.py's defaults for the rest, at the 512-128 checkpoints' final neural
#: rendering resolution.
FFHQ_RENDERING_KWARGS: dict[str, Any] = {
    "image_resolution": 512,
    "disparity_space_sampling": False,
    "clamp_mode": "softplus",
    "superresolution_module": "training.superresolution.SuperresolutionHybrid8XDC",
    "c_gen_conditioning_zero": False,
    "gpc_reg_prob": 0.5,
    "c_scale": 1.0,
    "superresolution_noise_mode": "none",
    "density_reg": 0.25,
    "density_reg_p_dist": 0.004,
    "reg_type": "l1",
    "decoder_lr_mul": 1.0,
    "sr_antialias": True,
    "depth_resolution": 48,
    "depth_resolution_importance": 48,
    "ray_start": 2.25,
    "ray_end": 3.3,
    "box_warp": 1,
    "avg_camera_radius": 2.7,
    "avg_camera_pivot": [0, 0, 0.2],
}
NEURAL_RENDERING_RESOLUTION = 128
TRUNCATION_PSI, TRUNCATION_CUTOFF = 0.7, 14
#: Render camera of the comparison (EG3D's LookAtPoseSampler angles, radians off the frontal view).
RENDER_YAW, RENDER_PITCH = 0.35, -0.15


# ================================================================================== EG3D-side steps
# These run in a process with EG3D's source first on sys.path and import nothing of lp3d.


def _eg3d_build(cfg: dict[str, Any]) -> dict[str, Any]:
    """A random-weight FFHQ 512-128 generator and discriminator, pickled as EG3D's training loop does."""
    import copy
    import pickle

    import dnnlib  # type: ignore[import-not-found]
    import torch

    torch.manual_seed(int(cfg["seed"]))
    common = dict(c_dim=25, img_resolution=512, img_channels=3)
    g_kwargs = dnnlib.EasyDict(
        class_name="training.triplane.TriPlaneGenerator",
        z_dim=512,
        w_dim=512,
        mapping_kwargs=dnnlib.EasyDict(num_layers=2),
        channel_base=32768,
        channel_max=512,
        fused_modconv_default="inference_only",
        rendering_kwargs=dict(FFHQ_RENDERING_KWARGS),
        num_fp16_res=0,
        conv_clamp=None,
        sr_num_fp16_res=4,
        sr_kwargs=dnnlib.EasyDict(
            channel_base=32768, channel_max=512, fused_modconv_default="inference_only"
        ),
    )
    d_kwargs = dnnlib.EasyDict(
        class_name="training.dual_discriminator.DualDiscriminator",
        channel_base=32768,
        channel_max=512,
        block_kwargs=dnnlib.EasyDict(freeze_layers=0),
        mapping_kwargs=dnnlib.EasyDict(),
        epilogue_kwargs=dnnlib.EasyDict(mbstd_group_size=4),
        disc_c_noise=0,
        num_fp16_res=4,
        conv_clamp=256,
    )
    G = dnnlib.util.construct_class_by_name(**g_kwargs, **common).train().requires_grad_(False)
    # The training loop registers the dataset's label std; a placeholder of the right shape here.
    G.register_buffer("dataset_label_std", torch.ones(25))
    G.neural_rendering_resolution = NEURAL_RENDERING_RESOLUTION
    D = dnnlib.util.construct_class_by_name(**d_kwargs, **common).train().requires_grad_(False)
    G_ema = copy.deepcopy(G).eval()
    training_set_kwargs = dnnlib.EasyDict(
        class_name="training.dataset.ImageFolderDataset",
        path="FFHQ_512.zip",
        use_labels=True,
        max_size=None,
        xflip=False,
        resolution=512,
        random_seed=0,
    )
    snapshot: dict[str, Any] = {"training_set_kwargs": dict(training_set_kwargs)}
    for name, module in [("G", G), ("D", D), ("G_ema", G_ema), ("augment_pipe", None)]:
        if module is not None:
            module = copy.deepcopy(module).eval().requires_grad_(False).cpu()
        snapshot[name] = module
    pkl = Path(cfg["pkl"])
    tmp = pkl.with_name(f".{pkl.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            pickle.dump(snapshot, f)
        os.replace(tmp, pkl)
    finally:
        tmp.unlink(missing_ok=True)
    g_params = sum(p.numel() for p in G.parameters())
    d_params = sum(p.numel() for p in D.parameters())
    sr = type(G.superresolution).__name__
    return {
        "rows": [
            {
                "name": "build",
                "ok": sr == "SuperresolutionHybrid8XDC" and pkl.stat().st_size > 0,
                "measured": f"TriPlaneGenerator {g_params / 1e6:.1f}M parameters ({sr}), "
                f"DualDiscriminator {d_params / 1e6:.1f}M; G.pkl {pkl.stat().st_size / 1e6:.0f} MB "
                f"({', '.join(snapshot)})",
            }
        ]
    }


class _TorchWithoutJitter:
    """``torch`` as EG3D's renderer module sees it, ``rand_like`` returning zeros (no coarse jitter)."""

    def __init__(self, torch: Any) -> None:
        self._torch = torch

    def __getattr__(self, name: str) -> Any:
        if name == "rand_like":
            return self._torch.zeros_like
        return getattr(self._torch, name)


def _eg3d_reference(cfg: dict[str, Any]) -> dict[str, Any]:
    """EG3D's own ws, planes, un-jittered render and super-resolution for one seed."""
    import functools
    from unittest import mock

    import legacy  # type: ignore[import-not-found]
    import torch
    import training.volumetric_rendering.renderer as renderer_module  # type: ignore[import-not-found]
    from camera_utils import FOV_to_intrinsics, LookAtPoseSampler  # type: ignore[import-not-found]

    device = torch.device(cfg["device"])
    start = time.perf_counter()
    with open(cfg["pkl"], "rb") as f:
        data = legacy.load_network_pkl(f)  # also checks the snapshot's layout
    G = data["G_ema"].to(device)
    load_s = time.perf_counter() - start
    rk = G.rendering_kwargs
    pivot = torch.tensor(rk["avg_camera_pivot"], device=device)
    radius = rk["avg_camera_radius"]

    def label(pose: Any, intrinsics: Any) -> Any:
        return torch.cat([pose.reshape(-1, 16), intrinsics.reshape(-1, 9)], 1)

    # The conditioning cameras exactly as EG3D's scripts build them.
    k_videos = torch.tensor([[4.2647, 0, 0.5], [0, 4.2647, 0.5], [0, 0, 1]], device=device)  # gen_videos.py
    c_videos = label(
        LookAtPoseSampler.sample(3.14 / 2, 3.14 / 2, pivot, radius=radius, device=device), k_videos
    )
    k_samples = FOV_to_intrinsics(18.837, device=device)  # gen_samples.py's default --fov-deg
    c_samples = label(
        LookAtPoseSampler.sample(np.pi / 2, np.pi / 2, pivot, radius=radius, device=device), k_samples
    )
    seed = int(cfg["seed"])
    z = torch.from_numpy(np.random.RandomState(seed).randn(1, G.z_dim)).to(device)
    c_render = label(
        LookAtPoseSampler.sample(
            np.pi / 2 + RENDER_YAW, np.pi / 2 + RENDER_PITCH, pivot, radius=radius, device=device
        ),
        k_videos,
    )
    resolution = int(cfg["resolution"])
    captured: dict[str, Any] = {}

    def record_sr_input(_module: Any, args: tuple[Any, ...]) -> None:
        captured["features"] = args[1].detach().clone()  # superresolution(rgb, feature_image, ws, ...)

    start = time.perf_counter()
    with torch.no_grad():
        ws_videos = G.mapping(z, c_videos, truncation_psi=TRUNCATION_PSI, truncation_cutoff=TRUNCATION_CUTOFF)
        ws_samples = G.mapping(
            z, c_samples, truncation_psi=TRUNCATION_PSI, truncation_cutoff=TRUNCATION_CUTOFF
        )
        planes = G.backbone.synthesis(ws_samples, update_emas=False, noise_mode="const")
        hook = G.superresolution.register_forward_pre_hook(record_sr_input)
        no_pdf_jitter = functools.partial(G.renderer.sample_pdf, det=True)
        try:
            with (
                mock.patch.object(renderer_module, "torch", _TorchWithoutJitter(torch)),
                mock.patch.object(G.renderer, "sample_pdf", no_pdf_jitter),
            ):
                out = G.synthesis(
                    ws_samples, c_render, neural_rendering_resolution=resolution, noise_mode="const"
                )
        finally:
            hook.remove()
        features = captured["features"]
        depth = out["image_depth"]
        ones = torch.ones_like(ws_samples)
        sr_ones = G.superresolution(
            features[:, :3], features, ones, noise_mode=rk["superresolution_noise_mode"]
        )
    render_s = time.perf_counter() - start

    def np32(t: Any) -> np.ndarray:
        return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())

    np.savez(
        cfg["reference"],
        z=z.cpu().numpy(),
        c_videos=np32(c_videos[0]),
        c_samples=np32(c_samples[0]),
        camera=np32(c_render[0]),
        ws_videos=np32(ws_videos[0]),
        ws_samples=np32(ws_samples[0]),
        planes=np32(planes[0]),
        features=np32(features[0]),
        rgb=np32(out["image_raw"][0]),
        depth=np32(depth[0, 0]),
        image=np32(out["image"][0]),
        image_ones=np32(sr_ones[0]),
    )
    return {
        "rows": [
            {
                "name": "eg3d-reference",
                "ok": tuple(features.shape) == (1, 32, resolution, resolution)
                and tuple(out["image"].shape) == (1, 3, 512, 512),
                "measured": f"legacy.load_network_pkl {load_s:.1f} s; mapping, planes "
                f"{tuple(planes.shape[1:])}, un-jittered synthesis at {resolution}² "
                f"({rk['depth_resolution']}+{rk['depth_resolution_importance']}) and SR to 512² "
                f"{render_s:.1f} s; the render's spread: features std {float(features.std()):.2f}, "
                f"depth {float(depth.min()):.3f} to {float(depth.max()):.3f}",
            }
        ]
    }


# ================================================================================== lp3d-side step


def _eg3d_importable_from(src: Path) -> list[str]:
    """EG3D packages this process could import from ``src`` (should be none in lp3d's processes)."""
    import importlib.util

    found = []
    for name in EG3D_PACKAGES:
        spec = importlib.util.find_spec(name) if name not in sys.modules else sys.modules[name].__spec__
        origin = getattr(spec, "origin", None) or ""
        locations = [origin, *(getattr(spec, "submodule_search_locations", None) or [])]
        if spec is not None and any(loc and Path(loc).resolve().is_relative_to(src) for loc in locations):
            found.append(name)
    return found


def _max_abs(a: Any, b: Any) -> float:
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    return float(np.abs(a - b).max())


def _lp3d_compare(cfg: dict[str, Any]) -> dict[str, Any]:
    """lp3d loads the pickle without EG3D on its path and reproduces EG3D's ws, planes, renders and SR."""
    import torch

    src = Path(cfg["eg3d_source"])
    rows: list[dict[str, Any]] = []
    leaked = _eg3d_importable_from(src)
    if leaked:
        raise RuntimeError(f"EG3D's {', '.join(leaked)} importable in lp3d's process before loading")

    import lp3d_render
    from lp3d.render.torch_twin import render_with_twin
    from lp3d.render.triplane import TriplaneData
    from lp3d.teachers.eg3d import EG3DTeacher

    ref = dict(np.load(cfg["reference"], allow_pickle=False))
    seed, resolution = int(cfg["seed"]), int(cfg["resolution"])

    start = time.perf_counter()
    teacher = EG3DTeacher.from_pickle(
        cfg["pkl"], eg3d_source=src, device=cfg["device"], conditioning="gen_samples"
    )
    load_s = time.perf_counter() - start
    on_path = [p for p in sys.path if p and Path(p).resolve() == src]
    rows.append(
        {
            "name": "load",
            "ok": not on_path,
            "measured": f"{type(teacher.generator).__name__} loaded in {load_s:.1f} s; EG3D's source "
            + ("still on sys.path afterwards" if on_path else "not on sys.path before or after"),
            "seconds": load_s,
        }
    )
    gen = teacher.generator
    settings = teacher.render_settings(resolution=resolution)

    def row_check(name: str, tol: float, what: Callable[[], tuple[str, float]]) -> None:
        start = time.perf_counter()
        try:
            text, err = what()
            rows.append(
                {"name": name, "ok": err <= tol, "measured": text, "seconds": time.perf_counter() - start}
            )
        except Exception as e:  # one failed comparison does not hide the others
            rows.append({"name": name, "ok": False, "measured": f"{type(e).__name__}: {e}"})

    def ws_row(conditioning: str, key: str) -> tuple[str, float]:
        t = (
            teacher
            if conditioning == "gen_samples"
            else EG3DTeacher(gen, device=cfg["device"], conditioning="gen_videos")
        )
        ws = t.latents([seed])[0].cpu().numpy()
        err = _max_abs(ws, ref[key])
        pose = _max_abs(
            t.conditioning_pose, ref["c_samples" if conditioning == "gen_samples" else "c_videos"]
        )
        return f"max abs Δ ws {err:.1e} (conditioning camera Δ {pose:.1e})", err

    row_check(
        "ws: conditioning='gen_videos' (the default) vs gen_videos.py",
        TOL_WS,
        lambda: ws_row("gen_videos", "ws_videos"),
    )
    row_check(
        "ws: conditioning='gen_samples' vs gen_samples.py",
        TOL_WS,
        lambda: ws_row("gen_samples", "ws_samples"),
    )

    def planes_row() -> tuple[str, float]:
        planes = teacher.planes([seed])[0].cpu().numpy()
        err = _max_abs(planes.reshape(96, *planes.shape[-2:]), ref["planes"])
        return f"{tuple(planes.shape)}: max abs Δ {err:.1e}", err

    row_check("planes (teacher.planes)", TOL_PLANES, planes_row)

    w0, b0, w1, b1 = teacher.decoder()
    rk = teacher.rendering_kwargs
    tri = TriplaneData(
        planes=ref["planes"].reshape(3, 32, *ref["planes"].shape[-2:]),
        w0=w0,
        b0=b0,
        w1=w1,
        b1=b1,
        box_warp=float(rk["box_warp"]),
        ray_start=float(rk["ray_start"]),
        ray_end=float(rk["ray_end"]),
    )
    camera = ref["camera"]
    samples = f"{settings.depth_resolution}+{settings.depth_resolution_importance}"

    def render_errors(out: dict[str, np.ndarray], who: str) -> tuple[str, float]:
        errs = {
            "rgb": _max_abs(out["rgb"], ref["rgb"]),
            "features": _max_abs(out["features"], ref["features"]),
            "depth": _max_abs(out["depth"], ref["depth"]),
        }
        text = f"{who} {resolution}², {samples}: max abs Δ " + ", ".join(
            f"{k} {v:.1e}" for k, v in errs.items()
        )
        return text, max(errs.values())

    def wgsl_row() -> tuple[str, float]:
        out = lp3d_render.render(
            tri.to_native(),
            camera,
            resolution=resolution,
            depth_resolution=settings.depth_resolution,
            depth_resolution_importance=settings.depth_resolution_importance,
        )
        return render_errors(out, "lp3d_render")

    def twin_row() -> tuple[str, float]:
        out = render_with_twin(
            tri,
            camera,
            resolution=resolution,
            depth_resolution=settings.depth_resolution,
            depth_resolution_importance=settings.depth_resolution_importance,
            device=cfg["device"],
        )
        return render_errors(out, "torch twin")

    row_check("render: lp3d_render vs EG3D", TOL_RENDER, wgsl_row)
    row_check("render: torch twin vs EG3D", TOL_RENDER, twin_row)

    features = torch.from_numpy(ref["features"][None])

    def sr_row(sr_w: Any, key: str, label: str) -> tuple[str, float]:
        t = EG3DTeacher(gen, device=cfg["device"], sr_w=sr_w)
        image = t.superresolve(features)[0].cpu().numpy()
        err = _max_abs(image, ref[key])
        return f"{label}: {tuple(image.shape)}, max abs Δ {err:.1e}", err

    own_w = torch.from_numpy(ref["ws_samples"][-1])
    row_check(
        "SR: teacher.superresolve vs G.synthesis",
        TOL_SR,
        lambda: sr_row(own_w, "image", "sr_w = the sample's w, vs EG3D's synthesis image"),
    )
    row_check(
        "SR: sr_w='ones' vs EG3D's SR with w = 1",
        TOL_SR,
        lambda: sr_row("ones", "image_ones", "the paper's constant w"),
    )
    return {"rows": rows}


WORKERS: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {
    "eg3d-build": _eg3d_build,
    "eg3d-reference": _eg3d_reference,
    "lp3d-compare": _lp3d_compare,
}


def _run_worker(name: str, config: Path) -> int:
    cfg = json.loads(config.read_text())
    result = WORKERS[name](cfg)
    out = Path(cfg["results"]) / f"{name}.json"
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(result, indent=1))
    os.replace(tmp, out)
    return 0


# ================================================================================== orchestration


@dataclasses.dataclass
class Row:
    """One line of the table."""

    step: str
    ok: bool | None  # None: skipped
    measured: str
    seconds: float | None = None


@dataclasses.dataclass(frozen=True)
class Step:
    name: str
    what: str
    needs: tuple[str, ...]
    run: Callable[[Check], list[Row]]


class StepError(Exception):
    """A step failed; the message says how (and where its log is)."""


@dataclasses.dataclass
class Check:
    """The state of one check run: settings, folders and the environments of the two sides."""

    script: Path
    eg3d_source: Path
    work: Path
    device: str
    seed: int
    resolution: int
    step_timeout: float

    @property
    def pkl(self) -> Path:
        return self.work / "G.pkl"

    @property
    def logs(self) -> Path:
        return self.work / "logs"

    def config_file(self) -> Path:
        path = self.work / "check.json"
        if not path.exists():
            cfg = {
                "eg3d_source": str(self.eg3d_source),
                "device": self.device,
                "seed": self.seed,
                "resolution": self.resolution,
                "pkl": str(self.pkl),
                "reference": str(self.work / "eg3d_reference.npz"),
                "results": str(self.work / "results"),
            }
            (self.work / "results").mkdir(exist_ok=True)
            path.write_text(json.dumps(cfg, indent=1))
        return path

    def env(self, *, eg3d: bool) -> dict[str, str]:
        """The environment of a step: EG3D's source first on PYTHONPATH for EG3D's side, and removed
        from it for lp3d's."""
        env = dict(os.environ)
        parts = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
        parts = [p for p in parts if Path(p).resolve() != self.eg3d_source]
        if eg3d:
            parts.insert(0, str(self.eg3d_source))
        env["PYTHONPATH"] = os.pathsep.join(parts)
        if not env["PYTHONPATH"]:
            del env["PYTHONPATH"]
        return env

    def run(self, name: str, argv: Sequence[str], *, eg3d: bool = False) -> str:
        """Run one subprocess in the work folder; its output goes to logs/<name>.log and is returned."""
        self.logs.mkdir(exist_ok=True)
        log = self.logs / f"{name.replace(':', '-')}.log"
        shown = f"WORK/{log.relative_to(self.work)}"  # the table names no machine paths
        with open(log, "w") as f:
            try:
                proc = subprocess.run(
                    list(argv),
                    cwd=self.work,
                    env=self.env(eg3d=eg3d),
                    stdout=f,
                    stderr=subprocess.STDOUT,
                    timeout=self.step_timeout,
                    check=False,
                )
            except subprocess.TimeoutExpired:
                raise StepError(f"no result after {self.step_timeout:.0f} s (log: {shown})") from None
        text = log.read_text(errors="replace")
        if proc.returncode != 0:
            tail = [line for line in text.splitlines() if line.strip()][-3:]
            raise StepError(f"exit status {proc.returncode}: {' | '.join(tail)} (log: {shown})")
        return text

    def worker(self, name: str, *, eg3d: bool) -> list[Row]:
        config = self.config_file()
        self.run(name, [sys.executable, str(self.script), "--worker", name, str(config)], eg3d=eg3d)
        result = json.loads((self.work / "results" / f"{name}.json").read_text())
        return [Row(r["name"], bool(r["ok"]), r["measured"], r.get("seconds")) for r in result["rows"]]

    def lp3d(self, name: str, module: str, *args: str) -> str:
        return self.run(name, [sys.executable, "-m", module, *args])


def _step_build(check: Check) -> list[Row]:
    return check.worker("eg3d-build", eg3d=True)


def _step_reference(check: Check) -> list[Row]:
    return check.worker("eg3d-reference", eg3d=True)


def _step_compare(check: Check) -> list[Row]:
    return check.worker("lp3d-compare", eg3d=False)


#: The training configurations tried: the default (CPU recipe: a cached synthetic dataset, here of
#: ``DATASET_IDENTITIES`` identities) and the paper recipe at the same tiny size (as ``lt``/``full``).
TRAIN_CONFIGS = ("tiny", "tiny-paper")
DATASET_IDENTITIES = 8


def _run_dir(config: str) -> str:
    return f"run-{config}"


def _step_train(check: Check, config: str) -> list[Row]:
    name = f"train:{config}"
    cpu_recipe = not config.endswith("-paper")  # its dataset: a few identities, cached in the work folder
    start = time.perf_counter()
    check.lp3d(
        name,
        "lp3d.train",
        *("--config", config, "--teacher", "eg3d", "--teacher-pkl", str(check.pkl)),
        *("--eg3d-source", str(check.eg3d_source), "--max-steps", "2", "--out", _run_dir(config)),
        *(
            ("--dataset-identities", str(DATASET_IDENTITIES), "--data-cache", "data-cache")
            if cpu_recipe
            else ()
        ),
        *("--device", check.device, "--no-progress"),
    )
    seconds = time.perf_counter() - start
    from lp3d.training import load_checkpoint

    ckpt = load_checkpoint(check.work / _run_dir(config))
    teacher = json.loads(ckpt.get("teacher_args") or "{}")
    recorded = teacher.get("teacher_pkl") == str(check.pkl.resolve()) and teacher.get("eg3d_source") == str(
        check.eg3d_source
    )
    ok = int(ckpt["step"]) == 2 and recorded
    return [
        Row(
            name,
            ok,
            f"2 steps; checkpoint at step {int(ckpt['step'])}, "
            + ("teacher pickle and source recorded" if recorded else f"teacher recorded as {teacher}"),
            seconds,
        )
    ]


def _step_eval(check: Check, config: str) -> list[Row]:
    name = f"eval:{config}"
    start = time.perf_counter()
    check.lp3d(
        name,
        "lp3d.cli",
        "eval",
        _run_dir(config),
        *("--teacher-pkl", str(check.pkl), "--eg3d-source", str(check.eg3d_source)),
        *("--n-identities", "2", "--baseline-steps", "0", "--out", f"eval-{config}"),
        *("--device", check.device, "--no-progress"),
    )
    seconds = time.perf_counter() - start
    report = json.loads((check.work / f"eval-{config}" / "report.json").read_text())
    psnr = report["student"].get("novel_psnr")
    ok = report["truth"]["teacher"] == "EG3DTeacher" and isinstance(psnr, float) and np.isfinite(psnr)
    return [
        Row(
            name,
            ok,
            f"report.json against {report['truth']['teacher']}, {len(report['identity_seeds'])} identities, "
            f"no baseline; student novel-view PSNR {psnr:.1f} dB (after 2 steps)",
            seconds,
        )
    ]


def _step_export(check: Check, config: str) -> list[Row]:
    name = f"export:{config}"
    model = check.work / f"model-{config}.onnx"
    start = time.perf_counter()
    text = check.lp3d(name, "lp3d.export", _run_dir(config), "-o", model.name)
    seconds = time.perf_counter() - start
    errors = re.findall(r"onnxruntime vs PyTorch max abs error (\S+)", text)
    ok = model.is_file() and bool(errors)
    size = model.stat().st_size / 1e6 if model.is_file() else 0.0
    what = f"{model.name} ({size:.1f} MB); onnxruntime vs PyTorch max abs error {', '.join(errors) or '?'}"
    if len(errors) > 1:
        what += " (encoder, super-resolution)"
    return [Row(name, ok, what, seconds)]


def _step_encode(check: Check, config: str) -> list[Row]:
    from lp3d.images import rgb_to_uint8, save_png
    from lp3d.render.triplane_io import load_triplane

    name = f"encode:{config}"
    photo = check.work / "eg3d_image.png"
    if not photo.exists():
        ref = np.load(check.work / "eg3d_reference.npz", allow_pickle=False)
        save_png(photo, rgb_to_uint8(ref["image"]))
    head = f"head-{config}.npz"
    start = time.perf_counter()
    check.lp3d(
        name,
        "lp3d.cli",
        *("encode", photo.name, "--no-detect", "--model", f"model-{config}.onnx", "-o", head),
    )
    seconds = time.perf_counter() - start
    tri = load_triplane(check.work / head)
    ok = bool(np.isfinite(tri.planes).all())
    what = f"EG3D's 512² SR image -> {head}, planes {tuple(tri.planes.shape)} {tri.planes.dtype}"
    return [Row(name, ok, what, seconds)]


def _per_config(config: str) -> tuple[Step, ...]:
    def bind(fn: Callable[[Check, str], list[Row]]) -> Callable[[Check], list[Row]]:
        return lambda check: fn(check, config)

    train = f"train:{config}"
    return (
        Step(
            train,
            f"python -m lp3d.train --config {config} --teacher eg3d ..., 2 steps",
            ("build",),
            bind(_step_train),
        ),
        Step(
            f"eval:{config}",
            "lp3d eval RUN --teacher-pkl ... --eg3d-source ...",
            (train,),
            bind(_step_eval),
        ),
        Step(f"export:{config}", "lp3d export RUN", (train,), bind(_step_export)),
        Step(
            f"encode:{config}",
            "lp3d encode (EG3D's image) with the exported model",
            (f"export:{config}", "eg3d-reference"),
            bind(_step_encode),
        ),
    )


STEPS = (
    Step("build", "EG3D: random-weight FFHQ 512-128 generator, pickled as training_loop.py", (), _step_build),
    Step("eg3d-reference", "EG3D: load, map, un-jittered synthesis and SR", ("build",), _step_reference),
    Step("lp3d-compare", "lp3d: load and compare with EG3D", ("eg3d-reference",), _step_compare),
    *(step for config in TRAIN_CONFIGS for step in _per_config(config)),
)


def run_steps(check: Check, steps: Sequence[Step] = STEPS) -> list[Row]:
    """Run the steps in order, skipping those whose prerequisites failed; print progress lines."""
    rows: list[Row] = []
    status: dict[str, bool] = {}
    for i, step in enumerate(steps, 1):
        print(f"[{i}/{len(steps)}] {step.name}: {step.what}", flush=True)
        missing = [n for n in step.needs if not status.get(n)]
        if missing:
            status[step.name] = False
            rows.append(Row(step.name, None, f"skipped: needs {', '.join(missing)}"))
            print(f"      skipped (needs {', '.join(missing)})", flush=True)
            continue
        start = time.perf_counter()
        try:
            got = step.run(check)
        except StepError as e:
            got = [Row(step.name, False, str(e))]
        except Exception as e:  # the check's own reading of a step's output failed: report, go on
            got = [Row(step.name, False, f"{type(e).__name__}: {e}")]
        seconds = time.perf_counter() - start
        if len(got) == 1 and got[0].seconds is None:
            got[0].seconds = seconds
        status[step.name] = all(r.ok for r in got)
        rows.extend(got)
        word = "pass" if status[step.name] else "FAIL"
        print(f"      {word} ({seconds:.1f} s)", flush=True)
        for r in got:
            if not r.ok or len(got) > 1:
                print(f"      {'ok  ' if r.ok else 'FAIL'} {r.step}: {r.measured}", flush=True)
    return rows


def machine_line(device: str) -> str:
    """The machine the table was made on, in one line."""
    import torch

    parts = [
        f"{platform.machine()}, {os.cpu_count()} CPUs",
        f"load average {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else "",
        f"Python {platform.python_version()}, torch {torch.__version__} ({torch.get_num_threads()} threads)",
        f"device {device}" + (f" ({torch.cuda.get_device_name()})" if device.startswith("cuda") else ""),
    ]
    try:
        import lp3d_render

        info = lp3d_render.adapter_info()
        parts.append(f"lp3d_render adapter {info.get('name')} ({info.get('driver_info', '')})")
    except Exception as e:  # the table still says which adapter could not be named
        parts.append(f"lp3d_render adapter unknown ({type(e).__name__})")
    return "; ".join(p for p in parts if p)


def format_table(rows: Sequence[Row], *, command: str, machine: str, total_s: float) -> str:
    """The markdown section: command, machine, date, tolerances, the table and a verdict."""
    passed = all(r.ok for r in rows)
    lines = [
        f"Command: `{command}`  ",
        f"Machine: {machine}  ",
        f"Date: {datetime.date.today().isoformat()}; total {total_s:.0f} s  ",
        f"Pass thresholds (max abs Δ): ws {TOL_WS:g}, planes {TOL_PLANES:g}, renders {TOL_RENDER:g}, "
        f"SR {TOL_SR:g}.",
        "",
        "| step | result | measured | s |",
        "|---|---|---|---|",
    ]
    for r in rows:
        result = "skipped" if r.ok is None else ("pass" if r.ok else "**FAIL**")
        seconds = "" if r.seconds is None else f"{r.seconds:.1f}"
        measured = r.measured.replace("|", "\\|").replace("\n", " ")
        lines.append(f"| {r.step} | {result} | {measured} | {seconds} |")
    lines += ["", f"Verdict: {'every check passed' if passed else 'FAILED'}."]
    return "\n".join(lines) + "\n"


def replace_section(text: str, section: str) -> str:
    """``text`` with the part between the markers replaced by ``section`` (appended when absent)."""
    block = f"{SECTION_BEGIN}\n{section.rstrip()}\n{SECTION_END}\n"
    begin, end = text.find(SECTION_BEGIN), text.find(SECTION_END)
    if begin >= 0 and end > begin:
        rest = text[end + len(SECTION_END) :]
        return text[:begin] + block + rest.lstrip("\n")
    if begin >= 0 or end >= 0:
        raise ValueError(f"only one of the markers {SECTION_BEGIN!r} and {SECTION_END!r} is present")
    if not text:
        return f"# EG3D check\n\n{block}"
    return text.rstrip("\n") + "\n\n" + block


def write_table(path: Path, section: str) -> None:
    from lp3d.atomic import atomic_path

    old = path.read_text() if path.exists() else ""
    new = replace_section(old, section)
    with atomic_path(path) as tmp:
        tmp.write_text(new)


def resolve_eg3d_source(text: str) -> Path:
    """NVlabs/eg3d's ``eg3d/`` folder from ``--eg3d-source`` (that folder or the repository root)."""
    root = Path(text).expanduser()
    if not root.is_dir():
        raise ValueError(f"--eg3d-source {text!r}: no such directory (want NVlabs/eg3d's eg3d/ folder)")
    for candidate in (root, root / "eg3d"):
        if all((candidate / f).is_file() for f in EG3D_FILES):
            return candidate.resolve()
    missing = [f for f in EG3D_FILES if not (root / f).is_file()]
    raise ValueError(
        f"--eg3d-source {text!r} is not NVlabs/eg3d's eg3d/ folder: missing {', '.join(missing)}"
    )


@contextlib.contextmanager
def work_folder(text: str | None) -> Iterator[Path]:
    """``--work`` (new or empty, kept) or a temporary folder (removed afterwards)."""
    if text is None:
        tmp = Path(tempfile.mkdtemp(prefix="lp3d-eg3d-check-"))
        try:
            yield tmp.resolve()
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return
    path = Path(text).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    yield path.resolve()


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python scripts/eg3d_check.py",
        description=__doc__.split("\n\n")[0],
        epilog="See the module docstring for what each step checks.",
    )
    p.add_argument("--eg3d-source", help="NVlabs/eg3d's eg3d/ folder (or the repository root); required")
    p.add_argument("--work", help="work folder, new or empty, kept afterwards (default: a temporary one)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    p.add_argument(
        "--resolution",
        type=int,
        default=NEURAL_RENDERING_RESOLUTION,
        help="rays per side of the compared render (default 128)",
    )
    p.add_argument("--seed", type=int, default=0, help="weights seed and identity seed (default 0)")
    p.add_argument("--table", help="also write the table into this markdown file (its eg3d-check section)")
    p.add_argument(
        "--step-timeout", type=float, default=1800.0, help="seconds one step may take (default 1800)"
    )
    p.add_argument("--worker", nargs=2, metavar=("NAME", "CONFIG"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker is not None:
        if args.worker[0] not in WORKERS:
            p.error(f"--worker: unknown worker {args.worker[0]!r}")
        return args
    if args.eg3d_source is None:
        p.error("--eg3d-source is required (NVlabs/eg3d's eg3d/ folder)")
    try:
        args.eg3d_source = resolve_eg3d_source(args.eg3d_source)
    except ValueError as e:
        p.error(str(e))
    if not 1 <= args.resolution <= 512:
        p.error(f"--resolution must be in [1, 512], got {args.resolution}")
    if not 0 <= args.seed < 2**32:
        p.error(f"--seed must be in [0, 2**32), got {args.seed}")
    if not re.fullmatch(r"cpu|cuda(:\d+)?", args.device):
        p.error(f"--device must be cpu, cuda or cuda:N, got {args.device!r}")
    if not args.step_timeout > 0:
        p.error(f"--step-timeout must be > 0, got {args.step_timeout}")
    if args.work is not None:
        work = Path(args.work).expanduser()
        if work.exists() and (not work.is_dir() or any(work.iterdir())):
            p.error(f"--work {args.work!r} must be a new or empty folder")
    if args.table is not None:
        table = Path(args.table)
        if table.exists() and not table.is_file():
            p.error(f"--table {args.table!r} is not a file")
        if table.is_file():
            try:
                replace_section(table.read_text(), "")
            except (ValueError, UnicodeDecodeError) as e:
                p.error(f"--table {args.table!r}: {e}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.worker is not None:
        return _run_worker(args.worker[0], Path(args.worker[1]))
    command = "python scripts/eg3d_check.py --eg3d-source EG3D/eg3d"
    for flag, value, default in [
        ("--device", args.device, "cpu"),
        ("--resolution", args.resolution, NEURAL_RENDERING_RESOLUTION),
        ("--seed", args.seed, 0),
    ]:
        if value != default:
            command += f" {flag} {value}"
    if args.table:
        command += f" --table {args.table}"
    start = time.perf_counter()
    with work_folder(args.work) as work:
        print(f"EG3D source: {args.eg3d_source}\nwork folder: {work}", flush=True)
        check = Check(
            script=Path(__file__).resolve(),
            eg3d_source=args.eg3d_source,
            work=work,
            device=args.device,
            seed=args.seed,
            resolution=args.resolution,
            step_timeout=args.step_timeout,
        )
        rows = run_steps(check)
    section = format_table(
        rows, command=command, machine=machine_line(args.device), total_s=time.perf_counter() - start
    )
    print()
    print(section, end="")
    if args.table:
        write_table(Path(args.table), section)
        print(f"wrote the table into {args.table}")
    return 0 if all(r.ok for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
