"""A small training checkpoint's contents and ``scripts/checkpoint_parts.py`` loaded as a module, for
the hostile-checkpoint tests and the fuzzer of the parts' manifest."""

from __future__ import annotations

import importlib.util
import json
from dataclasses import asdict
from types import ModuleType
from typing import Any

from support.paths import REPO

#: ``scripts/checkpoint_parts.py``.
PARTS_SCRIPT = REPO / "scripts" / "checkpoint_parts.py"


def parts_module() -> ModuleType:
    """``scripts/checkpoint_parts.py`` imported as the module ``checkpoint_parts``."""
    spec = importlib.util.spec_from_file_location("checkpoint_parts", PARTS_SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def tiny_state() -> dict[str, Any]:
    """What a ``tiny`` run's checkpoint holds (no optimiser state: enough for eval, export and parts)."""
    from lp3d.teachers import ProceduralTeacher
    from lp3d.training import CHECKPOINT_FORMAT, TRAIN_CONFIGS, SceneBounds, Student

    teacher = ProceduralTeacher(resolution=64)
    scene = SceneBounds.of(teacher.sample(0))
    student = Student(TRAIN_CONFIGS["tiny"], teacher.decoder(), scene)
    return {
        "format": CHECKPOINT_FORMAT,
        "config": TRAIN_CONFIGS["tiny"].to_json(),
        "teacher": "procedural",
        "teacher_args": json.dumps({}),
        "scene": json.dumps(asdict(scene)),
        "step": 7,
        "student": student.state_dict(),
    }
