"""``humfall campaign SPEC.yaml`` and ``humfall campaign report RESULTS``.

The lead wires this into humfall_ros/cli.py as ``campaign`` (argv after the word).
"""
from __future__ import annotations

import argparse
import json
import sys

from humfall_ros.campaign.spec import CampaignSpecError


def _run_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="humfall campaign", description=(
        "Run a push campaign (a grid or seeded random design over scenario keys, each trial a closed loop) "
        "into one Parquet table; `humfall campaign report RESULTS` writes its HTML report."))
    p.add_argument("spec", help="campaign spec YAML (or the name of one in config/campaigns)")
    p.add_argument("--address", default=None, help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--workers", type=int, default=None, help="parallel trials (default: all cores)")
    p.add_argument("--local", action="store_true", help="no Ray: a plain local pool of trial processes")
    p.add_argument("--graph", action="store_true", help="run each trial as `humfall up` (ROS graph) in its own "
                   "ROS_DOMAIN_ID instead of the in-process loop")
    p.add_argument("--out", default=None, help="output folder (default: the spec's output.dir)")
    p.add_argument("--fresh", action="store_true", help="move an existing output folder aside instead of resuming")
    p.add_argument("--retry-failed", action="store_true", help="rerun failed, timed-out and crashed trials")
    p.add_argument("--check", action="store_true", help="validate the spec and print the trial count; run nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--report", action="store_true", help="write report.html when the campaign ends")
    return p


def main(argv: list[str]) -> int:
    if argv and argv[0] == "report":
        p = argparse.ArgumentParser(prog="humfall campaign report",
                                    description="HTML report (plots + summary) of a campaign's results")
        p.add_argument("results", help="campaign folder or its results.parquet")
        p.add_argument("-o", "--out", default=None, help="HTML file (default: report.html beside the results)")
        a = p.parse_args(argv[1:])
        from humfall_ros.campaign.report import write_report

        try:
            out = write_report(a.results, a.out)
        except FileNotFoundError as e:
            print(f"humfall campaign report: {e}", file=sys.stderr)
            return 2
        print(out)
        return 0
    a = _run_parser().parse_args(argv)
    from humfall_ros.campaign import spec as spec_mod
    from humfall_ros.campaign.runner import RunOptions, prepare, run_campaign
    from humfall_ros.campaign.store import ResumeError

    opts = RunOptions(executor="local" if a.local else "ray", workers=a.workers, address=a.address,
                      mode="graph" if a.graph else None, fresh=a.fresh, retry_failed=a.retry_failed,
                      progress=not a.no_progress, out_dir=a.out)
    try:
        spec = spec_mod.load(a.spec)
        if a.check:
            spec, _, study, digest = prepare(spec, opts)
            print(json.dumps({"name": spec.name, "trials": study.total, "study": spec.study.type,
                              "output": str(spec.output_dir()), "spec_hash": digest}))
            return 0
        s = run_campaign(spec, opts)
    except (CampaignSpecError, ResumeError) as e:
        print(f"humfall campaign: {e}", file=sys.stderr)
        return 2
    except ConnectionError as e:  # ray.init(address=...) found no cluster or was refused
        print(f"humfall campaign: cannot join the Ray cluster: {e} (with Ray's token authentication the "
              "cluster's token must be here too: RAY_AUTH_TOKEN or ~/.ray/auth_token)", file=sys.stderr)
        return 2
    print(json.dumps({"results": s.results, "trials": s.total, "ran": s.ran, "resumed": s.resumed,
                      "status": s.status_counts, "wall_s": round(s.wall_s, 2),
                      "trials_per_minute": round(s.trials_per_minute, 2), "interrupted": s.interrupted}))
    if a.report and s.results:
        from humfall_ros.campaign.report import write_report

        print(write_report(s.results))
    return 130 if s.interrupted else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
