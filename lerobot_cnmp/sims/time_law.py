"""The minimum-jerk time law the sims' scripted planners move along."""

from __future__ import annotations

import numpy as np


def minimum_jerk(u):
    """The minimum-jerk time law ``10 u^3 - 15 u^4 + 6 u^5`` of ``u`` clipped to [0, 1]: 0 -> 1 with zero
    velocity and acceleration at both ends."""
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10.0 - 15.0 * u + 6.0 * u**2)
