"""Teachers: 3D-aware generators that the encoder is distilled from.

A teacher turns a seed into an EG3D-format triplane (planes, its decoder and scene bounds) that the
trainer renders from any camera. Two implementations share the :class:`Teacher` protocol:

* :class:`~lp3d.teachers.procedural.ProceduralTeacher`, the embedded default: stylised heads built
  in closed form, no weights, no training (how: :mod:`lp3d.teachers.procedural`);
* an EG3D adapter for a user-supplied generator pickle.

The trainer only relies on what is declared here.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from lp3d.render.triplane import TriplaneData


@runtime_checkable
class Teacher(Protocol):
    """What the trainer needs from a teacher.

    ``sample(seed)`` must be deterministic: the same seed gives the same triplane, bit for bit. Every
    triplane of one teacher shares the same decoder, box and ray range, so the trainer may batch
    planes under one decoder (:meth:`decoder`).
    """

    def sample(self, seed: int) -> TriplaneData:
        """One identity: planes (3, 32, H, W) float32 plus the decoder and scene bounds.

        ``source`` names the teacher and seed (e.g. ``"procedural seed 17"``).
        """
        ...

    def sample_batch(self, seeds: Sequence[int]) -> list[TriplaneData]:
        """``[sample(s) for s in seeds]``, possibly faster."""
        ...

    def decoder(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The shared effective decoder weights ``(w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,))`` float32."""
        ...


from lp3d.teachers.procedural import HeadParams, ProceduralTeacher  # noqa: E402  (after the protocol)


def __getattr__(name: str) -> object:
    # The EG3D adapter needs torch; import it only when asked, so that the procedural teacher (and
    # ``lp3d demo``) work on an install without the [train] extra.
    if name in ("EG3DTeacher", "EG3DLoadError"):
        from lp3d.teachers import eg3d

        return getattr(eg3d, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["EG3DLoadError", "EG3DTeacher", "HeadParams", "ProceduralTeacher", "Teacher"]
