"""The rig's soft shadow as a blurred disc fitted jointly with the room's light (rig_shadow.disc_shadow)."""

from __future__ import annotations

import numpy as np
import torch

from panoworld.depth.rig.shadow import disc_shadow
from tests.test_rig import _blotchy_floor

torch.set_num_threads(1)


def _h(theta):
    return np.tan(np.deg2rad(theta))


def _gradient(t, p):
    """The room's light: brighter to one side, a little toward two others (smooth, broad)."""
    return 1.0 + 0.25 * _h(t) * np.cos(p) + 0.15 * (_h(t) * np.sin(p)) ** 2


def _soft_disc(t, p):
    """The generator's soft shadow at a 1.5 m camera height: 45 % at the nadir, 0.4 m 1/e radius."""
    return 1.0 - 0.45 * np.exp(-((_h(t) / 0.27) ** 2))


def test_disc_depth_and_light_measured_under_a_room_light_gradient():
    for seed in (0, 1):
        face, theta, _, focal = _blotchy_floor(lambda t: np.full_like(t, 0.2), seed=seed,
                                               light=lambda t, p: _gradient(t, p) * _soft_disc(t, p))
        fit = disc_shadow(face, theta < 3.0, np.ones_like(theta, bool), theta, focal)
        assert abs(fit.depth - 0.45) < 0.03 and fit.gain_of_fit > 0.1, fit
        gain = fit.gain(theta)
        for deg in (6.0, 12.0, 18.0):
            ring = np.abs(theta - deg) < 1.0
            assert abs(np.median(gain[ring]) * _soft_disc(deg, 0.0) - 1.0) < 0.04, (seed, deg, fit)


def test_no_disc_in_a_room_light_gradient_alone():
    # No shadow: the room's light is the quadratic's; the disc explains (almost) nothing and removes < 3 % of the
    # light (development tripods without a shadow read a gain of fit <= 0.02, except 100 in the room's own shadow).
    for seed in (0, 1):
        face, theta, _, focal = _blotchy_floor(lambda t: np.full_like(t, 0.2), seed=seed, light=_gradient)
        fit = disc_shadow(face, theta < 3.0, np.ones_like(theta, bool), theta, focal)
        assert fit.gain_of_fit < 0.01 and np.all(fit.gain(theta)[theta > 3.0] < 1.03), fit
