//! Least squares of a design whose local parameter blocks touch only their own rows
//! ([`LocalBlock`]: a hexapod pose's six), block by block: each block's columns factorised on
//! its rows, the other columns projected off every block's span and factorised once (the
//! Schur complement), then the solution and the full covariance (XᵀX)⁻¹ assembled. Only for a
//! design of full column rank, which it proves from the factors (then the dense
//! pseudo-inverse is the inverse, and both give the same to rounding); else None, and the
//! caller takes the dense route.

use nalgebra::{DMatrix, DVector};

use super::diagnosis::{BlockLayout, LocalBlock};

/// A direction counts as determined when the design's smallest singular value is above this
/// fraction of its largest: ten times the dense route's rank cut, so both keep every one.
const FULL_RANK_MARGIN: f64 = 1e-8;

/// One block's thin SVD on its rows: U (rows × width), singular values, Vᵀ.
struct Factor {
    u: DMatrix<f64>,
    s: DVector<f64>,
    vt: DMatrix<f64>,
}

fn factor(m: DMatrix<f64>) -> Option<Factor> {
    if m.nrows() < m.ncols() {
        return None;
    }
    let svd = m.svd(true, true);
    Some(Factor {
        u: svd.u?,
        s: svd.singular_values,
        vt: svd.v_t?,
    })
}

/// The least-squares solution of x θ ≈ b and the covariance (xᵀx)⁻¹ with the rank (the
/// number of columns), when `blocks` hold for `x` (zero outside their rows, disjoint) and x
/// has full column rank with margin; None otherwise.
pub fn solve_blocked(
    x: &DMatrix<f64>,
    b: &DVector<f64>,
    blocks: &[LocalBlock],
) -> Option<(DVector<f64>, DMatrix<f64>, usize)> {
    let (n, p) = x.shape();
    let global = BlockLayout::of(x, blocks)?.global;
    let g = global.len();
    let g_all = DMatrix::from_fn(n, g, |r, j| x[(r, global[j])]);
    let mut factors = Vec::with_capacity(blocks.len());
    // Per block: T_k = L_k⁺ G_k (what the block's parameters carry of the global columns).
    let mut carried = Vec::with_capacity(blocks.len());
    let mut reduced = g_all.clone();
    let mut local_norm: f64 = 0.0;
    let mut local_min = f64::INFINITY;
    let mut carried_norm2 = 0.0;
    for block in blocks {
        let l = DMatrix::from_fn(block.rows.len(), block.columns.len(), |i, j| {
            x[(block.rows[i], block.columns.start + j)]
        });
        let f = factor(l)?;
        local_norm = local_norm.max(f.s.max());
        local_min = local_min.min(f.s.min());
        if f.s.min() <= 0.0 {
            return None;
        }
        let g_rows = DMatrix::from_fn(block.rows.len(), g, |i, j| g_all[(block.rows[i], j)]);
        let ut_g = f.u.tr_mul(&g_rows);
        let along = &f.u * &ut_g;
        for (i, &r) in block.rows.iter().enumerate() {
            for j in 0..g {
                reduced[(r, j)] -= along[(i, j)];
            }
        }
        let mut scaled = ut_g;
        for (i, mut row) in scaled.row_iter_mut().enumerate() {
            row /= f.s[i];
        }
        let t = f.vt.tr_mul(&scaled);
        carried_norm2 += t.norm_squared();
        carried.push(t);
        factors.push(f);
    }
    let global_norm = super::tall_svd::largest_singular_value(&g_all);
    let reduced_f = if g > 0 { Some(factor(reduced)?) } else { None };
    let reduced_min = reduced_f.as_ref().map_or(f64::INFINITY, |f| f.s.min());
    // σ_min(X) ≥ min(σ_min(G̃), σ_min(L)) / (1 + ‖T‖), σ_max(X) ≤ √(‖G‖² + ‖L‖²).
    let smallest = reduced_min.min(local_min) / (1.0 + carried_norm2.sqrt());
    let largest = (global_norm * global_norm + local_norm * local_norm).sqrt();
    let proven = smallest > FULL_RANK_MARGIN * largest;
    if !proven {
        return None;
    }
    // Global part: θ_G = V S⁻¹ Uᵀ (P b), covariance C_G = V S⁻² Vᵀ.
    let mut projected = b.clone();
    for (block, f) in blocks.iter().zip(&factors) {
        let local = DVector::from_fn(block.rows.len(), |i, _| b[block.rows[i]]);
        let along = &f.u * f.u.tr_mul(&local);
        for (i, &r) in block.rows.iter().enumerate() {
            projected[r] -= along[i];
        }
    }
    let (theta_g, cov_g) = match &reduced_f {
        Some(f) => {
            let coeff = f.u.tr_mul(&projected).component_div(&f.s);
            let mut v_scaled = f.vt.transpose();
            for (k, mut column) in v_scaled.column_iter_mut().enumerate() {
                column /= f.s[k];
            }
            (f.vt.tr_mul(&coeff), &v_scaled * v_scaled.transpose())
        }
        None => (DVector::zeros(0), DMatrix::zeros(0, 0)),
    };
    let mut theta = DVector::zeros(p);
    let mut cov = DMatrix::zeros(p, p);
    for (j, &c) in global.iter().enumerate() {
        theta[c] = theta_g[j];
        for (i, &d) in global.iter().enumerate() {
            cov[(c, d)] = cov_g[(j, i)];
        }
    }
    // Local parts: θ_k = L_k⁺ b_k − T_k θ_G; Cov(θ_G, θ_k) = −C_G T_kᵀ;
    // Cov(θ_k, θ_j) = δ_kj V_k S_k⁻² V_kᵀ + T_k C_G T_jᵀ.
    let cg_tt: Vec<DMatrix<f64>> = carried.iter().map(|t| &cov_g * t.transpose()).collect();
    for (k, (block, f)) in blocks.iter().zip(&factors).enumerate() {
        let local = DVector::from_fn(block.rows.len(), |i, _| b[block.rows[i]]);
        let own = f.vt.tr_mul(&f.u.tr_mul(&local).component_div(&f.s));
        let value = own - &carried[k] * &theta_g;
        let c0 = block.columns.start;
        for (i, v) in value.iter().enumerate() {
            theta[c0 + i] = *v;
        }
        for (j, &c) in global.iter().enumerate() {
            for i in 0..block.columns.len() {
                cov[(c, c0 + i)] = -cg_tt[k][(j, i)];
                cov[(c0 + i, c)] = -cg_tt[k][(j, i)];
            }
        }
        let mut v_scaled = f.vt.transpose();
        for (m, mut column) in v_scaled.column_iter_mut().enumerate() {
            column /= f.s[m];
        }
        let own_cov = &v_scaled * v_scaled.transpose();
        for (j, other) in blocks.iter().enumerate() {
            let cross = &carried[k] * &cg_tt[j];
            let d0 = other.columns.start;
            for a in 0..block.columns.len() {
                for e in 0..other.columns.len() {
                    let mut v = cross[(a, e)];
                    if j == k {
                        v += own_cov[(a, e)];
                    }
                    cov[(c0 + a, d0 + e)] = v;
                }
            }
        }
    }
    Some((theta, cov, p))
}
