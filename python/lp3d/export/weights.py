"""The weights an export ships: :func:`save_weights` (the torch weights file beside the ONNX model),
float16 rounding and storage (:func:`round_to_float16`, :func:`store_float16`, :func:`check_rounding`) and
the plane basis cut to fewer components (:func:`reduce_plane_basis`). Used by :mod:`lp3d.export.package`.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from lp3d.atomic import atomic_path
from lp3d.export.superres import superres_weights
from lp3d.nets.superres import SuperResolution
from lp3d.training.student import Student


def save_weights(
    student: Student,
    path: str | os.PathLike[str],
    *,
    half: bool = True,
    superres: SuperResolution | None = None,
) -> Path:
    """The student's inference weights as a plain ``torch.load(weights_only=True)`` dict that
    ``lp3d encode --backend torch --model PATH`` reads: ``config`` (EncoderConfig), ``encoder`` (state
    dict), ``plane_offset`` (or None), ``decoder`` {w0, b0, w1, b1} and ``bounds``, and with
    ``superres`` its ``{"config", "state"}`` (float32). ``half`` stores the encoder and offset in
    float16 (half the size; they load back into float32 parameters)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def cast(t: Tensor) -> Tensor:
        t = t.detach().cpu()
        return t.half() if half and t.is_floating_point() else t.clone()

    w0, b0, w1, b1 = (t.detach().cpu().clone() for t in student.decoder.weights())
    scene = student.scene
    data = {
        "format": "lp3d-encoder-weights-v1",
        "config": student.config.encoder.to_dict(),
        "encoder": {k: cast(v) for k, v in student.encoder.state_dict().items()},
        "plane_offset": None if student.plane_offset is None else cast(student.plane_offset),
        "decoder": {"w0": w0, "b0": b0, "w1": w1, "b1": b1},
        "bounds": {"box_warp": scene.box_warp, "ray_start": scene.ray_start, "ray_end": scene.ray_end},
    }
    if superres is not None:
        data["superres"] = superres_weights(superres)
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return path


@torch.no_grad()
def round_to_float16(student: Student) -> float:
    """Round the encoder's weights and the plane offset to float16 values (kept as float32 tensors), as
    the shipped files store them; returns the largest change of a weight. Exporting after this makes
    the float16 ONNX file and the float16 torch weights hold exactly the same numbers."""
    worst = 0.0
    params = [*student.encoder.parameters()] + (
        [student.plane_offset] if student.plane_offset is not None else []
    )
    for p in params:
        rounded = p.half().float()
        worst = max(worst, float((rounded - p).abs().max()))
        p.copy_(rounded)
    return worst


