"""Settings that follow the noise level: a table of tuned values interpolated in log noise."""

from __future__ import annotations

import math

__all__ = ["interpolate_by_noise"]


def interpolate_by_noise(table: dict, noise: float) -> float:
    """The value of ``table`` ({noise level: value}) at ``noise``: piecewise linear in log(noise)
    between the two levels around it (in log(value) too when both values are positive, so that a
    rate or a count grows by a constant factor per factor of noise), the end values beyond the
    table's range. Continuous in ``noise``: a cloud between two tuned levels gets settings between
    theirs, never the nearest level's."""
    levels = sorted(float(k) for k in table)
    vals = [float(table[k]) for k in sorted(table, key=float)]
    if not levels:
        raise ValueError("an empty table")
    if not noise > 0:
        raise ValueError(f"the noise level must be positive, got {noise}")
    if noise <= levels[0] or len(levels) == 1:
        return vals[0]
    if noise >= levels[-1]:
        return vals[-1]
    i = max(j for j in range(len(levels) - 1) if levels[j] <= noise)
    t = (math.log(noise) - math.log(levels[i])) / (math.log(levels[i + 1]) - math.log(levels[i]))
    a, b = vals[i], vals[i + 1]
    if a > 0 and b > 0:
        return float(math.exp((1 - t) * math.log(a) + t * math.log(b)))
    return float((1 - t) * a + t * b)
