"""The native GPU renderer ``lp3d_render``, imported on first use (importing it creates the GPU device)
with a one-line :class:`lp3d.errors.UserError` naming the fix when it is not installed, and
:func:`render`, its call with the :class:`~lp3d.render.settings.RenderSettings` the other two renderers
take."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from lp3d.errors import UserError
from lp3d.render.settings import RenderSettings, resolve_settings

if TYPE_CHECKING:
    from lp3d.render.triplane import TriplaneData

__all__ = ["native_superres", "native_triplane", "render", "renderer"]


def renderer() -> Any:
    """The ``lp3d_render`` module (imported on first use: it creates the GPU device)."""
    try:
        import lp3d_render
    except ImportError as e:
        raise UserError(
            f"the renderer lp3d_render is not installed ({e}); build it with ./dev setup"
        ) from None
    return lp3d_render


def native_triplane(tri: TriplaneData) -> Any:
    """The ``lp3d_render.Triplane`` of a TriplaneData (:meth:`TriplaneData.to_native`), with a
    one-line error naming the fix when the renderer is not installed."""
    renderer()
    return tri.to_native()


def native_superres(weights: dict[str, Sequence[np.ndarray]], *, input_resolution: int) -> Any:
    """An ``lp3d_render.SuperRes``: a folded super-resolution network on the GPU, from its weights
    under ``FoldedSuperResolution``'s names (``convs_up``, ``biases_up``, ``convs``, ``biases``,
    ``rgb_weights``, ``rgb_biases``: one float32 array per ×2 block each) for feature images of side
    ``input_resolution``. ``sr.apply(features (B, C, R, R))`` returns the images (B, 3, R_out, R_out)."""
    arrays = {k: [np.ascontiguousarray(a, dtype=np.float32) for a in v] for k, v in weights.items()}
    return renderer().SuperRes(**arrays, input_resolution=input_resolution)


def render(
    triplane: Any,
    camera: np.ndarray,
    settings: RenderSettings | None = None,
    *,
    outputs: Sequence[str] | None = None,
    **overrides: Any,
) -> dict[str, np.ndarray]:
    """``lp3d_render.render`` with a :class:`~lp3d.render.settings.RenderSettings` (skips included) and
    keyword overrides, as :func:`~lp3d.render.reference.render_reference` and
    :func:`~lp3d.render.torch_twin.render_torch` take them. ``triplane`` is an ``lp3d_render.Triplane``
    or a :class:`~lp3d.render.triplane.TriplaneData`; its bounds are used (the GPU renderer reads them
    from the triplane, so bounds cannot be overridden here)."""
    if set(overrides) & {"box_warp", "ray_start", "ray_end"}:
        raise TypeError("the GPU renderer takes the scene bounds from the triplane; set them there")
    settings, _ = resolve_settings(settings, overrides)
    native = triplane.to_native() if hasattr(triplane, "to_native") else triplane
    kwargs = settings.native_kwargs()
    if outputs is not None:
        kwargs["outputs"] = list(outputs)
    return dict(renderer().render(native, camera, **kwargs))
