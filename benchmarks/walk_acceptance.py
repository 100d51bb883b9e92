"""Issue 10's acceptance rows in one go (one JSON object): the five speeds, the turn, the speed change and the
TYPICAL_NOISE seeds, each a ``walk_loop.run_walk`` (ClosedLoop, lockstep, exact sensors unless said).

    python benchmarks/walk_acceptance.py [--jobs 2] [--rows speeds,turn,change,noise] [--set=KEY=VALUE ...]

Rows: ``speed_<km/h>`` (20 steps), ``turn`` (10 deg/s, 12 steps at 1.0 km/h), ``change`` (1.0 -> 1.8 km/h at
t = 6 s, 20 steps), ``noise_<seed>`` (1.0 km/h, 20 steps, TYPICAL_NOISE seeds 1-3). Each row: the WalkResult
fields (without its messages).
"""
from __future__ import annotations

import dataclasses
import json
import pathlib
import sys
from concurrent.futures import ProcessPoolExecutor

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

SPEEDS = (0.5, 1.0, 1.35, 1.8, 2.0, 2.5)


class _SpeedChange:
    """One ``cmd_walk`` of 1.8 km/h on the first tick at or after 6 s (a command every tick would re-plan every
    tick)."""

    def __init__(self):
        self.sent = False

    def __call__(self, loop, obs):
        from humfall_ros.walking.footsteps import WalkCommand

        if obs.time >= 6.0 and not self.sent:
            self.sent = True
            obs.inputs["cmd_walk"] = WalkCommand(1.8 / 3.6, 0.0)


def row(name: str, sets: list[str]) -> tuple[str, dict]:
    from humfall_ros.sim.sensors import TYPICAL_NOISE
    from walk_loop import run_walk

    if name.startswith("speed_"):
        res, _ = run_walk(float(name[6:]), 20, sets)
    elif name == "turn":
        res, _ = run_walk(1.0, 12, ["walk.turn_rate_deg_s=10", *sets])
    elif name == "change":
        res, _ = run_walk(1.0, 20, sets, inputs=_SpeedChange())
    elif name.startswith("noise_"):
        res, _ = run_walk(1.0, 20, sets, noise=dataclasses.replace(TYPICAL_NOISE, seed=int(name[6:])))
    else:
        raise ValueError(f"unknown row {name!r}")
    d = res.as_dict()
    d.pop("messages", None)
    return name, d


def main(argv: list[str]) -> int:
    jobs = int(argv[argv.index("--jobs") + 1]) if "--jobs" in argv else 2
    kinds = argv[argv.index("--rows") + 1].split(",") if "--rows" in argv else ["speeds", "turn", "change", "noise"]
    sets = [a.split("=", 1)[1] for a in argv if a.startswith("--set=")]
    names = []
    for k in kinds:
        names += {"speeds": [f"speed_{s}" for s in SPEEDS], "noise": [f"noise_{s}" for s in (1, 2, 3)]}.get(k, [k])
    out = {}
    with ProcessPoolExecutor(jobs) as pool:
        for name, d in pool.map(row, names, [sets] * len(names)):
            out[name] = d
            print(json.dumps({"row": name, **d}), file=sys.stderr, flush=True)   # progress, one line a row
    print(json.dumps({"sets": sets, "rows": out}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
