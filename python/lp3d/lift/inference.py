"""Running a trained encoder outside training: ONNX Runtime (default) or PyTorch.

:func:`load_encoder` returns a :class:`LoadedEncoder` whose ``package`` says what the encoder expects
(``image_size``) and what goes into its triplanes (decoder, scene bounds) and whose ``run`` maps
images (B, 3, S, S) float32 in [-1, 1] to planes (B, 3, 32, T, T) float32.

* ``onnx``: an ``.onnx`` file plus its ``MODEL.json`` sidecar (:mod:`lp3d.lift.model_package`).
* ``torch``: a plain state-dict checkpoint (``torch.load(weights_only=True)``, never unpickling
  code). Two layouts are understood: ``{"config": EncoderConfig dict, "encoder": state dict,
  "decoder": {w0, b0, w1, b1}, "bounds": {box_warp, ray_start, ray_end}}`` and the training
  checkpoint of ``python -m lp3d.train`` (``format`` "lp3d-train-checkpoint-v1", its ``student`` state
  dict and ``scene``). Missing decoder/bounds may come from a ``.json`` sidecar beside the checkpoint.

**Super-resolution.** A package may carry a super-resolution network (SR) beside the encoder, which
turns the renderer's raw *feature* image into the final image, as EG3D's does (paper Eq. 2, with the
constant w of the paper's supplement, so it needs nothing but the features). :func:`load_superres`
returns it as a :class:`LoadedSuperres` (or None when the package has none); the Python API in one
call::

    import lp3d_render
    from lp3d.lift.inference import load_superres

    sr = load_superres()                        # the shipped model's, or load_superres("MODEL.onnx")
    out = lp3d_render.render(tri, camera, resolution=sr.input_resolution, outputs=["features"])
    image = sr(out["features"])                 # (3, R_out, R_out) float32 in about [-1, 1]

``onnx``: the sidecar's ``superres`` entry (``MODEL.superres.onnx``, its SHA-256 checked on load).
``torch``: the checkpoint's ``superres`` (``{"config": SuperresConfig dict, "state": state dict}``,
written by ``lp3d export --weights``) or, for a training checkpoint of the paper recipe, its
student's trained SR. The CPU recipe trains none; ``python -m lp3d.superres_fit`` fits one for
such a model.

The backends are :mod:`lp3d.lift.onnx_backend` and :mod:`lp3d.lift.torch_backend`; the types they
return are in :mod:`lp3d.lift.loaded` (and importable from here).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lp3d.lift.loaded import Backend, LoadedEncoder, LoadedSuperres
from lp3d.lift.model_package import ModelPackageError, load_model_package
from lp3d.lift.onnx_backend import load_onnx_encoder, load_onnx_superres
from lp3d.lift.torch_backend import load_torch_encoder

__all__ = [
    "DEFAULT_MODEL",
    "Backend",
    "LoadedEncoder",
    "LoadedSuperres",
    "load_encoder",
    "load_superres",
    "superresolve",
]


#: The shipped model (may not exist until one is trained and exported).
DEFAULT_MODEL = Path(__file__).resolve().parent / "models" / "small.onnx"


def load_encoder(
    path: str | os.PathLike[str], backend: Backend | None = None, *, superres: bool = False
) -> LoadedEncoder:
    """Load an encoder; ``backend`` None picks ``torch`` for ``.pt``/``.pth``/folders, else ``onnx``.
    With ``superres`` the package's super-resolution network is loaded too (``.superres``, None when
    the package has none).

    Raises :class:`~lp3d.lift.model_package.ModelPackageError` (a ValueError) with a clear message for a
    missing file or sidecar, an unreadable model, or a layout that does not fit.
    """
    p = Path(path)
    folder = _check_model_path(p)
    if backend is None:
        backend = "torch" if p.suffix.lower() in (".pt", ".pth") or folder else "onnx"
    if backend == "onnx" and folder:
        raise ModelPackageError(f"{p}: is a folder; an ONNX model is a file (MODEL.onnx beside MODEL.json)")
    if backend == "torch" and folder and p.suffix.lower() == ".onnx":
        raise ModelPackageError(f"{p}: is a folder, not an ONNX model file")
    if backend == "onnx":
        if p.suffix.lower() in (".pt", ".pth"):
            raise ModelPackageError(f"{p}: a torch checkpoint; use --backend torch (or export it to ONNX)")
        return load_onnx_encoder(p, superres=superres)
    if backend == "torch":
        if p.suffix.lower() == ".onnx":
            raise ModelPackageError(f"{p}: an ONNX model; use --backend onnx")
        return load_torch_encoder(p, superres=superres)
    raise ModelPackageError(f"unknown backend {backend!r} (use onnx or torch)")


def _check_model_path(p: Path) -> bool:
    """Whether ``p`` is a folder (a run folder, for the torch backend); a regular file gives False and
    anything else (missing, a FIFO, a device) a ModelPackageError saying what it is, before any
    backend tries to read it."""
    from lp3d.render.npz_reader import open_regular_file

    try:
        file, _ = open_regular_file(p, "a model file")
    except IsADirectoryError:
        return True
    except FileNotFoundError:
        raise ModelPackageError(f"{p}: no such file") from None
    except OSError as e:
        raise ModelPackageError(str(e) if e.filename is None else f"{p}: {e.strerror}") from None
    file.close()
    return False


def load_superres(
    path: str | os.PathLike[str] | None = None, backend: Backend | None = None
) -> LoadedSuperres | None:
    """The super-resolution network of the model package ``path`` (default: the shipped model), or
    None when the package has none. ``backend`` as for :func:`load_encoder`. An ONNX package's encoder
    file is not loaded; a torch checkpoint is read whole.

    Raises :class:`~lp3d.lift.model_package.ModelPackageError` for a package or SR file that is missing,
    altered (SHA-256) or does not fit its sidecar entry.
    """
    p = Path(path) if path is not None else DEFAULT_MODEL
    if backend is None:
        backend = "torch" if p.suffix.lower() in (".pt", ".pth") or p.is_dir() else "onnx"
    if backend == "onnx" and p.suffix.lower() not in (".pt", ".pth"):
        package = load_model_package(p)
        return load_onnx_superres(package, package.superres) if package.superres is not None else None
    return load_encoder(p, backend, superres=True).superres


def superresolve(
    features: np.ndarray, *, model: str | os.PathLike[str] | None = None, backend: Backend | None = None
) -> np.ndarray:
    """One call from a raw feature render to the final image: ``features`` (B, 32, R, R) or (32, R, R)
    float32 (the renderer's ``features`` output at the network's ``input_resolution``) -> image
    (B, 3, R_out, R_out) or (3, R_out, R_out) in about [-1, 1], with the super-resolution network of
    ``model`` (default: the shipped model). Loads the network on every call: keep the result of
    :func:`load_superres` to run it many times.

    Raises :class:`~lp3d.lift.model_package.ModelPackageError` when the package has no such network.
    """
    sr = load_superres(model, backend)
    if sr is None:
        where = Path(model) if model is not None else DEFAULT_MODEL
        raise ModelPackageError(
            f"{where}: the model package has no super-resolution network (its sidecar has no 'superres'); "
            "render the raw image instead, or fit one with python -m lp3d.superres_fit"
        )
    return sr(features)
