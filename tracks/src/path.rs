//! Closed arc-length curves: the centreline (with track widths) and the raceline (with speeds).
//!
//! A [`ClosedCurve`] is a closed polyline `p_0 … p_{n-1}` (the segment `p_{n-1} → p_0` closes it) with
//! cumulative arc length `s_i = Σ_{k<i} |p_{k+1} - p_k|` and total length `L = s_n`. A point `q` is
//! projected onto the nearest segment `i` at parameter `t = clamp((q - p_i)·d_i / |d_i|², 0, 1)`,
//! giving arc length `s = s_i + t |d_i|`, lateral offset `e = d̂_i × (q - p_i)` (positive to the
//! left of the direction of travel) and the segment heading `ψ = atan2(d_i)`.

use crate::error::{Result, TrackError};
use nalgebra::{Point2, Vector2};

/// Where a point lies relative to a closed curve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Projection {
    /// Arc length of the foot point, in `[0, L)`.
    pub s: f64,
    /// Signed lateral offset, positive to the left of the direction of travel (m).
    pub lateral: f64,
    /// Heading of the curve at the foot point (rad).
    pub heading: f64,
    /// Index of the segment holding the foot point; pass it back as the hint next step.
    pub segment: usize,
}

/// A closed polyline parametrised by arc length.
#[derive(Clone, Debug)]
pub struct ClosedCurve {
    points: Vec<Point2<f64>>,
    /// Cumulative arc length, `n + 1` entries, the last one the total length.
    s: Vec<f64>,
}

/// How many segments either side of the hint a hinted projection searches before falling back to a
/// full search.
const HINT_WINDOW: usize = 16;

impl ClosedCurve {
    /// Builds a closed curve; a last point repeating the first is dropped, as are zero-length
    /// segments. `what` names the curve in errors.
    pub fn new(points: Vec<Point2<f64>>, what: &str) -> Result<Self> {
        let mut pts: Vec<Point2<f64>> = Vec::with_capacity(points.len());
        for p in points {
            if !(p.x.is_finite() && p.y.is_finite()) {
                return Err(TrackError::Invalid {
                    what: what.to_string(),
                    message: format!("point ({}, {}) is not finite", p.x, p.y),
                });
            }
            if pts.last().is_none_or(|q| (p - q).norm() > 1e-9) {
                pts.push(p);
            }
        }
        while pts.len() > 1 && (pts[0] - pts[pts.len() - 1]).norm() <= 1e-9 {
            pts.pop();
        }
        if pts.len() < 4 {
            return Err(TrackError::TooFewPoints {
                what: what.to_string(),
                found: pts.len(),
                needed: 4,
            });
        }
        let n = pts.len();
        let mut s = Vec::with_capacity(n + 1);
        s.push(0.0);
        for i in 0..n {
            let d = (pts[(i + 1) % n] - pts[i]).norm();
            s.push(s[i] + d);
        }
        Ok(Self { points: pts, s })
    }

    /// The vertices (without the closing repeat).
    pub fn points(&self) -> &[Point2<f64>] {
        &self.points
    }

    /// Number of vertices (= number of segments).
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Always false: a closed curve has at least four vertices.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Total arc length `L`.
    pub fn length(&self) -> f64 {
        self.s[self.points.len()]
    }

    /// Arc length at vertex `i`.
    pub fn s_at_vertex(&self, i: usize) -> f64 {
        self.s[i % self.points.len()]
    }

    /// Wraps any arc length into `[0, L)`.
    pub fn wrap_s(&self, s: f64) -> f64 {
        let l = self.length();
        let w = s.rem_euclid(l);
        if w >= l {
            0.0
        } else {
            w
        }
    }

    /// Segment index and parameter `t ∈ [0, 1)` at arc length `s` (wrapped).
    pub fn locate(&self, s: f64) -> (usize, f64) {
        let s = self.wrap_s(s);
        let n = self.points.len();
        // s[i] <= s < s[i+1]
        let i = match self.s[..=n].binary_search_by(|v| v.total_cmp(&s)) {
            Ok(i) => i.min(n - 1),
            Err(i) => (i - 1).min(n - 1),
        };
        let len = self.s[i + 1] - self.s[i];
        (
            i,
            if len > 0.0 {
                (s - self.s[i]) / len
            } else {
                0.0
            },
        )
    }

    /// The point at arc length `s` (wrapped), linearly interpolated.
    pub fn point_at(&self, s: f64) -> Point2<f64> {
        let (i, t) = self.locate(s);
        let a = self.points[i];
        let b = self.points[(i + 1) % self.points.len()];
        a + (b - a) * t
    }

    /// Direction of segment `i`.
    pub fn segment_vector(&self, i: usize) -> Vector2<f64> {
        let n = self.points.len();
        self.points[(i + 1) % n] - self.points[i % n]
    }

    /// Heading of the segment holding arc length `s`.
    pub fn heading_at(&self, s: f64) -> f64 {
        let d = self.segment_vector(self.locate(s).0);
        d.y.atan2(d.x)
    }

