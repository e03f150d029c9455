"""``python -m lp3d.train`` with two extra test configurations, for ``tests/training/test_distributed.py``.

Run as a script (``torchrun --nproc-per-node 2 tests/support/distributed_worker.py --config dist-paper ...``)
or imported (``main([...])`` in one process). The configurations are the tiny ones cut to a few
seconds a step, with every part of the recipe on within four steps:

* ``dist-paper`` (the paper's recipe, ``tiny-paper`` sizes): stage 2 from step 1, so the decoder,
  the SR and the discriminator all train, R1 every step, reference views on steps 0, 1 and from 3 on.
  Global batch 4, so 2 per rank on 2 ranks; the discriminator's minibatch-stddev groups of 2 then hold
  the same samples on a rank as in one process (``lp3d.training.distributed.shard``).
* ``dist-cpu`` (the CPU recipe, ``tiny`` sizes): a 4-identity cached dataset, regression at step 0
  and random rays from step 1, mirror flips, held-out curve of 2 identities.

With ``LP3D_TEST_PID_DIR`` set, each process first writes its pid to ``rank-<RANK>.pid`` there (for
the test that kills one rank).
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

from lp3d.train import main as train_main
from lp3d.training import TRAIN_CONFIGS, TrainConfig

CONFIGS: dict[str, TrainConfig] = {
    "dist-paper": dataclasses.replace(
        TRAIN_CONFIGS["tiny-paper"],
        name="dist-paper",
        discriminator=dataclasses.replace(TRAIN_CONFIGS["tiny-paper"].discriminator, mbstd_group_size=2),
        batch_size=4,
        warmup_steps=1,
        dense_reference_from=3,
        r1_interval=1,
        depth_resolution=4,
        depth_resolution_importance=2,
        mean_triplane_identities=4,
        checkpoint_every=2,
        sample_every=0,
    ),
    "dist-cpu": dataclasses.replace(
        TRAIN_CONFIGS["tiny"],
        name="dist-cpu",
        batch_size=4,
        dataset_identities=4,
        heldout_identities=2,
        regression_steps=1,
        rays_per_identity=16,
        depth_resolution=6,
        depth_resolution_importance=4,
        checkpoint_every=2,
        sample_every=0,
    ),
}
TRAIN_CONFIGS.update(CONFIGS)


def main(argv: list[str] | None = None) -> int:
    pid_dir = os.environ.get("LP3D_TEST_PID_DIR")
    if pid_dir:
        path = Path(pid_dir) / f"rank-{os.environ.get('RANK', '0')}.pid"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(f"{os.getpid()}\n")
        tmp.replace(path)
    return train_main(argv)


if __name__ == "__main__":
    sys.exit(main())
