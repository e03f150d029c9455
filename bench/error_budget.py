"""Where the shipped encoder's novel-view error comes from: a budget on training and held-out heads.

    python bench/error_budget.py --n-identities 16            # about 23 min on a loaded 2-core CPU

For each identity (teacher seeds ``0 ..`` = training identities, ``eval_seed_start ..`` = held-out
ones, inputs rendered as ``lp3d eval`` renders them) it renders the same novel views as the
evaluation (128², scored against the teacher at its native 256² planes) from:

* ``ceiling``: the teacher's own head at the student's 64² plane resolution;
* ``basis oracle``: the teacher's 64² planes projected (least squares) onto the shipped encoder's
  mean triplane plus its plane basis: the best any coefficient predictor could do with that basis;
* ``ceiling + noise``: the ceiling's planes plus independent Gaussian noise whose per-channel RMS is
  the student's per-channel plane error: what an error of the student's size costs when it has no
  structure (how steep the decoder makes the render in the planes);
* ``student``: the shipped model (``python/lp3d/lift/models/small.pt``, torch backend);
* ``mean head``: the encoder's mean triplane alone.

With ``--by-part``, also ``student's <part>``: the ceiling's planes with one part's four channels (its
shape channel and its three colour channels, :data:`lp3d.teachers.procedural_decoder.PARTS`) taken
from the student: how many dB each part's error costs on its own. With ``--shape-colour``, also
``student's shapes`` and ``student's colours``: the ceiling's planes with every part's shape channels,
or every part's colour channels, taken from the student: how the student's error splits between
where the parts are and what colour they have.

It reports novel-view PSNR and the channel-normalised plane L1 (the CPU recipe's L_tri, channels
divided by their spread over these identities) for each, split by training and held-out identities.
Equal numbers on the two splits say the student is not short of data but of fit.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from harness import add_model_argument, train_config_of  # bench/ is on sys.path when run as a script
from lp3d.evaluation.metrics import psnr
from lp3d.evaluation.protocol import (
    EvalSettings,
    input_camera,
    input_yaws,
    novel_view_cameras,
    reference_teachers,
    render_truth,
)
from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
from lp3d.lift.torch_backend import read_encoder_weights
from lp3d.teachers.procedural_decoder import N_PARTS, PARTS
from lp3d.training import SceneBounds, build_teacher

METHODS = ("ceiling", "basis oracle", "ceiling + noise", "student", "mean head")
#: The shipped model's torch weights (beside its ONNX encoder).
MODEL = DEFAULT_MODEL.with_suffix(".pt")


def basis_planes(state: dict[str, torch.Tensor], resolution: int) -> torch.Tensor:
    """The encoder's basis components at the plane resolution, flattened: (K, 3·32·T·T)."""
    comps = state["basis.components"].float()
    if comps.shape[-1] != resolution:
        comps = F.interpolate(comps, size=(resolution, resolution), mode="bilinear", align_corners=False)
    return comps.reshape(comps.shape[0], -1)


