//! What a tilt error motion of the rotary table does to the rotary tracer's step angles
//! (docs/rotary-tracer.md, "What the step angle measures"). The step angle is the turn of the
//! tracer's pivot about the fitted axis: a tilt τ of the table about a horizontal line through
//! the table top moves the pivot, h above that line, sideways by h·τ, and a turn of the
//! pivot of h·τ_r/r enters the step angle (τ_r: the tilt's component about the pivot's radial
//! direction, r: the pivot's distance from the axis). The fit here is the rotary tracer's own
//! (`fit_circle`), on exact station positions: no noise, only the tilt.

use std::f64::consts::TAU;

use geocal::solve::circle::fit_circle;
use nalgebra::{Rotation3, Vector3};
use rand::{Rng, SeedableRng};

/// The published set-up (config/rotary-tracer.toml): 12 stations 30° apart, the pivot 0.2 m
/// off the axis; the pivot 0.14 m above the table top, as in the tester's set-up.
const RADIUS_M: f64 = 0.2;
const PIVOT_HEIGHT_M: f64 = 0.14;
const STATIONS: usize = 12;
const ARCSEC: f64 = TAU / 360.0 / 3600.0;

/// Step errors (fitted turn from station 0 − commanded), radians, when the table stands
/// tilted by `tilts[k]` (a rotation vector, rad, about the table top's centre) at station k.
fn step_errors(tilts: &[Vector3<f64>]) -> Vec<f64> {
    let pivot = Vector3::new(RADIUS_M, 0.0, PIVOT_HEIGHT_M);
    let commanded = |k: usize| TAU * k as f64 / STATIONS as f64;
    let stations: Vec<Vector3<f64>> = (0..STATIONS)
        .map(|k| {
            let turned = Rotation3::from_axis_angle(&Vector3::z_axis(), commanded(k)) * pivot;
            Rotation3::new(tilts[k]) * turned
        })
        .collect();
    let fit = fit_circle(&stations, None, Some(Vector3::z())).expect("circle");
    (0..STATIONS)
        .map(|k| {
            let turned = if k == 0 { 0.0 } else { fit.angle_from(0, k).0 };
            let error = turned - commanded(k);
            (error + TAU / 2.0).rem_euclid(TAU) - TAU / 2.0
        })
        .collect()
}

/// The pivot's radial direction at station k.
fn radial(k: usize) -> Vector3<f64> {
    let a = TAU * k as f64 / STATIONS as f64;
    Vector3::new(a.cos(), a.sin(), 0.0)
}

#[test]
fn a_tilt_about_the_radius_enters_the_step_angle_as_h_tau_over_r() {
    // One station at a time tilted by 8 µrad about its radial direction: it moves sideways by
    // h·τ, so its step angle changes by −h·τ/r; the others are not moved.
    let tau = 8e-6;
    let expected = -PIVOT_HEIGHT_M * tau / RADIUS_M;
    let (mut tilted, mut others, mut tangent) = (0.0f64, 0.0f64, 0.0f64);
    for k in 1..STATIONS {
        let mut tilts = vec![Vector3::zeros(); STATIONS];
        tilts[k] = radial(k) * tau;
        let errors = step_errors(&tilts);
        tilted = tilted.max((errors[k] / expected - 1.0).abs());
        for (j, e) in errors.iter().enumerate().filter(|&(j, _)| j != k) {
            others = others.max((e / expected).abs());
            assert!(e.is_finite(), "station {j}");
        }
        // About the tangent instead: the pivot moves radially and vertically, not round; only
        // the circle's centre, fitted through it, moves a little.
        tilts[k] = radial(k).cross(&Vector3::z()) * tau;
        tangent = tangent.max((step_errors(&tilts)[k] / expected).abs());
    }
    println!(
        "one station tilted {:.0} µrad about its radius: its step angle {:.3} ″ (−h·τ/r = {:.3} ″) \
         within {:.1} %, the other stations' by up to {:.1} % of it; about its tangent: {:.1} %",
        tau * 1e6,
        expected * (1.0 - tilted) / ARCSEC,
        expected / ARCSEC,
        100.0 * tilted,
        100.0 * others,
        100.0 * tangent
    );
    // About the radius: exactly −h·τ/r (first order), nothing elsewhere.
    assert!(tilted < 1e-3, "{tilted}");
    assert!(others < 1e-3, "{others}");
    // About the tangent: only through the fitted centre's shift, a fraction of it.
    assert!(tangent < 0.25, "{tangent}");
}

#[test]
fn random_tilts_of_6_to_10_urad_give_arcsecond_step_errors() {
    // Each station tilted 6..10 µrad in a random horizontal direction, 20 seeds: the step
    // errors, and how well −h·τ_r/r (relative to station 0) predicts them.
    let (mut largest, mut worst_prediction) = (0.0f64, 0.0f64);
    for seed in 0..20u64 {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let tilts: Vec<Vector3<f64>> = (0..STATIONS)
            .map(|_| {
                let size = rng.random_range(6e-6..10e-6);
                let dir = rng.random_range(0.0..TAU);
                Vector3::new(dir.cos(), dir.sin(), 0.0) * size
            })
            .collect();
        let errors = step_errors(&tilts);
        let turn = |k: usize| -PIVOT_HEIGHT_M * tilts[k].dot(&radial(k)) / RADIUS_M;
        for (k, e) in errors.iter().enumerate().skip(1) {
            largest = largest.max(e.abs());
            worst_prediction = worst_prediction.max((e - (turn(k) - turn(0))).abs());
        }
    }
    println!(
        "tilts of 6..10 µrad, pivot {PIVOT_HEIGHT_M} m above the table top, {RADIUS_M} m off \
         the axis: step errors up to {:.2} ″; −h·τ_r/r predicts each within {:.2} ″",
        largest / ARCSEC,
        worst_prediction / ARCSEC
    );
    // h·τ/r at 10 µrad is 7 µrad = 1.44 ″, twice that between two stations; the radial and
    // vertical moves (tilts about the tangent) shift the fitted centre and add to it.
    let bound = 2.0 * PIVOT_HEIGHT_M * 10e-6 / RADIUS_M;
    assert!(largest > 0.3 * bound && largest <= 1.5 * bound, "{largest}");
    assert!(
        worst_prediction < 0.6 * largest,
        "{worst_prediction} of {largest}"
    );
}