def store_float16(path: str | os.PathLike[str], *, min_elements: int = 1024) -> Path:
    """Rewrite an ONNX file so its float32 initializers of at least ``min_elements`` values are stored
    as float16 and cast back to float32 by a ``Cast`` node (half the file; onnxruntime folds the casts
    when it loads the model, so inference still runs in float32). Atomic."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    path = Path(path)
    model = onnx.load(str(path))
    graph = model.graph
    casts = []
    for init in list(graph.initializer):
        if init.data_type != TensorProto.FLOAT or int(np.prod(init.dims)) < min_elements:
            continue
        stored = numpy_helper.from_array(
            numpy_helper.to_array(init).astype(np.float16), f"{init.name}.float16"
        )
        graph.initializer.remove(init)
        graph.initializer.append(stored)
        casts.append(helper.make_node("Cast", [stored.name], [init.name], to=TensorProto.FLOAT))
    for i, node in enumerate(casts):  # before their consumers: nodes stay topologically sorted
        graph.node.insert(i, node)
    onnx.checker.check_model(model)
    with atomic_path(path) as tmp:
        onnx.save(model, str(tmp))
    return path


@torch.no_grad()
def reduce_plane_basis(student: Student, images: Tensor, components: int) -> float:
    """Keep ``components`` planes of the student's plane basis: the rank-``components`` approximation of
    its output that is best (least squares) over ``images`` (N, 3, S, S), folded into the weights.

    The basis adds ``c(I) · P`` (c: K coefficients, P: K planes). Over the images, the centred outputs
    ``(c - c̄) · P`` have principal directions V; the reduced basis is the first ``components`` of them,
    its coefficients ``c · P · Vᵀ`` (a linear map folded into the coefficient MLP's last layer), and
    the part of the mean output ``c̄ · P`` outside V moves into the constant plane offset (exact: the
    upsampling is linear). Returns the largest change of a triplane value over ``images``.
    """
    basis = student.encoder.basis
    if basis is None or student.plane_offset is None:
        raise ValueError("reduce_plane_basis needs a student with a plane basis and a plane offset")
    k = basis.components.shape[0]
    if not 1 <= components <= k:
        raise ValueError(f"components must be in [1, {k}], got {components}")
    before = student.encode(images)
    if components == k:
        return 0.0
    captured: dict[str, Tensor] = {}
    handle = basis.coefficients.register_forward_hook(lambda m, i, o: captured.setdefault("c", o))
    student.encode(images[:1])  # warm the hook's shape path
    captured.clear()
    student.encode(images)
    handle.remove()
    c = captured["c"].double()  # (N, K)
    planes = basis.components.double().reshape(k, -1)  # (K, D)
    mean_c = c.mean(0)
    _, _, vh = torch.linalg.svd((c - mean_c) @ planes, full_matrices=False)
    v = vh[:components]  # (K', D), orthonormal rows
    project = planes @ v.T  # (K, K'): new coefficients = c · project
    mean_out = mean_c @ planes
    residual = mean_out - (mean_out @ v.T) @ v  # (D,): the constant part V does not hold
    last = basis.coefficients[-1]
    assert isinstance(last, nn.Linear)
    new_last = nn.Linear(last.in_features, components).to(last.weight)
    new_last.weight.copy_((project.T @ last.weight.double()).to(last.weight))
    new_last.bias.copy_((project.T @ last.bias.double()).to(last.bias))
    basis.coefficients[-1] = new_last
    shape = basis.components.shape[1:]
    basis.components = nn.Parameter(v.reshape(components, *shape).to(basis.components))
    t = student.config.encoder.triplane_resolution
    const = residual.reshape(1, *shape).float()
    if shape[-1] != t:
        const = torch.nn.functional.interpolate(const, size=(t, t), mode="bilinear", align_corners=False)
    student.plane_offset.add_(const.reshape(student.plane_offset.shape))
    cfg = dataclasses.replace(student.config.encoder, basis_components=components)
    student.encoder.config = cfg
    student.config = dataclasses.replace(student.config, encoder=cfg)
    return float((student.encode(images) - before).abs().max())


@torch.no_grad()
def check_rounding(reference: Student, rounded: Student, *, batch: int = 2, seed: int = 0) -> float:
    """Max absolute triplane difference between two students on seeded images (e.g. float32 weights
    against the same rounded to float16)."""
    s = reference.config.image_size
    image = torch.rand(batch, 3, s, s, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    return float((reference.eval().encode(image) - rounded.eval().encode(image)).abs().max())


def training_inputs(cfg: Any, teacher_name: str, data_cache: str | None, n: int = 256) -> Tensor:
    """The first ``n`` encoder inputs of the run's cached synthetic dataset (CPU recipe). Where that
    dataset is not cached here (a run trained on another machine), only its first ``n`` identities
    are synthesised (and cached): each identity is a pure function of its seed, so they are the
    same inputs."""
    from lp3d.training.run_teacher import RunTeacher
    from lp3d.training.synthetic_data import SyntheticDataset, default_cache_root
    from lp3d.training.teacher_factory import build_teacher, dataset_key

    if cfg.recipe != "cpu" or not teacher_name.startswith("procedural"):
        raise ValueError("--basis-components needs a CPU-recipe run of the procedural teacher")
    teacher = build_teacher(teacher_name, triplane_resolution=cfg.triplane_resolution)
    key = dataset_key(cfg, teacher, teacher_name)
    root = Path(data_cache) if data_cache else default_cache_root()
    try:
        data = SyntheticDataset.load(root / key.digest(), key)
    except ValueError:
        # Loaded when cached, else synthesised (with a progress bar): the first n identities alone.
        prefix = dataclasses.replace(key, n_identities=min(n, key.n_identities))
        run_teacher = RunTeacher.of(teacher, teacher_name, cfg, torch.device("cpu"), data_cache=root)
        data = run_teacher.open_dataset(prefix)
    return torch.from_numpy(data.ref_image[:n].astype(np.float32))