def project(target: torch.Tensor, offset: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """``offset + Σ c_k basis_k`` closest (least squares) to ``target``; all (1, 3, 32, T, T)."""
    residual = (target - offset).reshape(-1, 1)
    coeffs = torch.linalg.lstsq(basis.T.double(), residual.double()).solution.float()
    return offset + (basis.T @ coeffs).reshape(target.shape)


def shape_colour_swaps(ceiling: torch.Tensor, student: torch.Tensor) -> dict[str, torch.Tensor]:
    """The ceiling's planes with all the shape channels (0 .. N_PARTS-1), or all the colour channels
    (N_PARTS ..), taken from the student; all (1, 3, 32, T, T)."""
    shapes, colours = ceiling.clone(), ceiling.clone()
    shapes[:, :, :N_PARTS] = student[:, :, :N_PARTS]
    colours[:, :, N_PARTS:] = student[:, :, N_PARTS:]
    return {"student's shapes": shapes, "student's colours": colours}


def part_swaps(ceiling: torch.Tensor, student: torch.Tensor) -> dict[str, torch.Tensor]:
    """``{"student's <part>": the ceiling's planes with that part's shape and colour channels taken
    from the student}`` for every part of the procedural teacher's layout; all (1, 3, 32, T, T)."""
    out = {}
    for p, name in enumerate(PARTS):
        channels = [p, N_PARTS + 3 * p, N_PARTS + 3 * p + 1, N_PARTS + 3 * p + 2]
        planes = ceiling.clone()
        planes[:, :, channels] = student[:, :, channels]
        out[f"student's {name}"] = planes
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n-identities", type=int, default=16, help="identities per split (default 16)")
    add_model_argument(p)
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument(
        "--splits",
        nargs="+",
        choices=("training", "held-out"),
        default=["training", "held-out"],
        help="which identities to score (default both; held-out alone takes half the time)",
    )
    p.add_argument("--by-part", action="store_true", help="also swap in the student's planes part by part")
    p.add_argument(
        "--shape-colour",
        action="store_true",
        help="also swap in the student's shape channels alone, and its colour channels alone",
    )
    p.add_argument(
        "--flip-average",
        action="store_true",
        help="flip-average the student's planes (lp3d encode --flip-average)",
    )
    args = p.parse_args(argv)
    if args.n_identities < 2:
        p.error("--n-identities must be >= 2 (the plane scales are spreads over identities)")

    torch.manual_seed(args.seed)
    enc = load_encoder(args.model, "torch")
    # The reader the torch backend uses: packages and run checkpoints, whose encoder state and plane
    # offset sit in different places.
    weights = read_encoder_weights(Path(args.model))
    if weights.offset is None:
        p.error(f"{args.model}: no plane offset (the error budget is for CPU-recipe models)")
    offset = weights.offset.float().reshape(1, *weights.offset.shape[-4:])
    cfg = train_config_of(weights.checkpoint)
    t_res = cfg.triplane_resolution
    basis = basis_planes(weights.state, t_res)
    teacher = build_teacher("procedural", triplane_resolution=t_res)
    truth_teacher, ceiling_teacher = reference_teachers(teacher, cfg)
    assert ceiling_teacher is not None
    scene = SceneBounds.of(teacher.sample(0))
    dec = [torch.as_tensor(a) for a in teacher.decoder()]
    truth_dec = [torch.as_tensor(a) for a in truth_teacher.decoder()]
    views = novel_view_cameras(EvalSettings(), torch.device("cpu"))
    n = args.n_identities
    yaws = input_yaws(n)
    first = {"training": cfg.train_seeds[0], "held-out": cfg.eval_seed_start}
    splits = {s: [first[s] + i for i in range(n)] for s in args.splits}

    # Pass 1: every identity's truth, input image, ceiling planes and student planes.
    items: list[dict] = []
    t0 = time.perf_counter()
    for split, seeds in splits.items():
        for k, seed in enumerate(seeds):
            planes_t = torch.from_numpy(truth_teacher.sample(seed).planes.astype(np.float32)).unsqueeze(0)
            label, _ = input_camera(cfg, seed, float(yaws[k]))
            cam = torch.from_numpy(label).float().unsqueeze(0)
            image = render_truth(truth_teacher, planes_t, truth_dec, cam, cfg, scene)["high"]
            truth = render_truth(truth_teacher, planes_t, truth_dec, views, cfg, scene)["high"]
            ceiling = torch.from_numpy(ceiling_teacher.sample(seed).planes.astype(np.float32)).unsqueeze(0)
            student = torch.from_numpy(enc.encode(image.numpy(), flip_average=args.flip_average))
            items.append(
                {"split": split, "seed": seed, "truth": truth, "ceiling": ceiling, "student": student}
            )
            print(
                f"\r  encoded {len(items)}/{len(splits) * n} ({time.perf_counter() - t0:.0f} s)",
                end="",
                file=sys.stderr,
            )
    print(file=sys.stderr)
    stack = torch.cat([it["ceiling"] for it in items])
    scale = stack.transpose(0, 2).reshape(stack.shape[2], -1).std(dim=1).clamp_min(1e-3)
    err_rms = (torch.cat([it["student"] for it in items]) - stack).transpose(0, 2)
    err_rms = err_rms.reshape(stack.shape[2], -1).square().mean(dim=1).sqrt()

    # Pass 2: render every method's planes and score them.
    methods = list(METHODS) + ([f"student's {name}" for name in PARTS] if args.by_part else [])
    methods += ["student's shapes", "student's colours"] if args.shape_colour else []
    scores: dict[str, dict[str, list[tuple[float, float]]]] = {s: {m: [] for m in methods} for s in splits}
    for j, it in enumerate(items):
        ceiling = it["ceiling"]
        planes = {
            "ceiling": ceiling,
            "basis oracle": project(ceiling, offset, basis),
            "ceiling + noise": ceiling + torch.randn_like(ceiling) * err_rms.reshape(1, 1, -1, 1, 1),
            "student": it["student"],
            "mean head": offset,
            **(part_swaps(ceiling, it["student"]) if args.by_part else {}),
            **(shape_colour_swaps(ceiling, it["student"]) if args.shape_colour else {}),
        }
        for m, pl in planes.items():
            high = render_truth(teacher, pl, dec, views, cfg, scene)["high"]
            l_tri = float(((pl - ceiling).abs() / scale.reshape(1, 1, -1, 1, 1)).mean())
            scores[it["split"]][m].append((float(psnr(high, it["truth"]).mean()), l_tri))
        print(
            f"\r  rendered {j + 1}/{len(items)} ({time.perf_counter() - t0:.0f} s)", end="", file=sys.stderr
        )
    print(file=sys.stderr)

    print(
        f"\nmodel {args.model.name} ({cfg.name}, {basis.shape[0]} basis planes), {n} identities per split, "
        f"novel views at {cfg.image_size}², torch {torch.__version__}\n"
    )
    print("| planes | " + " | ".join(f"{s}: PSNR | {s}: L_tri" for s in splits) + " |")
    print("|---|" + "---|---|" * len(splits))
    for m in methods:
        cells = []
        for s in splits:
            ps, ls = zip(*scores[s][m], strict=True)
            cells += [f"{np.mean(ps):.2f} dB", f"{np.mean(ls):.3f}"]
        print(f"| {m} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
