"""How much of a change to one part's colour in the input reaches the shipped encoder's planes.

    python bench/part_probe.py --n-identities 32          # about 9 min on the 2-core CPU

For held-out identities of the procedural teacher (``--split training``: the dataset's first ones), with
the input cameras of ``lp3d eval`` (yaw spread over ±35°, pitch, radius and intrinsics from the training
reference distribution), each part's colour (``HeadParams``: skin, hair, shirt, backdrop, eyes, glasses'
frames) is changed twice in colour-logit space, once in luminance (+0.6 on R, G and B) and once in hue
(+0.6, −0.3, −0.3: the same luminance). Each time the changed head is rendered as the input and encoded,
and the change of the student's triplane ``Δs`` is compared with the change of the teacher's at the
student's resolution ``Δt`` (the ceiling's planes):

* **gain** ``<Δs, Δt> / <Δt, Δt>``: 1 when the student follows the change fully, 0 when it ignores it;
* **input pixels** that the change touches (by more than 2/255 in a channel): an input shows the
  part when at least 16 of its 128² pixels change; where none does, no encoder could follow it.

A low gain on a part the input shows is the encoder's miss; a low gain on a hidden one is a guess.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np
import torch

from harness import add_model_argument, train_config_of  # bench/ is on sys.path when run as a script
from lp3d.evaluation.protocol import input_camera, input_yaws, reference_teachers, render_truth
from lp3d.lift.inference import load_encoder
from lp3d.lift.torch_backend import read_encoder_weights
from lp3d.teachers.procedural_identity import HeadParams
from lp3d.training import SceneBounds, build_teacher

#: The probed colours: HeadParams field -> what the table calls it.
FIELDS = {
    "skin_rgb": "skin",
    "hair_rgb": "hair",
    "cloth_rgb": "shirt",
    "background_rgb": "backdrop",
    "eye_rgb": "eyes",
    "glasses_rgb": "glasses",
}
#: Colour-logit changes: the same size, one along luminance, one across it.
CHANGES = {"luminance": np.array([0.6, 0.6, 0.6]), "hue": np.array([0.6, -0.3, -0.3])}
#: An input pixel counts as touched when a channel moves by more than this ([-1, 1] image).
TOUCHED = 4.0 / 255.0
#: An input shows the part when the change touches at least this share of its pixels (16 of 128²).
SHOWN = 16 / 128**2


def changed(params: HeadParams, field: str, delta: np.ndarray) -> HeadParams:
    """``params`` with colour ``field`` moved by ``delta`` in logit space (kept inside 2..98%)."""
    c = np.clip(np.asarray(getattr(params, field), dtype=np.float64), 0.02, 0.98)
    moved = 1.0 / (1.0 + np.exp(-(np.log(c / (1.0 - c)) + delta)))
    rgb = tuple(float(v) for v in np.clip(moved, 0.02, 0.98))
    return dataclasses.replace(params, **{field: rgb})


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n-identities", type=int, default=32, help="held-out identities (default 32)")
    add_model_argument(p)
    p.add_argument(
        "--split",
        choices=("held-out", "training"),
        default="held-out",
        help="identities after lp3d eval's first seed (default) or the dataset's first ones",
    )
    args = p.parse_args(argv)
    if args.n_identities < 2:
        p.error("--n-identities must be >= 2")

    enc = load_encoder(args.model, "torch")
    cfg = train_config_of(read_encoder_weights(args.model).checkpoint)  # the backend's checked reader
    teacher = build_teacher("procedural", triplane_resolution=cfg.triplane_resolution)
    truth_teacher, ceiling_teacher = reference_teachers(teacher, cfg)
    assert ceiling_teacher is not None
    scene = SceneBounds.of(teacher.sample(0))
    truth_dec = [torch.as_tensor(a) for a in truth_teacher.decoder()]
    n = args.n_identities
    yaws = input_yaws(n)
    first = cfg.eval_seed_start if args.split == "held-out" else cfg.train_seeds[0]

    def observe(params: HeadParams, cam: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(input image, student planes, ceiling planes) of one head."""
        planes = torch.from_numpy(truth_teacher.build(params).planes.astype(np.float32)).unsqueeze(0)
        image = render_truth(truth_teacher, planes, truth_dec, cam, cfg, scene)["high"].numpy()
        return image, enc.run(image)[0], ceiling_teacher.build(params).planes

    # rows[(field, change)] = [(gain, touched share)] over the identities that have the part.
    rows: dict[tuple[str, str], list[tuple[float, float]]] = {(f, c): [] for f in FIELDS for c in CHANGES}
    t0 = time.perf_counter()
    for k in range(n):
        seed = first + k
        params = HeadParams.sample(seed)
        label, _ = input_camera(cfg, seed, float(yaws[k]))
        cam = torch.from_numpy(label).float().unsqueeze(0)
        image0, student0, ceiling0 = observe(params, cam)
        for field in FIELDS:
            if field == "glasses_rgb" and not params.glasses:
                continue
            for change, delta in CHANGES.items():
                image, student, ceiling = observe(changed(params, field, delta), cam)
                dt, ds = (ceiling - ceiling0).ravel(), (student - student0).ravel()
                norm = float(dt @ dt)
                if norm < 1e-6:  # the part is absent (a bald head's hair)
                    continue
                touched = float((np.abs(image - image0).max(axis=1) > TOUCHED).mean())
                rows[(field, change)].append((float(ds @ dt) / norm, touched))
        print(f"\r  identity {k + 1}/{n} ({time.perf_counter() - t0:.0f} s)", end="", file=sys.stderr)
    print(file=sys.stderr)

    print(
        f"\nmodel {args.model.name}, {n} {args.split} identities (seeds {first}..), lp3d eval's "
        "input cameras; gain 1: the student's planes move as the teacher's do, 0: not at all\n"
    )
    print(
        "| part | identities | input pixels touched (mean) | inputs that show it | "
        "luminance gain: shown / hidden | hue gain: shown / hidden |"
    )
    print("|---|---|---|---|---|---|")
    for field, name in FIELDS.items():
        if not rows[(field, "hue")]:  # no identity among these has the part (glasses, for a few)
            print(f"| {name} | 0 | – | – | – | – |")
            continue
        cells = []
        for change in CHANGES:
            gains, touched = (np.array(v) for v in zip(*rows[(field, change)], strict=True))
            shown = touched >= SHOWN
            cells.append(" / ".join(f"{gains[m].mean():.2f}" if m.any() else "–" for m in (shown, ~shown)))
        _, touched = zip(*rows[(field, "hue")], strict=True)
        touched_a = np.array(touched)
        print(
            f"| {name} | {len(touched_a)} | {100 * touched_a.mean():.1f}% | "
            f"{int((touched_a >= SHOWN).sum())} | {cells[0]} | {cells[1]} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
