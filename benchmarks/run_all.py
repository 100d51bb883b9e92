"""`make bench`: run every benchmark and print one JSON object of their figures."""
from __future__ import annotations

import json
import pathlib
import subprocess
import sys

HERE = pathlib.Path(__file__).resolve().parent
BENCHES = ["bench_suite.py", "bench_recorder.py", "bench_multicontact.py",
           # paper 2's sweep from one foot, as its own trees start (session 28; the issue's is from two feet)
           "bench_multicontact.py --initial-mode RF --wall 0",
           "bench_multicontact_library.py",
           # the plans made for the 3-D robot from their own library (session 43)
           "bench_multicontact_library.py --profile execution", "bench_multicontact_exec_tick.py",
           "bench_walking.py", "bench_fall.py", "bench_estop.py",
           # the ankle balance after a touchdown, as a function of the step and the capture point's depth (session 38;
           # its margin in the soles' hull since session 39), and with the hip strategy
           "bench_capture_balance.py", "bench_capture_balance.py --hip-flex 0.3",
           # paper 1's Q2 against the capture point at the touchdown, decided during and after the push (session 39)
           "bench_q2_prediction.py", "bench_q2_prediction.py --set params.safe_fall_controller.defer_scope=any"]
# bench_contract.py (vs a base commit) and bench_campaign.py (long) run on their own


def main() -> int:
    out, status = {}, 0
    for name in BENCHES:
        script, *args = name.split()
        path = HERE / script
        if not path.is_file():
            out[name] = {"skipped": "not present"}
            continue
        p = subprocess.run([sys.executable, str(path), *args], capture_output=True, text=True)
        try:
            out[name] = json.loads(p.stdout[p.stdout.index("{"):])
        except ValueError:
            out[name] = {"error": f"exit {p.returncode}", "stderr_tail": p.stderr[-2000:]}
        status = status or p.returncode
    print(json.dumps(out, indent=2))
    return status


if __name__ == "__main__":
    raise SystemExit(main())
