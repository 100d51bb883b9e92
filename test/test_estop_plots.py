"""humfall_ros/estop/plots.py: the figures from a trace (the bag path is exercised in test_estop_graph.py)."""
from __future__ import annotations

import numpy as np

from humfall_ros.estop.plots import plot_displacement, plot_run, run_from_trace


def _trace():
    t = np.arange(0.0, 3.0, 0.002)
    start = 1.0
    com = np.zeros((len(t), 3))
    com[:, 0] = 0.3 * np.minimum(t, start) + 0.1 * (1 - np.exp(-3.0 * np.clip(t - start, 0, None)))
    com[:, 2] = 0.7
    cop = com.copy()
    cop[:, 2] = 0.0
    ref = np.where((t >= start)[:, None], com, np.nan)
    return {"t": t, "com": com, "cop": cop + 0.005, "estop_com_ref": ref, "estop_zmp_ref": np.where(
        (t >= start)[:, None], cop, np.nan), "com_ref": com, "zmp_ref": cop, "walking": t < start,
        "frame_origin": np.array([0.3, 0.0]), "frame_major": np.array([0.0, 1.0]), "start": start,
        "polygon": np.array([[0.2, -0.15], [0.5, -0.15], [0.5, 0.15], [0.2, 0.15]]), "n3": 0.1}


def test_run_from_a_trace_joins_walking_and_stop_references_in_the_stop_frame():
    run = run_from_trace(_trace())
    assert np.isfinite(run.com_ref).all() and np.isfinite(run.zmp_ref).all()   # walking's before, the stop's after
    # the Minor axis is the Major axis turned by -90 deg: world +x is Minor for a Major along +y
    np.testing.assert_allclose(run.local(np.array([[1.3, 0.0]])), [[1.0, 0.0]])
    np.testing.assert_allclose(run.local(np.array([[0.3, 0.2]])), [[0.0, 0.2]])


def test_figures_are_written(tmp_path):
    paths = plot_run(run_from_trace(_trace(), "synthetic"), tmp_path)
    rows = [{"speed_kmh": v, "phase": "ds_start", "n3_m": -0.1 * v, "max_displacement_m": 0.1 * v,
             "predicted_max_zmp_minor_m": 0.01, "max_cop_minor_m": 0.02} for v in (0.5, 1.0)]
    paths.append(plot_displacement(rows, tmp_path / "fig7.png"))
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000
