#!/usr/bin/env python3
"""Independent ISO 230-2:2014 evaluation with numpy, to check geocal's src/evaluate/iso230_2.rs.

Reads curves as JSON (file argument): {"targets": [P_i], "up": [[x_ij]], "down": [[x_ij]]},
runs as rows and targets as columns, and prints the figures as JSON on stdout.
Exit status 3 when numpy is missing, 2 on bad input.
"""
import json
import sys

try:
    import numpy as np
except ImportError:
    print("numpy missing: pip install numpy", file=sys.stderr)
    sys.exit(3)


def one_direction(x):
    """x: runs x targets. Mean, sample standard deviation (ddof=1) and the figures."""
    n = x.shape[0]
    mean = x.mean(axis=0)
    s = x.std(axis=0, ddof=1) if n >= 2 else None
    out = {
        "runs": n,
        "mean": mean,
        "s": s,
        "E": float(np.ptp(mean)),
        "R": float(np.max(4.0 * s)) if s is not None else None,
        "A": float(np.max(mean + 2 * s) - np.min(mean - 2 * s)) if s is not None else None,
    }
    return out


def main():
    if len(sys.argv) != 2:
        print("usage: iso230_2.py CURVES.json", file=sys.stderr)
        sys.exit(2)
    with open(sys.argv[1], encoding="utf-8") as f:
        c = json.load(f)
    up = np.asarray(c["up"], dtype=float)
    down = np.asarray(c["down"], dtype=float)
    u, d = one_direction(up), one_direction(down)
    b_i = u["mean"] - d["mean"]
    bidir_mean = (u["mean"] + d["mean"]) / 2.0
    both = np.vstack([u["mean"], d["mean"]])
    su, sd = u["s"], d["s"]
    r_i = np.maximum.reduce([2 * su + 2 * sd + np.abs(b_i), 4 * su, 4 * sd])
    high = np.maximum(u["mean"] + 2 * su, d["mean"] + 2 * sd)
    low = np.minimum(u["mean"] - 2 * su, d["mean"] - 2 * sd)
    result = {
        "E_up": u["E"], "E_down": d["E"],
        "R_up": u["R"], "R_down": d["R"],
        "A_up": u["A"], "A_down": d["A"],
        "B": float(np.max(np.abs(b_i))),
        "B_mean": float(np.mean(b_i)),
        "E": float(both.max() - both.min()),
        "M": float(np.ptp(bidir_mean)),
        "R": float(np.max(r_i)),
        "A": float(high.max() - low.min()),
        "mean_up": u["mean"].tolist(),
        "mean_down": d["mean"].tolist(),
        "s_up": su.tolist(),
        "s_down": sd.tolist(),
        "B_i": b_i.tolist(),
        "R_i": r_i.tolist(),
    }
    json.dump(result, sys.stdout)
    print()


if __name__ == "__main__":
    main()
