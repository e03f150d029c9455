"""Fit a super-resolution network (SR) for a trained encoder whose recipe has none
(``python -m lp3d.superres_fit``; ``docs/training.md``).

The modules: :mod:`~lp3d.superres_fit.config` (:class:`FitConfig`), :mod:`~lp3d.superres_fit.data`
(the raw/high-resolution pairs, made once and cached), :mod:`~lp3d.superres_fit.train` (the network,
its steps and its score), :mod:`~lp3d.superres_fit.checkpoint` (``superres-fit.pt``) and
:mod:`~lp3d.superres_fit.fit` (:func:`fit_superres` and the command line).

May import :mod:`lp3d.training` (camera sampling, losses, the synthetic-data cache), :mod:`lp3d.lift`
and the layers below them; needs torch (the ``train`` extra).
"""

from lp3d.superres_fit.fit import (
    FIT_FORMAT,
    FitConfig,
    FitError,
    FitResult,
    PairKey,
    PairSet,
    StalePairsError,
    default_pair_cache,
    fit_superres,
    load_fit,
    model_fingerprint,
)

__all__ = [
    "FIT_FORMAT",
    "FitConfig",
    "FitError",
    "FitResult",
    "PairKey",
    "PairSet",
    "StalePairsError",
    "default_pair_cache",
    "fit_superres",
    "load_fit",
    "model_fingerprint",
]
