//! Kinematic chain of a 3-axis Cartesian machine (ISO 230-1 style): structure strings,
//! the 21 geometric errors, the exact error model and its first-order Jacobian.
//!
//! Conventions (full text in docs/kinematics.md):
//! - Positions are in the workpiece frame W, metres. At q = 0 with no errors every carriage
//!   frame, the foundation frame F and W coincide; carriage frames are parallel to F.
//! - A carriage moves relative to its parent (the element nearer the foundation) by
//!   `Trans(d·u + δ) · Rot(ε)`, with d = +q on the tool branch and d = −q on the workpiece
//!   branch (the table physically moves the other way), u the axis direction (squareness),
//!   δ = `linear_m`, ε = `angular_rad` (a rotation vector about the carriage origin).
//!   Errors are those of the physical carriage motion, so workpiece-branch errors move the
//!   tool point relative to the workpiece with the opposite sign.
//! - Squareness follows ISO 230-1: X is the reference direction, Y turns about z by
//!   `xy_rad` (EC0Y), Z turns by the rotation vector (`yz_rad`, `zx_rad`, 0) (EA0Z, EB0Z).

use std::fmt;
use std::str::FromStr;

use nalgebra::{
    IsometryMatrix3, Matrix3, Point3, Rotation3, SMatrix, SVector, Translation3, Vector3,
};
use serde::{Deserialize, Serialize};

/// A linear machine axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Axis {
    X,
    Y,
    Z,
}

impl Axis {
    pub const ALL: [Axis; 3] = [Axis::X, Axis::Y, Axis::Z];

    /// 0, 1, 2 for X, Y, Z: the index into `q`, `linear_m` and `angular_rad`.
    pub const fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }

    pub const fn letter(self) -> char {
        match self {
            Axis::X => 'X',
            Axis::Y => 'Y',
            Axis::Z => 'Z',
        }
    }

    pub fn from_letter(c: char) -> Option<Axis> {
        match c.to_ascii_uppercase() {
            'X' => Some(Axis::X),
            'Y' => Some(Axis::Y),
            'Z' => Some(Axis::Z),
            _ => None,
        }
    }

    /// Nominal unit direction of the axis.
    pub fn unit(self) -> Vector3<f64> {
        let mut v = Vector3::zeros();
        v[self.index()] = 1.0;
        v
    }

    /// ISO 230-1 names of the 6 errors of this axis, in `AxisErrors` order:
    /// linear along x, y, z, then rotations about x, y, z (e.g. EXX, EYX, EZX, EAX, EBX, ECX).
    pub const fn iso_names(self) -> [&'static str; 6] {
        match self {
            Axis::X => ["EXX", "EYX", "EZX", "EAX", "EBX", "ECX"],
            Axis::Y => ["EXY", "EYY", "EZY", "EAY", "EBY", "ECY"],
            Axis::Z => ["EXZ", "EYZ", "EZZ", "EAZ", "EBZ", "ECZ"],
        }
    }
}

impl fmt::Display for Axis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.letter())
    }
}

/// Why a structure string was rejected.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum StructureError {
    #[error("invalid machine structure {structure:?}: no foundation letter F (expected the letters X, Y, Z once each and F once, e.g. \"FYXZ\")")]
    MissingFoundation { structure: String },
    #[error("invalid machine structure {structure:?}: foundation letter F appears more than once (expected e.g. \"FYXZ\")")]
    RepeatedFoundation { structure: String },
    #[error("invalid machine structure {structure:?}: unknown letter {letter:?} at position {position} (allowed: X, Y, Z, F)")]
    UnknownLetter {
        structure: String,
        letter: char,
        position: usize,
    },
    #[error("invalid machine structure {structure:?}: axis {axis} appears more than once (each of X, Y, Z exactly once)")]
    RepeatedAxis { structure: String, axis: Axis },
    #[error("invalid machine structure {structure:?}: axis {axis} is missing (each of X, Y, Z exactly once, e.g. \"FYXZ\")")]
    MissingAxis { structure: String, axis: Axis },
}

