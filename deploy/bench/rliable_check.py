"""common/analysis/across_seeds.py against rliable on fixed score matrices: the IQM and the probability of
improvement, point estimates and stratified bootstrap intervals, both sides and their differences.

rliable 1.2.0 does not import under pandas 3 (its arch 7 calls a pandas decorator whose signature changed;
arch 8 drops an argument rliable passes), so this runs in a throwaway venv outside the repository, not in the
project's:

    python3 -m venv /tmp/rliable-venv
    /tmp/rliable-venv/bin/pip install rliable==1.2.0 'pandas==2.3.*' 'arch==7.2.*'
    PYTHONPATH=. /tmp/rliable-venv/bin/python deploy/bench/rliable_check.py > results/rliable-check.txt

Point estimates must agree to float rounding. Intervals come from different random draws (rliable draws from
numpy's global RandomState, seeded here; ours from a seeded Generator) and different percentile rules (arch
interpolates linearly; intervals.percentile_interval takes replicate values), so they agree only to the
bootstrap's own noise, which the check shows beside them: our interval again from a second seed.
"""

from __future__ import annotations

import argparse
import platform
from importlib.metadata import version

import numpy as np
from rliable import library, metrics

from common.analysis.across_seeds import Estimate, improvement_estimate, iqm, iqm_estimate, probability_of_improvement
from common.analysis.intervals import Bootstrap, Interval

CAP = 2000  # an episode's step cap: scores pile up there, which makes ties
PACKAGES = ("numpy", "scipy", "pandas", "arch", "rliable")


def cases() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Pairs (X, Y) of runs x tasks matrices, fixed by their seeds."""
    rng = np.random.default_rng(38)
    lengths = lambda runs, low, high: rng.integers(low, high, size=(runs, 10)).astype(np.float64)
    capped = lambda runs, low: np.minimum(lengths(runs, low, CAP + 800), CAP)
    single = lambda runs, mean: rng.normal(mean, 300.0, size=(runs, 1))
    shared = lengths(3, 100, CAP)
    return {
        "3 v 3 runs, 10 starts, lengths": (lengths(3, 300, CAP), lengths(3, 100, 1500)),
        "3 v 3 runs, 10 starts, many at the cap (ties)": (capped(3, 1000), capped(3, 600)),
        "12 v 6 runs (pooled), 10 starts": (lengths(12, 400, CAP), lengths(6, 100, 1600)),
        "5 v 3 runs, one score per run": (single(5, 1200.0), single(3, 1000.0)),
        "3 v 3 runs, equal on every start": (shared, shared.copy()),
    }


def rliable_estimates(x: np.ndarray, y: np.ndarray, replicates: int, seed: int) -> dict[str, Estimate]:
    np.random.seed(seed)  # rliable's StratifiedBootstrap draws from numpy's global RandomState
    iqm_points, iqm_intervals = library.get_interval_estimates(
        {"x": x}, lambda scores: np.array([metrics.aggregate_iqm(scores)]), reps=replicates)
    np.random.seed(seed)
    poi_points, poi_intervals = library.get_interval_estimates(
        {"x,y": [x, y]}, lambda a, b: np.array([metrics.probability_of_improvement(a, b)]), reps=replicates)
    as_estimate = lambda point, interval: Estimate(float(point[0]), _interval(interval))
    return {"IQM(X)": as_estimate(iqm_points["x"], iqm_intervals["x"]),
            "P(X>Y)": as_estimate(poi_points["x,y"], poi_intervals["x,y"])}


def our_estimates(x: np.ndarray, y: np.ndarray, replicates: int, seed: int) -> dict[str, Estimate]:
    bootstrap = Bootstrap(replicates=replicates, seed=seed)
    return {"IQM(X)": iqm_estimate(x, bootstrap), "P(X>Y)": improvement_estimate(x, y, bootstrap)}


def _interval(bounds: np.ndarray) -> Interval:
    """rliable's (2, 1) array of lower and upper bounds."""
    return Interval(float(bounds[0][0]), float(bounds[1][0]))


def report(replicates: int, seed: int) -> list[str]:
    lines = [f"python {platform.python_version()}; " + ", ".join(f"{name} {version(name)}" for name in PACKAGES),
             f"{replicates:,d} bootstrap replicates, 95% percentile intervals; rliable seeded with np.random.seed"
             f"({seed}), ours with Bootstrap(seed={seed}) and, for the bootstrap's own noise, seed {seed + 1}",
             "percentiles: rliable's (arch) interpolate linearly, ours are replicate values (inverted CDF)", ""]
    worst_point = worst_bound = 0.0
    for name, (x, y) in cases().items():
        theirs = rliable_estimates(x, y, replicates, seed)
        ours, again = our_estimates(x, y, replicates, seed), our_estimates(x, y, replicates, seed + 1)
        # the point estimates from the plain functions too, not only through the estimates
        assert ours["IQM(X)"].point == iqm(x) and ours["P(X>Y)"].point == probability_of_improvement(x, y)
        lines.append(f"## {name}: X {x.shape[0]} x {x.shape[1]}, Y {y.shape[0]} x {y.shape[1]}")
        for statistic in theirs:
            t, o, a = theirs[statistic], ours[statistic], again[statistic]
            point_gap = abs(t.point - o.point)
            bound_gap = max(abs(t.interval.low - o.interval.low), abs(t.interval.high - o.interval.high))
            noise = max(abs(a.interval.low - o.interval.low), abs(a.interval.high - o.interval.high))
            # the IQM is in steps, P(X>Y) a share: gaps compare as shares of the estimate for the IQM
            scale = max(abs(t.point), 1.0) if statistic == "IQM(X)" else 1.0
            worst_point, worst_bound = max(worst_point, point_gap / scale), max(worst_bound, bound_gap / scale)
            lines += [f"  {statistic}", f"    rliable  {_shown(t)}", f"    ours     {_shown(o)}",
                      f"    ours, seed {seed + 1}  {_shown(a)}",
                      f"    |difference|: point {point_gap:.3g}, interval ends {bound_gap:.4g} "
                      f"(ours between seeds: {noise:.4g})"]
        lines.append("")
    lines.append(f"largest point gap (relative for the IQM): {worst_point:.3g}; "
                 f"largest interval-end gap (relative for the IQM): {worst_bound:.4g}")
    return lines


def _shown(estimate: Estimate) -> str:
    return f"{estimate.point:.12g} [{estimate.interval.low:.6g}, {estimate.interval.high:.6g}]"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replicates", type=int, default=10_000, help="bootstrap replicates (default 10,000)")
    parser.add_argument("--seed", type=int, default=0, help="both sides' random seed (default 0)")
    args = parser.parse_args(argv)
    print("\n".join(report(args.replicates, args.seed)))


if __name__ == "__main__":
    main()