    /// Squared distance from `q` to segment `i` and the foot parameter `t ∈ [0, 1]`.
    #[inline]
    fn distance_to_segment(&self, q: &Point2<f64>, i: usize) -> (f64, f64) {
        let a = self.points[i];
        let d = self.segment_vector(i);
        let t = ((q - a).dot(&d) / d.norm_squared()).clamp(0.0, 1.0);
        ((q - (a + d * t)).norm_squared(), t)
    }

    /// The projection of `q` on segment `i` at foot parameter `t`.
    fn projection_on(&self, q: &Point2<f64>, i: usize, t: f64) -> Projection {
        let a = self.points[i];
        let d = self.segment_vector(i);
        let len = d.norm();
        let s = self.s[i] + t * len;
        Projection {
            s: if s >= self.length() { 0.0 } else { s },
            lateral: (d.x * (q.y - a.y) - d.y * (q.x - a.x)) / len,
            heading: d.y.atan2(d.x),
            segment: i,
        }
    }

    /// Nearest segment among `candidates`: `(index in candidates, segment, t)`.
    fn nearest(
        &self,
        q: &Point2<f64>,
        candidates: impl Iterator<Item = usize>,
    ) -> (usize, usize, f64) {
        let mut best = (f64::INFINITY, 0, 0, 0.0);
        for (k, i) in candidates.enumerate() {
            let (d2, t) = self.distance_to_segment(q, i);
            if d2 < best.0 {
                best = (d2, k, i, t);
            }
        }
        (best.1, best.2, best.3)
    }

    /// Projects `q` onto the whole curve (nearest segment).
    pub fn project(&self, q: &Point2<f64>) -> Projection {
        let (_, i, t) = self.nearest(q, 0..self.points.len());
        self.projection_on(q, i, t)
    }

    /// Projects `q` searching first a window of segments around `hint` (the previous step's
    /// segment); falls back to the full search when the nearest segment lies on the window's edge.
    pub fn project_near(&self, q: &Point2<f64>, hint: usize) -> Projection {
        let n = self.points.len();
        if n <= 2 * HINT_WINDOW + 1 {
            return self.project(q);
        }
        let window = (0..=2 * HINT_WINDOW).map(|k| (hint + n - HINT_WINDOW + k) % n);
        let (k, i, t) = self.nearest(q, window);
        if k == 0 || k == 2 * HINT_WINDOW {
            return self.project(q);
        }
        self.projection_on(q, i, t)
    }

    /// Signed curvature at each vertex from the circle through its neighbours (1/m, left positive).
    pub fn vertex_curvatures(&self) -> Vec<f64> {
        let n = self.points.len();
        (0..n)
            .map(|i| {
                let a = self.points[(i + n - 1) % n];
                let b = self.points[i];
                let c = self.points[(i + 1) % n];
                menger_curvature(&a, &b, &c)
            })
            .collect()
    }
}

/// Signed curvature of the circle through three points: `4·area / (|ab| |bc| |ca|)`.
pub fn menger_curvature(a: &Point2<f64>, b: &Point2<f64>, c: &Point2<f64>) -> f64 {
    let ab = b - a;
    let bc = c - b;
    let ca = a - c;
    let cross = ab.x * bc.y - ab.y * bc.x;
    let denom = ab.norm() * bc.norm() * ca.norm();
    if denom <= 0.0 {
        0.0
    } else {
        2.0 * cross / denom
    }
}

/// The track centreline with the free width to either side at each vertex.
#[derive(Clone, Debug)]
pub struct Centreline {
    /// The curve.
    pub curve: ClosedCurve,
    /// Free width to the right of each vertex (m).
    pub w_right: Vec<f64>,
    /// Free width to the left of each vertex (m).
    pub w_left: Vec<f64>,
}

impl Centreline {
    /// Builds a centreline from rows `(x, y, w_right, w_left)`; duplicate points are merged.
    pub fn new(rows: &[[f64; 4]], what: &str) -> Result<Self> {
        let mut pts = Vec::with_capacity(rows.len());
        let mut wr = Vec::with_capacity(rows.len());
        let mut wl = Vec::with_capacity(rows.len());
        for r in rows {
            let p = Point2::new(r[0], r[1]);
            if pts
                .last()
                .is_some_and(|q: &Point2<f64>| (p - q).norm() <= 1e-9)
            {
                continue;
            }
            if r[2] < 0.0 || r[3] < 0.0 {
                return Err(TrackError::Invalid {
                    what: what.to_string(),
                    message: format!("negative track width at ({}, {})", r[0], r[1]),
                });
            }
            pts.push(p);
            wr.push(r[2]);
            wl.push(r[3]);
        }
        let curve = ClosedCurve::new(pts, what)?;
        wr.truncate(curve.len());
        wl.truncate(curve.len());
        Ok(Self {
            curve,
            w_right: wr,
            w_left: wl,
        })
    }