/// A parsed kinematic chain such as `FYXZ`: letters left of F carry the workpiece (from the
/// workpiece down to the foundation), letters right of F carry the tool (from the foundation
/// out to the tool).
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct Structure {
    text: String,
    workpiece: Vec<Axis>,
    tool: Vec<Axis>,
}

impl Structure {
    /// Parse a structure string; case-insensitive, surrounding whitespace ignored.
    pub fn parse(s: &str) -> Result<Structure, StructureError> {
        let text = s.trim().to_ascii_uppercase();
        let err_text = || s.to_string();
        let mut f_pos = None;
        let mut seen = [false; 3];
        for (position, c) in text.chars().enumerate() {
            if c == 'F' {
                if f_pos.is_some() {
                    return Err(StructureError::RepeatedFoundation {
                        structure: err_text(),
                    });
                }
                f_pos = Some(position);
                continue;
            }
            let Some(axis) = Axis::from_letter(c) else {
                return Err(StructureError::UnknownLetter {
                    structure: err_text(),
                    letter: c,
                    position,
                });
            };
            if std::mem::replace(&mut seen[axis.index()], true) {
                return Err(StructureError::RepeatedAxis {
                    structure: err_text(),
                    axis,
                });
            }
        }
        if let Some(axis) = Axis::ALL.into_iter().find(|a| !seen[a.index()]) {
            return Err(StructureError::MissingAxis {
                structure: err_text(),
                axis,
            });
        }
        let Some(f_pos) = f_pos else {
            return Err(StructureError::MissingFoundation {
                structure: err_text(),
            });
        };
        // All letters are ASCII here, so char positions are byte positions.
        let axes = |part: &str| part.chars().filter_map(Axis::from_letter).collect();
        Ok(Structure {
            workpiece: axes(&text[..f_pos]),
            tool: axes(&text[f_pos + 1..]),
            text,
        })
    }

    /// The normalised (upper-case) structure string.
    pub fn as_str(&self) -> &str {
        &self.text
    }

    /// Tool-branch axes, from the foundation out to the tool.
    pub fn tool_axes(&self) -> &[Axis] {
        &self.tool
    }

    /// Workpiece-branch axes, from the workpiece down to the foundation (as written).
    pub fn workpiece_axes(&self) -> &[Axis] {
        &self.workpiece
    }

    /// True if the axis moves the workpiece rather than the tool.
    pub fn is_workpiece_axis(&self, axis: Axis) -> bool {
        self.workpiece.contains(&axis)
    }
}

impl FromStr for Structure {
    type Err = StructureError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Structure::parse(s)
    }
}

impl TryFrom<String> for Structure {
    type Error = StructureError;
    fn try_from(s: String) -> Result<Self, Self::Error> {
        Structure::parse(&s)
    }
}

impl From<Structure> for String {
    fn from(s: Structure) -> String {
        s.text
    }
}

impl fmt::Display for Structure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.text)
    }
}

/// The 6 errors of one axis's carriage at one position: `linear_m` along x, y, z (for axis X:
/// EXX positioning, EYX, EZX straightness) and `angular_rad` about x, y, z (EAX roll, EBX
/// pitch, ECX yaw for axis X), as motion of the physical carriage relative to its parent.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AxisErrors {
    pub linear_m: [f64; 3],
    pub angular_rad: [f64; 3],
}

/// The 3 position-independent squareness errors, ISO 230-1 style with X as reference:
/// `xy_rad` = EC0Y (Y direction turned about z: moving +y by L shifts x by −xy·L),
/// `yz_rad` = EA0Z (Z turned about x: moving +z by L shifts y by −yz·L),
/// `zx_rad` = EB0Z (Z turned about y: moving +z by L shifts x by +zx·L).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Squareness {
    pub xy_rad: f64,
    pub yz_rad: f64,
    pub zx_rad: f64,
}

