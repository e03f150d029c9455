"""Where a training step's time goes, per component, for the paper recipe and the CPU recipe.

    PYTHONPATH=python nice -n 10 python3 bench/train_profile.py [--repeats 3] [--threads 2] [--tiny]
        [--configs small-paper small] [--step-repeats 1] [--out FILE]

For each configuration of :data:`lp3d.training.TRAIN_CONFIGS` asked for (default ``small-paper`` and
``small``; ``--tiny`` adds ``tiny-paper`` and ``tiny``) it builds a :class:`lp3d.training.Trainer` on
the procedural teacher (CPU, a throw-away run directory and, for the CPU recipe, a throw-away
dataset cache of ``batch_size`` identities) and times each component of one step with the tensors
the trainer itself uses, replaying :meth:`~lp3d.training.Trainer.train_step` piece by piece:

* **paper recipe** (``small-paper``, ``tiny-paper``), in stage 1 (a step without the reference
  views, as 9 of 10 stage-1 steps are) and in stage 2 (a step past ``dense_reference_from``, where
  every step has the reference views; not an R1 step): teacher synthesis (``sample_batch``), teacher
  renders (reference image, multiview raw and high, reference raw on reference steps), encoder
  forward, student render forward + backward (whole images at ``raw_resolution``),
  super-resolution forward + backward, losses (triplane L1 + Eq. 5's image terms with the
  perceptual loss) forward + backward, in stage 1 the SR's own step on the teacher's pairs, in
  stage 2 the adversarial term (discriminator forward + backward into the renders) and the
  discriminator step, the encoder backward and the optimiser step;
* **CPU recipe** (``small``, ``tiny``), in the regression phase (``step < regression_steps``) and
  in the ray phase: data (indexing the cached arrays and mirror augmentation), encoder forward,
  encoder backward (with the channel-normalised triplane L1), the random-ray renders (teacher under
  ``no_grad``; student forward + backward) and the optimiser step; and, separately, the one-off
  cost per identity of the cached dataset (``teacher.sample_batch`` plus the teacher's render of
  the encoder's input at ``image_size``, timed on one batch) and what it adds per step when
  amortised over one run's ``total_steps``.

Backward passes are timed apart from forward passes by cutting the graph at each component's
output (a detached leaf that requires grad) and feeding the gradient back by hand, which does the
same arithmetic as the trainer's single ``backward()``. The sum of the components is compared with
a measured full :meth:`~lp3d.training.Trainer.train_step` at the same step (which also samples its own
batch). Every number is the median of ``--repeats`` passes after a warm-up pass on one identity;
the full step is the median of ``--step-repeats`` calls (default 1: a ``small-paper`` step takes
tens of seconds on two shared cores).

Output: a markdown table (config | recipe | batch | component | s per step | s per identity |
share), the one-off dataset costs of the CPU recipe, and a summary (config | s/step |
identities/step | identity-views per hour | ratio vs small-paper), with the torch version, the
thread count and ``os.getloadavg()`` at start and end. ``--out FILE`` also writes it atomically.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from lp3d.atomic import atomic_path
from lp3d.render.torch_twin import rays_from_cameras, render_rays
from lp3d.render.triplane import mirror_planes
from lp3d.training import (
    TRAIN_CONFIGS,
    Batch,
    TrainConfig,
    Trainer,
    build_teacher,
    render_teacher,
    render_views,
)
from lp3d.training.camera_sampling import sample_cameras
from lp3d.training.losses import ViewRenders, build_perceptual, l1, normalised_triplane_loss

Times = dict[str, float]


@dataclass
class Phase:
    """The median component times of one kind of step, and the measured full step."""

    config: str
    recipe: str
    phase: str
    batch: int
    step: int
    components: Times
    full_step: float

    @property
    def total(self) -> float:
        return sum(self.components.values())


@dataclass
class Synthesis:
    """The CPU recipe's one-off dataset cost, per identity, and its share of a run."""

    config: str
    identities: int
    total_steps: int
    per_identity: Times = field(default_factory=dict)
    #: The torch twin's input render of the same batches, s/identity, when the run renders its
    #: inputs otherwise (lp3d_render on a CPU run: ``RunTeacher.input_renderer``); None when it is the twin.
    twin_render: float | None = None

    @property
    def seconds_per_identity(self) -> float:
        return sum(self.per_identity.values())

    @property
    def amortised_per_step(self) -> float:
        return self.seconds_per_identity * self.identities / self.total_steps


