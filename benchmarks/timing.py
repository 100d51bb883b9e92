"""Timing summaries the benchmarks print (one definition for every bench script: they import it from their own
directory, which Python puts first on the path of a script it runs)."""
from __future__ import annotations

import numpy as np


def timing_ms(seconds, extra: tuple[str, ...] = ()) -> dict:
    """Median and 99th percentile of durations given in seconds, in ms (4 decimals), and the sample count;
    ``extra`` adds "min" / "max". No samples: the figures are None."""
    a = np.asarray(list(seconds), float) * 1e3
    keys = ("median", "p99", *extra)
    if not a.size:
        return {**{f"{k}_ms": None for k in keys}, "n": 0}
    value = {"median": np.median, "p99": lambda x: np.percentile(x, 99), "min": np.min, "max": np.max}
    return {**{f"{k}_ms": round(float(value[k](a)), 4) for k in keys}, "n": int(a.size)}