impl Squareness {
    /// ISO 230-1 names in field order.
    pub const ISO_NAMES: [&'static str; 3] = ["EC0Y", "EA0Z", "EB0Z"];

    /// Actual unit directions of the X, Y, Z axes (rotations built exactly).
    pub fn directions(&self) -> [Vector3<f64>; 3] {
        let y = Rotation3::from_scaled_axis(Vector3::new(0.0, 0.0, self.xy_rad)) * Axis::Y.unit();
        let z = Rotation3::from_scaled_axis(Vector3::new(self.yz_rad, self.zx_rad, 0.0))
            * Axis::Z.unit();
        [Axis::X.unit(), y, z]
    }
}

/// A source of the 21 geometric errors (truth, estimate, or none).
pub trait GeometricErrors {
    /// Errors of `axis`'s carriage when that axis is at commanded position `q_m`.
    fn axis(&self, axis: Axis, q_m: f64) -> AxisErrors;
    fn squareness(&self) -> Squareness;
}

/// The perfect machine.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoErrors;

impl GeometricErrors for NoErrors {
    fn axis(&self, _axis: Axis, _q_m: f64) -> AxisErrors {
        AxisErrors::default()
    }
    fn squareness(&self) -> Squareness {
        Squareness::default()
    }
}

/// Position-independent errors: the same 21 values everywhere. Useful to evaluate the exact
/// model at one point from a 21-vector (see [`ConstantErrors::from_vector`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ConstantErrors {
    pub axes: [AxisErrors; 3],
    pub squareness: Squareness,
}

impl ConstantErrors {
    /// From a vector in Jacobian column order (see [`ERROR_NAMES`]).
    pub fn from_vector(e: &ErrorVector) -> Self {
        let mut axes = [AxisErrors::default(); 3];
        for (i, a) in axes.iter_mut().enumerate() {
            for k in 0..3 {
                a.linear_m[k] = e[6 * i + k];
                a.angular_rad[k] = e[6 * i + 3 + k];
            }
        }
        ConstantErrors {
            axes,
            squareness: Squareness {
                xy_rad: e[18],
                yz_rad: e[19],
                zx_rad: e[20],
            },
        }
    }
}

impl GeometricErrors for ConstantErrors {
    fn axis(&self, axis: Axis, _q_m: f64) -> AxisErrors {
        self.axes[axis.index()]
    }
    fn squareness(&self) -> Squareness {
        self.squareness
    }
}

/// Number of geometric errors of a 3-axis machine.
pub const N_ERRORS: usize = 21;

/// The 21 error values at one point, in Jacobian column order.
pub type ErrorVector = SVector<f64, N_ERRORS>;

/// d(actual position)/d(error values), 3 x 21.
pub type ErrorJacobian = SMatrix<f64, 3, N_ERRORS>;

/// Column order of [`error_jacobian`] and [`ErrorVector`]: axis X's 6 errors, then Y's, then
/// Z's (each linear x, y, z then angular about x, y, z), then squareness xy, yz, zx.
pub const ERROR_NAMES: [&str; N_ERRORS] = [
    "EXX", "EYX", "EZX", "EAX", "EBX", "ECX", //
    "EXY", "EYY", "EZY", "EAY", "EBY", "ECY", //
    "EXZ", "EYZ", "EZZ", "EAZ", "EBZ", "ECZ", //
    "EC0Y", "EA0Z", "EB0Z",
];

/// Column of the first of `axis`'s 6 errors in the Jacobian.
pub const fn axis_column(axis: Axis) -> usize {
    6 * axis.index()
}

/// Column of the first squareness error (xy); yz and zx follow.
pub const SQUARENESS_COLUMN: usize = 18;

