"""The robust kernel that weighs loop links, and when a weighted closure counts as used (docs/MODEL.md
items 22 and 57).

Every gated loop hypothesis becomes a link at once (:mod:`hippomap.loop_closing`); its weight is the
kernel's weight of its residual on the map (:func:`kernel_weights`, whitened by the link's information
and kernel width, in the link's source frame), revised by :mod:`hippomap.map_correction` as the map
converges (iteratively reweighted least squares), so a true closure is applied fully and a false one
fades. A closure is *used* while its weight is at least :data:`USED_WEIGHT` (:func:`is_used`): what
every report, the service and the viewer count as a closure the map applies.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import InputError

__all__ = ["USED_WEIGHT", "WEIGHT_FLOOR", "is_used", "used_flags", "robust_weight", "kernel_weights"]

#: a loop link whose robust weight is at least this counts as used (applied); below, it has faded
USED_WEIGHT = 0.5
#: the least weight the kernel gives a loop link, so that no link is divided away entirely
WEIGHT_FLOOR = 1e-4


def is_used(status: str, weight: float) -> bool:
    """Whether a loop decision is *used* by the map: accepted, and its link's robust weight (NaN: it has
    no link, e.g. a closure that only relocalised the robot) at least ``USED_WEIGHT``. An accepted
    closure below it has *faded*: the robust kernel has taken it out of the map's solution."""
    return status == "accepted" and (math.isnan(weight) or weight >= USED_WEIGHT)


def used_flags(decisions: Sequence[Any], weights: np.ndarray) -> list[bool]:
    """Per loop decision (anything with a ``status``), whether the map uses it (:func:`is_used` of its status
    and ``weights``' entry, its link's robust weight; NaN: no link)."""
    return [is_used(d.status, w) for d, w in zip(decisions, weights.tolist())]


def robust_weight(whitened_sq, kernel: str = "cauchy"):
    """Weight of a link from its squared whitened residual χ² (IRLS): ``cauchy`` 1 / (1 + χ²),
    ``dcs`` min(1, 2Φ / (Φ + χ²)) with Φ = 1, ``none`` 1."""
    r2 = np.asarray(whitened_sq, dtype=float)
    if kernel == "cauchy":
        return 1.0 / (1.0 + r2)
    if kernel == "dcs":
        return np.minimum(1.0, 2.0 / (1.0 + r2))
    if kernel == "none":
        return np.ones_like(r2)
    raise InputError(f"unknown robust kernel {kernel!r}")


def kernel_weights(e: np.ndarray, info: np.ndarray, width: np.ndarray, kernel: str = "cauchy") -> np.ndarray:
    """Kernel weights of loop links with residuals ``e`` (K, 3) in their source frames,
    information ``info`` (K, 3: x, y, heading) and kernel widths ``width`` (K,): whitened by
    both, floored so that no link is divided away entirely."""
    chi2 = (e[:, 0] ** 2 * info[:, 0] + e[:, 1] ** 2 * info[:, 1] + e[:, 2] ** 2 * info[:, 2]) / width**2
    return np.maximum(robust_weight(chi2, kernel), WEIGHT_FLOOR)
