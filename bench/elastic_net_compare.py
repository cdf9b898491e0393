#!/usr/bin/env python3
"""Compare geocal's elastic net with scikit-learn's on the matrices the Rust bench wrote.

Usage: python3 bench/elastic_net_compare.py DIR   (DIR from `cargo bench --bench elastic_net`)
Same objective: (1/2N)||y - Xb||^2 + lam*(a*||b||_1 + (1-a)/2*||b||^2), raw columns, no intercept.
"""
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from sklearn.linear_model import ElasticNet
from sklearn.exceptions import ConvergenceWarning


def main() -> int:
    d = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    rust = json.loads((d / "rust_fits.json").read_text())
    print(f"{'case':>10} {'λ':>10} {'α':>4} {'max rel diff':>13} {'sk ms':>9} {'rust ms':>9} {'sk/rust':>8}")
    worst = 0.0
    for case in rust["cases"]:
        x = np.loadtxt(d / f"X_{case['name']}.csv", delimiter=",")
        y = np.loadtxt(d / f"y_{case['name']}.csv")
        xf = np.asfortranarray(x)
        for fit in case["fits"]:
            model = ElasticNet(alpha=fit["lambda"], l1_ratio=fit["alpha"], fit_intercept=False,
                               tol=1e-13, max_iter=2_000_000, selection="cyclic")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                t0 = time.perf_counter()
                model.fit(xf, y)
                sk_s = time.perf_counter() - t0
            b_sk = model.coef_
            b_rs = np.array(fit["coef"])
            rel = np.max(np.abs(b_rs - b_sk)) / max(np.max(np.abs(b_sk)), 1e-300)
            worst = max(worst, rel)
            print(f"{case['name']:>10} {fit['lambda']:>10.3e} {fit['alpha']:>4} {rel:>13.2e} "
                  f"{sk_s * 1e3:>9.2f} {fit['seconds'] * 1e3:>9.2f} {sk_s / fit['seconds']:>8.2f}")
    print(f"worst coefficient max relative difference: {worst:.2e} (aim 1e-6)")
    return 0 if worst < 1e-6 else 1


if __name__ == "__main__":
    sys.exit(main())