/// Pack the 21 error values that act at commanded position `q` (each axis's errors at its
/// own coordinate).
pub fn error_vector(errors: &dyn GeometricErrors, q: [f64; 3]) -> ErrorVector {
    let mut e = ErrorVector::zeros();
    for axis in Axis::ALL {
        let ae = errors.axis(axis, q[axis.index()]);
        let c = axis_column(axis);
        for k in 0..3 {
            e[c + k] = ae.linear_m[k];
            e[c + 3 + k] = ae.angular_rad[k];
        }
    }
    let s = errors.squareness();
    e[SQUARENESS_COLUMN] = s.xy_rad;
    e[SQUARENESS_COLUMN + 1] = s.yz_rad;
    e[SQUARENESS_COLUMN + 2] = s.zx_rad;
    e
}

/// Nominal target position in the workpiece frame: `q + target_offset_m`.
pub fn nominal_position(q: [f64; 3], target_offset_m: [f64; 3]) -> [f64; 3] {
    [
        q[0] + target_offset_m[0],
        q[1] + target_offset_m[1],
        q[2] + target_offset_m[2],
    ]
}

/// Pose of a carriage relative to its parent: nominal displacement `d_m` along `dir`, then
/// the carriage's linear errors, then its rotation about its own (displaced) origin.
fn carriage_pose(d_m: f64, dir: &Vector3<f64>, e: &AxisErrors) -> IsometryMatrix3<f64> {
    let t = dir * d_m + Vector3::from(e.linear_m);
    IsometryMatrix3::from_parts(
        Translation3::from(t),
        Rotation3::from_scaled_axis(Vector3::from(e.angular_rad)),
    )
}

/// Actual target position in the workpiece frame with the given errors, by exact
/// homogeneous transforms. `target_offset_m` is in the frame of the last tool-branch axis
/// (the foundation when the tool branch is empty).
pub fn actual_position(
    structure: &Structure,
    errors: &dyn GeometricErrors,
    q: [f64; 3],
    target_offset_m: [f64; 3],
) -> [f64; 3] {
    let dirs = errors.squareness().directions();
    // Foundation -> workpiece: the workpiece branch is written from the workpiece down.
    let mut f_to_w = IsometryMatrix3::identity();
    for &a in structure.workpiece_axes().iter().rev() {
        let qa = q[a.index()];
        f_to_w *= carriage_pose(-qa, &dirs[a.index()], &errors.axis(a, qa));
    }
    let mut f_to_t = IsometryMatrix3::identity();
    for &a in structure.tool_axes() {
        let qa = q[a.index()];
        f_to_t *= carriage_pose(qa, &dirs[a.index()], &errors.axis(a, qa));
    }
    let p_f = f_to_t * Point3::from(target_offset_m);
    let p_w = f_to_w.inverse_transform_point(&p_f);
    [p_w.x, p_w.y, p_w.z]
}

/// Skew matrix S(r) with S(r)·ε = r × ε.
fn skew(r: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -r.z, r.y, r.z, 0.0, -r.x, -r.y, r.x, 0.0)
}

