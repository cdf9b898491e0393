//! Identifiability of one linear(ised) block: rank, condition, the Cramér–Rao covariance of
//! what the block identifies, and its null directions named as parameter combinations.

use nalgebra::DMatrix;
use serde::Serialize;

/// A singular value below this fraction of the largest (columns scaled to unit norm) counts
/// as zero: the plan cannot see that direction.
const RANK_TOLERANCE: f64 = 1e-8;
/// A parameter whose unit vector has more than this share (scaled) in the null space is not
/// identifiable on its own.
const NULL_SHARE: f64 = 1e-6;
/// Components of a null direction smaller than this (scaled, leading component 1) are left
/// out of its name.
const COMPONENT_SHOWN: f64 = 1e-3;

/// One direction the plan cannot see: moving the parameters together by `coefficients`
/// (leading parameter 1, the others in their unit per unit of the leading one) changes no
/// reading.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct NullDirection {
    pub combination: String,
    pub parameters: Vec<String>,
    pub coefficients: Vec<f64>,
}

#[derive(Debug, Clone)]
pub struct BlockAnalysis {
    pub rank: usize,
    /// Largest over smallest kept singular value, columns scaled to unit norm.
    pub condition_number: f64,
    /// Pseudo-inverse of JᵀJ (J whitened): the Cramér–Rao covariance of every identifiable
    /// combination; entries of unidentifiable parameters mean nothing.
    pub covariance: DMatrix<f64>,
    /// Per parameter, its standard uncertainty, or None when it is not identifiable alone.
    pub sigma: Vec<Option<f64>>,
    pub null_directions: Vec<NullDirection>,
}

