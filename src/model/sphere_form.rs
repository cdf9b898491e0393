//! Form error of a reference sphere: real spherical harmonics of degree 2 and 3 at a unit
//! vector (unnormalised Cartesian forms). Degree 0 is the radius and degree 1 the centre, which
//! the methods estimate anyway.

use nalgebra::Vector3;

/// The harmonics' names, in the order of [`harmonics`].
pub const TERMS: [&str; 12] = [
    "c2_xy",
    "c2_yz",
    "c2_zz",
    "c2_xz",
    "c2_xx_yy",
    "c3_y3xx_yy",
    "c3_xyz",
    "c3_y5zz_1",
    "c3_z5zz_3",
    "c3_x5zz_1",
    "c3_zxx_yy",
    "c3_xxx_3yy",
];

/// The degree-2 and degree-3 harmonics at the unit vector `n`.
pub fn harmonics(n: &Vector3<f64>) -> [f64; 12] {
    let (x, y, z) = (n.x, n.y, n.z);
    [
        x * y,
        y * z,
        3.0 * z * z - 1.0,
        x * z,
        x * x - y * y,
        y * (3.0 * x * x - y * y),
        x * y * z,
        y * (5.0 * z * z - 1.0),
        z * (5.0 * z * z - 3.0),
        x * (5.0 * z * z - 1.0),
        z * (x * x - y * y),
        x * (x * x - 3.0 * y * y),
    ]
}

/// The harmonics that depend on the azimuth about z (all but the zonal `c2_zz` and
/// `c3_z5zz_3`): only these turn with a sphere turned about z.
const AZIMUTHAL: [usize; 10] = [0, 1, 3, 4, 5, 6, 7, 9, 10, 11];

/// The names of [`azimuthal_harmonics`], in its order.
pub const AZIMUTHAL_TERMS: [&str; 10] = {
    let mut names = [""; 10];
    let mut i = 0;
    while i < AZIMUTHAL.len() {
        names[i] = TERMS[AZIMUTHAL[i]];
        i += 1;
    }
    names
};

/// The harmonics at `n` that depend on the azimuth about z.
pub fn azimuthal_harmonics(n: &Vector3<f64>) -> [f64; 10] {
    let all = harmonics(n);
    AZIMUTHAL.map(|k| all[k])
}