@contextmanager
def clock(times: Times, name: str) -> Iterator[None]:
    """Add the wall time of the ``with`` body to ``times[name]``."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        times[name] = times.get(name, 0.0) + time.perf_counter() - t0


def _leaf(x: Tensor) -> Tensor:
    return x.detach().requires_grad_(True)


def _backward(outputs: list[Tensor], leaves: list[Tensor]) -> None:
    """Feed the gradients accumulated on ``leaves`` (cut copies of ``outputs``) back into the graph."""
    pairs = [(o, leaf.grad) for o, leaf in zip(outputs, leaves, strict=True) if leaf.grad is not None]
    if pairs and any(o.requires_grad for o, _ in pairs):
        torch.autograd.backward([o for o, _ in pairs], [g for _, g in pairs])


def _optimiser_step(tr: Trainer) -> None:
    """The tail of :meth:`Trainer.train_step`: unscale, clip, Adam, scheduler (no AMP on a CPU)."""
    cfg, opt = tr.config, tr.optimisation
    if cfg.grad_clip > 0:
        opt.scaler.unscale_(opt.opt_g)
        torch.nn.utils.clip_grad_norm_(tr.student.parameters(), cfg.grad_clip)
    opt.scaler.step(opt.opt_g)
    opt.scaler.update()
    opt.sched_g.step()


# --------------------------------------------------------------------------------------------------
# The paper recipe
# --------------------------------------------------------------------------------------------------


def paper_pass(tr: Trainer, step: int, b: int) -> Times:
    """One step of the paper recipe at ``step`` on ``b`` identities, component by component."""
    cfg = tr.config
    t: Times = {}
    tr.step = step
    tr.steps.set_trainable(step)
    tr.student.train()
    tr.discriminator.requires_grad_(False)
    weights = cfg.weights(step)
    is_ref = cfg.reference_step(step)
    stage = cfg.stage(step)
    use_d = stage == 2 and (weights.adversarial_reference > 0 or weights.adversarial_multiview > 0)
    rng = tr.data_rng

    with clock(t, "teacher synthesis (sample_batch)"):
        seeds = [int(s) for s in rng.integers(cfg.train_seeds[0], cfg.train_seeds[1], size=b)]
        ref_cams = torch.from_numpy(sample_cameras(cfg.reference_cameras, b, rng).labels).float()
        mv_cams = torch.from_numpy(sample_cameras(cfg.multiview_cameras, b, rng).labels).float()
        teacher_planes = tr.run_teacher.planes(tr.teacher.sample_batch(seeds))
    label = "teacher renders (ref image, mv raw + high" + (", ref raw)" if is_ref else ")")
    with clock(t, label):
        dec = tr.teacher_decoder
        f_ref, d_ref, ref_image = render_teacher(
            tr.teacher, teacher_planes, dec, ref_cams, cfg, tr.scene, raw=is_ref, high=True
        )
        f_mv, d_mv, h_mv = render_teacher(tr.teacher, teacher_planes, dec, mv_cams, cfg, tr.scene)
    assert ref_image is not None and f_mv is not None and d_mv is not None and h_mv is not None
    mv_t = ViewRenders(features=f_mv, high=h_mv, depth=d_mv)
    ref_t = None
    if is_ref:
        assert f_ref is not None and d_ref is not None
        ref_t = ViewRenders(features=f_ref, high=ref_image, depth=d_ref)

    tr.optimisation.opt_g.zero_grad(set_to_none=True)
    with clock(t, "encoder forward"):
        planes = tr.student.encode(ref_image, amp=tr.amp)
    p = _leaf(planes)

    render_name = f"student render fwd+bwd ({'2B' if is_ref else 'B'} views at {cfg.raw_resolution}²)"
    with clock(t, render_name):
        cams = torch.cat([mv_cams, ref_cams]) if is_ref else mv_cams
        out = render_views(
            torch.cat([p, p]) if is_ref else p, tr.student.decoder.weights(), cams, cfg, tr.scene
        )
        features, depth = out["features"], out["depth"]
    f_leaf, d_leaf = _leaf(features), _leaf(depth)
    with clock(t, "super-resolution fwd+bwd"):
        if stage == 1:  # the student's loss reaches the planes through the SR but not its weights
            frozen = {k: v.detach() for k, v in tr.student.superres.named_parameters()}
            high = torch.func.functional_call(tr.student.superres, frozen, (f_leaf,))
        else:
            high = tr.student.superres(f_leaf)
    h_leaf = _leaf(high)
    mv_s = ViewRenders(f_leaf[:b], h_leaf[:b], d_leaf[:b])
    ref_s = ViewRenders(f_leaf[b:], h_leaf[b:], d_leaf[b:]) if ref_t is not None else None

    with clock(t, "losses fwd+bwd (L1 + perceptual)"):
        total = planes.new_zeros(())
        if weights.triplane > 0:
            total = total + weights.triplane * tr.losses.triplane(
                p, tr.run_teacher.target_planes(teacher_planes)
            )
        plain = dataclasses.replace(weights, adversarial_reference=0.0, adversarial_multiview=0.0)
        total = total + tr.losses.views(mv_s, mv_t, plain, kind="multiview")[0]
        if ref_t is not None and ref_s is not None:
            total = total + tr.losses.views(ref_s, ref_t, plain, kind="reference")[0]
        total.backward()
    if use_d:
        with clock(t, "adversarial term (D fwd+bwd)"):
            adv_only = dataclasses.replace(
                weights,
                color_raw=0.0,
                color_high=0.0,
                perceptual_raw=0.0,
                perceptual_high=0.0,
                feature=0.0,
                depth=0.0,
                category=0.0,
            )
            adv = tr.losses.views(mv_s, mv_t, adv_only, kind="multiview", discriminator=tr.discriminator)[0]
            if ref_t is not None and ref_s is not None:
                adv = (
                    adv
                    + tr.losses.views(
                        ref_s, ref_t, adv_only, kind="reference", discriminator=tr.discriminator
                    )[0]
                )
            adv.backward()
    with clock(t, "super-resolution fwd+bwd"):
        _backward([high], [h_leaf])
    with clock(t, render_name):
        _backward([features, depth], [f_leaf, d_leaf])
    if stage == 1 and not tr.pretrained_sr:
        with clock(t, "SR on teacher pairs fwd+bwd (stage 1)"):
            sr_weights = dataclasses.replace(
                weights, color_raw=0.0, perceptual_raw=0.0, feature=0.0, depth=0.0, category=0.0
            )
            pairs = ViewRenders(f_mv, tr.student.superres(f_mv), d_mv)
            tr.losses.views(pairs, mv_t, sr_weights, kind="multiview")[0].backward()
    with clock(t, "encoder backward"):
        _backward([planes], [p])
    with clock(t, "optimiser step"):
        _optimiser_step(tr)
    if use_d:
        with clock(t, "discriminator step"):
            batch = Batch(seeds, teacher_planes, ref_cams, mv_cams, ref_image, mv_t, ref_t)
            fake = ViewRenders(f_leaf.detach(), h_leaf.detach(), d_leaf.detach())
            tr.steps.discriminator_step(step, batch, fake, is_ref)
    return t


# --------------------------------------------------------------------------------------------------
# The CPU recipe
# --------------------------------------------------------------------------------------------------


def cpu_pass(tr: Trainer, step: int, b: int) -> Times:
    """One step of the CPU recipe at ``step`` on ``b`` identities, component by component."""
    cfg, ds = tr.config, tr.dataset
    assert ds is not None
    t: Times = {}
    tr.step = step
    tr.steps.set_trainable(step)
    tr.student.train()
    rng = tr.data_rng
    with clock(t, "data (index cached arrays + mirror)"):
        idx = np.sort(rng.integers(0, len(ds), size=b))
        image = torch.from_numpy(ds.ref_image[idx].astype(np.float32))
        target = torch.from_numpy(ds.planes[idx].astype(np.float32))
        if cfg.mirror_augment:
            flip = torch.from_numpy(rng.random(len(idx)) < 0.5)
            image = torch.where(flip[:, None, None, None], image.flip(-1), image)
            target = torch.where(flip[:, None, None, None, None], mirror_planes(target), target)
    tr.optimisation.opt_g.zero_grad(set_to_none=True)
    with clock(t, "encoder forward"):
        planes = tr.student.encode(image, amp=tr.amp)
    p = _leaf(planes)
    if step >= cfg.regression_steps and cfg.rays_per_identity > 0 and cfg.ray_weight > 0:
        m, r = cfg.rays_per_identity, cfg.raw_resolution
        name_t = f"ray renders: teacher, no grad ({m} rays/identity)"
        with clock(t, name_t):
            cams = torch.from_numpy(sample_cameras(cfg.multiview_cameras, b, rng).labels).float()
            pixels = torch.from_numpy(rng.integers(0, r * r, size=(b, m)))
            origins, directions = rays_from_cameras(cams, r)
            gather = pixels.unsqueeze(-1).expand(-1, -1, 3)
            origins, directions = origins.gather(1, gather), directions.gather(1, gather)

            def rgb(planes_: Tensor, decoder: tuple[Tensor, ...] | list[Tensor]) -> Tensor:
                out = render_rays(
                    planes_,
                    *decoder,
                    origins,
                    directions,
                    bounds=tr.scene,
                    settings=cfg.render_settings(),
                )
                return out["features"][..., :3]

            with torch.no_grad():
                want = rgb(target, tr.teacher_decoder)
        with clock(t, "ray renders: student fwd+bwd"):
            ray = l1(rgb(p, tr.student.decoder.weights()), want, name="ray rgb")
            (cfg.ray_weight * ray).backward()
    with clock(t, "encoder backward (+ triplane L1)"):
        tri = normalised_triplane_loss(p, target, tr.plane_scale)
        (cfg.triplane_weight * tri).backward()
        _backward([planes], [p])
    with clock(t, "optimiser step"):
        _optimiser_step(tr)
    return t


def dataset_synthesis(tr: Trainer, repeats: int) -> Synthesis:
    """Per-identity cost of building the cached dataset: teacher planes and the input render."""
    cfg = tr.config
    b = cfg.batch_size
    backend = tr.run_teacher.input_backend()
    render = tr.run_teacher.input_renderer(backend)
    twin = tr.run_teacher.input_renderer("torch") if backend != "torch" else None
    runs: list[Times] = []
    twin_runs: list[Times] = []
    for i in range(repeats + 1):  # the first is the warm-up
        seeds = [cfg.train_seeds[0] + i * b + k for k in range(b)]
        cams = torch.from_numpy(sample_cameras(cfg.reference_cameras, b, tr.data_rng).labels).float()
        t: Times = {}
        with clock(t, "teacher.sample_batch"):
            planes = tr.run_teacher.planes(tr.teacher.sample_batch(seeds))
        with clock(t, f"input render at {cfg.image_size}²"):
            render(planes, cams)
        runs.append({k: v / b for k, v in t.items()})
        if twin is not None:
            t = {}
            with clock(t, "twin"):
                twin(planes, cams)
            twin_runs.append({k: v / b for k, v in t.items()})
    synth = Synthesis(
        cfg.name, TRAIN_CONFIGS[cfg.name].dataset_identities, cfg.total_steps, _medians(runs[1:])
    )
    if twin_runs:
        synth.twin_render = _medians(twin_runs[1:])["twin"]
    return synth


# --------------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------------


def _medians(runs: list[Times]) -> Times:
    names = list(dict.fromkeys(k for r in runs for k in r))
    return {k: statistics.median(r.get(k, 0.0) for r in runs) for k in names}


def profile_phase(
    tr: Trainer,
    phase: str,
    step: int,
    pass_fn: Callable[[Trainer, int, int], Times],
    repeats: int,
    step_repeats: int,
) -> Phase:
    cfg = tr.config
    pass_fn(tr, step, 1)  # warm-up on one identity
    runs: list[Times] = []
    full: list[float] = []
    # Passes and full steps alternate, so that both see the same (shared, drifting) machine load.
    for i in range(max(repeats, step_repeats)):
        if i < repeats:
            runs.append(pass_fn(tr, step, cfg.batch_size))
            print(f"  {cfg.name} {phase}: pass {sum(runs[-1].values()):.1f} s", file=sys.stderr, flush=True)
        if i < step_repeats:
            tr.step = step
            t0 = time.perf_counter()
            tr.train_step()
            full.append(time.perf_counter() - t0)
            print(f"  {cfg.name} {phase}: train_step {full[-1]:.1f} s", file=sys.stderr, flush=True)
    return Phase(cfg.name, cfg.recipe, phase, cfg.batch_size, step, _medians(runs), statistics.median(full))


def _r1_free(step: int, cfg: TrainConfig) -> int:
    """The first step from ``step`` on that is not a lazy-R1 step."""
    while step % cfg.r1_interval == 0:
        step += 1
    return step


def profile_config(
    name: str, repeats: int, step_repeats: int, work: Path
) -> tuple[list[Phase], Synthesis | None]:
    cfg = TRAIN_CONFIGS[name]
    # A dataset of one batch (the CPU recipe indexes it with replacement; its size does not change
    # a step's arithmetic) and 2 held-out identities (the fewest the held-out metrics accept).
    run_cfg = dataclasses.replace(cfg, dataset_identities=cfg.batch_size, heldout_identities=2)
    teacher = build_teacher("procedural", triplane_resolution=cfg.triplane_resolution)
    perceptual = build_perceptual(cfg.perceptual, lpips_net=cfg.lpips_net)
    t0 = time.perf_counter()
    tr = Trainer(
        run_cfg,
        work / f"run-{name}",
        teacher=teacher,
        perceptual=perceptual,
        progress=False,
        data_cache=work / "data",
    )
    print(f"{name}: trainer built in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    if cfg.recipe == "paper":
        s1 = 1 if not cfg.reference_step(1) else 2
        s2 = _r1_free(cfg.dense_reference_from + 1, cfg)
        phases = [
            profile_phase(tr, "stage 1", s1, paper_pass, repeats, step_repeats),
            profile_phase(tr, "stage 2", s2, paper_pass, repeats, step_repeats),
        ]
        return phases, None
    phases = [
        profile_phase(tr, "regression", 1, cpu_pass, repeats, step_repeats),
        profile_phase(tr, "ray", cfg.regression_steps + 1, cpu_pass, repeats, step_repeats),
    ]
    return phases, dataset_synthesis(tr, repeats)


def schedule_mean(cfg: TrainConfig, phases: list[Phase]) -> float:
    """Seconds per step averaged over the configuration's schedule (phase steps as weights)."""
    first, second = phases
    n1 = cfg.warmup_steps if cfg.recipe == "paper" else cfg.regression_steps
    return (n1 * first.total + (cfg.total_steps - n1) * second.total) / cfg.total_steps


