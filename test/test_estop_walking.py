"""A walking robot stops (scenario walking_estop, in process: ClosedLoop with walking and the e-stop through
the mux, benchmarks/estop_trials.py): planned from walking's pattern state of the trigger tick, no fall,
final CoG at n3 and on the feet's centre line, and two lockstep runs of the same trial are identical."""
from __future__ import annotations

import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))

import estop_trials  # noqa: E402


def test_a_walking_stop_at_the_double_support_start_is_repeatable_and_ends_at_n3():
    kw = {"step": 1, "after": 1.3}            # after the first swing: the shortest walk that has a stride
    a = estop_trials.run_trial(0.5, "ds_start", **kw)
    b = estop_trials.run_trial(0.5, "ds_start", **kw)
    for k in ("com", "cop", "cop_truth", "estop_com_ref"):
        assert np.array_equal(a.trace[k], b.trace[k], equal_nan=True), k       # lockstep: bit for bit
    m = a.metrics
    assert m["walk_refused"] is None and m["fell"] is False
    assert m["feasible"] is True and m["state"] in ("stopping", "stopped", "holding") and m["wait_s"] == 0.0
    # the mux hands the robot from walking to the e-stop at the trigger tick and never back
    act = a.trace["active"]
    k0 = int(np.argmax(act == "estop"))
    assert (act[:k0] == "locomotion").all() and (act[k0:] == "estop").all()
    assert a.trace["t"][k0] == m["trigger_time_s"]
    # planned from the walking pattern's state of that tick (reference CoG, its velocity, reference ZMP)
    plan = a.plan
    ws_com = a.trace["com_ref"][k0]
    np.testing.assert_array_equal(plan.state.com, ws_com)
    np.testing.assert_array_equal(plan.state.zmp, a.trace["zmp_ref"][k0])
    # final CoG: Major within 2 cm of n3, Minor within 1 cm of the feet's centre line, inside the polygon
    assert abs(m["final_cog_vs_n3_m"]) <= 0.02
    assert abs(m["final_cog_minor_m"]) <= 0.01
    assert m["final_cog_inside_m"] > 0.0
    # the CoG reference of the stop starts where walking's was (continuous) and the CoG stops moving
    np.testing.assert_allclose(a.trace["estop_com_ref"][k0], ws_com, atol=1e-9)
    assert m["stop_time_estimator_v_s"] <= m["stop_time_bound_s"] + 0.5
