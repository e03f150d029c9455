"""The benchmarks' encoder scenes: the shipped encoder's triplane of a frontal render of a head, as
``lp3d demo`` lifts its teacher portrait (what a user opens in the viewer)."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.triplane import TriplaneData


def encoder_outputs(heads: Iterable[TriplaneData]) -> Iterator[TriplaneData]:
    """For each head, the shipped encoder's triplane of its frontal render at the encoder's input
    size (the encoder is loaded once, on the first head)."""
    from lp3d.lift.inference import DEFAULT_MODEL, load_encoder

    enc = None
    for head in heads:
        enc = enc or load_encoder(DEFAULT_MODEL)
        size = enc.package.image_size
        image = lp3d_render.render(head.to_native(), look_at_camera(), resolution=size)["rgb"]
        yield enc.package.triplane(enc.run(image[None].astype(np.float32))[0])


def encoder_output(head: TriplaneData) -> TriplaneData:
    """`encoder_outputs` of one head."""
    return next(encoder_outputs([head]))


def saved_encoder_output(seed: int, folder: Path) -> TriplaneData:
    """`encoder_output` of procedural teacher head `seed`, encoded once and kept in `folder` as
    ``encoder-<seed>.npz`` (delete it to encode again with another model)."""
    from lp3d.render.triplane_io import load_triplane, save_triplane
    from lp3d.teachers import ProceduralTeacher

    path = folder / f"encoder-{seed}.npz"
    if not path.exists():
        folder.mkdir(parents=True, exist_ok=True)
        print(f"encoding head {seed}", file=sys.stderr, flush=True)
        save_triplane(path, encoder_output(ProceduralTeacher().sample(seed)))
    return load_triplane(path)