/// First-order model: d(actual_position)/d(error values) at zero errors, columns in
/// [`ERROR_NAMES`] order. `actual − nominal ≈ J · error_vector(errors, q)`; exact when only
/// linear errors are present.
pub fn error_jacobian(
    structure: &Structure,
    q: [f64; 3],
    target_offset_m: [f64; 3],
) -> ErrorJacobian {
    let qv = Vector3::from(q);
    let t = Vector3::from(target_offset_m);
    let disp = |a: Axis| a.unit() * q[a.index()];
    let mut j = ErrorJacobian::zeros();

    // Tool branch: a carriage error moves everything it carries, i.e. the target, by
    // δ + ε × r with r the target relative to the carriage origin (downstream travel + offset).
    let tool = structure.tool_axes();
    for (i, &a) in tool.iter().enumerate() {
        let r: Vector3<f64> = tool[i + 1..].iter().map(|&b| disp(b)).sum::<Vector3<f64>>() + t;
        let c = axis_column(a);
        j.fixed_view_mut::<3, 3>(0, c)
            .copy_from(&Matrix3::identity());
        j.fixed_view_mut::<3, 3>(0, c + 3).copy_from(&(-skew(&r)));
    }

    // Workpiece branch: the error moves the workpiece frame rigidly about the carriage origin
    // o = −(travel of this axis and those below it); the target seen from the workpiece moves
    // by the inverse, −(δ + ε × (p − o)).
    let p_f: Vector3<f64> = tool.iter().map(|&b| disp(b)).sum::<Vector3<f64>>() + t;
    let wp = structure.workpiece_axes();
    for (i, &a) in wp.iter().enumerate() {
        let below: Vector3<f64> = wp[i..].iter().map(|&b| disp(b)).sum();
        let r = p_f + below;
        let c = axis_column(a);
        j.fixed_view_mut::<3, 3>(0, c)
            .copy_from(&(-Matrix3::identity()));
        j.fixed_view_mut::<3, 3>(0, c + 3).copy_from(&skew(&r));
    }

    // Squareness turns the travel direction of Y and Z; same sign on both branches because
    // the relative tool-workpiece displacement along each axis is +q either way.
    let s = SQUARENESS_COLUMN;
    j[(0, s)] = -qv.y; // EC0Y: ẑ × ŷ = −x̂
    j[(1, s + 1)] = -qv.z; // EA0Z: x̂ × ẑ = −ŷ
    j[(0, s + 2)] = qv.z; // EB0Z: ŷ × ẑ = +x̂
    j
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const STRUCTURES: [&str; 12] = [
        "FYXZ", "FXYZ", "XFYZ", "YFXZ", "XYFZ", "FZYX", "ZFXY", "YXZF", "ZYFX", "XZFY", "FZXY",
        "YFZX",
    ];

    fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
    }

    fn assert_close(a: [f64; 3], b: [f64; 3], tol: f64, what: &str) {
        for k in 0..3 {
            assert!(
                (a[k] - b[k]).abs() <= tol,
                "{what}: component {k}: {a:?} vs {b:?} (tol {tol})"
            );
        }
    }

    #[test]
    fn parse_valid() {
        let s = Structure::parse("FYXZ").unwrap();
        assert_eq!(s.as_str(), "FYXZ");
        assert!(s.workpiece_axes().is_empty());
        assert_eq!(s.tool_axes(), &[Axis::Y, Axis::X, Axis::Z]);

        let s = Structure::parse(" xfyz ").unwrap();
        assert_eq!(s.as_str(), "XFYZ");
        assert_eq!(s.workpiece_axes(), &[Axis::X]);
        assert_eq!(s.tool_axes(), &[Axis::Y, Axis::Z]);
        assert!(s.is_workpiece_axis(Axis::X));

        let s = Structure::parse("XYFZ").unwrap();
        assert_eq!(s.workpiece_axes(), &[Axis::X, Axis::Y]);
        assert_eq!(s.tool_axes(), &[Axis::Z]);

        for text in STRUCTURES {
            let s: Structure = text.parse().unwrap();
            assert_eq!(s.to_string(), text);
            assert_eq!(s.workpiece_axes().len() + s.tool_axes().len(), 3);
        }
    }

    #[test]
    fn parse_invalid_messages() {
        let cases = [
            ("XYZ", "no foundation letter F"),
            ("FYXX", "axis X appears more than once"),
            ("FYX", "axis Z is missing"),
            ("FYXW", "unknown letter 'W' at position 3"),
            ("FFXYZ", "F appears more than once"),
            ("", "axis X is missing"),
        ];
        for (text, needle) in cases {
            let err = Structure::parse(text).unwrap_err().to_string();
            assert!(err.contains(needle), "{text:?}: {err}");
            assert!(err.contains(&format!("{text:?}")), "{text:?}: {err}");
        }
    }

    #[test]
    fn serde_roundtrip_and_rejects_invalid() {
        let s = Structure::parse("YFXZ").unwrap();
        let json = serde_json::to_string(&s).unwrap();
        assert_eq!(json, "\"YFXZ\"");
        let back: Structure = serde_json::from_str(&json).unwrap();
        assert_eq!(back, s);
        let err = serde_json::from_str::<Structure>("\"FYXQ\"").unwrap_err();
        assert!(err.to_string().contains("unknown letter"), "{err}");
    }

    #[test]
    fn no_errors_is_nominal() {
        let q = [0.31, -0.27, 0.55];
        let off = [0.01, -0.02, -0.15];
        for text in STRUCTURES {
            let s = Structure::parse(text).unwrap();
            let a = actual_position(&s, &NoErrors, q, off);
            assert_close(a, nominal_position(q, off), 1e-15, text);
        }
    }

    #[test]
    fn positioning_error_sign_per_branch() {
        let q = [0.2, 0.4, -0.3];
        let off = [0.0, 0.05, -0.1];
        let d = 7e-6;
        for text in STRUCTURES {
            let s = Structure::parse(text).unwrap();
            for axis in Axis::ALL {
                let mut e = ConstantErrors::default();
                e.axes[axis.index()].linear_m[axis.index()] = d;
                let dev = sub(actual_position(&s, &e, q, off), nominal_position(q, off));
                let sign = if s.is_workpiece_axis(axis) { -1.0 } else { 1.0 };
                let mut expected = [0.0; 3];
                expected[axis.index()] = sign * d;
                assert_close(dev, expected, 1e-15, &format!("{text} {axis}"));
            }
        }
    }

    #[test]
    fn abbe_error_of_first_tool_axis_by_hand() {
        // FYXZ: the Y bridge carries X and Z. Roll EAY = a about x, pivot at the Y carriage
        // origin (0, y, 0). Target relative to it: r = (x, 0, z + off_z). Rotating r about x
        // by a gives Δy = −sin(a)·r_z, Δz = (cos(a) − 1)·r_z.
        let s = Structure::parse("FYXZ").unwrap();
        let a = 1e-5;
        let mut e = ConstantErrors::default();
        e.axes[Axis::Y.index()].angular_rad[0] = a;
        let q = [0.2, 0.3, -0.4];
        for off_z in [0.0, -0.1, -0.3] {
            let off = [0.0, 0.0, off_z];
            let dev = sub(actual_position(&s, &e, q, off), nominal_position(q, off));
            let r_z = q[2] + off_z;
            assert_close(
                dev,
                [0.0, -a.sin() * r_z, (a.cos() - 1.0) * r_z],
                1e-16,
                "EAY",
            );
            // Proportional to the lever arm: 10 µrad · 0.5 m = 5 µm for off_z = −0.1.
            assert!((dev[1] / r_z + a).abs() < 1e-12);
        }
        // Yaw ECY about z: lever along x gives Δy = +c·x (first order).
        let mut e = ConstantErrors::default();
        e.axes[Axis::Y.index()].angular_rad[2] = a;
        let dev = sub(actual_position(&s, &e, q, [0.0; 3]), q);
        assert_close(
            dev,
            [0.2 * (a.cos() - 1.0), 0.2 * a.sin(), 0.0],
            1e-16,
            "ECY",
        );
        assert!((dev[1] - a * 0.2).abs() < 1e-15, "first order {dev:?}");
    }

    #[test]
    fn workpiece_axis_angular_error_pivots_about_table_carriage() {
        // XFYZ: table moves in X. Yaw ECX = c of the table about its origin (at −x in F).
        // Target relative to the table origin is q + off; seen from the table it turns by −c.
        let s = Structure::parse("XFYZ").unwrap();
        let c = 1e-5;
        let mut e = ConstantErrors::default();
        e.axes[Axis::X.index()].angular_rad[2] = c;
        let q = [0.3, 0.2, 0.1];
        let dev = sub(actual_position(&s, &e, q, [0.0; 3]), q);
        // Rotating (0.3, 0.2, 0.1) about z by −c; first order −c ẑ × r = (0.2c, −0.3c, 0).
        let (sn, cs) = c.sin_cos();
        let expected = [0.3 * cs + 0.2 * sn - 0.3, -0.3 * sn + 0.2 * cs - 0.2, 0.0];
        assert_close(dev, expected, 1e-16, "ECX table");
        assert_close(
            dev,
            [0.2 * c, -0.3 * c, 0.0],
            1e-10,
            "ECX table, first order",
        );
    }

    #[test]
    fn squareness_convention() {
        let s_rad: f64 = 4e-6;
        let l = 0.5;
        // Exact: the travel direction turns by s, so the along-axis part shortens by 1 − cos s.
        let (sn, cs) = s_rad.sin_cos();
        let short = (cs - 1.0) * l;
        for text in STRUCTURES {
            let s = Structure::parse(text).unwrap();
            let sq = |xy, yz, zx| ConstantErrors {
                squareness: Squareness {
                    xy_rad: xy,
                    yz_rad: yz,
                    zx_rad: zx,
                },
                ..Default::default()
            };
            // xy: moving +y by L shifts x by −s·L.
            let dev = sub(
                actual_position(&s, &sq(s_rad, 0.0, 0.0), [0.0, l, 0.0], [0.0; 3]),
                [0.0, l, 0.0],
            );
            assert_close(dev, [-sn * l, short, 0.0], 1e-16, text);
            assert!((dev[0] + s_rad * l).abs() < 1e-16);
            // yz: moving +z by L shifts y by −s·L.
            let dev = sub(
                actual_position(&s, &sq(0.0, s_rad, 0.0), [0.0, 0.0, l], [0.0; 3]),
                [0.0, 0.0, l],
            );
            assert_close(dev, [0.0, -sn * l, short], 1e-16, text);
            // zx: moving +z by L shifts x by +s·L.
            let dev = sub(
                actual_position(&s, &sq(0.0, 0.0, s_rad), [0.0, 0.0, l], [0.0; 3]),
                [0.0, 0.0, l],
            );
            assert_close(dev, [sn * l, 0.0, short], 1e-16, text);
            // Moving X is the reference: unaffected.
            let dev = sub(
                actual_position(&s, &sq(s_rad, s_rad, s_rad), [l, 0.0, 0.0], [0.0; 3]),
                [l, 0.0, 0.0],
            );
            assert_close(dev, [0.0; 3], 1e-16, text);
        }
    }

    fn random_errors(rng: &mut ChaCha8Rng, linear_m: f64, angular_rad: f64) -> ConstantErrors {
        let mut e = ErrorVector::zeros();
        for i in 0..N_ERRORS {
            let is_angular = i >= 18 || (i % 6) >= 3;
            let size = if is_angular { angular_rad } else { linear_m };
            e[i] = rng.random_range(-size..=size);
        }
        ConstantErrors::from_vector(&e)
    }

    #[test]
    fn jacobian_matches_exact_model_to_second_order() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut worst = 0.0f64;
        for text in STRUCTURES {
            let s = Structure::parse(text).unwrap();
            for _ in 0..50 {
                let q: [f64; 3] = std::array::from_fn(|_| rng.random_range(-0.5..0.5));
                let off: [f64; 3] = std::array::from_fn(|_| rng.random_range(-0.1..0.1));
                let errors = random_errors(&mut rng, 1e-6, 1e-6);
                let j = error_jacobian(&s, q, off);
                let e = error_vector(&errors, q);
                let lin = j * e;
                let dev = sub(
                    actual_position(&s, &errors, q, off),
                    nominal_position(q, off),
                );
                let resid = (Vector3::from(dev) - lin).amax();
                // Second-order terms are ~ ½(Σ|ε|)²·|lever| + |ε|·|δ|: a few 1e-12 m at this
                // size, against a first-order deviation of ~1e-6 m.
                assert!(resid < 1e-11, "{text}: {dev:?} vs {lin:?}");
                worst = worst.max(resid);
                // Shrinking the errors 10x must shrink the residual ~100x (second order).
                let e10 = e / 10.0;
                let small = ConstantErrors::from_vector(&e10);
                let dev10 = sub(
                    actual_position(&s, &small, q, off),
                    nominal_position(q, off),
                );
                let resid10 = (Vector3::from(dev10) - j * e10).amax();
                assert!(
                    resid10 < resid / 50.0 + 1e-17,
                    "{text}: {resid10} vs {resid}"
                );
            }
        }
        assert!(worst > 0.0);
    }

    #[test]
    fn jacobian_exact_for_linear_errors() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for text in STRUCTURES {
            let s = Structure::parse(text).unwrap();
            let q = [0.4, -0.3, 0.2];
            let off = [0.05, 0.0, -0.2];
            // Large (mm) linear errors, no rotations: still exact.
            let errors = random_errors(&mut rng, 1e-3, 0.0);
            let lin = error_jacobian(&s, q, off) * error_vector(&errors, q);
            let dev = sub(
                actual_position(&s, &errors, q, off),
                nominal_position(q, off),
            );
            assert_close(dev, [lin[0], lin[1], lin[2]], 1e-15, text);
        }
    }

    #[test]
    fn jacobian_columns_by_finite_difference() {
        // Column-by-column check catches a column that would be wrong but cancel in sums.
        let h = 1e-7;
        for text in STRUCTURES {
            let s = Structure::parse(text).unwrap();
            let q = [0.37, -0.21, 0.44];
            let off = [0.03, -0.06, -0.12];
            let j = error_jacobian(&s, q, off);
            for col in 0..N_ERRORS {
                let mut e = ErrorVector::zeros();
                e[col] = h;
                let plus = actual_position(&s, &ConstantErrors::from_vector(&e), q, off);
                e[col] = -h;
                let minus = actual_position(&s, &ConstantErrors::from_vector(&e), q, off);
                for k in 0..3 {
                    let fd = (plus[k] - minus[k]) / (2.0 * h);
                    assert!(
                        (fd - j[(k, col)]).abs() < 1e-8,
                        "{text} {}: row {k}: fd {fd} vs J {}",
                        ERROR_NAMES[col],
                        j[(k, col)]
                    );
                }
            }
        }
    }

    #[test]
    fn fyxz_without_offset_cannot_see_four_rotations() {
        // ref1: with the target at the tool point, ECX, EAZ, EBZ, ECZ have zero columns.
        let s = Structure::parse("FYXZ").unwrap();
        let j = error_jacobian(&s, [0.3, -0.7, 0.4], [0.0; 3]);
        let zero: Vec<&str> = (0..N_ERRORS)
            .filter(|&c| j.column(c).iter().all(|v| *v == 0.0))
            .map(|c| ERROR_NAMES[c])
            .collect();
        assert_eq!(zero, ["ECX", "EAZ", "EBZ", "ECZ"]);
    }

    #[test]
    fn error_vector_order_matches_names() {
        let mut e = ConstantErrors::default();
        e.axes[Axis::Y.index()].angular_rad[1] = 3.0; // EBY
        e.squareness.yz_rad = 5.0; // EA0Z
        let v = error_vector(&e, [0.0; 3]);
        let idx = |name| ERROR_NAMES.iter().position(|n| *n == name).unwrap();
        assert_eq!(v[idx("EBY")], 3.0);
        assert_eq!(v[idx("EA0Z")], 5.0);
        assert_eq!(v.iter().filter(|x| **x != 0.0).count(), 2);
        for axis in Axis::ALL {
            assert_eq!(
                &ERROR_NAMES[axis_column(axis)..axis_column(axis) + 6],
                &axis.iso_names()
            );
        }
        assert_eq!(&ERROR_NAMES[SQUARENESS_COLUMN..], &Squareness::ISO_NAMES);
    }
}
