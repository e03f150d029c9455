"""Old module paths, kept importable for one release (0.2) with a DeprecationWarning.

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
    "eval": "lp3d.training.eval",
    "export": "lp3d.training.export",
    "superres_fit": "lp3d.training.superres_fit",
    "demo": "lp3d.cli.demo",
    "view": "lp3d.cli.view",
}


class _AliasLoader(importlib.abc.Loader):
    """Loads an old name as the module at its new path (imported, not copied)."""

    def __init__(self, new: str) -> None:
        self.new = new

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        warnings.warn(
            f"{spec.name} has moved to {self.new}; the old name goes away in lp3d 0.2",
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
