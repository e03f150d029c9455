"""Distil a teacher into the LP3D encoder with synthetic data (paper §3.2, supplement "Training").

``python -m lp3d.train --config tiny --out runs/t`` trains the ``tiny`` configuration on the embedded
procedural teacher; ``--resume runs/t`` continues it exactly where it stopped.

One step (supplement, "Training"):

1. **Synthesis.** B identities (fresh seeds from the training range; evaluation seeds are disjoint),
   one reference camera ``P_ref`` (augmented, :data:`lp3d.training.camera_sampling.FFHQ_REFERENCE`) and one
   multiview camera ``P_mv`` (:data:`~lp3d.training.camera_sampling.FFHQ_MULTIVIEW`) each. The frozen teacher
   renders, with the torch twin of the renderer: the encoder's input I_ref at the encoder's image size,
   and for each view set the targets I_f, I_raw (= I_f[:3]) and I_D at the raw resolution and I_high
   at the image size.
2. **Student.** T̄ = E(I_ref); T̄ is rendered from P_mv (and from P_ref on reference steps) with the
   student's decoder, then super-resolved.
3. **Loss** (Eq. 5, :mod:`lp3d.training.losses`) and one optimiser step; in stage 2 also a discriminator step
   on teacher (real) vs student (fake) renders, with lazy R1.

Two-stage schedule (supplement): stage 1 (``warmup_steps``) without adversarial and category losses,
the reference-view loss every 10th synthesis, decoder and super-resolution frozen; stage 2 all losses
and all parameters, triplane weight 0.01, no feature loss, reference loss every 2nd step and, from
``dense_reference_from``, every step. Step counts are scaled per configuration (paper: 30k, 37.5k and
220k of batch 32 on 8 A100s).

Decisions where the paper is silent or the setting differs (all visible in :class:`TrainConfig`):

* **Teacher high-resolution images.** EG3D's I_512 comes out of its super-resolution network. A
  teacher may offer the same through the optional method ``superresolve(features (B,32,r,r)) ->
  (B,3,R,R)`` (the EG3D adapter's, with the constant w) and pretrained student SR weights through
  ``generator.superresolution`` (EG3D) or ``superres_state_dict()``. The procedural
  teacher has neither: its I_high (and the encoder input) are direct volume renders at the encoder's
  image size, which is exact and affordable on a CPU for the small configurations (a 128² render of
  12+12 samples per ray). In stage 1 the SR's parameters never learn from the student's loss (the
  paper freezes its pretrained SR; the student's high-resolution terms still reach the triplane through
  it). With no pretrained SR (procedural teacher), stage 1 trains it on the teacher's own pairs
  I_f -> I_high (L1 + perceptual at high resolution, logged as ``sr_*``), as EG3D's SR learnt from its
  generator's renders. The student decoder starts as a copy of the teacher's (the paper fine-tunes
  EG3D's) and is frozen in stage 1.
* **Alternating supervision.** "We compute losses for the reference set of cameras once every 10
  triplane syntheses": on those steps the reference-view terms are added to the multiview terms of the
  same step (one backward pass), rather than taking a separate gradient step.
* **Optimisers.** Adam with the paper's learning rates (1e-4; transformer 5e-5); betas (0.9, 0.999)
  (not stated); the decoder and the SR have their own rates (not stated; 1e-4 by default). The CPU
  configurations train their SR from scratch at 1e-3 and fine-tune the procedural decoder at 1e-6:
  its hand-built hidden units reach hundreds (gate slopes of 600-1500), so an Adam step of size lr on
  every weight moves its colour outputs by ~300·lr, and 1e-3 visibly broke the colours the moment
  stage 2 unfroze it. The discriminator uses
  EG3D's settings: Adam lr 0.002, betas (0, 0.99), R1 gamma 1 every 16 steps (lazy regularisation).
* **Depth.** I_D is rendered and logged; Eq. 5 has no depth term, so its weight is 0 by default.
* **Mean-triplane start** (CPU configurations only, ``mean_triplane_offset``): the student predicts
  an offset from the mean teacher triplane, as pSp/e4e predict offsets from the mean latent. Learning
  the head layout shared by every identity from scratch costs the tiny encoder more steps than a CPU
  test can afford; the paper's configurations train from scratch as published.
* **AMP** (CUDA only): the encoder's forward runs under fp16 autocast (the supplement's inference
  setting) with a gradient scaler; rendering, SR and the discriminator stay in float32.

The CPU recipe (``recipe="cpu"``: ``small``, ``tiny``; ``full``/``lt`` keep the published recipe).
The paper's step is slow on a CPU (``bench/train_profile.py``; ``bench/history/RESULTS.md``,
"Training profile"), most of it synthesising and rendering the teacher and rendering whole student
images, and its loss reaches the encoder mainly through renders of a step-like procedural decoder.
The CPU recipe spends the CPU on the encoder instead:

* **Data made once.** ``dataset_identities`` teacher identities (planes at the student's resolution
  and one input render each) are synthesised once into a content-hashed cache
  (:mod:`lp3d.training.synthetic_data`) and reused across steps, runs and resumes; horizontal flips with
  mirrored planes (:func:`lp3d.render.triplane.mirror_planes`) double them.
* **Triplane regression.** For ``regression_steps`` the only loss is L_tri with every channel
  divided by its spread over identities (:func:`lp3d.training.losses.normalised_triplane_loss`); after them an
  RGB L1 on ``rays_per_identity`` random rays of a random multiview camera is added (teacher and
  student rendered on the same rays; :func:`lp3d.render.torch_twin.render_rays`). ``small`` and ``tiny``
  regress for their whole schedule; ``--ray-from`` adds the ray phase to a run, also a resumed one.
  With teacher v1's step-like decoder the ray loss lowered both held-out PSNR and identity
  specificity. With v2's smooth decoder it helps, after a regression phase (``bench/history/RESULTS.md``,
  "A longer ray phase"; the shipped model's run is in its model card).
* **A plane basis.** The teacher's triplanes span its identities in about a hundred dimensions (the
  principal components of 512 heads and their mirrors leave 3 % of the held-out L1 at 128
  components), so the CPU encoders carry :class:`lp3d.nets.encoder.PlaneBasis`, started from those
  components (:func:`principal_planes`), beside the convolutional head; the student starts at the
  dataset's mean triplane.
* **No SR and no discriminator.** The procedural teacher renders its high-resolution image directly,
  and so does the student (``Student.render``); the decoder is the teacher's, frozen.
* **A cosine learning-rate decay** to 5 % at ``total_steps``, and a learning curve on held-out
  identities (``heldout.csv``: PSNR against their own and against other identities' teachers, and
  the identity specificity) at every checkpoint.

Checkpoints are plain dicts of tensors and JSON strings (``torch.load(weights_only=True)``), written
atomically; they carry the optimiser, scheduler, scaler and every RNG state, so resuming is exact.

**Distributed training** (``torchrun --nproc-per-node N -m lp3d.train ...``; :mod:`lp3d.training.distributed`,
``docs/training.md``). Each process takes ``cuda:LOCAL_RANK`` (NCCL) or the CPU (gloo) and builds its
own teacher and models from the same seed (rank 0's weights are broadcast). ``batch_size`` is the
global batch and must be a multiple of N: every rank draws the whole step's randomness from the one
seeded data stream and keeps the rows ``rank, rank + N, ...`` (the CPU recipe's dataset rows, flips
and rays likewise), so the stream does not depend on N. After each backward pass the student's and
the discriminator's gradients are averaged over the ranks by hand (no ``DistributedDataParallel``:
the student is called through ``encode``/``render``, parts freeze between stages and R1 takes a double
backward); ``log.csv`` holds the losses' means over the ranks. Rank 0 alone holds ``.lock`` and
writes the run directory (``world.json`` records N), computes the held-out curve and the samples
while the others wait, and synthesises a missing dataset before the others read it. Checkpoints
record N and every rank's RNG states: a resume on N processes is exact; on another number it is
allowed, with a note, and continues the same training up to float rounding. Without torchrun nothing
of this runs and one process trains exactly as described above.

The training loop, in import order (each module imports only those before it):
:mod:`~lp3d.training.config` (:class:`TrainConfig`, :data:`TRAIN_CONFIGS`),
:mod:`~lp3d.training.teacher_factory` (:func:`build_teacher`), :mod:`~lp3d.training.student`
(:class:`Student`, :class:`SceneBounds`), :mod:`~lp3d.training.checkpoint` (:func:`load_checkpoint`,
:func:`~lp3d.training.checkpoint.write_checkpoint`, RNG states), :mod:`~lp3d.training.optim` (the
optimisers, :class:`~lp3d.training.optim.Optimisation`), :mod:`~lp3d.training.run_teacher` (the
teacher as a run uses it), :mod:`~lp3d.training.steps` (the per-step data and losses,
:class:`~lp3d.training.steps.TrainingSteps`), :mod:`~lp3d.training.run_log` (``log.csv``),
:mod:`~lp3d.training.resume` (what a resumed run must share with its checkpoint),
:mod:`~lp3d.training.heldout` (the held-out curve and samples,
:class:`~lp3d.training.heldout.HeldoutViews`), :mod:`~lp3d.training.trainer` (:class:`Trainer`, which
builds those parts and owns them) and :mod:`~lp3d.training.distil` (:func:`train`, the one call that
builds the teacher and the trainer and runs it; ``lp3d train``'s options in :mod:`lp3d.cli.train`
become its arguments). No module imports another one's private names.
Beside it: ``camera_sampling``, ``synthetic_data``, ``run_dir``, ``distributed`` and
``tensorboard_log``. What uses a trained student lives in packages of its own beside this one:
:mod:`lp3d.evaluation` (``lp3d eval``), :mod:`lp3d.export` (``lp3d export``) and
:mod:`lp3d.superres_fit` (``lp3d superres-fit``). The command line, ``lp3d train`` and
``python -m lp3d.train``, is :mod:`lp3d.cli.train`.

May import: :mod:`lp3d.teachers`, :mod:`lp3d.nets`, :mod:`lp3d.render`, :mod:`lp3d.lift` and the
plumbing modules. Not the command line (:mod:`lp3d.cli`).
"""

