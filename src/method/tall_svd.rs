//! The thin SVD of a tall matrix (m rows ≫ n columns) through its Householder QR, A = Q R:
//! the SVD of the n × n factor R gives the singular values and the right vectors, and
//! U = Q U_R. A direct SVD of A applies every rotation of its iterations to the m × n U; this
//! way they run on n × n, and U is formed once, by Q's reflectors. Backward stable as the
//! direct SVD: the same singular values, rank decisions, projections and pseudo-inverse to
//! rounding.

use nalgebra::{DMatrix, Dyn, SVD};

pub type Svd = SVD<f64, Dyn, Dyn>;

/// Columns below which the direct SVD costs next to nothing whatever the rows.
const FEW_COLUMNS: usize = 32;

/// Whether QR first pays: from about 1.6 rows per column (LAPACK's crossover for the same
/// choice in its SVD drivers), and enough columns for the SVD's rotations to matter.
pub fn is_tall(rows: usize, columns: usize) -> bool {
    columns >= FEW_COLUMNS && 5 * rows >= 8 * columns
}

/// `svd_of(a)`'s thin SVD; for a tall `a`, `svd_of` of its factor R (the singular values
/// and vectors of both are the same to rounding) with U = Q U_R.
pub fn thin_svd(a: &DMatrix<f64>, svd_of: impl Fn(&DMatrix<f64>) -> Svd) -> Svd {
    if !is_tall(a.nrows(), a.ncols()) {
        return svd_of(a);
    }
    let qr = a.clone().qr();
    let mut svd = svd_of(&qr.r());
    if let Some(u_r) = svd.u.take() {
        svd.u = Some(qr.q() * u_r);
    }
    svd
}

/// The largest singular value, as the root of the Gram matrix's largest eigenvalue: that
/// eigenvalue is perfectly conditioned, so this is the SVD's value to rounding, at a fraction
/// of a tall matrix's bidiagonalisation. 0 for an empty matrix.
pub fn largest_singular_value(m: &DMatrix<f64>) -> f64 {
    if m.is_empty() {
        0.0
    } else {
        m.tr_mul(m).symmetric_eigenvalues().max().max(0.0).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DVector;

    /// A deterministic pseudo-random m × n matrix of rank `rank` (its last columns
    /// combinations of the first), columns scaled over four decades.
    fn matrix(m: usize, n: usize, rank: usize, seed: u64) -> DMatrix<f64> {
        let mut state = seed;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let base = DMatrix::from_fn(m, rank, |_, _| next());
        let mix = DMatrix::from_fn(rank, n, |i, j| if i == j { 1.0 } else { next() });
        let mut a = base * mix;
        for (c, mut column) in a.column_iter_mut().enumerate() {
            column *= 10f64.powf(4.0 * c as f64 / n as f64 - 2.0);
        }
        a
    }

    fn direct(a: &DMatrix<f64>) -> Svd {
        a.clone().svd(true, true)
    }

    /// Singular values, the kept directions' projectors U Uᵀ and V Vᵀ and the minimum-norm
    /// solution of the QR route against nalgebra's SVD of the whole matrix.
    #[test]
    fn qr_route_equals_the_direct_svd() {
        for (m, n, rank, seed) in [(300, 40, 40, 1), (500, 40, 33, 2), (64, 40, 40, 3)] {
            let a = matrix(m, n, rank, seed);
            let b = DVector::from_fn(m, |i, _| ((i * 37 % 11) as f64 - 5.0) * 0.1);
            let reference = direct(&a);
            let svd = thin_svd(&a, direct);
            let smax = reference.singular_values[0];
            let keep = |s: &DVector<f64>| {
                (0..s.len())
                    .filter(|&k| s[k] > 1e-9 * smax)
                    .collect::<Vec<_>>()
            };
            let (kept, kept_ref) = (keep(&svd.singular_values), keep(&reference.singular_values));
            assert_eq!(kept.len(), rank, "{m}×{n}");
            assert_eq!(kept_ref.len(), rank, "{m}×{n}");
            for k in 0..rank {
                let (x, y) = (svd.singular_values[k], reference.singular_values[k]);
                assert!((x - y).abs() <= 1e-12 * smax, "σ{k}: {x} vs {y}");
            }
            let (u, vt) = (svd.u.expect("U"), svd.v_t.expect("Vᵀ"));
            let (u_ref, vt_ref) = (
                reference.u.as_ref().expect("U"),
                reference.v_t.as_ref().expect("Vᵀ"),
            );
            let cols = |m: &DMatrix<f64>, k: &[usize]| m.select_columns(k);
            let rows = |m: &DMatrix<f64>, k: &[usize]| m.select_rows(k);
            let pu = cols(&u, &kept) * cols(&u, &kept).transpose();
            let pu_ref = cols(u_ref, &kept) * cols(u_ref, &kept).transpose();
            assert!((pu - pu_ref).amax() <= 1e-10, "U Uᵀ {m}×{n}");
            let pv = rows(&vt, &kept).transpose() * rows(&vt, &kept);
            let pv_ref = rows(vt_ref, &kept).transpose() * rows(vt_ref, &kept);
            assert!((pv - pv_ref).amax() <= 1e-10, "V Vᵀ {m}×{n}");
            let solve = |u: &DMatrix<f64>, s: &DVector<f64>, vt: &DMatrix<f64>| {
                kept.iter().fold(DVector::zeros(n), |x, &k| {
                    x + vt.row(k).transpose() * (u.column(k).dot(&b) / s[k])
                })
            };
            let x = solve(&u, &svd.singular_values, &vt);
            let x_ref = solve(u_ref, &reference.singular_values, vt_ref);
            assert!(
                (&x - &x_ref).norm() <= 1e-10 * x_ref.norm(),
                "solution {m}×{n}: {:e}",
                (&x - &x_ref).norm() / x_ref.norm()
            );
        }
    }

    /// The Gram route's largest singular value against the SVD's, on matrices of full and of
    /// deficient rank with columns over four decades, and an empty one.
    #[test]
    fn largest_singular_value_is_the_svds() {
        for (m, n, rank, seed) in [(300, 40, 40, 4), (500, 42, 30, 5), (6, 6, 6, 6)] {
            let a = matrix(m, n, rank, seed);
            let reference = a.clone().svd(false, false).singular_values.max();
            let value = largest_singular_value(&a);
            assert!(
                (value - reference).abs() <= 1e-13 * reference,
                "{m}×{n}: {value} vs {reference}"
            );
        }
        assert_eq!(largest_singular_value(&DMatrix::zeros(0, 3)), 0.0);
    }
}
