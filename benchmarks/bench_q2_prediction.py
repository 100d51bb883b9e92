"""How far is paper 1's Q2 from the capture point the robot really has at the step's touchdown? (session 39)

Q2 (eq. 1-2) is the capture point at the swing's touchdown predicted at the decision by a rigid inverted pendulum
about the stance pivot; the capture test and every ranking stand on it. This runs forward pushes on
``standing_push`` (``push.0.force=[F, 0, 0]``) with the ``stepping`` controller and, on the tick the swing sole
lands, reads the ground-truth capture point xi = x + v / omega and its margin inside both soles' hull. Beside the
decision's Q2 it reports the Q2 that also carries the swing leg's own mass to the landing (ours,
``swing_com_shift``: Q2 + ``HumanoidModel.swing_com_gain`` x (landing - swing sole at the decision)), for the
same decision, so both predictions are measured against one outcome.

    python benchmarks/bench_q2_prediction.py [--forces 337,452,500,607] [--set KEY=VALUE ...] [--duration 2.5]

(``--set``: scenario overrides, e.g. params.safe_fall_controller.defer_scope=any.) Prints one JSON object: per push
the decision, the predicted Q2 (paper / shifted), the measured xi, their errors [m], the margins inside the landed
hull [m] and whether the robot fell within ``--duration``; then the mean absolute errors.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from humfall_ros import scenario  # noqa: E402
from humfall_ros.dynamics.pendulum import GRAVITY  # noqa: E402
from humfall_ros.model.humanoid import SIDES, point_in_polygon_margin, support_polygon  # noqa: E402
from humfall_ros.sim.closed_loop import ClosedLoop  # noqa: E402
from humfall_ros.sim.fall_runs import controllers_for  # noqa: E402


def one_push(force: float, overrides: list[str], duration: float) -> dict:
    sc = scenario.load("standing_push", [f"push.0.force=[{force}, 0.0, 0.0]", *overrides])
    ctrls, monitors = controllers_for(sc, "stepping")
    loop = ClosedLoop(sc, ctrls, monitors)
    safe = getattr(ctrls[1], "inner", ctrls[1])
    out: dict = {"force_n": force}
    try:
        for _ in range(int(round(duration * sc["sim"]["control_rate"]))):
            loop.step()
            w = loop.world
            m = w.model
            d = safe.decision
            if d is not None and "case" not in out:
                out["decision_time_s"] = round(w.time, 3)
                out["case"] = d.case
                out["landing"] = np.round(d.landing, 3).tolist()
                out["q2_decision"] = np.asarray(d.q2, float)[:2]
                swing = safe.swing_of(safe.chosen.case) if safe.chosen.landing is not None else None
                out["swing"] = swing
                if swing is not None and safe.q_decision is not None:
                    gain = m.swing_com_gain(safe.q_decision, swing)
                    step = np.asarray(d.landing, float)[:2] - np.asarray(safe.swing_start_xy, float)
                    shift = gain @ step
                    shifted_on = bool(safe.config.swing_com_shift)
                    # the decision's Q2 is the paper's, or already shifted (swing_com_shift): report both
                    out["q2_paper"] = out["q2_decision"] - (shift if shifted_on else 0.0)
                    out["q2_shifted"] = out["q2_paper"] + shift
                    out["step_m"] = round(float(np.hypot(*step)), 3)
            if "case" in out and "touchdown_time_s" not in out and safe.touchdown_at is not None:
                q, v = w.pinocchio_state()
                m.forward(q)
                pin.centerOfMass(m.model, m.data, q, v)
                com, vc = m.data.com[0].copy(), m.data.vcom[0].copy()
                xi = com[:2] + vc[:2] / math.sqrt(GRAVITY / com[2])
                hull = support_polygon(np.vstack([m.sole_corners(sd)[:, :2] for sd in SIDES]))
                out["touchdown_time_s"] = round(w.time, 3)
                out["xi_measured"] = xi
                out["xi_margin_m"] = round(point_in_polygon_margin(xi, hull), 4)
                for k in ("q2_paper", "q2_shifted"):
                    if k in out:
                        out[f"{k}_error_m"] = round(float(np.linalg.norm(out[k] - xi)), 4)
                        out[f"{k}_margin_m"] = round(point_in_polygon_margin(out[k], hull), 4)
            if w.non_foot_contact():
                out["fell_s"] = round(w.time, 3)
                break
    finally:
        loop.close()
    for k in ("q2_decision", "q2_paper", "q2_shifted", "xi_measured"):
        if k in out:
            out[k] = np.round(out[k], 4).tolist()
    out["fell"] = "fell_s" in out
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--forces", default="337,452,500,607", help="forward push forces [N], comma-separated")
    ap.add_argument("--set", action="append", default=[], help="scenario override KEY=VALUE (repeatable)")
    ap.add_argument("--duration", type=float, default=2.5)
    a = ap.parse_args()
    runs = [one_push(float(f), a.set, a.duration) for f in a.forces.split(",")]
    summary = {}
    for k in ("q2_paper_error_m", "q2_shifted_error_m"):
        errs = [r[k] for r in runs if k in r]
        summary[k.replace("_m", "_mean_m")] = round(float(np.mean(errs)), 4) if errs else None
    print(json.dumps({"overrides": a.set, "runs": runs, **summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
