#![forbid(unsafe_code)]
//! The analytic primitives of a [`super::Scene`]: bounds, exact ray intersection and surface normals.

use nalgebra::{Matrix3, Point3, Vector3};

use super::bvh::Aabb;

/// Rays closer than this to their origin are ignored, so a ray never hits the surface it starts on.
const T_MIN: f64 = 1e-9;

/// A triangle; both faces are visible.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangle {
    pub vertices: [Point3<f64>; 3],
}

/// A box of half extents `half_extents` along the columns of `rotation` (its axes in the world),
/// centred at `center`. An identity rotation gives an axis-aligned box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrientedBox {
    pub center: Point3<f64>,
    pub rotation: Matrix3<f64>,
    pub half_extents: Vector3<f64>,
}

/// A closed cylinder with a vertical (world z) axis: bottom cap centred at `base`, top cap at
/// `base.z + height`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerticalCylinder {
    pub base: Point3<f64>,
    pub height: f64,
    pub radius: f64,
}

/// An ellipsoid with axes along world x, y, z (a sphere when the radii are equal).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ellipsoid {
    pub center: Point3<f64>,
    pub radii: Vector3<f64>,
}

/// One primitive of a scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Primitive {
    Triangle(Triangle),
    Box(OrientedBox),
    Cylinder(VerticalCylinder),
    Ellipsoid(Ellipsoid),
}

fn finite(values: impl IntoIterator<Item = f64>) -> bool {
    values.into_iter().all(f64::is_finite)
}

impl Primitive {
    /// Short name for error messages.
    pub fn kind(&self) -> &'static str {
        match self {
            Primitive::Triangle(_) => "triangle",
            Primitive::Box(_) => "box",
            Primitive::Cylinder(_) => "cylinder",
            Primitive::Ellipsoid(_) => "ellipsoid",
        }
    }

    /// Why the primitive is unusable, if it is.
    pub(crate) fn validate(&self) -> Result<(), String> {
        match self {
            Primitive::Triangle(t) => {
                if !finite(t.vertices.iter().flat_map(|v| v.coords.iter().copied())) {
                    return Err("non-finite vertex".into());
                }
                let [a, b, c] = t.vertices;
                let area2 = (b - a).cross(&(c - a)).norm();
                let scale = (b - a).norm().max((c - a).norm()).max(1e-300);
                if area2 <= 1e-12 * scale * scale {
                    return Err("degenerate (zero area)".into());
                }
            }
            Primitive::Box(b) => {
                if !finite(
                    b.center
                        .coords
                        .iter()
                        .chain(b.rotation.iter())
                        .chain(b.half_extents.iter())
                        .copied(),
                ) {
                    return Err("non-finite value".into());
                }
                if b.half_extents.iter().any(|&h| h <= 0.0) {
                    return Err("half extents must be positive".into());
                }
                let error = (b.rotation.transpose() * b.rotation - Matrix3::identity())
                    .abs()
                    .max();
                if error > 1e-6 || b.rotation.determinant() < 0.0 {
                    return Err("rotation is not orthonormal with determinant +1".into());
                }
            }
            Primitive::Cylinder(c) => {
                if !finite(c.base.coords.iter().copied().chain([c.height, c.radius])) {
                    return Err("non-finite value".into());
                }
                if c.height <= 0.0 || c.radius <= 0.0 {
                    return Err("height and radius must be positive".into());
                }
            }
            Primitive::Ellipsoid(e) => {
                if !finite(e.center.coords.iter().chain(e.radii.iter()).copied()) {
                    return Err("non-finite value".into());
                }
                if e.radii.iter().any(|&r| r <= 0.0) {
                    return Err("radii must be positive".into());
                }
            }
        }
        Ok(())
    }

    /// Axis-aligned bounds.
    pub(crate) fn bounds(&self) -> Aabb {
        match self {
            Primitive::Triangle(t) => {
                let mut aabb = Aabb::empty();
                for v in &t.vertices {
                    aabb.grow_point(v);
                }
                aabb
            }
            Primitive::Box(b) => {
                // Half extent of the rotated box along world axis i: Σ_j |R_ij| h_j.
                let reach = b.rotation.abs() * b.half_extents;
                Aabb {
                    min: b.center - reach,
                    max: b.center + reach,
                }
            }
            Primitive::Cylinder(c) => Aabb {
                min: Point3::new(c.base.x - c.radius, c.base.y - c.radius, c.base.z),
                max: Point3::new(
                    c.base.x + c.radius,
                    c.base.y + c.radius,
                    c.base.z + c.height,
                ),
            },
            Primitive::Ellipsoid(e) => Aabb {
                min: e.center - e.radii,
                max: e.center + e.radii,
            },
        }
    }

    /// Distance along the unit `direction` of the first intersection in `(T_MIN, t_max]`, if any.
    pub(crate) fn intersect(
        &self,
        origin: &Point3<f64>,
        direction: &Vector3<f64>,
        t_max: f64,
    ) -> Option<f64> {
        let t = match self {
            Primitive::Triangle(t) => intersect_triangle(t, origin, direction),
            Primitive::Box(b) => intersect_box(b, origin, direction),
            Primitive::Cylinder(c) => intersect_cylinder(c, origin, direction),
            Primitive::Ellipsoid(e) => intersect_ellipsoid(e, origin, direction),
        }?;
        (t > T_MIN && t <= t_max).then_some(t)
    }

    /// Unit outward normal at a surface point (the sign is irrelevant to the caller).
    pub(crate) fn normal_at(&self, point: &Point3<f64>) -> Vector3<f64> {
        match self {
            Primitive::Triangle(t) => {
                let [a, b, c] = t.vertices;
                (b - a).cross(&(c - a)).normalize()
            }
            Primitive::Box(b) => {
                let local = b.rotation.transpose() * (point - b.center);
                // The face is the axis where the point is relatively closest to the boundary.
                let axis = (0..3)
                    .max_by(|&i, &j| {
                        (local[i].abs() / b.half_extents[i])
                            .total_cmp(&(local[j].abs() / b.half_extents[j]))
                    })
                    .unwrap_or(0);
                let sign = if local[axis] >= 0.0 { 1.0 } else { -1.0 };
                b.rotation.column(axis) * sign
            }
            Primitive::Cylinder(c) => {
                let radial = Vector3::new(point.x - c.base.x, point.y - c.base.y, 0.0);
                let side_gap = (radial.norm() - c.radius).abs();
                let bottom_gap = (point.z - c.base.z).abs();
                let top_gap = (point.z - c.base.z - c.height).abs();
                if side_gap <= bottom_gap.min(top_gap) && radial.norm() > 0.0 {
                    radial.normalize()
                } else if bottom_gap < top_gap {
                    -Vector3::z()
                } else {
                    Vector3::z()
                }
            }
            Primitive::Ellipsoid(e) => {
                let d = point - e.center;
                Vector3::new(
                    d.x / (e.radii.x * e.radii.x),
                    d.y / (e.radii.y * e.radii.y),
                    d.z / (e.radii.z * e.radii.z),
                )
                .normalize()
            }
        }
    }
}

