"""The native GPU renderer ``lp3d_render``, imported on first use (importing it creates the GPU device)
with a one-line :class:`lp3d.errors.UserError` naming the fix when it is not installed."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from lp3d.errors import UserError

if TYPE_CHECKING:
    from lp3d.render.triplane import TriplaneData

__all__ = ["render_triplane", "renderer"]


def renderer() -> Any:
    """The ``lp3d_render`` module (imported on first use: it creates the GPU device)."""
    try:
        import lp3d_render
    except ImportError as e:
        raise UserError(
            f"the renderer lp3d_render is not installed ({e}); build it with ./dev setup"
        ) from None
    return lp3d_render


def render_triplane(tri: TriplaneData) -> Any:
    """The ``lp3d_render.Triplane`` of a TriplaneData (:meth:`TriplaneData.to_native`), with a
    one-line error naming the fix when the renderer is not installed."""
    renderer()
    return tri.to_native()