    /// Widths `(right, left)` at arc length `s`, linearly interpolated.
    pub fn widths_at(&self, s: f64) -> (f64, f64) {
        let (i, t) = self.curve.locate(s);
        let j = (i + 1) % self.curve.len();
        (
            self.w_right[i] + (self.w_right[j] - self.w_right[i]) * t,
            self.w_left[i] + (self.w_left[j] - self.w_left[i]) * t,
        )
    }
}

/// A racing line: a closed curve with a speed and acceleration profile at each vertex.
#[derive(Clone, Debug)]
pub struct Raceline {
    /// The curve.
    pub curve: ClosedCurve,
    /// Signed curvature at each vertex (1/m).
    pub kappa: Vec<f64>,
    /// Target speed at each vertex (m/s).
    pub speed: Vec<f64>,
    /// Longitudinal acceleration at each vertex (m/s²).
    pub accel: Vec<f64>,
}

impl Raceline {
    /// Speed at arc length `s`, linearly interpolated.
    pub fn speed_at(&self, s: f64) -> f64 {
        let (i, t) = self.curve.locate(s);
        let j = (i + 1) % self.curve.len();
        self.speed[i] + (self.speed[j] - self.speed[i]) * t
    }

    /// Lap time `Σ 2 Δs / (v_i + v_{i+1})` along the line (s).
    pub fn lap_time(&self) -> f64 {
        let n = self.curve.len();
        (0..n)
            .map(|i| {
                let ds = self.curve.s_at_vertex(i + 1) - self.curve.s_at_vertex(i);
                let ds = if i + 1 == n {
                    self.curve.length() - self.curve.s_at_vertex(i)
                } else {
                    ds
                };
                2.0 * ds / (self.speed[i] + self.speed[(i + 1) % n]).max(1e-9)
            })
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(side: f64, n_per_side: usize) -> ClosedCurve {
        let mut pts = Vec::new();
        let corners = [(0.0, 0.0), (side, 0.0), (side, side), (0.0, side)];
        for k in 0..4 {
            let (ax, ay) = corners[k];
            let (bx, by) = corners[(k + 1) % 4];
            for j in 0..n_per_side {
                let t = j as f64 / n_per_side as f64;
                pts.push(Point2::new(ax + (bx - ax) * t, ay + (by - ay) * t));
            }
        }
        ClosedCurve::new(pts, "square").unwrap()
    }

    #[test]
    fn length_and_interpolation_of_a_square() {
        let c = square(10.0, 5);
        assert!((c.length() - 40.0).abs() < 1e-12);
        let p = c.point_at(15.0);
        assert!((p - Point2::new(10.0, 5.0)).norm() < 1e-12);
        let p = c.point_at(-5.0); // wraps to 35
        assert!((p - Point2::new(0.0, 5.0)).norm() < 1e-12);
        assert!((c.heading_at(15.0) - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn projection_gives_arc_length_offset_and_heading() {
        let c = square(10.0, 5);
        // inside the square is to the left of the counter-clockwise direction of travel
        let pr = c.project(&Point2::new(3.0, 1.0));
        assert!((pr.s - 3.0).abs() < 1e-12);
        assert!((pr.lateral - 1.0).abs() < 1e-12);
        assert!(pr.heading.abs() < 1e-12);
        let pr = c.project(&Point2::new(11.5, 7.0));
        assert!((pr.s - 17.0).abs() < 1e-12);
        assert!((pr.lateral + 1.5).abs() < 1e-12);
        // the hinted search agrees with the full one, also across the seam
        for &(x, y) in &[(3.0, 1.0), (0.2, 0.3), (9.9, 9.0), (0.1, 9.7)] {
            let q = Point2::new(x, y);
            let full = c.project(&q);
            for hint in [0, 3, 10, 19] {
                let near = c.project_near(&q, hint);
                assert!((near.s - full.s).abs() < 1e-12, "hint {hint} at ({x},{y})");
            }
        }
    }

    #[test]
    fn closing_duplicate_and_too_few_points() {
        let pts = vec![
            Point2::new(0.0, 0.0),
            Point2::new(1.0, 0.0),
            Point2::new(1.0, 1.0),
            Point2::new(0.0, 1.0),
            Point2::new(0.0, 0.0),
        ];
        assert_eq!(ClosedCurve::new(pts, "c").unwrap().len(), 4);
        let err = ClosedCurve::new(vec![Point2::new(0.0, 0.0), Point2::new(1.0, 0.0)], "tiny")
            .unwrap_err();
        assert!(
            err.to_string().contains("tiny has 2 distinct points"),
            "{err}"
        );
    }

    #[test]
    fn curvature_of_a_circle() {
        let r = 5.0;
        let pts = (0..200)
            .map(|i| {
                let a = i as f64 / 200.0 * std::f64::consts::TAU;
                Point2::new(r * a.cos(), r * a.sin())
            })
            .collect();
        let c = ClosedCurve::new(pts, "circle").unwrap();
        for k in c.vertex_curvatures() {
            assert!((k - 1.0 / r).abs() < 1e-3, "{k}");
        }
    }
}