/// Analyse the whitened Jacobian `jw` (rows: observations / σ; columns: `names`).
pub fn analyse(names: &[String], jw: &DMatrix<f64>) -> BlockAnalysis {
    let n = jw.ncols();
    // Scale columns to unit norm: parameters in m and rad become comparable.
    let scale: Vec<f64> = (0..n)
        .map(|k| {
            let s = jw.column(k).norm();
            if s > 0.0 && s.is_finite() {
                s
            } else {
                1.0
            }
        })
        .collect();
    // Pad to at least n rows so the SVD returns the whole right singular basis.
    let rows = jw.nrows().max(n);
    let js = DMatrix::from_fn(rows, n, |r, c| {
        if r < jw.nrows() {
            jw[(r, c)] / scale[c]
        } else {
            0.0
        }
    });
    let svd = js.svd(false, true);
    let Some(v_t) = svd.v_t else {
        // nalgebra always returns V when asked; keep a defined answer regardless.
        return BlockAnalysis {
            rank: 0,
            condition_number: f64::INFINITY,
            covariance: DMatrix::zeros(n, n),
            sigma: vec![None; n],
            null_directions: Vec::new(),
        };
    };
    let s = &svd.singular_values;
    let largest = s.iter().copied().fold(0.0, f64::max);
    let kept: Vec<usize> = (0..s.len())
        .filter(|&i| s[i] > largest * RANK_TOLERANCE && s[i] > 0.0)
        .collect();
    let null: Vec<usize> = (0..s.len()).filter(|i| !kept.contains(i)).collect();
    let smallest = kept.iter().map(|&i| s[i]).fold(f64::INFINITY, f64::min);
    let condition_number = if kept.is_empty() {
        f64::INFINITY
    } else {
        largest / smallest
    };
    // Pseudo-inverse in scaled space, back to physical units: C = D⁻¹ Cs D⁻¹.
    let mut covariance = DMatrix::zeros(n, n);
    for &i in &kept {
        let v = v_t.row(i).transpose();
        covariance += &v * v.transpose() / (s[i] * s[i]);
    }
    for r in 0..n {
        for c in 0..n {
            covariance[(r, c)] /= scale[r] * scale[c];
        }
    }
    let null_share = |k: usize| -> f64 { null.iter().map(|&i| v_t[(i, k)].powi(2)).sum() };
    let sigma = (0..n)
        .map(|k| (null_share(k) <= NULL_SHARE).then(|| covariance[(k, k)].max(0.0).sqrt()))
        .collect();
    // A readable basis of the null space: reduced row echelon form with the largest pivots.
    let mut basis: Vec<Vec<f64>> = null
        .iter()
        .map(|&i| v_t.row(i).iter().copied().collect())
        .collect();
    let mut pivots = Vec::new();
    for r in 0..basis.len() {
        let Some((p, _)) = (0..n)
            .filter(|c| !pivots.contains(c))
            .map(|c| (c, basis[r][c].abs()))
            .max_by(|a, b| a.1.total_cmp(&b.1))
        else {
            break;
        };
        let lead = basis[r][p];
        basis[r].iter_mut().for_each(|v| *v /= lead);
        let row = basis[r].clone();
        for (o, other) in basis.iter_mut().enumerate() {
            if o != r {
                let f = other[p];
                other.iter_mut().zip(&row).for_each(|(v, w)| *v -= f * w);
            }
        }
        pivots.push(p);
    }
    let null_directions = basis
        .iter()
        .zip(&pivots)
        .map(|(z, &p)| {
            let mut order: Vec<usize> = (0..n)
                .filter(|&c| c == p || z[c].abs() > COMPONENT_SHOWN)
                .collect();
            order.sort_by(|&a, &b| z[b].abs().total_cmp(&z[a].abs()).then(a.cmp(&b)));
            // Physical coefficients: θ = z / scale, relative to the leading parameter.
            let coefficients: Vec<f64> = order
                .iter()
                .map(|&c| (z[c] / scale[c]) / (z[p] / scale[p]))
                .collect();
            let parameters: Vec<String> = order.iter().map(|&c| names[c].clone()).collect();
            let mut combination = String::new();
            for (k, (name, coef)) in parameters.iter().zip(&coefficients).enumerate() {
                if k == 0 {
                    combination.push_str(name);
                } else {
                    let sign = if *coef < 0.0 { '-' } else { '+' };
                    combination.push_str(&format!(" {sign} {:.4} {name}", coef.abs()));
                }
            }
            NullDirection {
                combination,
                parameters,
                coefficients,
            }
        })
        .collect();
    BlockAnalysis {
        rank: kept.len(),
        condition_number,
        covariance,
        sigma,
        null_directions,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: usize) -> Vec<String> {
        (0..n).map(|k| format!("p{k}")).collect()
    }

    #[test]
    fn full_rank_block_gives_the_inverse_of_the_normal_matrix() {
        let j = DMatrix::from_row_slice(3, 2, &[1.0, 0.0, 1.0, 1.0, 0.0, 2.0]);
        let a = analyse(&names(2), &j);
        let inv = (j.transpose() * &j).try_inverse().expect("invertible");
        assert_eq!(a.rank, 2);
        assert!(a.null_directions.is_empty());
        for k in 0..2 {
            assert!((a.sigma[k].expect("identifiable") - inv[(k, k)].sqrt()).abs() < 1e-12);
        }
    }

    /// Only p0 + 1000·p1 is seen (p1 in other units): the null direction is p1 − 1000·p0 up
    /// to its leading parameter, and p2 stays identifiable with its own σ.
    #[test]
    fn a_confounded_pair_is_named_with_physical_coefficients() {
        let j = DMatrix::from_row_slice(
            4,
            3,
            &[
                1.0, 1000.0, 0.0, //
                2.0, 2000.0, 0.0, //
                0.0, 0.0, 0.5, //
                1.0, 1000.0, 0.0,
            ],
        );
        let a = analyse(&names(3), &j);
        assert_eq!(a.rank, 2);
        assert_eq!(a.sigma[0], None);
        assert_eq!(a.sigma[1], None);
        assert!((a.sigma[2].expect("p2") - 2.0).abs() < 1e-12);
        assert_eq!(a.null_directions.len(), 1);
        let d = &a.null_directions[0];
        // Moving along it changes nothing: J θ = 0.
        let mut theta = [0.0; 3];
        for (p, c) in d.parameters.iter().zip(&d.coefficients) {
            theta[p[1..].parse::<usize>().expect("index")] = *c;
        }
        let moved = &j * nalgebra::DVector::from_column_slice(&theta);
        assert!(moved.amax() < 1e-9, "{moved}");
        assert_eq!(d.parameters.len(), 2, "{d:?}");
    }

    #[test]
    fn an_unobserved_parameter_is_named() {
        let j = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 3.0, 0.0]);
        let a = analyse(&names(2), &j);
        assert_eq!(a.rank, 1);
        assert_eq!(a.null_directions[0].combination, "p1");
        assert!(a.sigma[0].is_some() && a.sigma[1].is_none());
    }
}
