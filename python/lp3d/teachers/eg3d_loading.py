"""Loading a user's EG3D generator safely: EG3D's own source tree on ``sys.path`` only while its pickle
is read (and checked not to be shadowed by other packages), with errors that say what to pass
(:class:`EG3DLoadError`, :data:`EG3D_HINT`). Used by :mod:`lp3d.teachers.eg3d`.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import pickle
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: What to tell a user who has no (usable) EG3D generator.
EG3D_HINT = (
    "pass --teacher-pkl PATH to an EG3D FFHQ generator pickle (e.g. ffhqrebalanced512-128.pkl) "
    "and --eg3d-source PATH to a checkout of NVlabs/eg3d/eg3d"
)


#: Top-level packages of EG3D's source tree that its pickles import while being unpickled.
EG3D_SOURCE_PACKAGES = ("torch_utils", "dnnlib", "training")


class EG3DLoadError(RuntimeError):
    """The EG3D pickle or EG3D's source tree is missing or unusable; the message says what to pass."""


@contextlib.contextmanager
def _on_sys_path(directory: Path | None) -> Iterator[None]:
    """Put ``directory`` first on ``sys.path`` for the duration only (modules imported stay imported)."""
    if directory is None:
        yield
        return
    entry = str(directory)
    sys.path.insert(0, entry)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(entry)


def _eg3d_source_importable() -> bool:
    """Whether EG3D's source packages are already importable without ``eg3d_source``."""
    return all(
        name in sys.modules or importlib.util.find_spec(name) is not None for name in EG3D_SOURCE_PACKAGES
    )


def _check_not_shadowed(source: Path) -> None:
    """Refuse when a package named like EG3D's is already imported from elsewhere.

    Unpickling imports ``training`` etc. by name; a different, already imported ``training`` (another
    project's) would be used silently instead of EG3D's.
    """
    src = source.resolve()
    for name in EG3D_SOURCE_PACKAGES:
        mod = sys.modules.get(name)
        if mod is None:
            continue
        locations = [Path(p).resolve() for p in getattr(mod, "__path__", None) or []]
        file = getattr(mod, "__file__", None)
        if file:
            locations.append(Path(file).resolve().parent)
        if locations and not any(loc.is_relative_to(src) for loc in locations):
            raise EG3DLoadError(
                f"a module named {name!r} is already imported from {str(locations[0])!r}, which would shadow "
                f"EG3D's in {str(src)!r}; load the EG3D pickle in a fresh process (or before importing it)"
            )


def _resolve_eg3d_source(eg3d_source: str | os.PathLike[str]) -> Path:
    """The directory holding ``torch_utils/``, ``dnnlib/`` and ``training/``.

    Accepts the ``eg3d/eg3d`` folder itself or the repository root above it (a common slip).
    """
    root = Path(eg3d_source).expanduser()
    if not root.is_dir():
        raise EG3DLoadError(f"EG3D source directory not found: {str(root)!r}; {EG3D_HINT}")
    for candidate in (root, root / "eg3d"):
        if all((candidate / pkg).is_dir() for pkg in EG3D_SOURCE_PACKAGES):
            return candidate
    missing = [pkg for pkg in EG3D_SOURCE_PACKAGES if not (root / pkg).is_dir()]
    raise EG3DLoadError(
        f"{str(root)!r} is not EG3D's source tree "
        f"(missing {', '.join(p + '/' for p in missing)}); {EG3D_HINT}"
    )


def load_eg3d_generator(
    path: str | os.PathLike[str] | None, *, eg3d_source: str | os.PathLike[str] | None = None
) -> Any:
    """Unpickle an official EG3D network pickle and return its ``G_ema`` (as ``legacy.load_network_pkl``).

    **This executes code from the pickle** (EG3D pickles carry their classes' source and run it); only
    call it on a file you trust, at the user's request. ``eg3d_source`` (a checkout of NVlabs/eg3d's
    ``eg3d/`` folder, or the repository root) is put on ``sys.path`` while unpickling only; without it,
    EG3D's ``torch_utils``, ``dnnlib`` and ``training`` must already be importable. Raises
    :class:`EG3DLoadError` naming what to provide when the pickle or the source is missing, when
    unpickling fails, or when the file is not a dict with ``G_ema``. The module is returned as
    unpickled (on the CPU, in whatever train/eval mode it was saved).
    """
    if path is None:
        raise EG3DLoadError(f"no EG3D generator pickle given; {EG3D_HINT}")
    pkl = Path(path).expanduser()
    if not pkl.is_file():
        raise EG3DLoadError(f"EG3D generator pickle not found: {str(pkl)!r}; {EG3D_HINT}")
    source: Path | None = None
    if eg3d_source is not None:
        source = _resolve_eg3d_source(eg3d_source)
        _check_not_shadowed(source)
    elif not _eg3d_source_importable():
        raise EG3DLoadError(
            f"unpickling {str(pkl)!r} needs EG3D's source tree ({', '.join(EG3D_SOURCE_PACKAGES)}), "
            f"which is not importable; {EG3D_HINT}"
        )
    try:
        with _on_sys_path(source), open(pkl, "rb") as f:
            data = pickle.load(f)
    except ModuleNotFoundError as e:
        top = (e.name or "").split(".")[0]
        if top in EG3D_SOURCE_PACKAGES:
            where = f"not found in {str(source)!r}" if source is not None else "not importable"
            raise EG3DLoadError(
                f"unpickling {str(pkl)!r} needs module {e.name!r} from EG3D's source tree, {where}; "
                f"{EG3D_HINT}"
            ) from e
        raise EG3DLoadError(
            f"unpickling {str(pkl)!r} needs the Python package {e.name!r} (an EG3D dependency): install it"
        ) from e
    except Exception as e:  # a corrupt file or a source tree of another version: say which file
        raise EG3DLoadError(f"could not unpickle {str(pkl)!r} ({type(e).__name__}: {e}); {EG3D_HINT}") from e
    if not isinstance(data, dict) or "G_ema" not in data:
        got = f"a dict with keys {sorted(map(str, data))}" if isinstance(data, dict) else type(data).__name__
        raise EG3DLoadError(
            f"{str(pkl)!r} is not an EG3D network pickle: expected a dict with key 'G_ema' "
            f"(as written by EG3D's training loop), got {got}; {EG3D_HINT}"
        )
    return data["G_ema"]
