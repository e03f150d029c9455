"""Old module paths, kept importable until release 0.2 (:data:`REMOVED_IN`) with a DeprecationWarning.

lp3d's modules moved from one flat package into subpackages along the data flow (``docs/architecture.md``).
``import lp3d.camera`` (and ``python -m lp3d.eval``) still work: a finder on ``sys.meta_path`` answers
the old name with the module at its new path, the same object, so ``lp3d.camera is lp3d.render.camera``.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings
from types import CodeType, ModuleType

#: old ``lp3d.<name>`` -> its new dotted path.
MOVED = {
    "camera": "lp3d.render.camera",
    "settings": "lp3d.render.settings",
    "triplane": "lp3d.render.triplane",
    "triplane_io": "lp3d.render.triplane_io",
    "npz_reader": "lp3d.render.npz_reader",
    "sampling_rng": "lp3d.render.sampling_rng",
    "reference": "lp3d.render.reference",
    "render_torch": "lp3d.render.torch_twin",
    "mesh": "lp3d.render.mesh",
    "sample_scenes": "lp3d.render.sample_scenes",
    "native": "lp3d.render.native",
    "encoder": "lp3d.nets.encoder",
    "superres": "lp3d.nets.superres",
    "discriminator": "lp3d.nets.discriminator",
    "stylegan_ops": "lp3d.nets.stylegan_ops",
    "model_package": "lp3d.lift.model_package",
    "inference": "lp3d.lift.inference",
    "losses": "lp3d.training.losses",
    "camera_sampling": "lp3d.training.camera_sampling",
    "synthetic_data": "lp3d.training.synthetic_data",
    "distributed": "lp3d.training.distributed",
    "run_dir": "lp3d.training.run_dir",
    "tensorboard_log": "lp3d.training.tensorboard_log",
    "eval": "lp3d.cli.eval",
    "demo": "lp3d.cli.demo",
    "view": "lp3d.cli.view",
    # Evaluation, export and SR fitting left lp3d.training for packages of their own (issue 24).
    "training.eval": "lp3d.evaluation.evaluate",
    "training.eval_metrics": "lp3d.evaluation.metrics",
    "training.eval_report": "lp3d.evaluation.report",
    "training.eval_run": "lp3d.evaluation.identities",
    "training.eval_setup": "lp3d.evaluation.protocol",
    "training.export": "lp3d.export.package",
    "training.export_onnx": "lp3d.export.onnx",
    "training.export_superres": "lp3d.export.superres",
    "training.export_weights": "lp3d.export.weights",
    "training.superres_fit": "lp3d.superres_fit.fit",
    "training.superres_fit_checkpoint": "lp3d.superres_fit.checkpoint",
    "training.superres_fit_config": "lp3d.superres_fit.config",
    "training.superres_fit_data": "lp3d.superres_fit.data",
    "training.superres_fit_train": "lp3d.superres_fit.train",
    # lp3d train's parser joined the other commands' in lp3d.cli; lp3d.training.train() is the library call.
    "training.cli": "lp3d.cli.train",
}

#: The release in which the old names stop importing (a test fails once ``__version__`` reaches it
#: while :data:`MOVED` still holds names).
REMOVED_IN = "0.2"


class _AliasLoader(importlib.abc.Loader):
    """Loads an old name as the module at its new path (imported, not copied)."""

    def __init__(self, new: str) -> None:
        self.new = new

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        warnings.warn(
            f"{spec.name} has moved to {self.new}; the old name goes away in lp3d {REMOVED_IN}",
            DeprecationWarning,
            stacklevel=2,
        )
        module = importlib.import_module(self.new)
        self._spec = module.__spec__
        return module

    def exec_module(self, module: ModuleType) -> None:
        # The import system set the alias spec on the shared module object; give it its own back.
        module.__spec__ = self._spec

    def get_code(self, fullname: str) -> CodeType:
        """``python -m OLD`` runs NEW's ``main()`` (or NEW as ``__main__`` when it has none)."""
        target = importlib.import_module(self.new)
        if callable(getattr(target, "main", None)):
            source = f"import sys\nfrom {self.new} import main\nsys.exit(main())\n"
        else:
            source = f"import runpy\nrunpy.run_module({self.new!r}, run_name='__main__', alter_sys=True)\n"
        return compile(source, f"<{fullname}: moved to {self.new}>", "exec")


class _MovedFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname: str, path: object = None, target: object = None):  # type: ignore[override]
        prefix, _, name = fullname.partition(".")
        if prefix != "lp3d" or name not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, _AliasLoader(MOVED[name]))


def install() -> None:
    """Put the finder on ``sys.meta_path`` once (``lp3d/__init__.py`` calls it)."""
    if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedFinder())
