"""EG3D's triplane decoder as lp3d's effective weights: the OSGDecoder's two layers with their learning-rate
multipliers folded in (:func:`eg3d_decoder_weights`), read from a loaded generator. Used by
:mod:`lp3d.teachers.eg3d`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from lp3d.render.triplane import effective_decoder_weights


def generator_attr(obj: Any, dotted: str) -> Any:
    """``obj.a.b`` for ``"a.b"``, or a TypeError naming the missing attribute."""
    cur = obj
    for i, part in enumerate(dotted.split(".")):
        if not hasattr(cur, part):
            have = ".".join(dotted.split(".")[:i]) or "the generator"
            raise TypeError(
                f"generator does not have EG3D's TriPlaneGenerator interface: {have} has no {part!r} "
                f"(needed: generator.{dotted})"
            )
        cur = getattr(cur, part)
    return cur


def _fc_lr_multiplier(layer: Any, name: str) -> float:
    """The ``lr_multiplier`` of a StyleGAN2 ``FullyConnectedLayer``, checked against its gains.

    EG3D's layer stores ``weight_gain = lr_multiplier / sqrt(in_features)`` and ``bias_gain =
    lr_multiplier`` (no ``lr_multiplier`` attribute); accept any of the three.
    """
    in_features = int(layer.weight.shape[1])
    weight_gain = getattr(layer, "weight_gain", None)
    lr: Any = getattr(layer, "bias_gain", None)
    if lr is None:
        lr = getattr(layer, "lr_multiplier", None)
    if lr is None and weight_gain is not None:
        lr = float(weight_gain) * math.sqrt(in_features)
    if lr is None:
        raise TypeError(
            f"{name} does not look like StyleGAN2's FullyConnectedLayer (no weight_gain, bias_gain or "
            "lr_multiplier), so its effective weights are unknown"
        )
    lr = float(lr)
    if weight_gain is not None and not math.isclose(
        float(weight_gain), lr / math.sqrt(in_features), rel_tol=1e-6
    ):
        raise ValueError(
            f"{name}: weight_gain {float(weight_gain)!r} != lr_multiplier / sqrt(in_features) = "
            f"{lr / math.sqrt(in_features)!r}; not a StyleGAN2 FullyConnectedLayer"
        )
    if getattr(layer, "activation", "linear") != "linear":
        raise ValueError(f"{name}: activation must be 'linear' (EG3D's OSGDecoder), got {layer.activation!r}")
    return lr


def eg3d_decoder_weights(decoder: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """EG3D ``OSGDecoder`` -> effective ``(w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,))`` float32."""
    net = generator_attr(decoder, "net")
    if len(net) != 3:
        raise ValueError(
            f"decoder.net must be [FC, Softplus, FC] (EG3D's OSGDecoder), got {len(net)} modules"
        )
    act = net[1]
    # lp3d's renderers hard-code torch's default softplus (beta 1, threshold 20), as EG3D uses.
    if not isinstance(act, torch.nn.Softplus) or act.beta != 1 or act.threshold != 20:
        raise ValueError(
            f"decoder.net[1] must be torch.nn.Softplus() with default beta/threshold, got {act!r}"
        )
    lr0 = _fc_lr_multiplier(net[0], "decoder.net[0]")
    lr2 = _fc_lr_multiplier(net[2], "decoder.net[2]")
    if lr0 != lr2:  # OSGDecoder builds both layers with the same decoder_lr_mul
        raise ValueError(f"decoder layers have different lr_multipliers ({lr0} and {lr2})")

    def arrays(layer: Any) -> tuple[np.ndarray, np.ndarray]:
        w = layer.weight.detach().to("cpu", torch.float32).numpy()
        b = layer.bias
        b = np.zeros(w.shape[0], np.float32) if b is None else b.detach().to("cpu", torch.float32).numpy()
        return w, b

    (w0, b0), (w1, b1) = arrays(net[0]), arrays(net[2])
    return effective_decoder_weights(w0, b0, w1, b1, lr_multiplier=lr0)
