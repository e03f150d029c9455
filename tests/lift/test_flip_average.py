"""``lp3d.lift.flip_average``: the mean of an encoder's planes of a photo and the mirror of its planes of
the flipped photo; the same for numpy and torch, and the identity for an encoder that is already
mirror-equivariant (the property the training's flip augmentation teaches)."""

from __future__ import annotations

import numpy as np
import torch

from lp3d.lift.flip_average import flip_averaged
from lp3d.render.triplane import mirror_planes

B, S, C, T = 3, 8, 4, 6
RNG = np.random.default_rng(0)
#: A fixed linear "encoder" (images (B, 3, S, S) -> planes (B, 3, C, T, T)) with no symmetry at all.
WEIGHTS = RNG.standard_normal((3 * S * S, 3 * C * T * T)).astype(np.float32) / S


def lopsided(images):
    """Not mirror-equivariant: its planes of a flipped photo are not the mirror of its planes."""
    if isinstance(images, np.ndarray):
        return (images.reshape(len(images), -1) @ WEIGHTS).reshape(len(images), 3, C, T, T)
    return (images.reshape(len(images), -1) @ torch.from_numpy(WEIGHTS)).reshape(len(images), 3, C, T, T)


def symmetrised(images):
    """Mirror-equivariant by construction: lopsided(x) + mirror(lopsided(flip x))."""
    return lopsided(images) + mirror_planes(lopsided(images[..., ::-1].copy()))


def test_is_the_mean_of_the_two_passes_in_numpy_and_torch():
    x = RNG.standard_normal((B, 3, S, S)).astype(np.float32)
    want = 0.5 * (lopsided(x) + mirror_planes(lopsided(x[..., ::-1].copy())))
    got = flip_averaged(lopsided, x)
    assert got.shape == (B, 3, C, T, T)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
    # It changes a lopsided encoder's output: the test would not pass with flip_averaged = encode.
    assert np.abs(got - lopsided(x)).max() > 0.1
    got_t = flip_averaged(lopsided, torch.from_numpy(x))
    np.testing.assert_allclose(got_t.numpy(), want, rtol=0, atol=1e-5)


def test_leaves_a_mirror_equivariant_encoder_unchanged():
    x = RNG.standard_normal((B, 3, S, S)).astype(np.float32)
    np.testing.assert_allclose(flip_averaged(symmetrised, x), symmetrised(x), rtol=0, atol=1e-5)


def test_runs_the_encoder_once_on_twice_the_batch():
    calls = []

    def counted(images):
        calls.append(images.shape[0])
        return lopsided(images)

    flip_averaged(counted, RNG.standard_normal((B, 3, S, S)).astype(np.float32))
    assert calls == [2 * B]