/// Möller–Trumbore, double-sided.
fn intersect_triangle(t: &Triangle, origin: &Point3<f64>, direction: &Vector3<f64>) -> Option<f64> {
    let [a, b, c] = t.vertices;
    let e1 = b - a;
    let e2 = c - a;
    let p = direction.cross(&e2);
    let det = e1.dot(&p);
    if det.abs() < 1e-15 * e1.norm_squared().max(e2.norm_squared()) {
        return None;
    }
    let inv = 1.0 / det;
    let s = origin - a;
    let u = s.dot(&p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(&e1);
    let v = direction.dot(&q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    Some(e2.dot(&q) * inv)
}

/// Slab test in the box frame. From inside, the exit face is the hit.
fn intersect_box(b: &OrientedBox, origin: &Point3<f64>, direction: &Vector3<f64>) -> Option<f64> {
    let o = b.rotation.transpose() * (origin - b.center);
    let d = b.rotation.transpose() * direction;
    let mut t_near = f64::NEG_INFINITY;
    let mut t_far = f64::INFINITY;
    for i in 0..3 {
        let h = b.half_extents[i];
        if d[i].abs() < 1e-300 {
            if o[i].abs() > h {
                return None;
            }
            continue;
        }
        let t1 = (-h - o[i]) / d[i];
        let t2 = (h - o[i]) / d[i];
        t_near = t_near.max(t1.min(t2));
        t_far = t_far.min(t1.max(t2));
    }
    if t_near > t_far || t_far <= T_MIN {
        return None;
    }
    Some(if t_near > T_MIN { t_near } else { t_far })
}

fn intersect_cylinder(
    c: &VerticalCylinder,
    origin: &Point3<f64>,
    direction: &Vector3<f64>,
) -> Option<f64> {
    let (ox, oy) = (origin.x - c.base.x, origin.y - c.base.y);
    let (z_bottom, z_top) = (c.base.z, c.base.z + c.height);
    let r2 = c.radius * c.radius;
    let mut best = f64::INFINITY;
    // Side: |o_xy + t d_xy|² = r².
    let a = direction.x * direction.x + direction.y * direction.y;
    if a > 1e-300 {
        let half_b = ox * direction.x + oy * direction.y;
        let cc = ox * ox + oy * oy - r2;
        let disc = half_b * half_b - a * cc;
        if disc >= 0.0 {
            let root = disc.sqrt();
            for t in [(-half_b - root) / a, (-half_b + root) / a] {
                let z = origin.z + t * direction.z;
                if t > T_MIN && t < best && z >= z_bottom && z <= z_top {
                    best = t;
                }
            }
        }
    }
    // Caps: discs at z_bottom and z_top.
    if direction.z.abs() > 1e-300 {
        for z in [z_bottom, z_top] {
            let t = (z - origin.z) / direction.z;
            if t > T_MIN && t < best {
                let (x, y) = (ox + t * direction.x, oy + t * direction.y);
                if x * x + y * y <= r2 {
                    best = t;
                }
            }
        }
    }
    best.is_finite().then_some(best)
}

/// Scaled to the unit sphere; the scaled direction is not unit but `t` is preserved.
fn intersect_ellipsoid(
    e: &Ellipsoid,
    origin: &Point3<f64>,
    direction: &Vector3<f64>,
) -> Option<f64> {
    let o = (origin - e.center).component_div(&e.radii);
    let d = direction.component_div(&e.radii);
    let a = d.norm_squared();
    let half_b = o.dot(&d);
    let c = o.norm_squared() - 1.0;
    let disc = half_b * half_b - a * c;
    if disc < 0.0 {
        return None;
    }
    let root = disc.sqrt();
    let t0 = (-half_b - root) / a;
    let t1 = (-half_b + root) / a;
    if t0 > T_MIN {
        Some(t0)
    } else if t1 > T_MIN {
        Some(t1)
    } else {
        None
    }
}