def render_report(phases: list[Phase], synth: list[Synthesis], header: list[str], footer: list[str]) -> str:
    lines = [*header, ""]
    lines += [
        "| config | recipe | batch | component | s per step | s per identity | share |",
        "|---|---|---|---|---|---|---|",
    ]
    for ph in phases:
        tag = f"{ph.recipe}, {ph.phase} (step {ph.step})"
        for name, sec in ph.components.items():
            lines.append(
                f"| {ph.config} | {tag} | {ph.batch} | {name} | {sec:.2f} | {sec / ph.batch:.3f} | "
                f"{100 * sec / ph.total:.0f}% |"
            )
        lines.append(
            f"| {ph.config} | {tag} | {ph.batch} | **sum of components** | **{ph.total:.2f}** | "
            f"**{ph.total / ph.batch:.3f}** | 100% |"
        )
        lines.append(
            f"| {ph.config} | {tag} | {ph.batch} | measured `train_step()` | {ph.full_step:.2f} | "
            f"{ph.full_step / ph.batch:.3f} | {100 * ph.full_step / ph.total:.0f}% of sum |"
        )
    if synth:
        lines += [
            "",
            "One-off dataset synthesis of the CPU recipe (per identity, one batch timed; built once, then "
            "cached and reused by later runs):",
            "",
            "| config | teacher.sample_batch s/identity | input render s/identity | torch twin's input "
            "render s/identity (same batches) | s/identity | identities | one-off s | steps per run "
            "| amortised s/step | training steps it equals (ray phase) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for sy in synth:
            ray = next(p for p in phases if p.config == sy.config and p.phase == "ray")
            parts = list(sy.per_identity.values())
            one_off = sy.seconds_per_identity * sy.identities
            twin = (
                "the same"
                if sy.twin_render is None
                else f"{sy.twin_render:.3f} ({sy.twin_render / parts[1]:.2f}×)"
            )
            lines.append(
                f"| {sy.config} | {parts[0]:.3f} | {parts[1]:.3f} | {twin} | {sy.seconds_per_identity:.3f} | "
                f"{sy.identities} | {one_off:.0f} | {sy.total_steps} | {sy.amortised_per_step:.2f} | "
                f"{one_off / ray.total:.0f} |"
            )
    # Summary: the reference is small-paper's schedule mean when it was profiled.
    rows: list[tuple[str, float, int]] = []
    by_config: dict[str, list[Phase]] = {}
    for ph in phases:
        by_config.setdefault(ph.config, []).append(ph)
    for name, phs in by_config.items():
        cfg = TRAIN_CONFIGS[name]
        for ph in phs:
            rows.append((f"{name} ({ph.phase})", ph.total, ph.batch))
        mean = schedule_mean(cfg, phs)
        sy = next((s for s in synth if s.config == name), None)
        if sy is None:
            rows.append((f"{name} (schedule mean)", mean, cfg.batch_size))
        else:
            rows.append(
                (f"{name} (schedule mean + amortised dataset)", mean + sy.amortised_per_step, cfg.batch_size)
            )
    ref = next((r for r in rows if r[0] == "small-paper (schedule mean)"), None)
    lines += [
        "",
        "| config | s/step | identities/step | identity-views per hour | ratio vs small-paper |",
        "|---|---|---|---|---|",
    ]
    for label, sec, b in rows:
        ivph = b / sec * 3600
        ratio = f"{ivph / (ref[2] / ref[1] * 3600):.2f}×" if ref is not None else "—"
        lines.append(f"| {label} | {sec:.2f} | {b} | {ivph:,.0f} | {ratio} |")
    lines += ["", *footer]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument(
        "--configs", nargs="+", default=["small-paper", "small"], choices=sorted(TRAIN_CONFIGS)
    )
    parser.add_argument("--tiny", action="store_true", help="also profile tiny-paper and tiny")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes per phase (median)")
    parser.add_argument("--step-repeats", type=int, default=1, help="full train_step() calls per phase")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument("--out", type=Path, default=None, help="also write the markdown here (atomically)")
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.step_repeats < 1 or args.threads < 1:
        parser.error("--repeats, --step-repeats and --threads must be >= 1")
    configs = list(args.configs) + (["tiny-paper", "tiny"] if args.tiny else [])
    configs = list(dict.fromkeys(configs))
    if any(TRAIN_CONFIGS[c].recipe == "paper" and TRAIN_CONFIGS[c].name in ("full", "lt") for c in configs):
        parser.error("full and lt are GPU configurations; profile the CPU ones here")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    load0 = os.getloadavg()
    started = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="lp3d-train-profile-"))
    phases: list[Phase] = []
    synth: list[Synthesis] = []
    try:
        for name in configs:
            ph, sy = profile_config(name, args.repeats, args.step_repeats, work)
            phases += ph
            if sy is not None:
                synth.append(sy)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    load1 = os.getloadavg()
    header = [
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, {platform.machine()}, "
        f"{os.cpu_count()} CPUs; {datetime.date.today().isoformat()}; median of {args.repeats} passes "
        f"after a one-identity warm-up, full step median of {args.step_repeats}",
        f"load average (1, 5, 15 min) at start {tuple(round(x, 2) for x in load0)}, "
        f"at end {tuple(round(x, 2) for x in load1)}",
    ]
    footer = [
        "identity-views per hour = batch / (s per step) × 3600, from the sum of components; the ratio is "
        "against small-paper's schedule mean (stage-1 steps at the stage-1 cost, the rest at the stage-2 "
        "cost).",
        f"profile wall time {time.perf_counter() - started:.0f} s",
    ]
    text = render_report(phases, synth, header, footer)
    sys.stdout.write(text)
    if args.out is not None:
        with atomic_path(args.out) as tmp:
            Path(tmp).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
