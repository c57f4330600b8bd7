"""How often heavy random noise ends a job in a resend loop, in memory, on simulated time.

    python bench/noise_loops.py                 # 1,600 random jobs (four seeds of 400)
    python bench/noise_loops.py --jobs 400 --seed 1000

Each job is drawn as the property test in tests/protocol/test_loopback.py draws them: up to 150
commands, either flow mode, each fault at 0, 1, 5 or 15 %, Marlin's flush, duplicate drop
and missing ok switched at random, a receive buffer of 40-256 bytes, renumbering every 5-500
lines. Printed: how many jobs did not run exactly once to a confirmed end (the host stops
such a job with a sentence, "asked for line N ... times in a row"; it never loses or repeats
a line), and the first few.
"""

from __future__ import annotations

import argparse
import time

from repetrel_host.session.loopback import run_noise_case


def one_job(case: int) -> str | None:
    """None when the job ran exactly once to a confirmed end, else what happened."""
    commands, result = run_noise_case(case)
    if result.failure is not None:
        return result.failure.reason
    if result.executed != commands or not result.host.is_done:
        return "not run exactly once"
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, default=400, help="jobs per seed")
    parser.add_argument("--seed", type=int, action="append", help="first case of a run of jobs")
    args = parser.parse_args()
    started = time.monotonic()
    failures: list[tuple[int, str]] = []
    seeds = args.seed or [1000, 2000, 3000, 4000]
    for seed in seeds:
        for case in range(seed, seed + args.jobs):
            outcome = one_job(case)
            if outcome is not None:
                failures.append((case, outcome))
    total = args.jobs * len(seeds)
    print(f"{len(failures)} of {total} jobs did not run to a confirmed end under heavy noise")
    for case, outcome in failures[:5]:
        print(f"  job {case}: {outcome}")
    print(f"# {time.monotonic() - started:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