import importlib
from typing import Any

#: Each public name -> the module of this package that defines it, imported on first use, so that
#: ``lp3d.training.camera_sampling`` (or ``run_dir``) can be imported without the trainer and torch.
_EXPORTS = {
    "Batch": "steps",
    "CHECKPOINT_FORMAT": "checkpoint",
    "CheckpointError": "checkpoint",
    "LOG_COLUMNS": "run_log",
    "MAIN_WEIGHTS": "config",
    "NonFiniteError": "steps",
    "RECIPES": "config",
    "RUN_KEEPING_FIELDS": "config",
    "SceneBounds": "student",
    "Student": "student",
    "TEACHERS": "teacher_factory",
    "TEACHER_ARGS": "teacher_factory",
    "TRAIN_CONFIGS": "config",
    "TrainConfig": "config",
    "TrainResult": "distil",
    "Trainer": "trainer",
    "TriplaneDecoder": "student",
    "WARMUP_WEIGHTS": "config",
    "build_teacher": "teacher_factory",
    "config_differences": "config",
    "dataset_key": "teacher_factory",
    "load_checkpoint": "checkpoint",
    "principal_planes": "student",
    "render_teacher": "student",
    "render_views": "student",
    "resolve_teacher_args": "teacher_factory",
    "student_from_checkpoint": "checkpoint",
    "teacher_superres_state": "teacher_factory",
    "train": "distil",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'lp3d.training' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"lp3d.training.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
