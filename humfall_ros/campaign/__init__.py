"""Push campaigns: thousands of closed-loop trials from one spec, on this machine or a Ray cluster.

``spec`` (the YAML study spec, pydantic), ``design`` (grid / seeded random trials over
scenario keys), ``studies`` (a plain sweep; the fall-threshold map by bisection),
``server`` (one trial in an isolated, killable process), ``executors`` (local
process pool or Ray, same trial code), ``store`` (resumable Parquet fragments),
``runner`` (the loop with the progress bar), ``report`` (HTML page), ``cli``.
See docs/campaign.md.
"""
