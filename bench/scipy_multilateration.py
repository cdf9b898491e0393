#!/usr/bin/env python3
"""Reference solve of a geocal multilateration problem with scipy.optimize.least_squares.

Run by `cargo bench --bench multilateration`, which writes each synthetic problem to a JSON
file and reads back the last line this script prints (one JSON object: time, cost, ...).
Usable alone too:  python3 bench/scipy_multilateration.py PROBLEM.json [--jac analytic|2-point]

The problem (same unknowns and start as geocal's solver):
    residual_k = (length_k - (|P_station(k) - X_point(k)| - d_segment(k))) / sigma_k
over all point coordinates X (3n), station positions P (3m) and homing distances d (S),
with the 6 gauge coordinates listed in the file held at their nominal values. The reported
`chi2` = sum residual_k^2 = 2 * scipy's `cost`, which is geocal's `chi2`; it does not depend
on how the gauge is fixed.
"""

import argparse
import json
import sys
import time

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix


def load(path):
    with open(path) as f:
        p = json.load(f)
    return {
        "nominal": np.asarray(p["nominal_m"], dtype=float).reshape(-1, 3),
        "stations0": np.asarray(p["start_stations_m"], dtype=float).reshape(-1, 3),
        "distances0": np.asarray(p["start_distances_m"], dtype=float),
        "segment_station": np.asarray(p["segment_station"], dtype=np.int64),
        "obs_point": np.asarray(p["obs_point"], dtype=np.int64),
        "obs_segment": np.asarray(p["obs_segment"], dtype=np.int64),
        "obs_length": np.asarray(p["obs_length_m"], dtype=float),
        "obs_sigma": np.asarray(p["obs_sigma_m"], dtype=float),
        "fixed": [(int(i), int(a)) for i, a in p["fixed"]],
    }


class Problem:
    """Residuals and the analytic sparse Jacobian over the free parameters."""

    def __init__(self, d):
        self.n = len(d["nominal"])
        self.m = len(d["stations0"])
        self.s = len(d["distances0"])
        self.ip = d["obs_point"]
        self.isg = d["obs_segment"]
        self.js = d["segment_station"][self.isg]
        self.length = d["obs_length"]
        self.w = 1.0 / d["obs_sigma"]
        n, m = self.n, self.m
        self.full0 = np.concatenate([d["nominal"].ravel(), d["stations0"].ravel(), d["distances0"]])
        free = np.ones(self.full0.size, dtype=bool)
        for i, a in d["fixed"]:
            free[3 * i + a] = False
        self.free_idx = np.flatnonzero(free)
        col_of = -np.ones(self.full0.size, dtype=np.int64)
        col_of[self.free_idx] = np.arange(self.free_idx.size)

        # Seven Jacobian entries per residual: 3 point, 3 station, 1 distance column.
        nobs = self.ip.size
        full_cols = np.column_stack(
            [3 * self.ip, 3 * self.ip + 1, 3 * self.ip + 2,
             3 * n + 3 * self.js, 3 * n + 3 * self.js + 1, 3 * n + 3 * self.js + 2,
             3 * n + 3 * m + self.isg]
        )
        cols = col_of[full_cols]
        self.keep = cols >= 0
        rows = np.broadcast_to(np.arange(nobs)[:, None], cols.shape)[self.keep]
        cols = cols[self.keep]
        self.shape = (nobs, self.free_idx.size)
        # Build the CSR pattern once; each call only permutes the new values into it.
        order = coo_matrix(
            (np.arange(1, rows.size + 1, dtype=float), (rows, cols)), shape=self.shape
        ).tocsr()
        self.perm = order.data.astype(np.int64) - 1
        self.indices = order.indices.copy()
        self.indptr = order.indptr.copy()
        self.sparsity = csr_matrix(
            (np.ones(rows.size), self.indices, self.indptr), shape=self.shape
        )

    def x0(self):
        return self.full0[self.free_idx].copy()

    def unpack(self, x):
        full = self.full0.copy()
        full[self.free_idx] = x
        n, m = self.n, self.m
        return full[: 3 * n].reshape(-1, 3), full[3 * n : 3 * n + 3 * m].reshape(-1, 3), full[3 * n + 3 * m :]

    def fun(self, x):
        pts, sta, dist = self.unpack(x)
        r = np.linalg.norm(sta[self.js] - pts[self.ip], axis=1)
        return (self.length - (r - dist[self.isg])) * self.w

    def jac(self, x):
        pts, sta, _ = self.unpack(x)
        diff = sta[self.js] - pts[self.ip]
        u = diff / np.linalg.norm(diff, axis=1)[:, None]
        uw = u * self.w[:, None]
        vals = np.column_stack([uw, -uw, self.w])[self.keep]
        return csr_matrix((vals[self.perm], self.indices, self.indptr), shape=self.shape)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("problem")
    ap.add_argument("--jac", choices=["analytic", "2-point"], default="analytic")
    ap.add_argument("--tol", type=float, default=1e-12, help="ftol = xtol = gtol")
    ap.add_argument("--max-nfev", type=int, default=None)
    args = ap.parse_args()

    t_load = time.perf_counter()
    prob = Problem(load(args.problem))
    x0 = prob.x0()
    load_s = time.perf_counter() - t_load
    f0 = prob.fun(x0)

    kwargs = dict(method="trf", x_scale="jac", tr_solver="lsmr",
                  ftol=args.tol, xtol=args.tol, gtol=args.tol, max_nfev=args.max_nfev)
    if args.jac == "analytic":
        kwargs["jac"] = prob.jac
    else:
        kwargs["jac"] = "2-point"
        kwargs["jac_sparsity"] = prob.sparsity
    t0 = time.perf_counter()
    res = least_squares(prob.fun, x0, **kwargs)
    solve_s = time.perf_counter() - t0

    out = {
        "solver": f"scipy.optimize.least_squares(trf, lsmr, x_scale=jac, jac={args.jac})",
        "time_s": solve_s,
        "setup_s": load_s,
        "chi2_start": float(f0 @ f0),
        "chi2": float(2.0 * res.cost),
        "nfev": int(res.nfev),
        "njev": int(res.njev) if res.njev is not None else None,
        "status": int(res.status),
        "message": str(res.message),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
